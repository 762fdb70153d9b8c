"""The network model (parflow.models.network): Lees-Edwards geometry, rigid rods and the
stress identity under shear, the point response, C(r) and the spectrum of N against dense
numpy / brute force, save/load through model.network_file, bad input.

Under ``mpirun -n 2`` both ranks run every test (the PETSc objects are distributed over
COMM_WORLD, the numpy references are replicated), so the assertions hold on both."""
import itertools

import numpy as np
import pytest
from petsc4py import PETSc

from parflow import geometry
from parflow.observables import correlation as corr
from parflow.observables import response as resp
from parflow.geometry import pair_geometry
from parflow.dynamics.heun import Heun, StepControl
from parflow.models import network as nw
from parflow.models import network_build as nb
from parflow.run import Run, setup_logging
from parflow.scene import load_scene
from parflow.state import Bonds, InputError, Instant, State
from parflow.algebra.solvers import SingularOperator
from parflow.dynamics.bonded import BondedSystem
from systems import dense_operators


def _instant(system, state, F, **params):
    """An analysis instant of a network with the scene's model parameters ``params``."""
    model = {k: v[1] for k, v in nw.PARAMS.items()}
    model.update(params)
    return Instant(PETSc.COMM_WORLD, state, F, system, {"model": model})

PARAMS = dict(N=128, z=3.8, phi=0.88)


@pytest.fixture(scope="module")
def state():
    return nw.build(PARAMS, seed=7)


def sheared(st, gamma, s=None):
    out = st.copy()
    out.gamma = gamma
    if s is not None:
        out.s = s
    return out


def true_min_image(dx, h):
    """Brute-force minimum image: the shortest of the 3^d translates (by the remapped cell's
    vectors) of the reduced-rint image."""
    hr = geometry.remapped_cell(h)
    red = np.linalg.solve(hr, dx.T).T
    base = (red - np.rint(red)) @ hr.T
    best = base
    for n in itertools.product((-1, 0, 1), repeat=h.shape[0]):
        cand = base + hr @ np.array(n, float)
        pick = np.einsum("...d,...d->...", cand, cand) < np.einsum("...d,...d->...", best, best)
        best = np.where(pick[..., None], cand, best)
    return best


# --------------------------------------------------------------------------- geometry

def test_lees_edwards_rod_across_the_boundary():
    """A rod leaving the top of the box (image shift (0, 1)) after a shear gamma: the cell
    carries the affine motion, r = (gamma, 1), b = x y / r."""
    L = 10.0
    s = np.array([[0.5, 0.95], [0.5, 0.05]])
    st = State(s, np.diag([L, L]), nw.velocity_gradient("shear", 2), 0.0,
               Bonds([0], [1], [[0, 1]], [1.0]))
    for gamma in (0.0, 0.3, 0.7, 1.6):
        h = st.h if gamma == 0 else sheared(st, gamma).h
        assert np.allclose(h, [[L, gamma * L], [0, L]])
        r, ell, n, b = pair_geometry(s, h, st.E, st.bonds.i, st.bonds.j, st.bonds.shift)
        np.testing.assert_allclose(r[0], [gamma, 1.0], atol=1e-12)
        np.testing.assert_allclose(b[0], gamma / np.hypot(gamma, 1.0), atol=1e-12)
        # b is the rate of change of the length in the affine flow (finite difference)
        e = 1e-6
        rp = pair_geometry(s, h + e * st.E @ h, st.E, st.bonds.i, st.bonds.j, st.bonds.shift)[1]
        rm = pair_geometry(s, h - e * st.E @ h, st.E, st.bonds.i, st.bonds.j, st.bonds.shift)[1]
        assert (rp[0] - rm[0]) / (2 * e) == pytest.approx(b[0], rel=1e-7, abs=1e-9)
        # the minimum-image machinery (remapped cell) finds the same short vector
        mi = geometry.MinImage(h)
        assert abs(mi.hr[0, 1]) <= L / 2 + 1e-12
        v = mi.vectors(mi.reduced(s[1:]) - mi.reduced(s[:1]))
        assert np.linalg.norm(v) == pytest.approx(np.hypot(gamma, 1.0), rel=1e-12)


