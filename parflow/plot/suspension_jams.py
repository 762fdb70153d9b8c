"""The figure of where flowing suspensions shear-jam while compressed, across N, from
``parflow.post.suspension_jams``:

* ``suspension_jams_phiSJ``: the phi of each sample's certified shear jam (grey) and their
  mean with its standard error against N, one colour per compression rate; the fit
  phi_SJ(N) = phi_inf - a N^-0.71 where three sizes or more allow it, with phi_inf and its
  error, and with four sizes or more the fit with the exponent free (dotted); phi_J = 0.843
  of the mixture (dashed).  Samples that jammed at constant phi (after
  reaching ``compress_to``) are drawn as open circles; samples that ended or were stopped
  still flowing, as triangles pointing up at the phi they reached (a lower bound of their
  jam; not in the means or the fits).
* ``suspension_jams_rate`` (with two rates or more): the same jams against the compression
  rate, one colour per N.
* ``suspension_jams_per_strain`` (where one packing fraction has runs at two sizes or more):
  the certified jams per unit strain at constant phi against N, with the exact Poisson 95 %
  interval; a size with no jam yet is drawn as its upper bound (a triangle pointing down);
  each point labelled with its count and strain.
* ``suspension_excursions`` (where a constant-phi row has stress excursions recorded): the
  excursions per unit strain whose peak sigma reaches each level, against the level, one
  line per (N, phi); the certified jams per unit strain of the same samples beside them (a
  dashed line in the same colour: a jam is an excursion that does not come back; samples
  read from a table without excursions are in neither).

``python -m parflow.plot.suspension_jams PATH... [--out DIR]`` (PATH as for
``python -m parflow.post.suspension_jams``).
"""
from __future__ import annotations

import math
import sys

import numpy as np
from matplotlib.figure import Figure

from ..post.suspension_jams import FLOWING, PHI_J, analyse, format_table
from .base import across_ensembles_cli, new_figure


def _samples(ax, records, x_of) -> None:
    """Each shear jam among ``records`` at (x_of(record), its phi): grey, open if it came at
    constant phi."""
    for r in records:
        if r["shear_jam"]:
            ax.plot(x_of(r), r["phi"], "o", ms=3.5, zorder=1,
                    color="0.6" if not r["constant_phi"] else "none", markeredgecolor="0.5")


def _means(ax, rows, x, color: str, what: str, **style) -> None:
    """The mean phi of the shear jams of each group (table row) in ``rows`` at ``x``, with
    its standard error; the legend names ``what`` and the jams behind each mean."""
    m = np.array([t["phi_mean"] for t in rows], float)
    e = np.array([t["phi_sem"] for t in rows], float)
    ax.errorbar(x, m, yerr=np.nan_to_num(e), color=color, ms=6, capsize=3, zorder=3,
                label=f"{what}: mean ± s.e. "
                      f"({', '.join(str(t['n_shear_jams']) for t in rows)} jams)", **style)


def _finish(ax, xlabel: str, title: str) -> None:
    ax.axhline(PHI_J, color="k", ls="--", lw=0.8, label=f"φ_J = {PHI_J} (the mixture)")
    ax.set_xscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("φ at the shear jam")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="lower right")
    ax.set_title(title, fontsize=8.5)


