"""pytest set-up shared by every parflow test, serial and under ``mpirun -n N``.

* PETSc/SLEPc are initialised here with ``sys.argv[:1]`` so that pytest's own arguments
  are never parsed as PETSc options (``PETSC_OPTIONS`` in the environment still works).
  Test modules then simply ``from petsc4py import PETSc``.
* Under MPI every rank runs the whole session.  Rank 0 reports on the terminal; ranks > 0
  write their report to ``$TMPDIR/parflow-pytest-rank<r>.log`` and print one line on
  stderr per failure.
* After each test the ranks meet (a collective on a private communicator) and exchange
  whether the test failed anywhere.  A test that failed on any rank counts as failed on
  every rank: each rank's exit status reflects it, rank 0 lists it under "failures on
  other MPI ranks", and ``-x``/``--maxfail`` stop all ranks together.  The ranks also
  check that they collected the same tests, and stop together if one could not.
* A test that runs longer than ``PARFLOW_TEST_TIMEOUT`` seconds (default 600; 0 disables)
  dumps every thread's traceback and exits the process, so a rank stuck in a collective
  that its peers never enter cannot hang CI forever (mpirun then stops the other ranks).

Fixtures: ``comm`` (mpi4py ``COMM_WORLD``), ``mpi_tmp_path`` (one directory shared by all
ranks).  Marker: ``serial_only`` (skipped when the size of ``COMM_WORLD`` is > 1).
"""

import faulthandler
import hashlib
import os
import sys
import tempfile
from pathlib import Path


def _drop_inherited_singleton():
    """Open MPI's singleton init (MPI without mpirun, as in a serial session) writes its
    PMIx contact into the C environment.  A process started from such a one -- a
    pytest-xdist worker started by the controlling pytest -- inherits it, and would join
    the parent's singleton instead of starting its own, and hand it to every mpirun it
    runs (which then fails at once, silently).  Drop it before MPI starts here; ranks
    started by mpirun (OMPI_COMM_WORLD_SIZE set) keep theirs."""
    if os.environ.get("OMPI_MCA_ess") != "singleton" or "OMPI_COMM_WORLD_SIZE" in os.environ:
        return
    for k in list(os.environ):
        if k.startswith("PMIX_") or k in ("OMPI_MCA_ess", "OMPI_COMMAND", "OMPI_MCA_pmix",
                                          "OMPI_APP_CTX_NUM_PROCS") or k.startswith("OMPI_MCA_orte_"):
            del os.environ[k]                 # also unsetenv: the C environment


_drop_inherited_singleton()

import petsc4py  # noqa: E402

petsc4py.init(sys.argv[:1])
import slepc4py  # noqa: E402

slepc4py.init(sys.argv[:1])
from petsc4py import PETSc  # noqa: E402
from slepc4py import SLEPc  # noqa: E402
from mpi4py import MPI  # noqa: E402

import pytest  # noqa: E402

COMM_WORLD = MPI.COMM_WORLD
RANK = COMM_WORLD.Get_rank()
SIZE = COMM_WORLD.Get_size()
# Private duplicate for the infrastructure's own collectives, so that they can never be
# matched with a test's communication on COMM_WORLD.
_INFRA_COMM = COMM_WORLD.Dup()

TIMEOUT = float(os.environ.get("PARFLOW_TEST_TIMEOUT", "600"))
RANK_LOG = Path(tempfile.gettempdir()) / f"parflow-pytest-rank{RANK}.log"

_stderr_fd = None       # copy of the real stderr (pytest's fd capture leaves it alone)
_rank_log_file = None   # ranks > 0: where their terminal report goes
_failed = []            # node ids that failed on this rank
_failed_elsewhere = []  # (node id, ranks) that failed on other ranks only


def _version(v):
    return ".".join(map(str, v))


def _tell(msg):
    """One line on the real stderr from a quiet rank (> 0)."""
    if SIZE > 1 and RANK > 0 and _stderr_fd is not None:
        os.write(_stderr_fd, f"[rank {RANK}/{SIZE}] {msg}\n".encode())


def pytest_report_header(config):
    return (f"parflow: MPI size {SIZE}, PETSc {_version(PETSc.Sys.getVersion())}, "
            f"SLEPc {_version(SLEPc.Sys.getVersion())}, "
            f"test timeout {TIMEOUT:g} s (PARFLOW_TEST_TIMEOUT)")


@pytest.hookimpl(trylast=True)  # after the terminal plugin has registered its reporter
def pytest_configure(config):
    global _stderr_fd
    config.addinivalue_line(
        "markers", "serial_only: test needs a single MPI rank; skipped under mpirun -n >1")
    _stderr_fd = os.dup(2)
    if SIZE > 1 and RANK > 0:
        _quiet_terminal_reporter(config)


