"""Floppy networks by the WLKM protocol (parflow.models.network_build).  Serial numpy
only: under ``mpirun -n N`` every rank runs these independently in its own tmp_path."""
import os

import h5py
import numpy as np
import pytest

from parflow.models import network_build as nb
from parflow.packing import fire as pk
from parflow.state import Bonds, InputError


@pytest.fixture(scope="module")
def packing():
    return pk.make_packing(256, 0.88, seed=5)


@pytest.fixture(scope="module")
def net(packing):
    return nb.network_from_packing(packing, 3.8, seed=1)


def test_target_z_reached(net, packing):
    n = int((~packing.rattler).sum())
    assert net.n == n                                   # rattlers dropped, renumbered
    assert abs(net.z - 3.8) <= 1.0 / n + 1e-15
    assert len(net.bonds) == round(3.8 * n / 2)
    assert net.z0 == pytest.approx(packing.z)
    assert net.bonds.i.max() < n and net.bonds.j.max() < n


def test_bond_lengths_equal_rest_lengths(net):
    r = net.s[net.bonds.j] - net.s[net.bonds.i] + net.bonds.shift
    ell = np.linalg.norm(r @ net.h0.T, axis=1)
    assert np.max(np.abs(ell - net.bonds.l0)) < 1e-12
    assert np.all((net.s >= 0) & (net.s < 1))
    assert np.allclose(net.h0, np.diag(np.diag(net.h0)))


def test_degree_invariant_and_histogram(net):
    deg = net.degrees()
    assert deg.min() >= net.d + 1
    hist = net.info["coordination_histogram"]
    assert hist.sum() == net.n
    assert np.array_equal(hist, np.bincount(deg))
    assert net.info["min_degree"] == deg.min()


def test_no_self_stress_dense_rank(net):
    S = nb.rigidity_matrix_dense(net.s, net.h0, net.bonds)
    assert S.shape == (len(net.bonds), net.d * net.n)
    assert np.linalg.matrix_rank(S) == len(net.bonds)
    info = net.info["self_stress"]
    assert info["self_stresses"] == 0 and info["rank"] == len(net.bonds)
    # S S^T is positive definite
    assert np.linalg.eigvalsh(S @ S.T)[0] > 1e-8


def test_rigidity_matrix_rows(net):
    S = nb.rigidity_matrix_dense(net.s, net.h0, net.bonds)
    r = net.bond_vectors()
    nvec = r / np.linalg.norm(r, axis=1)[:, None]
    a = 0
    i, j, d = net.bonds.i[a], net.bonds.j[a], net.d
    assert np.allclose(S[a, d * j:d * j + d], nvec[a])
    assert np.allclose(S[a, d * i:d * i + d], -nvec[a])
    assert np.count_nonzero(S[a]) == 2 * d


def test_isotropy(net):
    ev = net.info["fabric_eigenvalues"]
    assert ev.sum() == pytest.approx(1.0)
    assert net.info["fabric_ratio"] > 0.7


@pytest.mark.parametrize("z", [3.5, 3.98])
def test_extremes_of_range(packing, z):
    net = nb.network_from_packing(packing, z, seed=2)
    assert abs(net.z - z) <= 1.0 / net.n + 1e-15
    assert net.degrees().min() >= 3
    assert net.info["self_stress"]["self_stresses"] == 0


def test_dilution_follows_max_sum_rule(packing):
    """Replay the removals in order: each removed bond had the largest z_i + z_j among
    the removable bonds at its turn."""
    keepn = ~packing.rattler
    ids = np.cumsum(keepn) - 1
    i, j = ids[packing.contacts_i], ids[packing.contacts_j]
    n = int(keepn.sum())
    keep, order = nb.dilute(n, i, j, round(3.6 * n / 2), 2, np.random.default_rng(0),
                            return_order=True)
    assert np.array_equal(np.sort(order), np.flatnonzero(~keep))
    alive = np.ones(i.shape[0], bool)
    deg = nb.degrees(n, i, j)
    for b in order:
        ok = alive & (deg[i] > 3) & (deg[j] > 3)
        assert ok[b]
        assert deg[i[b]] + deg[j[b]] == (deg[i] + deg[j])[ok].max()
        alive[b] = False
        deg[i[b]] -= 1
        deg[j[b]] -= 1


def test_dilution_seeded(packing):
    a = nb.network_from_packing(packing, 3.7, seed=11)
    b = nb.network_from_packing(packing, 3.7, seed=11)
    c = nb.network_from_packing(packing, 3.7, seed=12)
    assert np.array_equal(a.bonds.i, b.bonds.i) and np.array_equal(a.bonds.j, b.bonds.j)
    assert not (np.array_equal(a.bonds.i, c.bonds.i) and np.array_equal(a.bonds.j, c.bonds.j))


def test_make_network_end_to_end():
    net = nb.make_network(64, 3.9, phi=0.88, seed=0)
    assert abs(net.z - 3.9) <= 1.0 / net.n + 1e-15
    assert net.info["packing"]["n"] == 64


