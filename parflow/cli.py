"""Shared command-line plumbing: PETSc options first, one-line user errors, no MPI hangs."""
from __future__ import annotations

import signal
import sys
import threading
import traceback


def split_petsc_args(argv: list[str], flags_with_value: set[str]) -> tuple[list[str], list[str]]:
    """Separate application arguments (positional, ``--flag``) from PETSc options
    (``-name [value]``, single dash)."""
    app, petsc = [], []
    k = 0
    while k < len(argv):
        a = argv[k]
        if a.startswith("--") or a == "-h":
            app.append(a)
            if a in flags_with_value and k + 1 < len(argv):
                app.append(argv[k + 1])
                k += 1
        elif a.startswith("-") and len(a) > 1 and not _is_number(a):
            petsc.append(a)
            if k + 1 < len(argv) and (not argv[k + 1].startswith("-") or _is_number(argv[k + 1])):
                petsc.append(argv[k + 1])
                k += 1
        else:
            app.append(a)
        k += 1
    return app, petsc


def _is_number(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


def init_petsc(petsc_args: list[str]):
    """Initialise PETSc with the command line's PETSc options.  If PETSc is initialised
    already (``python -m parflow.spectrum`` imports it with the module, without arguments,
    and petsc4py.init then has no effect), the options are put into its database instead."""
    already = "petsc4py.PETSc" in sys.modules
    # the first import of petsc4py, on purpose here: init() must see the options first
    import petsc4py
    petsc4py.init([sys.argv[0]] + petsc_args)
    from petsc4py import PETSc
    from .algebra.spectrum import init_slepc    # (after init: see the module docstring)
    init_slepc()
    if already:
        db, k = PETSc.Options(), 0
        while k < len(petsc_args):
            name, value = petsc_args[k], None
            if k + 1 < len(petsc_args) and (not petsc_args[k + 1].startswith("-")
                                            or _is_number(petsc_args[k + 1])):
                value = petsc_args[k + 1]
                k += 1
            if name.startswith("-") and not _is_number(name):
                db.setValue(name.lstrip("-"), value)
            k += 1
    return PETSc


def cmdline_option_names(petsc_args: list[str]) -> set[str]:
    return {a.lstrip("-") for a in petsc_args if a.startswith("-") and not _is_number(a)}


def ranks_on_node(comm) -> int:
    """How many ranks of ``comm`` run on the same machine as rank 0 (collective): they share
    its memory."""
    from mpi4py import MPI      # (importing mpi4py initialises MPI: only once it is needed)
    if comm.getSize() == 1:
        return 1
    names = comm.tompi4py().gather(MPI.Get_processor_name(), root=0)
    return names.count(names[0]) if names is not None else 0


def _collective_cleanup():
    """``algebra.solvers.collective_cleanup`` (imported here, at the end of a command: this
    module is loaded before PETSc is initialised with the command line's options)."""
    from .algebra.solvers import collective_cleanup     # (after init_petsc: see the docstring)
    collective_cleanup()


def run_main(prog: str, body) -> int:
    """Call ``body()``; map errors to exit codes without hanging other ranks.

    InputError (collective by construction): one line on rank 0, exit 2.
    SolveError/Jammed raised collectively: one line, exit 1.
    WriteError (the run file could not be written, e.g. a full disk; raised on every rank by
    ``io.collective_write``): one line, exit 1.
    KeyboardInterrupt / SIGTERM (:class:`Terminated`): one line, exit 130 / 143 (a run takes
    the signal at the end of the step under way, on all ranks at once, and writes its
    checkpoint and status on the way out; a signal elsewhere, or a second one, aborts).
    Anything else: traceback, then MPI_Abort when running on several ranks.
    """
    # here, not at the top: this module is loaded before PETSc is initialised with the
    # command line's options, and these import petsc4py (and initialise MPI)
    from mpi4py import MPI

    from .algebra.solvers import SolveError
    from .io import WriteError
    from .state import STOPS, InputError, Terminated
    comm = MPI.COMM_WORLD

    if threading.current_thread() is threading.main_thread():   # (signals: main thread only)
        # SIGUSR1 / SIGUSR2 stand for SIGTERM / SIGINT: Open MPI's mpirun relays them to every
        # rank at once (SIGTERM and SIGINT it does not relay, it kills the ranks; docs/output.md
        # "Signals", scripts/mpirun-parflow).
        signal.signal(signal.SIGTERM, lambda signum, frame: STOPS.handle(2))
        signal.signal(signal.SIGUSR1, lambda signum, frame: STOPS.handle(2))
        signal.signal(signal.SIGUSR2, lambda signum, frame: STOPS.handle(1))
        if signal.getsignal(signal.SIGINT) is signal.default_int_handler:  # not if ignored (`&`)
            signal.signal(signal.SIGINT, lambda signum, frame: STOPS.handle(1))
    try:
        code = body() or 0
        _collective_cleanup()
        return code
    except InputError as exc:
        if comm.rank == 0:
            print(f"{prog}: error: {exc}", file=sys.stderr)
        _collective_cleanup()
        return 2
    except SolveError as exc:
        if comm.rank == 0:
            print(f"{prog}: solver error: {exc}", file=sys.stderr)
        _collective_cleanup()
        return 1
    except WriteError as exc:
        if comm.rank == 0:
            print(f"{prog}: write error: {exc}", file=sys.stderr)
        _collective_cleanup()
        return 1
    except (KeyboardInterrupt, Terminated) as exc:
        term = isinstance(exc, Terminated)
        collective = getattr(exc, "collective", False)
        if comm.rank == 0 or not collective:
            print(f"{prog}: {'terminated' if term else 'interrupted'}", file=sys.stderr)
        code = 143 if term else 130
        if comm.size > 1 and not collective:
            comm.Abort(code)       # raised on one rank, or mid-step: the others may be anywhere
        if collective:
            _collective_cleanup()
        return code
    except Exception:
        traceback.print_exc()
        sys.stderr.flush()
        if comm.size > 1:
            comm.Abort(1)
        return 1
