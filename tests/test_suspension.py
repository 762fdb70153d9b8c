"""Hard-disc suspension (dynamics.hard_discs, dynamics.lcp, models.suspension): initial states, Lees-Edwards neighbour search,
the contact LCP against an independent NNLS, no overlap, sigma identity, bad input, MPI."""
import os

import numpy as np
import pytest
from scipy.optimize import nnls

from parflow import geometry
from parflow.geometry import rigidity_csr
from parflow.post import suspension as su
from parflow.dynamics import hard_discs as hd
from parflow.dynamics import jamming
from parflow.dynamics import lcp as co
from parflow.models import suspension as msu
from parflow.observables.contacts import coordination
from parflow.state import InputError


@pytest.fixture(scope="module")
def dense():
    return msu.make_suspension(64, 0.82, seed=3)


def brute_pairs(state, skin):
    """All pairs with gap < skin, by trying every image shift in [-3, 3]^2."""
    s, h, R = state.s, state.h, state.radii
    out = {}
    for a in range(-3, 4):
        for bb in range(-3, 4):
            ds = s[None, :, :] - s[:, None, :] + np.array([a, bb])
            r = ds @ h.T
            dist = np.sqrt((r ** 2).sum(-1))
            gap = dist - R[:, None] - R[None, :]
            ii, jj = np.nonzero((gap < skin) & (np.arange(len(s))[:, None] < np.arange(len(s))[None, :]))
            for i, j in zip(ii, jj):
                out[(i, j)] = gap[i, j]
    return out


def test_initial_state(dense):
    assert dense.n == 64
    assert abs(dense.meta["phi"] - 0.82) < 1e-12
    assert hd.min_gap(dense) > 0
    R = np.unique(dense.radii)
    assert np.allclose(R, [0.5, 0.7]) and np.sum(dense.radii == 0.5) == 32


@pytest.mark.parametrize("gamma", [0.0, 0.37, 0.5, 0.83, 5.61, -2.4])
def test_candidates_match_brute_force(dense, gamma):
    st = dense.copy()
    st.gamma = gamma
    c = geometry.find_candidates(st.s, st.radii, st.h, st.E, 0.3)
    ref = brute_pairs(st, 0.3)
    assert len(c) == len(ref)
    for i, j, g in zip(c.i, c.j, c.gap):
        assert abs(ref[(i, j)] - g) < 1e-12
    # r from the returned shifts in the state's frame
    r = (st.s[c.j] + c.shift - st.s[c.i]) @ st.h.T
    assert np.allclose(r, c.r, atol=1e-12)
    assert np.allclose(c.b, c.n[:, 0] * c.r[:, 1])


@pytest.mark.parametrize("gamma", [0.3, 0.7, 2.3, -1.6])
def test_pair_across_lees_edwards_boundary(gamma):
    L = 10.0
    X0 = np.array([5.0, 9.5])
    r = 1.05 * np.array([0.6, 0.8])
    X1 = X0 + r - np.array([gamma * L, L])          # its image across the top is at X0 + r
    st = msu.from_configuration(np.array([X0, X1]), [0.5, 0.5], [L, L], gamma=gamma)
    c = geometry.find_candidates(st.s, st.radii, st.h, st.E, 0.1)
    assert len(c) == 1
    assert abs(c.gap[0] - 0.05) < 1e-12
    assert np.allclose(c.r[0], r, atol=1e-12)
    assert abs(c.b[0] - 0.6 * r[1]) < 1e-12          # b = n_x r_y, from r, not raw coordinates


def check_lcp(S, q, f, tol=1e-9):
    w = S @ (S.T @ f) + q
    assert np.all(f >= 0)
    assert w.min() >= -tol * max(1, np.abs(q).max())
    assert np.max(np.abs(f * w)) <= tol * max(1, np.abs(q).max() * max(1, f.max()))


def test_lcp_matches_nnls():
    st = msu.make_suspension(48, 0.6, seed=5)
    rng = np.random.default_rng(0)
    c = geometry.find_candidates(st.s, st.radii, st.h, st.E, 0.4)
    S = rigidity_csr(c.n, c.i, c.j, st.n)
    assert np.linalg.matrix_rank(S.toarray()) == len(c)    # q is in range(S)
    for dg in (1e-1, 1e-2, 1e-3):
        q = c.b + c.gap / dg
        f, info = co.solve_lcp(S, q)
        check_lcp(S, q, f)
        v = np.linalg.lstsq(S.toarray(), q, rcond=None)[0]      # S v = q
        f_ref, _ = nnls(S.T.toarray(), -v)                      # min |S^T f + v|, f >= 0
        assert np.allclose(f, f_ref, atol=1e-9 * max(1, f_ref.max()))
        # a random warm start reaches the same solution
        f2, _ = co.solve_lcp(S, q, warm=rng.random(len(c)) < 0.5)
        assert np.allclose(f2, f, atol=1e-9 * max(1, f.max()))