def test_network_bonds_follow_the_cell(state):
    """At fixed s, every rod (many cross the boundaries) is the affine image of itself;
    minimum-image lengths agree with the bond lengths past the remapping strain."""
    bd = state.bonds
    assert np.any(bd.shift != 0)
    r0 = pair_geometry(state.s, state.h, state.E, bd.i, bd.j, bd.shift)[0]
    for gamma in (0.4, 0.7):
        h = sheared(state, gamma).h
        r = pair_geometry(state.s, h, state.E, bd.i, bd.j, bd.shift)[0]
        np.testing.assert_allclose(r, r0 @ (np.eye(2) + gamma * state.E).T, atol=1e-12)
        mi = geometry.MinImage(h)
        sr = mi.reduced(state.s)
        v = mi.vectors(sr[bd.j] - sr[bd.i])
        np.testing.assert_allclose(np.linalg.norm(v, axis=1), np.linalg.norm(r, axis=1), rtol=1e-12)


def test_build_meta(state):
    m = state.meta
    assert m["model"] == "network" and m["n_nodes"] == state.n and m["n_bonds"] == len(state.bonds)
    assert abs(m["z"] - 3.8) <= 1.0 / state.n + 1e-15
    assert m["dz"] == pytest.approx(4.0 - m["z"])
    assert m["self_stresses"] == 0 and m["min_degree"] >= 3
    assert np.allclose(state.E, [[0, 1], [0, 0]])


# --------------------------------------------------------------------------- dynamics

def test_shear_keeps_rods_rigid_and_sigma_identity(state):
    sysm = BondedSystem(PETSc.COMM_WORLD, state)
    integ = Heun(sysm, StepControl())
    s, g = state.s.copy(), 0.0
    F = sysm.evaluate(s, g)
    worst, sig, steps = 0.0, [], 0
    for direction, n_steps in ((+1, 250), (-1, 60)):
        for _ in range(n_steps):
            R = integ.step(s, g, F, direction, 1e-4 if steps == 0 else R.next_dgamma)
            s, g, F = R.s, R.gamma, R.F
            steps += 1
            ell = np.linalg.norm(pair_geometry(s, F.h, state.E, state.bonds.i, state.bonds.j,
                                               state.bonds.shift)[0], axis=1)
            worst = max(worst, float(np.max(np.abs(ell - state.bonds.l0))))
            assert F.sigma_mismatch < max(1e-8, 100 * F.info.residual)
            sig.append(F.sigma)
            if direction > 0 and F.sigma > 1e5:
                break
    assert worst < 1e-10
    assert max(sig) > 1e2 * sig[0]                # it did approach jamming
    assert sig[-1] < 0.5 * max(sig)                # and relaxed after the reversal
    sysm.destroy()


def test_projection_falls_back_to_newton(state):
    """The quasi-Newton projection with a factor of N taken far from the constraint manifold
    does not contract; the Newton fallback (N refactorised where it stands) restores the rod
    lengths anyway, and with no refactorisation allowed the failure is reported."""
    sysm = BondedSystem(PETSc.COMM_WORLD, state)
    rng = np.random.default_rng(5)
    far = state.s + 0.05 * rng.standard_normal(state.s.shape)
    near = state.s + 0.002 * rng.standard_normal(state.s.shape)
    bd = state.bonds

    def lengths(s):
        return np.linalg.norm(pair_geometry(s, state.h, state.E, bd.i, bd.j, bd.shift)[0], axis=1)

    sysm.evaluate(far, 0.0)
    with pytest.raises(SingularOperator, match="did not converge"):
        sysm.project(near, 0.0, tol=1e-12, max_refactor=0)
    sysm.evaluate(far, 0.0)
    before = sysm.n_factor
    s, it, err = sysm.project(near, 0.0, tol=1e-12)
    assert sysm.n_factor > before                  # it did refactorise
    assert err <= 1e-12 and np.max(np.abs(lengths(s) - bd.l0)) <= 1e-12
    assert np.max(np.abs(s - near)) < 0.01         # a nearby point, not a distant solution
    sysm.destroy()


