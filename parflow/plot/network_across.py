"""Network figures across several runs (one colour per z; docs/networks.md).

* ``fig3a_sigma_z``     sigma(gamma) for every run.
* ``fig3b_reverse_z``   -dsigma/dgamma against sigma, divided by dz^(1/2), and C(dz) fitted.
* ``fig4_omega_min_z``  omega_min(sigma), omega_min sqrt(sigma/dz), and C2(dz) fitted.
* ``fig5_dos_z``        D(omega) of every run with, inset, omega*(dz) fitted; D against
                        omega/dz.

The power laws across runs are :func:`parflow.post.network.across_fits`.
"""
from __future__ import annotations

import math

import matplotlib
import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import FixedLocator, NullFormatter, NullLocator

from ..post.network import C2_SIGMA_MIN, network_seed, network_z, spectrum_instants
from .base import Skip, figure, new_figure, reference
from .network import (OMEGA_LABEL, SIGMA_LABEL, branch_note, dos_curve, draw_sigma_gamma,
                      run_label, z_key)


def _across_title(runs: list, what: str) -> str:
    Ns = sorted({str(r.param("N")) for r in runs})
    seeds = sorted({str(network_seed(r)) for r in runs})
    zs = sorted(network_z(r) for r in runs)
    return (f"{what} — network, N={'/'.join(Ns)}, seed {'/'.join(seeds)}, "
            f"z = {zs[0]:.3g}–{zs[-1]:.3g} ({len(runs)} runs)")


def _run_colors(items):
    """One colour per z (runs at the same z, e.g. several seeds, share it); ``items``: runs
    or (run, fits) pairs."""
    runs = [x[0] if isinstance(x, tuple) else x for x in items]
    zs = sorted({z_key(r) for r in runs})
    if len(zs) <= 10:
        table = {z: f"C{k}" for k, z in enumerate(zs)}
    else:
        cmap = matplotlib.colormaps["viridis"]
        table = {z: cmap(k / (len(zs) - 1)) for k, z in enumerate(zs)}
    return [table[z_key(r)] for r in runs]


def _run_markers(items, base="."):
    """A marker per run among the runs at its z (first: ``base``, then x, +, ...)."""
    runs = [x[0] if isinstance(x, tuple) else x for x in items]
    seen: dict = {}
    out = []
    for r in runs:
        z = z_key(r)
        k = seen.get(z, 0)
        seen[z] = k + 1
        out.append((base, "x", "+", "1", "2", "3")[k % 6])
    return out


@figure("fig3a_sigma_z", models={"network"}, across=True)
def fig3a_sigma_z(runs: list, fits: list, across: dict) -> Figure:
    """Fig. 3a across runs: sigma(gamma) for every z."""
    runs2 = [r for r in runs if "sigma" in r.ts and "gamma" in r.ts]
    if not runs2:
        raise Skip("no run with sigma / gamma")
    fig = new_figure(8, 5.5)
    ax = fig.subplots()
    for r, c in zip(runs2, _run_colors(runs2)):
        draw_sigma_gamma(ax, r, c, c, label=run_label(r))
    ax.set_xlabel(r"$\gamma$ (strain coordinate)")
    ax.set_ylabel(SIGMA_LABEL)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(branch_note(), fontsize=10)
    fig.suptitle(_across_title(runs2, "Fig. 3a: stress against strain"), fontsize=10)
    return fig


