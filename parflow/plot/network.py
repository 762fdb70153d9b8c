"""Network figures (paper Figs. 3, 4, 5, 8; docs/networks.md).

* ``fig3a_sigma``       sigma against gamma, forward to jamming then reversed.
* ``fig3b_reverse``     -dsigma/dgamma against sigma on the reversed branch, log-log, slope-2
                        reference, fitted exponent and C; the local C_k against sigma.
* ``fig4_omega_min``    omega_min against sigma (fitted slopes, reference -1/2) and
                        omega_min sqrt(sigma) with C2.
* ``fig5_dos``          D(omega) at the analysis instants coloured by sigma, omega* marked;
                        F(omega)/(D_p omega), the quantity that defines omega*.
* ``fig8_correlation``  C(r) of V_na at the analysis instants coloured by sigma (lin, log).
* ``fig8_response``     point-response |V|(r) with the stored two-exponential fits, the
                        collapse V(r) sqrt(sigma) against r / sqrt(sigma), l_c and l_r
                        against sigma.

The numbers are :func:`parflow.post.network.network_fits`; the helpers below the labels are
shared with the across-run figures (:mod:`.network_across`).
"""
from __future__ import annotations

import math

import numpy as np
from matplotlib.figure import Figure

from ..post.fits import segments
from ..post.network import (OMEGA_STAR_FRACTION, OMEGA_STAR_PLATEAU, RESOLVED_FRACTION,
                            across_fits, network_dz, network_fits, network_seed, network_z,
                            response_instants, spectrum_instants)
from ..post.report import fmt_exp
from .base import Run, Skip, figure, instant_colors, new_figure, reference, register_model, title

SIGMA_LABEL = r"$\sigma$ [$\eta_0\dot\gamma$]"


OMEGA_LABEL = r"$\omega$ (dimensionless: $\sqrt{\lambda(\mathcal{N})}$)"

DOS_PER_DECADE = 16               # log bins of D(omega) in the figures
CORR_MIN_COUNT = 50               # C(r) bins with fewer pairs are not drawn (as crossing_length)


def z_key(run: Run) -> float:
    """The z a run was made for (the scene's target; the network's z differs by < 1/N)."""
    z = run.param("z")
    return round(float(z), 4) if z is not None else round(network_z(run), 2)


def _network_title(run: Run, bits: list) -> list:
    nn = run.model_attrs.get("n_nodes")
    if nn is not None and bits[-1].startswith("N="):
        bits[-1] += f" ({int(nn)} nodes)"
    return bits + [f"z={network_z(run):.4g} (δz={network_dz(run):.3g})",
                   f"seed {network_seed(run)}"]


register_model("network", fits=network_fits, across=across_fits,
               order=lambda r: (z_key(r), str(network_seed(r))), title=_network_title)


def run_label(run: Run) -> str:
    return f"z={network_z(run):.3g} (δz={network_dz(run):.3g}), seed {network_seed(run)}"


def sigma_colors(inst, cmap="viridis"):
    return instant_colors(inst, key="sigma", cmap=cmap)


def branch_style(a) -> str:
    return "-" if a.get("direction", 1) > 0 else "--"


def branch_note() -> str:
    return "solid: forward, dashed: reversed"


def draw_sigma_gamma(ax, run, cf, cr, labels=False, label=""):
    ts = run.ts
    d = ts["direction"] if "direction" in ts else np.ones(len(ts["sigma"]), int)
    for a, b, sgn in segments(d):
        g, s = ts["gamma"][a:b], ts["sigma"][a:b]
        if a > 0:                                    # join the branches at the turn
            g, s = np.r_[ts["gamma"][a - 1], g], np.r_[ts["sigma"][a - 1], s]
        ok = np.isfinite(s) & (s > 0)
        lab = (("forward" if sgn > 0 else "reversed") if labels else
               (label if sgn > 0 else None))
        ax.semilogy(g[ok], s[ok], "-" if sgn > 0 else "--", color=cf if sgn > 0 else cr,
                    lw=1.2, label=lab)


