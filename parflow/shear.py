"""Main job: ``mpirun -n 2 python -m parflow.shear [scene.toml] [options] [PETSc options]``.

Without a scene file the embedded default scene runs (a chain in planar extension, forward
to <V^2> = 1e8 and back).  Any ``-option value`` with a single dash goes to PETSc and
overrides the scene's [petsc] table (e.g. ``-tau_pc_factor_mat_solver_type mumps``).

The imports of parflow's modules are inside the functions on purpose: PETSc must be
initialised with the command line's options (``cli.init_petsc``) before any module that
imports petsc4py is loaded, and ``--help``/``--print-scene`` need none of them.
"""
from __future__ import annotations

import argparse
import logging
import os
import sys

from .cli import cmdline_option_names, init_petsc, run_main, split_petsc_args
from .errors import collective

USAGE_FLAGS = {"--output", "--restart", "--max-steps", "--set", "--samples", "--ranks-per-sample"}


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m parflow.shear",
        description="Run a parflow scene (default: the embedded chain scene).",
        epilog="Single-dash options (-tau_ksp_type ...) are passed to PETSc; they override "
               "the scene's [petsc] table.")
    p.add_argument("scene", nargs="?", help="scene TOML file (default: embedded chain scene)")
    p.add_argument("--output", help="output HDF5 file (default: the scene's output.path)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    p.add_argument("--quiet", action="store_true", help="no progress line")
    p.add_argument("--restart", metavar="FILE", help="continue the run saved in FILE from its checkpoint "
                   "(with --output NEW: branch it, continuing a copy in NEW; FILE is left as it is, "
                   "and --set may then change the protocol, e.g. --set protocol.leg.0.sigma_above=3e4; "
                   "a run that is complete has its last leg reopened by such a change, e.g. "
                   "--set protocol.leg.0.strain=7 shears it on to a leg strain of 7)")
    p.add_argument("--max-steps", type=int, help="override protocol.max_steps (e.g. to extend a restarted run)")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="change a scene setting (repeatable), e.g. --set integrator.controller=PI; "
                        "with --restart: [integrator], [solver] and [output] keys only; the file "
                        "records every setting and a later restart applies them again")
    p.add_argument("--samples", type=int, metavar="K", help="run K samples of the scene in this "
                   "job (an ensemble, docs/ensembles.md; overrides ensemble.samples): the output "
                   "is a folder (--output FOLDER, default the scene's output.path without .h5); "
                   "--restart FOLDER continues it")
    p.add_argument("--retry", action="store_true", help="with --restart FOLDER: continue the "
                   "samples that stopped jammed or failed from their checkpoints too (after a "
                   "fix; their files record retried_after)")
    p.add_argument("--ranks-per-sample", type=int, metavar="r", help="ranks of each sample's "
                   "group (overrides ensemble.ranks_per_sample; default 1)")
    p.add_argument("--no-plots", action="store_true", help="do not draw the figures at the end")
    p.add_argument("--print-scene", action="store_true",
                   help="print the embedded default scene and exit (nothing else with it)")
    return p


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    app, petsc_args = split_petsc_args(argv, USAGE_FLAGS)
    args = parser().parse_args(app)
    if args.print_scene:
        others = [f for f, v in (("a scene file", args.scene), ("--restart", args.restart),
                                 ("--set", args.set), ("--output", args.output)) if v]
        if others or petsc_args:
            # one line, exit 2, as for every usage error (and no PETSc/MPI start-up for it)
            print(f"parflow.shear: error: --print-scene prints the embedded default scene and "
                  f"takes nothing else (given: {', '.join(others or ['PETSc options'])}); a scene "
                  f"file is its own text, and a run file keeps its scene in its attribute 'scene'",
                  file=sys.stderr)
            return 2
        # (here, not at the top: see the module docstring)
        from .scene import DEFAULT_SCENE
        print(DEFAULT_SCENE, end="")
        return 0
    PETSc = init_petsc(petsc_args)
    return run_main("parflow.shear", lambda: _run(args, petsc_args, PETSc))


MAX_SCENE_BYTES = 1 << 20       # a scene is a page of TOML; more is not a scene file


def _read(path):
    # (here, not at the top: see the module docstring)
    from .state import InputError
    try:
        with open(path, "rb") as fh:
            data = fh.read(MAX_SCENE_BYTES + 1)
    except OSError as exc:
        raise InputError(f"cannot read scene file {path!r}: {exc.strerror or exc}") from None
    if len(data) > MAX_SCENE_BYTES:
        raise InputError(f"scene file {path!r} is larger than {MAX_SCENE_BYTES >> 20} MB: "
                         f"it is not a scene (a TOML text file)")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data[:exc.start].count(b"\n") + 1
        col = exc.start - (data.rfind(b"\n", 0, exc.start) + 1) + 1
        raise InputError(f"scene file {path!r} is not UTF-8 text (byte 0x{data[exc.start]:02x} at "
                         f"line {line}, column {col}): TOML is UTF-8; save the file as UTF-8 "
                         f"(or it is not a scene file)") from None


