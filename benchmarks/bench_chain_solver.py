"""The chain's force solve: CHOLMOD (the default) against PETSc's own Cholesky
(``-tau_pc_factor_mat_solver_type petsc``, natural ordering: the factor of the chain's cyclic
tridiagonal N fills only its last row) on the mu = 2, N = 1e5 chain of the seed ensemble
(runs/ensemble_chain_mu2_N1e5.toml: eps = 0.1, RKC2 at tol 0.003), forward to <V^2> = 1e4
(~120 steps), analyses and figures off.  The two are run in interleaved pairs (this machine's
load moves a single timing by more than the difference); per run: the run's own wall time
(the file's wall_seconds, no start-up), steps, factorisations; per pair: the largest relative
difference of <V^2> between the two at the same step (same step sequence expected).
Writes docs/benchmarks/chain_solver.json.

    python benchmarks/bench_chain_solver.py [--pairs 5] [--N 100000] [--V2 1e4]
"""
from __future__ import annotations

import argparse
import os
import platform
import statistics
import subprocess
import sys
import tempfile

import h5py
import numpy as np

import results  # noqa: E402  (benchmarks/results.py)

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")

SCENE = """
title = "chain solver benchmark: mu = 2, eps = 0.1"
seed = {seed}
[model]
name = "chain"
N = {N}
epsilon = 0.1
mu = 2
[integrator]
method = "rkc"
tol = 0.003
[[protocol.leg]]
direction = "forward"
V2_above = {V2}
[observables]
analysis_every = 0
[output]
path = "unused.h5"
"""

PACKAGES = {"cholmod": [], "petsc": ["-tau_pc_factor_mat_solver_type", "petsc"]}


def run(scene: str, out: str, package: str) -> dict:
    cmd = [sys.executable, "-m", "parflow.shear", scene, "--output", out, "--overwrite",
           "--quiet", "--no-plots", *PACKAGES[package]]
    subprocess.run(cmd, check=True, cwd=ROOT)
    with h5py.File(out) as f:
        return dict(package=package, status=str(f.attrs["status"]), steps=int(f.attrs["steps"]),
                    factorisations=int(f.attrs["n_factorisations"]),
                    solver=str(f.attrs["solver"]),
                    wall_seconds=round(float(f.attrs["wall_seconds"]), 3),
                    loadavg_end=[round(float(x), 2) for x in f.attrs["loadavg_end"]]), \
            f["timeseries/V2"][:]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=5)
    ap.add_argument("--N", type=int, default=100_000)
    ap.add_argument("--V2", type=float, default=1e4)
    ap.add_argument("--seed", type=int, default=4215923173971654960)   # the ensemble's sample 0
    args = ap.parse_args()
    if args.pairs < 1 or args.N < 10 or not args.V2 > 0:
        print("bench_chain_solver: --pairs >= 1, --N >= 10 and --V2 > 0 are needed", file=sys.stderr)
        return 2
    runs, pairs = [], []
    with tempfile.TemporaryDirectory() as tmp:
        scene = os.path.join(tmp, "scene.toml")
        with open(scene, "w") as fh:
            fh.write(SCENE.format(seed=args.seed, N=args.N, V2=args.V2))
        for p in range(args.pairs):
            order = ("cholmod", "petsc") if p % 2 == 0 else ("petsc", "cholmod")
            got = {}
            for pkg in order:
                rec, v2 = run(scene, os.path.join(tmp, f"{pkg}.h5"), pkg)
                rec["pair"] = p
                runs.append(rec)
                got[pkg] = (rec, v2)
                print(f"pair {p} {pkg:8s} {rec['steps']} steps {rec['wall_seconds']:.2f} s", flush=True)
            (a, va), (b, vb) = got["cholmod"], got["petsc"]
            same = a["steps"] == b["steps"]
            diff = float(np.max(np.abs(va - vb) / np.abs(va))) if same else float("nan")
            pairs.append(dict(pair=p, same_steps=same, V2_max_rel_diff=diff,
                              speedup=round(a["wall_seconds"] / b["wall_seconds"], 3)))
    walls = {k: [r["wall_seconds"] for r in runs if r["package"] == k] for k in PACKAGES}
    summary = dict(
        mean_wall={k: round(statistics.mean(v), 3) for k, v in walls.items()},
        range_wall={k: [min(v), max(v)] for k, v in walls.items()},
        pairs_in_petsc_favour=sum(p["speedup"] > 1 for p in pairs),
        mean_speedup=round(statistics.mean(p["speedup"] for p in pairs), 3))
    out = results.write("chain_solver", dict(
        benchmark="chain force solve: CHOLMOD vs PETSc's own Cholesky",
        scene=dict(N=args.N, epsilon=0.1, mu=2, integrator="rkc, tol 0.003", V2_above=args.V2,
                   seed=args.seed),
        machine=platform.node(), cpu=platform.processor() or platform.machine(),
        runs=runs, pairs=pairs, summary=summary))
    print(f"mean wall {summary['mean_wall']}, {summary['pairs_in_petsc_favour']}/{args.pairs} pairs "
          f"in PETSc's favour, mean speedup {summary['mean_speedup']}; wrote {os.path.relpath(out)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