def dos_curve(a: dict):
    """(omega bin centres, D) for an instant: from the full spectrum on fixed log bins
    (DOS_PER_DECADE per decade, so that instants compare), else the stored binned D."""
    if "omega" in a:
        w = np.asarray(a["omega"], float)
        w = w[np.isfinite(w)]
        pos = w[w > 0]
        if pos.size < 2:
            return np.array([]), np.array([])
        k0 = math.floor(math.log10(pos.min()) * DOS_PER_DECADE)
        k1 = math.ceil(math.log10(pos.max()) * DOS_PER_DECADE)
        edges = 10.0 ** (np.arange(k0, k1 + 1) / DOS_PER_DECADE)
        h, _ = np.histogram(w, edges)
        D = h / (w.size * np.diff(edges))
    else:
        edges, D = np.asarray(a["dos_edges"], float), np.asarray(a["dos"], float)
    x = np.sqrt(edges[1:] * edges[:-1])
    return x, np.where(D > 0, D, np.nan)       # empty bins break the line


def _good_corr(a):
    r, C = np.asarray(a["corr_r"], float), np.asarray(a["corr_C"], float)
    ok = np.isfinite(C)
    if "corr_counts" in a:
        ok &= np.asarray(a["corr_counts"]) >= CORR_MIN_COUNT
    return r[ok], C[ok]


@figure("fig3a_sigma", models={"network"})
def fig3a_sigma(run: Run, fits: dict) -> Figure:
    """Fig. 3a: sigma against gamma, forward to jamming then reversed, log-y."""
    ts = run.ts
    if "sigma" not in ts or "gamma" not in ts:
        raise Skip("no sigma / gamma in /timeseries")
    fig = new_figure(7.5, 5.2)
    ax = fig.subplots()
    draw_sigma_gamma(ax, run, "C0", "C3", labels=True)
    ax.set_xlabel(r"$\gamma$ (strain coordinate)")
    ax.set_ylabel(SIGMA_LABEL)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.suptitle(title(run, "Fig. 3a: stress against strain"), fontsize=10)
    return fig


@figure("fig3b_reverse", models={"network"})
def fig3b_reverse(run: Run, fits: dict) -> Figure:
    """Fig. 3b: -dsigma/dgamma against sigma on the reversed branch, log-log, with the fit
    (exponent a and C of -dsigma/dgamma = sigma^2/C) and the local C_k."""
    r = fits.get("reverse")
    if r is None:
        raise Skip("no reversed branch (direction == -1) with sigma and strain")
    br = r["branch"]
    ok = (br["dsdg"] < 0) & (br["sigma"] > 0)
    if ok.sum() < 3:
        raise Skip("reversed branch has fewer than 3 decreasing records")
    lo, hi = r["window"]
    fig = new_figure(12.5, 5.0)
    ax, ax2 = fig.subplots(1, 2)
    s, y = br["sigma"][ok], -br["dsdg"][ok]
    ax.loglog(s, y, ".", ms=4, color="C3", label="finite differences of the time series")
    ax.axvspan(lo, hi, color="0.92", zorder=0, label=f"fit window σ ∈ [{lo:g}, {hi:g}]")
    if np.isfinite(r["C"]):
        xs = np.geomspace(max(lo, s.min()), min(hi, s.max()), 20)
        ax.loglog(xs, xs ** 2 / r["C"], "-", color="C3", lw=2.5, alpha=0.5,
                  label=f"σ²/C, C = {r['C']:.4g} ± {r['C_err']:.2g}")
    if np.isfinite(r["slope"]):
        m = (s >= lo) & (s <= hi)
        k = float(np.median(np.log(y[m]) - r["slope"] * np.log(s[m]))) if m.any() else np.nan
        xs = np.geomspace(s.min(), s.max(), 20)
        ax.loglog(xs, np.exp(k) * xs ** r["slope"] * 3, ":", color="k", lw=1,
                  label=f"fit slope a = {r['slope']:.3f} ± {r['slope_err']:.3f} (×3)")
    xm = math.sqrt(s.min() * s.max())
    reference(ax, xm, float(np.exp(np.median(np.log(y / s ** 2)))) * xm ** 2 / 3, 2.0,
               math.sqrt(s.max() / s.min()), "reference slope 2 (÷3)")
    ax.set_xlabel(SIGMA_LABEL)
    ax.set_ylabel(r"$-d\sigma/d\tilde\gamma$  ($\tilde\gamma$: strain since the reversal)")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    ax.set_title("reversed branch: paper −dσ/dγ = σ²/C(δz)", fontsize=10)
    Ck = br["C"][ok]
    pos = Ck > 0
    ax2.semilogx(s[pos], Ck[pos], ".", ms=4, color="C3",
                 label=r"local $C_k = \Delta x/\Delta(1/\sigma)$")
    if np.isfinite(r["C"]):
        ax2.axhline(r["C"], color="k", lw=1, label=f"fit C = {r['C']:.4g}")
    ax2.axvspan(lo, hi, color="0.92", zorder=0)
    if pos.any():
        top = np.percentile(Ck[pos], 95)
        ax2.set_ylim(0, 2 * top)
    ax2.set_xlabel(SIGMA_LABEL)
    ax2.set_ylabel(r"$C = \sigma^2 / (-d\sigma/d\tilde\gamma)$")
    ax2.grid(True, alpha=0.3)
    ax2.legend(fontsize=8)
    ax2.set_title("constant where the σ² law holds", fontsize=10)
    fig.suptitle(title(run, "Fig. 3b: reversed branch"), fontsize=10)
    return fig