# --------------------------------------------------------------------------- analyses

@pytest.fixture(scope="module")
def strained(state):
    """The network at gamma = 0.3 with randomly displaced nodes (rods no longer at rest
    length, which does not matter for the linear algebra) and its dense operators."""
    rng = np.random.default_rng(3)
    st = sheared(state, 0.3, state.s + 0.002 * rng.standard_normal(state.s.shape))
    st.bonds = Bonds(st.bonds.i, st.bonds.j, st.bonds.shift,
                     np.linalg.norm(pair_geometry(st.s, st.h, st.E, st.bonds.i, st.bonds.j,
                                                  st.bonds.shift)[0], axis=1))
    S, N, b, r, n = dense_operators(st)
    return st, S, N, r, n


def test_point_response_against_dense(strained):
    st, S, N, r, n = strained
    sysm = BondedSystem(PETSc.COMM_WORLD, st)
    F = sysm.evaluate(st.s, st.gamma)
    rods = resp.pick_rods(st.s, F.h, st.bonds, 3)
    assert len(set(rods.tolist())) == 3
    dr = 0.5
    pr = resp.point_response(sysm, st.s, F.h, st.bonds, rods, dr)
    # dense reference: N f = e_beta, V = S^T f, distances by brute-force minimum image
    x = st.s @ F.h.T
    mid = x[st.bonds.i] + 0.5 * r
    rmax = geometry.min_image_radius(F.h)
    nb_ = int(rmax / dr)
    sums, cnt, sf, cf, VV = np.zeros(nb_), np.zeros(nb_), np.zeros(nb_), np.zeros(nb_), []
    for beta in rods:
        e = np.zeros(len(st.bonds))
        e[beta] = 1.0
        f = np.linalg.solve(N, e)
        V = (S.T @ f).reshape(-1, 2)
        VV.append(V.ravel() @ V.ravel())
        assert VV[-1] == pytest.approx(f[beta], rel=1e-9)        # <V|V> = f_beta
        dn = np.linalg.norm(true_min_image(x - mid[beta], F.h), axis=1)
        db = np.linalg.norm(true_min_image(mid - mid[beta], F.h), axis=1)
        for dist, w, sm, c in ((dn, np.linalg.norm(V, axis=1), sums, cnt), (db, np.abs(f), sf, cf)):
            k = (dist / dr).astype(int)
            ok = k < nb_
            np.add.at(sm, k[ok], w[ok])
            np.add.at(c, k[ok], 1)
    np.testing.assert_array_equal(pr["counts_V"], cnt)
    np.testing.assert_array_equal(pr["counts_f"], cf)
    with np.errstate(invalid="ignore"):
        np.testing.assert_allclose(pr["V_mean"], sums / cnt, rtol=1e-7, equal_nan=True)
        np.testing.assert_allclose(pr["f_mean"], sf / cf, rtol=1e-7, equal_nan=True)
    np.testing.assert_allclose(pr["VV"], VV, rtol=1e-7)
    sysm.destroy()


def test_two_exponential_fit_recovers_lengths():
    r = np.arange(0.25, 40, 0.5)
    P = 2.0 * np.exp(-r / 1.5) + 0.05 * np.exp(-r / 12.0)
    fit = resp.fit_two_exponentials(r, P * (1 + 1e-3 * np.sin(7 * r)))
    assert fit["l_c"] == pytest.approx(1.5, rel=0.02)
    assert fit["l_r"] == pytest.approx(12.0, rel=0.02)
    assert fit["l_c_err"] < 0.05 and fit["l_r_err"] < 0.5


