"""The deflated force solve (parflow.algebra.deflated, [solver] preset = "deflated") against
the direct CHOLMOD solve near jamming: same forces and V_na, the sigma identity; without
deflation, with the same iteration budget, CG must fail with a SolveError naming the
non-convergence; 1 rank = 2 ranks to solver tolerance; a short run with the preset keeps the
rod lengths and the stress identity.

Under ``mpirun -n 2`` the deflated solves run on the row-distributed N (COMM_WORLD) and are
compared with the same solve on one rank (COMM_SELF) and with the direct solve."""
import h5py
import numpy as np
import pytest
from petsc4py import PETSc

from parflow.algebra.deflated import DeflatedSolver
from parflow.algebra.solvers import SolveError
from parflow.dynamics.bonded import BondedSystem
from parflow.run import Run, setup_logging
from parflow.scene import load_scene

SCENE = """
seed = 7
[model]
name = "network"
N = 128
z = 3.8
[[protocol.leg]]
direction = "forward"
sigma_above = {sigma}
strain = {strain}
[observables]
snapshot_every = {snap}
omega_min_every = {omega}
[solver]
preset = "{preset}"
[output]
path = "{path}"
"""


def _run(path, sigma, preset="direct", snap=0, omega=0, strain=10.0):
    scene = load_scene(SCENE.format(sigma=sigma, preset=preset, path=path, snap=snap, omega=omega,
                                    strain=strain))
    setup_logging(PETSc.COMM_WORLD, quiet=True)
    assert Run(scene, PETSc.COMM_WORLD, path, quiet=True).execute() == "complete"
    PETSc.COMM_WORLD.tompi4py().Barrier()
    return scene


@pytest.fixture(scope="module")
def jammed(tmp_path_factory):
    """A 128-node network sheared (direct solve) to sigma >= 1e6: its state at the end."""
    from parflow.models import get_model      # noqa: PLC0415  (only for this fixture)
    comm = PETSc.COMM_WORLD.tompi4py()
    folder = comm.bcast(str(tmp_path_factory.mktemp("deflated")) if comm.rank == 0 else None)
    path = folder + "/jam.h5"
    scene = _run(path, 1e6, snap=1)
    with h5py.File(path, "r") as f:
        last = sorted(f["snapshots"])[-1]
        s, gamma = f["snapshots"][last]["s"][()], float(f["snapshots"][last].attrs["gamma"])
        sigma = float(f["timeseries"]["sigma"][-1])
    assert sigma >= 1e6
    state = get_model("network").build(scene["model"], 7)
    state.s, state.gamma = s, gamma
    return state


def _system(state, preset, comm=None):
    return BondedSystem(comm or PETSc.COMM_WORLD, state, preset, "auto")


def exact_tau(state, n, b):
    """N tau = -b for N = S S^T built from the unit vectors n in extended precision (numpy's
    longdouble), by iterative refinement of the double LAPACK solve: the exact solution for
    these n to ~1e-15 (the direct solve factorises N rounded to double, whose entries carry
    eps each: near jamming that moves tau by ~eps ||N|| / lambda_1 ~ 1e-9)."""
    i, j, nc = state.bonds.i, state.bonds.j, len(state.bonds)
    S = np.zeros((nc, state.d * state.n), dtype=np.longdouble)
    rows = np.arange(nc)
    for c in range(state.d):
        S[rows, state.d * i + c] -= n[:, c]
        S[rows, state.d * j + c] += n[:, c]
    NL = S @ S.T
    N = NL.astype(float)
    bL = -np.asarray(b, dtype=np.longdouble)
    x = np.linalg.solve(N, -b)
    for _ in range(10):
        x = x + np.linalg.solve(N, (bL - NL @ x.astype(np.longdouble)).astype(float))
    return x


def test_deflated_against_direct_near_jamming(jammed):
    """At sigma >= 1e6 (lambda_1 ~ 2e-8, cond ~ 3e8) the deflated solve gives tau to 1e-10 of
    the exact solution, and the sigma identity to 1e-9; it agrees with the direct solve to
    the direct solve's own error (~1e-9 here: the rounding of N's entries)."""
    st = jammed
    direct, defl = _system(st, "direct"), _system(st, "deflated")
    try:
        Fd = direct.evaluate(st.s, st.gamma)
        F = defl.evaluate(st.s, st.gamma)
        assert Fd.sigma >= 1e6
        lam = defl.tau_solver.ritz
        assert lam[0] < 1e-5 * lam[1]          # the isolated soft mode that stalls plain CG
        assert F.info.backward_error <= 1e-15
        ref = exact_tau(st, F.n, F.b)
        err = np.linalg.norm(F.tau - ref) / np.linalg.norm(ref)
        err_direct = np.linalg.norm(Fd.tau - ref) / np.linalg.norm(ref)
        assert err <= 1e-10, err
        assert err_direct <= 1e-8, err_direct
        d_tau = np.linalg.norm(F.tau - Fd.tau) / np.linalg.norm(Fd.tau)
        d_V = np.linalg.norm(F.V_na - Fd.V_na) / np.linalg.norm(Fd.V_na)
        assert min(d_tau, d_V) <= err + err_direct + 1e-12, (d_tau, d_V, err, err_direct)
        assert F.sigma_mismatch <= 1e-9
        assert abs(F.sigma - Fd.sigma) <= 1e-8 * Fd.sigma
    finally:
        direct.destroy()
        defl.destroy()


