"""What every figure module uses: the run-file reader (for now), :class:`Skip`, the figure
registry with its :func:`figure` decorator, the per-model table (:func:`register_model`),
and the drawing helpers (Agg canvas, reference slopes, fit lines, colours, titles).

A figure module registers each figure beside its definition::

    @figure("fig3b_reverse", models={"network"})
    def fig3b_reverse(run, fits) -> Figure: ...

    @figure("fig3b_reverse_z", models={"network"}, across=True)
    def fig3b_reverse_z(runs, fits, across) -> Figure: ...

``models=None``: the figure applies to every model.  An across-run figure is for exactly one
model.  Figures are drawn in the order they are registered (the order in which
``parflow.plot`` imports the figure modules).  A model's fits, the fits across its runs, the
order of its runs and the extra words of its titles are given once per model by
:func:`register_model`.
"""
from __future__ import annotations

import argparse
import math
import os
import sys
from dataclasses import dataclass
from typing import Callable, NamedTuple

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.cm import ScalarMappable
from matplotlib.colors import LogNorm, Normalize
from matplotlib.figure import Figure

from ..errors import InputError
from ..post.network_across_ensembles import analyse_or_report, missing_path
from ..post.runs import Run, load


class RunFileError(Exception):
    """FILE is missing or is not a parflow run file (reported as one line, exit status 2)."""


class Skip(Exception):
    """A figure whose data are absent: skipped, with the reason."""


# ---------------------------------------------------------------------------------------
# Reading (through io.RunFile, the one reader of the format)
# ---------------------------------------------------------------------------------------
def load_run(path: str) -> Run:
    """Read a parflow run file (``post.runs.load``, through ``io.RunFile``) into a
    :class:`Run`.  Raises :class:`RunFileError` with a one-line message."""
    if not os.path.exists(path):
        raise RunFileError(f"{path}: no such file")
    if os.path.isdir(path):
        raise RunFileError(f"{path}: is a directory, not a parflow run file")
    try:
        return load(path)
    except InputError as exc:
        raise RunFileError(f"{path}: not a parflow run file ({exc})") from None


# ---------------------------------------------------------------------------------------
# Registry
# ---------------------------------------------------------------------------------------
class FigureSpec(NamedTuple):
    """A registered figure: its name (the file stem), the models it applies to (None: any)
    and the function that draws it."""
    name: str
    models: frozenset | None
    draw: Callable


FIGURES: list[FigureSpec] = []          # one run: draw(run, fits) -> Figure
ACROSS_FIGURES: list[FigureSpec] = []   # several runs of one model: draw(runs, fits, across)


def figure(name: str, models=None, across: bool = False):
    """Register the decorated function as figure ``name`` for ``models`` (a set of model
    names; None: every model), or with ``across`` as a figure across several runs of the
    one model in ``models``."""
    models = None if models is None else frozenset(models)
    if across and (models is None or len(models) != 1):
        raise ValueError(f"across-run figure {name!r} must name exactly one model")

    def register(draw):
        table = ACROSS_FIGURES if across else FIGURES
        if any(s.name == name for s in FIGURES + ACROSS_FIGURES):
            raise ValueError(f"figure {name!r} is registered twice")
        table.append(FigureSpec(name, models, draw))
        return draw
    return register


@dataclass(frozen=True)
class ModelSpec:
    """What the driver needs to know of a model beyond its figures."""
    fits: Callable                      # fits(run) -> dict (the numbers of one run)
    across: Callable | None = None      # across(list of fits) -> dict (several runs)
    order: Callable | None = None       # sort key of its runs in across-run figures
    title: Callable | None = None       # title(run, bits) -> bits (words of the titles)


MODELS: dict[str, ModelSpec] = {}


def register_model(name: str, fits: Callable, across: Callable | None = None,
                   order: Callable | None = None, title: Callable | None = None) -> None:
    """Give model ``name`` its fits, across-run fits, run order and title words."""
    MODELS[name] = ModelSpec(fits, across, order, title)


