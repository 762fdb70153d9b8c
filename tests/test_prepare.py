"""python -m parflow.prepare compress: a suspension state compressed to a higher packing
fraction, relaxed without overlaps, usable as a scene's configuration_file."""
import os
import subprocess
import sys

import numpy as np
import pytest

from parflow import prepare
from parflow.models import suspension as su
from parflow.geometry import cell_at, velocity_gradient
from parflow.models import suspension as msu
from parflow.state import InputError

pytestmark = pytest.mark.serial_only       # pure numpy; the CLI test launches a process


def test_rectangular_positions_undo_an_integer_strain():
    rng = np.random.default_rng(0)
    h0 = np.diag([10.0, 10.0])
    r = rng.random((50, 2)) * 10.0
    h = cell_at(h0, velocity_gradient("shear", 2), 2.0)     # gamma Ly / Lx = 2: a rectangle
    s = r @ np.linalg.inv(h).T
    s -= np.floor(s)                                        # wrapped in the sheared cell
    np.testing.assert_allclose(prepare.rectangular_positions(s, h0, 2.0), r, atol=1e-12)
    with pytest.raises(InputError, match="not a rectangle"):
        prepare.rectangular_positions(s, h0, 0.3)


def test_compress_relaxes_overlaps_and_keeps_the_structure():
    st = su.make_suspension(128, 0.76, seed=3)
    box = np.diag(st.h0).copy()
    X = st.s @ st.h0.T
    pos, box1, info = prepare.compress(X, st.radii, box, 0.78)
    new = su.from_configuration(pos, st.radii, box1)         # refuses overlaps
    assert new.meta["phi"] == pytest.approx(0.78, abs=1e-12)
    assert su.min_gap(new) >= 0.5e-6 * 2 * st.radii.min()
    assert info["phi0"] == pytest.approx(0.76, abs=1e-12)
    assert info["rms_move"] < 0.5                            # relaxed, not reshuffled
    with pytest.raises(InputError, match="not above"):
        prepare.compress(X, st.radii, box, 0.70)


def test_cli_from_a_run_file(tmp_path):
    from systems import run_scene
    from parflow.scene import load_scene
    run = tmp_path / "r.h5"
    scene = load_scene(f'seed = 2\n[model]\nname = "suspension"\nN = 96\nphi = 0.76\n'
                       f'[[protocol.leg]]\ndirection = "forward"\nstrain = 0.01\n'
                       f'[output]\npath = "{run}"\n')
    assert run_scene(scene) == "complete"
    env = dict(os.environ, PYTHONPATH=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

    def cli(*args):
        return subprocess.run([sys.executable, "-m", "parflow.prepare", "compress", *map(str, args)],
                              capture_output=True, text=True, env=env, timeout=120)
    out = tmp_path / "c.npz"
    res = cli(run, "--phi", 0.78, "--out", out)              # checkpoint at gamma = 0.01
    assert res.returncode == 2 and "not a rectangle" in res.stderr and not out.exists()
    res = cli(run, "--phi", 0.78, "--out", out, "--from", "initial")
    assert res.returncode == 0, res.stderr
    with np.load(out) as z:
        assert float(z["phi"]) == pytest.approx(0.78) and float(z["min_gap"]) > 0
        assert str(z["source_state"]) == "initial"
    st = msu.load_configuration(str(out), dict(N=96, phi=0.78))   # what a scene does with it
    assert st.n == 96 and st.meta["phi"] == pytest.approx(0.78)
    res = cli(tmp_path / "missing.h5", "--phi", 0.78, "--out", out)
    assert res.returncode == 2 and "does not exist" in res.stderr
