"""Step-size control on a floppy network: controller ("I", "PI") and tolerance against a tight
reference, on the way to jamming.

A network (z = 3.8, packing at phi = 0.88, seed 1) is sheared forward until sigma = 1e5.
Each case is compared with a reference run (tol = max_displacement = 0.005, controller "I"):

* err_forward: max over the forward branch of |log sigma - log sigma_ref| at equal gamma;
* err_gamma: |gamma - gamma_ref| where sigma first crosses 1e4 (log-interpolated), relative
  to gamma_ref(1e5) - gamma_ref(1e4) -- the strain left to go there;
* steps, rejected trial steps, factorisations of N, seconds of the step loop.

    python benchmarks/bench_network_control.py [--n 4096]   -> docs/benchmarks/network_control.json
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

import petsc4py

petsc4py.init(sys.argv[:1])
import h5py  # noqa: E402
import numpy as np  # noqa: E402
from petsc4py import PETSc  # noqa: E402

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from parflow.run import Run, setup_logging  # noqa: E402
from parflow.scene import load_scene  # noqa: E402

import results  # noqa: E402  (benchmarks/results.py)
from common import NETWORK_MODEL, network_file  # noqa: E402  (benchmarks/common.py)

SCENE = NETWORK_MODEL + """[[protocol.leg]]
direction = "forward"
sigma_above = 1e5
[integrator]
tol = {tol}
max_displacement = {tol}
controller = "{controller}"
[output]
path = "{path}"
"""
CASES = [(0.2, "I"), (0.2, "PI"), (0.15, "I"), (0.15, "PI"), (0.05, "I"), (0.05, "PI"),
         (0.02, "I"), (0.02, "PI")]
REF = (0.005, "I")


def run(tmp, n, network, tol, controller):
    path = os.path.join(tmp, f"{tol}_{controller}.h5")
    scene = load_scene(SCENE.format(n=n, network=network, tol=tol, controller=controller, path=path))
    setup_logging(PETSc.COMM_SELF, quiet=True)
    Run(scene, PETSc.COMM_SELF, path, quiet=True).execute()
    with h5py.File(path) as f:
        ts = f["timeseries"]
        d = {k: ts[k][:] for k in ("gamma", "sigma", "rejected", "wall")}
        d["factorisations"] = int(f.attrs["n_factorisations"])
    d["loop_seconds"] = float(d["wall"][-1] - d["wall"][0])
    return d


def crossing(d, level):
    return results.crossing(d["gamma"], d["sigma"], level)


def compare(d, ref):
    g, ls = d["gamma"], np.log(d["sigma"])
    sel = g <= ref["gamma"][-1]
    err_fwd = float(np.max(np.abs(ls[sel] - np.interp(g[sel], ref["gamma"], np.log(ref["sigma"])))))
    g4, r4, r5 = crossing(d, 1e4), crossing(ref, 1e4), crossing(ref, 1e5)
    return dict(err_forward=err_fwd, err_gamma=abs(g4 - r4) / (r5 - r4))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=4096)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        network = network_file(tmp, args.n, PETSc.COMM_WORLD)
        ref = run(tmp, args.n, network, *REF)
        print(f"reference tol {REF[0]}: {ref['gamma'].size - 1} steps, {ref['loop_seconds']:.1f} s", flush=True)
        rows = []
        for tol, controller in CASES:
            d = run(tmp, args.n, network, tol, controller)
            row = dict(tol=tol, controller=controller, steps=int(d["gamma"].size - 1),
                       rejected=int(d["rejected"].sum()), factorisations=d["factorisations"],
                       loop_seconds=d["loop_seconds"], **compare(d, ref))
            rows.append(row)
            print(f"tol {tol:5.3f} {controller:2s}  steps {row['steps']:5d}  rejected {row['rejected']:4d}  "
                  f"factorisations {row['factorisations']:5d}  loop {row['loop_seconds']:6.1f} s  "
                  f"err_forward {row['err_forward']:.2e}  err_gamma {row['err_gamma']:.2e}", flush=True)
    out = dict(benchmark="step-size control on a network: error against a tight reference vs cost",
               system=f"network N={args.n} z=3.8 phi=0.88 seed=1, forward to sigma=1e5, 1 rank",
               reference=dict(tol=REF[0], controller=REF[1], steps=int(ref["gamma"].size - 1),
                              loop_seconds=ref["loop_seconds"]),
               date=time.strftime("%Y-%m-%d %H:%M:%S"), load=os.getloadavg(), rows=rows)
    results.write(f"network_control_N{args.n}", out)


if __name__ == "__main__":
    main()
