"""Suspension figures (paper Figs. 6-7; docs/suspensions.md).

Statistics use the rows and analysis instants past ``observables.analysis_from_strain`` of
the scene (the transient), or the last half of the run if the scene has none.

Single run:

* ``fig6a_sigma``        sigma(gamma) over the statistics window, steps with collisions marked
                         (at N = 4096 nearly all of them); p and mu.
* ``fig6b_relaxation``   -dsigma/dgamma against sigma over pairs of collision-free steps
                         (``post.suspension.relaxation``), slope-2 reference and fit.
* ``fig6c_delta_gamma``  distance to jamming delta_gamma (frozen contacts sheared backwards)
                         against sigma, slope -1 reference and fit.
* ``fig6d_omega_min``    omega_min of the frozen contact network against sigma, slope -1/2.
* ``fig6f_forces``       P(f/<f>) of the force-bearing contacts, averaged over instants.
* ``fig7a_correlation``  C(r) of V_na, mean and spread over instants; point response.

Across runs (several phi):

* ``fig6b_relaxation_phi``, ``fig6c_delta_gamma_phi``, ``fig6d_omega_min_phi``: the power laws
                         of Figs. 6b-d with the analysis instants of all runs pooled (one run
                         spans a narrow range of sigma; the laws appear across phi).
* ``fig6e_sigma_dz``     <sigma> against dz = 2d - z2 (slope -2.7) and against phi; p, mu.
* ``fig7b_lengths``      l_c (point response; C(r) 1/e length) against p (slope 0.18) and dz
                         (slope -1/2).

The numbers are :mod:`parflow.post.suspension`.
"""
from __future__ import annotations

import math
import warnings

import numpy as np

from ..post.fits import fit_power_law_err
from ..post.suspension import (PRED, across_suspension, pooled_points, suspension_across,
                               suspension_fits, window_instants, window_rows)
from .base import Run, Skip, figure, new_figure, reference, register_model


register_model("suspension", fits=suspension_fits, across=suspension_across)


def _phi_text(run: Run) -> str:
    """phi of the scene, or phi -> compress_to for a run compressed while it flowed."""
    to = run.param("compress_to", 0.0)
    return f"{run.param('phi')}→{to}" if to else f"{run.param('phi')}"


def _title(run: Run, what: str) -> str:
    return (f"{what} — suspension N={run.param('N')}, φ={_phi_text(run)}, "
            f"seed {run.scene.get('seed', '?')}")


def _need_rows(run: Run):
    if "sigma" not in run.ts or "strain" not in run.ts:
        raise Skip("no sigma / strain in /timeseries")
    m = window_rows(run)
    if m.sum() < 3:
        raise Skip("fewer than 3 rows past the transient (observables.analysis_from_strain)")
    return m


@figure("fig6a_sigma", models={"suspension"})
def fig6a_sigma(run: Run, fits: dict):
    m = _need_rows(run)
    ts = run.ts
    fig = new_figure(9, 6.5)
    ax, ax2 = fig.subplots(2, 1, sharex=True)
    g = ts["strain"][m]
    ax.semilogy(g, ts["sigma"][m], "-", lw=0.8, label="σ = |V_na|²/Ω")
    if "n_coll" in ts:
        c = m & (ts["n_coll"] > 0)
        ax.semilogy(ts["strain"][c], ts["sigma"][c], ".", ms=2.5, color="C3",
                    label="steps with collisions")
    ax.set_ylabel("σ  [η0 γ̇ / a0]")
    ax.legend(fontsize=8)
    for q, lab in (("pressure", "p"), ("mu", "μ = σ/p")):
        if q in ts:
            ax2.semilogy(g, ts[q][m], "-", lw=0.8, label=lab)
    ax2.set_xlabel("strain γ")
    ax2.legend(fontsize=8)
    s = fits.get("sigma", (math.nan, math.nan))
    ax.set_title(f"⟨σ⟩ = {s[0]:.4g} ± {s[1]:.2g}", fontsize=9)
    frac = float(np.mean(ts["n_coll"][m] > 0)) if "n_coll" in ts else math.nan
    fig.suptitle(_title(run, f"Fig. 6a: σ(γ) in steady flow ({100 * frac:.0f} % of the steps "
                             f"have collisions; dσ/dγ between them: Fig. 6b)"), fontsize=10)
    return fig