def test_lcp_dense_complementarity(dense):
    c = geometry.find_candidates(dense.s, dense.radii, dense.h, dense.E, 0.3)
    S = rigidity_csr(c.n, c.i, c.j, dense.n)
    assert len(c) > 2 * dense.n                        # N_C is singular
    q = c.b + c.gap / 1e-3
    f, info = co.solve_lcp(S, q)
    check_lcp(S, q, f)
    assert info.min_w >= -1e-9


@pytest.mark.parametrize("dg", [1e-2, 1e-3])
def test_pivoting_phases_agree(dense, dg):
    """Block pivoting, projected Newton and Lawson-Hanson (each made to finish the solve
    from random warm sets) give the same V = S^T f (f need not be unique: N_C is
    singular) and a complementary solution."""
    c = geometry.find_candidates(dense.s, dense.radii, dense.h, dense.E, 0.3)
    S = rigidity_csr(c.n, c.i, c.j, dense.n)
    q = c.b + c.gap / dg
    f0, _ = co.solve_lcp(S, q, bpp_max=30, newton_max=0)
    V0 = S.T @ f0
    rng = np.random.default_rng(7)
    modes = set()
    for k in range(6):
        warm = rng.random(len(c)) < 0.5
        for kw in (dict(bpp_max=1, newton_max=150),      # projected Newton after one solve
                   dict(bpp_max=1, newton_max=0),        # Lawson-Hanson after one solve
                   {}):                                  # the default
            f, info = co.solve_lcp(S, q, warm=warm, **kw)
            modes.add(info.mode)
            check_lcp(S, q, f)
            assert np.abs(S.T @ f - V0).max() <= 1e-9 * np.abs(V0).max()
            if kw.get("newton_max") == 0:
                assert info.newton == 0 and info.mode != "newton"
    assert "newton" in modes                  # the projected-Newton phase did the work


def test_newton_phase_on_singular_sets():
    """Duplicated contacts (N_AA exactly singular) from a random warm set: the projected
    Newton phase meets shifted solves and still ends in a valid f."""
    st = msu.make_suspension(32, 0.7, seed=2)
    c = geometry.find_candidates(st.s, st.radii, st.h, st.E, 0.05)
    S1 = rigidity_csr(c.n, c.i, c.j, st.n).toarray()
    import scipy.sparse as sp
    S = sp.csr_matrix(np.vstack([S1, S1[:3]]))
    rng = np.random.default_rng(1)
    q = -np.abs(S @ rng.standard_normal(S.shape[1])) - 0.1
    for k in range(4):
        f, info = co.solve_lcp(S, q, warm=rng.random(S.shape[0]) < 0.5, bpp_max=1)
        check_lcp(S, q, f, tol=1e-7)


def test_near_singular_active_set_refined():
    """A recorded LCP (tests/reference/near_singular_lcp.npz: N = 1024, phi = 0.84, sigma =
    3e6, 2 796 candidates) whose active N_AA is near-singular with forces ~1e10: the shifted
    solve's error (1e-12 ||N_AA|| f ~ 0.05 on w) must be refined away against N_AA, to the
    step's acceptance (|min w| within 64 x the round-off floor, overlap dg |w| <= 1e-12).
    With 4 refinement steps, each required to halve the residual, min w stayed at -0.05: a
    solver failure at every step size on an LCP the LP shows feasible."""
    import scipy.sparse as sp
    d = np.load(os.path.join(os.path.dirname(__file__), "reference", "near_singular_lcp.npz"))
    S = sp.csr_matrix((d["data"], d["indices"], d["indptr"]), shape=tuple(d["shape"]))
    dg = 5.52e-9
    q = d["b"] + d["gap"] / dg
    f, info = co.solve_lcp(S, q, d["warm"])
    assert info.singular >= 1 and f.max() > 1e9
    w_tol = max(1e-8 * max(1.0, np.abs(d["b"]).max()), co.FLOOR_FACTOR * info.floor)
    assert -info.min_w <= w_tol and dg * max(0.0, -info.min_w) <= 1e-12
    assert info.comp <= w_tol * f.max()


def test_uphill_solve_along_a_null_vector_is_mirrored():
    """Contact 3 = contacts 1 + 2: the self-stress u = (1, 1, -1).  At f = (1, 1, 0), w =
    (0, 0, -0.1): adding contact 3 makes the set singular, and a solve that leaves a
    multiple of u can point uphill (z - f = t u, w . u > 0) or downhill (-t u).  Uphill,
    with a negative force in the mirror, it is mirrored (2 f - z: contact 3 loaded, phi
    lower); downhill, not along a null vector, or with a mirror all >= 0 (that would be a
    compressed self-stress: for the certificate), z is kept."""
    import scipy.sparse as sp
    S = sp.csr_matrix(np.array([[1.0, 0, -1, 0], [0, 1.0, 0, -1], [1.0, 1, -1, -1]]))
    N = (S @ S.T).tocsr()
    u = np.array([1.0, 1.0, -1.0])
    assert np.allclose(S.T @ u, 0.0)
    f = np.array([1.0, 1.0, 0.0])
    q = -(N @ f) - np.array([0.0, 0.0, 0.1])
    w = N @ f + q
    A = np.ones(3, bool)
    norm = float(abs(N).sum(axis=1).max())
    info = co.LCPInfo()
    z = co._mirrored(N, w, f, f + 10 * u, norm, A, info)
    np.testing.assert_allclose(z, f - 10 * u)
    assert info.mirrored == 1 and w @ (z - f) < 0 and z[2] > 0
    for kept in (f - 10 * u,                        # downhill already
                 f + np.array([0.0, 0.0, -10.0]),   # uphill, but N d != 0
                 f + 0.5 * u):                      # the mirror f - u/2 >= 0
        assert co._mirrored(N, w, f, kept, norm, A, info) is kept
    assert info.mirrored == 1