def test_save_load_round_trip(net, tmp_path):
    path = tmp_path / "net.h5"
    nb.save_network(path, net)
    assert path.exists() and not os.path.exists(str(path) + ".tmp")
    back = nb.load_network(path)
    assert np.array_equal(back.s, net.s) and np.array_equal(back.h0, net.h0)
    for k in ("i", "j", "shift", "l0"):
        assert np.array_equal(getattr(back.bonds, k), getattr(net.bonds, k))
    assert back.z0 == net.z0 and back.seed == net.seed
    assert np.array_equal(back.info["coordination_histogram"], net.info["coordination_histogram"])
    assert back.info["packing"]["phi"] == net.info["packing"]["phi"]
    with h5py.File(path, "r") as f:
        assert f.attrs["format"] == nb.FORMAT
        assert f.attrs["format_version"] == nb.FORMAT_VERSION


def test_save_is_atomic(net, tmp_path, monkeypatch):
    path = tmp_path / "net.h5"
    nb.save_network(path, net)
    before = path.read_bytes()

    def boom(*a, **k):
        raise KeyboardInterrupt
    monkeypatch.setattr(nb, "_write_info", boom)
    with pytest.raises(KeyboardInterrupt):
        nb.save_network(path, net)
    assert path.read_bytes() == before                  # old file untouched
    assert not os.path.exists(str(path) + ".tmp")


def test_load_rejects_bad_files(net, tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        nb.load_network(tmp_path / "missing.h5")
    junk = tmp_path / "junk.h5"
    junk.write_text("not hdf5")
    with pytest.raises(InputError, match="not a parflow network"):
        nb.load_network(junk)
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f.create_dataset("x", data=np.arange(3))
    with pytest.raises(InputError, match="not a parflow network"):
        nb.load_network(other)
    good = tmp_path / "good.h5"
    nb.save_network(good, net)
    with h5py.File(good, "a") as f:
        f.attrs["format_version"] = 99
    with pytest.raises(InputError, match="version 99"):
        nb.load_network(good)
    nb.save_network(good, net)
    with h5py.File(good, "a") as f:
        f["bonds/l0"][0] *= 1.01
    with pytest.raises(InputError, match="rest lengths"):
        nb.load_network(good)
    nb.save_network(good, net)
    with h5py.File(good, "a") as f:
        del f["bonds/shift"]
    with pytest.raises(InputError, match="missing"):
        nb.load_network(good)


@pytest.mark.parametrize("z, msg", [
    (4.0, r"a floppy network needs z < 2d = 4 in 2D: z = 2d is isostatic/rigid"),
    (4.5, r"z < 2d = 4"),
    (2.5, r"below d \+ 1 = 3"),
    (float("nan"), "finite"),
])
def test_bad_target_z(packing, z, msg):
    with pytest.raises(InputError, match=msg):
        nb.network_from_packing(packing, z)


def test_too_small():
    with pytest.raises(InputError, match="too small"):
        nb.make_network(8, 3.8)


def test_dilution_stuck_is_reported():
    # two K4's (all degrees 3) joined by nothing: nothing is removable in 2D
    i = np.array([0, 0, 0, 1, 1, 2, 4, 4, 4, 5, 5, 6])
    j = np.array([1, 2, 3, 2, 3, 3, 5, 6, 7, 6, 7, 7])
    with pytest.raises(InputError, match="dilution stopped at z = 3.0000"):
        nb.dilute(8, i, j, 10, 2, np.random.default_rng(0))


def test_bonds_type(net):
    assert isinstance(net.bonds, Bonds)
    assert net.bonds.shift.shape == (len(net.bonds), 2)


def test_three_dimensional_network():
    p = pk.make_packing(128, 0.72, d=3, seed=2)
    net = nb.network_from_packing(p, 5.5, seed=0)
    assert net.d == 3 and net.h0.shape == (3, 3)
    assert abs(net.z - 5.5) <= 1.0 / net.n + 1e-15
    assert net.degrees().min() >= 4
    assert net.info["self_stress"]["self_stresses"] == 0
    with pytest.raises(InputError, match="z < 2d = 6 in 3D"):
        nb.network_from_packing(p, 6.0)


def test_sparse_and_dense_rigidity_matrices_agree(net):
    S = nb.rigidity_matrix_dense(net.s, net.h0, net.bonds)
    Ss = nb.rigidity_matrix_sparse(net.s, net.h0, net.bonds)
    assert np.array_equal(Ss.toarray(), S)


def test_self_stress_is_detected():
    """A rigid triangle plus a fourth, redundant bond on a square with both diagonals:
    the complete graph K4 in 2D has 6 bonds on 8 - 3 = 5 degrees of freedom: one
    self-stress."""
    s = np.array([[0.1, 0.1], [0.3, 0.1], [0.3, 0.3], [0.1, 0.3]])
    i = np.array([0, 1, 2, 3, 0, 1])
    j = np.array([1, 2, 3, 0, 2, 3])
    bonds = Bonds(i, j, np.zeros((6, 2), dtype=int), np.ones(6))
    info = nb.self_stress_check(s, np.eye(2) * 10.0, bonds)
    assert info["self_stresses"] == 1 and info["rank"] == 5
