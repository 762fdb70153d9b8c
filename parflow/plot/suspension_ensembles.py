"""Figures of suspension ensembles across phi (docs/suspensions.md "Ensembles across phi"),
from ``parflow.post.suspension_across_ensembles`` (Figs. 6e and 7b with error bars):

* ``suspension_ensembles_across``: sigma and p against phi with the divergence fits (phi_c
  free, and fixed at phi_J); sigma and p against dz = 4 - z2 (predicted slope -2.7); mu
  against phi (~0.1 near jamming); l_c against p (0.18) and against dz (-1/2, with the
  C(r) length); C2 = median omega_min sqrt(sigma) against dz (1/2); delta_gamma * sigma
  against sigma (flat); the exponents of omega_min(sigma) (-1/2) and delta_gamma(sigma) (-1)
  over the instants of each phi pooled, against phi.
  Every point is the ensemble mean with its standard error; grey dots are the samples.

``python -m parflow.plot.suspension_ensembles FOLDER... [--out DIR]`` (FOLDER as for
``python -m parflow.post.suspension_across_ensembles``).
"""
from __future__ import annotations

import math
import sys

import numpy as np
from matplotlib.figure import Figure

from ..post.suspension_across_ensembles import PHI_J, analyse, format_table
from .base import across_ensembles_cli, new_figure, reference


def _points(ax, rows, x, y, color, label, xkey_is_phi=False):
    """Means with standard errors (both axes where x is a measured quantity), samples grey."""
    xs = np.array([t["phi"] if xkey_is_phi else t[x]["mean"] for t in rows], float)
    xe = None if xkey_is_phi else np.array([t[x]["sem"] for t in rows], float)
    ym = np.array([t[y]["mean"] for t in rows], float)
    ye = np.array([t[y]["sem"] for t in rows], float)
    for k, t in enumerate(rows):
        v = np.asarray(t[y]["values"], float)
        xv = (np.full(v.size, xs[k]) if xkey_is_phi else np.asarray(t[x]["values"], float))
        ax.plot(xv, v, ".", color="0.65", ms=3, zorder=1)
    ok = np.isfinite(xs) & np.isfinite(ym)
    ax.errorbar(xs[ok], ym[ok], yerr=np.nan_to_num(ye[ok]),
                xerr=None if xe is None else np.nan_to_num(xe[ok]), fmt="o", color=color,
                ms=4.5, capsize=2.5, zorder=3, label=label)
    return xs[ok], ym[ok]


def _power(ax, fit, xs, color, label):
    if not np.isfinite(fit["exponent"]) or xs.size < 2:
        return
    xl = np.geomspace(xs.min() / 1.1, xs.max() * 1.1, 30)
    boot = f", boot. ± {fit['boot_err']:.2f}" if np.isfinite(fit["boot_err"]) else ""
    ax.plot(xl, fit["prefactor"] * xl ** fit["exponent"], "-", color=color, lw=1.4, alpha=0.7,
            label=f"{label}: slope {fit['exponent']:.2f} ± {fit['err']:.2f}{boot}")
    if np.isfinite(fit["predicted"]):
        xm = math.sqrt(xs.min() * xs.max())
        reference(ax, xm, fit["prefactor"] * xm ** fit["exponent"] * 1.3, fit["predicted"],
                  math.sqrt(xs.max() / xs.min()) * 1.1, f"predicted {fit['predicted']:+g}",
                  color="0.35")


def _power_panel(a, rows, fits, series, xlabel, title, ylog=True):
    """Log-log panel: for each (y, x, fit name, label, colour) the means, samples and the
    fitted power law of ``fits[name]`` with its predicted slope."""
    for y, x, name, lab, color in series:
        xs, _ = _points(a, rows, x, y, color, lab)
        _power(a, fits[name], xs, color, lab.split(" ")[0])
    a.set_xscale("log")
    if ylog:
        a.set_yscale("log")
    a.set_xlabel(xlabel)
    a.set_title(title, fontsize=9)


