"""Figures from parflow run files (PNG by default).

    python -m parflow.plot FILE [FILE ...] [--out/--outdir DIR] [--format png] [--only NAME]

writes every figure that each FILE supports into DIR (default: ``<FILE stem>_plots`` next to
FILE; with several files ``DIR/<FILE stem>/``), and with several files the figures across
runs (e.g. Figs. 3-5 across z) into DIR (default: ``across_runs_plots`` next to the first
file).  Prints the paths written on stdout, and on stderr which figures were skipped and
why, plus the fitted numbers.  Exit status: 0 success, 1 a figure failed, 2 a FILE is
missing or not a parflow run file (or DIR cannot be written).  Figures are chosen by the
run's model and by what it contains; a figure whose data are absent is skipped with the
reason, never an error.

The figures, one module per model, each registered beside its definition by
``@figure(name, models=...)`` (:mod:`.base`): :mod:`.common` (every model: stress_strain,
step_diagnostics, omega_min), :mod:`.chain` (paper Fig. 2), :mod:`.network` (Figs. 3, 4, 5,
8), :mod:`.network_across` (the same across z), :mod:`.suspension` (Figs. 6-7).  The numbers
they show and the lines printed are computed by :mod:`parflow.post`.

Python API: :func:`plot_file` (paths written), :func:`make_plots` (paths, skipped figures
and fits), :func:`make_across_plots`, :func:`load_run`, :func:`main`; the fits
:func:`chain_fits`, :func:`network_fits`, :func:`across_fits`, :func:`fit_omega_star`,
:func:`fit_power_law`, :func:`fit_power_law_err`, :func:`fit_divergence_point`,
:func:`fit_window`, :func:`typical_dgamma`, :func:`log_bin` and :func:`format_fits` are
those of :mod:`parflow.post`, re-exported here.

Only numpy, h5py and matplotlib (Agg canvas, no pyplot) are used: plotting needs neither
MPI nor PETSc.
"""
from __future__ import annotations

import argparse
import os
import sys
from dataclasses import dataclass

from matplotlib.figure import Figure

# the fits, re-exported (documented API of parflow.plot)
from ..post.chain import chain_fits  # noqa: F401
from ..post.fits import (fit_divergence_point, fit_power_law, fit_power_law_err,  # noqa: F401
                         fit_window, log_bin, typical_dgamma)
from ..post.network import across_fits, fit_omega_star, network_fits  # noqa: F401
from ..post.report import format_fits
# the figure modules register their figures on import, in this order (= the order drawn)
from . import chain, common, network, network_across, suspension  # noqa: F401
from .base import (ACROSS_FIGURES, FIGURES, MODELS, Run, RunFileError, Skip,  # noqa: F401
                   figure, load_run, save_figure)
from .ensemble import ENSEMBLE_FIGURES, make_ensemble_plots  # noqa: F401  (FOLDER of an ensemble)

__all__ = ["ACROSS_FIGURES", "FIGURES", "MODELS", "PlotResult", "Run", "RunFileError", "Skip",
           "across_fits", "chain_fits", "default_outdir", "figure", "fit_divergence_point",
           "fit_omega_star", "fit_power_law", "fit_power_law_err", "fit_window", "format_fits",
           "load_run", "log_bin", "main", "make_across_plots", "make_plots", "model_fits",
           "network_fits", "plot_file", "typical_dgamma"]


@dataclass
class PlotResult:
    written: list            # paths
    skipped: list            # (figure name, reason)
    failed: list             # (figure name, "ExceptionType: message")
    fits: dict               # the model's fits of the run (or, across runs, model/runs/across)


def model_fits(run: Run) -> dict:
    """The fitted numbers of a run, by its model's registered fits ({} for other models)."""
    spec = MODELS.get(run.model)
    return spec.fits(run) if spec is not None else {}


def default_outdir(path: str) -> str:
    stem = os.path.splitext(os.path.basename(path))[0]
    return os.path.join(os.path.dirname(os.path.abspath(path)), stem + "_plots")


def make_plots(path: str, outdir: str | None = None, fmt: str = "png",
               only: list[str] | None = None, run: Run | None = None) -> PlotResult:
    """Draw every figure the run file supports (``run``: the file already loaded).
    Raises :class:`RunFileError`."""
    run = run if run is not None else load_run(path)
    outdir = outdir or default_outdir(path)
    res = PlotResult([], [], [], {})
    try:
        fits = model_fits(run)
    except Exception as exc:  # the figures that need no fit are still drawn
        fits = {}
        res.failed.append(("fits", f"{type(exc).__name__}: {exc}"))
    res.fits = fits
    if not run.ts or not len(next(iter(run.ts.values()))):
        for spec in FIGURES:
            if not only or spec.name in only:
                res.skipped.append((spec.name, "no rows in /timeseries"))
        return res
    for name, models, draw in FIGURES:
        if only and name not in only:
            continue
        if models is not None and run.model not in models:
            res.skipped.append((name, f"model is {run.model!r}, not {'/'.join(sorted(models))}"))
            continue
        _draw(res, name, lambda: draw(run, fits), outdir, fmt)
    return res


def _draw(res: PlotResult, name: str, draw, outdir: str, fmt: str) -> None:
    """Draw one figure into ``res``: written, skipped (:class:`Skip`) or failed (any other
    exception: a bad figure must not cost the others)."""
    try:
        fig = draw()
    except Skip as exc:
        res.skipped.append((name, str(exc)))
        return
    except Exception as exc:
        res.failed.append((name, f"{type(exc).__name__}: {exc}"))
        return
    res.written.append(_save(fig, outdir, name, fmt))


