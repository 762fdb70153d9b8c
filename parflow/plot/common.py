"""Figures for every model.

* ``stress_strain``     sigma and <V^2> against the accumulated strain, legs coloured (a
                        suspension's also as means over windows of equal strain).
* ``step_diagnostics``  dgamma, err, rejected, sigma_mismatch, length_error, residual, ...
                        against the step number.
* ``omega_min``         omega_min against sigma, log-log, reference slope -1/2.
"""
from __future__ import annotations

import math

import numpy as np
from matplotlib.figure import Figure

from ..post.fits import fit_power_law
from ..post.report import fmt_exp
from ..post.suspension import strain_window_means
from .base import QLABEL, Run, Skip, figure, new_figure, reference, title


def _leg_label(run: Run, k: int) -> str:
    ts = run.ts
    d = ts["direction"][ts["leg"] == k] if "direction" in ts else []
    word = "" if len(d) == 0 else (" forward" if d[-1] > 0 else " reverse")
    return f"leg {k}{word}"


def _by_leg(run: Run):
    """(leg index, row mask) for each leg present (one group if there is no leg column)."""
    ts = run.ts
    n = len(ts.get("step", next(iter(ts.values()), [])))
    if "leg" not in ts:
        return [(0, np.ones(n, bool))]
    return [(int(k), ts["leg"] == k) for k in np.unique(ts["leg"])]


@figure("stress_strain")
def fig_stress_strain(run: Run, fits: dict) -> Figure:
    """(g1) sigma and <V^2> against the accumulated strain, legs coloured, log-y."""
    ts = run.ts
    qs = [q for q in ("sigma", "V2") if q in ts and np.any(ts[q] > 0)]
    if "strain" not in ts or not qs:
        raise Skip("no strain with sigma or V2 in /timeseries")
    fig = new_figure(8.5, 2.9 * len(qs) + 0.6)
    axes = fig.subplots(len(qs), 1, squeeze=False, sharex=True)[:, 0]
    labels = {"sigma": r"$\sigma$", "V2": QLABEL["V2"]}
    steps_vary = run.model == "suspension" and "dgamma" in ts and len(ts["strain"]) > 40
    windows = max(10, min(200, len(ts["strain"]) // 20))
    legs = _by_leg(run)
    for ax, q in zip(axes, qs):
        for k, m in legs:
            x, y = ts["strain"][m], ts[q][m]
            ok = np.isfinite(y) & (y > 0)
            ax.semilogy(x[ok], y[ok], ".-", ms=2, lw=0.8, color=f"C{k % 10}",
                        label=_leg_label(run, k) if "leg" in ts else None)
            if steps_vary:
                # a suspension's per-step value depends on the step's size (a step cut
                # after an infeasible LCP can dip 10-100x): means over equal strain
                xc, yc = strain_window_means(x, ts["dgamma"][m], y, windows)
                ax.semilogy(xc, yc, "-", lw=1.4, color="k",
                            label=f"mean over {np.ptp(x) / windows:.2g} strain" if k == legs[0][0] else None)
        ax.set_ylabel(labels[q])
        ax.grid(True, alpha=0.3)
        if "leg" in ts or steps_vary:
            ax.legend(fontsize=8)
    if "phi" in ts:             # a suspension compressed while it flowed: phi on the right
        tw = axes[0].twinx()
        tw.plot(ts["strain"], ts["phi"], "-", lw=1.0, color="0.4")
        tw.set_ylabel("φ (grey)", color="0.4")
    axes[-1].set_xlabel(r"accumulated strain $\sum|d\gamma|$")
    fig.suptitle(title(run, "stress against strain") + f"\nstatus: {run.attrs.get('status', '?')}",
                 fontsize=10)
    return fig


_DIAG = [("dgamma", r"$|d\gamma|$", True), ("err", "err (step error estimate)", True),
         ("rejected", "rejected steps", False), ("sigma_mismatch", "σ mismatch", True),
         ("length_error", "length error", True), ("residual", "residual", True),
         ("backward_error", "backward error", True), ("proj_iter", "projection iterations", False),
         ("refinements", "refinements", False)]


@figure("step_diagnostics")
def fig_step_diagnostics(run: Run, fits: dict) -> Figure:
    """(g2) step diagnostics against the step number (log-y where positive)."""
    ts = run.ts
    present = [d for d in _DIAG if d[0] in ts]
    if "step" not in ts or not present or len(ts["step"]) < 2:
        raise Skip("no step diagnostics in /timeseries")
    ncol = 3
    nrow = math.ceil(len(present) / ncol)
    fig = new_figure(13, 2.8 * nrow + 0.6)
    axes = fig.subplots(nrow, ncol, squeeze=False, sharex=True).ravel()
    for ax, (q, lab, logy) in zip(axes, present):
        y = np.asarray(ts[q], float)
        if q == "dgamma":
            y = np.abs(y)
        pos = np.isfinite(y) & (y > 0)
        use_log = logy and pos.any()
        for k, m in _by_leg(run):
            mm = m & (pos if use_log else np.isfinite(y))
            ax.plot(ts["step"][mm], y[mm], ".", ms=2, color=f"C{k % 10}",
                    label=_leg_label(run, k) if "leg" in ts else None)
        if use_log:
            ax.set_yscale("log")
        ax.set_title(lab + ("" if use_log or not logy else " (no positive values)"), fontsize=9)
        ax.grid(True, alpha=0.3)
    for ax in axes[len(present):]:
        ax.set_visible(False)
    for ax in axes[max(0, len(present) - ncol):len(present)]:
        ax.set_xlabel("step")
        ax.xaxis.set_tick_params(labelbottom=True)
    if "leg" in ts:
        axes[0].legend(fontsize=7, markerscale=3)
    fig.suptitle(title(run, "step diagnostics"), fontsize=10)
    return fig


@figure("omega_min")
def fig_omega_min(run: Run, fits: dict) -> Figure:
    """(g3) omega_min against sigma (log-log), reference slope -1/2."""
    ts = run.ts
    if "omega_min" not in ts or "sigma" not in ts:
        raise Skip("no omega_min in /timeseries")
    w, s = np.asarray(ts["omega_min"], float), np.asarray(ts["sigma"], float)
    ok = np.isfinite(w) & np.isfinite(s) & (w > 0) & (s > 0)
    if not ok.any():
        raise Skip("omega_min was not computed (all NaN)")
    fig = new_figure(7, 5.2)
    ax = fig.subplots()
    d = ts["direction"] if "direction" in ts else np.ones(len(w), int)
    for sgn, lab, c in ((1, "forward", "C0"), (-1, "reverse", "C3")):
        m = ok & (d == sgn)
        if m.any():
            fit = fit_power_law(s[m], w[m])
            ax.loglog(s[m], w[m], "o", ms=4, color=c,
                      label=f"{lab}: fit slope {fmt_exp(fit[0])}" if np.isfinite(fit[0]) else lab)
    sx, wx = s[ok], w[ok]
    x0 = math.sqrt(sx.min() * sx.max())
    reference(ax, x0, float(np.exp(np.mean(np.log(wx)))) * 1.5, -0.5,
               max(3.0, math.sqrt(sx.max() / sx.min())), "reference slope -1/2")
    ax.set_xlabel(r"$\sigma$")
    ax.set_ylabel(r"$\omega_{min}$")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.suptitle(title(run, "lowest frequency against stress"), fontsize=10)
    return fig
