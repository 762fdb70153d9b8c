"""S, N, b, the force solve, V_na, the stress identity and omega_min against dense numpy,
on small random bonded systems with random image shifts, in sheared and extended cells.
Run serially and under mpirun -n 2 (rows of S and N then live on two ranks)."""
import numpy as np
import pytest
from petsc4py import PETSc

from parflow.geometry import cell_at, pair_geometry, velocity_gradient
from parflow.algebra.solvers import SingularOperator
from parflow.dynamics.bonded import BondedSystem
from parflow.state import Bonds, InputError, State

from systems import dense_operators, local_rows_dense, random_bonded_state

CASES = [("shear", 0.3), ("shear", -1.7), ("extension", 0.2), ("extension", -0.4)]


@pytest.mark.parametrize("parallel", ["replicated", "redundant"])
@pytest.mark.parametrize("flow,gamma", CASES)
def test_S_N_b_against_dense(comm, flow, gamma, parallel):
    """Rows of S and N split over the ranks ("redundant": distributed assembly) or whole on
    every rank ("replicated")."""
    st = random_bonded_state(flow=flow, gamma=gamma, seed=7)
    sysm = BondedSystem(PETSc.COMM_WORLD, st, parallel=parallel)
    if comm.size > 1:
        assert (sysm.ops.hi - sysm.ops.lo < len(st.bonds)) == (parallel == "redundant")
    F = sysm.evaluate(st.s, gamma)
    S, Nd, b, r, n = dense_operators(st)
    lo, hi, S_loc = local_rows_dense(sysm.ops.S_at(), S.shape[1])
    np.testing.assert_allclose(S_loc, S[lo:hi], atol=1e-14)
    lo, hi, N_loc = local_rows_dense(sysm.ops.N, Nd.shape[1])
    np.testing.assert_allclose(N_loc, Nd[lo:hi], atol=1e-14)
    np.testing.assert_allclose(F.b, b, atol=1e-13)
    np.testing.assert_allclose(F.r, r, atol=1e-13)
    # V_na from the numpy form of S^T equals the distributed PETSc S^T tau
    np.testing.assert_allclose(F.V_na, sysm.ops.ST(sysm.ops.tau), atol=1e-13 * np.abs(F.V_na).max())
    sysm.destroy()


@pytest.mark.parametrize("parallel", ["replicated", "redundant", "mumps"])
@pytest.mark.parametrize("flow,gamma", CASES)
def test_force_solve_and_stress_identity(comm, flow, gamma, parallel):
    st = random_bonded_state(n=40, extra=8, flow=flow, gamma=gamma, seed=11)
    sysm = BondedSystem(PETSc.COMM_WORLD, st, parallel=parallel)
    F = sysm.evaluate(st.s, gamma)
    S, Nd, b, _, _ = dense_operators(st)
    tau = np.linalg.solve(Nd, -b)
    cond = np.linalg.cond(Nd)
    np.testing.assert_allclose(F.tau, tau, rtol=0, atol=1e-13 * cond * np.abs(tau).max())
    V_na = (S.T @ tau).reshape(st.n, st.d)
    np.testing.assert_allclose(F.V_na, V_na, atol=1e-12 * cond * np.abs(V_na).max())
    # sigma = |V_na|^2 / Omega = -<tau|b> / Omega
    omega = abs(np.linalg.det(st.h0))
    assert F.sigma == pytest.approx(np.sum(V_na ** 2) / omega, rel=1e-10)
    assert F.sigma_mismatch < 1e-12
    # S V = 0 for the total velocity V = V_f + V_na (rigid rods)
    assert np.abs(S @ V_na.ravel() + b).max() < 1e-11 * np.abs(b).max()
    # pressure p = sum tau l / (d Omega)
    assert F.pressure == pytest.approx(np.sum(tau * st.bonds.l0) / (st.d * omega), rel=1e-10)
    assert F.info.reason > 0 and F.info.backward_error < 1e-14
    sysm.destroy()


def test_shear_cell_is_lees_edwards():
    h0 = np.diag([3.0, 2.0])
    E = velocity_gradient("shear", 2)
    np.testing.assert_allclose(cell_at(h0, E, 0.7), [[3.0, 0.7 * 2.0], [0.0, 2.0]])
    E = velocity_gradient("extension", 2)
    np.testing.assert_allclose(cell_at(h0, E, 0.5), np.diag([3 * np.exp(0.5), 2 * np.exp(-0.5)]))
    assert abs(np.linalg.det(cell_at(h0, E, 0.5))) == pytest.approx(6.0)