@figure("fig6b_relaxation", models={"suspension"})
def fig6b_relaxation(run: Run, fits: dict):
    """-dsigma/dgamma against sigma: at the analysis instants from the frozen contacts sheared
    along the flow (the suspension's dynamics until the next collision), and from pairs of
    consecutive collision-free steps of equal size (within 2x) when there are any
    (``post.suspension.relaxation``; small N only: at N = 4096 nearly every step has a
    collision)."""
    rs, rd = fits.get("relax_frozen_points", (np.array([]), np.array([])))
    ok = np.isfinite(rs) & np.isfinite(rd) & (rs > 0) & (rd > 0)
    pairs = fits.get("relaxation", {}).get("points")
    if pairs is not None and len(pairs[0]) < 3:
        pairs = None
    if ok.sum() < 2 and pairs is None:
        raise Skip("no relaxation rate at the analysis instants and no collision-free step pairs")
    fig = new_figure(6.5, 5)
    ax = fig.subplots()
    f = fits.get("relax_frozen", {})
    if ok.sum():
        ax.loglog(rs[ok], rd[ok], "o", ms=4, label="instants (frozen contacts along the flow)")
        x0 = float(np.exp(np.mean(np.log(rs[ok]))))
        reference(ax, x0, x0 ** 2 / f.get("C_median", np.nan), 2.0, 10,
                   f"σ²/C, median C = {f.get('C_median', math.nan):.3g}")
    if pairs is not None:
        ax.loglog(*pairs, ".", ms=3, alpha=0.5, label="collision-free step pairs")
    ax.set_xlabel("σ")
    ax.set_ylabel("−dσ/dγ")
    ax.set_title(f"exponent {f.get('exponent', math.nan):.3f} ± {f.get('err', math.nan):.3f} "
                 f"(pred. 2)", fontsize=9)
    ax.legend(fontsize=8)
    fig.suptitle(_title(run, "Fig. 6b: dσ/dγ = −σ²/C between collisions"), fontsize=10)
    return fig


def _power_fig(run, fits, key, ylabel, pred, what):
    sig, y = fits.get(key + "_points", (np.array([]), np.array([])))
    ok = np.isfinite(sig) & np.isfinite(y) & (sig > 0) & (y > 0)
    if ok.sum() < 2:
        raise Skip(f"fewer than 2 analysis instants with {key} (observables.analysis_strain)")
    fig = new_figure(6.5, 5)
    ax = fig.subplots()
    ax.loglog(sig[ok], y[ok], "o", ms=4, label="analysis instants")
    f = fits[key]
    if np.isfinite(f["exponent"]):
        xs = np.geomspace(sig[ok].min(), sig[ok].max(), 20)
        ax.plot(xs, f["prefactor"] * xs ** f["exponent"], "-", lw=2, alpha=0.5,
                label=f"fit: exponent {f['exponent']:.3f} ± {f['err']:.3f}")
    x0 = float(np.exp(np.mean(np.log(sig[ok]))))
    y0 = float(np.exp(np.mean(np.log(y[ok]))))
    reference(ax, x0, y0, pred, 10, f"slope {pred:g} (paper)")
    ax.set_xlabel("σ")
    ax.set_ylabel(ylabel)
    ax.legend(fontsize=8)
    fig.suptitle(_title(run, what), fontsize=10)
    return fig


@figure("fig6c_delta_gamma", models={"suspension"})
def fig6c_delta_gamma(run: Run, fits: dict):
    return _power_fig(run, fits, "delta_gamma", "δγ (frozen contacts sheared backwards)",
                      PRED["delta_gamma"], "Fig. 6c: distance to jamming δγ ∝ 1/σ")


