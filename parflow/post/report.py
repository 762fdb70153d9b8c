"""The text lines that summarise the fits (printed by ``python -m parflow.plot`` on stderr).

:func:`format_fits` takes the ``fits`` of a run (``chain_fits``, ``network_fits``,
``suspension_fits``) or of several runs (``dict(model, runs, across)``) and looks the
formatter up by the model in :data:`REPORTS`.
"""
from __future__ import annotations

import math

import numpy as np

from .network import RESOLVED_FRACTION
from .suspension import PRED


def fmt_exp(p: float) -> str:
    """An exponent with its sign and three decimals ("n/a" if not finite)."""
    return "n/a" if not np.isfinite(p) else f"{p:+.3f}"


def format_chain_fits(fits: dict) -> list[str]:
    """Summary lines of :func:`parflow.post.chain.chain_fits`."""
    th = fits["theory"]
    lines = []
    for which, gc in fits.get("gamma_c", {}).items():
        r = fits["forward"][which]
        lo, hi = r["window"]
        ex = ", ".join(f"{q} {fmt_exp(r[q][0])} (theory {th[q]:+.3g})"
                       for q in ("V2", "dtheta2", "thetadot2") if q in r)
        lines.append(f"forward, gamma_c {which} = {gc:.8g}: {ex}; window gamma_c-gamma in "
                     f"[{lo:.3g}, {hi:.3g}]")
    if "lengths" in fits:
        L = fits["lengths"]
        lines.append("lengths: " + ", ".join(
            f"{k} {fmt_exp(v[0])}" for k, v in L.items())
            + f" (theory l_corr {th['l_corr']:+.3g}, l_r {th['l_r']:+.3g})")
    if "reverse" in fits:
        r = fits["reverse"]
        t = r["turn"]
        line = (f"reverse, gamma_turn = {fits['gamma_turn']:.10g}: V2 {fmt_exp(t['V2'][0])} "
                f"(theory -1) against gamma_turn-gamma in [{t['window'][0]:.3g}, "
                f"{t['window'][1]:.3g}]")
        if "tilde" in r:
            w = r["tilde"]["window"]
            line += (f"; {fmt_exp(r['tilde']['V2'][0])} against gamma~_c-gamma in [{w[0]:.3g}, "
                     f"{w[1]:.3g}], gamma~_c - gamma_turn = "
                     f"{r['gamma_c_tilde'] - fits['gamma_turn']:.3g}")
        lines.append(line)
    return lines


def format_network_fits(f: dict) -> list[str]:
    """Summary lines of :func:`parflow.post.network.network_fits`."""
    lines = []
    head = f"z = {f['z']:.4g} (dz = {f['dz']:.3g}), seed {f['seed']}"
    if "reverse" in f:
        r = f["reverse"]
        lines.append(f"{head}: reversed branch, -dsigma/dgamma ~ sigma^a over sigma in "
                     f"[{r['window'][0]:g}, {r['window'][1]:g}] ({r['n']} records): a = "
                     f"{r['slope']:.3f} +- {r['slope_err']:.3f} (pred. 2), C = {r['C']:.4g} "
                     f"+- {r['C_err']:.2g} (local C_k median {r['C_median']:.4g})")
    if "omega_min" in f:
        o = f["omega_min"]
        lines.append(f"{head}: omega_min ~ sigma^x for sigma >= {o['sigma_min']:g}: forward "
                     f"{fmt_exp(o['forward'][0])} ({o['forward'][2]}), reverse "
                     f"{fmt_exp(o['reverse'][0])} ({o['reverse'][2]}) (pred. -1/2); C2 = "
                     f"omega_min sqrt(sigma) = {o['C2']:.4g} ({o['C2_p16']:.4g}-"
                     f"{o['C2_p84']:.4g})")
    if "omega_star" in f:
        o = f["omega_star"]
        each = ", ".join(f"{p['omega_star']:.4f} (sigma {p['sigma']:.3g})"
                         for p in o["instants"])
        lines.append(f"{head}: omega* = {o['omega_star']:.4f} +- {o['err']:.4f} (instants: "
                     f"{each})")
    if "response" in f:
        r = f["response"]
        res = [x for x in r["instants"] if x["resolved"]]
        if res:
            lines.append(f"{head}: point response, l_r ~ sigma^{r['l_r_vs_sigma']['exponent']:.3f}"
                         f" +- {r['l_r_vs_sigma']['err']:.3f} over {len(res)} instants with "
                         f"l_r < {RESOLVED_FRACTION:g} r_max (pred. 0.5); l_r/sqrt(sigma) = "
                         + ", ".join(f"{x['lr_over_sqrt_sigma']:.2f}" for x in res)
                         + "; B sqrt(sigma) = "
                         + ", ".join(f"{x['B_sqrt_sigma']:.3g}" for x in res))
    return lines


