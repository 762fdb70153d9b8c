"""Stopping a run with a signal: serially, under mpirun, through scripts/mpirun-parflow and
`make run` (docs/output.md "Signals").

Each case starts a long chain run, waits until the file holds a few time-series rows, sends
one signal and checks: the exit status, one line naming the signal, no traceback, the file
left with status "interrupted" and a checkpoint of the last time-series row, and that
--restart continues from it.
"""
import os
import shutil
import signal
import subprocess
import sys
import time

import h5py
import pytest
from hang_guard import guard

pytestmark = pytest.mark.serial_only      # each test launches its own processes

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
LAUNCHER = os.path.join(ROOT, "scripts", "mpirun-parflow")

# ~1e4 steps of a few ms each: runs for several seconds, checkpoints every 5 steps
SCENE = """
seed = 1
[model]
name = "chain"
N = 200
epsilon = 0.1
mu = 0
[[protocol.leg]]
direction = "forward"
V2_above = 1e12
[output]
checkpoint_every = 5
flush_seconds = 0.2
"""

STOPPED = {signal.SIGTERM: (143, "terminated"), signal.SIGUSR1: (143, "terminated"),
           signal.SIGINT: (130, "interrupted"), signal.SIGUSR2: (130, "interrupted")}


def _env():
    return dict(os.environ, PYTHONPATH=ROOT)


def _mpirun():
    return shutil.which("mpirun") or "mpirun"


def _wait_for_rows(proc, out, rows=5, timeout=guard(60.0)):
    """Until the file holds more than ``rows`` time-series rows (the run loop is going)."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        assert proc.poll() is None, f"the run ended before it was signalled: {proc.stderr.read()}"
        try:
            with h5py.File(out, "r") as f:
                if f["timeseries/step"].shape[0] > rows:
                    return
        except (OSError, KeyError):      # not written yet, or being flushed
            pass
        time.sleep(0.1)
    raise AssertionError(f"no progress in {out} after {timeout} s")


def _signal_run(cmd, out, sig, group=False):
    """Run ``cmd``, send ``sig`` once it has made progress (to its whole process group if
    ``group``: what a terminal's Ctrl-C does); returns (exit status, stderr)."""
    # SIGINT at its default in the child even when the suite runs in a background job (which
    # inherits it ignored; parflow and the shell keep an ignored SIGINT ignored)
    proc = subprocess.Popen(cmd, env=_env(), cwd=ROOT, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, start_new_session=group,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        _wait_for_rows(proc, out)
        if group:
            os.killpg(proc.pid, sig)
        else:
            proc.send_signal(sig)
        _, err = proc.communicate(timeout=guard(60))
    finally:
        if proc.poll() is None:          # (a failed assertion above: leave nothing running)
            proc.kill()
            proc.communicate()
    return proc.returncode, err


def _assert_stopped(code, err, out, sig, expect_code=None, restart_cmd=()):
    exit_code, word = STOPPED[sig]
    assert code == (exit_code if expect_code is None else expect_code), err
    assert err.count(f"parflow.shear: {word}") == 1, err
    assert "Traceback" not in err and "exited on signal" not in err, err
    with h5py.File(out) as f:
        assert f.attrs["status"] == "interrupted", f.attrs["message"]
        assert "--restart" in f.attrs["message"] and "mid-step" not in f.attrs["message"]
        n = f["timeseries/step"].shape[0]
        assert n > 5
        assert int(f["checkpoint"].attrs["step"]) == int(f["timeseries/step"][-1]) == n - 1
    res = subprocess.run([*restart_cmd, sys.executable, "-m", "parflow.shear", "--restart",
                          str(out), "--max-steps", str(n + 3), "--no-plots", "--quiet"],
                         env=_env(), cwd=ROOT, capture_output=True, text=True, timeout=guard(120))
    assert res.returncode == 0, res.stderr
    with h5py.File(out) as f:
        assert f.attrs["status"] == "budget" and int(f["timeseries/step"][-1]) == n + 3


def _shear_cmd(tmp_path):
    scene = tmp_path / "s.toml"
    scene.write_text(SCENE)
    out = tmp_path / "o.h5"
    return [sys.executable, "-m", "parflow.shear", str(scene), "--output", str(out),
            "--quiet", "--no-plots"], out


@pytest.mark.parametrize("sig", [signal.SIGUSR1, signal.SIGUSR2])
def test_usr_signals_stop_like_term_and_int(tmp_path, sig):
    """Serially, SIGUSR1 is taken like SIGTERM (143) and SIGUSR2 like SIGINT (130)."""
    cmd, out = _shear_cmd(tmp_path)
    code, err = _signal_run(cmd, out, sig)
    _assert_stopped(code, err, out, sig)


def test_usr1_to_mpirun_reaches_every_rank(tmp_path):
    """`kill -USR1 <mpirun>`: Open MPI relays SIGUSR1 to the ranks at once; they stop at the
    same step with a checkpoint and mpirun exits with their status, 143."""
    cmd, out = _shear_cmd(tmp_path)
    code, err = _signal_run([_mpirun(), "-n", "2", *cmd], out, signal.SIGUSR1)
    _assert_stopped(code, err, out, signal.SIGUSR1)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_launcher_relays_term_and_int(tmp_path, sig):
    """scripts/mpirun-parflow, sent SIGTERM / SIGINT, has the ranks stop cleanly and exits
    143 / 130; the two-rank run continues with --restart through the launcher."""
    cmd, out = _shear_cmd(tmp_path)
    code, err = _signal_run([LAUNCHER, "-n", "2", *cmd], out, sig)
    _assert_stopped(code, err, out, sig,
                    restart_cmd=(LAUNCHER, "-n", "2") if sig == signal.SIGTERM else ())


def test_launcher_without_mpirun(tmp_path):
    res = subprocess.run([LAUNCHER, "-n", "2", "true"], capture_output=True, text=True,
                         env=dict(_env(), MPIRUN=str(tmp_path / "no-mpirun")), timeout=guard(30))
    assert res.returncode == 2
    assert res.stderr.startswith("mpirun-parflow: error: ") and "not found" in res.stderr
    assert len(res.stderr.splitlines()) == 1


def test_ctrl_c_on_make_run(tmp_path):
    """Ctrl-C on `make run` (SIGINT to the terminal's whole foreground process group: make
    and the launcher; mpirun and its ranks are in groups of their own) stops the run
    with a checkpoint; make reports status 130 and dies of SIGINT."""
    if subprocess.run(["make", "-q", "-C", ROOT, "setup"], capture_output=True).returncode != 0:
        pytest.skip("make setup is not up to date (make run would run it first)")
    scene = tmp_path / "s.toml"
    scene.write_text(SCENE)
    out = tmp_path / "o.h5"
    cmd = ["make", "--no-print-directory", "-C", ROOT, "run", f"SCENE={scene}",
           f"ARGS=--output {out} --quiet --no-plots"]
    code, err = _signal_run(cmd, out, signal.SIGINT, group=True)
    assert "Error 130" in err, err
    _assert_stopped(code, err, out, signal.SIGINT, expect_code=-signal.SIGINT)