def _branch(src: str, dst: str, overwrite: bool, n_legs: int,
            new_protocol: bool = False) -> tuple[int, bool]:
    """Copy the run file ``src`` to ``dst`` (the branch then restarts from its checkpoint):
    (the checkpoint's step, whether the last leg was reopened).  With ``new_protocol`` (the
    branch's ``--set`` changes protocol keys) a run that had done all its ``n_legs`` legs has
    its last leg reopened in the copy, its strain and steps so far taken from the time series
    (:func:`_reopen_last_leg`): a longer leg or a stop stress not yet reached continues it,
    one already met ends it again at once.  ``src`` was checked by ``_restart_scene``; it is
    only read.  ``dst`` appears complete or not at all."""
    # (here, not at the top: see the module docstring)
    from .io import atomic_h5, check_output_path
    from .state import InputError
    if os.path.abspath(src) == os.path.abspath(dst):
        raise InputError("--output names the file being restarted: to continue the run itself, "
                         "drop --output; to branch it, give a new file")
    check_output_path(dst, overwrite)
    try:
        with atomic_h5(dst, source=src) as f:
            step = int(f["checkpoint"].attrs["step"])
            f.attrs["branched_from"] = f"{os.path.abspath(src)} at step {step}"
            reopened = (new_protocol and int(f["checkpoint"].attrs["leg"]) >= n_legs
                        and _reopen_last_leg(f, n_legs))
    except OSError as exc:
        raise InputError(f"cannot write the branch {dst!r}: {exc.strerror or exc}; "
                         f"{src!r} was not changed") from None
    return step, reopened


def _reopen_last_leg(f, n_legs: int) -> bool:
    """Set the checkpoint of the open run file ``f`` (all ``n_legs`` legs done) back into its
    last leg: leg = n_legs - 1, with the strain and steps that leg ran (from the time series'
    ``leg``, ``strain`` and ``step`` columns up to the checkpoint's row; the row before the
    leg's first is where it began, the initial row for a first leg).  False, and nothing
    changed, if the time series cannot say (no such columns, no row of that leg)."""
    # (here, not at the top: see the module docstring)
    import numpy as np
    ck, ts = f["checkpoint"].attrs, f["timeseries"]
    if n_legs < 1 or not all(k in ts for k in ("leg", "strain", "step")):
        return False
    n = int(ck["n_rows"])
    rows = np.flatnonzero(ts["leg"][:n] == n_legs - 1)
    if rows.size == 0:
        return False
    k0 = int(rows[0])
    strain0 = float(ts["strain"][k0 - 1]) if k0 > 0 else 0.0
    step0 = int(ts["step"][k0 - 1]) if k0 > 0 else 0
    ck["leg"] = n_legs - 1
    ck["leg_strain"] = max(0.0, float(ck["strain"]) - strain0)
    ck["leg_steps"] = int(ck["step"]) - step0
    return True


def _restart_scene(path):
    """The scene text and stored settings of the run file ``path``, after checking that its
    checkpoint can be restarted from (``checkpoint.check_checkpoint``): a hostile or damaged file
    is refused here, before the restart (or a branch) touches anything."""
    # (here, not at the top: see the module docstring)
    from .checkpoint import check_checkpoint
    from .io import RunFile
    from .scene import load_scene
    from .state import InputError
    with RunFile(path) as run:
        if not run.has_checkpoint:
            raise InputError(f"{path!r} has no checkpoint: it cannot be restarted; the file was not changed")
        text = run.scene_text
        if not text:
            raise InputError(f"{path!r} has no scene attribute: it cannot be restarted; "
                             f"the file was not changed")
        scene = load_scene(text, path)
        check_checkpoint(run.h5, path, len(scene["protocol"]["leg"]), scene["model"]["name"])
        return text, run.settings


