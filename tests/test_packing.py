"""Jammed soft-disc packings (parflow.packing: mixture, fire, pairs, pairs_numba).  Serial
(numpy kernel, and the optional numba kernel with 1 or 2 threads): under ``mpirun -n N``
every rank runs these independently."""
from pathlib import Path

import numpy as np
import pytest

from parflow.errors import InputError
from parflow.packing import fire, mixture, pairs


@pytest.fixture(scope="module")
def pack():
    return fire.make_packing(128, 0.88, seed=3)


def brute_pairs(pos, radii, box):
    """All overlapping pairs by O(N^2) minimum image: (i, j, r_vec, overlap)."""
    n = pos.shape[0]
    i, j = np.triu_indices(n, 1)
    dr = pos[j] - pos[i]
    dr -= box * np.round(dr / box)
    r = np.linalg.norm(dr, axis=1)
    sig = radii[i] + radii[j]
    m = r < sig
    return i[m], j[m], dr[m], 1.0 - r[m] / sig[m]


def test_mixture_and_box(pack):
    assert pack.n == 128 and pack.d == 2
    assert np.count_nonzero(pack.radii == 0.5) == 64
    assert np.count_nonzero(np.isclose(pack.radii, 0.7)) == 64
    assert pack.phi == pytest.approx(0.88)
    assert mixture.packing_fraction(pack.radii, pack.box) == pytest.approx(0.88, rel=1e-12)
    s = pack.reduced
    assert np.all((s >= 0) & (s < 1))


def test_force_tolerance_reached(pack):
    # recompute the forces from scratch by brute force
    i, j, dr, ov = brute_pairs(pack.positions, pack.radii, pack.box)
    sig = pack.radii[i] + pack.radii[j]
    r = np.linalg.norm(dr, axis=1)
    f = (ov / sig)[:, None] * dr / r[:, None]           # force on j
    F = np.zeros_like(pack.positions)
    np.add.at(F, j, f)
    np.add.at(F, i, -f)
    fmax = np.sqrt((F ** 2).sum(1)).max()
    fscale = (ov / sig).mean()
    assert fscale == pytest.approx(pack.force_scale, rel=1e-6)
    assert fmax < max(pack.ftol * fscale, fire.force_floor(pack.box)) * 1.0001
    assert pack.max_force == pytest.approx(fmax, rel=1e-3, abs=1e-15)
    p = (ov / sig * r).sum() / (2 * np.prod(pack.box))
    assert pack.pressure == pytest.approx(p, rel=1e-10)
    assert pack.energy == pytest.approx(0.5 * (ov ** 2).sum(), rel=1e-10)


def test_contacts_match_distances_and_no_rattler_left(pack):
    i, j, dr, ov = brute_pairs(pack.positions, pack.radii, pack.box)
    nr = ~pack.rattler
    m = nr[i] & nr[j]
    brute = set(zip(i[m].tolist(), j[m].tolist()))
    got = set(zip(pack.contacts_i.tolist(), pack.contacts_j.tolist()))
    assert got == brute
    assert np.all(pack.contacts_i < pack.contacts_j)
    # image shifts: r = L (s_j + n - s_i) is the overlapping minimum-image vector
    r = pack.contact_vectors()
    sig = pack.radii[pack.contacts_i] + pack.radii[pack.contacts_j]
    assert np.all(np.linalg.norm(r, axis=1) < sig)
    assert pack.contacts_shift.dtype.kind == "i"
    # no rattler remains: every kept particle has >= d + 1 contacts among the kept
    deg = np.bincount(pack.contacts_i, minlength=pack.n) + np.bincount(pack.contacts_j, minlength=pack.n)
    assert np.all(deg[nr] >= pack.d + 1)
    assert np.all(deg[pack.rattler] == 0)
    assert pack.z == pytest.approx(2 * len(got) / nr.sum())
    # jammed: at least isostatic (Nc >= d (N' - 1) + 1)
    assert len(got) >= pack.d * (nr.sum() - 1) + 1
    assert pack.pressure > 0