def format_across_fits(a: dict) -> list[str]:
    """Summary lines of :func:`parflow.post.network.across_fits`."""
    names = dict(C="C of the reversed branch", C2="C2 = omega_min sqrt(sigma)",
                 omega_star="omega*")
    lines = []
    for k, v in a.items():
        f = v["fit"]
        how = (f"weighted, chi2/dof = {f['chi2'] / f['dof']:.2g}" if v["weighted"] and f["dof"]
               else "weighted" if v["weighted"] else "unweighted")
        lines.append(f"across runs: {names[k]} ~ dz^b, b = {f['exponent']:.3f} +- "
                     f"{f['err']:.3f} (pred. {v['predicted']:+g}; {f['n']} runs, {how})")
    return lines


def format_suspension_fits(f: dict) -> list[str]:
    """Summary lines of :func:`parflow.post.suspension.suspension_fits`."""
    if not f or "sigma" not in f:
        return []
    rel = f.get("relaxation", {})
    lines = [f"suspension phi={f['phi']:.4g}: <sigma> = {f['sigma'][0]:.4g} +- {f['sigma'][1]:.2g}, "
             f"<p> = {f.get('pressure', (math.nan,))[0]:.4g}, <mu> = {f.get('mu', (math.nan,))[0]:.4g}, "
             f"z = {f.get('z', (math.nan,))[0]:.4g} (z2 {f.get('z2', (math.nan,))[0]:.4g}, "
             f"z_all {f.get('z_all', (math.nan,))[0]:.4g}), "
             f"{f.get('collisions_per_strain', math.nan):.4g} collisions per unit strain",
             f"  relaxation (frozen contacts, instants): -dsigma/dgamma ~ sigma^"
             f"{f['relax_frozen']['exponent']:.3f} +- {f['relax_frozen']['err']:.3f} (pred. 2), "
             f"median C = {f['relax_frozen']['C_median']:.4g}; collision-free step pairs: "
             f"{rel.get('pairs', 0)} (slope {rel.get('slope', math.nan):.3f}; "
             f"{rel.get('step_jumps', 0)} more across a step-size jump, left out)",
             f"  delta_gamma ~ sigma^{f['delta_gamma']['exponent']:.3f} +- {f['delta_gamma']['err']:.3f} (pred. -1)",
             f"  omega_min ~ sigma^{f['omega_min']['exponent']:.3f} +- {f['omega_min']['err']:.3f} (pred. -0.5)",
             f"  l_c (point response) = {f['resp_l_c'][0]:.3g}, C(r) 1/e length = {f['corr_length'][0]:.3g}"]
    return lines


def format_across_suspension(ac: dict) -> list[str]:
    """Summary lines of the pooled and across-phi fits."""
    def fl(key, pred):
        f = ac.get(key, {})
        lo, hi = f.get("sigma_range", (math.nan, math.nan))
        return (f"  {key}: exponent {f.get('exponent', math.nan):.3f} +- {f.get('err', math.nan):.3f} "
                f"(pred. {pred:g}) over sigma {lo:.3g}-{hi:.3g}, {f.get('n', 0)} instants")
    lines = ["suspension across runs (analysis instants pooled):",
             fl("relax_frozen", PRED["relaxation"]), fl("delta_gamma", PRED["delta_gamma"]),
             fl("omega_min", PRED["omega_min"]),
             f"  delta_gamma * sigma = {ac['delta_gamma_sigma'][0]:.4g} (sd {ac['delta_gamma_sigma'][1]:.2g})"]
    for key, pred in (("sigma_dz", PRED["sigma_dz"]), ("sigma_dz_all", PRED["sigma_dz"]),
                      ("sigma_dz_dp1", PRED["sigma_dz"]),
                      ("lc_p", PRED["lc_p"]), ("lc_dz", PRED["lc_dz"])):
        f = ac.get(key, {})
        lines.append(f"  {key}: exponent {f.get('exponent', math.nan):.3f} +- {f.get('err', math.nan):.3f} "
                     f"(pred. {pred:g}), {f.get('n', 0)} runs")
    fc = ac.get("phi_c", {})
    lines.append(f"  sigma ~ (phi_c - phi)^-beta: phi_c = {fc.get('phi_c', math.nan):.4f}, "
                 f"beta = {fc.get('beta', math.nan):.2f} (rms {fc.get('rms', math.nan):.2g}, "
                 f"{fc.get('n', 0)} runs; expected phi_c ~ 0.843)")
    lines.append("  phi, dz, <sigma>, <p>, mu, l_c: " + "; ".join(
        f"{p:.3f}, {d:.3f}, {s:.4g}, {pp:.4g}, {m:.3f}, {lc:.3g}" for p, d, s, pp, m, lc in
        zip(ac["phi"], ac["dz"], ac["sigma"], ac["p"], ac["mu"], ac["lc"])))
    return lines


# model -> (lines of one run's fits, lines of the fits across runs)
REPORTS = {
    "chain": (format_chain_fits, None),
    "network": (format_network_fits, format_across_fits),
    "suspension": (format_suspension_fits, format_across_suspension),
}


def format_fits(fits: dict) -> list[str]:
    """Human-readable lines summarising the fits of one run, or (a dict with ``across``)
    of several runs of one model; none for a model without a formatter."""
    if not fits:
        return []
    one, across = REPORTS.get(fits.get("model"), (None, None))
    if "across" in fits:
        return across(fits["across"]) if across is not None else []
    return one(fits) if one is not None else []