@figure("fig6d_omega_min", models={"suspension"})
def fig6d_omega_min(run: Run, fits: dict):
    return _power_fig(run, fits, "omega_min", "ω_min of the frozen contact network",
                      PRED["omega_min"], "Fig. 6d: ω_min ∝ 1/√σ")


@figure("fig6f_forces", models={"suspension"})
def fig6f_forces(run: Run, fits: dict):
    inst = [a for a in window_instants(run) if "force_P" in a]
    if not inst:
        raise Skip("no P(f) in the analysis groups")
    edges = inst[0]["force_edges"]
    P = np.nanmean(np.array([a["force_P"] for a in inst]), axis=0)
    x = np.sqrt(edges[:-1] * edges[1:])
    fig = new_figure(6.5, 5)
    ax = fig.subplots()
    ok = P > 0
    ax.loglog(x[ok], P[ok], "o-", ms=3)
    ax.set_xlabel("f / ⟨f⟩")
    ax.set_ylabel("P(f/⟨f⟩)")
    ax.set_title(f"{len(inst)} instants, force-bearing contacts", fontsize=9)
    fig.suptitle(_title(run, "contact-force distribution"), fontsize=10)
    return fig


@figure("fig7a_correlation", models={"suspension"})
def fig7a_correlation(run: Run, fits: dict):
    inst = [a for a in window_instants(run) if "corr_C" in a]
    if not inst:
        raise Skip("no C(r) in the analysis groups")
    fig = new_figure(11, 4.6)
    ax, ax2 = fig.subplots(1, 2)
    # the largest r (half the smallest cell height) changes as the cell shears: common bins
    nb = min(len(a["corr_C"]) for a in inst)
    r = inst[0]["corr_r"][:nb]
    C = np.array([a["corr_C"][:nb] for a in inst])
    with warnings.catch_warnings():            # empty bins (no pair that close) are NaN
        warnings.simplefilter("ignore", RuntimeWarning)
        ax.plot(r, np.nanmean(C, axis=0), "-", color="k", label=f"mean of {len(C)} instants")
        ax.fill_between(r, np.nanpercentile(C, 16, axis=0), np.nanpercentile(C, 84, axis=0),
                        alpha=0.3, label="16–84 %")
    ax.axhline(0, color="0.6", lw=0.8)
    ax.set_xlabel("r  [a0]")
    ax.set_ylabel("C(r) = ⟨V_i·V_j⟩/⟨V²⟩")
    lc = fits.get("corr_length", (math.nan, math.nan))
    ax.set_title(f"1/e length {lc[0]:.3g} a0", fontsize=9)
    ax.legend(fontsize=8)
    resp = [a for a in inst if "resp_V" in a]
    if resp:
        nb = min(len(a["resp_V"]) for a in resp)
        rr = resp[0]["resp_r"][:nb]
        V = np.array([a["resp_V"][:nb] for a in resp])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            ax2.semilogy(rr, np.nanmean(V, axis=0), "-", color="C1")
        lcr = fits.get("resp_l_c", (math.nan, math.nan))
        ax2.set_title(f"point response of the frozen contacts: l_c = {lcr[0]:.3g} a0", fontsize=9)
    ax2.set_xlabel("r  [a0]")
    ax2.set_ylabel("|V|(r)")
    fig.suptitle(_title(run, "Fig. 7a: velocity correlation and point response"), fontsize=10)
    return fig


# ------------------------------------------------------------------------------ across runs

def _across_title(runs, what):
    # (a run compressed while it flowed: the phi it reached)
    phis = sorted(float(r.param("compress_to", 0.0) or r.param("phi", math.nan)) for r in runs)
    return f"{what} — suspension N={runs[0].param('N')}, φ = {phis[0]:.3f}–{phis[-1]:.3f} ({len(runs)} runs)"


