"""Shear jamming is declared only with a proof (dynamics.jamming): a compressed self-stress
tau >= 0, S^T tau = 0, tau . q < 0 (Farkas: the contact LCP is infeasible).  A genuinely
jammed packing yields the certificate, status "jammed" and the run file's /jam record; a
mixed-sign over-constrained cluster that the flow does not load is solved, not declared
jammed; the refined singular solve against a dense one; no overlap at phi = 0.84."""
import h5py
import numpy as np
import pytest
import scipy.sparse as sp
from scipy.optimize import nnls

from parflow import geometry
from parflow.dynamics import hard_discs as hd
from parflow.dynamics import jamming as jm
from parflow.dynamics import lcp as co
from parflow.models import suspension as msu
from parflow.scene import load_scene
from systems import run_scene

VACANCIES = [9, 22, 29, 42, 52, 63]


def vacancy_crystal():
    """A touching triangular crystal of 8 x 8 discs (radius 0.5 - 5e-13: gaps 1e-12) with six
    vacancies, phi = 0.822 < phi_J: it still spans the cell and is over-constrained, and the
    shear compresses its 120-degree bonds -- it jams within a strain of ~1e-12."""
    nx, ny = 8, 8
    X = np.array([[i + 0.5 * (j % 2), j * np.sqrt(3) / 2] for j in range(ny) for i in range(nx)])
    keep = np.ones(nx * ny, bool)
    keep[VACANCIES] = False
    return X[keep], np.full(keep.sum(), 0.5 - 5e-13), np.array([nx, ny * np.sqrt(3) / 2])


def flower():
    """Seven touching discs (a centre and a hexagonal ring): 12 contacts on 11 internal
    degrees of freedom, one self-stress, of mixed sign (any self-stress of a finite cluster
    is: sum tau |r| = 0, the virial of balanced forces)."""
    ang = np.arange(6) * np.pi / 3 + 0.3
    X = np.vstack([[0, 0], np.column_stack([np.cos(ang), np.sin(ang)])]) + 5.0
    st = msu.from_configuration(X, np.full(7, 0.5 - 5e-13), [10, 10])
    c = geometry.find_candidates(st.s, st.radii, st.h, st.E, 0.05)
    return st, c, geometry.rigidity_csr(c.n, c.i, c.j, st.n), X - 5.0


def test_jammed_crystal_certificate():
    X, R, box = vacancy_crystal()
    st = msu.from_configuration(X, R, box)
    assert st.meta["phi"] < 0.843
    sim = hd.Suspension(st)
    with pytest.raises(hd.ShearJammed, match="proved by a compressed self-stress") as ei:
        for _ in range(20):
            sim.step()
    cert = ei.value.certificate
    assert cert["certified"] and cert["tau_q"] < 0 and cert["tau_b"] < 0
    assert cert["support"] >= 6 and cert["residual"] <= 1e-12
    assert cert["v_bound"] >= cert["v_admissible"]
    assert cert["dg"] >= sim.dg_min and cert["dg"] == cert["dg_tried"][-1]
    assert cert["strain_budget"] < cert["dg"]        # the step cannot close the gaps in time
    # the proof checks independently: tau >= 0 on real contacts, S^T tau = 0, tau . q < 0
    c = geometry.find_candidates(st.s, st.radii, st.h, st.E, sim.skin)
    S = geometry.rigidity_csr(c.n, c.i, c.j, st.n).toarray()
    key = {(i, j): a for a, (i, j) in enumerate(zip(c.i, c.j))}
    rows = [key[(i, j)] for i, j in zip(*ei.value.pairs)]
    tau = ei.value.tau
    assert np.all(tau > 0) and np.max(tau) == 1.0
    assert np.linalg.norm(S[rows].T @ tau) <= 1e-12
    q = c.b[rows] + c.gap[rows] / cert["dg"]
    assert tau @ q == pytest.approx(cert["tau_q"], rel=1e-9) and tau @ q < 0
    assert sim.max_overlap <= 1e-9 and hd.min_gap(st) >= -1e-9


