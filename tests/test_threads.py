"""solver.parallel = "threads" (parflow.shear): under mpirun -n 2 the run goes on rank 0
alone with one BLAS thread per rank (one threaded CHOLMOD factorisation instead of the same
factorisation on every rank), the other rank waits without spinning.  The result equals the
one-rank run to round-off (threaded BLAS sums in another order); an error inside the run and
a signal reach every rank: one line, the right exit status, no hang."""
import os
import shutil
import signal
import subprocess
import sys

import h5py
import numpy as np
import pytest
from test_signals import _assert_stopped, _signal_run
from hang_guard import guard

pytestmark = pytest.mark.serial_only      # each test launches its own processes

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCENE = """
seed = 3
[model]
name = "network"
N = 400
z = 3.8
{network}
[[protocol.leg]]
direction = "forward"
sigma_above = 1e4
[solver]
parallel = "{parallel}"
"""


def _shear(*args, mpi=0, timeout=180):
    cmd = [sys.executable, "-m", "parflow.shear", *map(str, args), "--quiet", "--no-plots"]
    if mpi:
        cmd = [shutil.which("mpirun") or "mpirun", "-n", str(mpi)] + cmd
    return subprocess.run(cmd, capture_output=True, text=True, timeout=guard(timeout), cwd=ROOT,
                          env=dict(os.environ, PYTHONPATH=ROOT))


def _scene(tmp_path, parallel, network=""):
    p = tmp_path / f"{parallel}.toml"
    p.write_text(SCENE.format(parallel=parallel, network=network))
    return p


def test_threads_equal_one_rank(tmp_path):
    one, two = tmp_path / "one.h5", tmp_path / "two.h5"
    assert _shear(_scene(tmp_path, "auto"), "--output", one).returncode == 0
    res = _shear(_scene(tmp_path, "threads"), "--output", two, mpi=2)
    assert res.returncode == 0, res.stderr
    with h5py.File(one) as a, h5py.File(two) as b:
        assert b.attrs["status"] == "complete" and b.attrs["parallel"] == "threads"
        sa, sb = a["timeseries/sigma"][:], b["timeseries/sigma"][:]
        assert sa.size == sb.size > 20
        np.testing.assert_allclose(sb, sa, rtol=1e-8)


def test_threads_error_inside_the_run_reaches_every_rank(tmp_path):
    """The network file is opened inside the run, on rank 0 only: its error must end both
    ranks with exit 2 and one line."""
    scene = _scene(tmp_path, "threads", network=f'network_file = "{tmp_path}/missing.h5"')
    res = _shear(scene, "--output", tmp_path / "o.h5", mpi=2, timeout=120)
    assert res.returncode == 2, res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.startswith("parflow.shear: error:")]
    assert len(lines) == 1 and "missing.h5" in lines[0], res.stderr
    assert "Traceback" not in res.stderr


def test_threads_usr1_stops_the_run_with_a_checkpoint(tmp_path):
    scene = tmp_path / "long.toml"
    scene.write_text(SCENE.format(parallel="threads", network="").replace(
        "sigma_above = 1e4", "sigma_above = 1e9") + "[output]\ncheckpoint_every = 5\nflush_seconds = 0.2\n"
        + "[integrator]\ntol = 0.001\n")
    out = tmp_path / "o.h5"
    cmd = [shutil.which("mpirun") or "mpirun", "-n", "2", sys.executable, "-m", "parflow.shear",
           str(scene), "--output", str(out), "--quiet", "--no-plots"]
    code, err = _signal_run(cmd, out, signal.SIGUSR1)
    _assert_stopped(code, err, out, signal.SIGUSR1)


def test_threads_run_with_omega_min_exits(tmp_path):
    """In threads mode omega_min runs on rank 0 alone, while SLEPc's finalisation at exit is
    collective: SLEPc must be initialised on every rank (cli.init_petsc), or rank 0 hangs
    after the run (it did, with the others in MPI_Finalize).  A hang ends this test in its
    timeout."""
    scene = tmp_path / "omega.toml"
    scene.write_text(SCENE.format(parallel="threads", network="")
                     + "[observables]\nomega_min_every = 5\n")
    out = tmp_path / "o.h5"
    res = _shear(scene, "--output", out, mpi=2, timeout=120)
    assert res.returncode == 0, res.stderr
    with h5py.File(out) as f:
        assert f.attrs["status"] == "complete"
        om = f["timeseries/omega_min"][:]
        assert np.isfinite(om).sum() >= 3 and (om[np.isfinite(om)] > 0).all()
