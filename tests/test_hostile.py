"""Hostile input to the entry points (parflow.shear, parflow.prepare, parflow.modes,
parflow.spectrum): each is refused with one line ``parflow.<cmd>: error: ...`` naming the
problem, exit status 2, no traceback, no file written, and no hang under ``mpirun -n 2``."""
import os
import shutil
import subprocess
import sys

import h5py
import pytest
from test_cli import GOOD
from hang_guard import guard

pytestmark = pytest.mark.serial_only      # each test launches its own processes

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def cli(module, *args, mpi=0, timeout=120, cwd=None):
    cmd = [sys.executable, "-m", f"parflow.{module}", *map(str, args)]
    if mpi:
        cmd = [shutil.which("mpirun") or "mpirun", "-n", str(mpi)] + cmd
    env = dict(os.environ, PYTHONPATH=ROOT)
    return subprocess.run(cmd, capture_output=True, text=True, timeout=guard(timeout), cwd=cwd, env=env)


def shear(*args, **kw):
    return cli("shear", *args, **kw)


def files(folder):
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


def assert_refused(res, prog, *fragments):
    """Exit 2, exactly one ``parflow.<prog>: error:`` line holding every fragment, no traceback."""
    assert res.returncode == 2, res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.startswith(f"parflow.{prog}: error:")]
    assert len(lines) == 1, res.stderr
    assert "Traceback" not in res.stderr and "petsc4py.PETSc.Error" not in res.stderr, res.stderr
    for frag in fragments:
        assert frag in lines[0], lines[0]
    return lines[0]


def write(path, data):
    (path.write_bytes if isinstance(data, bytes) else path.write_text)(data)
    return path


# ------------------------------------------------------------------ scene files not UTF-8

NOT_UTF8 = [
    pytest.param(b'title = "caf\xe9 au lait"\n' + GOOD.encode(), "line 1, column 13", id="latin1-title"),
    pytest.param(bytes(range(128, 256)) * 4, "byte 0x80 at line 1, column 1", id="binary-junk"),
    pytest.param(GOOD.encode().replace(b"mu = 0", b"mu = 0 # \xff"), "byte 0xff", id="junk-in-comment"),
]


@pytest.mark.parametrize("mpi", [0, 2])
@pytest.mark.parametrize("data, where", NOT_UTF8)
def test_scene_not_utf8(tmp_path, data, where, mpi):
    scene = write(tmp_path / "s.toml", data)
    before = files(tmp_path)
    res = shear(scene, "--output", tmp_path / "o.h5", mpi=mpi)
    assert_refused(res, "shear", "is not UTF-8 text", where, "save the file as UTF-8")
    assert files(tmp_path) == before


def test_scene_file_too_large_or_not_a_file(tmp_path):
    big = write(tmp_path / "big.toml", "# " + "x" * (2 << 20) + "\n" + GOOD)
    assert_refused(shear(big, "--output", tmp_path / "o.h5"), "shear", "larger than 1 MB")
    assert_refused(shear(tmp_path, "--output", tmp_path / "o.h5"), "shear",
                   "cannot read scene file", "Is a directory")
    assert not (tmp_path / "o.h5").exists()


# ------------------------------------------------------------------ absurd sizes

SIZES = {"chain": "", "network": "z = 3.8\n", "suspension": "phi = 0.8\n"}


def sized_scene(model, n):
    return (f'[model]\nname = "{model}"\nN = {n}\n{SIZES[model]}'
            f'[[protocol.leg]]\ndirection = "forward"\nstrain = 0.01\n')


@pytest.mark.parametrize("n", [10 ** 9, 10 ** 12, 2 ** 70])
@pytest.mark.parametrize("model", sorted(SIZES))
def test_absurd_size_refused_before_allocating(tmp_path, model, n):
    scene = write(tmp_path / "s.toml", sized_scene(model, n))
    before = files(tmp_path)
    res = shear(scene, "--output", tmp_path / "o.h5", timeout=60)
    line = assert_refused(res, "shear", "model.N =", f"a {model} of that size would need about",
                          "this machine has", "choose model.N <=")
    assert "MemoryError" not in res.stderr and "Maximum allowed size" not in res.stderr, line
    assert files(tmp_path) == before


def test_absurd_size_under_mpirun(tmp_path):
    scene = write(tmp_path / "s.toml", sized_scene("network", 10 ** 12))
    res = shear(scene, "--output", tmp_path / "o.h5", mpi=2, timeout=60)
    assert_refused(res, "shear", "would need about", "on each of 2 ranks")
    assert not (tmp_path / "o.h5").exists()


