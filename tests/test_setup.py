"""The newcomer path: scripts/env.sh and scripts/setup.sh on a machine where nothing is
installed yet.  CI runs where PETSc is already installed, so it cannot see that path; these
tests play the fresh machine by pointing the PETSc/SLEPc search roots at empty folders."""
import os
import subprocess
from pathlib import Path

import pytest
from hang_guard import guard

pytestmark = pytest.mark.serial_only      # shells out; nothing MPI about it

REPO = Path(__file__).resolve().parent.parent


def _env(tmp_path, petsc_root=None, slepc_root=None, **extra):
    """The environment of a fresh shell: no PETSc/SLEPc variables, search roots given."""
    empty = tmp_path / "empty"
    empty.mkdir(exist_ok=True)
    env = {k: v for k, v in os.environ.items() if k not in ("PETSC_DIR", "SLEPC_DIR")}
    env["PARFLOW_PETSC_ROOT"] = str(petsc_root or empty)
    env["PARFLOW_SLEPC_ROOT"] = str(slepc_root or empty)
    env.update(extra)
    return env


def _source(shell_cmd, env):
    script = shell_cmd + ' -c \'. scripts/env.sh; echo "PETSC_DIR=${PETSC_DIR-<unset>}"; ' \
                         'echo "SLEPC_DIR=${SLEPC_DIR-<unset>}"\''
    return subprocess.run(script, shell=True, cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=guard(30))


@pytest.mark.parametrize("shell", ["bash -euo pipefail", "sh -eu"])
def test_env_sh_on_a_machine_without_petsc(tmp_path, shell):
    """The bug a fresh machine hit: `ls` of a glob that matched nothing exited 2 and, under
    `set -euo pipefail`, killed setup.sh before apt ever ran."""
    res = _source(shell, _env(tmp_path))
    assert res.returncode == 0, res.stderr
    assert "PETSC_DIR=<unset>" in res.stdout and "SLEPC_DIR=<unset>" in res.stdout, res.stdout


def test_env_sh_picks_the_newest_petsc_and_its_slepc(tmp_path):
    petsc, slepc = tmp_path / "petscdir", tmp_path / "slepcdir"
    for d in ("petsc3.9/x86_64-linux-gnu-real", "petsc3.18/x86_64-linux-gnu-real",
              "petsc3.18/x86_64-linux-gnu-complex"):
        (petsc / d).mkdir(parents=True)
    for d in ("slepc3.18/x86_64-linux-gnu-real", "slepc3.19/x86_64-linux-gnu-real"):
        (slepc / d).mkdir(parents=True)
    res = _source("bash -euo pipefail", _env(tmp_path, petsc, slepc))
    assert res.returncode == 0, res.stderr
    # version-aware: 3.18 > 3.9; the SLEPc of the same version and arch, not the newest one
    assert f"PETSC_DIR={petsc}/petsc3.18/x86_64-linux-gnu-real" in res.stdout, res.stdout
    assert f"SLEPC_DIR={slepc}/slepc3.18/x86_64-linux-gnu-real" in res.stdout, res.stdout


def _x86_avx2() -> bool:
    try:
        return os.uname().machine == "x86_64" and " avx2" in open("/proc/cpuinfo").read()
    except OSError:
        return False


