"""Large-N spectrum job on a saved state: ``mpirun -n 2 python -m parflow.spectrum STATE.h5``.

STATE.h5 is a parflow run file (the state at its checkpoint, or at ``--step`` if that step
has a snapshot) or a network file (``network_build.save_network``, at gamma = 0).  The rods
of that state give N = S S^T; its spectrum omega = sqrt(lambda(N)) is computed by

* ``--method low`` (default): the ``--k`` lowest eigenpairs, SLEPc Krylov-Schur with
  shift-and-invert at 0 on the force solver's Cholesky factor (``-spec_...`` options);
* ``--method interval``: every omega in [``--omega-min``, ``--omega-max``] by SLEPc spectrum
  slicing (needs the inertia of the factor: MUMPS, ``-spec_st_...`` options);
* ``--method dense``: all of it with numpy (Nc <= 10 000, rank 0), for checks.

The result goes to ``--output`` (default STATE.spectrum.h5) atomically (a temporary file
renamed at the end: never half-written), with the source, step, strain, method, sizes,
wall time and the command line.  Distributed like a run (``--parallel``: auto, replicated,
redundant, mumps); any ``-option`` with a single dash goes to PETSc.

The modules that import petsc4py (algebra, dynamics, models, provenance) are imported inside
the functions, after ``cli.init_petsc`` has initialised PETSc with the command line's options.
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

from . import __version__
from .cli import cmdline_option_names, init_petsc, run_main, split_petsc_args
from .errors import collective
from .geometry import pair_geometry
from .io import FORMAT, RunFile, atomic_h5, check_output_path, h5_attr, open_hdf5
from .state import InputError, State

METHODS = ("low", "interval", "dense")
DENSE_MAX = 10_000


def parser() -> argparse.ArgumentParser:
    # (before cli.init_petsc: PETSc starts without the command line, which init_petsc then
    # puts into its options database)
    from .algebra.solvers import PARALLEL_FACTORS
    p = argparse.ArgumentParser(prog="python -m parflow.spectrum",
                                description="Spectrum of N = S S^T of a saved state.",
                                epilog="Single-dash options (-spec_eps_ncv 64 ...) go to PETSc/SLEPc.")
    p.add_argument("state", help="parflow run file or network file")
    p.add_argument("--step", type=int, default=None,
                   help="use the snapshot of this step (default: the checkpoint, or the network)")
    p.add_argument("--method", choices=METHODS, default="low")
    p.add_argument("--k", type=int, default=6, help="number of lowest pairs for --method low")
    p.add_argument("--omega-min", type=float, default=0.0, help="--method interval: lower end")
    p.add_argument("--omega-max", type=float, default=None, help="--method interval: upper end")
    p.add_argument("--vectors", action="store_true", help="also store the eigenvectors (low)")
    p.add_argument("--parallel", choices=list(PARALLEL_FACTORS), default="auto")
    p.add_argument("--output", default=None, help="output HDF5 (default: STATE.spectrum.h5)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    return p


def load_state(path: str, step: int | None = None) -> tuple[State, dict]:
    """(State with bonds at the chosen instant, provenance dict) from a run or network file."""
    f = open_hdf5(path)
    is_run = f.attrs.get("format") == FORMAT
    f.close()
    if not is_run:
        # (models import petsc4py: here, after cli.init_petsc)
        from .models import network as nw
        from .models import network_build as nb
        net = nb.load_network(path)
        if step is not None:
            raise InputError("--step applies to run files, not to network files")
        return nw.state_from_network(net), dict(source_kind="network", where="network", step=0,
                                                model="network")
    with RunFile(path) as run:
        if "bonds" not in run.h5["initial"]:
            raise InputError(f"{path!r} is a run of model {run.model or '?'} without "
                             f"rods: its spectra are computed by the run's analyses")
        if step is None:
            if not run.has_checkpoint:
                raise InputError(f"{path!r} has no checkpoint: give --step of a snapshot")
            ck = run.checkpoint()
            s, gamma, where, step = ck["s"], float(ck["gamma"]), "checkpoint", int(ck["step"])
        else:
            have = run.snapshot_steps()
            if step not in have:
                raise InputError(f"{path!r} has no snapshot at step {step} (snapshots: "
                                 f"{have[:10]}{' ...' if len(have) > 10 else ''}; the scene's "
                                 f"observables.snapshot_every makes them)")
            snap = run.snapshot(step)
            s, gamma, where = snap["s"], float(snap["gamma"]), f"snapshots/{step:08d}"
        init = run.initial()
        state = State(s, init["h0"], init["E"], gamma, State.from_groups(init).bonds)
        return state, dict(source_kind="run", where=where, step=step, model=run.model)


def _dense_omega(state: State) -> np.ndarray:
    from .models.network import dense_spectrum  # (after cli.init_petsc)
    bd = state.bonds
    _, _, n, _ = pair_geometry(state.s, state.h, state.E, bd.i, bd.j, bd.shift)
    return dense_spectrum(n, bd, state.n)


def compute(comm, state: State, method: str, k: int = 6, interval=(0.0, None),
            parallel: str = "auto", vectors: bool = False) -> dict:
    """The spectrum of the state's N (collective).  Returns dict(omega, [modes], info...)."""
    # (after cli.init_petsc: see the module docstring)
    from .algebra.spectrum import omega_from_lambda, on_force_factor
    from .dynamics.bonded import BondedSystem
    nc = len(state.bonds)
    t0 = time.perf_counter()
    if method == "dense":
        if nc > DENSE_MAX:
            raise InputError(f"--method dense needs Nc <= {DENSE_MAX} (Nc = {nc}): use low or interval")
        omega = _dense_omega(state) if comm.getRank() == 0 else None
        omega = comm.tompi4py().bcast(omega, root=0)
        return dict(omega=omega, seconds=time.perf_counter() - t0, parallel="rank 0")
    system = BondedSystem(comm, state, "direct", parallel)
    try:
        system.evaluate(state.s, state.gamma, what="spectrum job")   # loads N and factors it
        if method == "low":
            if not 1 <= k < nc:
                raise InputError(f"--k must be in [1, Nc) = [1, {nc}), got {k}")
            spec = on_force_factor(system, k)
            try:
                lam, vecs = spec.solve(vectors=vectors)
                modes = None
                if vectors:
                    modes = np.array([system.ops.gather(v) for v in vecs])
                    for v in vecs:
                        v.destroy()
            finally:
                spec.destroy()
            out = dict(omega=omega_from_lambda(lam), eigenvalues=lam)
            if modes is not None:
                out["modes"] = modes
        else:
            out = _interval(system, *interval)
        out.update(seconds=time.perf_counter() - t0, parallel=system.parallel)
        return out
    finally:
        system.destroy()