def _pooled_fig(runs, fits, key, ylabel, pred, what):
    x, y, ph = pooled_points(fits, key)
    ok = np.isfinite(x) & np.isfinite(y) & (x > 0) & (y > 0)
    if ok.sum() < 3 or len({p for p in ph[ok]}) < 2:
        raise Skip(f"needs {key} at analysis instants of 2 or more runs")
    fig = new_figure(6.8, 5.2)
    ax = fig.subplots()
    for p in sorted(set(ph[ok])):
        m = ok & (ph == p)
        ax.loglog(x[m], y[m], "o", ms=4, label=f"φ = {p:.3f}")
    f = fit_power_law_err(x, y)
    xs = np.geomspace(x[ok].min(), x[ok].max(), 20)
    if np.isfinite(f["exponent"]):
        ax.plot(xs, f["prefactor"] * xs ** f["exponent"], "-", color="k", lw=2, alpha=0.4,
                label=f"fit: {f['exponent']:.3f} ± {f['err']:.3f}")
    reference(ax, float(np.exp(np.mean(np.log(x[ok])))), float(np.exp(np.mean(np.log(y[ok])))),
               pred, 10, f"slope {pred:g} (paper)")
    ax.set_xlabel("σ (of the frozen contacts at the instant)")
    ax.set_ylabel(ylabel)
    ax.legend(fontsize=8)
    fig.suptitle(_across_title(runs, what), fontsize=10)
    return fig


@figure("fig6b_relaxation_phi", models={"suspension"}, across=True)
def fig6b_relaxation_phi(runs, fits, across):
    return _pooled_fig(runs, fits, "relax_frozen", "−dσ/dγ (frozen contacts along the flow)",
                       PRED["relaxation"], "Fig. 6b: dσ/dγ = −σ²/C")


@figure("fig6c_delta_gamma_phi", models={"suspension"}, across=True)
def fig6c_delta_gamma_phi(runs, fits, across):
    return _pooled_fig(runs, fits, "delta_gamma", "δγ (frozen contacts sheared backwards)",
                       PRED["delta_gamma"], "Fig. 6c: δγ ∝ 1/σ")


@figure("fig6d_omega_min_phi", models={"suspension"}, across=True)
def fig6d_omega_min_phi(runs, fits, across):
    return _pooled_fig(runs, fits, "omega_min", "ω_min of the frozen contact network",
                       PRED["omega_min"], "Fig. 6d: ω_min ∝ 1/√σ")


