"""Figures of network ensembles across dz (docs/networks.md "Ensembles across dz"), from
``parflow.post.network_across_ensembles``:

* ``network_ensembles_across``   C (over sigma = 1e3-1e5, over 1e4-1e5, and of the averaged
                                 branch), C2, omega*, l_c against dz: the ensemble mean with its
                                 standard error, each sample (small grey dots), the weighted
                                 power-law fit (exponent ± WLS error, bootstrap error) and
                                 the predicted slope;
* ``network_ensembles_reverse``  the ensemble-averaged reversed branch |dsigma/dgamma|
                                 against sigma (the networks' curves of the ensemble's
                                 folders or tables, pooled as ``post.network_across_ensembles.
                                 pooled_curve``: mean ± standard error where every network
                                 counts), its local
                                 C = sigma^2 / <|dsigma/dgamma|>, and C dz^(1/2) (the curves
                                 coincide if C ~ dz^-1/2).

``python -m parflow.plot.network_ensembles FOLDER... [--out DIR]`` (FOLDER as for
``python -m parflow.post.network_across_ensembles``).
"""
from __future__ import annotations

import math
import sys

import numpy as np
from matplotlib.figure import Figure

from ..post.network import REVERSE_SIGMA
from ..post.network_across_ensembles import LC_SIGMA, analyse, format_table
from .base import across_ensembles_cli, new_figure, reference
from .network_across import _plain_log_ticks

LABELS = {"C": "C  (−dσ/dγ̃ = σ²/C, reversed branch, σ = 10³–10⁵)",
          "C_hi": "C_hi  (the same fit over σ = 10⁴–10⁵)",
          "C_curve": "C of the averaged branch (σ = 10³–10⁵, jackknife)",
          "C2": "C₂ = median ω_min √σ  (σ ≥ 10³)",
          "omega_star": "ω*  (gap of D(ω), γ = 0)",
          "l_c": f"l_c  (point response, {LC_SIGMA[0]:g} ≤ σ ≤ {LC_SIGMA[1]:g})"}


def _panel(ax, rows, fit, q, color, label_N):
    dz = np.array([t["dz"] for t in rows])
    m = np.array([t[q]["mean"] for t in rows])
    e = np.array([t[q]["sem"] for t in rows])
    for d, t in zip(dz, rows):
        v = np.asarray(t[q].get("values", []), float)
        ax.plot(np.full(v.size, d), v, ".", color="0.6", ms=3, zorder=1)
    ok = np.isfinite(m)
    ax.errorbar(dz[ok], m[ok], yerr=np.where(np.isfinite(e[ok]), e[ok], 0), fmt="o",
                color=color, ms=5, capsize=3, zorder=3,
                label=f"N = {label_N}: mean ± s.e. ({', '.join(str(t[q]['n']) for t in rows)})")
    boot = f"; boot. ± {fit['boot_err']:.2f}" if np.isfinite(fit["boot_err"]) else ""
    if np.isfinite(fit["exponent"]):
        xs = np.geomspace(dz[ok].min() / 1.15, dz[ok].max() * 1.15, 20)
        ax.plot(xs, fit["prefactor"] * xs ** fit["exponent"], "-", color=color, lw=1.5,
                alpha=0.7, label=f"fit δz^({fit['exponent']:.2f} ± {fit['err']:.2f}{boot})")
        xm = math.sqrt(dz[ok].min() * dz[ok].max())
        reference(ax, xm, fit["prefactor"] * xm ** fit["exponent"] * 1.25, fit["predicted"],
                  math.sqrt(dz[ok].max() / dz[ok].min()) * 1.1,
                  f"predicted slope {fit['predicted']:+g}", color="0.3")


