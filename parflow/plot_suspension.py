"""Suspension figures (paper Figs. 6-7; docs/suspensions.md), drawn by ``parflow.plot``.

Statistics use the rows and analysis instants past ``observables.analysis_from_strain`` of
the scene (the transient), or the last half of the run if the scene has none.

Single run:

* ``fig6a_sigma``        sigma(gamma) over the statistics window, steps with collisions marked
                         (at N = 4096 nearly all of them); p and mu.
* ``fig6b_relaxation``   -dsigma/dgamma against sigma over pairs of collision-free steps
                         (``suspension.relaxation``), slope-2 reference and fit.
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
"""
from __future__ import annotations

import math
import warnings

import numpy as np

from .plot import (Run, Skip, _figure, _reference, fit_power_law_err)

PRED = dict(relaxation=2.0, delta_gamma=-1.0, omega_min=-0.5, sigma_dz=-2.7, lc_p=0.18,
            lc_dz=-0.5)


def _from_strain(run: Run) -> float:
    x = run.scene.get("observables", {}).get("analysis_from_strain")
    strain = run.ts.get("strain")
    if x:
        return float(x)
    return 0.5 * float(strain[-1]) if strain is not None and len(strain) else 0.0


def window_rows(run: Run) -> np.ndarray:
    """Boolean mask of the rows in the statistics window (forward steps past the transient)."""
    ts = run.ts
    m = np.asarray(ts["strain"]) >= _from_strain(run)
    if "step" in ts:
        m &= np.asarray(ts["step"]) > 0
    if "direction" in ts:
        m &= np.asarray(ts["direction"]) > 0
    return m


def window_instants(run: Run) -> list[dict]:
    x0 = _from_strain(run)
    return [a for a in run.analysis if float(a.get("strain", a.get("gamma", 0.0))) >= x0 - 1e-12]


def _mean_err(x: np.ndarray, blocks: int = 10) -> tuple[float, float]:
    """Mean and its error from block averages (the series is correlated)."""
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return math.nan, math.nan
    if x.size < 2 * blocks:
        return float(x.mean()), float(x.std() / math.sqrt(max(x.size - 1, 1)))
    b = np.array([c.mean() for c in np.array_split(x, blocks)])
    return float(x.mean()), float(b.std(ddof=1) / math.sqrt(blocks))


def _strain_weighted(x, w):
    x, w = np.asarray(x, float), np.abs(np.asarray(w, float))
    ok = np.isfinite(x) & (w > 0)
    return float(np.sum(x[ok] * w[ok]) / np.sum(w[ok])) if ok.any() else math.nan


def suspension_fits(run: Run) -> dict:
    """Averages over the statistics window and the power laws of Figs. 6-7 for one run."""
    from .suspension import relaxation
    ts = run.ts
    if "sigma" not in ts or "strain" not in ts:
        return dict(model="suspension")
    m = window_rows(run)
    out = dict(model="suspension", phi=float(run.model_attrs.get("phi", run.param("phi", math.nan))),
               N=int(run.param("N", 0) or 0), rows=int(m.sum()),
               strain_window=(float(np.min(ts["strain"][m])) if m.any() else math.nan,
                              float(np.max(ts["strain"][m])) if m.any() else math.nan))
    dg = ts.get("dgamma", np.ones_like(ts["sigma"]))
    for q in ("sigma", "pressure", "mu", "z", "z_all", "z2"):
        if q in ts and m.any():
            mean, err = _mean_err(ts[q][m])
            out[q] = (_strain_weighted(ts[q][m], dg[m]), err)
    if m.any() and "collisions" in ts:
        st = ts["strain"][m]
        span = float(st.max() - st.min())
        dc = float(ts["collisions"][m][-1] - ts["collisions"][m][0])
        out["collisions_per_strain"] = dc / span if span > 0 else math.nan
    if m.sum() > 4 and "n_coll" in ts:
        idx = np.flatnonzero(m)
        rel = relaxation(ts["gamma"][idx], ts["dgamma"][idx], ts["sigma"][idx], ts["n_coll"][idx])
        out["relaxation"] = rel
    inst = window_instants(run)
    rs = np.array([a.get("relax_sigma", np.nan) for a in inst], float)
    rd = -np.array([a.get("relax_dsdg", np.nan) for a in inst], float)
    out["relax_frozen"] = fit_power_law_err(rs, rd)
    out["relax_frozen_points"] = (rs, rd)
    rc = np.array([a.get("relax_C", np.nan) for a in inst], float)
    rc = rc[np.isfinite(rc)]
    out["relax_frozen"]["C_median"] = float(np.median(rc)) if rc.size else math.nan
    # x axis: the stress of the frozen contact network at the instant, on which delta_gamma
    # and omega_min are measured (the row's sigma belongs to the step, whose size it depends
    # on; e.g. a leg's last step is cut short to end the leg)
    sig = np.array([a.get("frozen_sigma", np.nan) for a in inst], float)
    for key, q in (("delta_gamma", "delta_gamma"), ("omega_min", "frozen_omega_min")):
        y = np.array([a.get(q, np.nan) for a in inst], float)
        out[key] = fit_power_law_err(sig, y)
        out[key + "_points"] = (sig, y)
    for key in ("resp_l_c", "corr_length"):
        y = np.array([a.get(key, np.nan) for a in inst], float)
        y = y[np.isfinite(y) & (y > 0)]
        out[key] = (float(np.median(y)), float(np.std(y) / math.sqrt(len(y)))) if y.size else (math.nan, math.nan)
    out["instants"] = len(inst)
    return out