@pytest.mark.skipif(not _x86_avx2(), reason="the kernel pin is for x86-64 with AVX2")
@pytest.mark.parametrize("shell", ["bash -euo pipefail", "sh -eu"])
def test_env_sh_pins_the_blas_kernels(tmp_path, shell):
    """docs/conventions.md "The same numbers on every machine": OpenBLAS on its Haswell
    kernels whatever the CPU (and numpy off AVX-512), a value already set left alone, and the
    pin reaching the library (parflow.provenance.kernels asks OpenBLAS)."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("OPENBLAS_CORETYPE", "NPY_DISABLE_CPU_FEATURES")}
    probe = shell + """ -c '. scripts/env.sh; echo "CORE=$OPENBLAS_CORETYPE"; \
        .venv/bin/python -c "from parflow.provenance import kernels; print(kernels())"'"""
    res = subprocess.run(probe, shell=True, cwd=REPO, env=env, capture_output=True,
                         text=True, timeout=guard(60))
    assert res.returncode == 0, res.stderr
    assert "CORE=Haswell" in res.stdout and "openblas Haswell, numpy AVX2" in res.stdout, \
        res.stdout + res.stderr
    assert "AVX512" not in res.stdout and "cannot disable" not in res.stderr, res.stderr
    res = subprocess.run(shell + """ -c '. scripts/env.sh; echo "CORE=$OPENBLAS_CORETYPE"'""",
                         shell=True, cwd=REPO, env=dict(env, OPENBLAS_CORETYPE="Sandybridge"),
                         capture_output=True, text=True, timeout=guard(30))
    assert "CORE=Sandybridge" in res.stdout, res.stdout + res.stderr


def test_setup_reaches_apt_on_a_machine_without_petsc(tmp_path):
    """setup.sh under `set -euo pipefail` gets as far as the apt step (dry run: nothing is
    installed) when none of the system packages is there."""
    env = _env(tmp_path, PARFLOW_SETUP_DRY_RUN="1")
    res = subprocess.run(["bash", "scripts/setup.sh"], cwd=REPO, env=env, capture_output=True,
                         text=True, timeout=guard(120))
    assert res.returncode == 0, res.stdout + res.stderr
    assert "dry run: would run apt-get update && apt-get install -y" in res.stdout, res.stdout
    assert "python3-petsc4py" in res.stdout and "openmpi-bin" in res.stdout


def test_ci_entry_point_runs_the_readme_test_command():
    """.ci/run calls `make test`, and `make test` fails on pytest's exit 5 (no tests)."""
    ci = (REPO / ".ci" / "run").read_text()
    assert "make test" in ci and "set -euo pipefail" in ci
    readme = (REPO / "README.md").read_text()
    assert "make test" in readme and "make run" in readme
    res = subprocess.run(["make", "-n", "test"], cwd=REPO, capture_output=True, text=True,
                         timeout=guard(60))
    assert res.returncode == 0, res.stderr
    assert "pytest" in res.stdout and "mpirun" in res.stdout
    # a selection that matches no test is pytest's exit 5: make must fail on it, not pass
    res = subprocess.run(["make", "--no-print-directory", "test-serial",
                          "PYTEST_ARGS=tests/test_setup.py -k no_such_test_anywhere"],
                         cwd=REPO, capture_output=True, text=True, timeout=guard(120))
    assert res.returncode != 0, res.stdout
    # pytest's own words for it ("deselected" in one process, "no tests ran" under xdist),
    # and make reporting exit status 5
    assert "deselected" in res.stdout or "no tests ran" in res.stdout, res.stdout
    assert "Error 5" in res.stderr, res.stderr


def test_serial_tests_run_on_every_core_even_after_env_sh():
    """make test-serial takes one test process per core it may use -- also when
    scripts/env.sh (OMP_NUM_THREADS = 1, which nproc obeys) was sourced first."""
    cores = len(os.sched_getaffinity(0))
    env = dict(os.environ, OMP_NUM_THREADS="1")
    env.pop("TEST_JOBS", None)
    res = subprocess.run(["make", "-n", "--no-print-directory", "test-serial"], cwd=REPO, env=env,
                         capture_output=True, text=True, timeout=guard(60))
    assert res.returncode == 0, res.stderr
    assert f"jobs={cores};" in res.stdout, res.stdout


def test_git_commit_is_read_once_per_process(monkeypatch):
    """An ensemble's later samples record the commit the process started with, not a HEAD
    that moved while it ran (the code in memory is what was imported)."""
    import subprocess as sp

    from parflow import provenance
    calls = []
    real = sp.run

    def counting(*a, **kw):
        calls.append(a[0])
        return real(*a, **kw)
    provenance.git_commit.cache_clear()
    monkeypatch.setattr(provenance.subprocess, "run", counting)
    first = provenance.git_commit()
    assert provenance.git_commit() == first and len(calls) == 2      # rev-parse + status
    provenance.git_commit.cache_clear()
