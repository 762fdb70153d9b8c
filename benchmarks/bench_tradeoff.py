"""Speed against accuracy: step-control and solver presets against a tight reference.

A chain (N = 2000, eps = 0.1, seed 1) is driven forward until <V^2> = 1e6 (gamma_c - gamma
~ 1e-4, cond(N) ~ 1e7) and reversed for 0.5 % strain.  Each preset combination is compared
with a reference run (integrator tol = max_displacement = 0.002, solver "accurate"):

* err_forward: max over the forward branch of |log sigma - log sigma_ref| at equal gamma
  (reference interpolated in gamma);
* err_gamma: the error on the strain where <V^2> crosses 1e6 (interpolated between steps),
  relative to the distance gamma_c - gamma there;
* err_reverse: max over the reversed branch (first 0.5 % strain) of |log sigma - log sigma_ref|
  at equal distance from the turning point.  The reversed branch grows from round-off
  (docs/chain.md), so this measures how reproducible the buckled state is, not only the
  integration error;
* wall seconds and the number of accepted steps.

    python benchmarks/bench_tradeoff.py        -> docs/benchmarks/tradeoff.json
"""
from __future__ import annotations

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

SCENE = """
seed = 1
[model]
name = "chain"
N = 2000
epsilon = 0.1
[[protocol.leg]]
direction = "forward"
V2_above = 1e6
[[protocol.leg]]
direction = "reverse"
strain = 0.005
[integrator]
{integrator}
[solver]
preset = "{solver}"
[output]
path = "{path}"
"""


def run(tmp, name, integrator, solver):
    path = os.path.join(tmp, name + ".h5")
    scene = load_scene(SCENE.format(integrator=integrator, solver=solver, path=path))
    setup_logging(PETSc.COMM_SELF, quiet=True)
    t = time.perf_counter()
    Run(scene, PETSc.COMM_SELF, path, quiet=True).execute()
    wall = time.perf_counter() - t
    with h5py.File(path) as f:
        ts = f["timeseries"]
        data = {k: ts[k][:] for k in ("gamma", "sigma", "direction", "V2")}
        data["gamma_c"] = float(f["model"].attrs["gamma_c"])
    data["wall"] = wall
    return data


def branches(d):
    fw = d["direction"] >= 0
    rv = d["direction"] < 0
    turn = d["gamma"][fw][-1]
    return fw, rv, turn


def crossing(d, level=1e6):
    """gamma where <V^2> crosses ``level`` on the forward branch (log-linear interpolation
    between the two steps around it), independent of where the last step happened to land."""
    fw = d["direction"] >= 0
    return results.crossing(d["gamma"][fw], d["V2"][fw], level)


def compare(d, ref):
    fw, rv, turn = branches(d)
    rfw, rrv, rturn = branches(ref)
    g = d["gamma"][fw]
    ls = np.log(d["sigma"][fw])
    sel = (g >= ref["gamma"][rfw][0]) & (g <= rturn)
    err_fwd = float(np.max(np.abs(ls[sel] - np.interp(g[sel], ref["gamma"][rfw], np.log(ref["sigma"][rfw])))))
    gx, rgx = crossing(d), crossing(ref)
    err_gamma = abs(gx - rgx) / (ref["gamma_c"] - rgx)
    x = turn - d["gamma"][rv]
    xr = rturn - ref["gamma"][rrv]
    sel = (x >= xr[0]) & (x <= xr[-1])
    err_rev = float(np.max(np.abs(np.log(d["sigma"][rv][sel]) -
                                  np.interp(x[sel], xr, np.log(ref["sigma"][rrv]))))) if sel.any() else float("nan")
    return dict(err_forward=err_fwd, err_gamma=float(err_gamma), err_reverse=err_rev)


def main():
    cases = [("fast", "direct"), ("default", "direct"), ("tight", "direct"),
             ("default", "accurate"), ("tight", "accurate")]
    with tempfile.TemporaryDirectory() as tmp:
        ref = run(tmp, "ref", "tol = 0.002\nmax_displacement = 0.002", "accurate")
        rows = []
        for integ, solver in cases:
            d = run(tmp, f"{integ}_{solver}", f'preset = "{integ}"', solver)
            row = dict(integrator=integ, solver=solver, wall_seconds=d["wall"],
                       steps=int(d["gamma"].size - 1), **compare(d, ref))
            rows.append(row)
            print(f"{integ:8s} {solver:9s} wall {row['wall_seconds']:6.2f} s  steps {row['steps']:6d}  "
                  f"err_forward {row['err_forward']:.2e}  err_gamma {row['err_gamma']:.2e}  "
                  f"err_reverse {row['err_reverse']:.2e}", flush=True)
        out = dict(benchmark="presets: error against a tight reference vs wall time",
                   system="chain N=2000 eps=0.1 seed=1, forward to <V^2>=1e6, reverse 0.5% strain",
                   reference=dict(tol=0.002, max_displacement=0.002, solver="accurate",
                                  wall_seconds=ref["wall"], steps=int(ref["gamma"].size - 1)),
                   date=time.strftime("%Y-%m-%d %H:%M:%S"), load=os.getloadavg(), rows=rows)
    results.write("tradeoff", out)


if __name__ == "__main__":
    main()
