"""Figures of an ensemble folder (``python -m parflow.plot FOLDER``): each averaged curve of
``FOLDER/summary.h5`` (``parflow.post.ensemble``) as its mean with a band of one standard
error, over the samples drawn thin.  Registered like the one-run figures, in a table of
their own (:data:`ENSEMBLE_FIGURES`: name -> draw(summary, curve name) -> Figure), one
figure per curve the summary holds (``ensemble_<curve>``)."""
from __future__ import annotations

import os

import numpy as np

from ..post.ensemble import read_summary
from .base import Skip, new_figure, save_figure

ENSEMBLE_FIGURES: dict = {}


def ensemble_figure(name: str):
    def register(draw):
        ENSEMBLE_FIGURES[name] = draw
        return draw
    return register


@ensemble_figure("ensemble_curve")
def ensemble_curve(summary: dict, curve: str):
    """One averaged curve: the samples (thin, grey), the mean (line) and mean +- one
    standard error (band) where every sample covers the grid; the ensemble fit of <V^2> on
    the chain's forward curve (its window shaded)."""
    c = summary["curves"][curve]
    x, m, e, n, vals = c["x"], c["mean"], c["sem"], c["count"], c["values"]
    ok = np.isfinite(m) & (n >= 1)
    if not ok.any():
        raise Skip(f"curve {curve}: no sample covers the grid")
    ok &= n == n[ok].max()        # the mean where every sample counts (no jumps at the ends)
    fig = new_figure(6.0, 4.2)
    ax = fig.add_subplot()
    for row in vals:
        ax.plot(x, row, "-", color="0.7", lw=0.6)
    band = ok & np.isfinite(e)
    lo = m - e
    if c.get("yscale") == "log":
        lo = np.where(lo > 0, lo, m * 1e-3)
    ax.fill_between(x[band], lo[band], (m + e)[band], color="C0", alpha=0.3,
                    label="mean ± standard error")
    ax.plot(x[ok], m[ok], "-", color="C0", lw=1.8, label=f"mean of {int(n.max())} samples")
    fit = summary["ensemble_fits"].get("V2_forward_exponent") if curve == "V2_forward" else None
    if fit is not None and np.isfinite(fit["value"]):
        ax.axvspan(fit["window_lo"], fit["window_hi"], color="C1", alpha=0.08,
                   label=f"fit: exponent {fit['value']:.3f} ± {fit['jackknife_err']:.3f} (jackknife)")
    ax.set_xscale(str(c.get("xscale", "linear")))
    ax.set_yscale(str(c.get("yscale", "linear")))
    ax.set_xlabel(str(c.get("xlabel", "")))
    ax.set_ylabel(str(c.get("ylabel", curve)))
    ax.set_title(f"{curve} — ensemble ({summary['attrs'].get('model', '')}, "
                 f"{summary['attrs'].get('n_used', 0)} samples)", fontsize=9)
    ax.legend(fontsize=8)
    return fig


def make_ensemble_plots(folder: str, outdir: str | None = None, fmt: str = "png") -> tuple:
    """Draw the figures of ``FOLDER/summary.h5`` into ``outdir`` (default FOLDER/plots).
    Returns (paths written, [(name, reason skipped)])."""
    path = os.path.join(folder, "summary.h5")
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{folder}: no summary.h5 (not an ensemble folder, or not finished)")
    summary = read_summary(path)
    outdir = outdir or os.path.join(folder, "plots")
    written, skipped = [], []
    for curve in summary["curves"]:
        name = f"ensemble_{curve}"
        try:
            fig = ENSEMBLE_FIGURES["ensemble_curve"](summary, curve)
        except Skip as exc:
            skipped.append((name, str(exc)))
            continue
        os.makedirs(outdir, exist_ok=True)
        written.append(save_figure(fig, os.path.join(outdir, f"{name}.{fmt}"), fmt))
    return written, skipped