def test_memory_estimate_against_a_given_machine():
    """The estimate scales with N and with the ranks that hold a replicated system; the check
    refuses only what does not fit (here a 1 GB machine), and says what would."""
    from parflow.models import check_memory, machine_memory, memory_needed
    from parflow.state import InputError
    have, where = machine_memory()
    assert have > 0 and where
    one = memory_needed("network", 10 ** 5)
    assert memory_needed("network", 10 ** 6) > 5 * one
    assert memory_needed("network", 10 ** 5, n_ranks=2) == pytest.approx(2 * one)
    check_memory("chain", {"N": 10 ** 5}, available=(1e9, "test"))
    with pytest.raises(InputError, match=r"model.N = 10,000,000: .* more than the 1 GB this "
                                         r"machine has \(test\); choose model.N <= 9\d\d,\d\d\d"):
        check_memory("chain", {"N": 10 ** 7}, available=(1e9, "test"))
    with pytest.raises(InputError, match="1.181e\\+21"):
        check_memory("suspension", {"N": 2 ** 70}, n_ranks=2)


# ------------------------------------------------------------------ PETSc option values

BAD_OPTIONS = [
    pytest.param(["-tau_pc_type", "nonsense"], "-tau_pc_type nonsense",
                 "Unable to find requested PC type nonsense", id="pc_type"),
    pytest.param(["-tau_ksp_type", "nonsense"], "-tau_ksp_type nonsense",
                 "Unable to find requested KSP type nonsense", id="ksp_type"),
    pytest.param(["-tau_ksp_max_it", "abc"], "-tau_ksp_max_it abc",
                 "Input string abc has no integer value", id="ksp_max_it"),
    pytest.param(["-tau_pc_factor_mat_solver_type", "nonsense"],
                 "-tau_pc_factor_mat_solver_type nonsense", "Could not locate solver type nonsense",
                 id="factor_package"),
    pytest.param(["-spec_eps_type", "nonsense"], "-spec_eps_type nonsense",
                 "Unknown EPS type given: nonsense", id="eps_type"),
]


@pytest.mark.parametrize("mpi", [0, 2])
@pytest.mark.parametrize("where", ["command line", "scene"])
@pytest.mark.parametrize("option, named, petsc_says", BAD_OPTIONS)
def test_petsc_option_values_rejected(tmp_path, option, named, petsc_says, where, mpi):
    if mpi and option[0] not in ("-tau_pc_type", "-tau_ksp_max_it", "-spec_eps_type"):
        pytest.skip("the collective path is the same for every option")
    out = tmp_path / "o.h5"
    if where == "scene":
        text = GOOD + f'\n[petsc]\n{option[0][1:]} = "{option[1]}"\n'
        res = shear(write(tmp_path / "s.toml", text), "--output", out, mpi=mpi)
        source = "scene's [petsc] table"
    else:
        res = shear(write(tmp_path / "s.toml", GOOD), "--output", out, *option, mpi=mpi)
        source = "command line"
    assert_refused(res, "shear", f"PETSc rejected option {named} ({source})", petsc_says)
    assert not out.exists() and not (tmp_path / "o.h5.tmp").exists()


@pytest.mark.parametrize("entry, message", [
    ('"" = 1', "a PETSc option name is letters"),
    ('"tau ksp_type" = "cg"', "a PETSc option name is letters"),
    ('tau_pc_type = "lu cholesky"', "an option value is one word"),
    ('tau_pc_type = "-lu"', "an option value is one word"),
    ("tau_ksp_rtol = nan", "must be finite"),
    ("tau = { pc_type = 'lu', ksp = { type = 'c g' } }", "an option value is one word"),
    ("tau = { pc_type = 'lu' }\ntau_pc_type = 'cholesky'", "given twice"),
])
def test_petsc_table_entries_petsc_would_misread(entry, message):
    """Keys and values that PETSc's option parser would split or drop silently."""
    from parflow.scene import load_scene
    from parflow.state import InputError
    with pytest.raises(InputError, match=message):
        load_scene(GOOD + f"\n[petsc]\n{entry}\n")