def test_feasible_lcp_has_no_certificate(dense_state):
    """On a flowing packing the LP finds no compressed self-stress (min tau . q = 0)."""
    st = dense_state
    c = geometry.find_candidates(st.s, st.radii, st.h, st.E, 0.3)
    S = geometry.rigidity_csr(c.n, c.i, c.j, st.n)
    cert = jm.compressed_self_stress(S, c.b, c.gap, 1e-3, 1e3)
    assert not cert.certified and cert.support == 0 and cert.strain_budget == np.inf


@pytest.fixture(scope="module")
def dense_state():
    return msu.make_suspension(64, 0.82, seed=3)


def test_mixed_sign_cluster_is_not_jammed():
    """A flower pressed from outside (q = S x for a uniform contraction x, plus a little
    shear): every contact active, N_AA singular, its null vector of mixed sign and not loaded
    (u . q = 0).  The LCP has a solution (agreeing with NNLS), the LP no certificate."""
    st, c, S, X = flower()
    assert len(c) == 12 and np.linalg.matrix_rank(S.toarray()) == 11
    u = np.linalg.svd(S.toarray().T)[2][-1]
    assert u.min() < 0 < u.max()                       # mixed sign
    x = -X.ravel()
    for scale in (1.0, 1e4, 1e7):
        q = scale * (S @ x) + 1e-3 * c.b
        assert abs(u @ (S @ x)) <= 1e-12                # the self-stress is not loaded
        cert = jm.compressed_self_stress(S, q, np.zeros_like(q), 1.0, 1e3)
        assert not cert.certified
        for warm in (None, np.ones(len(c), bool)):
            f, info = co.solve_lcp(S, q, warm=warm)
            w = S @ (S.T @ f) + q
            floor = co.roundoff_floor(S @ S.T, f)
            assert np.all(f >= 0) and w.min() >= -max(1e-10, 100 * floor)
            assert np.max(np.abs(f * w)) <= 100 * floor * max(1.0, f.max())
            # V = S^T f is unique (the LCP of a PSD N): against NNLS on the range of S
            v = np.linalg.lstsq(S.toarray(), q, rcond=None)[0]
            f_ref = nnls(S.T.toarray(), -v)[0]
            np.testing.assert_allclose(S.T @ f, S.T @ f_ref, rtol=0, atol=1e-9 * scale)


def test_flower_keeps_flowing():
    """The flower alone in a dilute cell under shear: it flows (rotates and opens), no jam."""
    st, _, _, _ = flower()
    sim = hd.Suspension(st)
    stats = sim.run(0.3)
    assert st.gamma == pytest.approx(0.3) and len(stats) > 10
    assert sim.max_overlap <= 1e-9


def test_refined_singular_solve_matches_dense():
    """An exactly singular, consistent N_AA (duplicated contacts): the shifted solve refined
    against the unshifted N_AA satisfies N_AA x = rhs to round-off, as a dense minimum-norm
    solve does (the shifted solve alone is off by ~ shift |x|)."""
    st = msu.make_suspension(32, 0.7, seed=2)
    c = geometry.find_candidates(st.s, st.radii, st.h, st.E, 0.05)
    S1 = geometry.rigidity_csr(c.n, c.i, c.j, st.n)
    S = sp.vstack([S1, S1[:3]]).tocsr()
    N = (S @ S.T).tocsr()
    rng = np.random.default_rng(1)
    V = rng.standard_normal(S.shape[1])
    q = -1e6 * (S @ V)                         # consistent: q in range(N) = range(S)
    info = co.LCPInfo()
    act = co.ActiveSolver(N, q, info)
    A = np.ones(S.shape[0], bool)
    x = act.solve(A)
    act.release()
    assert info.singular == 1
    Nd = N.toarray()
    ref = np.linalg.lstsq(Nd, -q, rcond=None)[0]
    res = Nd @ x + q
    floor = co.roundoff_floor(N, x)
    assert np.abs(res).max() <= 100 * floor
    assert np.abs(Nd @ ref + q).max() <= 100 * floor
    # the velocities (unique) agree with the dense solve
    np.testing.assert_allclose(S.T @ x, S.T @ ref, rtol=0, atol=1e-9 * np.abs(S.T @ ref).max())


@pytest.mark.parametrize("seed", [0, 1])
def test_no_overlap_at_phi_084(seed):
    st = msu.make_suspension(64, 0.84, seed=seed)
    sim = hd.Suspension(st)
    try:
        sim.run(0.02, max_steps=300)
    except hd.ShearJammed as exc:              # allowed, but only with its proof
        assert exc.certificate["certified"]
    assert sim.max_overlap <= 1e-9 and hd.min_gap(st) >= -1e-9