def _quiet_terminal_reporter(config):
    """Send this rank's terminal report to RANK_LOG instead of the shared stdout."""
    global _rank_log_file
    pm = config.pluginmanager
    old = pm.get_plugin("terminalreporter")
    if old is None:
        return
    pm.unregister(old)
    try:
        from _pytest.terminal import TerminalReporter
        _rank_log_file = open(RANK_LOG, "w", encoding="utf-8")
        pm.register(TerminalReporter(config, _rank_log_file), "terminalreporter")
    except Exception:  # pragma: no cover - private pytest API moved: stay silent instead
        pass


def pytest_unconfigure(config):
    global _rank_log_file, _stderr_fd
    if _rank_log_file is not None:
        _rank_log_file.close()
        _rank_log_file = None
    if _stderr_fd is not None:
        os.close(_stderr_fd)
        _stderr_fd = None


def pytest_collection_modifyitems(config, items):
    if SIZE > 1:
        skip = pytest.mark.skip(reason=f"serial_only: MPI size is {SIZE}")
        for item in items:
            if item.get_closest_marker("serial_only"):
                item.add_marker(skip)


def pytest_collection_finish(session):
    """All ranks must run the same tests in the same order, or the per-test collective
    below would pair different tests.  If not, or if any rank had a collection error,
    every rank stops before running anything."""
    if SIZE == 1:
        return
    digest = hashlib.sha1("\n".join(i.nodeid for i in session.items).encode()).hexdigest()
    states = _INFRA_COMM.allgather((digest, session.testsfailed))
    bad = [r for r, (_, n) in enumerate(states) if n]
    if bad:
        if not session.testsfailed:  # pytest_runtestloop stops on testsfailed > 0
            session.testsfailed = 1
            _warn(session, f"collection errors on MPI rank(s) {bad}; not running tests")
    elif len({d for d, _ in states}) > 1:
        session.testsfailed += 1
        _warn(session, "MPI ranks collected different tests; not running tests")


def _warn(session, msg):
    tr = session.config.pluginmanager.get_plugin("terminalreporter")
    if tr is not None:
        tr.write_line(f"parflow conftest: {msg}", red=True)
    _tell(msg)


def _arm_watchdog():
    if TIMEOUT > 0:
        faulthandler.dump_traceback_later(
            TIMEOUT, exit=True, file=_stderr_fd if _stderr_fd is not None else sys.__stderr__)


def _disarm_watchdog():
    if TIMEOUT > 0:
        faulthandler.cancel_dump_traceback_later()


@pytest.hookimpl(hookwrapper=True)
def pytest_collection(session):
    _arm_watchdog()  # covers the rank exchange in pytest_collection_finish
    try:
        yield
    finally:
        _disarm_watchdog()


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    """Per test: watchdog over setup, call, teardown and the rank exchange; then the
    ranks exchange failure flags (this is also the barrier that keeps them in step)."""
    _arm_watchdog()
    n_failed = len(_failed)
    try:
        yield
        if SIZE > 1:
            failed_here = len(_failed) > n_failed
            flags = _INFRA_COMM.allgather(failed_here)
            if any(flags) and not failed_here:
                session = item.session
                ranks = [r for r, f in enumerate(flags) if f]
                _failed_elsewhere.append((item.nodeid, ranks))
                session.testsfailed += 1
                maxfail = item.config.getvalue("maxfail")
                if maxfail and session.testsfailed >= maxfail:
                    session.shouldfail = f"stopping after failure on MPI rank(s) {ranks}"
    finally:
        _disarm_watchdog()


def pytest_runtest_logreport(report):
    if report.failed and not hasattr(report, "wasxfail"):  # as pytest counts failures
        _failed.append(report.nodeid)
        _tell(f"FAILED {report.nodeid} ({report.when}); details in {RANK_LOG}")


def pytest_collectreport(report):
    if report.failed:
        _tell(f"ERROR collecting {report.nodeid}; details in {RANK_LOG}")


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    if _failed_elsewhere:
        tr = terminalreporter
        tr.write_sep("=", "failures on other MPI ranks", red=True)
        for nodeid, ranks in _failed_elsewhere:
            logs = ", ".join(str(RANK_LOG).replace(f"rank{RANK}", f"rank{r}") for r in ranks)
            tr.write_line(f"FAILED {nodeid} on rank(s) {ranks}: see {logs}")


def pytest_sessionfinish(session, exitstatus):
    if int(exitstatus) != 0:
        _tell(f"pytest exit status {int(exitstatus)}, {len(_failed)} failure(s) on this "
              f"rank; full report in {RANK_LOG}")


@pytest.fixture(scope="session")
def comm():
    """mpi4py's COMM_WORLD (size 1 in a serial run)."""
    return COMM_WORLD


@pytest.fixture
def mpi_tmp_path(tmp_path):
    """A temporary directory common to all ranks (rank 0's ``tmp_path``), e.g. for
    parallel HDF5.  Same as ``tmp_path`` in a serial run.  Single-node runs only."""
    path = _INFRA_COMM.bcast(str(tmp_path) if RANK == 0 else None, root=0)
    return Path(path)
