"""python -m parflow.modes: the lowest modes of N along a run and the share of sigma each
carries, against dense linear algebra; the CLI on a small network run with snapshots."""
import os
import subprocess
import sys

import h5py
import numpy as np
import pytest
from systems import dense_operators, random_bonded_state, run_scene

from parflow import modes
from parflow.scene import load_scene
from hang_guard import guard

pytestmark = pytest.mark.serial_only       # serial scipy analysis; the CLI test launches a process


def test_participation_ratio():
    assert modes.participation(np.ones(50)) == pytest.approx(1.0)
    e = np.zeros((40, 2))
    e[3] = [0.6, 0.8]
    assert modes.participation(e) == pytest.approx(1 / 40)


def test_mode_table_matches_dense():
    st = random_bonded_state(n=30, extra=6)
    S, N, b, r, n = dense_operators(st)
    lam, psi = np.linalg.eigh(N)
    total = b @ np.linalg.solve(N, b)
    share = (psi.T @ b) ** 2 / lam / total
    assert share.sum() == pytest.approx(1.0, rel=1e-10)       # the shares of all modes
    t = modes.mode_table(n, b, st.bonds.i, st.bonds.j, st.n, k=4)
    np.testing.assert_allclose(t["lam"], lam[:4], rtol=1e-9)
    np.testing.assert_allclose(t["share"], share[:4], rtol=1e-7, atol=1e-12)
    assert t["sigma_omega"] == pytest.approx(total, rel=1e-10)
    for q in range(4):
        assert t["pr_stress"][q] == pytest.approx(modes.participation(psi[:, q]), rel=1e-6)
        assert t["pr_motion"][q] == pytest.approx(
            modes.participation((S.T @ psi[:, q]).reshape(st.n, 2)), rel=1e-6)


def _network_run(path, extra=""):
    scene = load_scene(f'seed = 7\n[model]\nname = "network"\nN = 128\nz = 3.8\n'
                       f'[[protocol.leg]]\ndirection = "forward"\nsigma_above = 200\n'
                       f'[output]\npath = "{path}"\n{extra}')
    assert run_scene(scene) in ("complete", "budget")


def test_cli_on_a_network_run(tmp_path):
    run = tmp_path / "net.h5"
    _network_run(run, "[observables]\nsnapshot_every = 5\n")
    env = dict(os.environ, PYTHONPATH=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    res = subprocess.run([sys.executable, "-m", "parflow.modes", str(run), "--k", "2"],
                         capture_output=True, text=True, env=env, timeout=guard(300))
    assert res.returncode == 0, res.stderr
    out = tmp_path / "net.modes.h5"
    assert (tmp_path / "net_plots" / "modes.png").exists()
    with h5py.File(run) as f, h5py.File(out) as m:
        n_snap = len(f["snapshots"])
        assert m["lam"].shape == (n_snap, 2) and np.all(np.diff(m["lam"][:], axis=1) >= 0)
        assert np.all((m["share"][:] >= 0) & (m["share"][:] <= 1 + 1e-9))
        np.testing.assert_array_equal(m["step"][:], sorted(int(g.attrs["step"])
                                                           for g in f["snapshots"].values()))
        # close to jamming (sigma ~ 200 at N = 128) the lowest mode carries most of sigma
        assert m["share"][-1, 0] > 0.5
    # a run without snapshots: one clear line, exit 2, nothing written
    run2 = tmp_path / "bare.h5"
    _network_run(run2)
    res = subprocess.run([sys.executable, "-m", "parflow.modes", str(run2)],
                         capture_output=True, text=True, env=env, timeout=guard(120))
    assert res.returncode == 2 and "snapshot_every" in res.stderr
    assert not (tmp_path / "bare.modes.h5").exists()
