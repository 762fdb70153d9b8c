"""Chain figures (DESIGN §6, paper Fig. 2; docs/chain.md).

* ``chain_forward``     <V^2>, <dtheta^2>, <thetadot^2> against gamma_c - gamma, log-log, for
                        gamma_c = ln(N / Lx0) (model attribute) and for gamma_c fitted where
                        <V^2>^(-(1+mu)/(3+mu)) extrapolates to zero; fitted and theory slopes.
* ``chain_reverse``     reverse branch: <V^2> against gamma_turn - gamma and against
                        gamma~_c - gamma (gamma~_c: where 1/<V^2> extrapolates to zero), log-log,
                        slope -1, with the forward branch against gamma_turn - gamma (the two
                        branches do not coincide); 1/<V^2> near the turn on linear axes.
* ``chain_correlation`` C(n) at the forward analysis instants coloured by <V^2>; C against
                        n / l_corr.
* ``chain_lengths``     l_corr, l_r and <dtheta^2>^(-1/2) against gamma_c - gamma, log-log.
* ``chain_response``    |tau_n| / |tau_0| of the point response, semilog-y.

The numbers are :func:`parflow.post.chain.chain_fits`.
"""
from __future__ import annotations

import math

import numpy as np
from matplotlib.figure import Figure

from ..post.chain import chain_fits, length_cap, primary_gamma_c
from ..post.fits import forward_instants, forward_rows, reverse_rows
from ..post.report import fmt_exp
from .base import (QLABEL, Run, Skip, anchor, figure, fit_line, instant_colors, new_figure,
                   positive, reference, register_model, title)


def _chain_title(run: Run, bits: list) -> list:
    return bits + [f"μ={run.param('mu', 0)}"]


register_model("chain", fits=chain_fits, title=_chain_title)