def test_singular_active_set_is_handled():
    """Duplicated contacts: N_AA is exactly singular (a self-stress); no crash, a valid f."""
    st = msu.make_suspension(32, 0.7, seed=2)
    c = geometry.find_candidates(st.s, st.radii, st.h, st.E, 0.05)
    S1 = rigidity_csr(c.n, c.i, c.j, st.n).toarray()
    S = np.vstack([S1, S1[:3]])
    import scipy.sparse as sp
    S = sp.csr_matrix(S)
    q = -np.abs(S @ np.random.default_rng(1).standard_normal(S.shape[1])) - 0.1
    f, info = co.solve_lcp(S, q, warm=np.ones(S.shape[0], bool))
    assert info.singular >= 1
    check_lcp(S, q, f, tol=1e-7)


def test_redundant_contact_dropped_on_mixed_sign_null_vector():
    """Three contacts duplicated: N_AA has three null vectors e_a - e_a', of mixed sign and
    not loaded (q_a = q_a').  Each is dropped explicitly: one contact of each pair ends with
    zero force (the min-norm solution splits the force between the two), the other carries
    it all, V = S^T f is the same as with every pair split, and the LCP holds.  Loaded null
    vectors (q_a != q_a') and a compressed self-stress (the recorded near-jammed LCP,
    all-positive and loaded) are left to the pivoting."""
    import scipy.sparse as sp
    st = msu.make_suspension(32, 0.7, seed=2)
    c = geometry.find_candidates(st.s, st.radii, st.h, st.E, 0.05)
    S1 = rigidity_csr(c.n, c.i, c.j, st.n).toarray()
    m = S1.shape[0]
    S = sp.csr_matrix(np.vstack([S1, S1[:3]]))
    q = -np.abs(S @ np.random.default_rng(1).standard_normal(S.shape[1])) - 0.1
    f, info = co.solve_lcp(S, q, warm=np.ones(S.shape[0], bool))
    check_lcp(S, q, f, tol=1e-7)
    assert info.dropped >= 3
    pairs = np.array([(f[k], f[m + k]) for k in range(3)])
    assert np.all(pairs.min(axis=1) == 0.0) and np.all(pairs.max(axis=1) > 0.1)
    # against the same LCP without the duplicates: the force of a pair is the one contact's
    f1, _ = co.solve_lcp(sp.csr_matrix(S1), q[:m])
    np.testing.assert_allclose(pairs.sum(axis=1), f1[:3], rtol=1e-9)
    np.testing.assert_allclose(S.T @ f, S1.T @ f1, rtol=0, atol=1e-9 * np.abs(S1.T @ f1).max())
    # loaded (the duplicate's q larger by 0.05: u . q != 0): nothing to drop explicitly; the
    # pivoting opens the duplicate (f = 0, w = 0.05) and the first carries the force
    q2 = q.copy()
    q2[m:] = q[:3] + 0.05
    f, info = co.solve_lcp(S, q2, warm=np.ones(S.shape[0], bool))
    check_lcp(S, q2, f, tol=1e-7)
    assert info.singular >= 1 and info.dropped == 0
    np.testing.assert_allclose(f[m:], 0.0, atol=0)
    np.testing.assert_allclose(f[:3], f1[:3], rtol=1e-9)

    d = np.load(os.path.join(os.path.dirname(__file__), "reference", "near_singular_lcp.npz"))
    Sr = sp.csr_matrix((d["data"], d["indices"], d["indptr"]), shape=tuple(d["shape"]))
    f, info = co.solve_lcp(Sr, d["b"] + d["gap"] / 5.52e-9, d["warm"])
    assert info.singular >= 1 and info.dropped == 0


def test_first_tries_get_the_smaller_lcp_budget(dense, monkeypatch):
    """A step's first two tries solve their LCP with LCP_SOLVES_FIRST solves at most, the
    third (the step cut twice) with LCP_SOLVES.  A first try above the last accepted step
    that fails is retried at the last step's size, and every later failure cuts the step by
    RETRY_FACTOR; the step that succeeds is the one taken."""
    import copy
    sim = hd.Suspension(copy.deepcopy(dense))
    sim.step()
    calls, sizes = [], []
    real, forces = hd.solve_lcp, sim.forces

    def flaky(S, q, warm=None, **kw):
        calls.append(kw["max_solves"])
        if len(calls) <= 2:
            raise co.LCPFailure("made to fail")
        return real(S, q, warm, **kw)

    def sized(c, dg, *a, **kw):
        sizes.append(dg)
        return forces(c, dg, *a, **kw)
    monkeypatch.setattr(hd, "solve_lcp", flaky)
    monkeypatch.setattr(sim, "forces", sized)
    dg0, last = sim.next_dgamma(), sim.last_dg
    assert dg0 > last > 0                       # the first try grew above the last step
    st = sim.step()
    assert calls == [hd.LCP_SOLVES_FIRST, hd.LCP_SOLVES_FIRST, hd.LCP_SOLVES]
    assert hd.LCP_SOLVES_FIRST < hd.LCP_SOLVES
    assert sizes == [dg0, last, last * hd.RETRY_FACTOR]
    assert st.dgamma == last * hd.RETRY_FACTOR

    # a first try not above the last step is cut by RETRY_FACTOR at once
    calls.clear()
    sizes.clear()
    st = sim.step(cap=sim.last_dg)
    assert len(sizes) == 3 and sizes[1] == sizes[0] * hd.RETRY_FACTOR