def test_affine_rate_across_the_lees_edwards_boundary():
    """A rod crossing the top boundary: b = x y / r computed from r_alpha, not from raw
    coordinates (which differ by the box velocity gamma_dot L_y)."""
    h0 = np.diag([10.0, 10.0])
    E = velocity_gradient("shear", 2)
    s = np.array([[0.5, 0.95], [0.52, 0.02]])          # j is above i through the boundary
    for gamma in (0.0, 0.3, -0.45):
        h = cell_at(h0, E, gamma)
        r, ell, n, b = pair_geometry(s, h, E, np.array([0]), np.array([1]), np.array([[0, 1]]))
        x, y = r[0]
        assert b[0] == pytest.approx(x * y / ell[0], rel=1e-14)
        assert y == pytest.approx(0.7)


@pytest.mark.parametrize("parallel", ["replicated", "redundant", "mumps"])
@pytest.mark.parametrize("flow", ["shear", "extension"])
def test_omega_min_against_eigvalsh(comm, flow, parallel):
    from parflow.algebra.spectrum import LowSpectrum, omega_from_lambda
    st = random_bonded_state(n=50, extra=10, flow=flow, gamma=0.1, seed=5)
    sysm = BondedSystem(PETSc.COMM_WORLD, st)
    sysm.evaluate(st.s, 0.1)
    _, Nd, _, _, _ = dense_operators(st)
    lam = np.linalg.eigvalsh(Nd)
    spec = LowSpectrum(sysm.ops.N, k=4, parallel=parallel)
    vals, vecs = spec.solve(vectors=True)
    np.testing.assert_allclose(vals, lam[:4], rtol=1e-8)
    assert omega_from_lambda(vals)[0] == pytest.approx(np.sqrt(lam[0]), rel=1e-8)
    for v, l in zip(vecs, vals):                 # eigenvector residual
        w = v.duplicate()
        sysm.ops.N.mult(v, w)
        w.axpy(-l, v)
        assert w.norm() < 1e-8 * v.norm()
    spec.destroy()
    sysm.destroy()


@pytest.mark.parametrize("parallel", ["replicated", "redundant", "mumps"])
def test_singular_N_is_reported(comm, parallel):
    """Three collinear-free bonds on a triangle plus a duplicate: a state of self-stress."""
    s = np.array([[0.1, 0.1], [0.4, 0.15], [0.2, 0.5]])
    i, j = np.array([0, 1, 2, 0]), np.array([1, 2, 0, 1])
    st = State(s, np.eye(2) * 5, velocity_gradient("shear", 2), 0.0,
               Bonds(i, j, np.zeros((4, 2), int), np.ones(4)))
    sysm = BondedSystem(PETSc.COMM_WORLD, st, parallel=parallel)
    with pytest.raises(SingularOperator):
        sysm.evaluate(s, 0.0)
    sysm.destroy()


def test_bad_bonds_rejected():
    with pytest.raises(InputError, match="out of range"):
        Bonds([0], [5], [[0, 0]], [1.0]).validate(3)
    with pytest.raises(InputError, match="itself"):
        Bonds([1], [1], [[0, 0]], [1.0]).validate(3)
    with pytest.raises(InputError, match="positive"):
        Bonds([0], [1], [[0, 0]], [-1.0]).validate(3)


@pytest.mark.parametrize("shared", [False, True])
def test_low_spectrum_follows_the_current_values_of_N(comm, shared):
    """One LowSpectrum object reused while N's values change (as in a run), with its own
    factor or sharing the force solver's; the force solve still works afterwards."""
    from parflow.algebra.spectrum import LowSpectrum
    st = random_bonded_state(n=40, extra=8, flow="shear", gamma=0.0, seed=9)
    sysm = BondedSystem(PETSc.COMM_WORLD, st)
    spec = LowSpectrum(sysm.ops.N, k=2, ksp=sysm.tau_solver.ksp if shared else None)
    for gamma in (0.0, 0.5, 1.0):
        st.gamma = gamma
        F = sysm.evaluate(st.s, gamma)
        _, Nd, b, _, _ = dense_operators(st)
        vals, _ = spec.solve()
        np.testing.assert_allclose(vals, np.linalg.eigvalsh(Nd)[:2], rtol=1e-8)
        np.testing.assert_allclose(F.tau, np.linalg.solve(Nd, -b), rtol=1e-9, atol=1e-12)
        F2 = sysm.evaluate(st.s, gamma)
        np.testing.assert_allclose(F2.tau, F.tau, rtol=1e-12, atol=1e-14)
    spec.destroy()
    sysm.destroy()