def test_same_seed_same_packing(pack):
    again = fire.make_packing(128, 0.88, seed=3)
    assert np.array_equal(again.positions, pack.positions)
    assert np.array_equal(again.radii, pack.radii)
    assert np.array_equal(again.contacts_i, pack.contacts_i)
    assert np.array_equal(again.contacts_shift, pack.contacts_shift)
    assert again.iterations == pack.iterations
    other = fire.make_packing(128, 0.88, seed=4)
    assert not np.array_equal(other.positions, pack.positions)


def test_pair_list_forces_match_brute_force():
    rng = np.random.default_rng(0)
    n = 64
    radii = mixture.binary_radii(n)
    L = mixture.box_side(radii, 0.9, 2)
    box = np.full(2, L)
    X = (rng.random((n, 2)) * L).T.copy()
    pl = pairs.NumpyPairs(radii, box, 0.3)
    X = pl.build(X)
    X += 0.1 * (rng.random(X.shape) - 0.5)          # move less than skin/2, unwrapped
    F = np.empty_like(X)
    pl.forces(X, F)
    i, j, dr, ov = brute_pairs(X.T % L, radii, box)
    sig = radii[i] + radii[j]
    f = (ov / sig)[:, None] * dr / np.linalg.norm(dr, axis=1)[:, None]
    Fb = np.zeros((n, 2))
    np.add.at(Fb, j, f)
    np.add.at(Fb, i, -f)
    assert np.allclose(F.T, Fb, atol=1e-14)


def test_target_pressure():
    p = fire.make_packing(64, 0.87, seed=1, pressure=0.02, pressure_rtol=0.02)
    assert p.pressure == pytest.approx(0.02, rel=0.02)
    assert len(p.info["stages"]) >= 2


def test_three_dimensions():
    p = fire.make_packing(128, 0.72, d=3, seed=2)
    assert p.d == 3 and p.box.shape == (3,)
    nr = ~p.rattler
    assert p.n_contacts >= 3 * (nr.sum() - 1) + 1
    assert p.z >= 6.0 - 0.2


def test_below_jamming_is_refused():
    with pytest.raises(InputError, match=r"no contacts after minimisation; phi_J ≈ 0.843"):
        fire.make_packing(64, 0.75, seed=0)


@pytest.mark.parametrize("kw, msg", [
    (dict(n=4, phi=0.88), "too small"),
    (dict(n=64, phi=1.2), "phi must be in"),
    (dict(n=64, phi=0.88, ftol=0.0), "ftol"),
    (dict(n=64, phi=0.88, pressure=-1.0), "pressure"),
    (dict(n=64, phi=None), "give phi"),
    (dict(n=64, phi=0.88, d=1), "d must be"),
])
def test_bad_inputs(kw, msg):
    with pytest.raises(InputError, match=msg):
        fire.make_packing(**kw)


def test_remove_rattlers_cascade():
    # a triangle (degree 2 each) hanging off nothing: all rattlers in 2D
    i = np.array([0, 1, 0])
    j = np.array([1, 2, 2])
    r, keep = fire.remove_rattlers(3, i, j, 2)
    assert r.all() and not keep.any()


def test_morton_order_is_a_local_permutation():
    rng = np.random.default_rng(1)
    s = rng.random((1000, 2))
    o = fire.morton_order(s)
    assert np.array_equal(np.sort(o), np.arange(1000))
    step = np.linalg.norm(np.diff(s[o], axis=0), axis=1).mean()
    assert step < 0.25 * np.linalg.norm(np.diff(s, axis=0), axis=1).mean()


def test_tiny_tolerance_stops_at_round_off_floor():
    p = fire.make_packing(64, 0.88, seed=2, ftol=1e-30, max_iter=200_000)
    assert p.max_force < fire.force_floor(p.box)


needs_numba = pytest.mark.skipif(not pairs.have_numba(), reason="numba not installed (optional kernel)")


def _random_state(d, n=200, seed=None):
    rng = np.random.default_rng(d if seed is None else seed)
    radii = mixture.binary_radii(n)
    L = mixture.box_side(radii, 0.9 if d == 2 else 0.7, d)
    box = np.full(d, L)
    X = (rng.random((n, d)) * L).T.copy()
    return radii, box, X, rng


