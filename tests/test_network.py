"""The network model (parflow.models.network): Lees-Edwards geometry, rigid rods and the
stress identity under shear, the point response, C(r) and the spectrum of N against dense
numpy / brute force, save/load through model.network_file, bad input.

Under ``mpirun -n 2`` both ranks run every test (the PETSc objects are distributed over
COMM_WORLD, the numpy references are replicated), so the assertions hold on both."""
import itertools

import numpy as np
import pytest
from petsc4py import PETSc

from parflow.cell import pair_geometry
from parflow.integrate import Heun, StepControl
from parflow.models import network as nw
from parflow.models import network_build as nb
from parflow.run import Run, setup_logging
from parflow.scene import load_scene
from parflow.state import Bonds, InputError, State
from parflow.system import BondedSystem
from systems import dense_operators

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
    hr = nw.remapped_cell(h)
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
        mi = nw.MinImage(h)
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
        mi = nw.MinImage(h)
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
    rods = nw.pick_rods(st.s, F.h, st.bonds, 3)
    assert len(set(rods.tolist())) == 3
    dr = 0.5
    pr = nw.point_response(sysm, st.s, F.h, st.bonds, rods, dr)
    # dense reference: N f = e_beta, V = S^T f, distances by brute-force minimum image
    x = st.s @ F.h.T
    mid = x[st.bonds.i] + 0.5 * r
    rmax = nw.min_image_radius(F.h)
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
    fit = nw.fit_two_exponentials(r, P * (1 + 1e-3 * np.sin(7 * r)))
    assert fit["l_c"] == pytest.approx(1.5, rel=0.02)
    assert fit["l_r"] == pytest.approx(12.0, rel=0.02)
    assert fit["l_c_err"] < 0.05 and fit["l_r_err"] < 0.5


def test_velocity_correlation_against_brute_force(strained):
    st = strained[0]
    h = st.h
    V = np.random.default_rng(1).standard_normal((st.n, 2))
    dr = 0.4
    out = nw.velocity_correlation(st.s, h, V, dr, block=700)      # several row blocks
    x = st.s @ h.T
    iu, ju = np.triu_indices(st.n, 1)
    dist = np.linalg.norm(true_min_image(x[ju] - x[iu], h), axis=1)
    rmax = nw.min_image_radius(h)
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
        st.meta.update(spectrum=mode, n_low=4, correlation=0, response_rods=2)
        out = nw.analyses(sysm, st, F)
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