def test_last_resort_budget_before_a_solver_failure(dense, monkeypatch):
    """A step whose LCPs give up at every size (and no compressed self-stress proves a jam)
    is taken again with the last-resort budget, and succeeds there like the plain step; if
    that gives up too, the run fails with LCPGaveUp (a ContactSolveError) saying so."""
    import copy
    ref = hd.Suspension(copy.deepcopy(dense))
    ref.step()
    expect = ref.step()
    sim = hd.Suspension(copy.deepcopy(dense))
    sim.step()
    real, budgets = hd.solve_lcp, []

    def gives_up(S, q, warm=None, **kw):
        budgets.append(kw.get("max_solves"))
        if kw.get("max_solves") != hd.LCP_SOLVES_LAST:
            raise co.LCPFailure("made to give up")
        assert kw["max_singular"] == hd.SINGULAR_LAST
        return real(S, q, warm, **kw)
    monkeypatch.setattr(hd, "solve_lcp", gives_up)
    got = sim.step()
    assert sim.last_resorts == 1 and not sim._last_resort
    assert budgets.count(hd.LCP_SOLVES_LAST) == 1 and len(budgets) > 3
    assert got.dgamma == expect.dgamma and got.sigma == pytest.approx(expect.sigma, rel=1e-9)
    np.testing.assert_allclose(sim.state.s, ref.state.s, rtol=0, atol=1e-12)
    assert sim.checkpoint()["last_resorts"] == 1
    assert hd.Suspension.restore(sim.checkpoint()).last_resorts == 1
    # the first row of a run (probe, also on a restart) likewise
    c, f, V, dg = sim.probe()
    assert sim.last_resorts == 2 and not sim._last_resort and f.shape == (len(c),)

    def always(S, q, warm=None, **kw):
        raise co.LCPFailure("made to give up")
    monkeypatch.setattr(hd, "solve_lcp", always)
    s0 = sim.state.s.copy()
    with pytest.raises(hd.LCPGaveUp, match="last-resort budget too") as exc:
        sim.step()
    assert isinstance(exc.value, co.ContactSolveError)
    assert sim.last_resorts == 3 and not sim._last_resort
    np.testing.assert_array_equal(sim.state.s, s0)          # the state left at the last step
    with pytest.raises(hd.LCPGaveUp, match="last-resort budget too"):   # not a traceback
        sim.probe()
    assert sim.last_resorts == 4 and not sim._last_resort

    # every try solved but rejected (w < 0 reported), no certificate: more solves would not
    # help, so no last resort -- a plain ContactSolveError
    def rejected(S, q, warm=None, **kw):
        f, info = real(S, q, warm, **kw)
        info.min_w = -1.0
        return f, info
    monkeypatch.setattr(hd, "solve_lcp", rejected)
    with pytest.raises(co.ContactSolveError, match="not proved infeasible") as exc:
        sim.step()
    assert not isinstance(exc.value, hd.LCPGaveUp) and sim.last_resorts == 4


def test_steps_no_overlap_and_sigma_identity(dense):
    st = dense.copy()
    sim = hd.Suspension(st)
    stats = sim.run(0.15)
    assert st.gamma >= 0.15 - 1e-12
    assert len(stats) > 10
    assert sim.max_overlap <= 1e-9
    assert hd.min_gap(st) >= -1e-9
    for s in stats:
        # |V_na|^2 = -<f|b> - <f|h>/dg (complementarity), to solver accuracy
        assert abs(s.sigma - (s.sigma_fb + s.gap_work)) <= 1e-8 * max(1, s.sigma)
        assert s.lcp.min_w >= -1e-9
    assert stats[-1].sigma > 0 and stats[-1].pressure > 0
    assert coordination(sim.last_c, sim.last_f, st.n, st.d)["z_all"] > 0
    assert sim.collisions > 0


def test_restart_same_trajectory(dense):
    a = hd.Suspension(dense.copy())
    a.run(0.03)
    ck = a.checkpoint()
    a.run(0.03)
    b = hd.Suspension.restore(ck)
    b.run(0.03)
    assert np.array_equal(a.state.s, b.state.s) and a.state.gamma == b.state.gamma
    assert a.sigma == b.sigma and a.steps == b.steps and a.collisions == b.collisions