def test_velocity_correlation_against_brute_force(strained):
    st = strained[0]
    h = st.h
    V = np.random.default_rng(1).standard_normal((st.n, 2))
    dr = 0.4
    out = corr.velocity_correlation(st.s, h, V, dr, block=700)      # several row blocks
    x = st.s @ h.T
    iu, ju = np.triu_indices(st.n, 1)
    dist = np.linalg.norm(true_min_image(x[ju] - x[iu], h), axis=1)
    rmax = geometry.min_image_radius(h)
    k = (dist / dr).astype(int)
    nb_ = int(rmax / dr)
    ok = k < nb_
    sums = np.bincount(k[ok], np.einsum("pd,pd->p", V[iu], V[ju])[ok], nb_)
    cnt = np.bincount(k[ok], None, nb_)
    np.testing.assert_array_equal(out["counts"], cnt)
    np.testing.assert_allclose(out["sum_VV"], sums, rtol=1e-10, atol=1e-10)
    V2 = np.mean(np.sum(V ** 2, axis=1))
    with np.errstate(invalid="ignore"):
        np.testing.assert_allclose(out["C"], sums / cnt / V2, rtol=1e-10, equal_nan=True)
    assert cnt.sum() > 0.5 * len(iu)           # most pairs are within r_max = L/2


def test_spectrum_against_eigvalsh(strained):
    st, S, N, r, n = strained
    st = st.copy()
    lam = np.linalg.eigvalsh(N)
    np.testing.assert_allclose(nw.dense_N(n, st.bonds, st.n), N, atol=1e-14)
    sysm = BondedSystem(PETSc.COMM_WORLD, st)
    F = sysm.evaluate(st.s, st.gamma)
    for mode in ("dense", "low"):
        out = nw.analyses(_instant(sysm, st, F, spectrum=mode, n_low=4, correlation=False,
                                   response_rods=2))
        if mode == "dense":
            np.testing.assert_allclose(out["arrays"]["omega"] ** 2, lam, rtol=1e-9, atol=1e-12)
            edges, D = out["arrays"]["dos_edges"], out["arrays"]["dos"]
            assert np.sum(D * np.diff(edges)) == pytest.approx(1.0, abs=1e-12)
        else:
            np.testing.assert_allclose(out["arrays"]["omega_low"] ** 2, lam[:4], rtol=1e-7)
    sysm.destroy()


# --------------------------------------------------------------------------- input

def test_network_file_round_trip(tmp_path, state):
    net = nw.make(PARAMS, seed=7)
    path = str(tmp_path / "net.h5")
    nb.save_network(path, net)
    loaded = nw.build(dict(PARAMS, network_file=path), seed=7)
    np.testing.assert_array_equal(loaded.s, state.s)
    np.testing.assert_array_equal(loaded.h0, state.h0)
    for k in ("i", "j", "shift", "l0"):
        np.testing.assert_array_equal(getattr(loaded.bonds, k), getattr(state.bonds, k))
    assert loaded.meta["network_file"] == path
    # the loaded network does not match a different scene: clear message, every mismatch
    with pytest.raises(InputError, match=r"does not match the scene: .*z = .*seed = 7 \(scene: seed = 8\)"):
        nw.build(dict(PARAMS, z=3.7, network_file=path), seed=8)
    with pytest.raises(InputError, match=r"N = 128 particles \(scene: model.N = 256\)"):
        nw.build(dict(PARAMS, N=256, network_file=path), seed=7)
    with pytest.raises(InputError, match="does not exist"):
        nw.build(dict(PARAMS, network_file=str(tmp_path / "missing.h5")), seed=7)


def scene_text(path, model="", legs=None, extra=""):
    legs = legs or '[[protocol.leg]]\ndirection = "forward"\nsigma_above = 1e4\n' \
                   '[[protocol.leg]]\ndirection = "reverse"\nsigma_below = 20\nstrain = 0.05\n'
    return f"""
seed = 7
[model]
name = "network"
N = 128
z = 3.8
{model}
{legs}
[output]
path = "{path}"
{extra}
"""


@pytest.mark.parametrize("z, msg", [(4.0, "floppy network needs z < 2d = 4"),
                                    (3.99, "out of range"), (3.2, "out of range")])
def test_bad_z(z, msg):
    with pytest.raises(InputError, match=msg):
        load_scene(scene_text("out.h5").replace("z = 3.8", f"z = {z}"))
    with pytest.raises(InputError, match="model.z"):
        nw.check_z(z)