def _run(args, petsc_args, PETSc) -> int:
    # (here, not at the top: see the module docstring)
    from .cli import ranks_on_node
    from .io import check_output_path
    from .run import Run, setup_logging
    from .scene import DEFAULT_SCENE, apply_settings, check_resources, load_scene, with_overrides
    from .algebra.solvers import check_options_on, insert_options
    from .state import InputError

    comm = PETSc.COMM_WORLD
    setup_logging(comm, args.quiet)
    if args.output is not None and not args.output.strip():
        raise InputError("--output is empty: give a file name, or drop --output to write the "
                         "scene's output.path")
    if args.max_steps is not None and args.max_steps <= 0:
        raise InputError("--max-steps must be a positive integer")
    if args.samples is not None and not 0 < args.samples <= 10**6:
        raise InputError("--samples must be a positive integer (at most 1000000)")
    if args.ranks_per_sample is not None and args.ranks_per_sample <= 0:
        raise InputError("--ranks-per-sample must be a positive integer")
    if args.retry and not (args.restart and os.path.isdir(args.restart)):
        raise InputError("--retry continues an ensemble's jammed or failed samples: give it "
                         "with --restart FOLDER (a single run restarts with --restart FILE)")
    if args.restart and os.path.isdir(args.restart):
        return _ensemble(args, petsc_args, comm, None)
    if args.restart:
        if args.scene:
            raise InputError("--restart FILE takes the scene from FILE: do not give a scene with it")
        if args.samples is not None or args.ranks_per_sample is not None:
            raise InputError("--samples / --ranks-per-sample: --restart FILE continues one run; "
                             "an ensemble restarts from its folder (--restart FOLDER)")
        text, before = collective(comm, _restart_scene, args.restart)
        scene = load_scene(text, args.restart)
        scene = apply_settings(scene, before)    # the file's own settings, checked when they were given
        branch = bool(args.output)
        scene = apply_settings(scene, args.set, restart=True, branch=branch)
    else:
        if args.scene:
            text, source = collective(comm, _read, args.scene), args.scene
        else:
            text, source = DEFAULT_SCENE, "<default scene>"
        scene = apply_settings(with_overrides(load_scene(text, source), args.output), args.set)
        if (args.samples or scene["ensemble"]["samples"]) > 0:
            return _ensemble(args, petsc_args, comm, scene, source)
        if args.ranks_per_sample is not None:
            raise InputError("--ranks-per-sample is for an ensemble: give --samples K too")
    # before anything is allocated or written: the size against the machine's memory, the
    # PETSc options against PETSc (scene [petsc] table, then the command line, which wins)
    collective(comm, check_resources, scene, comm.getSize(), ranks_on_node(comm))
    cmdline = cmdline_option_names(petsc_args)
    insert_options(scene["petsc"], cmdline)
    check_options_on(comm, cmdline)
    if args.restart:
        path = args.restart
        if branch:       # continue a copy of the run in another file; FILE is left as it is
            new_protocol = any(x.strip().startswith("protocol.") for x in args.set or [])
            step, reopened = collective(comm, _branch, args.restart, args.output, args.overwrite,
                                        len(scene["protocol"]["leg"]), new_protocol)
            path = args.output
            logging.getLogger("parflow").info(
                "branching %s at its checkpoint (step %d) into %s%s", args.restart, step, path,
                " (it had done all its legs: its last leg reopened)" if reopened else "")
    else:
        path = scene["output"]["path"]
        if args.scene and _same_file(args.scene, path):
            raise InputError(f"the output {path!r} is the scene file itself: write the run to "
                             f"another file (--output)")
        collective(comm, check_output_path, path, args.overwrite)
    def run(on):
        return Run(scene, on, path, quiet=args.quiet, cmdline_options=cmdline,
                   restart=bool(args.restart), max_steps=args.max_steps).execute()
    if scene["solver"]["parallel"] == "threads" and comm.getSize() > 1:
        status = _on_rank0_with_threads(comm, PETSc, run, ranks_on_node(comm))
    else:
        status = run(comm)
    if not args.no_plots and comm.getRank() == 0:
        _plots(path, args.quiet)
    return 0 if status in ("complete", "jammed", "budget") else 1


def _on_rank0_with_threads(comm, PETSc, work, threads: int):
    """solver.parallel = "threads": ``work(COMM_SELF)`` on rank 0 alone, with ``threads`` BLAS
    threads (one factorisation on the node's cores instead of one identical factorisation per
    rank); the other ranks wait without spinning (their signals deferred: mpirun relays
    SIGUSR1/2 to every rank, and rank 0 stops the run) and then return -- or raise -- what
    rank 0 did."""
    import pickle                                       # (only for this mode)
    from .algebra.comm import idle_barrier
    from .algebra.solvers import set_blas_threads, use_cores
    from .state import STOPS
    mpi = comm.tompi4py()
    if mpi.Get_rank() == 0:
        _, prev = use_cores(threads)
        try:
            out = ("return", work(PETSc.COMM_SELF))
        except BaseException as exc:            # noqa: B036  (handed to every rank, below)
            out = ("raise", exc)
        finally:
            if prev is not None:
                set_blas_threads(prev)
        try:
            pickle.dumps(out)
        except Exception:                       # an exception that does not pickle
            out = ("raise", RuntimeError(f"{type(out[1]).__name__}: {out[1]}"))
        idle_barrier(comm)
        mpi.bcast(out, root=0)
    else:
        with STOPS.deferred():
            idle_barrier(comm)
        out = mpi.bcast(None, root=0)
    kind, value = out
    if kind == "raise":
        value.collective = True                 # raised on every rank at once (cli.main)
        raise value
    return value