def test_compression_while_shearing():
    """compress_rate: the discs swell, R = R0 sqrt(phi/phi0), phi = phi0 + rate gamma until
    compress_to, with no overlap (the swelling is in q) and sigma = sigma_fb + gap_work."""
    st = msu.make_suspension(64, 0.78, seed=3)
    r0 = st.radii.copy()
    sim = hd.Suspension(st, compress_rate=0.2, compress_to=0.80)
    phi0 = sim.phi
    assert phi0 == pytest.approx(0.78, abs=1e-12)
    phis = []
    stats = sim.run(0.06, callback=lambda s, _: phis.append(s.phi))
    np.testing.assert_allclose(phis, phi0 + 0.2 * np.array([s.gamma for s in stats]), rtol=0,
                               atol=1e-13)
    ck = sim.checkpoint()
    stats += sim.run(0.09)
    assert sim.phi == 0.80 and st.gamma == pytest.approx(0.15, abs=1e-12)
    np.testing.assert_allclose(st.radii, r0 * np.sqrt(0.80 / phi0), rtol=1e-15)
    assert np.pi * np.sum(st.radii ** 2) / st.volume == pytest.approx(0.80, abs=1e-14)
    assert sim.max_overlap <= 1e-9 and hd.min_gap(st) >= -1e-9
    for s in stats:
        assert abs(s.sigma - (s.sigma_fb + s.gap_work)) <= 1e-8 * max(1, s.sigma)
        assert s.lcp.min_w >= -1e-9
    # restart in the middle of the compression = uninterrupted, bit for bit
    b = hd.Suspension.restore(ck)
    assert b.phi == phis[-1] and np.array_equal(b.state.radii, r0 * np.sqrt(b.phi / phi0))
    b.run(0.09)
    assert np.array_equal(b.state.s, st.s) and b.phi == sim.phi and b.sigma == sim.sigma
    with pytest.raises(InputError, match="compress_to"):
        hd.Suspension(msu.make_suspension(64, 0.78, seed=3), compress_rate=0.1, compress_to=0.7)


def test_jam_while_compressing_is_certified():
    """Discs swollen fast toward phi_J jam on the way (N = 64 at phi = 0.825, seed 1): the
    certificate holds the swelling in tau.b, records phi and the shear's own share."""
    st = msu.make_suspension(64, 0.80, seed=1)
    sim = hd.Suspension(st, compress_rate=0.5, compress_to=0.842)
    with pytest.raises(hd.ShearJammed, match="while the discs swell") as exc:
        sim.run(0.2)
    rec, tau = exc.value.certificate, exc.value.tau
    assert rec["certified"] and rec["tau_b"] < 0 and rec["strain_budget"] <= hd.JAM_BUDGET
    assert 0.80 < rec["phi"] == sim.phi < 0.842
    assert np.all(tau > 0) and rec["support"] == tau.size
    assert sim.max_overlap <= 1e-9


@pytest.mark.parametrize("kw, msg", [
    (dict(phi=0.843), "jamming"), (dict(phi=0.9), "jamming"), (dict(phi=-0.1), "phi"),
    (dict(phi=0.8, ratio=0.0), "ratio"), (dict(phi=0.8, ratio=-1.4), "ratio"),
    (dict(phi=0.8, composition=(0.5, 0.6)), "sum to 1"),
    (dict(phi=0.8, composition=(1.2, -0.2)), ">= 0"),
])
def test_bad_input(kw, msg):
    with pytest.raises(InputError, match=msg):
        msu.make_suspension(64, **kw)


def test_overlapping_configuration_refused():
    with pytest.raises(InputError, match="overlapping"):
        msu.from_configuration([[1.0, 1.0], [1.5, 1.0], [5, 5]], [0.5, 0.5, 0.5], [10, 10])
    with pytest.raises(InputError, match="> 0"):
        msu.from_configuration([[1.0, 1.0], [5, 5]], [0.5, 0.0], [10, 10])
    with pytest.raises(InputError, match="jamming"):
        msu.from_configuration([[1.0, 1.0]], [0.5], [0.9, 1.0])


def _recorded(name: str) -> hd.Suspension:
    """The stepper restored from a checkpoint recorded in tests/reference (.npz)."""
    import json
    d = np.load(os.path.join(os.path.dirname(__file__), "reference", name))
    ck = {k: d[k] for k in d.files if k != "controls"}
    ck["controls"] = json.loads(str(d["controls"]))
    return hd.Suspension.restore(ck)


def test_contacts_closed_to_round_off_are_not_overlaps():
    """A state written by a run has its closed contacts at gaps of +- a few eps ||h||: such a
    configuration is accepted (its closed contacts stay contacts), a larger overlap is not."""
    st = _recorded("creeping_state.npz").state
    new = msu.from_configuration(st.s @ st.h.T, st.radii, np.diag(st.h0), st.gamma)
    c = geometry.find_candidates(new.s, new.radii, new.h, new.E, 0.0)
    tol = hd.gap_roundoff(new.h)
    assert (c.gap < 0).sum() > 1000 and c.gap.min() >= -tol
    assert new.meta["phi"] == pytest.approx(0.84094, abs=1e-5)
    # two discs at a gap of -1e-15 (within 4 eps ||h|| = 9e-15) touch; at -1e-12 they overlap
    touching = msu.from_configuration([[1.0, 1.0], [2.0 - 1e-15, 1.0]], [0.5, 0.5], [10, 10])
    assert touching.n == 2
    with pytest.raises(InputError, match="overlapping pair.*1e-12"):
        msu.from_configuration([[1.0, 1.0], [2.0 - 1e-12, 1.0]], [0.5, 0.5], [10, 10])


