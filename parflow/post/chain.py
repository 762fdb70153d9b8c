"""The chain's numbers (DESIGN §6, paper Fig. 2): gamma_c (the model attribute and fitted),
the forward exponents of <V^2>, <dtheta^2>, <thetadot^2> against gamma_c - gamma, the
exponents of l_corr, l_r and <dtheta^2>^(-1/2), the reverse exponent of <V^2>, and the strain
at which the reversed branch departs from the forward one (reversal_departure)."""
from __future__ import annotations

import numpy as np

from .fits import (BINS_PER_DECADE, fit_divergence_point, fit_power_law, fit_window,
                   forward_instants, forward_rows, reverse_rows, typical_dgamma)


def chain_theory(mu: float) -> dict:
    """Exponents of DESIGN §6 (x = gamma_c - gamma on the forward branch)."""
    p = (3.0 + mu) / (1.0 + mu)
    return dict(V2=-p, dtheta2=p, thetadot2=-1.0, l_corr=-1.0 / (1.0 + mu), l_r=-p / 2,
                reverse_V2=-1.0)


def chain_fits(run) -> dict:
    """The chain's fitted numbers: gamma_c (attribute and fitted), forward exponents for each
    gamma_c, reverse exponent, exponents of l_corr, l_r and <dtheta^2>^(-1/2).  Keys absent
    when their data are; the fitted gamma_c is absent, too, when it lies at or before the
    largest gamma the forward branch reached (linearised with the mean-field exponent, data
    that diverge faster put it there)."""
    mu = float(run.param("mu", 0) or 0)
    th = chain_theory(mu)
    out: dict = dict(model="chain", mu=mu, theory=th)
    fw = forward_rows(run)
    if fw is None or "V2" not in run.ts or "gamma" not in run.ts:
        return out
    ts = run.ts
    g, V2 = ts["gamma"][fw], ts["V2"][fw]
    dg = typical_dgamma(ts["dgamma"][fw]) if "dgamma" in ts else 0.0
    out["dgamma_typical"] = dg
    out["gamma_end"] = float(g[-1])
    gcs = {}
    if np.isfinite(run.model_attrs.get("gamma_c", np.nan)):
        gcs["attr"] = float(run.model_attrs["gamma_c"])
    gfit = fit_divergence_point(g, V2, th["V2"])
    if np.isfinite(gfit) and gfit > g.max():     # one the run went past is none
        gcs["fit"] = gfit
    out["gamma_c"] = gcs
    out["forward"] = {}
    for which, gc in gcs.items():
        x = gc - g
        lo, hi = fit_window(x, dg)
        res = dict(window=(lo, hi))
        for q in ("V2", "dtheta2", "thetadot2"):
            if q in ts:
                res[q] = fit_power_law(x, ts[q][fw], lo, hi, BINS_PER_DECADE)
        out["forward"][which] = res
    gc = primary_gamma_c(gcs)
    if gc is not None:
        inst = [a for a in forward_instants(run) if gc - a["gamma"] > 0]
        if inst:
            x = np.array([gc - a["gamma"] for a in inst])
            lo, hi = fit_window(x, dg)
            cap = length_cap(run)
            lengths = {}
            for q in ("l_corr", "l_r", "dtheta2^-1/2"):
                if q == "dtheta2^-1/2":
                    y = np.array([float(a.get("dtheta2", np.nan)) for a in inst]) ** -0.5
                else:
                    y = np.array([float(a.get(q, np.nan)) for a in inst])
                    y = np.where(y < cap, y, np.nan)      # measured beyond N/2: finite size
                lengths[q] = fit_power_law(x, y, lo, hi)
            out["lengths"] = lengths
            out["lengths_window"] = (lo, hi)
    rv = reverse_rows(run)
    if rv is not None:
        rows, gturn = rv
        gr, Vr = ts["gamma"][rows], ts["V2"][rows]
        out["gamma_turn"] = gturn
        rev = dict()
        # against gamma_turn - gamma (> 0: gamma decreases), past the plateau that follows the turn
        xr = gturn - gr
        lo, hi = reverse_window(xr, Vr)
        rev["turn"] = dict(window=(lo, hi), V2=fit_power_law(xr, Vr, lo, hi, BINS_PER_DECADE))
        # gamma~_c: where 1/V2, linear in gamma once past the plateau (one to two decades below
        # the value at the turn), extrapolates to zero
        gct = fit_divergence_point(gr, Vr, chain_theory(mu)["reverse_V2"], decades=1.0, skip=1.0)
        rev["gamma_c_tilde"] = gct
        if np.isfinite(gct):
            xt = gct - gr
            lo, hi = reverse_window(xt, Vr)
            rev["tilde"] = dict(window=(lo, hi), V2=fit_power_law(xt, Vr, lo, hi, BINS_PER_DECADE))
        out["reverse"] = rev
    return out


def length_cap(run) -> float:
    """N/2: longer lengths are finite-size artefacts and stay out of the fits."""
    N = run.param("N")
    if N is None:
        Cs = [len(a["C_n"]) for a in run.analysis if "C_n" in a]
        N = 2 * (Cs[0] - 1) if Cs else None
    return float(N) / 2 if N else float("inf")


def primary_gamma_c(gcs: dict) -> float | None:
    """gamma_c used by the figures with a single x axis: the exact ln(N a0 / Lx(0)) (the
    chain is straight, hence jammed, exactly there), else the fitted one.  The fitted value
    is a diagnostic of how far the run is from the asymptotic regime, not a better gamma_c."""
    return gcs.get("attr", gcs.get("fit"))


def reverse_window(x, V2):
    """Fit window on the reverse branch: from where <V^2> has dropped by a factor 10 below its
    value at the turn (past the initial plateau) to the end of the branch."""
    x, V2 = np.asarray(x, float), np.asarray(V2, float)
    ok = np.isfinite(V2) & (x > 0)
    if ok.sum() < 3:
        return float("nan"), float("nan")
    v_turn = V2[np.isfinite(V2)][0]
    past = ok & (V2 <= v_turn / 10.0)
    lo = float(x[past].min()) if past.any() else float(x[ok].min())
    return lo, float(x[ok].max())


def reversal_departure(d, level: float = 0.1, interpolate: bool = False) -> float:
    """Strain since the reversal where the reversed branch leaves the forward one (``d``: the
    timeseries columns gamma, V2, direction; NaN if it never leaves): the first reversed row
    where |ln V2_rev - ln V2_fwd| (the forward branch interpolated to the row's gamma) exceeds
    ``level``; with ``interpolate``, the crossing between that row and the one before,
    log-linear in the deviation (it grows exponentially)."""
    f, r = d["direction"] > 0, d["direction"] < 0
    if not r.any():
        return float("nan")
    gf, vf = d["gamma"][f], d["V2"][f]
    g_turn = gf[-1]
    gr, vr = d["gamma"][r], d["V2"][r]
    ok = gr >= gf[0]
    x = g_turn - gr[ok]
    dev = np.abs(np.log(vr[ok]) - np.interp(gr[ok], gf, np.log(vf)))
    if not np.any(dev > level):
        return float("nan")
    k = int(np.argmax(dev > level))
    if not interpolate or k == 0 or dev[k - 1] <= 0:
        return float(x[k])
    a, b = np.log(dev[k - 1]), np.log(dev[k])
    return float(x[k - 1] + (np.log(level) - a) / (b - a) * (x[k] - x[k - 1]))
