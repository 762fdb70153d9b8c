"""The contact LCP: a fresh factorisation of N_AA for every active set, against one
factorisation kept and bordered (Schur complement) updates (dynamics.lcp.ActiveSolver).

Takes a suspension run file with a checkpoint (e.g. out/fig6_suspension_phi0.840.h5), steps
the suspension on from it for ``--steps`` steps recording every LCP the steps solve, then
solves each recorded LCP again with each strategy, one process, and compares: wall time,
solves, factorisations, and the largest difference of V = S^T f from the recorded solution
(f itself is not unique when N_C is singular; V is).  Writes docs/benchmarks/lcp.json.

    python benchmarks/bench_lcp.py out/fig6_suspension_phi0.840.h5 --steps 40
    python benchmarks/bench_lcp.py          # makes out/bench_lcp_phi0.840.h5 first (300 steps)
    python benchmarks/bench_lcp.py --strategies RUN [RUN ...] --steps 60
        # block pivoting / projected Newton / Lawson-Hanson on the same LCPs of each run
    python benchmarks/bench_lcp.py --factors RUN --steps 40 [--repeat 3]
        # the factorisation of N_AA: CHOLMOD auto / simplicial / supernodal, SuperLU
        # (interleaved, --repeat passes each); writes docs/benchmarks/lcp_factors.json
    python benchmarks/bench_lcp.py --budget RUN --steps 600
        # the first tries' LCP budget (150 solves) against 600 on every try, stepping on
        # from RUN's checkpoint; writes docs/benchmarks/lcp_budget.json
    python benchmarks/bench_lcp.py --retry [STATE ...] [--seconds 120 --rounds 2]
        # a failed first try retried at the last step's size (the default) against at
        # RETRY_FACTOR x its size, stepping on from each state (default: the creeping
        # N = 8192 state and out/bench_lcp_phi0.840.h5); writes docs/benchmarks/lcp_retry.json
    python benchmarks/bench_lcp.py --closed-gaps [--seconds 120]
        # closed contacts at round-off gaps taken as they are against closed exactly
        # (hard_discs.GAP_ROUNDOFF), on the recorded creeping N = 8192 state
        # (tests/reference/creeping_state.npz): its LCP at steps 1e-10 - 1e-6, then stepping
        # on for --seconds each; writes docs/benchmarks/lcp_closed_gaps.json
    python benchmarks/bench_lcp.py --profile RUN --steps 60
        # where the default LCP's time goes (fresh factorisations, the bordered updates'
        # column solves, single solves, the rest), the unit costs on the final active sets,
        # and CG on a step's N_AA preconditioned by the previous step's factor of the same
        # contacts; writes docs/benchmarks/lcp_profile.json
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

import numpy as np

import results  # noqa: E402  (benchmarks/results.py)

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
sys.path.insert(0, ROOT)
DEFAULT_RUN = os.path.join(ROOT, "out", "bench_lcp_phi0.840.h5")


def _stepper(path: str):
    """The suspension stepper (and its state) restored from the checkpoint of ``path``."""
    from petsc4py import PETSc

    from parflow.dynamics.engines import make_engine
    from parflow.io import read_run
    from parflow.run import Run
    from parflow.scene import load_scene

    with read_run(path) as f:
        scene = load_scene(f.attrs["scene"])
    run = Run(scene, PETSc.COMM_SELF, path, restart=True, quiet=True)
    state, ck = run.load_checkpoint()
    return make_engine(PETSc.COMM_SELF, state, scene, run.model, ck).sim, state


def record(path: str, steps: int) -> tuple[list, dict]:
    """The LCPs (S, q, warm, f) solved by ``steps`` steps from the checkpoint of ``path``."""
    import parflow.dynamics.hard_discs as su

    sim, state = _stepper(path)
    out = []
    solve = su.solve_lcp

    def recording(S, q, warm=None, **kw):
        f, info = solve(S, q, warm, **kw)
        out.append((S, q, warm, f))
        return f, info

    su.solve_lcp = recording
    try:
        g0 = sim.state.gamma
        for _ in range(steps):
            sim.step(1)
    finally:
        su.solve_lcp = solve
    meta = dict(file=os.path.relpath(path, ROOT), phi=float(sim.phi),
                N=int(state.n), gamma_from=float(g0), gamma_to=float(sim.state.gamma),
                steps=steps, sigma_end=float(sim.sigma))
    return out, meta


# the pivoting strategies compared by --strategies (keyword arguments of solve_lcp)
STRATEGIES = {
    "bpp30-lh": dict(bpp_max=30, newton_max=0),          # the solver before 2026-12-02
    "bpp30-newton": dict(bpp_max=30, newton_max=150),
    "bpp2-newton": dict(bpp_max=2, newton_max=150),      # the default since 2026-12-02
}


def measure(instances: list, max_border: int = 80, **lcp_kw) -> dict:
    import parflow.dynamics.lcp as co

    init = co.ActiveSolver.__init__

    def patched(self, *a, **kw):
        init(self, *a, **kw)
        self.max_border = max_border

    co.ActiveSolver.__init__ = patched
    try:
        wall, solves, facts, bordered, fails, dv, newton, modes = 0.0, 0, 0, 0, 0, 0.0, 0, {}
        for S, q, warm, f_ref in instances:
            t0 = time.perf_counter()
            try:
                f, info = co.solve_lcp(S, q, warm, **lcp_kw)
            except co.LCPFailure:
                fails += 1
                wall += time.perf_counter() - t0
                continue
            wall += time.perf_counter() - t0
            solves += info.iterations
            facts += info.factorizations
            bordered += info.bordered
            newton += info.newton
            modes[info.mode] = modes.get(info.mode, 0) + 1
            V, Vr = S.T @ f, S.T @ f_ref
            dv = max(dv, float(np.abs(V - Vr).max() / max(np.abs(Vr).max(), 1e-300)))
    finally:
        co.ActiveSolver.__init__ = init
    n = len(instances)
    return dict(max_border=max_border, lcps=n, wall_s=round(wall, 3),
                ms_per_lcp=round(1e3 * wall / n, 1), solves_per_lcp=round(solves / n, 1),
                factorisations_per_lcp=round(facts / n, 2),
                bordered_per_lcp=round(bordered / n, 1), newton_per_lcp=round(newton / n, 1),
                modes=modes, failures=fails, max_rel_dV=dv, **lcp_kw)


def strategies(runs: list, steps: int) -> int:
    """Each strategy on the same recorded LCPs of each run file (recorded with the default)."""
    missing = [r for r in runs if not os.path.exists(r)]
    if missing:
        print(f"bench_lcp: no such run file {missing[0]!r}", file=sys.stderr)
        return 2
    cases = []
    for run in runs:
        instances, meta = record(run, steps)
        rows = []
        for name, kw in STRATEGIES.items():
            rows.append(dict(strategy=name, **measure(instances, **kw)))
            print(meta["file"], rows[-1])
        cases.append(dict(meta, rows=rows))
    data = dict(cases=cases, measured=time.strftime("%Y-%m-%d %H:%M:%S"),
                loadavg=list(os.getloadavg()))
    print("wrote", results.write("lcp_strategies", data))
    return 0


# the factorisations compared by --factors: (name, SelfFactor kind, CHOLMOD method or None)
FACTORS = (("cholmod-auto", "cholmod", "AUTO"), ("cholmod-simplicial", "cholmod", "SIMPLICIAL"),
           ("cholmod-supernodal", "cholmod", "SUPERNODAL"), ("superlu", "superlu", None))


def factors(run: str, steps: int, repeat: int) -> int:
    """The default LCP solve on the same recorded LCPs with each factorisation of N_AA,
    the passes interleaved (a load that drifts hits each alike); wall = the median pass."""
    from petsc4py import PETSc

    if not os.path.exists(run):
        print(f"bench_lcp: no such run file {run!r}", file=sys.stderr)
        return 2
    instances, meta = record(run, steps)
    opts = PETSc.Options()
    key = "contact_mat_cholmod_factor"
    before = opts.getString(key) if opts.hasName(key) else None
    passes = {name: [] for name, _, _ in FACTORS}
    try:
        for _ in range(repeat):
            for name, kind, method in FACTORS:
                if method is not None:
                    opts.setValue(key, method)
                passes[name].append(measure(instances, factor=kind))
    finally:
        if before is None:
            opts.delValue(key)
        else:
            opts.setValue(key, before)
    rows = []
    for name, kind, method in FACTORS:
        p = passes[name]
        walls = [r["wall_s"] for r in p]
        row = dict(p[int(np.argsort(walls)[len(walls) // 2])], factor=name,
                   wall_s_passes=walls)
        rows.append(row)
        print(meta["file"], name, row)
    data = dict(meta, rows=rows, repeat=repeat, measured=time.strftime("%Y-%m-%d %H:%M:%S"),
                loadavg=list(os.getloadavg()))
    print("wrote", results.write("lcp_factors", data))
    return 0


def _timing(solve, times: list):
    """``solve`` (solve_lcp) that appends (seconds, solved) of every call to ``times``."""
    from parflow.dynamics.lcp import LCPFailure

    def timed(S, q, warm=None, **kw):
        t0 = time.perf_counter()
        try:
            out = solve(S, q, warm, **kw)
        except LCPFailure:
            times.append((time.perf_counter() - t0, False))
            raise
        times.append((time.perf_counter() - t0, True))
        return out
    return timed


def budget(run: str, steps: int) -> int:
    """The first tries' LCP budget (hard_discs.LCP_SOLVES_FIRST): the same ``steps`` steps
    from the checkpoint of ``run``, stepped once with LCP_SOLVES solves on every try (the code
    before 2026-12-05) and once with the default, one process, every LCP timed.  The
    trajectories are the same until an LCP needs more solves than the smaller budget, and
    part after that (the step is chaotic in its round-off): compare strain per hour."""
    import parflow.dynamics.hard_discs as su

    if not os.path.exists(run):
        print(f"bench_lcp: no such run file {run!r}", file=sys.stderr)
        return 2
    rows, meta = [], None
    first0 = su.LCP_SOLVES_FIRST
    for name, first in ((f"{su.LCP_SOLVES} solves on every try", su.LCP_SOLVES),
                        ("default", first0)):
        sim, state = _stepper(run)
        solve, times = su.solve_lcp, []
        su.solve_lcp, su.LCP_SOLVES_FIRST = _timing(solve, times), first
        g0, r0, t0 = sim.state.gamma, sim.infeasible_reductions, time.perf_counter()
        try:
            for _ in range(steps):
                sim.step(1)
        finally:
            su.solve_lcp, su.LCP_SOLVES_FIRST = solve, first0
        wall = time.perf_counter() - t0
        lcp_s = sum(t for t, _ in times)
        fail_s = sum(t for t, ok in times if not ok)
        strain = sim.state.gamma - g0
        rows.append(dict(variant=name, lcp_solves_first=first, lcp_solves=su.LCP_SOLVES,
                         lcps=len(times), gave_up=sum(1 for _, ok in times if not ok),
                         gave_up_s=round(fail_s, 2), lcp_s=round(lcp_s, 2), wall_s=round(wall, 2),
                         strain=strain, retries=sim.infeasible_reductions - r0,
                         strain_per_hour_lcp=3600 * strain / lcp_s,
                         strain_per_hour=3600 * strain / wall, sigma_end=float(sim.sigma)))
        print(rows[-1])
        if meta is None:
            meta = dict(file=os.path.relpath(run, ROOT), N=int(state.n), gamma_from=float(g0),
                        phi=float(sim.phi), steps=steps)
    data = dict(meta, rows=rows, measured=time.strftime("%Y-%m-%d %H:%M:%S"),
                loadavg=list(os.getloadavg()))
    print("wrote", results.write("lcp_budget", data))
    return 0


def _pcg(M, b, prec, rtol: float = 1e-13, maxit: int = 200) -> int:
    """Iterations of conjugate gradients on M x = b preconditioned by ``prec`` (x0 = prec b)
    to a relative residual ``rtol`` (maxit + 1: not reached)."""
    x = prec(b)
    r = b - M @ x
    z = prec(r)
    p, rz, nb = z.copy(), float(r @ z), float(np.linalg.norm(b))
    for it in range(maxit + 1):
        if float(np.linalg.norm(r)) <= rtol * nb:
            return it
        Ap = M @ p
        a = rz / float(p @ Ap)
        x += a * p
        r -= a * Ap
        z = prec(r)
        rz, rz0 = float(r @ z), rz
        p = z + (rz / rz0) * p
    return maxit + 1


def profile(run: str, steps: int) -> int:
    """Where the default LCP solve's time goes, on the LCPs of ``steps`` steps from the
    checkpoint of ``run`` (one process): every SelfFactor call timed by kind -- a fresh
    factorisation (analysis + numeric + its first solve), the multi-right-hand-side solves
    of the bordered updates' new columns, single solves -- and the rest (sparse products,
    Schur complements, the pivoting's own work).  Then, on the LCPs' final active sets: a
    fresh factorisation against a numeric refactorisation of the same pattern, one solve,
    the multi-right-hand-side solve per column; the contact changes from the warm set to
    the solution; and conjugate gradients on a step's warm set N_AA preconditioned by the
    previous LCP's factor of the same contacts (the previous step's values) -- how far a
    factor kept across steps would carry."""
    from petsc4py import PETSc

    import parflow.dynamics.lcp as co
    from parflow.algebra.solvers import SelfFactor

    if not os.path.exists(run):
        print(f"bench_lcp: no such run file {run!r}", file=sys.stderr)
        return 2
    instances, meta = record(run, steps)
    # 1. the split of the LCP time, two passes (the second is reported; the first warms up)
    split = None
    solve0, init0 = SelfFactor.solve, SelfFactor.__init__
    for _ in range(2):
        acc = dict(setup=0.0, factorise=0.0, columns=0.0, solve=0.0)
        cnt = dict(setup=0, factorise=0, columns=0, column_rhs=0, solve=0)

        def init(self, M, kind, _acc=acc, _cnt=cnt):
            t0 = time.perf_counter()
            init0(self, M, kind)
            _acc["setup"] += time.perf_counter() - t0
            _cnt["setup"] += 1

        def solve(self, rhs, _acc=acc, _cnt=cnt):
            kind = ("columns" if rhs.ndim == 2 else
                    "factorise" if self.kind == "cholmod" and not self.factored else "solve")
            t0 = time.perf_counter()
            out = solve0(self, rhs)
            _acc[kind] += time.perf_counter() - t0
            _cnt[kind] += 1
            if rhs.ndim == 2:
                _cnt["column_rhs"] += rhs.shape[1]
            return out

        SelfFactor.__init__, SelfFactor.solve = init, solve
        try:
            row = measure(instances)
        finally:
            SelfFactor.__init__, SelfFactor.solve = init0, solve0
        n = row["lcps"]
        split = dict(lcps=n, ms_per_lcp=row["ms_per_lcp"], solves_per_lcp=row["solves_per_lcp"],
                     factorisations_per_lcp=row["factorisations_per_lcp"],
                     ms_factorise=1e3 * acc["factorise"] / n, ms_setup=1e3 * acc["setup"] / n,
                     ms_columns=1e3 * acc["columns"] / n, ms_solve=1e3 * acc["solve"] / n,
                     columns_per_lcp=cnt["column_rhs"] / n, solves_single_per_lcp=cnt["solve"] / n,
                     column_calls_per_lcp=cnt["columns"] / n)
        split["ms_rest"] = split["ms_per_lcp"] - sum(split[k] for k in (
            "ms_factorise", "ms_setup", "ms_columns", "ms_solve"))
    print("split", split, flush=True)
    # 2. unit costs on the final active sets, and the changes per LCP
    unit = dict(fresh=[], numeric=[], solve=[], per_column={1: [], 16: [], 64: []})
    changes, sizes = [], []
    rng = np.random.default_rng(0)
    for S, q, warm, f in instances:
        A = f > 0
        if warm is not None:
            changes.append(int(np.count_nonzero(A != warm)))
    for S, q, warm, f in instances[::2]:
        N = (S @ S.T).tocsr()
        idx = np.flatnonzero(f > 0)
        M = N[idx][:, idx].tocsr()
        rhs = -q[idx]
        sizes.append(idx.size)
        t0 = time.perf_counter()
        fac = SelfFactor(M, "cholmod")
        fac.solve(rhs)
        unit["fresh"].append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        for _ in range(5):
            fac.solve(rhs)
        unit["solve"].append((time.perf_counter() - t0) / 5)
        for k in unit["per_column"]:
            B = rng.standard_normal((idx.size, k))
            t0 = time.perf_counter()
            fac.solve(B)
            unit["per_column"][k].append((time.perf_counter() - t0) / k)
        # the same pattern, new values: PETSc refactorises numerically, keeping the analysis
        it = PETSc.IntType
        fac.A.setValuesCSR(M.indptr.astype(it), M.indices.astype(it), M.data * (1 + 1e-9))
        fac.A.assemble()
        t0 = time.perf_counter()
        fac.ksp.setOperators(fac.A)
        fac.solve(rhs)
        unit["numeric"].append(time.perf_counter() - t0)
        fac.destroy()
    med = lambda v: 1e3 * float(np.median(v))          # noqa: E731
    units = dict(rows=int(np.median(sizes)), ms_fresh=med(unit["fresh"]),
                 ms_numeric=med(unit["numeric"]), ms_solve=med(unit["solve"]),
                 ms_per_column={str(k): med(v) for k, v in unit["per_column"].items()},
                 changes_median=float(np.median(changes)), changes_mean=float(np.mean(changes)))
    print("units", units, flush=True)
    # 3. the previous LCP's factor (same contacts, the last step's values) as a preconditioner
    its, lcps = [], []
    for (S0, q0, w0, f0), (S1, q1, w1, f1) in zip(instances[:-1], instances[1:]):
        A0 = f0 > 0
        if w1 is None or int(w1.sum()) != int(A0.sum()):
            continue                    # a contact of the set left the candidates
        N0, N1 = (S0 @ S0.T).tocsr(), (S1 @ S1.T).tocsr()
        M0, M1 = N0[A0][:, A0].tocsr(), N1[w1][:, w1].tocsr()
        if not (np.array_equal(M0.indptr, M1.indptr) and np.array_equal(M0.indices, M1.indices)):
            continue                    # not the same contacts in the same order
        fac = SelfFactor(M0, "cholmod")
        its.append(_pcg(M1, -q1[w1], fac.solve))
        lcps.append(float(abs(M1 - M0).max() / abs(M0).max()))
        fac.destroy()
    carry = dict(pairs=len(its), pcg_iterations_median=float(np.median(its)) if its else None,
                 pcg_iterations_max=int(max(its)) if its else None,
                 rel_change_median=float(np.median(lcps)) if lcps else None, rtol=1e-13)
    print("carry", carry, flush=True)
    data = dict(meta, split=split, units=units, carry=carry,
                measured=time.strftime("%Y-%m-%d %H:%M:%S"), loadavg=list(os.getloadavg()))
    print("wrote", results.write("lcp_profile", data))
    return 0


CREEPING_STATE = os.path.join(ROOT, "tests", "reference", "creeping_state.npz")


def _restore(path: str):
    """The suspension stepper restored from a checkpoint saved as .npz (tests/reference)."""
    import json

    import parflow.dynamics.hard_discs as su

    d = np.load(path)
    ck = {k: d[k] for k in d.files if k != "controls"}
    ck["controls"] = json.loads(str(d["controls"]))
    return su.Suspension.restore(ck)


def _step_for(sim, seconds: float) -> dict:
    """Step ``sim`` on for ``seconds`` (every LCP timed): steps, strain, step sizes, the LCPs
    that gave up and their time, retries, sigma at the end, the largest overlap; a shear jam
    ends it early (``jammed_after_s``)."""
    import parflow.dynamics.hard_discs as su

    solve, times = su.solve_lcp, []
    su.solve_lcp = _timing(solve, times)
    g0, r0, n, dgs, jam = sim.state.gamma, sim.infeasible_reductions, 0, [], None
    t0 = time.perf_counter()
    try:
        while time.perf_counter() - t0 < seconds:
            try:
                sim.step(1)
            except su.ShearJammed:
                jam = round(time.perf_counter() - t0, 1)
                break
            n += 1
            dgs.append(sim.last_dg)
    finally:
        su.solve_lcp = solve
    wall = time.perf_counter() - t0
    return dict(wall_s=round(wall, 1), steps=n, strain=sim.state.gamma - g0,
                dg_median=float(np.median(dgs)) if dgs else 0.0,
                dg_max=float(np.max(dgs)) if dgs else 0.0, lcps=len(times),
                gave_up=sum(1 for _, ok in times if not ok),
                gave_up_s=round(sum(t for t, ok in times if not ok), 1),
                retries=sim.infeasible_reductions - r0, sigma_end=float(sim.sigma),
                max_overlap=sim.max_overlap, jammed_after_s=jam)


def retry(paths: list, seconds: float, rounds: int) -> int:
    """The retry of a failed first try (hard_discs.RETRY_AT_LAST): at RETRY_FACTOR x its size
    (off, the code before 2026-12-06) against at the last accepted step's size first (on, the
    default), stepping on from each state (a .npz checkpoint as in tests/reference, or a run
    file with a checkpoint) for ``seconds``, ``rounds`` times each, off and on interleaved,
    one process.  The trajectories part at the first retry (the step is chaotic in its
    round-off): compare strain per unit time over the rounds."""
    import parflow.dynamics.hard_discs as su

    missing = [p for p in paths if not os.path.exists(p)]
    if missing:
        print(f"bench_lcp: no such state or run file {missing[0]!r}", file=sys.stderr)
        return 2
    if not seconds > 0 or rounds < 1:
        print("bench_lcp: --seconds must be positive and --rounds at least 1", file=sys.stderr)
        return 2
    default, states = su.RETRY_AT_LAST, []
    try:
        for path in paths:
            rows = []
            for k in range(rounds):
                for on in (False, True):
                    su.RETRY_AT_LAST = on
                    sim = _restore(path) if path.endswith(".npz") else _stepper(path)[0]
                    meta = dict(file=os.path.relpath(path, ROOT), N=int(sim.state.n),
                                phi=float(sim.phi), gamma_from=float(sim.state.gamma))
                    rows.append(dict(retry_at_last=on, round=k, **_step_for(sim, seconds)))
                    print(rows[-1])
            states.append(dict(meta, rows=rows))
    finally:
        su.RETRY_AT_LAST = default
    data = dict(seconds=seconds, rounds=rounds, states=states,
                measured=time.strftime("%Y-%m-%d %H:%M:%S"), loadavg=list(os.getloadavg()))
    print("wrote", results.write("lcp_retry", data))
    return 0


def closed_gaps(path: str, seconds: float) -> int:
    """Closed contacts at round-off gaps, as they are (GAP_ROUNDOFF = 0, the code before
    2026-12-05) and closed exactly (the default): the LCP of the state at a range of steps,
    then the stepping from the state for ``seconds`` each, one process, every LCP timed."""
    import parflow.dynamics.hard_discs as su
    from parflow.dynamics.lcp import LCPFailure
    from parflow.geometry import find_candidates

    if not os.path.exists(path):
        print(f"bench_lcp: no such state file {path!r}", file=sys.stderr)
        return 2
    if not seconds > 0:
        print("bench_lcp: --seconds must be positive", file=sys.stderr)
        return 2
    variants = (("as they are", 0.0), ("closed exactly", su.GAP_ROUNDOFF))
    default = su.GAP_ROUNDOFF
    lcps, stepping = [], []
    try:
        for name, k in variants:
            su.GAP_ROUNDOFF = k
            sim = _restore(path)
            st = sim.state
            start = dict(N=int(st.n), phi=float(sim.phi), gamma_from=float(st.gamma))
            c = find_candidates(st.s, st.radii, st.h, st.E, sim.skin)
            for dg in (1e-10, 1e-9, 1e-8, 1e-7, 1e-6):
                t0 = time.perf_counter()
                try:
                    _, _, f, _, info, _ = sim.forces(c, dg)
                    row = dict(solved=True, solves=info.iterations, singular=info.singular,
                               min_w=info.min_w)
                except LCPFailure as exc:
                    row = dict(solved=False, why=str(exc))
                lcps.append(dict(row, gaps=name, dg=dg, ms=1e3 * (time.perf_counter() - t0)))
                print(lcps[-1])
            stepping.append(dict(gaps=name, gap_roundoff=k, **_step_for(sim, seconds)))
            print(stepping[-1])
    finally:
        su.GAP_ROUNDOFF = default
    data = dict(file=os.path.relpath(path, ROOT), **start, seconds=seconds, lcps=lcps,
                stepping=stepping,
                measured=time.strftime("%Y-%m-%d %H:%M:%S"), loadavg=list(os.getloadavg()))
    print("wrote", results.write("lcp_closed_gaps", data))
    return 0


def _make_default_run() -> None:
    """DEFAULT_RUN: 300 steps of runs/fig6_suspension_phi0.840.toml from rest."""
    subprocess.run([sys.executable, "-m", "parflow.shear",
                    os.path.join(ROOT, "runs", "fig6_suspension_phi0.840.toml"),
                    "--output", DEFAULT_RUN, "--max-steps", "300", "--no-plots", "--quiet"],
                   cwd=ROOT, check=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run", nargs="?", default=DEFAULT_RUN,
                    help="a suspension run file with a checkpoint (default: %(default)s, made "
                         "from runs/fig6_suspension_phi0.840.toml by 300 steps if missing)")
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--borders", default="0,20,80,200",
                    help="max_border values to compare (0: a fresh factorisation every solve)")
    ap.add_argument("--strategies", nargs="+", metavar="RUN",
                    help="compare the pivoting strategies (STRATEGIES: block pivoting, projected "
                         "Newton, Lawson-Hanson) on the LCPs of --steps steps from each of these "
                         "run files instead; writes docs/benchmarks/lcp_strategies.json")
    ap.add_argument("--factors", metavar="RUN",
                    help="compare the factorisations of N_AA (FACTORS) on the LCPs of --steps "
                         "steps from RUN; writes docs/benchmarks/lcp_factors.json")
    ap.add_argument("--repeat", type=int, default=3, help="passes of each factorisation (--factors)")
    ap.add_argument("--budget", metavar="RUN",
                    help="the first tries' LCP budget: --steps steps from RUN's checkpoint with "
                         "600 solves on every try and with the default; writes "
                         "docs/benchmarks/lcp_budget.json")
    ap.add_argument("--closed-gaps", nargs="?", const=CREEPING_STATE, metavar="STATE",
                    help="closed contacts at round-off gaps as they are against closed exactly, "
                         "on STATE (default: %(const)s); writes "
                         "docs/benchmarks/lcp_closed_gaps.json")
    ap.add_argument("--retry", nargs="*", metavar="STATE",
                    help="the retry of a failed first try at the last step's size against at "
                         "RETRY_FACTOR x its size, stepping on from each STATE (.npz or run "
                         "file; default: the creeping state and the phi = 0.840 run file); "
                         "writes docs/benchmarks/lcp_retry.json")
    ap.add_argument("--profile", metavar="RUN",
                    help="where the LCP time goes on --steps steps from RUN (factorisations, "
                         "bordered columns, solves, the rest), the unit costs, and the "
                         "previous step's factor as a preconditioner; writes "
                         "docs/benchmarks/lcp_profile.json")
    ap.add_argument("--rounds", type=int, default=2, help="rounds of each variant (--retry)")
    ap.add_argument("--seconds", type=float, default=120.0,
                    help="stepping time of each variant (--closed-gaps, --retry)")
    a = ap.parse_args(argv)
    if a.closed_gaps:
        return closed_gaps(a.closed_gaps, a.seconds)
    if a.retry is not None:
        if not a.retry and not os.path.exists(DEFAULT_RUN):
            _make_default_run()
        return retry(a.retry or [CREEPING_STATE, DEFAULT_RUN], a.seconds, a.rounds)
    if a.steps < 1:
        print("bench_lcp: --steps must be a positive integer", file=sys.stderr)
        return 2
    if a.budget:
        return budget(a.budget, a.steps)
    if a.profile:
        return profile(a.profile, a.steps)
    if a.factors:
        return factors(a.factors, a.steps, a.repeat)
    if a.strategies:
        return strategies(a.strategies, a.steps)
    if not os.path.exists(a.run):
        if a.run != DEFAULT_RUN:
            print(f"bench_lcp: no such run file {a.run!r}", file=sys.stderr)
            return 2
        _make_default_run()
    instances, meta = record(a.run, a.steps)
    rows = [measure(instances, int(b)) for b in a.borders.split(",")]
    for r in rows:
        print(r)
    data = dict(meta, rows=rows, measured=time.strftime("%Y-%m-%d %H:%M:%S"),
                loadavg=list(os.getloadavg()))
    print("wrote", results.write("lcp", data))
    return 0


if __name__ == "__main__":
    sys.exit(main())