def test_ranks_agree(comm, dense):
    sim = hd.Suspension(dense.copy())
    stats = sim.run(0.02)
    mine = np.concatenate([sim.state.s.ravel(), [s.sigma for s in stats]])
    everyone = comm.allgather(mine)
    for other in everyone:
        assert np.array_equal(other, mine)


def test_factor_backends_agree(dense):
    c = geometry.find_candidates(dense.s, dense.radii, dense.h, dense.E, 0.3)
    S = rigidity_csr(c.n, c.i, c.j, dense.n)
    q = c.b + c.gap / 1e-3
    f1, i1 = co.solve_lcp(S, q, factor="cholmod")
    f2, i2 = co.solve_lcp(S, q, factor="superlu")
    assert np.allclose(f1, f2, atol=1e-9 * max(1, f1.max()))
    with pytest.raises(InputError, match="factor"):
        co.solve_lcp(S, q, factor="lu")


def test_jam_proved_beyond_a_small_strain_budget():
    """A recorded N = 1024, phi = 0.84 state (tests/reference/jam_budget_state.npz, sigma =
    1.3e5) where every step from 1e-12 to 1e-9 fails in the solver and the LP finds no
    compressed self-stress at the smallest step, but proves one at the largest (tau.b < 0)
    whose gaps close after 1.8e-10 strain: shear-jammed within that budget (<= JAM_BUDGET),
    not a solver failure; the record says at which step it was proved."""
    sim = _recorded("jam_budget_state.npz")
    with pytest.raises(hd.ShearJammed, match="strain budget") as e:
        sim.step(1)
    rec = e.value.certificate
    assert rec["certified"] and rec["tau_b"] < 0
    assert rec["dg"] > min(rec["dg_tried"]) and 0 < rec["strain_budget"] <= hd.JAM_BUDGET


def test_jam_to_working_precision():
    """A recorded N = 1024, phi = 0.84 state compressed in flow (tests/reference/
    near_null_jam_state.npz, sigma = 4e9): every step from 1e-12 up leaves w = -0.13 on ~1 950
    active contacts, and the LP finds no compressed self-stress (S^T tau = 0 to its tolerance):
    the active N_AA has one all-positive near-null vector (eigenvalue ~3e-14 ||N_AA||) that
    the flow compresses, whose gaps close within 3e-14 strain.  Shear-jammed to working
    precision (kind "near-null" in the record), not a solver failure."""
    sim = _recorded("near_null_jam_state.npz")
    st = sim.state
    c = geometry.find_candidates(st.s, st.radii, st.h, st.E, sim.skin)
    S = rigidity_csr(c.n, c.i, c.j, st.n)
    lp = jamming.compressed_self_stress(S, c.b, sim.gaps(c), 1e-12, 1e12)
    assert not lp.certified
    with pytest.raises(hd.ShearJammed, match="working precision") as e:
        sim.step(1)
    rec = e.value.certificate
    assert rec["kind"] == "near-null" and rec["certified"] and rec["tau_b"] < 0
    assert rec["rayleigh"] <= jamming.NEAR_NULL and rec["support"] > 1900
    assert 0 <= rec["strain_budget"] <= hd.JAM_BUDGET
    assert st.gamma == float(np.load(os.path.join(os.path.dirname(__file__), "reference",
                                                  "near_null_jam_state.npz"))["gamma"])


def test_near_self_stress_needs_a_load():
    """The near-null certificate on a touching triangular crystal (every contact closed, the
    contact network over-constrained): sheared, its self-stresses are compressed and one is
    found (tau >= 0, S^T tau = 0 to round-off); with no flow (q = 0) nothing is, though the
    self-stresses are the same."""
    from parflow.state import State
    nx, ny = 6, 6
    X = np.array([[i + 0.5 * (j % 2), j * np.sqrt(3) / 2] for j in range(ny) for i in range(nx)])
    h0 = np.diag([nx, ny * np.sqrt(3) / 2])
    st = State(X @ np.linalg.inv(h0).T, h0, np.array([[0.0, 1.0], [0.0, 0.0]]), 0.0, None,
               np.full(nx * ny, 0.5))
    c = geometry.find_candidates(st.s, st.radii, st.h, st.E, 0.1)
    S = rigidity_csr(c.n, c.i, c.j, st.n)
    gap = np.zeros(len(c))
    active = np.ones(len(c), bool)
    cert = jamming.near_self_stress(S, active, c.b, gap, 1e-6, 1e12)
    assert cert.certified and cert.kind == "near-null" and cert.tau_b < 0 and cert.tau.min() >= 0
    assert cert.rayleigh <= 1e-20 and cert.strain_budget == 0.0
    none = jamming.near_self_stress(S, active, 0.0 * c.b, gap, 1e-6, 1e12)
    assert not none.certified