def test_run_network_scene(mpi_tmp_path, comm):
    """Through the driver: forward to sigma = 1e4, reverse; analyses at the instants asked
    for, with the positions of that instant; a bad network_file stops every rank."""
    import h5py
    path = str(mpi_tmp_path / "net_run.h5")
    scene = load_scene(scene_text(path, extra='[observables]\nanalysis_quantity = "sigma"\n'
                                              'analysis_per_decade = 1\n'))
    setup_logging(PETSc.COMM_WORLD, quiet=True)
    assert Run(scene, PETSc.COMM_WORLD, path, quiet=True).execute() == "complete"
    comm.Barrier()
    with h5py.File(path, "r") as f:
        ts = f["timeseries"]
        assert np.max(ts["length_error"][()]) < 1e-10
        assert np.max(ts["sigma"][()]) >= 1e4 and ts["sigma"][-1] <= 20
        assert np.all(ts["z"][()] == ts["z"][0])
        groups = list(f["analysis"])
        assert len(groups) >= 4
        a = f["analysis"][groups[-1]]
        assert a["corr_C"].shape == a["corr_r"].shape and np.isfinite(a.attrs["VV"])
        assert a.attrs["resp_l_c"] > 0
    comm.Barrier()
    bad = load_scene(scene_text(path + "2", model=f'network_file = "{path}"'))
    with pytest.raises(InputError, match="not a parflow network"):
        Run(bad, PETSc.COMM_WORLD, path + "2", quiet=True).execute()


# --------------------------------------------------------------------------- C(r) by FFT

def random_state(n, gamma=0.7, seed=0, noise=0.5, waves=30):
    """n uniformly random nodes (density 0.74, as in the networks) in a cell sheared by gamma
    (0.7 > 1/2: the Lees-Edwards remapping matters) and a velocity field correlated over a
    few a0 (a sum of plane waves that are periodic in the sheared cell) plus white noise."""
    rng = np.random.default_rng(seed)
    L = np.sqrt(n / 0.74)
    h = np.array([[L, gamma * L], [0.0, L]])
    s = rng.random((n, 2))
    x = s @ h.T
    V = noise * rng.standard_normal((n, 2))
    for _ in range(waves):
        k = 2 * np.pi * np.linalg.solve(h.T, rng.integers(-5, 6, 2).astype(float))
        V += rng.standard_normal(2)[None, :] * np.cos(x @ k + 2 * np.pi * rng.random())[:, None]
    return s, h, V


def pair_r2(mi, s, iu, ju):
    """Squared minimum-image distances of pairs (the reduced-rint formula; below r_max it is
    the true minimum image, see test_velocity_correlation_against_brute_force)."""
    sr = mi.reduced(s)
    return corr.min_image_r2(mi.hr, [sr[ju, c] - sr[iu, c] for c in range(s.shape[1])])