@needs_numba
@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("threads", [1, 2])
def test_numba_kernel_is_bit_identical_to_numpy(d, threads):
    """Same pair list (cell list vs cKDTree), same forces, overlaps and FIRE reductions,
    to the last bit, also after the particles moved (unwrapped) within skin/2.  N spans
    several reduction blocks, so with 2 threads both threads work."""
    max_threads = pairs.numba_kernels().max_threads()
    if threads > max_threads:
        pytest.skip(f"numba has {max_threads} thread(s) here (CPU affinity)")
    radii, box, X, rng = _random_state(d, n=2 * pairs.BLOCK + 300)
    dX = 0.19 * (rng.random(X.shape) - 0.5)        # |dX| < skin/2 = 0.2
    V = rng.random(X.shape) - 0.5
    out = {}
    for kernel in ("numpy", "numba"):
        pl = pairs.pair_list(radii, box, 0.4, kernel, threads if kernel == "numba" else None)
        with pl.threads_set():
            Xk = pl.build(X.copy())
            half = tuple(a.copy() for a in (pl.i, pl.j, pl.S, pl.isig))
            Xk = Xk + dX
            F = np.empty_like(Xk)
            ov = pl.forces(Xk, F)
            G = np.empty_like(Xk)
            red = pl.step(Xk, V, G, 0.37)
            Xu, Vu = Xk.copy(), V.copy()
            vmax2 = pl.update(Xu, Vu, G, 0.05, False, 0.9, 0.013)
            Xb, Vb = Xk.copy(), V.copy()
            pl.update(Xb, Vb, G, 0.05, True, 0.9, None)
            disp = pl.max_displacement(Xu)
        out[kernel] = (half, F, ov, G, red, Xu, Vu, vmax2, Xb, Vb, disp)
    a, b = out["numpy"], out["numba"]
    for x, y in zip(a[0], b[0]):
        assert np.array_equal(x, y)
    assert np.all(a[0][0] < a[0][1])
    assert np.array_equal(a[1], b[1]) and np.array_equal(a[2], b[2])
    assert np.array_equal(a[1], a[3]) and np.array_equal(b[1], b[3])
    assert a[4] == b[4]
    for x, y in zip(a[5:], b[5:]):
        assert np.array_equal(x, y)


@needs_numba
def test_cell_list_finds_every_pair():
    """The cell list lists exactly the pairs closer than R_i + R_j + skin (brute force)."""
    radii, box, X, _ = _random_state(2, n=300, seed=7)
    pl = pairs.pair_list(radii, box, 0.4, "numba", 1)
    Xw = pl.build(X.copy())
    i, j = np.triu_indices(radii.size, 1)
    dr = Xw.T[j] - Xw.T[i]
    dr -= box * np.round(dr / box)
    m = (dr ** 2).sum(1) < (radii[i] + radii[j] + 0.4) ** 2
    assert set(zip(pl.i.tolist(), pl.j.tolist())) == set(zip(i[m].tolist(), j[m].tolist()))


@needs_numba
def test_numba_packing_equals_numpy_packing(pack):
    p = fire.make_packing(128, 0.88, seed=3, kernel="numba")
    q = fire.make_packing(128, 0.88, seed=3, kernel="numpy")
    assert p.info["kernel"] == "numba" and q.info["kernel"] == "numpy"
    assert p.info["threads"] == 1
    assert np.array_equal(p.positions, q.positions)
    assert np.array_equal(p.contacts_j, q.contacts_j)
    assert p.iterations == q.iterations and p.info["n_builds"] == q.info["n_builds"]
    assert np.array_equal(p.positions, pack.positions)
    assert p.iterations == pack.iterations


@needs_numba
def test_numba_3d_packing_equals_numpy():
    p = fire.make_packing(128, 0.72, d=3, seed=2, kernel="numba")
    q = fire.make_packing(128, 0.72, d=3, seed=2, kernel="numpy")
    assert np.array_equal(p.positions, q.positions) and p.iterations == q.iterations