def test_good_petsc_options_still_run_and_unused_ones_still_warn(tmp_path):
    out = tmp_path / "o.h5"
    res = shear(write(tmp_path / "s.toml", GOOD), "--output", out, "--no-plots",
                "-tau_ksp_max_it", "5", "-tau_pc_factor_mat_solver_type", "petsc",
                "-spec_eps_ncv", "8")
    assert res.returncode == 0, res.stderr
    # the check parses them on scratch objects: the real solver's use is still what counts
    assert "not used" in res.stderr and "-tau_ksp_max_it" in res.stderr, res.stderr  # PREONLY skips it
    with h5py.File(out) as f:
        assert "parflowcheck" not in f.attrs["petsc_options"]
        assert "tau_pc_factor_mat_solver_type petsc" in f.attrs["petsc_options"]
    # eigensolver options bring SLEPc up on every rank, not only on the one that checks them
    res = shear(write(tmp_path / "s.toml", GOOD), "--output", out, "--overwrite", "--quiet",
                "--no-plots", "-spec_eps_ncv", "8", mpi=2, timeout=60)
    assert res.returncode == 0, res.stderr


# ------------------------------------------------------------------ output paths

BAD_OUTPUT = [
    pytest.param(["--output", "/proc/o.h5"], "cannot create files in the output folder '/proc'", id="proc"),
    pytest.param(["--output", "/proc/nowhere/o.h5"], "cannot create the output folder", id="proc-sub"),
    pytest.param(["--output", "OUT/newdir/"], "names a folder, not a file", id="trailing-slash"),
    pytest.param(["--output", ""], "--output is empty", id="empty"),
    pytest.param(["--output", "   "], "--output is empty", id="blank"),
    pytest.param(["--output", "OUT/" + "x" * 300 + ".h5"], "is too long (303 characters)", id="long-name"),
    pytest.param(["--output", "/dev/null", "--overwrite"], "is not a regular file", id="device"),
    pytest.param(["--output", "SCENE", "--overwrite"], "is the scene file itself", id="scene-itself"),
]


@pytest.mark.parametrize("args, message", BAD_OUTPUT)
def test_output_path_that_cannot_be_written(tmp_path, args, message):
    scene = write(tmp_path / "s.toml", GOOD)
    args = [str(scene) if a == "SCENE" else a.replace("OUT", str(tmp_path)) for a in args]
    before = files(tmp_path)
    assert_refused(shear(scene, *args), "shear", message)
    assert files(tmp_path) == before
    assert scene.read_text() == GOOD


def test_output_paths_in_the_scene_and_under_mpirun(tmp_path):
    scene = write(tmp_path / "s.toml", GOOD + '\n[output]\npath = "/proc/o.h5"\n')
    assert_refused(shear(scene), "shear", "cannot create files in the output folder '/proc'")
    assert_refused(shear(scene, mpi=2), "shear", "cannot create files in the output folder '/proc'")
    scene = write(tmp_path / "s.toml", GOOD + '\n[output]\npath = ""\n')
    assert_refused(shear(scene), "shear", "output.path", "a non-empty path")
    assert files(tmp_path) == ["s.toml"]


# ------------------------------------------------------------------ scenes without a model

@pytest.mark.parametrize("mpi", [0, 2])
def test_scene_without_model_table(tmp_path, mpi):
    text = GOOD[GOOD.index("[[protocol.leg]]"):]
    res = shear(write(tmp_path / "s.toml", text), "--output", tmp_path / "o.h5", mpi=mpi)
    assert_refused(res, "shear", "has no [model] table", "name =")
    assert not (tmp_path / "o.h5").exists()


def test_model_without_name_and_the_defaults_that_must_keep_working(tmp_path):
    res = shear(write(tmp_path / "s.toml", GOOD.replace('name = "chain"\n', "")),
                "--output", tmp_path / "o.h5")
    assert_refused(res, "shear", "model.name is missing")
    from parflow.scene import DEFAULT_SCENE, load_scene
    assert load_scene(DEFAULT_SCENE)["model"]["N"] == 10000      # the embedded scene
    printed = cli("shear", "--print-scene")
    assert printed.returncode == 0 and load_scene(printed.stdout)["model"]["name"] == "chain"
    # with a scene file it would print the default scene, not the file's: refused, one line
    scene = write(tmp_path / "s2.toml", GOOD)
    for extra in ([scene], ["--set", "model.N=20"], ["-tau_ksp_type", "cg"]):
        res = cli("shear", "--print-scene", *extra)
        assert res.returncode == 2 and res.stdout == ""
        assert len(res.stderr.strip().splitlines()) == 1 and "--print-scene" in res.stderr


# ------------------------------------------------------------------ the other entry points

@pytest.fixture(scope="module")
def chain_run(tmp_path_factory):
    """A 50-rod chain run with snapshots and a checkpoint."""
    d = tmp_path_factory.mktemp("chain")
    run = d / "run.h5"
    res = shear(write(d / "s.toml", GOOD + "\n[observables]\nsnapshot_every = 3\n"),
                "--output", run, "--quiet", "--no-plots")
    assert res.returncode == 0, res.stderr
    return run