def _ensemble(args, petsc_args, comm, scene, source=None) -> int:
    """The ensemble branch (``parflow.ensemble``): ``scene`` the loaded scene of a new
    ensemble, or None for ``--restart FOLDER`` (the scene then comes from its index)."""
    # (here, not at the top: see the module docstring)
    from .cli import ranks_on_node
    from .ensemble import folder_of, read_index, run_ensemble
    from .scene import apply_settings, check_resources, load_scene
    from .algebra.solvers import check_options_on, insert_options
    from .state import InputError
    if scene is None:                         # --restart FOLDER
        folder = args.restart
        if args.scene or args.set or args.output:
            raise InputError("--restart FOLDER continues the ensemble in FOLDER with its own "
                             "scene and settings: do not give a scene, --set or --output with it")
        idx = collective(comm, read_index, folder)["attrs"]
        text, source = str(idx["scene"]), os.path.join(folder, "ensemble.h5")
        settings = [x for x in str(idx.get("scene_settings", "")).split("\n") if x]
        scene = apply_settings(load_scene(text, source), settings)
        stored, rps = int(idx["samples"]), int(idx["ranks_per_sample"])
        samples = args.samples if args.samples is not None else stored
        if samples < stored:
            raise InputError(f"--samples {samples}: the ensemble in {folder!r} has {stored} "
                             f"samples; a restart can add samples, not drop them")
        rps = args.ranks_per_sample or rps
    else:
        folder = args.output or folder_of(scene["output"]["path"])
        settings = list(scene.get("settings", []))
        samples = args.samples or scene["ensemble"]["samples"]
        rps = args.ranks_per_sample or scene["ensemble"]["ranks_per_sample"]
        if args.scene and _same_file(args.scene, folder):
            raise InputError(f"the output {folder!r} is the scene file itself")
    if not folder.strip():
        raise InputError("the ensemble's output folder is empty: give --output FOLDER")
    n = comm.getSize()
    if n % rps:
        raise InputError(f"ranks_per_sample = {rps} does not divide the job's {n} ranks: run on "
                         f"a multiple of {rps} ranks")
    if scene["solver"]["parallel"] == "threads" and rps > 1:
        raise InputError("solver.parallel = 'threads' runs a sample on one rank of its group: "
                         "an ensemble gets its parallelism from samples side by side; use "
                         "--ranks-per-sample 1 (or another solver.parallel)")
    collective(comm, check_resources, scene, rps, ranks_on_node(comm))
    cmdline = cmdline_option_names(petsc_args)
    insert_options(scene["petsc"], cmdline)
    check_options_on(comm, cmdline)
    base = dict(text=scene["text"], seed=scene["seed"], source=source or "<scene>",
                settings=settings, scene=scene)
    code = run_ensemble(base, folder, samples, rps, restart=bool(args.restart),
                        overwrite=args.overwrite, cmdline=cmdline, max_steps=args.max_steps,
                        quiet=args.quiet, retry=args.retry)
    if not args.no_plots and comm.getRank() == 0:
        try:
            from .plot import make_ensemble_plots    # (matplotlib only when figures are drawn)
            written, _ = make_ensemble_plots(folder)
            if written:
                logging.getLogger("parflow").info("figures: %s", ", ".join(written))
        except Exception as exc:    # a figure must never turn a good ensemble into a failure
            logging.getLogger("parflow").warning("plots not drawn (%s: %s); run python -m "
                                                 "parflow.plot %s", type(exc).__name__, exc, folder)
    return code


def _same_file(a: str, b: str) -> bool:
    try:
        return os.path.samefile(a, b)
    except (OSError, ValueError):
        return False


def _plots(path: str, quiet: bool) -> None:
    """Figures of the finished run, next to the file (python -m parflow.plot FILE redraws)."""
    log = logging.getLogger("parflow")
    try:
        from .plot import make_plots     # (matplotlib only when figures are drawn)
        res = make_plots(path)
    except Exception as exc:            # a figure must never turn a good run into a failure
        log.warning("plots not drawn (%s: %s); run python -m parflow.plot %s", type(exc).__name__, exc, path)
        return
    if res.written:
        log.info("figures: %s", ", ".join(res.written))


if __name__ == "__main__":
    sys.exit(main())