@figure("fig4_omega_min", models={"network"})
def fig4_omega_min(run: Run, fits: dict) -> Figure:
    """Fig. 4: omega_min against sigma (fits over sigma >= C2_SIGMA_MIN, slope -1/2) and
    omega_min sqrt(sigma) against sigma (C2)."""
    o = fits.get("omega_min")
    if o is None:
        raise Skip("omega_min was not computed (observables.omega_min_every = 0)")
    ts = run.ts
    w, s = np.asarray(ts["omega_min"], float), np.asarray(ts["sigma"], float)
    d = ts["direction"] if "direction" in ts else np.ones(w.size, int)
    ok = np.isfinite(w) & np.isfinite(s) & (w > 0) & (s > 0)
    fig = new_figure(12.5, 5.0)
    ax, ax2 = fig.subplots(1, 2)
    for sgn, name, c, mk in ((1, "forward", "C0", "o"), (-1, "reverse", "C3", "s")):
        m = ok & (d == sgn)
        if not m.any():
            continue
        p = o[name]
        ax.loglog(s[m], w[m], mk, ms=3, color=c, mfc="none",
                  label=f"{name}: slope {fmt_exp(p[0])} (σ ≥ {o['sigma_min']:g}, {p[2]} pts)")
        ax2.semilogx(s[m], w[m] * np.sqrt(s[m]), mk, ms=3, color=c, mfc="none", label=name)
    sx = s[ok]
    if np.isfinite(o["C2"]):
        xs = np.geomspace(sx.min(), sx.max(), 20)
        ax.loglog(xs, o["C2"] / np.sqrt(xs), "k--", lw=1,
                  label=r"$C_2/\sqrt{\sigma}$ (slope −1/2)")
        ax2.axhline(o["C2"], color="k", lw=1,
                    label=f"C₂ = {o['C2']:.4g} (median, σ ≥ {o['sigma_min']:g}; "
                          f"16–84 %: {o['C2_p16']:.4g}–{o['C2_p84']:.4g})")
    ax.axvline(o["sigma_min"], color="0.6", ls=":", lw=1)
    ax2.axvline(o["sigma_min"], color="0.6", ls=":", lw=1)
    ax.set_xlabel(SIGMA_LABEL)
    ax.set_ylabel(r"$\omega_{min}$ (dimensionless)")
    ax2.set_xlabel(SIGMA_LABEL)
    ax2.set_ylabel(r"$\omega_{min}\sqrt{\sigma}$")
    for a_ in (ax, ax2):
        a_.grid(True, alpha=0.3)
        a_.legend(fontsize=8)
    ax.set_title("paper: ω_min ≈ C₂(δz)/√σ", fontsize=10)
    ax2.set_title("C₂ = ω_min √σ (dotted: σ from which C₂ is taken)", fontsize=10)
    fig.suptitle(title(run, "Fig. 4: lowest frequency of N against stress"), fontsize=10)
    return fig


