"""CHOLMOD's own choices on a network's N (issue "Numerics built for the near-singular
regime": what a factorisation and a solve cost, and whether CHOLMOD's settings move them).

For each network (the benchmarks' z = 3.8 network of N nodes, or a saved network file) N =
S S^T at its initial configuration is factorised on one rank with CHOLMOD through PETSc, once
per variant of CHOLMOD's settings (PETSc options ``mat_cholmod_*`` under a prefix of the
variant's own):

  supernodal   the default (CHOLMOD picks supernodal for these matrices; AMD ordering)
  simplicial   ``mat_cholmod_factor = simplicial`` (an up-looking factor, no BLAS)
  orderings9   ``mat_cholmod_nmethods = 9``: the best fill of nine orderings (AMD, METIS,
               NESDIS variants; the analysis is paid once per network, its pattern fixed)
  smallsuper   less supernode amalgamation (``nrelax = 1,4,16``, ``zrelax = 0.5,0.05,0.01``)

Per variant: the first factorisation (analysis + numeric), the numeric refactorisation of the
same pattern (median of refactorisation + solve, less the solve), one solve with one
right-hand side (median), nonzeros of the factor.
A ROS2 or stage-PCG step at N = 40 000 takes ~28 solves per factorisation
(docs/benchmarks.md, "Integrators on a network"), so the solve weighs as much as the
factorisation there.

    python benchmarks/bench_cholmod.py [--sizes 40000] [--network-file out/network_N1e6_z3.8.h5]
        [--repeat 5] [--rounds 2]   ->  docs/benchmarks/cholmod.json
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import petsc4py

petsc4py.init(sys.argv[:1])
import numpy as np  # noqa: E402
from petsc4py import PETSc  # noqa: E402

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from parflow.algebra.solvers import configure_cholesky  # noqa: E402
from parflow.dynamics.bonded import BondedSystem  # noqa: E402
from parflow.geometry import velocity_gradient  # noqa: E402
from parflow.models.network_build import load_network  # noqa: E402
from parflow.state import State  # noqa: E402

import results  # noqa: E402  (benchmarks/results.py)
from common import network_file  # noqa: E402  (benchmarks/common.py)

VARIANTS = {
    "supernodal": {},
    "simplicial": {"mat_cholmod_factor": "simplicial"},
    "orderings9": {"mat_cholmod_nmethods": 9},
    "smallsuper": {"mat_cholmod_nrelax": "1,4,16", "mat_cholmod_zrelax": "0.5,0.05,0.01"},
}


def network_N(path: str) -> tuple[PETSc.Mat, int]:
    """N at the network's initial configuration (a copy on COMM_SELF) and its node count."""
    net = load_network(path)
    st = State(net.s, net.h0, velocity_gradient("shear", 2), 0.0, net.bonds)
    sysm = BondedSystem(PETSc.COMM_SELF, st, parallel="replicated")
    sysm.ops.update(sysm.geometry(st.s, 0.0)[3])
    M = sysm.ops.N.duplicate(copy=True)
    sysm.destroy()
    return M, net.n


def measure(M: PETSc.Mat, name: str, opts: dict, repeat: int) -> dict:
    prefix = f"bench_cholmod_{name}_"
    db = PETSc.Options()
    for k, v in opts.items():
        db.setValue(prefix + k, v)
    A = M.duplicate(copy=True)
    ksp = PETSc.KSP().create(PETSc.COMM_SELF)
    ksp.setOptionsPrefix(prefix)
    configure_cholesky(ksp, prefix)          # one rank: preonly + Cholesky by CHOLMOD
    pc = ksp.getPC()
    ksp.setOperators(A)
    ksp.setFromOptions()
    x, b = A.createVecs()
    b.setRandom()
    t = time.perf_counter()
    ksp.setUp()
    first = time.perf_counter() - t
    ksp.solve(b, x)
    refactor, solve = [], []
    for _ in range(repeat):
        A.assemble()                        # "new" values, same pattern: numeric refactorisation
        t = time.perf_counter()
        ksp.solve(b, x)                     # (PETSc refactorises at the solve)
        refactor.append(time.perf_counter() - t)
    for _ in range(4 * repeat):
        t = time.perf_counter()
        ksp.solve(b, x)
        solve.append(time.perf_counter() - t)
    if ksp.getConvergedReason() < 0:
        raise RuntimeError(f"{name}: the solve failed ({ksp.getConvergedReason()})")
    r = x.duplicate()
    A.mult(x, r)
    r.axpy(-1.0, b)
    rel = r.norm() / b.norm()
    nz = int(pc.getFactorMatrix().getInfo()["nz_used"])
    for o in (ksp, A, x, b, r):
        o.destroy()
    for k in opts:
        db.delValue(prefix + k)
    t_solve = float(np.median(solve))
    return dict(variant=name, options=opts, first_seconds=first,
                refactor_seconds=float(np.median(refactor)) - t_solve, solve_seconds=t_solve,
                factor_nonzeros=nz, residual=float(rel))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", default="40000", help="benchmark networks of these node counts")
    ap.add_argument("--network-file", action="append", default=[],
                    help="also a saved network (e.g. out/network_N1e6_z3.8.h5)")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--rounds", type=int, default=2)
    args = ap.parse_args()
    if PETSc.COMM_WORLD.getSize() != 1:
        raise SystemExit("bench_cholmod.py runs on one rank")
    variants = args.variants.split(",")
    if not set(variants) <= set(VARIANTS):
        raise SystemExit(f"--variants: a subset of {list(VARIANTS)}")
    paths = [network_file(os.path.join("out", "bench_network_integrators"), int(float(n)),
                          PETSc.COMM_WORLD) for n in args.sizes.split(",") if n]
    paths += args.network_file
    load_start = os.getloadavg()
    records = []
    for p in paths:
        M, n = network_N(p)
        # the variants interleaved, --rounds times: each number is the smallest of its rounds'
        # medians (other jobs on the machine slow a whole round, not one variant)
        runs = {v: [] for v in variants}
        for _ in range(args.rounds):
            for v in variants:
                runs[v].append(measure(M, v, VARIANTS[v], args.repeat))
        rows = []
        for v in variants:
            r = dict(runs[v][0])
            for k in ("first_seconds", "refactor_seconds", "solve_seconds"):
                r[k] = min(x[k] for x in runs[v])
            rows.append(r)
            print(f"N = {n}, Nc = {M.getSize()[0]}: {v:11s} first {r['first_seconds']:.3f} s, "
                  f"refactor {r['refactor_seconds']:.4f} s, "
                  f"solve {1e3 * r['solve_seconds']:.2f} ms, nnz(L) {r['factor_nonzeros']:,}, "
                  f"residual {r['residual']:.1e}", flush=True)
        records.append(dict(network=os.path.basename(p), n=n, nc=M.getSize()[0],
                            nnz_N=int(M.getInfo()["nz_used"]), rows=rows, repeat=args.repeat,
                            rounds=args.rounds, date=time.strftime("%Y-%m-%d %H:%M"),
                            load_start=load_start, load_end=os.getloadavg()))
        M.destroy()
    # the records of other networks (an earlier invocation) stay
    kept = []
    if os.path.exists(results.path("cholmod")):
        with open(results.path("cholmod")) as fh:
            done = {r["network"] for r in records}
            kept = [r for r in json.load(fh).get("records", []) if r["network"] not in done]
    results.write("cholmod", dict(benchmark="CHOLMOD settings on a network's N",
                                  records=kept + records))


if __name__ == "__main__":
    main()
