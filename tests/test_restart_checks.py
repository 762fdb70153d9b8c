"""python -m parflow.shear --restart FILE on files whose checkpoint cannot be continued: a
checkpoint of another run grafted in, non-finite or missing values, counters that disagree
with the time series, a file cut short.  Each is refused with one line naming the file and
the problem, exit 2, no traceback, the file byte-for-byte as it was and no branch written,
on one rank and under mpirun -n 2.  Also: the first row of a suspension run obeys
sigma = sigma_fb + gap_work like every other row."""
import shutil

import h5py
import numpy as np
import pytest
from test_cli import GOOD, assert_user_error, shear

pytestmark = pytest.mark.serial_only      # each test launches its own processes

NETWORK = """
seed = 7
[model]
name = "network"
N = 128
z = 3.8
[[protocol.leg]]
direction = "forward"
sigma_above = 200
"""

SUSPENSION = """
seed = 3
[model]
name = "suspension"
N = 64
phi = 0.78
[[protocol.leg]]
direction = "forward"
strain = 0.02
[output]
checkpoint_every = 2
"""


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Small runs stopped by their step budget, each with a checkpoint: a chain (N = 50), the
    smallest network of the tests (N = 128) and a suspension (N = 64)."""
    d = tmp_path_factory.mktemp("runs")
    out = {}
    for name, text in (("chain", GOOD), ("network", NETWORK), ("suspension", SUSPENSION)):
        (d / f"{name}.toml").write_text(text)
        path = d / f"{name}.h5"
        res = shear(d / f"{name}.toml", "--output", path, "--max-steps", 5, "--quiet", "--no-plots")
        assert res.returncode == 0, res.stderr
        with h5py.File(path) as f:
            assert f.attrs["status"] == "budget" and int(f["checkpoint"].attrs["step"]) == 5
        out[name] = path
    return out


def _graft(dst, src):
    """Replace dst's checkpoint by src's (a checkpoint that belongs to another run)."""
    with h5py.File(src, "r") as s, h5py.File(dst, "a") as f:
        del f["checkpoint"]
        s.copy("checkpoint", f)


def _set_attr(key, value):
    def edit(f, runs):
        f["checkpoint"].attrs[key] = value
    return edit


def _del_attr(key):
    def edit(f, runs):
        del f["checkpoint"].attrs[key]
    return edit


def _array(key, fn):
    def edit(f, runs):
        a = fn(f["checkpoint"][key][()])
        del f["checkpoint"][key]
        f["checkpoint"][key] = a
    return edit


def _nan_s(s):
    s = s.copy()
    s[3, 1] = np.nan
    return s


def _file_model(f, runs):
    f.attrs["model"] = "network"


def _no_checkpoint(f, runs):
    del f["checkpoint"]


def _short_column(f, runs):
    f["timeseries/sigma"].resize((3,))


# (case id, base run, edit of an open copy or a run to graft, message fragment)
HOSTILE = [
    ("nan-positions", "chain", _array("s", _nan_s), "/checkpoint/s has 1 non-finite value"),
    ("inf-gamma", "chain", _set_attr("gamma", np.inf), "gamma = inf is not finite"),
    ("network-checkpoint-in-chain", "chain", "network",
     "/checkpoint/s has shape (128, 2) but /initial/s has (50, 2)"),
    ("chain-checkpoint-in-network", "network", "chain",
     "/checkpoint/s has shape (50, 2) but /initial/s has (128, 2)"),
    ("suspension-checkpoint-in-chain", "chain", "suspension",
     "written by the contacts engine (it has active_keys, vmax, collisions)"),
    ("chain-checkpoint-in-suspension", "suspension", "chain",
     "written by the bonded engine (it has tau, err_prev)"),
    ("no-step", "chain", _del_attr("step"), "the checkpoint has no step"),
    ("no-n-rows", "network", _del_attr("n_rows"), "the checkpoint has no n_rows"),
    ("step-not-a-number", "chain", _set_attr("step", "five"), "step = 'five' is not a number"),
    ("half-the-rows-of-s", "chain", _array("s", lambda s: s[: len(s) // 2]),
     "/checkpoint/s has shape (25, 2) but /initial/s has (50, 2)"),
    ("tau-of-another-size", "network", _array("tau", lambda t: t[:-7]),
     "/checkpoint/tau has shape"),
    ("positions-of-another-run", "chain", _array("s", lambda s: s[::-1].copy()),
     "do not keep this file's rods at their lengths"),
    ("no-checkpoint", "chain", _no_checkpoint, "has no checkpoint: it cannot be restarted"),
    ("file-model-differs", "chain", _file_model, "the file's model is 'network' but its scene's is 'chain'"),
    ("n-rows-beyond-time-series", "chain", _set_attr("n_rows", 1000),
     "n_rows = 1000 but the time series has 6 row(s)"),
    ("step-disagrees-with-time-series", "chain", _set_attr("step", 6),
     "step = 6 but the time series' step at row n_rows - 1 = 5 is 5"),
    ("column-shorter-than-n-rows", "chain", _short_column,
     "time-series column(s) sigma have fewer than n_rows = 6 rows"),
    ("leg-outside-the-scene", "chain", _set_attr("leg", 4), "leg = 4 but the scene has 1 leg(s)"),
    ("suspension-step-count", "suspension", _set_attr("steps", 99),
     "the suspension's step count 99 differs from the run's step = 5"),
    ("suspension-contact-keys", "suspension", _array("active_keys", lambda k: k + 64 * 64),
     "/checkpoint/active_keys are not contact keys"),
    ("suspension-phi-not-a-packing-fraction", "suspension", _set_attr("phi", 1.7),
     "checkpoint attribute phi = 1.7 is not a packing fraction in (0, 1)"),
]


def _hostile_copy(runs, tmp_path, case):
    _, base, edit, _ = case
    path = tmp_path / f"{case[0]}.h5"
    shutil.copyfile(runs[base], path)
    if isinstance(edit, str):
        _graft(path, runs[edit])
    else:
        with h5py.File(path, "a") as f:
            edit(f, runs)
    return path


@pytest.mark.parametrize("mpi", [0, 2], ids=["serial", "mpi2"])
@pytest.mark.parametrize("case", HOSTILE, ids=[c[0] for c in HOSTILE])
def test_hostile_checkpoint_is_refused_before_the_file_is_touched(runs, tmp_path, case, mpi):
    path = _hostile_copy(runs, tmp_path, case)
    before = path.read_bytes()
    res = shear("--restart", path, "--max-steps", 50, "--quiet", "--no-plots", mpi=mpi, timeout=120)
    assert_user_error(res, repr(str(path)), case[3])
    assert res.stderr.count("parflow.shear: error:") == 1
    assert "the file was not changed" in res.stderr
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]     # no .tmp, no plots


@pytest.mark.parametrize("mpi", [0, 2], ids=["serial", "mpi2"])
@pytest.mark.parametrize("name", ["network-checkpoint-in-chain", "no-step"])
def test_hostile_checkpoint_is_not_branched(runs, tmp_path, name, mpi):
    case = next(c for c in HOSTILE if c[0] == name)
    path = _hostile_copy(runs, tmp_path, case)
    before = path.read_bytes()
    branch = tmp_path / "branch.h5"
    res = shear("--restart", path, "--output", branch, "--quiet", "--no-plots", mpi=mpi)
    assert_user_error(res, repr(str(path)), case[3], "the file was not changed")
    assert path.read_bytes() == before
    assert not branch.exists() and not (tmp_path / "branch.h5.tmp").exists()


@pytest.mark.parametrize("mpi", [0, 2], ids=["serial", "mpi2"])
@pytest.mark.parametrize("damage", ["cut-in-half", "superblock-overwritten"])
def test_damaged_run_file(runs, tmp_path, damage, mpi):
    """A run file with the HDF5 signature but cut short (a copy that did not finish, a full
    disk) or damaged is reported as such, not as "not an HDF5 file"."""
    data = runs["chain"].read_bytes()
    path = tmp_path / "damaged.h5"
    if damage == "cut-in-half":
        data = data[: len(data) // 2]
    else:
        data = data[:8] + bytes(64) + data[72:]       # signature kept, superblock zeroed
    path.write_bytes(data)
    res = shear("--restart", path, "--quiet", "--no-plots", mpi=mpi)
    assert_user_error(res, repr(str(path)), "truncated HDF5 file", f"({len(data)} bytes",
                      "restore it from a copy")
    if damage == "cut-in-half":
        assert "is a truncated HDF5 file" in res.stderr
        assert f"of its {len(runs['chain'].read_bytes())})" in res.stderr
    assert path.read_bytes() == data
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]


def test_not_hdf5_at_all(tmp_path):
    path = tmp_path / "x.h5"
    path.write_bytes(b"\x89HDF but not really" + bytes(600))     # no signature at 0 or 512
    res = shear("--restart", path, "--quiet", "--no-plots")
    assert_user_error(res, "is not an HDF5 file", "no HDF5 signature")
    res = shear("--restart", tmp_path, "--quiet", "--no-plots")
    assert_user_error(res, "is a directory")


def test_user_block_file_is_recognised(tmp_path):
    """An HDF5 file with a 512-byte user block has its signature at byte 512: it is HDF5
    (here not a run file), not "not an HDF5 file"."""
    path = tmp_path / "ub.h5"
    with h5py.File(path, "w", userblock_size=512) as f:
        f["a"] = 1
    assert_user_error(shear("--restart", path, "--quiet", "--no-plots"), "is not a parflow run file")


@pytest.mark.parametrize("name, mpi", [("chain", 0), ("chain", 2), ("network", 0),
                                       ("suspension", 0), ("suspension", 2)])
def test_good_checkpoints_still_restart(runs, tmp_path, name, mpi):
    """The checks refuse none of the checkpoints runs write (serial and 2-rank restarts)."""
    path = tmp_path / f"{name}.h5"
    shutil.copyfile(runs[name], path)
    res = shear("--restart", path, "--max-steps", 8, "--quiet", "--no-plots", mpi=mpi)
    assert res.returncode == 0, res.stderr
    with h5py.File(path) as f:
        assert f.attrs["restarted_at_step"] == 5
        ts = f["timeseries/step"][:]
        assert f.attrs["status"] in ("budget", "complete") and ts[-1] > 5
        np.testing.assert_array_equal(ts, np.arange(len(ts)))


@pytest.mark.parametrize("mpi", [0, 2], ids=["serial", "mpi2"])
def test_suspension_first_row_obeys_the_stress_identity(tmp_path, mpi):
    """sigma = |V_na|^2/Omega = sigma_fb + gap_work (LCP complementarity) at every row,
    the first one included: its gap work is that of the forces the first row reports (the
    first step's), not 0."""
    scene = tmp_path / "s.toml"
    scene.write_text(SUSPENSION)
    out = tmp_path / "s.h5"
    res = shear(scene, "--output", out, "--quiet", "--no-plots", mpi=mpi)
    assert res.returncode == 0, res.stderr
    with h5py.File(out) as f:
        ts = f["timeseries"]
        sigma, fb, gw = ts["sigma"][:], ts["sigma_fb"][:], ts["gap_work"][:]
        assert ts["dgamma"][0] == 0.0 and len(sigma) > 3
    np.testing.assert_allclose(fb + gw, sigma, rtol=1e-9)
    assert gw[0] != 0.0            # this start has open gaps that the first step closes