def phi_sj_figure(res: dict) -> Figure:
    fig = new_figure(6.4, 4.6)
    ax = fig.add_subplot(1, 1, 1)
    rates = sorted({t["compress_rate"] for t in res["table"]})
    for k, rate in enumerate(rates):
        rows = [t for t in res["table"] if t["compress_rate"] == rate]
        color = f"C{k}"
        shift = 1 + 0.03 * (k - 0.5 * (len(rates) - 1))   # the rates' samples side by side
        _samples(ax, [r for r in res["records"] if r["compress_rate"] == rate],
                 lambda r: r["N"] * shift)
        up = [(r["N"], r["phi"]) for r in res["records"]
              if r["compress_rate"] == rate and r["status"] in FLOWING and not r["shear_jam"]]
        if up:
            x, y = np.array(up, float).T
            ax.plot(x * shift, y, "^", ms=5, zorder=2,
                    color="none", markeredgecolor=color,
                    label=f"still flowing at {rate:g} per unit strain (a lower bound), "
                          f"{len(up)}")
        rows = [t for t in rows if t["n_shear_jams"]]
        Ns = np.array([t["N"] for t in rows], float)
        _means(ax, rows, Ns, color, f"compressed at {rate:g} per unit strain", fmt="s")
        f = res["fits"].get(rate, {})
        if f and not math.isnan(f.get("phi_inf", math.nan)):
            n = np.geomspace(Ns.min() / 1.5, 1e6, 200)
            ax.plot(n, f["phi_inf"] - f["a"] * n ** -f["x"], "-", color=color, lw=1,
                    label=f"φ_∞ − a N^−{f['x']:g}: φ_∞ = {f['phi_inf']:.4f} ± "
                          f"{f['phi_inf_err']:.4f} (χ²/dof {f['chi2_dof']:.1f})")
        g = res.get("fits_free", {}).get(rate, {})
        if g and not math.isnan(g.get("phi_inf", math.nan)):
            n = np.geomspace(Ns.min() / 1.5, 1e6, 200)
            ax.plot(n, g["phi_inf"] - g["a"] * n ** -g["x"], ":", color=color, lw=1.2,
                    label=f"exponent free: N^−{g['x']:.2f}, φ_∞ = {g['phi_inf']:.4f} "
                          f"({g['phi_inf_range'][0]:.4f}–{g['phi_inf_range'][1]:.4f})")
    n = sum(t["n_samples"] for t in res["table"])
    _finish(ax, "N", f"Where a flowing suspension shear-jams while compressed: {n} samples\n"
                     "(grey: one each; open: jammed at constant φ, after compress_to; "
                     "▵: still flowing)")
    return fig


def phi_sj_rate_figure(res: dict) -> Figure:
    """phi_SJ against the compression rate, one colour per N: each sample's jam (grey; open
    if at constant phi), the mean with its standard error joined across rates."""
    fig = new_figure(6.4, 4.6)
    ax = fig.add_subplot(1, 1, 1)
    sizes = sorted({t["N"] for t in res["table"] if t["n_shear_jams"]})
    for k, N in enumerate(sizes):
        color = f"C{k}"
        shift = 1 + 0.04 * (k - 0.5 * (len(sizes) - 1))   # the sizes' samples side by side
        _samples(ax, [r for r in res["records"] if r["N"] == N],
                 lambda r: r["compress_rate"] * shift)
        rows = sorted((t for t in res["table"] if t["N"] == N and t["n_shear_jams"]),
                      key=lambda t: t["compress_rate"])
        x = np.array([t["compress_rate"] for t in rows], float) * shift
        _means(ax, rows, x, color, f"N = {N}", fmt="s-", lw=1)
    _finish(ax, "compression rate dφ/dγ",
            "Where a flowing suspension shear-jams, against the compression rate\n"
            "(grey: one sample each; open: jammed at constant φ, after compress_to)")
    return fig


def _rate_phis(res: dict) -> list:
    """The packing fractions whose constant-phi rates cover two sizes or more."""
    rows = res.get("rates", [])
    return sorted(p for p in {r["phi"] for r in rows}
                  if len({r["N"] for r in rows if r["phi"] == p}) > 1)


