"""Cost of one force evaluation against the raw factorisation it wraps (issue 2, "Speed").

One parflow force evaluation = pair geometry (numpy), values of N (CSR, pattern locked),
numeric refactorisation + solve (PETSc KSP), residual check, gather of tau and
V_na = S^T tau.  The reference, timed on the same matrix in the same run, is a bare PETSc
KSP (preonly + Cholesky, same factor package) doing only the numeric refactorisation and
the solve.  Ratio = parflow / raw; the target is <= 1.2 at Nc = 1e5.

Systems: rigid chains (Nc = N: a narrow-band N) and 2D floppy networks (z = 3.8 from a
jammed packing; for Nc = 1e6 a perturbed triangular lattice diluted by the same WLKM rule,
which has the same 2D sparsity structure).

    python benchmarks/bench_force.py [--sizes 1e4,1e5,1e6] [--repeat 20]
    mpirun -n 2 python benchmarks/bench_force.py

Results are appended to docs/benchmarks/force.json (one record per system and rank count).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

import petsc4py

petsc4py.init(sys.argv[:1])
import numpy as np  # noqa: E402
from petsc4py import PETSc  # noqa: E402

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from parflow.geometry import velocity_gradient  # noqa: E402
from parflow.models import chain  # noqa: E402
from parflow.algebra.comm import idle_barrier  # noqa: E402
from parflow.algebra.solvers import configure_cholesky, set_blas_threads, use_cores  # noqa: E402
from parflow.state import Bonds, State  # noqa: E402
from parflow.dynamics.bonded import BondedSystem  # noqa: E402

import results  # noqa: E402  (benchmarks/results.py)


def chain_state(nc: int) -> State:
    return chain.build(dict(N=nc, epsilon=0.1, mu=0), seed=1)


def network_state(n: int, z: float = 3.8) -> tuple[State, dict]:
    from parflow.models.network_build import network_from_packing
    from parflow.packing.fire import make_packing
    t = time.perf_counter()
    pk = make_packing(n, phi=0.88, seed=1)
    net = network_from_packing(pk, z, seed=1, check_self_stress=False)
    st = State(net.s, net.h0, velocity_gradient("shear", 2), 0.0, net.bonds)
    return st, dict(kind="network (packing, WLKM)", n_nodes=net.n, build_seconds=time.perf_counter() - t)


def lattice_state(n_bonds: int, z: float = 3.8) -> tuple[State, dict]:
    """Perturbed triangular lattice diluted by the WLKM rule to coordination z."""
    from parflow.models.network_build import dilute
    t = time.perf_counter()
    n_nodes = int(2 * n_bonds / z)
    L = int(np.sqrt(n_nodes))
    L += L % 2
    ix, iy = np.meshgrid(np.arange(L), np.arange(L), indexing="ij")
    ix, iy = ix.ravel(), iy.ravel()
    idx = lambda x, y: (x % L) * L + (y % L)  # noqa: E731
    i_list, j_list, sh = [], [], []
    for dx, dy in ((1, 0), (0, 1), (-1, 1)):          # triangular lattice on a sheared grid
        jx, jy = ix + dx, iy + dy
        i_list.append(idx(ix, iy))
        j_list.append(idx(jx, jy))
        sh.append(np.column_stack([jx // L, jy // L]))
    i, j, shift = np.concatenate(i_list), np.concatenate(j_list), np.concatenate(sh)
    rng = np.random.default_rng(1)
    keep = dilute(L * L, i, j, int(z * L * L / 2), 2, rng)
    i, j, shift = i[keep], j[keep], shift[keep]
    a = np.column_stack([ix + 0.5 * iy, iy * np.sqrt(3) / 2]).astype(float)
    a += 0.15 * rng.standard_normal(a.shape)
    h0 = np.array([[L, 0.5 * L], [0.0, L * np.sqrt(3) / 2]])
    s = a @ np.linalg.inv(h0).T
    r = (s[j] + shift - s[i]) @ h0.T
    st = State(s, h0, velocity_gradient("shear", 2), 0.0, Bonds(i, j, shift, np.linalg.norm(r, axis=1)))
    return st, dict(kind="triangular lattice, WLKM-diluted", n_nodes=L * L,
                    build_seconds=time.perf_counter() - t)


def timeit(fn, repeat, comm=None):
    comm = (comm or PETSc.COMM_WORLD).tompi4py()
    fn()                                   # warm-up (symbolic factorisation, caches)
    ts = []
    for _ in range(repeat):
        comm.Barrier()
        t = time.perf_counter()
        fn()
        comm.Barrier()
        ts.append(time.perf_counter() - t)
    return float(np.median(ts))


def measure(st: State, repeat: int, parallel: str, comm=None) -> dict:
    comm = comm or PETSc.COMM_WORLD
    sysm = BondedSystem(comm, st, parallel=parallel)
    s0 = st.s.copy()
    k = [0]

    def force():                            # a slightly different configuration each time
        k[0] += 1
        sysm.evaluate(s0, 1e-9 * k[0])

    t_force = timeit(force, repeat, comm)
    # geometry alone, and N values alone, for the breakdown
    t_geom = timeit(lambda: sysm.geometry(s0, 1e-9), repeat, comm)
    n = sysm.geometry(s0, 0.0)[3]
    t_load = timeit(lambda: sysm.ops.update(n), repeat, comm)

    # raw: a bare KSP on a copy of N, numeric refactorisation + solve only
    M = sysm.ops.N.duplicate(copy=True)
    ksp = PETSc.KSP().create(M.getComm())      # COMM_SELF when the algebra is replicated
    ksp.setOptionsPrefix("raw_")
    configure_cholesky(ksp, "raw_", sysm.parallel)
    ksp.setOperators(M)
    ksp.setFromOptions()
    x, b = M.createVecs()
    b.set(1.0)

    def raw():
        M.assemble()                        # new state, same pattern: numeric refactor only
        ksp.solve(b, x)
        if ksp.getConvergedReason() < 0:
            raise RuntimeError("raw solve failed")

    t_raw = timeit(raw, repeat, comm)
    package = sysm.tau_solver.package
    ksp.destroy(), M.destroy(), x.destroy(), b.destroy()
    sysm.destroy()
    return dict(force_seconds=t_force, raw_refactor_solve_seconds=t_raw,
                ratio=t_force / t_raw, geometry_seconds=t_geom, load_N_seconds=t_load,
                factor_package=package)


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--sizes", default="1e4,1e5,1e6")
    p.add_argument("--systems", default="chain,network")
    p.add_argument("--repeat", type=int, default=15)
    p.add_argument("--parallel", default="auto",
                   choices=["auto", "replicated", "redundant", "mumps", "threads"])
    args = p.parse_args()
    comm = PETSc.COMM_WORLD
    records = []
    for size in [int(float(x)) for x in args.sizes.split(",")]:
        for system in args.systems.split(","):
            if system == "chain":
                st, info = chain_state(size), dict(kind="chain", n_nodes=size)
            elif size <= 200_000:
                st, info = network_state(int(size / 1.9))
            else:
                st, info = lattice_state(size)
            rec = dict(system=system, Nc=len(st.bonds), ranks=comm.getSize(), parallel=args.parallel, **info)
            if args.parallel == "threads" and comm.getSize() > 1:
                # as parflow.shear does it: rank 0 alone with one BLAS thread per rank, the
                # others waiting without spinning
                if comm.getRank() == 0:
                    _, prev = use_cores(comm.getSize())
                    rec.update(measure(st, args.repeat, "threads", PETSc.COMM_SELF))
                    if prev is not None:
                        set_blas_threads(prev)
                idle_barrier(comm)
                rec = comm.tompi4py().bcast(rec, root=0)
            else:
                rec.update(measure(st, args.repeat, args.parallel))
            records.append(rec)
            if comm.getRank() == 0:
                print(f"{system:8s} Nc={rec['Nc']:8d} ranks={rec['ranks']} {rec['factor_package']:18s} "
                      f"force {1e3 * rec['force_seconds']:8.2f} ms  raw {1e3 * rec['raw_refactor_solve_seconds']:8.2f} ms  "
                      f"ratio {rec['ratio']:.2f}  (geometry {1e3 * rec['geometry_seconds']:.2f} ms, "
                      f"N values {1e3 * rec['load_N_seconds']:.2f} ms)", flush=True)
    if comm.getRank() == 0:
        data = {"benchmark": "force evaluation vs raw refactor+solve", "records": []}
        if os.path.exists(results.path("force")):
            with open(results.path("force")) as fh:
                data = json.load(fh)
        keyf = lambda r: (r["system"], r["Nc"], r["ranks"], r["parallel"])  # noqa: E731
        new = {keyf(r) for r in records}
        data["records"] = [r for r in data["records"] if keyf(r) not in new] + records
        data["machine"] = dict(platform=platform.platform(), cpus=os.cpu_count(),
                               load=os.getloadavg())
        data["date"] = time.strftime("%Y-%m-%d %H:%M:%S")
        results.write("force", data)


if __name__ == "__main__":
    main()