@figure("chain_forward", models={"chain"})
def fig_chain_forward(run: Run, fits: dict) -> Figure:
    """(a) <V^2>, <dtheta^2>, <thetadot^2> against gamma_c - gamma, one column per gamma_c."""
    fw = forward_rows(run)
    if fw is None or "V2" not in run.ts:
        raise Skip("no forward branch (direction == +1) with V2")
    gcs = fits.get("gamma_c", {})
    if not gcs:
        raise Skip("neither the gamma_c attribute nor a fitted gamma_c is available")
    qs = [q for q in ("V2", "dtheta2", "thetadot2") if q in run.ts]
    th = fits["theory"]
    cols = [c for c in ("attr", "fit") if c in gcs]
    fig = new_figure(5.6 * len(cols) + 0.4, 3.3 * len(qs) + 0.6)
    axes = fig.subplots(len(qs), len(cols), squeeze=False, sharex="col")
    g = run.ts["gamma"][fw]
    colors = {"V2": "C0", "dtheta2": "C1", "thetadot2": "C2"}
    for j, which in enumerate(cols):
        gc = gcs[which]
        res = fits["forward"][which]
        lo, hi = res["window"]
        x = gc - g
        for i, q in enumerate(qs):
            ax = axes[i, j]
            xx, yy = positive(x, run.ts[q][fw])
            ax.loglog(xx, yy, ".", ms=2.5, color=colors[q], label="data")
            fit = res.get(q, (np.nan, np.nan))
            fit_line(ax, fit, lo, hi, f"fit: slope {fmt_exp(fit[0])}", colors[q])
            x0, y0 = anchor(fit, lo, hi)
            if not np.isfinite(x0) and xx.size:            # no fit: hang it on the data
                x0, y0 = xx[len(xx) // 2], yy[len(yy) // 2]
            span = math.sqrt(hi / lo) if np.isfinite(lo) and hi > lo else 10.0
            reference(ax, x0, y0 * 2.5, th[q], max(span, 3.0), f"theory: slope {th[q]:+.3g}")
            if np.isfinite(lo):
                ax.axvspan(lo, hi, color="0.9", zorder=0)
            ax.set_ylabel(QLABEL[q])
            ax.grid(True, which="major", alpha=0.3)
            ax.legend(fontsize=8, loc="best")
        axes[-1, j].set_xlabel(r"$\gamma_c - \gamma$" + ("  (γ_c = ln N/Lx0)" if which == "attr"
                                                           else "  (γ_c fitted)"))
        head = (r"$\gamma_c = \ln(N/L_{x0})$ = " if which == "attr" else
                r"$\gamma_c$ fitted ($\langle V^2\rangle^{-(1+\mu)/(3+\mu)}\to 0$) = ")
        axes[0, j].set_title(head + f"{gc:.6g}", fontsize=10)
    gline = "; ".join(f"γ_c({'attr' if k == 'attr' else 'fit'}) = {v:.6g}" for k, v in gcs.items())
    fig.suptitle(title(run, "forward branch") + f"\n{gline}; run ends at γ = "
                 f"{fits['gamma_end']:.6g}; grey: fit window", fontsize=10)
    return fig


@figure("chain_reverse", models={"chain"})
def fig_chain_reverse(run: Run, fits: dict) -> Figure:
    """(b) the reverse branch against gamma_turn - gamma and gamma~_c - gamma, with the
    forward branch against gamma_turn - gamma; 1/<V^2> on linear axes near the turn."""
    rv = reverse_rows(run)
    if rv is None or "V2" not in run.ts:
        raise Skip("no reverse branch (direction == -1)")
    rows, gturn = rv
    if rows.stop - rows.start < 3:
        raise Skip("reverse branch has fewer than 3 rows")
    ts = run.ts
    gr, Vr = ts["gamma"][rows], ts["V2"][rows]
    res = fits["reverse"]
    gct = res.get("gamma_c_tilde", np.nan)
    fig = new_figure(13, 5.0)
    ax, ax2 = fig.subplots(1, 2)
    fw = forward_rows(run)
    if fw is not None:
        xf, yf = positive(gturn - ts["gamma"][fw], ts["V2"][fw])
        ax.loglog(xf, yf, ".", ms=2, color="C0", alpha=0.7,
                  label=r"forward, against $\gamma_{turn}-\gamma$")
    xr, yr = positive(gturn - gr, Vr)
    ax.loglog(xr, yr, ".", ms=3, color="C3", label=r"reverse, against $\gamma_{turn}-\gamma$")
    fit_t = res["turn"]["V2"]
    fit_line(ax, fit_t, *res["turn"]["window"], f"fit: slope {fmt_exp(fit_t[0])}", "C3")
    fit = fit_t
    lo, hi = res["turn"]["window"]
    if "tilde" in res:
        xt, yt = positive(gct - gr, Vr)
        ax.loglog(xt, yt, "+", ms=3, color="C4", alpha=0.8,
                  label=r"reverse, against $\tilde\gamma_c-\gamma$")
        fit = res["tilde"]["V2"]
        lo, hi = res["tilde"]["window"]
        fit_line(ax, fit, lo, hi, f"fit: slope {fmt_exp(fit[0])}", "C4")
    x0, y0 = anchor(fit, lo, hi)
    span = math.sqrt(hi / lo) if np.isfinite(lo) and hi > lo else 10.0
    reference(ax, x0, y0 * 4, -1.0, span, "theory: slope -1")
    ax.set_xlabel(r"$\gamma_{turn} - \gamma$  or  $\tilde\gamma_c - \gamma$")
    ax.set_ylabel(QLABEL["V2"])
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8, loc="lower left")
    ax.set_title("log-log; fits from where ⟨V²⟩ has dropped 10× below its turning value",
                 fontsize=9)
    # 1/V2 on linear axes near the turn: straight if <V^2> ~ 1/(gamma~_c - gamma)
    near = Vr >= Vr[0] / 300
    ax2.plot(gturn - gr[near], 1 / Vr[near], ".", ms=4, color="C3", label="reverse")
    if np.isfinite(gct):
        sel = (Vr <= Vr[0] / 10) & (Vr >= Vr[0] / 100)
        if sel.any():
            a = np.polyfit(gr[sel], 1 / Vr[sel], 1)[0]
            xs = np.linspace(gturn - gct, np.max(gturn - gr[near]), 50)
            ax2.plot(xs, a * (gturn - xs - gct), "k-", lw=1, alpha=0.6,
                     label="linear fit (⟨V²⟩ 10–100× below the turn)")
        ax2.axvline(gturn - gct, color="k", ls=":", lw=1,
                    label=r"$\gamma_{turn}-\tilde\gamma_c$" + f" = {gturn - gct:.3g}")
    ax2.set_xlabel(r"$\gamma_{turn} - \gamma$")
    ax2.set_ylabel(r"$1/\langle V^2\rangle$")
    ax2.ticklabel_format(style="sci", scilimits=(-3, 3))
    ax2.grid(True, alpha=0.3)
    ax2.legend(fontsize=8, loc="upper left")
    ax2.set_title(r"$1/\langle V^2\rangle$ near the turn (linear axes)", fontsize=10)
    line = (f"γ_turn = {gturn:.9g}; reverse exponent {fmt_exp(fit_t[0])} against γ_turn − γ")
    if "tilde" in res:
        line += f", {fmt_exp(res['tilde']['V2'][0])} against γ̃_c − γ (γ̃_c − γ_turn = " \
                f"{gct - gturn:.3g})"
    fig.suptitle(title(run, "reverse branch") + f"\n{line}; theory −1", fontsize=10)
    return fig