def test_block_sum_order():
    """The fixed summation order of the FIRE reductions: blocks of BLOCK in order."""
    rng = np.random.default_rng(5)
    t = rng.standard_normal(2 * pairs.BLOCK + 17) * 10.0 ** rng.integers(-8, 8, 2 * pairs.BLOCK + 17)
    parts = []
    for k in range(0, t.size, pairs.BLOCK):
        s = 0.0
        for x in t[k:k + pairs.BLOCK].tolist():
            s += x
        parts.append(s)
    total = 0.0
    for x in parts:
        total += x
    assert pairs.block_sum(t) == total


@needs_numba
def test_numba_thread_count_checked_and_small_box_falls_back():
    radii = mixture.binary_radii(16)
    box = np.full(2, 4.0)                          # < 2 (cut + skin) = 4.4
    assert pairs.pair_list(radii, box, 0.4, "auto").kernel == "numpy"
    with pytest.raises(InputError, match="box side"):
        pairs.pair_list(radii, box, 0.4, "numba")
    with pytest.raises(InputError, match="threads"):
        pairs.pair_list(radii, np.full(2, 50.0), 0.4, "numba", threads=999)


def test_unknown_kernel():
    with pytest.raises(InputError, match="kernel"):
        fire.make_packing(64, 0.88, kernel="cuda")


@needs_numba
def test_pair_list_picks_a_class_per_kernel():
    radii = mixture.binary_radii(64)
    box = np.full(2, 50.0)
    numpy_pl = pairs.pair_list(radii, box, 0.4, "numpy")
    numba_pl = pairs.pair_list(radii, box, 0.4, "numba")
    assert type(numpy_pl) is pairs.NumpyPairs and numpy_pl.kernel == "numpy"
    assert type(numba_pl).__name__ == "NumbaPairs" and numba_pl.kernel == "numba"
    assert isinstance(numba_pl, pairs.PairList) and numba_pl.threads == pairs.DEFAULT_THREADS
    assert pairs.pair_list(radii, box, 0.4, "auto").kernel == "numba"
    assert numpy_pl.threads is None


def test_mixture_is_the_one_source():
    """The suspension's constants and radii are the mixture's (no second copy)."""
    from parflow.models import suspension as su
    from parflow.models import suspension as msu
    assert mixture.PHI_J == {2: 0.843, 3: 0.648}
    assert su.PHI_J == msu.PHI_J == mixture.PHI_J_2D == mixture.PHI_J[2]
    assert su.RADIUS_RATIO == mixture.RADIUS_RATIO == 1.4 and mixture.SMALL_DIAMETER == 1.0
    for name in ("binary_radii", "check_mixture", "check_phi"):
        assert getattr(su, name) is getattr(mixture, name)
    assert mixture.phi_j(4) == mixture.PHI_J[3]


def test_binary_radii_split_and_labels():
    r = mixture.binary_radii(8)
    assert np.array_equal(r, [0.5] * 4 + [0.7] * 4)
    # round half to even by default; the packings keep their n // 2 small particles
    assert np.count_nonzero(mixture.binary_radii(7) == 0.5) == 4
    assert np.count_nonzero(mixture.binary_radii(7, n_small=3) == 0.5) == 3
    assert np.count_nonzero(fire.make_packing(15, 0.88, seed=1).radii == 0.5) == 7
    # rng: one permutation of the sorted radii, drawn from the generator given
    a = mixture.binary_radii(50, 1.2, (0.3, 0.7), np.random.default_rng(4))
    b = mixture.binary_radii(50, 1.2, (0.3, 0.7))[np.random.default_rng(4).permutation(50)]
    assert np.array_equal(a, b) and np.count_nonzero(a == 0.5) == 15
    with pytest.raises(InputError, match="sum to 1"):
        mixture.binary_radii(10, 1.4, (0.5, 0.6))
    assert mixture.ball_volume(3, 1.0) == pytest.approx(4.0 / 3.0 * np.pi)


def test_packing_package_does_not_use_petsc():
    for path in Path(fire.__file__).parent.glob("*.py"):
        text = path.read_text()
        assert "petsc4py" not in text and "slepc4py" not in text and "mpi4py" not in text, path
