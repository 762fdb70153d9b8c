"""parflow's exceptions, at the bottom of the import graph (everything may import this).

* :class:`InputError` -- a user error: one line, no traceback, exit status 2.
* :class:`Terminated` -- SIGTERM arrived: the run stops at a step boundary with a
  checkpoint, like an interrupt (exit 143).
"""
from __future__ import annotations


class InputError(ValueError):
    """A user error: reported as one line, without a traceback."""


class Terminated(BaseException):
    """SIGTERM arrived (``kill``, a batch scheduler's time limit): the run stops at the end
    of the step under way, leaves a checkpoint and says so in its status, like an interrupt."""
