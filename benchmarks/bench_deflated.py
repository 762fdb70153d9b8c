"""The deflated force solve against the direct one, along a network sheared toward jamming.

A network (packing at phi = 0.88, WLKM dilution to z = 3.8, seed 1) is sheared forward with
the direct solver; the configuration where sigma first exceeds each decade 10, 1e2, ... is
saved (out/bench_deflated/states_N{n}.npz, made once).  At each saved state: the direct
solve (numeric factorisation + solve, CHOLMOD), the deflated solve ([solver] preset =
"deflated": k lowest eigenvectors from SLEPc at the first solve, then the solve with that
space: iterations, time), and, for comparison, the same CG without deflation (20 000
iterations at most).  Also the lowest eigenvalues, the difference from the direct solve,
the sigma identity, and at the top state the preconditioners and k.

    python benchmarks/bench_deflated.py --n 4096
    mpirun -n 2 python benchmarks/bench_deflated.py --n 4096
    -> docs/benchmarks/deflated.json (one record per N and rank count)
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
import numpy as np  # noqa: E402
from petsc4py import PETSc  # noqa: E402

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from parflow.algebra.deflated import DeflatedSolver  # noqa: E402
from parflow.dynamics.bonded import BondedSystem  # noqa: E402
from parflow.dynamics.engines import make_engine  # noqa: E402
from parflow.models import get_model  # noqa: E402
from parflow.scene import load_scene  # noqa: E402

import results  # noqa: E402  (benchmarks/results.py)
from common import NETWORK_MODEL, network_file  # noqa: E402  (benchmarks/common.py)

SCENE = NETWORK_MODEL + """[[protocol.leg]]
direction = "forward"
sigma_above = {top}
[output]
path = "{folder}/unused.h5"
"""


def states(folder, n, top):
    """The configurations where sigma first exceeds 10, 100, ..., top (made once)."""
    comm = PETSc.COMM_WORLD
    path = os.path.join(folder, f"states_N{n}.npz")
    if os.path.exists(path):
        return np.load(path)
    network = network_file(folder, n, comm)
    scene = load_scene(SCENE.format(n=n, network=network, top=top, folder=folder))
    model = get_model("network")
    eng = make_engine(PETSc.COMM_SELF, model.build(scene["model"], 1), scene, model)
    F = eng.start()
    level, out = 1, dict(s=[], gamma=[], sigma=[])
    t = time.perf_counter()
    while level <= np.log10(top) + 1e-9:
        eng.step(1, None)
        F = eng.F
        if F.sigma >= 10.0 ** level:
            out["s"].append(eng.s.copy())
            out["gamma"].append(eng.gamma)
            out["sigma"].append(F.sigma)
            if comm.getRank() == 0:
                print(f"  state sigma = {F.sigma:.3e} at gamma = {eng.gamma:.5f} "
                      f"({time.perf_counter() - t:.0f} s)", flush=True)
            while F.sigma >= 10.0 ** level:
                level += 1
            if comm.getRank() == 0:       # after each decade: an interrupted run keeps them
                np.savez(path + ".part.npz", **{k: np.array(v) for k, v in out.items()})
    eng.destroy()
    if comm.getRank() == 0:
        os.replace(path + ".part.npz", path)
    comm.tompi4py().Barrier()
    return np.load(path)


def timed(fn, repeat=2):
    """Median wall time of fn() over ``repeat`` calls (all ranks in step), its last result."""
    mpi = PETSc.COMM_WORLD.tompi4py()
    ts = []
    for _ in range(repeat):
        mpi.Barrier()
        t = time.perf_counter()
        res = fn()
        mpi.Barrier()
        ts.append(time.perf_counter() - t)
    return float(np.median(ts)), res


def rel(a, b):
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


def at_state(state, s, gamma, plain_max_it, extra=False):
    comm = PETSc.COMM_WORLD
    st = state.copy()
    st.s, st.gamma = s, gamma
    row = {}
    direct = BondedSystem(comm, st, "direct", "auto")
    t_direct, Fd = timed(lambda: direct.evaluate(s, gamma))
    row.update(sigma=Fd.sigma, direct_seconds=t_direct, direct_backward_error=Fd.info.backward_error,
               direct_sigma_mismatch=Fd.sigma_mismatch, direct_parallel=direct.parallel)
    direct.destroy()

    defl = BondedSystem(comm, st, "deflated", "auto")
    sol = defl.tau_solver
    mpi = comm.tompi4py()
    mpi.Barrier()
    t = time.perf_counter()
    F = defl.evaluate(s, gamma)                       # the first solve computes the space
    t_first = time.perf_counter() - t
    t_solve, F = timed(lambda: defl.evaluate(s, gamma))
    t_refresh, _ = timed(sol.refresh, 1)
    row.update(k=sol.k, pc=sol.describe(), lambda_low=[float(v) for v in sol.ritz[:3]],
               first_solve_seconds=t_first, iterations=int(F.info.refinements),
               seconds=t_solve, backward_error=F.info.backward_error,
               sigma_mismatch=F.sigma_mismatch, tau_vs_direct=rel(F.tau, Fd.tau),
               V_vs_direct=rel(F.V_na, Fd.V_na), refresh_seconds=t_refresh,
               deflation_space_mb_per_rank=2 * sol.W.nbytes / 2**20,
               rows_per_rank=int(sol.hi - sol.lo))
    ops = defl.ops
    if plain_max_it:
        db = PETSc.Options()
        db.setValue("plain_defl_max_it", plain_max_it)
        plain = DeflatedSolver(ops.N, "plain_", defl.parallel, deflate=False)
        plain.norm_bound = ops.norm_bound
        ops.set_local(ops.rhs, -F.b)
        x = ops.tau.duplicate()
        t = time.perf_counter()
        try:
            info = plain.solve(ops.rhs, x, "plain CG")
            row.update(plain_iterations=int(info.refinements))
        except Exception as exc:                       # noqa: BLE001  (recorded: the point)
            row.update(plain_iterations=None, plain_error=str(exc).split(";")[0])
        row["plain_seconds"] = time.perf_counter() - t
        plain.destroy()
        x.destroy()
    if extra:
        row["variants"] = variants(defl, F)
    defl.destroy()
    return row


PCS = [("icc", "pc_type=icc"), ("jacobi", "pc_type=jacobi"),
       ("bjacobi/icc", "pc_type=bjacobi sub_pc_type=icc"),
       ("bjacobi(8)/cholmod", "pc_type=bjacobi pc_bjacobi_blocks=8 sub_pc_type=cholesky "
                              "sub_pc_factor_mat_solver_type=cholmod"),
       ("asm/icc", "pc_type=asm sub_pc_type=icc"),
       ("gamg", "pc_type=gamg"), ("hypre", "pc_type=hypre")]


VARIANTS = dict(pcs=None, ks=(1, 4, 8, 20))    # set from the command line


def variants(defl, F):
    """Preconditioners and k at one state: iterations and time per solve."""
    ops, out = defl.ops, []
    db = PETSc.Options()
    for case, (name, spec) in enumerate(PCS):
        if PETSc.COMM_WORLD.getSize() > 1 and name == "icc":
            continue                                   # serial only
        if VARIANTS["pcs"] is not None and name not in VARIANTS["pcs"]:
            continue
        for k in VARIANTS["ks"]:
            if k != 8 and name not in ("icc", "bjacobi/icc", "jacobi"):
                continue
            p = f"v{case}k{k}_"
            for kv in spec.split():
                key, val = kv.split("=")
                db.setValue(p + key, val)
            db.setValue(p + "defl_max_it", 20000)
            sol = DeflatedSolver(ops.N, p, defl.parallel, k=k)
            sol.norm_bound = ops.norm_bound
            sol.set_factor(ops.S_at)
            x = ops.tau.duplicate()
            ops.set_local(ops.rhs, -F.b)
            try:
                sol.solve(ops.rhs, x, "variant")
                t, info = timed(lambda: sol.solve(ops.rhs, x, "variant"))
                out.append(dict(pc=name, k=k, iterations=int(info.refinements), seconds=t))
            except Exception as exc:                   # noqa: BLE001  (recorded)
                out.append(dict(pc=name, k=k, iterations=None, error=str(exc).split(";")[0]))
            if PETSc.COMM_WORLD.getRank() == 0:
                print("   ", out[-1], flush=True)
            sol.destroy()
            x.destroy()
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=4096)
    ap.add_argument("--top", type=float, default=1e8)
    ap.add_argument("--plain-max-it", type=int, default=20000)
    ap.add_argument("--variants", action="store_true", help="preconditioners and k at the top state")
    ap.add_argument("--variants-only", action="store_true",
                    help="only the variants at the top state, into the existing record")
    ap.add_argument("--variant-pcs", default=None, help="comma-separated names from PCS")
    ap.add_argument("--variant-ks", default="1,4,8,20")
    ap.add_argument("--folder", default=os.path.join("out", "bench_deflated"))
    args = ap.parse_args()
    VARIANTS["pcs"] = None if args.variant_pcs is None else args.variant_pcs.split(",")
    VARIANTS["ks"] = tuple(int(k) for k in args.variant_ks.split(","))
    comm = PETSc.COMM_WORLD
    rank, size = comm.getRank(), comm.getSize()
    os.makedirs(args.folder, exist_ok=True)
    S = states(args.folder, args.n, args.top)
    network = os.path.join(args.folder, f"network_N{args.n}.h5")
    scene = load_scene(SCENE.format(n=args.n, network=network, top=args.top, folder=args.folder))
    state = get_model("network").build(scene["model"], 1)
    if args.variants_only:
        # the preconditioners and k at the top state only, merged into the existing record
        m = len(S["sigma"]) - 1
        row = at_state(state, S["s"][m], float(S["gamma"][m]), 0, extra=True)
        if rank == 0:
            with open(results.path("deflated")) as fh:
                old = json.load(fh)
            rec = next(r for r in old["records"] if r["n"] == args.n and r["ranks"] == size)
            rec["rows"][-1]["variants"] = row["variants"]
            results.write("deflated", old)
        return
    rows = []
    for m in range(len(S["sigma"])):
        last = m == len(S["sigma"]) - 1
        row = at_state(state, S["s"][m], float(S["gamma"][m]), args.plain_max_it,
                       extra=args.variants and last)
        rows.append(row)
        if rank == 0:
            print(f"sigma {row['sigma']:9.3e}  lambda_1 {row['lambda_low'][0]:.2e}  direct "
                  f"{1e3 * row['direct_seconds']:7.1f} ms | deflated {row['iterations']:5d} it "
                  f"{1e3 * row['seconds']:7.1f} ms (first {row['first_solve_seconds']:.2f} s, "
                  f"refresh {row['refresh_seconds']:.2f} s), dtau {row['tau_vs_direct']:.1e}, "
                  f"mismatch {row['sigma_mismatch']:.1e} (direct {row['direct_sigma_mismatch']:.1e})"
                  f" | plain {row.get('plain_iterations')}", flush=True)
    if rank == 0:
        old = {}
        p = results.path("deflated")
        if os.path.exists(p):
            with open(p) as fh:
                old = json.load(fh)
        recs = [r for r in old.get("records", []) if not (r["n"] == args.n and r["ranks"] == size)]
        recs.append(dict(n=args.n, nc=len(state.bonds), ranks=size,
                         date=time.strftime("%Y-%m-%d %H:%M:%S"), load_end=os.getloadavg(),
                         peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                         rows=rows))
        results.write("deflated", dict(benchmark="deflated CG against the direct force solve, "
                                                 "network sheared toward jamming", records=recs))


if __name__ == "__main__":
    main()
