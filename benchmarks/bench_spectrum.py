"""omega_min and the 6 lowest eigenpairs of N at Nc ~ 1e6 (target: <= 10 s on 2 ranks).

A WLKM-diluted perturbed triangular lattice (z = 3.8, the sparsity of a 2D floppy network),
N loaded at gamma = 0; SLEPc Krylov-Schur, shift-and-invert at 0 on a Cholesky factor
(parflow.algebra.spectrum.LowSpectrum): by default the force solver's factor of N, as in a run that
tracks omega_min (--own-factor: a factorisation of its own, symbolic analysis included).  Writes docs/benchmarks/spectrum.json (one record per rank
count and factorisation).

    python benchmarks/bench_spectrum.py [--nc 1e6] ;  mpirun -n 2 python benchmarks/bench_spectrum.py
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import petsc4py

petsc4py.init(sys.argv[:1])
from petsc4py import PETSc  # noqa: E402

import results  # noqa: E402  (benchmarks/results.py)
from bench_force import lattice_state  # noqa: E402
from parflow.algebra.spectrum import LowSpectrum, omega_from_lambda  # noqa: E402
from parflow.dynamics.bonded import BondedSystem  # noqa: E402


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--nc", type=float, default=1e6)
    p.add_argument("--k", type=int, default=6)
    p.add_argument("--parallel", default="auto", choices=["auto", "replicated", "redundant", "mumps"])
    p.add_argument("--own-factor", action="store_true",
                   help="factorise N for SLEPc instead of reusing the force solver's factor")
    args = p.parse_args()
    comm = PETSc.COMM_WORLD
    st, info = lattice_state(int(args.nc))
    sysm = BondedSystem(comm, st, parallel=args.parallel)
    sysm.evaluate(st.s, 0.0)
    comm.tompi4py().Barrier()
    t = time.perf_counter()
    spec = LowSpectrum(sysm.ops.N, k=args.k, parallel=args.parallel,
                       ksp=None if args.own_factor else sysm.tau_solver.ksp)
    lam, _ = spec.solve()
    comm.tompi4py().Barrier()
    wall = time.perf_counter() - t
    its = spec.eps.getIterationNumber()
    spec.destroy()
    rec = dict(Nc=len(st.bonds), k=args.k, ranks=comm.getSize(), parallel=args.parallel,
               factor="own" if args.own_factor else "shared with the force solve",
               seconds=round(wall, 3), iterations=its, omega=[float(w) for w in omega_from_lambda(lam)],
               system=info["kind"], load=os.getloadavg())
    if comm.getRank() == 0:
        print(rec, flush=True)
        data = {"benchmark": "omega_min and the k lowest eigenpairs of N", "records": []}
        if os.path.exists(results.path("spectrum")):
            with open(results.path("spectrum")) as fh:
                data = json.load(fh)
        data["records"] = [r for r in data["records"]
                           if (r["Nc"], r["ranks"], r["parallel"], r["k"], r.get("factor")) !=
                           (rec["Nc"], rec["ranks"], rec["parallel"], rec["k"], rec["factor"])] + [rec]
        data["date"] = time.strftime("%Y-%m-%d %H:%M:%S")
        results.write("spectrum", data)
    sysm.destroy()


if __name__ == "__main__":
    main()
