"""The figure of a suspension run's averages in windows of equal strain, from
``parflow.post.suspension_windows``:

* ``suspension_windows``: sigma (top) and mu = sigma/p (bottom) averaged over each window of
  each run, with their block errors, at the window's centre in strain; one colour per run,
  its whole-range mean as a dotted line.  A stationary run scatters about its line.

``python -m parflow.plot.suspension_windows RUN.h5... [--width W] [--from-strain X]
[--to-strain Y] [--out DIR]`` (the windows as for ``python -m parflow.post.suspension_windows``).
"""
from __future__ import annotations

import os
import sys

import numpy as np
from matplotlib.figure import Figure

from ..post.suspension_windows import command_line, format_table
from .base import new_figure, save_figure


def windows_figure(res: dict) -> Figure:
    """sigma and mu in the windows of each run of ``res`` (``post.suspension_windows``)."""
    fig = new_figure(6.4, 5.6)
    axes = fig.subplots(2, 1, sharex=True)
    for k, r in enumerate(res["runs"]):
        color = f"C{k % 10}"
        x = np.array([0.5 * (w["lo"] + w["hi"]) for w in r["windows"]])
        label = os.path.splitext(os.path.basename(r["path"]))[0]
        for ax, q in zip(axes, ("sigma", "mu")):
            if q not in r["whole"]:
                continue
            y = np.array([w[q][0] for w in r["windows"]], float)
            e = np.array([w[q][1] for w in r["windows"]], float)
            ax.errorbar(x, y, yerr=np.nan_to_num(e), fmt="o-", color=color, ms=4, capsize=3,
                        label=f"{label} ({r['whole']['hi'] - r['whole']['lo']:.2g} strain)")
            ax.axhline(r["whole"][q][0], color=color, ls=":", lw=1)
    axes[0].set_ylabel("σ (strain-weighted window mean)")
    axes[1].set_ylabel("μ = σ/p")
    axes[1].set_xlabel("strain")
    for ax in axes:
        ax.grid(True, alpha=0.3)
    axes[0].legend(fontsize=7)
    axes[0].set_title(f"Window means over {res['width']:g} strain, block errors "
                      f"(dotted: each run's mean over its range)", fontsize=8.5)
    return fig


def _figures(res: dict) -> list:
    return [("suspension_windows", windows_figure(res))]


def _output_arguments(ap) -> None:
    ap.add_argument("--out", default=None, help="output folder (default: the first RUN's)")
    ap.add_argument("--format", default="png", choices=("png", "pdf", "svg"))


def main(argv=None) -> int:
    name = "suspension_windows"
    args, res = command_line(argv, f"python -m parflow.plot.{name}",
                             "sigma and mu of suspension runs in windows of equal strain: are "
                             "they stationary?", _output_arguments)
    if res is None:
        return 2
    out = args.out or os.path.dirname(args.paths[0]) or "."
    try:
        os.makedirs(out, exist_ok=True)
        for fname, fig in _figures(res):
            print(save_figure(fig, os.path.join(out, f"{fname}.{args.format}"), args.format))
    except OSError as e:
        print(f"{name}: cannot write {out}: {e.strerror or e}", file=sys.stderr)
        return 2
    print("\n".join(format_table(res)), file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