def across_figure(res: dict) -> Figure:
    """C (three ways), C2, omega*, l_c against dz for every N of ``res`` (``analyse``)."""
    fig = new_figure(17, 9.5)
    axes = fig.subplots(2, 3).ravel()
    Ns = sorted({t["N"] for t in res["table"]})
    for ax, q in zip(axes, ("C", "C_hi", "C_curve", "C2", "omega_star", "l_c")):
        alldz = []
        for k, N in enumerate(Ns):
            rows = sorted((t for t in res["table"] if t["N"] == N), key=lambda t: t["dz"])
            if not any(np.isfinite(t[q]["mean"]) for t in rows):
                continue
            _panel(ax, rows, res["across"][N][q], q, f"C{k}", N)
            alldz += [t["dz"] for t in rows]
        ax.set_xscale("log")
        ax.set_yscale("log")
        if alldz:
            _plain_log_ticks(ax, alldz)
        ax.set_xlabel(r"$\delta z = 2d - z$")
        ax.set_ylabel(LABELS[q])
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    n = sum(t["n_samples"] for t in res["table"])
    fig.suptitle(f"Network ensembles across δz: {len(res['table'])} ensembles, {n} networks "
                 f"(grey: one network each)", fontsize=10)
    return fig


def reverse_figure(res: dict) -> Figure:
    """The averaged reversed branches of the ensembles of ``res`` (each entry's
    ``reverse_curve``: the networks' curves of its folders or tables, pooled):
    <|dsigma/dgamma|> against sigma; the local C of the averaged branch, sigma^2 / <|dsigma/
    dgamma|> (flat where the sigma^2 law holds); the same times dz^(1/2) (the curves of all
    dz coincide if C ~ dz^-1/2)."""
    fig = new_figure(17, 5.2)
    ax, ax2, ax3 = fig.subplots(1, 3)
    rows = sorted(res["table"], key=lambda t: (t["N"], t["dz"]))
    k = 0
    for t in rows:
        c = t.get("reverse_curve")
        if c is None:
            continue
        x, m, e, n = (np.asarray(c[k], float) for k in ("x", "mean", "sem", "count"))
        ok = np.isfinite(m) & (n == n.max()) & (m > 0)
        lo = np.where(m - e > 0, m - e, m * 0.5)
        col = f"C{k % 10}"
        ls = "-" if t["N"] == rows[0]["N"] else "--"
        k += 1
        lab = f"N = {t['N']}, δz = {t['dz']:.3g} ({int(n.max())} networks)"
        ax.fill_between(x[ok], lo[ok], (m + e)[ok], color=col, alpha=0.25, lw=0)
        ax.plot(x[ok], m[ok], ls, color=col, lw=1.3, label=lab)
        Cl, Ch, Cm = x ** 2 / (m + e), x ** 2 / lo, x ** 2 / m     # the band of C from m ± e
        for a_, f in ((ax2, 1.0), (ax3, math.sqrt(t["dz"]))):
            a_.fill_between(x[ok], Cl[ok] * f, Ch[ok] * f, color=col, alpha=0.25, lw=0)
            a_.plot(x[ok], Cm[ok] * f, ls, color=col, lw=1.3)
    for a_ in (ax, ax2, ax3):
        a_.set_xscale("log")
        a_.set_yscale("log")
        a_.axvspan(*REVERSE_SIGMA, color="0.93", zorder=0)
        a_.set_xlabel(r"$\sigma$")
        a_.grid(True, which="both", alpha=0.3)
    reference(ax, 1e4, 1e4 ** 2 / 0.03 / 5, 2.0, 30, "slope 2")
    ax.set_ylabel(r"ensemble mean of $|d\sigma/d\tilde\gamma|$ (reversed leg)")
    ax2.set_ylabel(r"local $C = \sigma^2 / \langle|d\sigma/d\tilde\gamma|\rangle$")
    ax3.set_ylabel(r"$C\,\delta z^{1/2}$")
    ax.legend(fontsize=7)
    ax.set_title("mean ± standard error where every network counts (grey: C fit window)",
                 fontsize=9)
    ax2.set_title("flat where −dσ/dγ = σ²/C", fontsize=9)
    ax3.set_title("curves coincide if C ∝ δz^−1/2", fontsize=9)
    return fig


def main(argv=None) -> int:
    return across_ensembles_cli(
        argv, "python -m parflow.plot.network_ensembles", "Figures of network ensembles across dz",
        analyse, format_table, "no network ensemble found",
        lambda res: [("network_ensembles_across", across_figure(res)),
                     ("network_ensembles_reverse", reverse_figure(res))])


if __name__ == "__main__":
    sys.exit(main())
