"""Hang guards of the tests that start processes (``python -m parflow.shear``, ``mpirun``,
``make``): each waits at most ``guard(seconds)`` for its process.

The seconds are what the process takes on an idle 2-core machine with ample room (most end
in 2-20 s).  On a loaded machine -- other jobs on the cores, a niced test run -- they may not
be enough; raising ``PARFLOW_TEST_TIMEOUT`` (the per-test watchdog of conftest.py, default
600 s) above its default scales every guard by the same factor, so one variable gives the
whole suite more time.  ``PARFLOW_TEST_TIMEOUT=0`` (no watchdog) leaves the guards as they
are: they are what stops a hung subprocess then.
"""
import os

DEFAULT_TIMEOUT = 600.0


def scale() -> float:
    """The factor on every guard: PARFLOW_TEST_TIMEOUT / 600, at least 1."""
    t = float(os.environ.get("PARFLOW_TEST_TIMEOUT", str(DEFAULT_TIMEOUT)))
    return max(1.0, t / DEFAULT_TIMEOUT)


def guard(seconds: float) -> float:
    """How long a test waits for a process that takes ``seconds`` on an idle machine."""
    return float(seconds) * scale()