@figure("fig5_dos", models={"network"})
def fig5_dos(run: Run, fits: dict) -> Figure:
    """Fig. 5: D(omega) at the analysis instants (coloured by sigma) with omega* marked, and
    the quantity that defines omega*: F(omega) / (D_p omega) (fit_omega_star)."""
    inst = spectrum_instants(run)
    if not inst:
        if any("omega_low" in a for a in run.analysis):
            raise Skip("only the lowest frequencies were computed (model.spectrum = 'low'): "
                       "no D(omega)")
        raise Skip("no analysis groups with a spectrum (model.spectrum = 'none')")
    cols, sm = sigma_colors(inst)
    ost = {p["step"]: p for p in fits.get("omega_star", {}).get("instants", [])}
    fig = new_figure(12.5, 5.0)
    ax, ax2 = fig.subplots(1, 2)
    for a, c in zip(inst, cols):
        x, D = dos_curve(a)
        ax.loglog(x, D, branch_style(a), color=c, lw=1.2, marker=".", ms=3)
        p = ost.get(int(a.get("step", -1)))
        if p is not None and np.isfinite(p["omega_star"]):
            ax.axvline(p["omega_star"], color=c, ls=branch_style(a), lw=0.8, alpha=0.8)
    ost_all = fits.get("omega_star")
    if ost_all is not None and np.isfinite(ost_all["omega_star"]):
        ax.plot([], [], "k-", lw=0.8, label=f"ω* (vertical lines): {ost_all['omega_star']:.4f} ± "
                                             f"{ost_all['err']:.4f} (mean of instants)")
        Dp = np.nanmean([p["D_plateau"] for p in ost.values()])
        ax.axhline(Dp, color="0.5", ls=":", lw=1,
                   label=f"plateau D_p = {Dp:.3f} (ω ∈ {OMEGA_STAR_PLATEAU})")
    ax.set_xlabel(OMEGA_LABEL)
    ax.set_ylabel(r"$D(\omega)$ (normalised to 1)")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    ax.set_title(f"density of states at the analysis instants ({branch_note()})", fontsize=10)
    fig.colorbar(sm, ax=ax, label=SIGMA_LABEL)
    drawn = False
    for a, c in zip(inst, cols):
        p = ost.get(int(a.get("step", -1)))
        if p is None or not np.isfinite(p["D_plateau"]):
            continue
        w = np.sort(np.asarray(a["omega"], float))
        F = np.arange(w.size) / w.size
        m = (w > 0) & (w < OMEGA_STAR_PLATEAU[1])
        ax2.plot(w[m], F[m] / (p["D_plateau"] * w[m]), branch_style(a), color=c, lw=1.2,
                 label=f"σ = {p['sigma']:.3g}: ω* = {p['omega_star']:.4f} ± {p['err']:.4f}")
        ax2.plot(p["omega_c"], OMEGA_STAR_FRACTION, "o", color=c, ms=5)
        drawn = True
    if drawn:
        ax2.axhline(OMEGA_STAR_FRACTION, color="k", lw=0.8, ls=":")
        ax2.set_ylim(0, 1.3)
        ax2.set_xscale("log")
        wcs = [p["omega_c"] for p in ost.values() if np.isfinite(p["omega_c"])]
        if wcs:
            ax2.set_xlim(0.1 * min(wcs), OMEGA_STAR_PLATEAU[1])
        ax2.legend(fontsize=8, loc="upper left")
    else:
        ax2.text(0.5, 0.5, "no full spectrum (omega): ω* not measured", ha="center",
                 transform=ax2.transAxes)
    ax2.set_xlabel(OMEGA_LABEL)
    ax2.set_ylabel(r"$F(\omega) / (D_p\,\omega)$")
    ax2.grid(True, alpha=0.3)
    ax2.set_title(f"ω* = (1 − {OMEGA_STAR_FRACTION:g}) ω_c, ω_c (dots): last crossing of "
                  f"{OMEGA_STAR_FRACTION:g}", fontsize=10)
    fig.suptitle(title(run, "Fig. 5: density of states of N and its gap ω*"), fontsize=10)
    return fig