def _save(fig: Figure, outdir: str, name: str, fmt: str) -> str:
    os.makedirs(outdir, exist_ok=True)
    return save_figure(fig, os.path.join(outdir, f"{name}.{fmt}"), fmt)


def default_across_outdir(paths: list[str]) -> str:
    return os.path.join(os.path.dirname(os.path.abspath(paths[0])), "across_runs_plots")


def make_across_plots(paths: list[str], outdir: str | None = None, fmt: str = "png",
                      only: list[str] | None = None, runs: list | None = None) -> PlotResult:
    """The figures that compare several runs (e.g. Fig. 3-5 across z), drawn from the runs
    of the model each figure is for.  ``fits`` of the result: dict(model, runs=[per-run
    fits], across=the model's across-run fits).  Raises :class:`RunFileError`."""
    runs = runs if runs is not None else [load_run(p) for p in paths]
    outdir = outdir or default_across_outdir(paths)
    res = PlotResult([], [], [], {})
    cache: dict = {}
    for name, models, draw in ACROSS_FIGURES:
        if only and name not in only:
            continue
        (model,) = models
        spec = MODELS.get(model)
        sel = [r for r in runs if r.model == model and r.ts and len(next(iter(r.ts.values())))]
        if spec is not None and spec.order is not None:
            sel.sort(key=spec.order)
        if len(sel) < 2:
            res.skipped.append((name, f"needs 2 or more {model} runs with rows in /timeseries "
                                      f"(got {len(sel)})"))
            continue
        if model not in cache:
            fl = [model_fits(r) for r in sel]
            cache[model] = (fl, spec.across(fl) if spec is not None and spec.across else {})
            res.fits = dict(model=model, runs=fl, across=cache[model][1])
        fl, ac = cache[model]
        _draw(res, name, lambda: draw(sel, fl, ac), outdir, fmt)
    return res


def plot_file(path: str, outdir: str | None = None, fmt: str = "png",
              only: list[str] | None = None) -> list[str]:
    """Draw every figure the run file supports (or those named in ``only``); returns the
    paths written.  Raises :class:`RunFileError`."""
    return make_plots(path, outdir, fmt, only).written


def _outdirs(paths: list[str], out: str | None) -> list[str | None]:
    """Where each file's own figures go: ``out`` for one file; ``out/<stem>`` for several
    (``<stem>-2``, ... if stems repeat); the default next to each file without ``out``."""
    if len(paths) == 1:
        return [out]
    if out is None:
        return [None] * len(paths)
    seen: dict = {}
    dirs = []
    for p in paths:
        stem = os.path.splitext(os.path.basename(p))[0]
        seen[stem] = seen.get(stem, 0) + 1
        dirs.append(os.path.join(out, stem if seen[stem] == 1 else f"{stem}-{seen[stem]}"))
    return dirs


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m parflow.plot",
        description="Draw the figures parflow run files support: each file's own figures, "
                    "and with several files the figures across runs (e.g. Figs. 3-5 across z).")
    ap.add_argument("files", nargs="+", metavar="FILE", help="parflow run file(s) (HDF5)")
    ap.add_argument("--out", "--outdir", dest="out", metavar="DIR", default=None,
                    help="output folder (default: <FILE stem>_plots next to FILE).  With "
                         "several files: each file's figures in DIR/<FILE stem>/, the figures "
                         "across runs in DIR (default: across_runs_plots next to the first "
                         "file)")
    ap.add_argument("--format", default="png", choices=("png", "pdf", "svg"),
                    help="image format (default png)")
    ap.add_argument("--only", metavar="NAME", action="append",
                    choices=[s.name for s in FIGURES + ACROSS_FIGURES],
                    help="draw only this figure (repeatable)")
    args = ap.parse_args(argv)
    if len(args.files) == 1 and os.path.isfile(os.path.join(args.files[0], "summary.h5")):
        return _ensemble_main(args.files[0], args.out, args.format)
    try:
        runs = [load_run(p) for p in args.files]
    except RunFileError as exc:
        print(f"parflow.plot: error: {exc}", file=sys.stderr)
        return 2
    several = len(args.files) > 1
    results = []
    try:
        for path, run, od in zip(args.files, runs, _outdirs(args.files, args.out)):
            results.append((path, make_plots(path, od, args.format, args.only, run=run)))
        if several:
            results.append((None, make_across_plots(args.files, args.out, args.format,
                                                    args.only, runs=runs)))
    except OSError as exc:                      # the output folder cannot be written
        where = exc.filename or args.out or default_outdir(args.files[0])
        print(f"parflow.plot: error: cannot write {where}: {exc.strerror or exc}",
              file=sys.stderr)
        return 2
    failed = False
    for path, res in results:
        for p in res.written:
            print(p)
        where = "" if not several else (f" ({path})" if path else " (across runs)")
        for name, why in res.skipped:
            print(f"parflow.plot: skipped {name}{where}: {why}", file=sys.stderr)
        for name, why in res.failed:
            print(f"parflow.plot: FAILED {name}{where}: {why}", file=sys.stderr)
        for line in format_fits(res.fits):
            print(f"parflow.plot: {line}", file=sys.stderr)
        failed |= bool(res.failed)
    return 1 if failed else 0


def _ensemble_main(folder: str, out: str | None, fmt: str) -> int:
    """``python -m parflow.plot FOLDER``: the averaged figures of an ensemble folder."""
    try:
        written, skipped = make_ensemble_plots(folder, out, fmt)
    except (OSError, ValueError, KeyError) as exc:
        print(f"parflow.plot: error: {folder}: {exc}", file=sys.stderr)
        return 2
    for p in written:
        print(p)
    for name, why in skipped:
        print(f"parflow.plot: skipped {name}: {why}", file=sys.stderr)
    return 0