def across_figure(res: dict, N: int | None = None) -> Figure:
    """The eight panels of the module docstring for one N (default: the largest)."""
    Ns = sorted({t["N"] for t in res["table"]})
    N = N if N is not None else Ns[-1]
    rows = sorted((t for t in res["table"] if t["N"] == N), key=lambda t: t["phi"])
    fits = res["across"][N]
    fig = new_figure(20, 9.5)
    ax = fig.subplots(2, 4).ravel()
    # (a) sigma and p against phi, divergence fits
    a = ax[0]
    for k, y in enumerate(("sigma", "pressure")):
        _points(a, rows, "phi", y, f"C{k}", y if y == "sigma" else "p", xkey_is_phi=True)
        phi = np.array([t["phi"] for t in rows])
        for key, ls in (("free", "-"), ("fixed", ":")):
            f = fits[f"{y}_phi_{key}"]
            if not np.isfinite(f["beta"]):
                continue
            xl = np.linspace(phi.min() - 0.002, min(f["phi_c"] - 5e-4, phi.max() + 0.004), 60)
            err = f["beta_boot_err"]
            a.plot(xl, f["prefactor"] * (f["phi_c"] - xl) ** -f["beta"], ls, color=f"C{k}",
                   lw=1.2, label=f"φ_c = {f['phi_c']:.4f}{' (fixed)' if f['fixed'] else ''}, "
                                 f"β = {f['beta']:.2f} ± {err:.2f}")
    a.axvline(PHI_J, color="0.5", lw=0.8, ls="--")
    a.set_yscale("log")
    a.set_xlabel("φ")
    a.set_title("σ, p = A (φ_c − φ)^−β", fontsize=9)
    _power_panel(ax[1], rows, fits, (("sigma", "dz", "sigma_dz", "σ", "C0"),
                                     ("pressure", "dz", "pressure_dz", "p", "C1")),
                 "δz = 4 − z2", "σ, p against δz (Fig. 6e)")
    a = ax[2]                                               # mu against phi
    _points(a, rows, "phi", "mu", "C2", "μ = σ/p", xkey_is_phi=True)
    a.axhline(0.1, color="0.5", lw=0.8, ls="--", label="μ ≈ 0.1 near jamming")
    a.set_xlabel("φ")
    a.set_title("stress ratio μ", fontsize=9)
    _power_panel(ax[3], rows, fits, (("l_c", "pressure", "lc_p", "l_c (point response)", "C3"),),
                 "p", "l_c against p (Fig. 7b)")
    _power_panel(ax[4], rows, fits, (("l_c", "dz", "lc_dz", "l_c", "C3"),
                                     ("corr_length", "dz", "corr_dz", "C(r) 1/e length", "C4")),
                 "δz = 4 − z2", "lengths against δz (Fig. 7b)")
    _power_panel(ax[5], rows, fits, (("C2", "dz", "C2_dz", "C₂ = median ω_min √σ", "C5"),),
                 "δz = 4 − z2", "C₂ against δz (ω_min ≈ C₂/√σ)")
    _power_panel(ax[6], rows, fits, (("dgs", "sigma", "dgs_sigma", "δγ·σ (frozen contacts)",
                                      "C6"),), "σ", "δγ ∝ 1/σ: δγ·σ flat (Fig. 6c)",
                 ylog=False)
    # (h) the exponents of omega_min(sigma) and delta_gamma(sigma) within one phi
    a = ax[7]
    for k, (q, lab, pred) in enumerate((("omega_exp_pooled", "ω_min(σ)", -0.5),
                                        ("dgamma_exp_pooled", "δγ(σ)", -1.0))):
        phi = np.array([t["phi"] for t in rows]) + (k - 0.5) * 4e-4
        m = np.array([t[q]["mean"] for t in rows])
        e = np.array([t[q]["sem"] for t in rows])
        a.errorbar(phi, m, yerr=np.nan_to_num(e), fmt="o", color=f"C{k + 7}", ms=4.5,
                   capsize=2.5, label=f"exponent of {lab}, instants of a φ pooled (jackknife)")
        a.axhline(pred, color=f"C{k + 7}", lw=0.8, ls="--", label=f"predicted {pred:+g}")
    a.set_xlabel("φ")
    a.set_title("ω_min ∝ σ^x, δγ ∝ σ^y within one φ (Figs. 6c-d)", fontsize=9)
    for a in ax:
        a.grid(True, which="both", alpha=0.3)
        a.legend(fontsize=6.5)
    n = sum(t["n_samples"] for t in rows)
    fig.suptitle(f"Suspension ensembles across φ, N = {N}: {len(rows)} ensembles, {n} samples "
                 f"(mean ± standard error; grey: one sample each)", fontsize=10)
    return fig


def main(argv=None) -> int:
    return across_ensembles_cli(
        argv, "python -m parflow.plot.suspension_ensembles",
        "Figures of suspension ensembles across phi (PATH: ensemble folders, sample tables, or "
        "folders holding them)", analyse, format_table,
        "no suspension ensemble with a finished sample found",
        lambda res: [(f"suspension_ensembles_across_N{N}", across_figure(res, N))
                     for N in sorted({t["N"] for t in res["table"]})])


if __name__ == "__main__":
    sys.exit(main())