def test_closed_gaps_at_round_off_are_closed():
    """A recorded N = 8192 state compressed in flow (tests/reference/creeping_state.npz: phi
    = 0.8409, sigma = 50), from which a run crept on at steps of 1e-10 - 1e-9 for hours.
    Its ~15 000 closed contacts sit at gaps within 4 eps ||h|| of zero, half of them
    negative: taken as they are, each is a violation of w >= 0 of ~eps/dg that the pivoting
    chases through singular active sets.  The step's LCP sees them as 0
    (Suspension.gaps): at dg = 1e-8 it ends in a few solves, no singular set, w >= 0 to
    round-off; with the raw gaps it meets singular sets or fails; and a step from the state
    is accepted at the size the step control tries first."""
    sim = _recorded("creeping_state.npz")
    st = sim.state
    c = geometry.find_candidates(st.s, st.radii, st.h, st.E, sim.skin)
    tol = hd.gap_roundoff(st.h)
    closed = np.abs(c.gap) <= tol
    assert closed.sum() > 15000 and (c.gap[closed] < 0).sum() > 5000
    g = sim.gaps(c)
    assert np.all(g[closed] == 0.0) and np.array_equal(g[~closed], c.gap[~closed])
    dg = 1e-8
    S, q, f, V, info, warm = sim.forces(c, dg)
    assert info.iterations <= 10 and info.singular == 0
    assert info.min_w >= -co.FLOOR_FACTOR * info.floor and dg * max(0.0, -info.min_w) <= 1e-18
    try:
        _, raw = co.solve_lcp(S, q + (c.gap - g) / dg, warm)
        assert raw.singular >= 1
    except co.LCPFailure:
        pass
    n0, dg0 = sim.infeasible_reductions, sim.next_dgamma()
    step = sim.step(1)
    assert sim.infeasible_reductions == n0 and step.dgamma == dg0
    assert sim.max_overlap <= 1e-12


def test_shear_jammed_crystal_is_diagnosed():
    """A touching triangular crystal is over-constrained: the shear compresses its 120-degree
    bonds, the LCP has no overlap-free solution at any step size -> ShearJammed, no overlap."""
    from parflow.state import State
    nx, ny = 6, 6
    X = np.array([[i + 0.5 * (j % 2), j * np.sqrt(3) / 2] for j in range(ny) for i in range(nx)])
    h0 = np.diag([nx, ny * np.sqrt(3) / 2])
    st = State(X @ np.linalg.inv(h0).T, h0, np.array([[0.0, 1.0], [0.0, 0.0]]), 0.0, None,
               np.full(nx * ny, 0.5))
    assert abs(hd.min_gap(st)) < 1e-12
    sim = hd.Suspension(st, dg_min=1e-6)
    s0 = st.s.copy()
    with pytest.raises(hd.ShearJammed, match="shear-jammed"):
        sim.step()
    assert np.array_equal(st.s, s0) and st.gamma == 0.0        # nothing half-done
    assert sim.infeasible_reductions > 0


def test_small_system_singular_sets_no_overlap():
    """N = 64 at phi = 0.82 meets states of self-stress: handled, no overlap."""
    st = msu.make_suspension(64, 0.82, seed=0)
    sim = hd.Suspension(st)
    stats = sim.run(0.4)
    assert sim.max_overlap <= 1e-9 and hd.min_gap(st) >= -1e-9
    for s in stats:
        assert s.dgamma * max(0.0, -s.lcp.min_w) <= 1e-12


def test_relaxation_fit_exact():
    g = np.cumsum(np.full(40, 1e-3))
    dg = np.full(40, 1e-3)
    C = 7.0
    sig = 1.0 / (1.0 / 50.0 + (g - dg) / C)      # evaluated at the start of each step
    nc = np.zeros(40, int)
    nc[20] = 3                                   # one collision: pairs touching step 20 skipped
    r = su.relaxation(g, dg, sig, nc)
    assert r["pairs"] == 37 and r["decreasing"] == 1.0
    assert abs(r["slope"] - 2.0) < 1e-9 and abs(r["C"] - C) < 1e-9
    assert r["step_jumps"] == 0 and len(r["points"][0]) == 37


def test_relaxation_leaves_out_step_size_jumps():
    """A step cut to a tenth changes sigma through its size (h/dgamma), not by relaxation:
    the pairs on either side of the jump are left out, the rest still give slope 2."""
    dg = np.full(40, 1e-3)
    dg[25] = 1e-4                                # a cut step: pairs (24, 25) and (25, 26)
    g = np.cumsum(dg)
    C = 7.0
    sig = 1.0 / (1.0 / 50.0 + (g - dg) / C)
    sig[25] *= 0.05                              # its sigma dips
    r = su.relaxation(g, dg, sig, np.zeros(40, int))
    assert r["pairs"] == 37 and r["step_jumps"] == 2 and r["decreasing"] == 1.0
    assert abs(r["slope"] - 2.0) < 1e-9 and abs(r["C"] - C) < 1e-9
    r_all = su.relaxation(g, dg, sig, np.zeros(40, int), max_ratio=20.0)
    assert r_all["pairs"] == 39 and r_all["decreasing"] < 1.0     # the dip counted: wrong


