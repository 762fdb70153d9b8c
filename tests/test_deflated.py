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

from parflow.algebra import operators
from parflow.algebra.deflated import DeflatedSolver
from parflow.algebra.operators import extended_precision_available
from parflow.algebra.solvers import SolveError
from parflow.dynamics import bonded
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
def jam_run(tmp_path_factory):
    """A 128-node network sheared (direct solve) to sigma >= 1e6: (run file, scene)."""
    comm = PETSc.COMM_WORLD.tompi4py()
    folder = comm.bcast(str(tmp_path_factory.mktemp("deflated")) if comm.rank == 0 else None)
    path = folder + "/jam.h5"
    return path, _run(path, 1e6, snap=1)


@pytest.fixture(scope="module")
def jammed(jam_run):
    """The state at the end of ``jam_run`` (sigma >= 1e6)."""
    from parflow.models import get_model      # noqa: PLC0415  (only for this fixture)
    path, scene = jam_run
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
    the exact solution, and the sigma identity to 1e-9; the direct solve (with its correction
    in extended precision) to 1e-12; they agree to
    the direct solve's own error."""
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
        # the direct solve corrected in extended precision (bonded.IDENTITY_RTOL)
        assert err_direct <= 1e-12, err_direct
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


# --- the direct solve near jamming: its correction in extended precision ----------------

# the dense references (the residual, exact_tau) are computed in long double
needs_long_double = pytest.mark.skipif(not extended_precision_available(),
                                       reason="numpy's long double is double on this platform")


@needs_long_double
def test_extended_residual_against_a_dense_one(jammed):
    """RigidityOperators.residual_extended against -b - S S^T tau with a dense long-double S,
    at the direct solve's tau: the residual is round-off there (~1e-16 ||N|| ||tau||), and the
    two agree to 1e-3 of it -- in double it would be noise of its own size."""
    st = jammed
    sysm = _system(st, "direct")
    try:
        F = sysm.evaluate(st.s, st.gamma)
        i, j, nc = st.bonds.i, st.bonds.j, len(st.bonds)
        S = np.zeros((nc, st.d * st.n), dtype=np.longdouble)
        rows = np.arange(nc)
        for c in range(st.d):
            S[rows, st.d * i + c] -= F.n[:, c]
            S[rows, st.d * j + c] += F.n[:, c]
        dense = (-np.asarray(F.b, np.longdouble) - S @ (S.T @ np.asarray(F.tau, np.longdouble)))
        r = sysm.ops.residual_extended(F.tau, F.b, F.n)
        scale = np.linalg.norm(F.tau) * sysm.ops.norm_bound
        assert np.linalg.norm(r) <= 1e-14 * scale            # a solved system: round-off
        assert np.linalg.norm(r - dense.astype(float)) <= 1e-3 * np.linalg.norm(r)
        r_double = -F.b - sysm.ops.matvec_at(F.n)(F.tau)
        assert np.linalg.norm(r_double - dense.astype(float)) > 1e-2 * np.linalg.norm(r)
    finally:
        sysm.destroy()


@needs_long_double
def test_direct_solve_corrected_to_the_exact_forces(jammed, monkeypatch):
    """At sigma >= 1e6 the factor alone leaves tau wrong by ~1e-9 along the soft mode (the
    sigma identity shows it); the correction from the extended residual brings tau to 1e-12
    of the exact solution and the identity below IDENTITY_RTOL -- on the loaded factor, and on
    a nearby configuration's factor (the reused-factor PCG of a step's last force)."""
    st = jammed
    sysm = _system(st, "direct")
    try:
        monkeypatch.setattr(bonded, "IDENTITY_RTOL", np.inf)     # the factor alone
        F0 = sysm.evaluate(st.s, st.gamma)
        monkeypatch.undo()
        ref = exact_tau(st, F0.n, F0.b)
        err0 = np.linalg.norm(F0.tau - ref) / np.linalg.norm(ref)
        assert F0.sigma_mismatch > 10 * bonded.IDENTITY_RTOL and err0 > 1e-11   # what is fixed
        F = sysm.evaluate(st.s, st.gamma)
        assert sysm.n_identity_refined >= 1
        assert F.sigma_mismatch <= bonded.IDENTITY_RTOL
        assert np.linalg.norm(F.tau - ref) <= 1e-12 * np.linalg.norm(ref)
        assert abs(F.sigma - F0.sigma) <= 10 * err0 * F0.sigma

        # the factor of a configuration a strain 1e-5 / sigma away, by PCG (one reused
        # solve; at 1e-3 / sigma this small network's PCG misses REUSE_BERR and factorises)
        dg = 1e-5 / F.sigma
        s2, g2 = st.s + dg * F.ds, st.gamma + dg
        G_ref = sysm.evaluate(s2, g2)                 # factorised at (s2, g2), corrected
        sysm.load(F.n)
        sysm.reuse_factor = True
        n_ref, reused = sysm.n_identity_refined, sysm.n_reused
        G = sysm.evaluate(s2, g2, reuse=True)
        assert sysm.ops.values_stale and sysm.n_reused == reused + 1
        assert sysm.n_identity_refined > n_ref
        assert G.sigma_mismatch <= bonded.IDENTITY_RTOL
        assert np.linalg.norm(G.tau - G_ref.tau) <= 1e-12 * np.linalg.norm(G_ref.tau)
    finally:
        sysm.destroy()