@pytest.mark.parametrize("scheme", ["ngp", "cic"])
def test_fft_correlation_is_the_grid_sum(scheme):
    """Without exact short-range bins, the FFT method is, to round-off, the sum over pairs
    i < j of V_i.V_j (and of 1) placed at the grid offsets of their deposits (NGP: nearest
    points; CIC: all 2^d x 2^d corner pairs with weight w_i w_j), binned by the offset's
    minimum-image length: the FFT, the removal of the i = j terms (which CIC spreads over
    offsets -1, 0, 1) and the halving are checked against a direct sum that has no self terms."""
    s, h, V = random_state(300, seed=4)
    dr, spacing = 0.5, 0.3
    out = corr.velocity_correlation_fft(s, h, V, dr, spacing=spacing, scheme=scheme, r_exact=0)
    assert out["n_exact"] == 0 and out["scheme"] == scheme
    M = np.array(corr.correlation_grid(h, spacing))
    np.testing.assert_array_equal(out["grid"], M)
    mi = geometry.MinImage(h)
    u = mi.reduced(s) * M
    n = len(s)
    iu, ju = np.triu_indices(n, 1)
    dots = np.einsum("pd,pd->p", V[iu], V[ju])
    nbins = int(mi.rmax / dr)
    sums, cnt = np.zeros(nbins), np.zeros(nbins)
    if scheme == "ngp":
        g = np.floor(u + 0.5)
        options = [(g, g, np.ones(n), np.ones(n))]
    else:
        g0 = np.floor(u)
        f = u - g0
        corners = [np.array(c) for c in itertools.product((0, 1), repeat=2)]
        wts = [np.prod(np.where(c == 1, f, 1 - f), axis=1) for c in corners]
        options = [(g0 + ci, g0 + cj, wi, wj) for ci, wi in zip(corners, wts)
                   for cj, wj in zip(corners, wts)]
    for gi, gj, wi, wj in options:
        off = (gj[ju] - gi[iu]) / M                      # reduced grid offset of the pair
        r2 = corr.min_image_r2(mi.hr, [off[:, 0], off[:, 1]])
        k = (np.sqrt(r2) / dr).astype(int)
        ok = k < nbins
        w = (wi[iu] * wj[ju])[ok]
        sums += np.bincount(k[ok], w * dots[ok], nbins)
        cnt += np.bincount(k[ok], w, nbins)
    np.testing.assert_allclose(out["counts"], cnt, rtol=1e-9, atol=1e-8)
    np.testing.assert_allclose(out["sum_VV"], sums, rtol=1e-9, atol=1e-8)
    if scheme == "ngp":
        np.testing.assert_array_equal(out["counts"], cnt)    # integers, rounded


@pytest.fixture(scope="module")
def random_exact():
    """3000 random nodes at gamma = 0.7 with a correlated field, their exact C(r), and the
    distance and V_i.V_j of every pair."""
    s, h, V = random_state(3000, seed=1)
    ex = corr.velocity_correlation(s, h, V, 0.5)
    iu, ju = np.triu_indices(len(s), 1)
    r = np.sqrt(pair_r2(geometry.MinImage(h), s, iu, ju))
    dots = np.einsum("pd,pd->p", V[iu], V[ju])
    return s, h, V, ex, r, dots


@pytest.mark.parametrize("scheme", ["ngp", "cic"])
def test_fft_correlation_against_exact(scheme, random_exact):
    """3000 random nodes, gamma = 0.7, a correlated field.  Bins below r_exact: the same
    pairs as the exact function (counts equal, C to round-off).  Above: every pair is binned
    at a distance within eps (grid_resolution) of its true one, so a bin can only gain or
    lose the pairs whose true distance is within eps of one of its edges: |dcounts| <= their
    number and |dsum| <= the sum of their |V_i.V_j| (computed here from all pairs); C within
    the bound these imply.  And in practice far better than the bound."""
    s, h, V, ex, r, dots = random_exact
    absdot = np.abs(dots)
    dr = 0.5
    ff = corr.velocity_correlation_fft(s, h, V, dr, scheme=scheme)
    eps = ff["eps"]
    ne = ff["n_exact"]
    assert ne == int(corr.CORR_R_EXACT / dr) and eps < dr
    np.testing.assert_array_equal(ff["counts"][:ne], ex["counts"][:ne])
    np.testing.assert_allclose(ff["C"][:ne], ex["C"][:ne], rtol=1e-10, atol=1e-12)
    nbins = ex["counts"].size
    # edges e dr (e = 1..nbins) within eps of a pair: e_lo..e_hi (at most 2 as eps < dr);
    # such a pair may move between bins e - 1 and e
    V2 = ex["V2"]
    near_cnt, near_abs, near_dev2 = (np.zeros(nbins + 1) for _ in range(3))
    e_lo = np.floor((r - eps) / dr).astype(int) + 1
    e_hi = np.floor((r + eps) / dr).astype(int)
    for t in (0, 1):
        e = e_lo + t
        m = (e <= e_hi) & (e >= 1) & (e <= nbins)
        for b in (e[m] - 1, e[m]):
            near_cnt += np.bincount(b, None, nbins + 1)
            near_abs += np.bincount(b, absdot[m], nbins + 1)
            dev = dots[m] - np.append(ex["C"], 0.0)[b] * V2        # v - C(bin) V2
            near_dev2 += np.bincount(b, np.nan_to_num(dev) ** 2, nbins + 1)
    near_cnt, near_abs, near_dev2 = near_cnt[:nbins], near_abs[:nbins], near_dev2[:nbins]
    far = slice(ne, None)
    dcnt = np.abs(ff["counts"] - ex["counts"])[far]
    dsum = np.abs(ff["sum_VV"] - ex["sum_VV"])[far]
    assert np.all(dcnt <= near_cnt[far] + 1e-6)
    assert np.all(dsum <= near_abs[far] + 1e-6)
    # C = sum / (counts V2): |dC| <= (|dsum| + |C_ex| V2 |dcounts|) / (counts_fft V2)
    bound = (near_abs + np.abs(ex["C"]) * V2 * near_cnt) / (ff["counts"] * V2)
    dC = np.abs(ff["C"] - ex["C"])
    assert np.all(dC[far] <= bound[far] + 1e-12)
    # That bound (0.8-1.6 here) assumes every pair near an edge moves the same way.  They
    # move both ways, so dC is a sum of +-(V_i.V_j - C V2) / (counts V2) over those pairs,
    # of size ~ their root sum of squares: dC <= 3 rss (measured dC / rss <= 1.0 over 3
    # seeds x 2 schemes, max dC 0.004 on bins of >= 100 pairs)
    rss = np.sqrt(near_dev2) / (ff["counts"] * V2)
    ok = (ex["counts"] >= 100) & (np.arange(nbins) >= ne)
    assert np.all(dC[ok] <= 3 * rss[ok])
    assert dC[ok].max() < 0.01 < np.median(bound[ok])