@figure("fig3b_reverse_z", models={"network"}, across=True)
def fig3b_reverse_z(runs: list, fits: list, across: dict) -> Figure:
    """Fig. 3b across runs: -dsigma/dgamma against sigma; divided by dz^(1/2) (collapse if
    C ~ dz^(-1/2)); C against dz with its fit."""
    sel = [(r, f) for r, f in zip(runs, fits) if "reverse" in f]
    if not sel:
        raise Skip("no run with a reversed branch")
    fig = new_figure(17, 5.2)
    ax, ax2, ax3 = fig.subplots(1, 3)
    lo, hi = sel[0][1]["reverse"]["window"]
    allx = []
    for (r, f), c, mk in zip(sel, _run_colors(sel), _run_markers(sel)):
        br = f["reverse"]["branch"]
        ok = (br["dsdg"] < 0) & (br["sigma"] > 0)
        s, y = br["sigma"][ok], -br["dsdg"][ok]
        allx.append(s)
        fr = f["reverse"]
        lab = f"{run_label(r)}: a = {fr['slope']:.3f}, C = {fr['C']:.4g}"
        ax.loglog(s, y, mk, ms=3, color=c, label=lab)
        ax2.loglog(s, y / math.sqrt(f["dz"]), mk, ms=3, color=c)
    allx = np.concatenate(allx)
    for a_ in (ax, ax2):
        a_.axvspan(lo, hi, color="0.92", zorder=0)
        a_.set_xlabel(SIGMA_LABEL)
        a_.grid(True, alpha=0.3)
    if allx.size:
        xm = math.sqrt(allx.min() * allx.max())
        span = math.sqrt(allx.max() / allx.min())
        Cm = np.nanmedian([f["reverse"]["C"] for _, f in sel])
        dzm = np.nanmedian([f["dz"] for _, f in sel])
        if np.isfinite(Cm):
            reference(ax, xm, xm ** 2 / Cm / 5, 2.0, span, "reference slope 2 (÷5)")
            reference(ax2, xm, xm ** 2 / Cm / math.sqrt(dzm) / 5, 2.0, span,
                       "reference slope 2 (÷5)")
    ax.set_ylabel(r"$-d\sigma/d\tilde\gamma$  ($\tilde\gamma$: strain since the reversal)")
    ax2.set_ylabel(r"$(-d\sigma/d\tilde\gamma)\,/\,\delta z^{1/2}$")
    ax.legend(fontsize=7 if len(sel) <= 8 else 5.5, loc="upper left")
    ax2.legend(fontsize=8, loc="upper left")
    ax.set_title(f"reversed branches (grey: fit window σ ∈ [{lo:g}, {hi:g}])", fontsize=10)
    ax2.set_title("collapse if C ∝ δz^−1/2", fontsize=10)
    _across_panel(ax3, across.get("C"), "C (fit of 1/σ = 1/σ₀ + γ̃/C)", -0.5)
    fig.suptitle(_across_title([r for r, _ in sel], "Fig. 3b: reversed branch, "
                                                    "−dσ/dγ = σ²/C(δz)"), fontsize=10)
    return fig


def _across_panel(ax, a: dict | None, ylabel: str, pred: float, loglog: bool = True):
    """value(dz) with error bars, the weighted power-law fit and the predicted slope."""
    if a is None:
        ax.text(0.5, 0.5, "needs runs at 2 or more δz", ha="center", transform=ax.transAxes)
        ax.set_xlabel(r"$\delta z = 2d - z$")
        ax.set_ylabel(ylabel)
        return
    dz, y, e, f = a["dz"], a["value"], a["err"], a["fit"]
    ax.errorbar(dz, y, yerr=np.where(np.isfinite(e), e, 0), fmt="o", color="C0", ms=5,
                capsize=3, label="runs")
    if np.isfinite(f["exponent"]):
        xs = np.geomspace(dz.min() / 1.2, dz.max() * 1.2, 20)
        ax.plot(xs, f["prefactor"] * xs ** f["exponent"], "-", color="C0", lw=1.5, alpha=0.7,
                label=f"fit: δz^({f['exponent']:.2f} ± {f['err']:.2f})")
        xm = math.sqrt(dz.min() * dz.max())
        reference(ax, xm, f["prefactor"] * xm ** f["exponent"] * 1.3, pred,
                   math.sqrt(dz.max() / dz.min()) * 1.2, f"predicted slope {pred:+g}")
    if loglog:
        ax.set_xscale("log")
        ax.set_yscale("log")
        _plain_log_ticks(ax, dz)
    ax.set_xlabel(r"$\delta z = 2d - z$")
    ax.set_ylabel(ylabel)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)


def _plain_log_ticks(ax, x, y=None):
    """Log axes labelled at the data values (x, and y if given), plain numbers, no minor
    labels."""
    for axis, v in ((ax.xaxis, x), (ax.yaxis, y)):
        if v is None:
            continue
        v = np.asarray(v, float)
        v = np.unique([float(f"{t:.2g}") for t in v[np.isfinite(v) & (v > 0)]])
        axis.set_major_locator(FixedLocator(v))
        axis.set_major_formatter(lambda t, pos: f"{t:.3g}")
        axis.set_minor_locator(NullLocator())
        axis.set_minor_formatter(NullFormatter())