def jam_rate_figure(res: dict) -> Figure:
    """Certified jams per unit strain at constant phi against N (``res["rates"]``), one
    colour per phi with runs at two sizes or more: the rate with its exact Poisson interval,
    or, with no jam yet, the interval's upper end (a triangle pointing down)."""
    fig = new_figure(6.4, 4.6)
    ax = fig.add_subplot(1, 1, 1)
    for k, phi in enumerate(_rate_phis(res)):
        rows = sorted((r for r in res["rates"] if r["phi"] == phi), key=lambda r: r["N"])
        color = f"C{k}"
        hit = [r for r in rows if r["n_jams"] > 0]
        if hit:
            x = np.array([r["N"] for r in hit], float)
            y = np.array([r["rate"] for r in hit], float)
            lo = y - np.array([r["rate_ci"][0] for r in hit], float)
            hi = np.array([r["rate_ci"][1] for r in hit], float) - y
            ax.errorbar(x, y, yerr=[lo, hi], fmt="o-", color=color, capsize=3, ms=5,
                        label=f"φ = {phi:.4f}: jams per unit strain (Poisson 95 %)")
        zero = [r for r in rows if r["n_jams"] == 0]
        if zero:
            ax.plot([r["N"] for r in zero], [r["rate_ci"][1] for r in zero], "v", ms=7,
                    color="none", markeredgecolor=color,
                    label=f"φ = {phi:.4f}: no jam yet (upper end of the 95 % interval)")
        for r in rows:
            y = r["rate"] if r["n_jams"] else r["rate_ci"][1]
            ax.annotate(f"{r['n_jams']} in {r['strain']:.3g}", (r["N"], y), fontsize=7,
                        textcoords="offset points", xytext=(5, 4))
    ax.set_xscale("log")
    ax.set_yscale("log")
    sizes = [r["N"] for r in res["rates"] if r["phi"] in _rate_phis(res)]
    ax.set_xlim(min(sizes) / 1.3, max(sizes) * 1.8)        # room for the labels
    ax.set_xlabel("N")
    ax.set_ylabel("certified jams per unit strain")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="lower left")
    ax.set_title("Shear jams of flowing suspensions at constant φ, against N\n"
                 "(labels: jams in strain at that φ)", fontsize=8.5)
    return fig


def _excursion_rows(res: dict) -> list:
    """The constant-phi rows with stress excursions recorded (a strain to divide by)."""
    return [r for r in res.get("rates", [])
            if r.get("excursions") and r["excursions"]["n_samples"]
            and r["excursions"]["strain"] > 0]


def excursion_figure(res: dict) -> Figure:
    """Stress excursions per unit strain whose peak reaches sigma, against sigma, one colour
    per (N, phi); the same samples' certified jams per unit strain as a dashed line."""
    fig = new_figure(6.4, 4.6)
    ax = fig.add_subplot(1, 1, 1)
    rows = sorted(_excursion_rows(res), key=lambda r: (r["phi"], r["N"]))
    for k, r in enumerate(rows):
        e, color = r["excursions"], f"C{k}"
        x = np.array(e["levels"], float)
        y = np.array(e["per_strain"], float)
        hit = y > 0
        ax.plot(x[hit], y[hit], "o-", color=color, ms=5,
                label=f"N = {r['N']}, φ = {r['phi']:.4f}: {e['n_samples']} samples, "
                      f"{e['strain']:.3g} strain")
        if e.get("jams"):
            ax.axhline(e["jams_per_strain"], color=color, ls="--", lw=1,
                       label=f"   certified jams: {e['jams']} ({e['jams_per_strain']:.3g} per "
                             f"unit strain)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("σ reached at the peak")
    ax.set_ylabel("excursions per unit strain")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="lower left")
    e = rows[0]["excursions"] if rows else dict(on=0, off=0, quiet=0)
    ax.set_title(f"Stress excursions of flowing suspensions at constant φ: σ ≥ {e['on']:g} "
                 f"until below {e['off']:g} for {e['quiet']:g} strain\n(dashed: the "
                 f"certified jams, excursions that do not come back)", fontsize=8.5)
    return fig


def _figures(res: dict) -> list:
    out = [("suspension_jams_phiSJ", phi_sj_figure(res))]
    if len({t["compress_rate"] for t in res["table"] if t["n_shear_jams"]}) > 1:
        out.append(("suspension_jams_rate", phi_sj_rate_figure(res)))
    if _rate_phis(res):
        out.append(("suspension_jams_per_strain", jam_rate_figure(res)))
    if _excursion_rows(res):
        out.append(("suspension_excursions", excursion_figure(res)))
    return out


def main(argv=None) -> int:
    return across_ensembles_cli(
        argv, "python -m parflow.plot.suspension_jams",
        "The figures of phi_SJ(N) and of phi_SJ against the rate: where compressed, flowing "
        "suspensions shear-jam (PATH: ensemble folders, jam tables, or folders holding them)",
        analyse, format_table,
        "no compressed suspension ensemble sample found",
        _figures)


if __name__ == "__main__":
    sys.exit(main())