def test_fft_correlation_plane_wave():
    """A circularly polarised plane wave V_i = (cos k.x_i, sin k.x_i), k = 2 pi h^-T m
    (periodic in the sheared cell): V_i.V_j = cos(k.r_ij), <V^2> = 1.

    (a) Nodes on every point of the FFT grid (no quantisation): C(bin) = mean of cos(k.r_D)
    over the grid offsets D != 0 whose minimum-image length is in the bin (each offset holds
    N ordered pairs), for the FFT (both schemes, no exact bins) and for the exact function.
    (b) 3000 random nodes: C(r) is the ring average of J_0(|k| r) over the bin, up to the
    sampling noise (< 5 / sqrt(pairs)) and the blur of the bin edges by the grid, second
    order in eps: (|k| eps)^2 / 2 from the curvature, |k| eps^2 / (2 r) from |r + delta|."""
    from scipy.special import j1
    dr, spacing, gamma = 0.5, 0.31, 0.7
    L = 16.3
    h = np.array([[L, gamma * L], [0.0, L]])
    mi = geometry.MinImage(h)
    M = np.array(corr.correlation_grid(h, spacing))
    g = np.stack(np.meshgrid(*[np.arange(m) for m in M], indexing="ij"), -1).reshape(-1, 2)
    s = (g / M) @ np.linalg.inv(mi.to_r).T               # h-reduced coordinates of grid points
    k = 2 * np.pi * np.linalg.solve(h.T, np.array([2.0, -1.0]))
    ph = (g / M) @ mi.hr.T @ k
    V = np.column_stack([np.cos(ph), np.sin(ph)])
    D = g[1:] / M                                        # the offsets D != 0
    r2 = corr.min_image_r2(mi.hr, [D[:, 0].copy(), D[:, 1].copy()])
    rD = (D - np.rint(D)) @ mi.hr.T
    nbins = int(mi.rmax / dr)
    kb = (np.sqrt(r2) / dr).astype(int)
    ok = kb < nbins
    expect = np.bincount(kb[ok], np.cos(rD[ok] @ k), nbins) / np.bincount(kb[ok], None, nbins)
    ex = corr.velocity_correlation(s, h, V, dr)
    np.testing.assert_allclose(ex["C"], expect, rtol=0, atol=1e-10)
    for scheme in ("ngp", "cic"):
        ff = corr.velocity_correlation_fft(s, h, V, dr, spacing=spacing, scheme=scheme, r_exact=0)
        np.testing.assert_array_equal(ff["grid"], M)
        np.testing.assert_allclose(ff["C"], expect, rtol=0, atol=1e-9)
        np.testing.assert_allclose(ff["counts"], ex["counts"], rtol=1e-12, atol=1e-6)
    # (b) random nodes against the continuum
    s, h, _ = random_state(3000, seed=2)
    k = 2 * np.pi * np.linalg.solve(h.T, np.array([2.0, -3.0]))
    kk = np.linalg.norm(k)
    ph = (s @ h.T) @ k
    V = np.column_stack([np.cos(ph), np.sin(ph)])
    ff = corr.velocity_correlation_fft(s, h, V, dr)
    assert ff["V2"] == pytest.approx(1.0, rel=1e-12)
    r1 = np.arange(ff["C"].size) * dr
    r2_ = r1 + dr
    ring = 2.0 / (r2_ ** 2 - r1 ** 2) * (r2_ * j1(kk * r2_) - r1 * j1(kk * r1)) / kk
    ok = ff["counts"] >= 100
    eps = ff["eps"]
    tol = 5.0 / np.sqrt(ff["counts"]) + 0.5 * (kk * eps) ** 2 \
        + kk * eps ** 2 / (2 * np.maximum(r1, dr))
    assert np.all(np.abs(ff["C"] - ring)[ok] <= tol[ok])
    assert np.abs(ff["C"] - ring)[ok].max() < 0.03       # measured: 0.012-0.020


