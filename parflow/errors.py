"""parflow's exceptions, at the bottom of the import graph (everything may import this).

* :class:`InputError` -- a user error: one line, no traceback, exit status 2.
* :class:`Terminated` -- SIGTERM arrived: the run stops at a step boundary with a
  checkpoint, like an interrupt (exit 143).
* :func:`collective` -- run a check on rank 0 and raise its InputError on every rank, so an
  error found by one rank never leaves the others waiting in a collective.
"""
from __future__ import annotations


class InputError(ValueError):
    """A user error: reported as one line, without a traceback."""


class Terminated(BaseException):
    """SIGTERM arrived (``kill``, a batch scheduler's time limit): the run stops at the end
    of the step under way, leaves a checkpoint and says so in its status, like an interrupt."""


def collective(comm, fn, *args):
    """Run ``fn`` on rank 0 only; an InputError there is raised on every rank (no hang).
    Returns fn's result, broadcast."""
    result, err = None, None
    if comm.getRank() == 0:
        try:
            result = fn(*args)
        except InputError as exc:
            err = str(exc)
    result, err = comm.tompi4py().bcast((result, err), root=0)
    if err is not None:
        raise InputError(err)
    return result