@figure("fig8_correlation", models={"network"})
def fig8_correlation(run: Run, fits: dict) -> Figure:
    """Fig. 8: C(r) of V_na at the analysis instants, coloured by sigma; linear and log-y."""
    inst = [a for a in run.analysis if "corr_C" in a and "corr_r" in a]
    if not inst:
        raise Skip("no analysis groups with corr_C (model.correlation = false)")
    cols, sm = sigma_colors(inst)
    fig = new_figure(12.5, 5.0)
    ax, ax2 = fig.subplots(1, 2)
    for a, c in zip(inst, cols):
        r, C = _good_corr(a)
        ax.semilogx(r, C, branch_style(a), color=c, lw=1.2)
        ax2.semilogy(r, np.where(C > 0, C, np.nan), branch_style(a), color=c, lw=1.0)
    ax.axhline(0, color="k", lw=0.6)
    ax.axhline(np.exp(-1), color="0.5", lw=0.6, ls=":")
    ax.set_xlabel(r"$r$ [$a_0$]")
    ax.set_ylabel(r"$C(r) = \langle V_i\cdot V_j\rangle / \langle V^2\rangle$")
    ax.set_title(f"velocity correlation of V_na ({branch_note()}; dotted: 1/e)", fontsize=10)
    ax2.set_xlabel(r"$r$ [$a_0$]")
    ax2.set_ylabel(r"$C(r)$ (positive values, log)")
    ax2.set_title("log-y: initial decay on l_c, weak tail on l_r", fontsize=10)
    ax2.set_ylim(1e-3, 1.5)
    for a_ in (ax, ax2):
        a_.grid(True, alpha=0.3)
    fig.colorbar(sm, ax=[ax, ax2], label=SIGMA_LABEL)
    fig.suptitle(title(run, f"Fig. 8: velocity correlations (bins with ≥ {CORR_MIN_COUNT} "
                             "pairs)"), fontsize=10)
    return fig