def test_jammed_run_writes_certificate(comm, mpi_tmp_path):
    """Through the scene driver: status "jammed" and the /jam group (docs/output.md)."""
    X, R, box = vacancy_crystal()
    path = str(mpi_tmp_path / "jam.h5")
    conf = str(mpi_tmp_path / "crystal.npz")
    if comm.rank == 0:
        np.savez(conf, positions=X, radii=R, box=box)
    comm.barrier()
    phi = float(np.pi * np.sum(R ** 2) / np.prod(box))
    scene = load_scene(f"""
seed = 1
[model]
name = "suspension"
N = {len(R)}
phi = {phi!r}
configuration_file = "{conf}"
[[protocol.leg]]
direction = "forward"
strain = 0.01
[output]
path = "{path}"
""")
    assert run_scene(scene) == "jammed"
    comm.barrier()
    with h5py.File(path) as f:
        assert f.attrs["status"] == "jammed"
        assert "compressed self-stress" in f.attrs["message"]
        g = f["jam"]
        assert g.attrs["certified"] and g.attrs["tau_q"] < 0 and g.attrs["tau_b"] < 0
        assert g.attrs["support"] == g["tau"].shape[0] == g["contact_i"].shape[0]
        assert g.attrs["strain_budget"] < g.attrs["dg"]
        assert g.attrs["gamma"] == pytest.approx(f["timeseries/gamma"][-1], abs=1e-15)
        assert len(g.attrs["dg_tried"]) >= 1 and np.all(g["tau"][:] > 0)
    comm.barrier()


def test_larger_step_after_small_ones_fail():
    """A straight periodic line of discs along the diagonal, each contact overlapping by
    1e-13: a self-stress (tau = 1) that the shear decompresses (tau.b > 0) but that the
    overlaps compress at steps below -tau.h / tau.b = 2e-13 (q = b + h/dg).  Every step from
    4e-14 down to dg_min fails; the LP shows tau.b > 0, so this is not jamming: the step
    control tries larger steps and goes on."""
    from parflow.state import State
    m = 20
    L = m / np.sqrt(2)
    t = (np.arange(m) + 0.5) / m
    s = np.column_stack([t, t])
    st = State(s, np.diag([L, L]), np.array([[0.0, 1.0], [0.0, 0.0]]), 0.0, None,
               np.full(m, 0.5 + 5e-14))
    assert hd.min_gap(st) == pytest.approx(-1e-13, rel=1e-2)
    sim = hd.Suspension(st, dg_min=1e-16)
    sim.last_dg = 1e-14                       # the growth cap: the first try is 4e-14
    stats = sim.step()
    assert sim.upward_searches == 1 and sim.infeasible_reductions >= 3
    assert stats.dgamma > 2e-13
    assert hd.min_gap(st) >= -1e-13           # the overlap did not grow
    sim.run(0.01)
    assert hd.min_gap(st) >= 0                # the shear opened the line


def test_solver_failure_is_not_jamming(dense_state, monkeypatch):
    """An LCP solver that fails at every step on a flowing packing: no certificate (the LP
    finds none), larger steps tried, then a ContactSolveError (a SolveError: the driver's
    status "failed", exit 1) -- never ShearJammed."""
    from parflow.algebra.solvers import SolveError
    sim = hd.Suspension(dense_state.copy())
    sim.run(0.005)
    g0 = sim.state.gamma

    def broken(*a, **k):
        raise co.LCPFailure("contact LCP: broken on purpose")
    monkeypatch.setattr(hd, "solve_lcp", broken)
    with pytest.raises(co.ContactSolveError, match="not proved infeasible") as ei:
        sim.step()
    assert isinstance(ei.value, SolveError) and not isinstance(ei.value, hd.ShearJammed)
    assert "broken on purpose" in str(ei.value) and "certified = False" in str(ei.value)
    # the step, and once more with the last-resort budget: an upward search in each
    assert sim.upward_searches == 2 and sim.last_resorts == 1 and sim.state.gamma == g0
    assert isinstance(ei.value, hd.LCPGaveUp) and "last-resort budget too" in str(ei.value)