def _title(run: Run, what: str) -> str:
    return (f"{what} — suspension N={run.param('N')}, φ={run.param('phi')}, "
            f"seed {run.scene.get('seed', '?')}")


def _need_rows(run: Run):
    if "sigma" not in run.ts or "strain" not in run.ts:
        raise Skip("no sigma / strain in /timeseries")
    m = window_rows(run)
    if m.sum() < 3:
        raise Skip("fewer than 3 rows past the transient (observables.analysis_from_strain)")
    return m


def fig6a_sigma(run: Run, fits: dict):
    m = _need_rows(run)
    ts = run.ts
    fig = _figure(9, 6.5)
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


def fig6b_relaxation(run: Run, fits: dict):
    """-dsigma/dgamma against sigma: at the analysis instants from the frozen contacts sheared
    along the flow (the suspension's dynamics until the next collision), and from pairs of
    consecutive collision-free steps of the run when there are any (small N only: at
    N = 4096 nearly every step has a collision)."""
    rs, rd = fits.get("relax_frozen_points", (np.array([]), np.array([])))
    ok = np.isfinite(rs) & np.isfinite(rd) & (rs > 0) & (rd > 0)
    ts = run.ts
    pairs = None
    if "n_coll" in ts and "sigma" in ts:
        m = window_rows(run)
        idx = np.flatnonzero(m)
        if idx.size > 2:
            g0 = ts["gamma"][idx] - ts["dgamma"][idx]
            s, nc = ts["sigma"][idx], ts["n_coll"][idx]
            dsdg = np.diff(s) / np.diff(g0)
            dec = (nc[:-1] == 0) & (nc[1:] == 0) & (dsdg < 0)
            if dec.sum() >= 3:
                pairs = (np.sqrt(s[:-1] * s[1:])[dec], -dsdg[dec])
    if ok.sum() < 2 and pairs is None:
        raise Skip("no relaxation rate at the analysis instants and no collision-free step pairs")
    fig = _figure(6.5, 5)
    ax = fig.subplots()
    f = fits.get("relax_frozen", {})
    if ok.sum():
        ax.loglog(rs[ok], rd[ok], "o", ms=4, label="instants (frozen contacts along the flow)")
        x0 = float(np.exp(np.mean(np.log(rs[ok]))))
        _reference(ax, x0, x0 ** 2 / f.get("C_median", np.nan), 2.0, 10,
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
    fig = _figure(6.5, 5)
    ax = fig.subplots()
    ax.loglog(sig[ok], y[ok], "o", ms=4, label="analysis instants")
    f = fits[key]
    if np.isfinite(f["exponent"]):
        xs = np.geomspace(sig[ok].min(), sig[ok].max(), 20)
        ax.plot(xs, f["prefactor"] * xs ** f["exponent"], "-", lw=2, alpha=0.5,
                label=f"fit: exponent {f['exponent']:.3f} ± {f['err']:.3f}")
    x0 = float(np.exp(np.mean(np.log(sig[ok]))))
    y0 = float(np.exp(np.mean(np.log(y[ok]))))
    _reference(ax, x0, y0, pred, 10, f"slope {pred:g} (paper)")
    ax.set_xlabel("σ")
    ax.set_ylabel(ylabel)
    ax.legend(fontsize=8)
    fig.suptitle(_title(run, what), fontsize=10)
    return fig


def fig6c_delta_gamma(run: Run, fits: dict):
    return _power_fig(run, fits, "delta_gamma", "δγ (frozen contacts sheared backwards)",
                      PRED["delta_gamma"], "Fig. 6c: distance to jamming δγ ∝ 1/σ")


def fig6d_omega_min(run: Run, fits: dict):
    return _power_fig(run, fits, "omega_min", "ω_min of the frozen contact network",
                      PRED["omega_min"], "Fig. 6d: ω_min ∝ 1/√σ")


def fig6f_forces(run: Run, fits: dict):
    inst = [a for a in window_instants(run) if "force_P" in a]
    if not inst:
        raise Skip("no P(f) in the analysis groups")
    edges = inst[0]["force_edges"]
    P = np.nanmean(np.array([a["force_P"] for a in inst]), axis=0)
    x = np.sqrt(edges[:-1] * edges[1:])
    fig = _figure(6.5, 5)
    ax = fig.subplots()
    ok = P > 0
    ax.loglog(x[ok], P[ok], "o-", ms=3)
    ax.set_xlabel("f / ⟨f⟩")
    ax.set_ylabel("P(f/⟨f⟩)")
    ax.set_title(f"{len(inst)} instants, force-bearing contacts", fontsize=9)
    fig.suptitle(_title(run, "contact-force distribution"), fontsize=10)
    return fig


def fig7a_correlation(run: Run, fits: dict):
    inst = [a for a in window_instants(run) if "corr_C" in a]
    if not inst:
        raise Skip("no C(r) in the analysis groups")
    fig = _figure(11, 4.6)
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
    phis = sorted(float(r.param("phi", math.nan)) for r in runs)
    return f"{what} — suspension N={runs[0].param('N')}, φ = {phis[0]:.3f}–{phis[-1]:.3f} ({len(runs)} runs)"


def fit_phi_c(phi, sigma, phi_max: float = 0.9) -> dict:
    """sigma = A (phi_c - phi)^(-beta): phi_c by scanning, A and beta by least squares in
    log-log at each phi_c; the phi_c of smallest residual.  NaN with fewer than 4 runs (three
    parameters)."""
    phi, sigma = np.asarray(phi, float), np.asarray(sigma, float)
    ok = np.isfinite(phi) & np.isfinite(sigma) & (sigma > 0)
    out = dict(phi_c=math.nan, beta=math.nan, rms=math.nan, n=int(ok.sum()))
    if ok.sum() < 4:
        return out
    x, y = phi[ok], np.log(sigma[ok])
    best = None
    for pc in np.linspace(x.max() + 1e-4, phi_max, 4000):
        X = np.log(pc - x)
        a, b = np.polyfit(X, y, 1)
        rms = float(np.sqrt(np.mean((y - (a * X + b)) ** 2)))
        if best is None or rms < best[0]:
            best = (rms, pc, -a)
    out.update(rms=best[0], phi_c=float(best[1]), beta=float(best[2]))
    return out


def across_suspension(fits: list[dict]) -> dict:
    """sigma(dz) and l_c(p), l_c(dz) across runs (dz = 4 - z2)."""
    def col(key, k=0):
        return np.array([f.get(key, (math.nan, math.nan))[k] for f in fits], float)
    # dz from z2 (rattlers: fewer than 2 force-bearing contacts, removed iteratively): the
    # d + 1 rule of jammed packings removes every particle of a flowing N = 4096 state
    dz = 4.0 - col("z2")
    out = dict(dz=dz, phi=np.array([f.get("phi", math.nan) for f in fits]), sigma=col("sigma"),
               sigma_err=col("sigma", 1), p=col("pressure"), mu=col("mu"),
               lc=col("resp_l_c"), lc_err=col("resp_l_c", 1), corr=col("corr_length"))
    out["sigma_dz"] = fit_power_law_err(dz, out["sigma"], out["sigma_err"])
    # the same with every particle counted (z_all): how much the rattler rule matters
    out["dz_all"] = 4.0 - col("z_all")
    out["sigma_dz_all"] = fit_power_law_err(out["dz_all"], out["sigma"], out["sigma_err"])
    # DESIGN's rule (< d + 1 contacts, iteratively) where it leaves a backbone (z >= 3: at
    # phi <= 0.825 it removes most particles of a flowing state, and z there means little)
    z_dp1 = col("z")
    out["dz_dp1"] = np.where(z_dp1 >= 3.0, 4.0 - z_dp1, np.nan)
    out["sigma_dz_dp1"] = fit_power_law_err(out["dz_dp1"], out["sigma"], out["sigma_err"])
    out["phi_c"] = fit_phi_c(out["phi"], out["sigma"])
    out["lc_p"] = fit_power_law_err(out["p"], out["lc"])
    out["lc_dz"] = fit_power_law_err(dz, out["lc"])
    return out


def fig6e_sigma_dz(runs, fits, across):
    ac = across_suspension(fits)
    if np.sum(np.isfinite(ac["sigma"]) & (ac["dz"] > 0)) < 2:
        raise Skip("needs 2 or more runs with z < 4 in the statistics window")
    fig = _figure(11, 4.6)
    ax, ax2 = fig.subplots(1, 2)
    ax.errorbar(ac["dz"], ac["sigma"], yerr=ac["sigma_err"], fmt="o")
    ax.set_xscale("log")
    ax.set_yscale("log")
    f = ac["sigma_dz"]
    ok = np.isfinite(ac["sigma"]) & (ac["dz"] > 0)
    x0 = float(np.exp(np.mean(np.log(ac["dz"][ok]))))
    y0 = float(np.exp(np.mean(np.log(ac["sigma"][ok]))))
    _reference(ax, x0, y0, PRED["sigma_dz"], 2, "slope −2.7 (paper)")
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


def fig7b_lengths(runs, fits, across):
    ac = across_suspension(fits)
    ok = np.isfinite(ac["lc"]) & (ac["lc"] > 0)
    if ok.sum() < 2:
        raise Skip("needs 2 or more runs with a point-response l_c")
    fig = _figure(11, 4.6)
    ax, ax2 = fig.subplots(1, 2)
    ax.errorbar(ac["p"], ac["lc"], yerr=ac["lc_err"], fmt="o", label="l_c (point response)")
    ax.loglog(ac["p"], ac["corr"], "s", label="C(r) 1/e length")
    _reference(ax, float(np.exp(np.mean(np.log(ac["p"][ok])))),
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
        _reference(ax2, float(np.exp(np.mean(np.log(ac["dz"][good])))),
                   float(np.exp(np.mean(np.log(ac["lc"][good])))), PRED["lc_dz"], 2,
                   "slope −1/2 (paper)")
    ax2.set_xlabel("δz = 4 − z")
    ax2.set_ylabel("l_c  [a0]")
    ax2.set_title(f"l_c ∝ δz^{ac['lc_dz']['exponent']:.2f}±{ac['lc_dz']['err']:.2f}", fontsize=9)
    ax2.legend(fontsize=8)
    fig.suptitle(_across_title(runs, "Fig. 7b: l_c ∝ δz^−1/2 ∝ p^0.18"), fontsize=10)
    return fig


def _pooled(fits: list[dict], key: str):
    """Points (sigma, y, phi) of ``key`` pooled over the runs (one run covers a narrow range
    of sigma; the power laws of Fig. 6 appear across phi)."""
    xs, ys, ph = [], [], []
    for f in fits:
        x, y = f.get(key + "_points", (np.array([]), np.array([])))
        xs.append(np.asarray(x, float))
        ys.append(np.asarray(y, float))
        ph.append(np.full(len(x), f.get("phi", math.nan)))
    if not xs:
        return np.array([]), np.array([]), np.array([])
    return np.concatenate(xs), np.concatenate(ys), np.concatenate(ph)


def pooled_fits(fits: list[dict]) -> dict:
    out = {}
    for key in ("relax_frozen", "delta_gamma", "omega_min"):
        x, y, _ = _pooled(fits, key)
        out[key] = fit_power_law_err(x, y)
        ok = np.isfinite(x) & (x > 0)
        out[key]["sigma_range"] = (float(x[ok].min()), float(x[ok].max())) if ok.any() else (math.nan, math.nan)
    x, y, _ = _pooled(fits, "delta_gamma")
    ok = np.isfinite(x) & np.isfinite(y)
    out["delta_gamma_sigma"] = (float(np.median(x[ok] * y[ok])), float(np.std(x[ok] * y[ok]))) if ok.any() else (math.nan, math.nan)
    return out


def _pooled_fig(runs, fits, key, ylabel, pred, what):
    x, y, ph = _pooled(fits, key)
    ok = np.isfinite(x) & np.isfinite(y) & (x > 0) & (y > 0)
    if ok.sum() < 3 or len({p for p in ph[ok]}) < 2:
        raise Skip(f"needs {key} at analysis instants of 2 or more runs")
    fig = _figure(6.8, 5.2)
    ax = fig.subplots()
    for p in sorted(set(ph[ok])):
        m = ok & (ph == p)
        ax.loglog(x[m], y[m], "o", ms=4, label=f"φ = {p:.3f}")
    f = fit_power_law_err(x, y)
    xs = np.geomspace(x[ok].min(), x[ok].max(), 20)
    if np.isfinite(f["exponent"]):
        ax.plot(xs, f["prefactor"] * xs ** f["exponent"], "-", color="k", lw=2, alpha=0.4,
                label=f"fit: {f['exponent']:.3f} ± {f['err']:.3f}")
    _reference(ax, float(np.exp(np.mean(np.log(x[ok])))), float(np.exp(np.mean(np.log(y[ok])))),
               pred, 10, f"slope {pred:g} (paper)")
    ax.set_xlabel("σ (of the frozen contacts at the instant)")
    ax.set_ylabel(ylabel)
    ax.legend(fontsize=8)
    fig.suptitle(_across_title(runs, what), fontsize=10)
    return fig


def fig6b_relaxation_phi(runs, fits, across):
    return _pooled_fig(runs, fits, "relax_frozen", "−dσ/dγ (frozen contacts along the flow)",
                       PRED["relaxation"], "Fig. 6b: dσ/dγ = −σ²/C")


def fig6c_delta_gamma_phi(runs, fits, across):
    return _pooled_fig(runs, fits, "delta_gamma", "δγ (frozen contacts sheared backwards)",
                       PRED["delta_gamma"], "Fig. 6c: δγ ∝ 1/σ")


def fig6d_omega_min_phi(runs, fits, across):
    return _pooled_fig(runs, fits, "omega_min", "ω_min of the frozen contact network",
                       PRED["omega_min"], "Fig. 6d: ω_min ∝ 1/√σ")


FIGURES = [
    ("fig6a_sigma", {"suspension"}, fig6a_sigma),
    ("fig6b_relaxation", {"suspension"}, fig6b_relaxation),
    ("fig6c_delta_gamma", {"suspension"}, fig6c_delta_gamma),
    ("fig6d_omega_min", {"suspension"}, fig6d_omega_min),
    ("fig6f_forces", {"suspension"}, fig6f_forces),
    ("fig7a_correlation", {"suspension"}, fig7a_correlation),
]
ACROSS_FIGURES = [
    ("fig6b_relaxation_phi", "suspension", fig6b_relaxation_phi),
    ("fig6c_delta_gamma_phi", "suspension", fig6c_delta_gamma_phi),
    ("fig6d_omega_min_phi", "suspension", fig6d_omega_min_phi),
    ("fig6e_sigma_dz", "suspension", fig6e_sigma_dz),
    ("fig7b_lengths", "suspension", fig7b_lengths),
]


def format_suspension_fits(f: dict) -> list[str]:
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
             f"{rel.get('pairs', 0)} (slope {rel.get('slope', math.nan):.3f})",
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