@figure("fig8_response", models={"network"})
def fig8_response(run: Run, fits: dict) -> Figure:
    """Point response: |V|(r) coloured by sigma with the two-exponential fits, the collapse
    V(r) sqrt(sigma) against r / sqrt(sigma), and l_c, l_r against sigma."""
    inst = response_instants(run)
    if not inst:
        raise Skip("no analysis groups with the point response (resp_V)")
    rf = fits["response"]["instants"]
    cols, sm = sigma_colors(inst)
    fig = new_figure(16, 5.0)
    ax, ax2, ax3 = fig.subplots(1, 3)
    for a, c, x in zip(inst, cols, rf):
        r, V = np.asarray(a["resp_r"], float), np.asarray(a["resp_V"], float)
        ok = np.isfinite(V) & (V > 0)
        if "resp_counts_V" in a:
            ok &= np.asarray(a["resp_counts_V"]) > 0
        st = branch_style(a)
        ax.semilogy(r[ok], V[ok], st, color=c, lw=1.2)
        if np.isfinite(x["A"]) and np.isfinite(x["l_c"]) and x["l_c"] > 0:
            tail = x["B"] * np.exp(-r[ok] / x["l_r"]) if np.isfinite(x["l_r"]) and \
                np.isfinite(x["B"]) else x["B"] if np.isfinite(x["B"]) else 0.0
            ax.semilogy(r[ok], x["A"] * np.exp(-r[ok] / x["l_c"]) + tail, ":", color=c, lw=0.9)
        s = x["sigma"]
        if s > 0:
            ax2.semilogy(r[ok] / math.sqrt(s), V[ok] * math.sqrt(s), st, color=c,
                         lw=1.5 if x["resolved"] else 0.6, alpha=1.0 if x["resolved"] else 0.35)
    ax.set_xlabel(r"$r$ [$a_0$] (distance from the extended rod)")
    ax.set_ylabel(r"$\langle|V|\rangle(r)$ (per unit extension rate of the rod)")
    ax.set_title(f"point response ({branch_note()}; dotted: "
                 r"$Ae^{-r/l_c}+Be^{-r/l_r}$)", fontsize=10)
    ax2.set_xlabel(r"$r/\sqrt{\sigma}$")
    ax2.set_ylabel(r"$\langle|V|\rangle\sqrt{\sigma}$")
    res = [x for x in rf if x["resolved"]]
    txt = (f"instants with l_r < {RESOLVED_FRACTION:g} r_max (bold): l_r/√σ = "
           + ", ".join(f"{x['lr_over_sqrt_sigma']:.2f}" for x in res) + "; B√σ = "
           + ", ".join(f"{x['B_sqrt_sigma']:.2g}" for x in res)) if res else \
        f"no instant with l_r below {RESOLVED_FRACTION:g} r_max"
    ax2.set_title("collapse (paper): V√σ against r/√σ", fontsize=10)
    if res:                         # where the resolved curves overlap, and a bit beyond
        xr = 1.5 * min(x["rmax"] / math.sqrt(x["sigma"]) for x in res)
        lows = []
        for a, x in zip(inst, rf):
            if x["resolved"]:
                r, V = np.asarray(a["resp_r"], float), np.asarray(a["resp_V"], float)
                m = (r / math.sqrt(x["sigma"]) <= xr) & np.isfinite(V) & (V > 0)
                if m.any():
                    lows.append(float(np.min(V[m])) * math.sqrt(x["sigma"]))
        ax2.set_xlim(0, xr)
        if lows:
            ax2.set_ylim(bottom=0.5 * min(lows))
    ax2.text(0.02, 0.02, txt, transform=ax2.transAxes, fontsize=7, va="bottom", wrap=True)
    sg = np.array([x["sigma"] for x in rf])
    for key, mk, c, lab in (("l_c", "o", "C0", r"$l_c$"), ("l_r", "s", "C3", r"$l_r$")):
        v = np.array([x[key] for x in rf])
        fin = np.isfinite(v) & (v > 0) & (sg > 0)
        for sgn, mfc in ((1, c), (-1, "none")):
            m = fin & (np.array([x["direction"] for x in rf]) == sgn)
            if m.any():
                ax3.loglog(sg[m], v[m], mk, color=c, mfc=mfc, ms=6,
                           label=f"{lab} ({'forward' if sgn > 0 else 'reversed'})")
    lrf = fits["response"]["l_r_vs_sigma"]
    if np.isfinite(lrf["exponent"]):
        xs = np.geomspace(min(x["sigma"] for x in res), max(x["sigma"] for x in res), 20)
        ax3.loglog(xs, lrf["prefactor"] * xs ** lrf["exponent"], "-", color="C3", lw=2.5,
                   alpha=0.45, label=f"fit l_r ~ σ^{lrf['exponent']:.2f} ± {lrf['err']:.2g}")
    if sg[sg > 0].size:
        xm = math.sqrt(sg[sg > 0].min() * sg[sg > 0].max())
        y0 = np.nanmedian([x["lr_over_sqrt_sigma"] for x in res]) if res else 2.5
        reference(ax3, xm, y0 * math.sqrt(xm), 0.5, math.sqrt(sg[sg > 0].max() / sg[sg > 0].min()),
                   "reference √σ")
    rmax = np.nanmin([x["rmax"] for x in rf])
    if np.isfinite(rmax):
        ax3.axhline(rmax, color="0.4", ls=":", lw=1, label=f"r_max = {rmax:.3g} (profile end)")
    ax3.set_ylim(top=3 * rmax if np.isfinite(rmax) else None)
    ax3.set_xlabel(SIGMA_LABEL)
    ax3.set_ylabel(r"length [$a_0$]")
    ax3.grid(True, alpha=0.3)
    ax3.legend(fontsize=7, loc="best")
    ax3.set_title("fitted lengths (paper: l_c ∝ δz^−1/2, l_r ∝ √σ)", fontsize=10)
    for a_ in (ax, ax2):
        a_.grid(True, alpha=0.3)
    fig.colorbar(sm, ax=[ax, ax2], label=SIGMA_LABEL)
    fig.suptitle(title(run, "point response and its collapse"), fontsize=10)
    return fig