# ---------------------------------------------------------------------------------------
# Figure helpers
# ---------------------------------------------------------------------------------------
def new_figure(w, h) -> Figure:
    """A w x h inch figure on an Agg canvas (no pyplot), constrained layout."""
    fig = Figure(figsize=(w, h), dpi=110, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def save_figure(fig: Figure, path: str, fmt: str | None = None, **kw) -> str:
    """Save ``fig`` to ``path`` whole or not at all (a twin ``path.part``, renamed over
    ``path``; removed on any error): a figure is never left half-written.  ``fmt`` defaults
    to the extension of ``path``."""
    fmt = fmt or os.path.splitext(path)[1].lstrip(".") or "png"
    tmp = path + ".part"
    try:
        fig.savefig(tmp, format=fmt, **kw)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise
    return path


def reference(ax, x0, y0, slope, span, label, **kw):
    """A dashed power law y = y0 (x/x0)^slope over [x0/span, x0*span]."""
    if not (np.isfinite(x0) and np.isfinite(y0) and x0 > 0 and y0 > 0):
        return
    xs = np.geomspace(x0 / span, x0 * span, 20)
    kw.setdefault("color", "k")
    ax.plot(xs, y0 * (xs / x0) ** slope, "--", lw=1.2, label=label, **kw)


def fit_line(ax, fit, lo, hi, label, color):
    """The fitted power law ``fit`` = (exponent, prefactor) over [lo, hi], thick and pale."""
    p, A = fit
    if np.isfinite(p) and np.isfinite(lo) and np.isfinite(hi):
        xs = np.geomspace(lo, hi, 20)
        ax.plot(xs, A * xs ** p, "-", color=color, lw=2.5, alpha=0.45, label=label)


def anchor(fit, lo, hi):
    """A point on the fitted line in the middle of the window (to hang reference slopes)."""
    p, A = fit
    if not (np.isfinite(p) and np.isfinite(lo) and np.isfinite(hi)):
        return float("nan"), float("nan")
    xm = math.sqrt(lo * hi)
    return xm, A * xm ** p


def positive(x, y):
    """The points with x and y positive and finite."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    ok = np.isfinite(x) & np.isfinite(y) & (x > 0) & (y > 0)
    return x[ok], y[ok]


QLABEL = {"V2": r"$\langle V^2\rangle$", "dtheta2": r"$\langle\Delta\theta^2\rangle$",
          "thetadot2": r"$\langle\dot\theta^2\rangle$"}


def title(run: Run, what: str) -> str:
    """``what — FILE (model, N=..., and the model's own words)``."""
    name = os.path.basename(run.path)
    bits = [f"{run.model}"]
    if run.param("N") is not None:
        bits.append(f"N={run.param('N')}")
    spec = MODELS.get(run.model)
    if spec is not None and spec.title is not None:
        bits = spec.title(run, bits)
    return f"{what} — {name} ({', '.join(bits)})"


def instant_colors(inst, key="V2", cmap="viridis"):
    """One colour per analysis instant by its value of ``key`` (log scale), and the
    mappable for the colour bar."""
    v = np.array([float(a.get(key, np.nan)) for a in inst])
    ok = np.isfinite(v) & (v > 0)
    if ok.sum() >= 2 and v[ok].max() > v[ok].min():
        norm = LogNorm(v[ok].min(), v[ok].max())
    else:
        norm = Normalize(0, 1)
    sm = ScalarMappable(norm=norm, cmap=cmap)
    cols = [sm.to_rgba(x) if np.isfinite(x) and x > 0 else (0.5, 0.5, 0.5, 1) for x in v]
    return cols, sm


def across_ensembles_cli(argv, prog: str, description: str, analyse, format_table,
                         empty: str, figures) -> int:
    """The command line of an across-ensembles figure module: PATH... [--out DIR] [--format];
    ``figures(res)`` gives (name, Figure) pairs for ``res = analyse(paths)``; the table on
    stderr.  Exit 2 with one line: ``empty`` when nothing is found, or the ValueError of a
    bad input.  --out defaults to the first PATH (its folder, for a file)."""
    ap = argparse.ArgumentParser(prog=prog, description=description)
    ap.add_argument("folders", nargs="+", metavar="PATH",
                    help="ensemble folders (or what the analysis reads), or folders holding them")
    ap.add_argument("--out", default=None, help="output folder (default: the first PATH)")
    ap.add_argument("--format", default="png", choices=("png", "pdf", "svg"))
    args = ap.parse_args(argv)
    name = prog.rsplit(" ", 1)[-1]
    if missing_path(args.folders, name):
        return 2
    res = analyse_or_report(analyse, (args.folders,), name, empty)
    if res is None:
        return 2
    first = args.folders[0]
    out = args.out or (first if os.path.isdir(first) else os.path.dirname(first) or ".")
    os.makedirs(out, exist_ok=True)
    for fname, fig in figures(res):
        p = save_figure(fig, os.path.join(out, f"{fname}.{args.format}"), args.format)
        print(p)
    print("\n".join(format_table(res)), file=sys.stderr)
    return 0
