"""Bad input to python -m parflow.shear: one clear line, non-zero exit, no file, no hang."""
import os
import shutil
import subprocess
import sys

import h5py
import numpy as np
import pytest
from hang_guard import guard

pytestmark = pytest.mark.serial_only      # each test launches its own processes

GOOD = """
seed = 1
[model]
name = "chain"
N = 50
epsilon = 0.1
mu = 0
[[protocol.leg]]
direction = "forward"
V2_above = 100.0
"""


def shear(*args, cwd=None, timeout=120, mpi=0):
    cmd = [sys.executable, "-m", "parflow.shear", *map(str, args)]
    if mpi:
        cmd = [shutil.which("mpirun") or "mpirun", "-n", str(mpi)] + cmd
    env = dict(os.environ, PYTHONPATH=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    return subprocess.run(cmd, capture_output=True, text=True, timeout=guard(timeout), cwd=cwd, env=env)


def scene_file(tmp_path, text, name="s.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def assert_user_error(res, *fragments):
    assert res.returncode == 2, res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.startswith("parflow.shear: error:")]
    assert len(lines) == 1, res.stderr
    assert "Traceback" not in res.stderr
    for frag in fragments:
        assert frag in lines[0], lines[0]


BAD = [
    ("N = 50\nepsilon = [", "malformed TOML"),
    (GOOD.replace("epsilon = 0.1", "epsilom = 0.1"), "did you mean 'epsilon'"),
    (GOOD.replace("[model]", "[modle]"), "did you mean 'model'"),
    (GOOD.replace("N = 50", "N = 2"), "model.N = 2 is out of range"),
    (GOOD.replace("N = 50", 'N = "ten"'), "model.N must be of type int"),
    (GOOD.replace("epsilon = 0.1", "epsilon = 0.0"), "model.epsilon = 0.0 is out of range"),
    (GOOD.replace("epsilon = 0.1", "epsilon = -0.1"), "model.epsilon"),
    (GOOD.replace("mu = 0", "mu = 1"), "model.mu = 1 is out of range: must be spectral exponent mu (even"),
    (GOOD.replace("V2_above = 100.0", "V2_above = -5.0"), "protocol.leg[0].V2_above = -5.0 is out of range"),
    (GOOD.replace('direction = "forward"', 'direction = "sideways"'), "'forward' or 'reverse'"),
    (GOOD.replace("V2_above = 100.0", ""), "has no stop rule"),
    (GOOD.replace('name = "chain"', 'name = "gas"'), "model.name must be one of"),
    (GOOD + '\n[solver]\npreset = "fastest"\n', "solver.preset"),
]


@pytest.mark.parametrize("text,message", BAD)
def test_bad_scene(tmp_path, text, message):
    out = tmp_path / "o.h5"
    res = shear(scene_file(tmp_path, text), "--output", out)
    assert_user_error(res, message)
    assert not out.exists()


def test_missing_scene_file(tmp_path):
    assert_user_error(shear(tmp_path / "nope.toml"), "cannot read scene file")


def test_unwritable_output(tmp_path):
    blocker = tmp_path / "afile"
    blocker.write_text("x")
    res = shear(scene_file(tmp_path, GOOD), "--output", blocker / "sub" / "o.h5")
    assert_user_error(res, "cannot create the output folder")


def test_existing_output_needs_overwrite(tmp_path):
    out = tmp_path / "o.h5"
    out.write_bytes(b"precious")
    res = shear(scene_file(tmp_path, GOOD), "--output", out)
    assert_user_error(res, "exists: pass --overwrite")
    assert out.read_bytes() == b"precious"
    res = shear(scene_file(tmp_path, GOOD), "--output", out, "--overwrite", "--quiet")
    assert res.returncode == 0, res.stderr
    with h5py.File(out) as f:
        assert f.attrs["status"] == "complete"
    assert not (tmp_path / "o.h5.tmp").exists()
    figures = list((tmp_path / "o_plots").glob("*.png"))      # the main job draws its figures
    assert any(p.name == "stress_strain.png" for p in figures), figures


def test_restart_from_a_file_that_is_not_a_run(tmp_path):
    txt = tmp_path / "x.h5"
    txt.write_text("not hdf5")
    assert_user_error(shear("--restart", txt), "is not an HDF5 file")
    other = tmp_path / "y.h5"
    with h5py.File(other, "w") as f:
        f["a"] = 1
    assert_user_error(shear("--restart", other), "is not a parflow run file")
    assert_user_error(shear("--restart", tmp_path / "none.h5"), "does not exist")


def test_unused_petsc_option_warns(tmp_path):
    out = tmp_path / "o.h5"
    res = shear(scene_file(tmp_path, GOOD + '\n[petsc]\ntau_pc_factor_nonsense = 3\n'),
                "--output", out, "--no-plots", "-tau_ksp_bogus", "1")
    assert res.returncode == 0, res.stderr
    assert "not used" in res.stderr and "-tau_pc_factor_nonsense" in res.stderr \
        and "-tau_ksp_bogus" in res.stderr


def test_command_line_petsc_option_wins_over_scene(tmp_path):
    out = tmp_path / "o.h5"
    text = GOOD + '\n[petsc]\ntau_pc_factor_mat_solver_type = "petsc"\n'
    res = shear(scene_file(tmp_path, text), "--output", out, "--quiet", "--no-plots",
                "-tau_pc_factor_mat_solver_type", "cholmod")
    assert res.returncode == 0, res.stderr
    with h5py.File(out) as f:
        assert "cholmod" in f.attrs["solver"]


def test_bad_scene_under_mpirun_does_not_hang(tmp_path):
    out = tmp_path / "o.h5"
    res = shear(scene_file(tmp_path, GOOD.replace("N = 50", "N = 1")), "--output", out,
                mpi=2, timeout=60)
    assert res.returncode != 0
    assert res.stderr.count("parflow.shear: error: model.N = 1 is out of range") == 1
    assert not out.exists()


def test_two_rank_run_completes(tmp_path):
    out = tmp_path / "o.h5"
    res = shear(scene_file(tmp_path, GOOD), "--output", out, "--no-plots", mpi=2, timeout=120)
    assert res.returncode == 0, res.stderr
    with h5py.File(out) as f:
        assert f.attrs["n_ranks"] == 2 and f.attrs["status"] == "complete"


def _signal_mid_run(tmp_path, sig):
    """Start a long serial chain run, send ``sig`` once it has flushed a few rows; returns
    (exit code, stderr, output path)."""
    import time
    out = tmp_path / "o.h5"
    text = GOOD.replace("N = 50", "N = 3000").replace("V2_above = 100.0", "V2_above = 1e12") + \
        "\n[output]\nflush_seconds = 0.2\n"
    env = dict(os.environ, PYTHONPATH=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    cmd = [sys.executable, "-m", "parflow.shear", str(scene_file(tmp_path, text)),
           "--output", str(out), "--quiet", "--no-plots"]
    import signal
    # SIGINT at its default in the child even when this test runs in a background job (there
    # it is inherited as ignored, and parflow rightly keeps an ignored SIGINT ignored)
    proc = subprocess.Popen(cmd, env=env, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.time() + 60
        while time.time() < deadline:
            time.sleep(0.5)
            try:
                with h5py.File(out, "r") as f:
                    if f["timeseries/step"].shape[0] > 5:
                        break
            except (OSError, KeyError):       # not written yet
                pass
        time.sleep(0.7)
    finally:
        proc.send_signal(sig)
        try:
            _, err = proc.communicate(timeout=guard(60))
        except subprocess.TimeoutExpired:
            proc.kill()                   # no run left behind by a failing test
            proc.communicate()
            raise
    return proc.returncode, err, out


def test_killed_run_leaves_a_readable_file(tmp_path):
    """SIGKILL in the middle of a run: the file is the complete file of the last flush."""
    import signal
    _, _, out = _signal_mid_run(tmp_path, signal.SIGKILL)
    with h5py.File(out) as f:                        # opens: not corrupt
        assert f.attrs["status"] == "running"
        n = f["timeseries/step"].shape[0]
        assert n > 5 and all(f["timeseries"][k].shape == (n,) for k in f["timeseries"])


@pytest.mark.parametrize("name", ["SIGTERM", "SIGINT"])
def test_signal_stops_with_checkpoint_and_status(tmp_path, name):
    """SIGTERM (kill, a scheduler's time limit) or Ctrl-C on a serial run: exit 143 / 130,
    status 'interrupted', a checkpoint at the end of the last whole step, which is the last
    time-series row; the run continues from it with --restart.  (Under mpirun, which does
    not pass SIGTERM/SIGINT on to its ranks: tests/test_signals.py.)"""
    import signal
    code, err, out = _signal_mid_run(tmp_path, getattr(signal, name))
    word, exit_code = ("terminated", 143) if name == "SIGTERM" else ("interrupted", 130)
    assert code == exit_code and err.count(word) == 1, err
    with h5py.File(out) as f:
        assert f.attrs["status"] == "interrupted" and "--restart" in f.attrs["message"]
        n = f["timeseries/step"].shape[0]
        assert int(f["checkpoint"].attrs["step"]) == int(f["timeseries/step"][-1]) == n - 1
    res = shear("--restart", out, "--max-steps", n + 3, "--no-plots", "--quiet")
    assert res.returncode == 0, res.stderr
    with h5py.File(out) as f:
        assert f.attrs["status"] == "budget" and f["timeseries/step"][-1] == n + 3


def test_stop_signals_are_taken_at_step_boundaries():
    """StopSignals alone: outside a run loop a signal raises at once; inside, it waits for
    check(); a second one raises at once, marked mid-step (no checkpoint then)."""
    from parflow.state import StopSignals, Terminated
    stops = StopSignals()
    with pytest.raises(KeyboardInterrupt):
        stops.handle(1)
    with stops.deferred():
        stops.handle(2)                        # recorded, not raised
        with pytest.raises(Terminated) as exc:
            stops.check()
        assert exc.value.collective and not exc.value.mid_step
        stops.check()                          # taken once
        stops.handle(1)
        with pytest.raises(Terminated) as exc:
            stops.handle(2)
        assert exc.value.mid_step and not exc.value.collective
        stops.handle(2)
    assert stops.pending == 0                  # a signal in the last step is dropped with it


def test_every_scene_in_runs_is_valid():
    """Each runs/*.toml parses and validates (keys, types, ranges, model parameters)."""
    import glob

    from parflow.scene import load_scene
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    paths = sorted(glob.glob(os.path.join(root, "runs", "*.toml")))
    assert len(paths) >= 10
    for p in paths:
        with open(p) as f:
            scene = load_scene(f.read(), p)
        assert scene["protocol"]["leg"], p


def test_eta_window_follows_the_leg():
    """A leg toward a stress target takes its ETA from the last 30 s (progress slows near
    jamming); a leg that stops on strain alone from STRAIN_ETA_WINDOW, so that sigma's swings
    in a flowing suspension do not throw it about."""
    from parflow.protocol import STRAIN_ETA_WINDOW, Leg
    assert Leg(dict(direction="forward", sigma_above=1e6), 0, 1).eta().window == 30.0
    assert Leg(dict(direction="reverse", V2_below=10.0, strain=0.1), 0, 1).eta().window == 30.0
    strain = Leg(dict(direction="forward", strain=3.0), 0, 1).eta()
    assert strain.window == STRAIN_ETA_WINDOW >= 300.0
    # 1 s a step, the strain rate swinging 4x every 100 s: the long window keeps the ETA
    # within 30 % of the mean rate's, a 30 s window does not
    short = Leg(dict(direction="forward", sigma_above=1e6), 0, 1).eta()
    frac, late, late_short = 0.0, [], []
    for k in range(1, 1500):
        frac += (4e-4 if (k // 100) % 2 else 1e-4) / 2.0
        e, s = strain.update(float(k), frac, k), short.update(float(k), frac, k)
        if k > 700:
            late.append(e * 1.25e-4 / (1 - frac))
            late_short.append(s * 1.25e-4 / (1 - frac))
    assert max(abs(np.array(late) - 1)) < 0.3 and max(abs(np.array(late_short) - 1)) > 0.5


def test_eta_window_spans_enough_steps():
    """The leg ETA uses at least 30 s and 30 steps of history: slow steps whose progress
    goes up and down do not make it jump."""
    from parflow.protocol import EtaEstimate
    eta = EtaEstimate(window=30.0, min_steps=30)
    # 15 s per step; progress 0.001 per step on average, alternating +0.003 / -0.001
    frac, out = 0.0, []
    for k in range(1, 200):
        frac += 0.003 if k % 2 else -0.001
        out.append(eta.update(15.0 * k, frac, k))
    rate = 0.001 / 15.0
    late = np.array(out[100:])
    late = late[np.isfinite(late)]
    expect = (1.0 - frac) / rate
    assert late.size > 50 and np.all(np.abs(late[-10:] / expect - 1) < 0.2)
    # a pure 30 s window would have swung between "done soon" and "never"
    short = EtaEstimate(window=30.0, min_steps=0)
    vals = [short.update(15.0 * k, f, k) for k, f in enumerate(np.cumsum(
        [0.003 if k % 2 else -0.001 for k in range(1, 200)]), start=1)]
    assert np.nanmax(vals[100:]) / np.nanmin(vals[100:]) > 2


def test_progress_pace_reads_in_seconds_a_step_when_slow():
    """The progress line's speed: steps a second from one a second up, seconds a step below
    (an N = 10^6 network step takes ~20 s: "0.0 steps/s" said nothing)."""
    from parflow.protocol import pace
    assert pace(4.56) == "4.6 steps/s" and pace(1.0) == "1.0 steps/s"
    assert pace(0.05) == "20.0 s/step" and pace(0.5) == "2.0 s/step"
    assert pace(0.0) == "0.0 steps/s"
