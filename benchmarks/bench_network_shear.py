"""A network sheared forward to sigma = 1e6 and back (issue 3, "Speed and memory": N = 40 000,
forward to 1e6 and back in <= 3 minutes on 2 cores).

The network (packing at phi = 0.88, WLKM dilution to z = 3.8, seed 1) is built once and saved;
each case loads it and runs forward until sigma >= 1e6, then reversed until sigma <= 10, with
no analyses and no omega_min (the shear alone).  Cases: integrator preset default / fast, and
fast with the step's last force from the reused factor (solver.reuse_factor = "on").  The
error of each case is max |log sigma - log sigma_ref| on the forward branch at equal gamma
against the default-preset run, and |gamma_1e6 - gamma_1e6,ref| where sigma crosses 1e6.

    mpirun -n 2 python benchmarks/bench_network_shear.py [--n 40000]
    -> docs/benchmarks/network_shear.json (one record per N and rank count)
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import sys
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
from common import FORWARD_AND_BACK, network_file  # noqa: E402  (benchmarks/common.py)

SETTINGS = """[integrator]
preset = "{preset}"
[solver]
reuse_factor = "{reuse}"
"""
CASES = [("default", "off"), ("fast", "off"), ("fast", "on")]


def run(folder, n, network, preset, reuse):
    comm = PETSc.COMM_WORLD
    path = os.path.join(folder, f"shear_{preset}_{reuse}.h5")
    scene = load_scene(FORWARD_AND_BACK.format(n=n, network=network, path=path,
                                               settings=SETTINGS.format(preset=preset, reuse=reuse)))
    setup_logging(comm, quiet=True)
    comm.tompi4py().Barrier()
    t = time.perf_counter()
    status = Run(scene, comm, path, quiet=True).execute()
    wall = time.perf_counter() - t
    comm.tompi4py().Barrier()
    with h5py.File(path) as f:
        ts = f["timeseries"]
        d = {k: ts[k][:] for k in ("gamma", "sigma", "direction", "wall", "rejected")}
        counters = {k: int(f.attrs[k]) for k in ("n_factorisations", "n_reused_factor")}
        solver = str(f.attrs["solver"])
    fw = d["direction"] > 0
    return dict(preset=preset, reuse_factor=reuse, status=status, wall_seconds=wall,
                loop_seconds=float(d["wall"][-1] - d["wall"][0]),
                steps_forward=int(fw.sum() - 1), steps_reverse=int((~fw).sum()),
                rejected=int(d["rejected"].sum()), solver=solver, **counters,
                sigma_end=float(d["sigma"][-1])), d


def crossing(d, level=1e6):
    fw = d["direction"] > 0
    return results.crossing(d["gamma"][fw], d["sigma"][fw], level)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=40000)
    ap.add_argument("--folder", default=os.path.join("out", "bench_network_shear"))
    args = ap.parse_args()
    comm = PETSc.COMM_WORLD
    rank, size = comm.getRank(), comm.getSize()
    os.makedirs(args.folder, exist_ok=True)
    network = network_file(args.folder, args.n, comm)
    rows, data = [], {}
    for preset, reuse in CASES:
        row, d = run(args.folder, args.n, network, preset, reuse)
        data[(preset, reuse)] = d
        rows.append(row)
        if rank == 0:
            print(f"{preset:8s} reuse {reuse:3s}: {row['status']}, loop {row['loop_seconds']:.1f} s, "
                  f"steps {row['steps_forward']} + {row['steps_reverse']}, rejected {row['rejected']}, "
                  f"factorisations {row['n_factorisations']}, reused {row['n_reused_factor']}", flush=True)
    ref = data[("default", "off")]
    rfw = ref["direction"] > 0
    for row, (key, d) in zip(rows, data.items()):
        fw = d["direction"] > 0
        g, ls = d["gamma"][fw], np.log(d["sigma"][fw])
        sel = g <= ref["gamma"][rfw][-1]
        row["err_forward"] = float(np.max(np.abs(ls[sel] - np.interp(g[sel], ref["gamma"][rfw],
                                                                      np.log(ref["sigma"][rfw])))))
        row["err_gamma_1e6"] = abs(crossing(d) - crossing(ref))
    if rank == 0:
        old = {}
        p = results.path("network_shear")
        if os.path.exists(p):
            with open(p) as fh:
                old = json.load(fh)
        recs = [r for r in old.get("records", []) if not (r["n"] == args.n and r["ranks"] == size)]
        recs.append(dict(n=args.n, ranks=size, date=time.strftime("%Y-%m-%d %H:%M:%S"),
                         load_end=os.getloadavg(),
                         peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                         rows=rows))
        results.write("network_shear", dict(benchmark="network forward to sigma = 1e6 and back",
                                            records=recs))
        for r in rows:
            print(f"{r['preset']:8s} reuse {r['reuse_factor']:3s}: err_forward {r['err_forward']:.2e}, "
                  f"err_gamma_1e6 {r['err_gamma_1e6']:.2e}", flush=True)


if __name__ == "__main__":
    main()
