"""Strong scaling of the deflated force solve: iterations, time and communication per rank
count, at one saved network state (issue "Numerics built for the near-singular regime":
"a strong-scaling table ... with more ranks on the 2 cores (oversubscribed), the iteration
counts and communication volume", and the inputs of the performance model in docs/solvers.md).

The state: the configuration of ``bench_deflated.py`` where sigma first passed ``--sigma``
(out/bench_deflated/states_N{n}.npz, made by that benchmark).  On P ranks, N is row-distributed
(``parallel = "auto"``), the preconditioner is block Jacobi with one ICC(0) block per rank (ICC(0)
on one rank), k = 4 deflation vectors from SLEPc at the first solve.  The second solve is the
measured one, inside a PETSc log stage: its wall time, CG iterations, and over all ranks the
MPI messages and bytes PETSc sent (the halo exchange of each product with N), PETSc's
reductions, and the reductions of the deflation itself (mpi4py allreduces of the products with
W^T, counted here); per rank the rows, the nonzeros of its block of N and the ghost entries
it receives per product.

    mpirun -n P --oversubscribe python benchmarks/bench_deflated_scaling.py --n 4096 [--sigma 1e4]
    -> docs/benchmarks/deflated_scaling.json (one record per N, sigma and rank count)

Times with more ranks than cores are not speeds (the ranks take turns); iterations, messages,
bytes and reductions do not depend on that.
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
from mpi4py import MPI  # noqa: E402
from petsc4py import PETSc  # noqa: E402

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from parflow.dynamics.bonded import BondedSystem  # noqa: E402
from parflow.models import get_model  # noqa: E402
from parflow.scene import load_scene  # noqa: E402

import results  # noqa: E402  (benchmarks/results.py)
from bench_deflated import SCENE, states  # noqa: E402

EVENTS = ("KSPSolve", "MatMult", "PCApply", "VecTDot", "VecNorm", "VecAXPY", "VecAYPX")


class CountingComm:
    """An mpi4py communicator whose allreduce calls are counted (the deflation's W^T products)."""

    def __init__(self, mpi):
        self._mpi, self.allreduces, self.numbers = mpi, 0, 0

    def allreduce(self, x, *a, **kw):
        self.allreduces += 1
        self.numbers += int(np.size(x))
        return self._mpi.allreduce(x, *a, **kw)

    def __getattr__(self, name):
        return getattr(self._mpi, name)


def ghosts(ops) -> tuple[int, int]:
    """(nonzeros of this rank's rows of N, distinct off-rank columns they touch: the ghost
    entries a product with N receives)."""
    cols = np.asarray(ops._n_indices)
    off = cols[(cols < ops.lo) | (cols >= ops.hi)]
    return int(cols.size), int(np.unique(off).size)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=4096)
    ap.add_argument("--sigma", type=float, default=1e4, help="the state where sigma first passed this")
    ap.add_argument("--folder", default=os.path.join("out", "bench_deflated"))
    args = ap.parse_args()
    comm = PETSc.COMM_WORLD
    mpi = comm.tompi4py()
    rank, size = comm.getRank(), comm.getSize()
    path = os.path.join(args.folder, f"states_N{args.n}.npz")
    if not os.path.exists(path):
        raise SystemExit(f"{path}: run benchmarks/bench_deflated.py --n {args.n} first (it saves the states)")
    S = states(args.folder, args.n, 1e8)
    m = int(np.argmin(np.abs(np.log(S["sigma"] / args.sigma))))
    network = os.path.join(args.folder, f"network_N{args.n}.h5")
    scene = load_scene(SCENE.format(n=args.n, network=network, top=1e8, folder=args.folder))
    st = get_model("network").build(scene["model"], 1)
    s, gamma = S["s"][m], float(S["gamma"][m])
    st.s, st.gamma = s, gamma
    PETSc.Log.begin()
    sysm = BondedSystem(comm, st, "deflated", "auto")
    sol = sysm.tau_solver
    F0 = sysm.evaluate(s, gamma)                      # the first solve: SLEPc's space
    counting = CountingComm(sol.mpi)
    sol.mpi = counting
    stage = PETSc.Log.Stage("timed deflated solve")
    mpi.Barrier()
    t = time.perf_counter()
    stage.push()
    F = sysm.evaluate(s, gamma)
    stage.pop()
    wall = time.perf_counter() - t
    mpi.Barrier()
    its = int(F.info.refinements)
    perf = {}
    for name in EVENTS:
        info = PETSc.Log.Event(name).getPerfInfo(stage.id)
        # messages and bytes summed over the ranks, counts, times and reductions their maximum
        perf[name] = {k: mpi.allreduce(float(info.get(k, 0.0)),
                                       op=MPI.SUM if k in ("numMessages", "messageLength") else MPI.MAX)
                      for k in ("count", "time", "flops", "numMessages", "messageLength", "numReductions")}
    nnz, gh = ghosts(sysm.ops)
    per_rank = mpi.gather(dict(rows=int(sysm.ops.hi - sysm.ops.lo), nnz=nnz, ghosts=gh,
                               deflation_allreduces=counting.allreduces,
                               deflation_numbers=counting.numbers), root=0)
    if rank == 0:
        ks = perf["KSPSolve"]
        row = dict(n=args.n, nc=len(st.bonds), ranks=size, sigma=float(F.sigma), sigma_level=args.sigma,
                   cores=os.cpu_count(), date=time.strftime("%Y-%m-%d %H:%M:%S"),
                   load=os.getloadavg(), pc=sol.describe(), k=sol.k, iterations=its,
                   seconds=wall, ms_per_iteration=1e3 * wall / max(its, 1),
                   sigma_mismatch=F.sigma_mismatch, backward_error=F.info.backward_error,
                   tau_vs_first=float(np.linalg.norm(F.tau - F0.tau) / np.linalg.norm(F0.tau)),
                   messages=ks["numMessages"], message_bytes=ks["messageLength"],
                   petsc_reductions=ks["numReductions"],
                   messages_per_iteration=ks["numMessages"] / max(its, 1),
                   bytes_per_iteration=ks["messageLength"] / max(its, 1),
                   reductions_per_iteration=(ks["numReductions"]
                                             + per_rank[0]["deflation_allreduces"]) / max(its, 1),
                   events=perf, per_rank=per_rank)
        p = results.path("deflated_scaling")
        old = {}
        if os.path.exists(p):
            with open(p) as fh:
                old = json.load(fh)
        recs = [r for r in old.get("records", [])
                if not (r["n"] == args.n and r["ranks"] == size and r["sigma_level"] == args.sigma)]
        recs.append(row)
        recs.sort(key=lambda r: (r["n"], r["sigma_level"], r["ranks"]))
        results.write("deflated_scaling", dict(benchmark="deflated CG: strong scaling and "
                                                          "communication at one network state",
                                               records=recs))
        print(f"N {args.n} P {size} sigma {row['sigma']:.3g}: {its} iterations, {wall:.2f} s "
              f"({row['ms_per_iteration']:.2f} ms/it), {row['messages_per_iteration']:.1f} messages "
              f"and {row['bytes_per_iteration']:.0f} B per iteration, "
              f"{row['reductions_per_iteration']:.2f} reductions per iteration, ghosts "
              f"{[r['ghosts'] for r in per_rank]}", flush=True)
    sysm.destroy()


if __name__ == "__main__":
    main()