@figure("fig4_omega_min_z", models={"network"}, across=True)
def fig4_omega_min_z(runs: list, fits: list, across: dict) -> Figure:
    """Fig. 4 across runs: omega_min(sigma), omega_min sqrt(sigma / dz) (collapse if
    C2 ~ sqrt(dz)), C2 against dz."""
    sel = [(r, f) for r, f in zip(runs, fits) if "omega_min" in f]
    if not sel:
        raise Skip("no run with omega_min (observables.omega_min_every = 0)")
    fig = new_figure(17, 5.2)
    ax, ax2, ax3 = fig.subplots(1, 3)
    for (r, f), c in zip(sel, _run_colors(sel)):
        ts = r.ts
        w, s = np.asarray(ts["omega_min"], float), np.asarray(ts["sigma"], float)
        d = ts["direction"] if "direction" in ts else np.ones(w.size, int)
        ok = np.isfinite(w) & np.isfinite(s) & (w > 0) & (s > 0)
        for sgn, mk in ((1, "o"), (-1, "s")):
            m = ok & (d == sgn)
            lab = f"{run_label(r)}: C₂ = {f['omega_min']['C2']:.4g}" if sgn > 0 else None
            ax.loglog(s[m], w[m], mk, ms=2.5, color=c, mfc="none" if sgn < 0 else c, label=lab)
            ax2.semilogx(s[m], w[m] * np.sqrt(s[m] / f["dz"]), mk, ms=2.5, color=c,
                         mfc="none" if sgn < 0 else c)
    allx = np.concatenate([np.asarray(r.ts["sigma"], float) for r, _ in sel])
    allx = allx[np.isfinite(allx) & (allx > 0)]
    if allx.size:
        C2m = np.nanmedian([f["omega_min"]["C2"] for _, f in sel])
        reference(ax, math.sqrt(allx.min() * allx.max()),
                   C2m / (allx.min() * allx.max()) ** 0.25 * 2, -0.5,
                   math.sqrt(allx.max() / allx.min()), "reference slope −1/2")
    ax.set_ylabel(r"$\omega_{min}$ (dimensionless)")
    ax2.set_ylabel(r"$\omega_{min}\sqrt{\sigma}\,/\,\sqrt{\delta z}$")
    for a_ in (ax, ax2):
        a_.set_xlabel(SIGMA_LABEL)
        a_.grid(True, alpha=0.3)
        a_.axvline(C2_SIGMA_MIN, color="0.6", ls=":", lw=1)
    ax.legend(fontsize=7)
    ax.set_title("filled: forward, open: reversed", fontsize=10)
    ax2.set_title("collapse if C₂ ∝ √δz", fontsize=10)
    _across_panel(ax3, across.get("C2"), r"$C_2$ = median $\omega_{min}\sqrt{\sigma}$ "
                                         f"(σ ≥ {C2_SIGMA_MIN:g})", 0.5)
    fig.suptitle(_across_title([r for r, _ in sel], "Fig. 4: ω_min ≈ C₂(δz)/√σ"), fontsize=10)
    return fig


@figure("fig5_dos_z", models={"network"}, across=True)
def fig5_dos_z(runs: list, fits: list, across: dict) -> Figure:
    """Fig. 5 across runs: D(omega) of every run (its first spectrum) with omega* marked and,
    inset, omega* against dz with its fit; D against omega / dz (gap edges align if
    omega* ~ dz)."""
    sel = [(r, f) for r, f in zip(runs, fits) if spectrum_instants(r)]
    if not sel:
        raise Skip("no run with a spectrum (model.spectrum = 'none')")
    fig = new_figure(13.5, 5.4)
    ax, ax2 = fig.subplots(1, 2)
    for (r, f), c in zip(sel, _run_colors(sel)):
        a = spectrum_instants(r)[0]
        x, D = dos_curve(a)
        ost = f.get("omega_star")
        lab = run_label(r) + f", σ = {float(a.get('sigma', np.nan)):.3g}"
        if ost is not None and np.isfinite(ost["omega_star"]):
            lab += f": ω* = {ost['omega_star']:.4f} ± {ost['err']:.4f}"
            ax.axvline(ost["omega_star"], color=c, lw=0.8, ls=":")
        ax.loglog(x, D, "-", color=c, lw=1.2, marker=".", ms=3, label=lab)
        ax2.loglog(x / f["dz"], D, "-", color=c, lw=1.2, marker=".", ms=3)
    ax.set_xlabel(OMEGA_LABEL)
    ax.set_ylabel(r"$D(\omega)$ (normalised to 1)")
    ax.set_ylim(3e-3, 3.0)
    ax.legend(fontsize=7, loc="upper left")
    ax.set_title("first spectrum of each run (dotted: ω*, mean over the run's spectra)",
                 fontsize=10)
    ax2.set_xlabel(r"$\omega / \delta z$")
    ax2.set_ylabel(r"$D(\omega)$")
    ax2.set_title("gap edges align if ω* ∝ δz", fontsize=10)
    for a_ in (ax, ax2):
        a_.grid(True, alpha=0.3)
    a = across.get("omega_star")
    ins = ax.inset_axes([0.45, 0.1, 0.5, 0.38])
    _across_panel(ins, a, "ω*", 1.0)
    if a is not None:
        _plain_log_ticks(ins, a["dz"], a["value"])
    ins.tick_params(labelsize=7)
    ins.xaxis.label.set_fontsize(8)
    ins.yaxis.label.set_fontsize(8)
    if ins.get_legend() is not None:
        ins.legend(fontsize=6, loc="upper left")
    fig.suptitle(_across_title([r for r, _ in sel], "Fig. 5: density of states, gap ω* ∝ δz"),
                 fontsize=10)
    return fig