@figure("chain_correlation", models={"chain"})
def fig_chain_correlation(run: Run, fits: dict) -> Figure:
    """(c) C(n) at forward instants, coloured by <V^2>, and C against n / l_corr."""
    inst = [a for a in forward_instants(run) if "C_n" in a]
    if not inst:
        raise Skip("no forward analysis groups with C_n")
    cols, sm = instant_colors(inst)
    fig = new_figure(12.5, 4.6)
    ax, ax2 = fig.subplots(1, 2)
    for a, c in zip(inst, cols):
        C = np.asarray(a["C_n"], float)
        n = np.arange(C.size)
        ax.plot(n[1:], C[1:], "-", color=c, lw=1.2)
        lc = float(a.get("l_corr", np.nan))
        if np.isfinite(lc) and lc > 0:
            ax2.plot(n[1:] / lc, C[1:], "-", color=c, lw=1.2)
    for a_ in (ax, ax2):
        a_.set_xscale("log")
        a_.axhline(0, color="k", lw=0.6)
        a_.axhline(np.exp(-1), color="0.5", lw=0.6, ls=":")
        a_.grid(True, alpha=0.3)
        a_.set_ylabel("C(n)")
    u = np.geomspace(1e-2, 3, 100)
    ax2.plot(u, np.exp(-u ** 2), "k--", lw=1, label=r"guide: $e^{-(n/l_{corr})^2}$")
    ax2.legend(fontsize=8, loc="lower left")
    ax.set_xlabel("n (rods along the chain)")
    ax2.set_xlabel(r"$n / l_{corr}$")
    ax.set_title("velocity correlation, forward instants (dotted: 1/e)", fontsize=10)
    ax2.set_title(r"collapse: $l_{corr}$ = first n with C(n) < 1/e", fontsize=10)
    fig.colorbar(sm, ax=[ax, ax2], label=QLABEL["V2"])
    fig.suptitle(title(run, "velocity correlation C(n)"), fontsize=10)
    return fig