def test_correlation_method_by_size(monkeypatch, comm, strained):
    """corr_method "auto": exact up to CORR_EXACT_MAX nodes, FFT above; through the analyses
    C(r) is computed on rank 0 and broadcast, and equals on every rank, bit for bit, the
    same computation done locally (the serial result)."""
    s, h, V = random_state(500, seed=3)
    assert corr.correlation(s, h, V, 0.5)["method"] == "exact"
    monkeypatch.setattr(corr, "CORR_EXACT_MAX", 499)
    out = corr.correlation(s, h, V, 0.5)
    assert out["method"] == "fft"
    ref = corr.velocity_correlation_fft(s, h, V, 0.5)
    np.testing.assert_array_equal(out["C"], ref["C"])
    with pytest.raises(InputError, match="method must be one of"):
        corr.correlation(s, h, V, 0.5, method="fast")
    st = strained[0].copy()
    sysm = BondedSystem(PETSc.COMM_WORLD, st)
    F = sysm.evaluate(st.s, st.gamma)
    monkeypatch.setattr(corr, "CORR_EXACT_MAX", st.n - 1)
    for method, expect in (("auto", "fft"), ("exact", "exact"), ("fft", "fft")):
        res = nw.analyses(_instant(sysm, st, F, correlation=True, corr_method=method,
                                   corr_dr=0.25, spectrum="none", response_rods=1))
        assert res["scalars"]["corr_method"] == expect
        local = corr.correlation(st.s, F.h, F.V_na, 0.25, 0.0, expect)
        np.testing.assert_array_equal(res["arrays"]["corr_C"], local["C"])
        np.testing.assert_array_equal(res["arrays"]["corr_counts"], local["counts"])
        every = comm.allgather(res["arrays"]["corr_C"])
        assert all(np.array_equal(c, every[0], equal_nan=True) for c in every)
        if expect == "fft":                    # a small cell: images in the exact bins
            assert 0 < res["scalars"]["corr_eps"] < 0.25
            ne = int(round(res["scalars"]["corr_r_exact"] / 0.25))
            ex = corr.velocity_correlation(st.s, F.h, F.V_na, 0.25)
            assert ne == 12 and ex["counts"][ne - 1] > 0
            np.testing.assert_array_equal(local["counts"][:ne], ex["counts"][:ne])
            np.testing.assert_allclose(local["C"][:ne], ex["C"][:ne], rtol=1e-10, equal_nan=True)
    sysm.destroy()
