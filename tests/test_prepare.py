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
from hang_guard import guard

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
                              capture_output=True, text=True, env=env, timeout=guard(120))
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


ENSEMBLE_SCENE = """seed = 4
[model]
name = "suspension"
N = 96
phi = {phi}
{config}
[ensemble]
samples = {samples}
[[protocol.leg]]
direction = "forward"
strain = {strain}
[output]
path = "unused.h5"
"""


def test_ensemble_folder_compressed_into_one_start_per_sample(tmp_path):
    """An ensemble's samples (1.0 strain: a rectangle again) compressed to phi = 0.78 into one
    .npz per sample; an ensemble scene with {sample} in configuration_file starts sample k
    from file k; too few files, or {sample} outside an ensemble, fail with one line (exit 2)."""
    import h5py
    env = dict(os.environ, PYTHONPATH=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

    def run(*args, module="parflow.shear"):
        return subprocess.run([sys.executable, "-m", module, *map(str, args)],
                              capture_output=True, text=True, env=env, timeout=guard(300))
    (tmp_path / "a.toml").write_text(ENSEMBLE_SCENE.format(phi=0.76, config="", samples=2,
                                                           strain=1.0))
    res = run(tmp_path / "a.toml", "--output", tmp_path / "ens", "--quiet", "--no-plots")
    assert res.returncode == 0, res.stderr
    out = tmp_path / "conf" / "c_{sample}.npz"
    res = run("compress", tmp_path / "ens", "--phi", 0.78, "--out", tmp_path / "conf" / "c.npz",
              module="parflow.prepare")
    assert res.returncode == 2 and "{sample}" in res.stderr and len(res.stderr.splitlines()) == 1
    res = run("compress", tmp_path / "ens", "--phi", 0.86, "--out", out, module="parflow.prepare")
    assert res.returncode == 2 and "2 of 2 samples not compressed" in res.stderr    # > phi_J
    assert len(res.stderr.strip().splitlines()) == 1
    res = run("compress", tmp_path / "ens", "--phi", 0.78, "--out", out, module="parflow.prepare")
    assert res.returncode == 0, res.stderr
    assert sorted(os.listdir(tmp_path / "conf")) == ["c_0000.npz", "c_0001.npz"]
    with np.load(tmp_path / "conf" / "c_0001.npz") as z:
        assert str(z["source"]).endswith("sample_0001.h5") and float(z["phi"]) == pytest.approx(0.78)
        pos1 = z["positions"]
    config = f'configuration_file = "{out}"'
    (tmp_path / "b.toml").write_text(ENSEMBLE_SCENE.format(phi=0.78, config=config, samples=2,
                                                           strain=0.01))
    res = run(tmp_path / "b.toml", "--output", tmp_path / "ens2", "--quiet", "--no-plots")
    assert res.returncode == 0, res.stderr
    from parflow.io import RunFile
    with RunFile(str(tmp_path / "ens2" / "sample_0001.h5")) as rf:
        init = rf.initial()
        assert 'c_0001.npz' in rf.scene_text and "{sample}" not in rf.scene_text
    r = init["s"] @ init["h0"].T
    box = np.diag(init["h0"])
    assert np.allclose(r - np.floor(r / box) * box, pos1, atol=1e-12)
    with h5py.File(tmp_path / "ens2" / "sample_0000.h5") as f:
        assert f.attrs["status"] == "complete"
    # three samples, two files: the third is recorded as failed, the others run (exit 1)
    (tmp_path / "c.toml").write_text(ENSEMBLE_SCENE.format(phi=0.78, config=config, samples=3,
                                                           strain=0.01))
    res = run(tmp_path / "c.toml", "--output", tmp_path / "ens3", "--quiet", "--no-plots")
    assert res.returncode == 1 and "c_0002.npz" in res.stderr
    with h5py.File(tmp_path / "ens3" / "ensemble.h5") as f:
        st = [x.decode() if isinstance(x, bytes) else str(x) for x in f["status"][()]]
    assert st == ["complete", "complete", "failed"]
    # no file at all: refused before any sample runs
    (tmp_path / "e.toml").write_text(ENSEMBLE_SCENE.format(
        phi=0.78, config=config.replace("c_{sample}", "x_{sample}"), samples=2, strain=0.01))
    res = run(tmp_path / "e.toml", "--output", tmp_path / "ens4", "--quiet", "--no-plots")
    assert res.returncode == 2 and "no sample has its file" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "ens4" / "sample_0000.h5").exists()
    # {sample} in a single run
    (tmp_path / "d.toml").write_text(ENSEMBLE_SCENE.format(phi=0.78, config=config, samples=3,
                                                           strain=0.01).replace("[ensemble]\nsamples = 3\n", ""))
    res = run(tmp_path / "d.toml", "--output", tmp_path / "one.h5", "--quiet", "--no-plots")
    assert res.returncode == 2 and "only an ensemble fills in" in res.stderr


def test_run_state_of_a_compressing_run_has_its_swollen_radii(tmp_path):
    """A run that compressed while shearing (phi 0.76 -> 0.77 over its 1.0 strain): prepare
    reads the checkpoint with the radii of the checkpoint's phi, not the initial ones, and
    compresses that flowing state further."""
    from systems import run_scene
    from parflow.scene import load_scene
    run = tmp_path / "r.h5"
    scene = load_scene(f'seed = 2\n[model]\nname = "suspension"\nN = 96\nphi = 0.76\n'
                       f'compress_rate = 0.01\ncompress_to = 0.80\n'
                       f'[[protocol.leg]]\ndirection = "forward"\nstrain = 1.0\n'
                       f'[output]\npath = "{run}"\n')
    assert run_scene(scene) == "complete"
    s, h0, gamma, radii, _ = prepare.load_run_state(str(run))
    assert gamma == pytest.approx(1.0, abs=1e-12)
    assert np.pi * np.sum(radii ** 2) / abs(np.linalg.det(h0)) == pytest.approx(0.77, abs=1e-12)
    X = prepare.rectangular_positions(s, h0, gamma)
    state = su.from_configuration(X, radii, np.diag(h0), 0.0)   # no overlap at these radii
    assert state.meta["phi"] == pytest.approx(0.77, abs=1e-12)
    pos, box1, info = prepare.compress(X, radii, np.diag(h0), 0.78)
    assert info["phi0"] == pytest.approx(0.77, abs=1e-12)