@figure("chain_lengths", models={"chain"})
def fig_chain_lengths(run: Run, fits: dict) -> Figure:
    """(d) l_corr, l_r and <dtheta^2>^(-1/2) against gamma_c - gamma (forward), log-log."""
    gc = primary_gamma_c(fits.get("gamma_c", {}))
    inst = [a for a in forward_instants(run) if "l_corr" in a or "l_r" in a]
    if not inst:
        raise Skip("no forward analysis groups with l_corr / l_r")
    if gc is None:
        raise Skip("no gamma_c (attribute or fit)")
    th = fits["theory"]
    L = fits.get("lengths", {})
    cap = length_cap(run)
    wlo, whi = fits.get("lengths_window", (0.0, np.inf))
    x = np.array([gc - a["gamma"] for a in inst])
    fig = new_figure(7.5, 5.6)
    ax = fig.subplots()
    spec = [("l_corr", r"$l_{corr}$", "C0", "o", th["l_corr"]),
            ("l_r", r"$l_r$ (exponential fit of $\tau_n$)", "C3", "s", th["l_r"])]
    for key, lab, c, mk, p_th in spec:
        y = np.array([float(a.get(key, np.nan)) for a in inst])
        xx, yy = positive(x, y)
        if not xx.size:
            continue
        fit = L.get(key, (np.nan, np.nan))
        ax.loglog(xx, yy, mk, color=c, ms=6, label=f"{lab}: fit slope {fmt_exp(fit[0])}")
        inside = (yy < cap) & (xx >= wlo) & (xx <= whi)
        if inside.any():
            fit_line(ax, fit, xx[inside].min(), xx[inside].max(), None, c)
        i = len(xx) // 2
        reference(ax, xx[i], yy[i] * 1.8, p_th, 10, f"theory slope {p_th:+.3g}", color=c)
    fw = forward_rows(run)
    if "dtheta2" in run.ts and fw is not None:
        xx, yy = positive(gc - run.ts["gamma"][fw], run.ts["dtheta2"][fw] ** -0.5)
        ax.loglog(xx, yy, "-", color="C1", lw=1, alpha=0.7,
                  label=r"$\langle\Delta\theta^2\rangle^{-1/2}$ (timeseries)")
    y = np.array([float(a.get("dtheta2", np.nan)) for a in inst]) ** -0.5
    xx, yy = positive(x, y)
    if xx.size:
        fit = L.get("dtheta2^-1/2", (np.nan, np.nan))
        ax.loglog(xx, yy, "^", color="C1", ms=6, mfc="none",
                  label=r"$\langle\Delta\theta^2\rangle^{-1/2}$ at the instants: fit slope "
                        + fmt_exp(fit[0]))
    if np.isfinite(cap):
        ax.axhline(cap, color="0.4", ls=":", lw=1, label="N/2 (finite size: above it, not fitted)")
    ax.set_xlabel(r"$\gamma_c - \gamma$" + f"  (γ_c = {gc:.6g}, "
                  + ("fitted" if "fit" in fits.get("gamma_c", {}) else "ln N/Lx0") + ")")
    ax.set_ylabel("length (rods)")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.suptitle(title(run, "length scales, forward branch"), fontsize=10)
    return fig


@figure("chain_response", models={"chain"})
def fig_chain_response(run: Run, fits: dict) -> Figure:
    """(e) |tau_n| / |tau_0| of the point response, semilog-y, forward (and reverse)."""
    inst = [a for a in run.analysis if "tau_response" in a]
    if not inst:
        raise Skip("no analysis groups with tau_response")
    groups = [("forward instants", [a for a in inst if a.get("direction", 1) > 0], "viridis"),
              ("reverse instants", [a for a in inst if a.get("direction", 1) < 0], "plasma")]
    groups = [gr for gr in groups if gr[1]]
    fig = new_figure(6.2 * len(groups) + 0.5, 4.8)
    axes = fig.subplots(1, len(groups), squeeze=False)[0]
    for ax, (what, sel, cmap) in zip(axes, groups):
        cols, sm = instant_colors(sel, cmap=cmap)
        for a, c in zip(sel, cols):
            t = np.abs(np.asarray(a["tau_response"], float))
            if t.size == 0 or not t[0] > 0:
                continue
            p = t / t[0]
            n = np.arange(p.size)
            ok = p > 0
            ax.semilogy(n[ok], p[ok], "-", color=c, lw=1.2)
        ax.set_ylim(max(ax.get_ylim()[0], 1e-16), 2.0)
        ax.set_xlabel("n (distance from the elongated rod)")
        ax.set_ylabel(r"$|\tau_n| / |\tau_0|$")
        ax.grid(True, alpha=0.3)
        ax.set_title(what, fontsize=10)
        fig.colorbar(sm, ax=ax, label=QLABEL["V2"])
    fig.suptitle(title(run, "point response profiles"), fontsize=10)
    return fig