def _interval(system, wmin: float, wmax: float | None) -> dict:
    """Every eigenvalue of N in [wmin^2, wmax^2] (``algebra.spectrum.slice_interval``)."""
    from .algebra.spectrum import omega_from_lambda, slice_interval  # (after cli.init_petsc)
    if wmax is None or not (0.0 <= wmin < wmax):
        raise InputError("--method interval needs 0 <= --omega-min < --omega-max")
    lam = slice_interval(system.ops.N, wmin, wmax)
    return dict(omega=omega_from_lambda(lam), eigenvalues=lam)


def write(path: str, result: dict, attrs: dict) -> None:
    """The spectrum file, whole or not at all (``io.atomic_h5``)."""
    with atomic_h5(path) as f:
        f.attrs["format"] = "parflow-spectrum-1"
        for k, v in attrs.items():
            f.attrs[k] = h5_attr(v)
        for k, v in result.items():
            if isinstance(v, np.ndarray):
                f.create_dataset(k, data=v)
            else:
                f.attrs[k] = h5_attr(v)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    app, petsc_args = split_petsc_args(argv, {"--step", "--method", "--k", "--omega-min",
                                              "--omega-max", "--parallel", "--output"})
    args = parser().parse_args(app)
    PETSc = init_petsc(petsc_args)
    return run_main("parflow.spectrum", lambda: _job(args, argv, petsc_args, PETSc))


def _same_file(a: str, b: str) -> bool:
    try:
        return os.path.samefile(a, b)
    except (OSError, ValueError):
        return False


def _job(args, argv, petsc_args, PETSc) -> int:
    # (after cli.init_petsc: see the module docstring)
    from .algebra.solvers import check_options_on
    from .provenance import git_commit, versions
    comm = PETSc.COMM_WORLD
    if args.output is not None and not args.output.strip():
        raise InputError("--output is empty: give a file name, or drop --output to write "
                         "STATE.spectrum.h5")
    if args.method == "low" and args.k < 1:
        raise InputError(f"--k must be >= 1, got {args.k}")
    collective(comm, lambda p: open_hdf5(p).close(), args.state)   # the input exists, is HDF5
    out = args.output or os.path.splitext(args.state)[0] + ".spectrum.h5"
    if collective(comm, _same_file, args.state, out):
        raise InputError(f"--output {out!r} is the input file itself: choose another file")
    check_options_on(comm, cmdline_option_names(petsc_args))   # -spec_..., -tau_...
    collective(comm, check_output_path, out, args.overwrite)
    state, prov = collective(comm, load_state, args.state, args.step)
    res = compute(comm, state, args.method, args.k, (args.omega_min, args.omega_max),
                  args.parallel, args.vectors)
    if comm.getRank() == 0:
        attrs = dict(source=os.path.abspath(args.state), method=args.method, gamma=state.gamma,
                     n_nodes=state.n, n_rods=len(state.bonds), n_ranks=comm.getSize(),
                     command=" ".join(["python -m parflow.spectrum"] + list(argv)),
                     parflow_version=__version__, versions=versions(), git_commit=git_commit(),
                     created=time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                     petsc_options=" ".join(petsc_args), **prov)
        write(out, res, attrs)
        w = res["omega"]
        print(f"parflow.spectrum: {len(w)} eigenvalue(s) of N (Nc = {len(state.bonds)}) by "
              f"{args.method} in {res['seconds']:.2f} s on {comm.getSize()} rank(s); "
              f"omega_min = {w[0]:.6g}" if len(w) else "no eigenvalue in the interval",
              file=sys.stderr)
        print(f"parflow.spectrum: wrote {out}", file=sys.stderr)
    comm.tompi4py().Barrier()
    return 0


if __name__ == "__main__":          # python -m parflow.spectrum STATE.h5 [options]
    sys.exit(main())