def test_strain_weighted_mean_and_error():
    """Steps of very different size: the mean is weighted by strain and so is the error
    (blocks of equal strain), so a stretch of tiny steps at a huge sigma (a jam's last
    steps) weighs by its strain, not by its count."""
    rng = np.random.default_rng(3)
    x = 100.0 + rng.normal(0.0, 5.0, 400)
    w = np.full(400, 1e-3)
    x2, w2 = np.concatenate([x, np.full(300, 1e9)]), np.concatenate([w, np.full(300, 1e-15)])
    m, e = su._mean_err(x2, w2)
    assert abs(m - np.average(x2, weights=w2)) < 1e-9 * m and abs(m - x.mean()) < 1e-3
    assert e < 5.0                               # unweighted blocks: ~1e8
    m1, e1 = su._mean_err(x, w)                  # equal weights: the plain block error
    blocks = np.array([b.mean() for b in np.array_split(x, 10)])
    assert abs(m1 - x.mean()) < 1e-9 and abs(e1 - blocks.std(ddof=1) / np.sqrt(10)) < 1e-9


def test_strain_window_means():
    """Means over windows of equal strain, each step weighted by its strain."""
    dg = np.array([0.1, 0.1, 0.05, 0.05, 0.2, 0.3, 0.2])
    strain = np.cumsum(dg)
    y = np.array([1.0, 3.0, 10.0, 20.0, 2.0, 4.0, 6.0])
    xc, yc = su.strain_window_means(strain, dg, y, 2)          # windows [0, 0.5], [0.5, 1]
    assert np.allclose(xc, [0.25, 0.75])
    assert np.allclose(yc, [(0.1 + 0.3 + 0.5 + 1.0 + 0.4) / 0.5, (1.2 + 1.2) / 0.5])


def test_bordered_solves_match_fresh_factorisations(dense):
    """A walk of active sets, a few contacts in and out per move: the solutions from one
    factorisation with bordered (Schur complement) updates equal dense solves; a border
    larger than max_border, or one that makes N_AA singular, gets a fresh factorisation."""
    c = geometry.find_candidates(dense.s, dense.radii, dense.h, dense.E, 0.3)
    S = rigidity_csr(c.n, c.i, c.j, dense.n)
    N = (S @ S.T).tocsr()
    Nd = N.toarray()
    q = c.b + c.gap / 1e-3
    rng = np.random.default_rng(4)
    A = rng.random(len(c)) < 0.3
    info = co.LCPInfo()
    act = co.ActiveSolver(N, q, info, max_border=12)
    moves = 0
    for size in [3] * 10 + [20] + [2] * 5:
        flip = rng.choice(len(c), size, replace=False)
        A[flip] = ~A[flip]
        x = act.solve(A)
        idx = np.flatnonzero(A)
        ref = np.linalg.solve(Nd[np.ix_(idx, idx)], -q[idx])
        assert np.all(x[~A] == 0)
        assert np.allclose(x[idx], ref, rtol=0, atol=1e-9 * np.abs(ref).max())
        moves += 1
    act.release()
    assert info.bordered >= 8                  # most moves did not factorise
    assert 2 <= info.factorizations < moves    # the first, and after the 20-contact move
    assert info.singular == 0


def test_bordered_singular_border_falls_back(dense):
    """Adding a copy of an active contact makes N_AA singular: the bordered update notices
    (singular Schur complement), the fresh factorisation is shifted and counted."""
    import scipy.sparse as sp
    c = geometry.find_candidates(dense.s, dense.radii, dense.h, dense.E, 0.3)
    S1 = rigidity_csr(c.n, c.i, c.j, dense.n)
    S = sp.vstack([S1, S1[:1]]).tocsr()
    N = (S @ S.T).tocsr()
    q = np.concatenate([c.b, c.b[:1]]) + 1.0
    A = np.zeros(S.shape[0], bool)
    A[:40] = True
    info = co.LCPInfo()
    act = co.ActiveSolver(N, q, info)
    act.solve(A)
    A[-1] = True
    x = act.solve(A)
    act.release()
    assert info.singular == 1 and info.bordered == 0 and np.all(np.isfinite(x))


def test_cholmod_breakdown_switches_to_superlu():
    """A matrix CHOLMOD cannot factor (singular: blocks of rank 1): the event is counted and
    the rest of the LCP factorises with SuperLU (a CHOLMOD factorisation that breaks down
    leaks its partial factor in PETSc 3.18)."""
    import scipy.sparse as sp
    N = sp.kron(sp.identity(100), sp.csr_matrix(np.ones((4, 4)))).tocsr()
    info = co.LCPInfo()
    act = co.ActiveSolver(N, -np.ones(400), info)
    assert act.kind == "cholmod"
    x = act.solve(np.ones(400, bool))
    assert np.all(np.isfinite(x))
    act.release()
    assert info.singular == 1 and act.kind == "superlu"