@needs_long_double
def test_double_double_where_long_double_is_double(jammed, monkeypatch):
    """Where long double is double (Windows, Apple silicon) the residual is formed in
    double-double arithmetic (forced here): at the direct solve's tau (a residual that is
    round-off) it agrees with the long-double one, and the corrected force meets the identity
    and the exact tau all the same."""
    st = jammed
    sysm = _system(st, "direct")
    try:
        F = sysm.evaluate(st.s, st.gamma)            # as the platform does it
        monkeypatch.setattr(operators, "extended_precision_available", lambda: False)
        r_dd = sysm.ops.residual_extended(F.tau, F.b, F.n)
        assert np.linalg.norm(r_dd) <= 1e-14 * np.linalg.norm(F.tau) * sysm.ops.norm_bound
        monkeypatch.undo()
        r_ld = sysm.ops.residual_extended(F.tau, F.b, F.n)
        # long double carries ~3 digits of a residual 1e-16 of its terms (eps 1.1e-19),
        # double-double ~16: they agree to long double's
        assert np.linalg.norm(r_dd - r_ld) <= 1e-2 * np.linalg.norm(r_ld)
        monkeypatch.setattr(operators, "extended_precision_available", lambda: False)
        G = sysm.evaluate(st.s, st.gamma)
        assert G.sigma_mismatch <= bonded.IDENTITY_RTOL
        ref = exact_tau(st, G.n, G.b)
        assert np.linalg.norm(G.tau - ref) <= 1e-12 * np.linalg.norm(ref)
        assert np.linalg.norm(G.tau - F.tau) <= 1e-13 * np.linalg.norm(F.tau)
    finally:
        sysm.destroy()


def test_direct_run_keeps_the_identity(jam_run):
    """The whole run to sigma >= 1e6 with the direct solve: identity <= IDENTITY_RTOL at every
    step, the correction counted in the run file."""
    path, _ = jam_run
    with h5py.File(path, "r") as f:
        ts = f["timeseries"]
        assert np.max(ts["sigma"][()]) >= 1e6
        assert np.max(ts["sigma_mismatch"][()]) <= bonded.IDENTITY_RTOL
        assert int(f.attrs["n_identity_refined"]) > 0


def test_restart_with_corrections_equals_uninterrupted(jam_run, mpi_tmp_path, comm):
    """Stopped a few steps before sigma = 1e6 (where every force is corrected) and restarted
    from the checkpoint (its tau is the corrected one): the same run, bit for bit."""
    full, _ = jam_run
    part = str(mpi_tmp_path / "part.h5")
    with h5py.File(full, "r") as f:
        n = len(f["timeseries/gamma"]) - 1
        assert int(f.attrs["n_identity_refined"]) > 0
        assert f["timeseries/sigma"][n - 5] > 1e5     # where the factor alone is off by ~1e-11+
    scene = load_scene(SCENE.format(sigma=1e6, preset="direct", path=part, snap=1, omega=0,
                                    strain=10.0))
    setup_logging(PETSc.COMM_WORLD, quiet=True)
    assert Run(scene, PETSc.COMM_WORLD, part, quiet=True, max_steps=n - 5).execute() == "budget"
    comm.Barrier()
    assert Run(scene, PETSc.COMM_WORLD, part, quiet=True, restart=True,
               max_steps=10**6).execute() == "complete"
    comm.Barrier()
    with h5py.File(full, "r") as a, h5py.File(part, "r") as b:
        for q in ("gamma", "sigma", "sigma_tb", "sigma_mismatch", "dgamma"):
            np.testing.assert_array_equal(a["timeseries"][q][:], b["timeseries"][q][:])
        np.testing.assert_array_equal(a["checkpoint/tau"][:], b["checkpoint/tau"][:])
    comm.Barrier()