@figure("fig6e_sigma_dz", models={"suspension"}, across=True)
def fig6e_sigma_dz(runs, fits, across):
    ac = across_suspension(fits)
    if np.sum(np.isfinite(ac["sigma"]) & (ac["dz"] > 0)) < 2:
        raise Skip("needs 2 or more runs with z < 4 in the statistics window")
    fig = new_figure(11, 4.6)
    ax, ax2 = fig.subplots(1, 2)
    ax.errorbar(ac["dz"], ac["sigma"], yerr=ac["sigma_err"], fmt="o")
    ax.set_xscale("log")
    ax.set_yscale("log")
    f = ac["sigma_dz"]
    ok = np.isfinite(ac["sigma"]) & (ac["dz"] > 0)
    x0 = float(np.exp(np.mean(np.log(ac["dz"][ok]))))
    y0 = float(np.exp(np.mean(np.log(ac["sigma"][ok]))))
    reference(ax, x0, y0, PRED["sigma_dz"], 2, "slope −2.7 (paper)")
    ax.set_xlabel("δz = 4 − z  (z: particles with ≥ 2 contacts)")
    ax.set_ylabel("⟨σ⟩")
    fa = ac["sigma_dz_all"]
    ax.loglog(ac["dz_all"], ac["sigma"], "s", mfc="none", color="C1",
              label=f"δz from z_all (all particles): {fa['exponent']:.2f} ± {fa['err']:.2f}")
    fd = ac["sigma_dz_dp1"]
    if fd["n"] >= 2:
        ax.loglog(ac["dz_dp1"], ac["sigma"], "^", mfc="none", color="C2",
                  label=f"δz, rattlers < d+1 contacts (z ≥ 3 only): {fd['exponent']:.2f} ± "
                        f"{fd['err']:.2f}")
    ax.set_title(f"fit exponent {f['exponent']:.2f} ± {f['err']:.2f} (z2)", fontsize=9)
    ax.legend(fontsize=8)
    ax2.semilogy(ac["phi"], ac["sigma"], "o", label="⟨σ⟩")
    fc = ac["phi_c"]
    if np.isfinite(fc["phi_c"]):
        xs = np.linspace(np.nanmin(ac["phi"]), np.nanmax(ac["phi"]), 50)
        ok = np.isfinite(ac["sigma"])
        lnA = np.mean(np.log(ac["sigma"][ok]) + fc["beta"] * np.log(fc["phi_c"] - ac["phi"][ok]))
        ax2.semilogy(xs, np.exp(lnA) * (fc["phi_c"] - xs) ** -fc["beta"], "-", color="C0", alpha=0.5,
                     label=f"(φ_c − φ)^−{fc['beta']:.2f}, φ_c = {fc['phi_c']:.4f}")
    ax2.semilogy(ac["phi"], ac["p"], "s-", label="⟨p⟩")
    ax3 = ax2.twinx()
    ax3.plot(ac["phi"], ac["mu"], "^-", color="C2", label="μ = σ/p")
    ax3.set_ylabel("μ")
    ax2.set_xlabel("φ")
    ax2.legend(fontsize=8, loc="upper left")
    ax3.legend(fontsize=8, loc="lower right")
    fig.suptitle(_across_title(runs, "Fig. 6e: σ ∝ δz^−2.7; σ, p, μ against φ"), fontsize=10)
    return fig


@figure("fig7b_lengths", models={"suspension"}, across=True)
def fig7b_lengths(runs, fits, across):
    ac = across_suspension(fits)
    ok = np.isfinite(ac["lc"]) & (ac["lc"] > 0)
    if ok.sum() < 2:
        raise Skip("needs 2 or more runs with a point-response l_c")
    fig = new_figure(11, 4.6)
    ax, ax2 = fig.subplots(1, 2)
    ax.errorbar(ac["p"], ac["lc"], yerr=ac["lc_err"], fmt="o", label="l_c (point response)")
    ax.loglog(ac["p"], ac["corr"], "s", label="C(r) 1/e length")
    reference(ax, float(np.exp(np.mean(np.log(ac["p"][ok])))),
               float(np.exp(np.mean(np.log(ac["lc"][ok])))), PRED["lc_p"], 3, "slope 0.18 (paper)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("⟨p⟩")
    ax.set_ylabel("length  [a0]")
    ax.set_title(f"l_c ∝ p^{ac['lc_p']['exponent']:.2f}±{ac['lc_p']['err']:.2f}", fontsize=9)
    ax.legend(fontsize=8)
    ax2.errorbar(ac["dz"], ac["lc"], yerr=ac["lc_err"], fmt="o")
    ax2.set_xscale("log")
    ax2.set_yscale("log")
    good = ok & (ac["dz"] > 0)
    if good.sum() >= 1:
        reference(ax2, float(np.exp(np.mean(np.log(ac["dz"][good])))),
                   float(np.exp(np.mean(np.log(ac["lc"][good])))), PRED["lc_dz"], 2,
                   "slope −1/2 (paper)")
    ax2.set_xlabel("δz = 4 − z")
    ax2.set_ylabel("l_c  [a0]")
    ax2.set_title(f"l_c ∝ δz^{ac['lc_dz']['exponent']:.2f}±{ac['lc_dz']['err']:.2f}", fontsize=9)
    ax2.legend(fontsize=8)
    fig.suptitle(_across_title(runs, "Fig. 7b: l_c ∝ δz^−1/2 ∝ p^0.18"), fontsize=10)
    return fig