def test_modes_refuses_existing_output_and_too_many_modes(chain_run, tmp_path):
    out = tmp_path / "m.h5"
    out.write_bytes(b"precious")
    res = cli("modes", chain_run, "--output", out, "--no-plot")
    assert_refused(res, "modes", "exists: pass --overwrite")
    assert out.read_bytes() == b"precious"
    for k in ("50", "1000000000"):
        res = cli("modes", chain_run, "--k", k, "--output", tmp_path / "k.h5", "--no-plot")
        assert_refused(res, "modes", f"--k {k}: the run has 50 rods", "at most Nc - 1 = 49")
    assert_refused(cli("modes", chain_run, "--output", ""), "modes", "--output is empty")
    assert_refused(cli("modes", chain_run, "--output", "/proc/m.h5"), "modes", "'/proc'")
    assert_refused(cli("modes", tmp_path / "nope" / "r.h5"), "modes", "does not exist")
    assert files(tmp_path) == ["m.h5"]
    res = cli("modes", chain_run, "--output", out, "--overwrite", "--no-plot", "--k", "2")
    assert res.returncode == 0, res.stderr
    with h5py.File(out) as f:
        assert f["lam"].shape[1] == 2


@pytest.mark.parametrize("mpi", [0, 2])
def test_spectrum_bad_options_and_paths(chain_run, tmp_path, mpi):
    out = tmp_path / "sp.h5"
    res = cli("spectrum", chain_run, "--output", out, "-spec_eps_type", "nonsense", mpi=mpi)
    assert_refused(res, "spectrum", "PETSc rejected option -spec_eps_type nonsense",
                   "Unknown EPS type given: nonsense")
    res = cli("spectrum", chain_run, "--output", out, "-tau_pc_type", "nonsense", mpi=mpi)
    assert_refused(res, "spectrum", "-tau_pc_type nonsense", "Unable to find requested PC type")
    res = cli("spectrum", chain_run, "--method", "interval", "--omega-max", "1",
              "--output", out, "-spec_eps_ncv", "x1", mpi=mpi)
    assert_refused(res, "spectrum", "-spec_eps_ncv x1", "has no integer value")
    assert_refused(cli("spectrum", chain_run, "--output", "", mpi=mpi), "spectrum", "--output is empty")
    assert_refused(cli("spectrum", chain_run, "--output", str(tmp_path) + "/", mpi=mpi),
                   "spectrum", "names a folder")
    assert_refused(cli("spectrum", chain_run, "--output", chain_run, "--overwrite", mpi=mpi),
                   "spectrum", "is the input file itself")
    assert files(tmp_path) == []


@pytest.fixture(scope="module")
def suspension_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("susp")
    run = d / "run.h5"
    text = ('seed = 2\n[model]\nname = "suspension"\nN = 96\nphi = 0.76\n'
            '[[protocol.leg]]\ndirection = "forward"\nstrain = 0.01\n')
    res = shear(write(d / "s.toml", text), "--output", run, "--quiet", "--no-plots")
    assert res.returncode == 0, res.stderr
    return run


def test_prepare_output_paths(suspension_run, tmp_path):
    """--out into a missing folder creates it, as shear does; paths that cannot be written and
    an existing file (without --overwrite) are refused before the compression runs."""
    args = ("compress", suspension_run, "--phi", "0.78", "--from", "initial")
    for out, message in [("/proc/c.npz", "cannot create files in the output folder '/proc'"),
                         (str(tmp_path / "c.h5"), "must be a file name ending in .npz"),
                         (str(tmp_path / ".npz"), "must be a file name ending in .npz"),
                         (str(tmp_path / ("x" * 300 + ".npz")), "is too long")]:
        assert_refused(cli("prepare", *args, "--out", out), "prepare", message)
    assert_refused(cli("prepare", *args[:3], "nan", "--out", tmp_path / "c.npz"), "prepare",
                   "--phi must be a finite number")
    assert files(tmp_path) == []
    out = tmp_path / "new" / "folder" / "c.npz"
    res = cli("prepare", *args, "--out", out)
    assert res.returncode == 0, res.stderr
    assert files(tmp_path) == ["new", "new/folder", "new/folder/c.npz"]
    stamp = out.stat().st_mtime_ns
    assert_refused(cli("prepare", *args, "--out", out), "prepare", "exists: pass --overwrite", "--out")
    assert out.stat().st_mtime_ns == stamp
    res = cli("prepare", *args, "--out", out, "--overwrite")
    assert res.returncode == 0, res.stderr