def test_without_deflation_convergence_fails_loudly(jammed):
    """Same preconditioner and iteration budget (1.5 times what the deflated CG needed): without
    the soft mode deflated, CG does not converge, and says so."""
    st = jammed
    sysm = _system(st, "direct")
    try:
        F = sysm.evaluate(st.s, st.gamma)
        ops = sysm.ops
        db = PETSc.Options()
        db.setValue("tdefl_pc_type", "jacobi")
        db.setValue("tdefl_defl_max_refine", 0)         # CG alone, no refinement after it
        on = DeflatedSolver(ops.N, "tdefl_", sysm.parallel, k=1)
        on.norm_bound = ops.norm_bound
        ops.set_local(ops.rhs, -F.b)
        x = ops.tau.duplicate()
        info = on.solve(ops.rhs, x, "with deflation")
        # (E from N W, not from S^T W: within the direct solve's own error, ~1e-9 here)
        assert np.linalg.norm(ops.gather(x) - F.tau) <= 1e-8 * np.linalg.norm(F.tau)
        # measured here: 255 iterations with the soft mode deflated; without, 464 to CG's
        # tolerance and a refinement after it (747 in all)
        budget = int(1.5 * info.refinements)
        db.setValue("tdefl_off_pc_type", "jacobi")
        db.setValue("tdefl_off_defl_max_refine", 0)
        db.setValue("tdefl_off_defl_max_it", budget)
        off = DeflatedSolver(ops.N, "tdefl_off_", sysm.parallel, deflate=False)
        off.norm_bound = ops.norm_bound
        with pytest.raises(SolveError, match=rf"did not converge: DIVERGED_MAX_IT after {budget} "
                                             r"iterations without deflation"):
            off.solve(ops.rhs, x, "without deflation")
        for o in (on, off, x):
            o.destroy()
    finally:
        sysm.destroy()


def test_one_rank_equals_two_ranks(jammed):
    """The deflated solve on COMM_WORLD (distributed under mpirun -n 2: block Jacobi/ICC) and
    on COMM_SELF (one rank, ICC) give the same forces to solver tolerance."""
    st = jammed
    dist, self_ = _system(st, "deflated"), _system(st, "deflated", PETSc.COMM_SELF)
    try:
        F2, F1 = dist.evaluate(st.s, st.gamma), self_.evaluate(st.s, st.gamma)
        assert dist.ops.comm.getSize() == PETSc.COMM_WORLD.getSize()
        assert np.linalg.norm(F2.tau - F1.tau) <= 1e-10 * np.linalg.norm(F1.tau)
        assert abs(F2.sigma - F1.sigma) <= 1e-10 * F1.sigma
    finally:
        dist.destroy()
        self_.destroy()


def test_refresh_recovers_the_soft_mode(jammed):
    """The factorless refresh (inverse iteration with the deflated CG, Rayleigh-Ritz on
    [W, N^-1 W]) turns a spoilt space back into the lowest eigenvector SLEPc finds, and
    the solve with any space gives the same forces (the coarse solve is exact)."""
    st = jammed
    sysm = _system(st, "deflated")
    try:
        F0 = sysm.evaluate(st.s, st.gamma)
        sol = sysm.tau_solver
        lam0 = sol.ritz.copy()
        rng = np.random.default_rng(3)
        nc = sysm.ops.nc
        # each vector moved by ~20 degrees, in a direction drawn the same on every rank
        W = sol.W + 0.35 * rng.standard_normal((nc, sol.k))[sol.lo:sol.hi] / np.sqrt(nc)
        sol._set_space(W)
        F1 = sysm.evaluate(st.s, st.gamma)
        # the soft mode partly in CG's part: CG alone has the accuracy of N (the direct
        # solve's, 1e-8 here); the refinement on the residual b - S (S^T x) restores it
        assert np.linalg.norm(F1.tau - F0.tau) <= 1e-11 * np.linalg.norm(F0.tau)
        for _ in range(2):
            lam = sol.refresh()
        assert abs(lam[0] - lam0[0]) <= 1e-8 * lam0[0], (lam, lam0)
        assert sol.n_refresh >= 3          # (and one by the growth rule after F1's solve)
        F2 = sysm.evaluate(st.s, st.gamma)
        assert np.linalg.norm(F2.tau - F0.tau) <= 1e-11 * np.linalg.norm(F0.tau)
    finally:
        sysm.destroy()


def test_short_run_with_the_preset(mpi_tmp_path):
    path = str(mpi_tmp_path / "defl_run.h5")
    _run(path, 1e4, preset="deflated", omega=5, strain=0.01)
    with h5py.File(path, "r") as f:
        ts = f["timeseries"]
        assert "deflated" in str(f.attrs["solver"])
        assert len(ts["sigma"]) >= 10
        assert np.max(ts["length_error"][()]) < 1e-10
        assert np.max(ts["sigma_mismatch"][()]) <= 1e-9
        assert np.max(ts["backward_error"][()]) <= 1e-14
        om = ts["omega_min"][()]
        assert np.all(np.isfinite(om[om > 0])) and np.any(om > 0)
