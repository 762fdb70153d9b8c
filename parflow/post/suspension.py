"""The suspension's numbers (paper Figs. 6-7; docs/suspensions.md).

Statistics use the rows and analysis instants past ``observables.analysis_from_strain`` of
the scene (the transient), or the last half of the run if the scene has none.  One run:
strain-weighted averages of sigma, p, mu and z with block errors, and the power laws of
Figs. 6b-d over its analysis instants (:func:`suspension_fits`).  Several runs: the same
power laws with the instants of all runs pooled (:func:`pooled_fits`: one run spans a
narrow range of sigma), sigma(dz), l_c(p), l_c(dz) and sigma = A (phi_c - phi)^(-beta)
(:func:`across_suspension`, :func:`fit_phi_c`).
"""
from __future__ import annotations

import math

import numpy as np

from .fits import fit_power_law_err

PRED = dict(relaxation=2.0, delta_gamma=-1.0, omega_min=-0.5, sigma_dz=-2.7, lc_p=0.18,
            lc_dz=-0.5)


def _from_strain(run) -> float:
    x = run.scene.get("observables", {}).get("analysis_from_strain")
    strain = run.ts.get("strain")
    if x:
        return float(x)
    return 0.5 * float(strain[-1]) if strain is not None and len(strain) else 0.0


def forward_steps(ts) -> np.ndarray:
    """Boolean mask of the rows of the time series ``ts`` that are forward steps (step > 0,
    direction > 0 where those columns exist)."""
    m = np.ones(len(ts["strain"]), bool)
    if "step" in ts:
        m &= np.asarray(ts["step"]) > 0
    if "direction" in ts:
        m &= np.asarray(ts["direction"]) > 0
    return m


def window_rows(run) -> np.ndarray:
    """Boolean mask of the rows in the statistics window (forward steps past the transient)."""
    return (np.asarray(run.ts["strain"]) >= _from_strain(run)) & forward_steps(run.ts)


def window_instants(run) -> list[dict]:
    """The analysis instants in the statistics window."""
    x0 = _from_strain(run)
    return [a for a in run.analysis if float(a.get("strain", a.get("gamma", 0.0))) >= x0 - 1e-12]


def _mean_err(x: np.ndarray, w: np.ndarray | None = None,
              blocks: int = 10) -> tuple[float, float]:
    """Mean and its error from block averages (the series is correlated).

    With weights ``w`` (the strain of each step) the mean is weighted and the blocks hold
    equal strain, each block's own weighted mean: the per-step value of a suspension is the
    dissipation of its step, whose size varies 100-fold near jamming (steps cut after an
    infeasible LCP, a few long ones between), so blocks of equal step count would weigh the
    stretches of tiny steps around a stress peak like the rest (:func:`strain_window_means`
    over the window's own strain)."""
    x = np.asarray(x, float)
    ok = np.isfinite(x)
    if w is not None:
        w = np.abs(np.asarray(w, float))
        ok &= np.isfinite(w) & (w > 0)
        w = w[ok]
    x = x[ok]
    if x.size == 0:
        return math.nan, math.nan
    if w is None:
        w = np.ones_like(x)
    mean = float(np.sum(w * x) / np.sum(w))
    if blocks < 2:
        return mean, math.nan
    if x.size < 2 * blocks:
        return mean, float(x.std() / math.sqrt(max(x.size - 1, 1)))
    _, b = strain_window_means(np.cumsum(w), w, x, blocks)
    if b.size < blocks:                  # one step longer than a block: too few to block
        return mean, float(x.std() / math.sqrt(max(x.size - 1, 1)))
    return mean, float(b.std(ddof=1) / math.sqrt(blocks))


def _strain_weighted(x, w):
    """Mean of x weighted by |w| (the strain of each step)."""
    return _mean_err(x, w, blocks=0)[0]


def strain_window_means(strain: np.ndarray, dgamma: np.ndarray, y: np.ndarray,
                        windows: int) -> tuple[np.ndarray, np.ndarray]:
    """y averaged over ``windows`` windows of equal strain, each step weighted by its strain
    (``strain``: the accumulated strain at the end of each step): (window centres, means),
    windows without a step left out.  A suspension's per-step sigma is the dissipation of
    its step and depends on the step's size (a step cut to a tenth after an infeasible LCP
    can sit 10-100x below its neighbours); the window means do not."""
    x = np.asarray(strain, float)
    w = np.abs(np.asarray(dgamma, float))
    y = np.asarray(y, float)
    ok = np.isfinite(x) & np.isfinite(w) & np.isfinite(y) & (w > 0)
    x, w, y = x[ok], w[ok], y[ok]
    if x.size == 0 or windows < 1:
        return np.zeros(0), np.zeros(0)
    lo, hi = float((x - w).min()), float(x.max())
    if not hi > lo:
        return np.array([hi]), np.array([float(np.sum(w * y) / np.sum(w))])
    k = np.minimum(((x - 0.5 * w - lo) / (hi - lo) * windows).astype(np.int64), windows - 1)
    ws = np.bincount(k, weights=w, minlength=windows)
    wy = np.bincount(k, weights=w * y, minlength=windows)
    has = ws > 0
    centres = lo + (np.arange(windows) + 0.5) * (hi - lo) / windows
    return centres[has], wy[has] / ws[has]


def relaxation(gamma: np.ndarray, dgamma: np.ndarray, sigma: np.ndarray,
               n_coll: np.ndarray, max_ratio: float = 2.0) -> dict:
    """dsigma/dgamma between collisions, against sigma (paper: dsigma/dgamma = -sigma^2/C).

    Inputs are per-step series (StepStats.gamma is the strain at the *end* of a step; sigma
    was evaluated at its start, gamma - dgamma).  Uses pairs of consecutive steps that are
    both collision-free; the difference quotient is set against the geometric mean of the
    two sigmas, which makes it exact for sigma = 1/(1/sigma_0 + gamma/C).

    Pairs whose step sizes differ by more than ``max_ratio`` are left out: a step's sigma
    depends on its size (the gaps that the previous step left open weigh h/dgamma in its
    LCP), so the step cut to a tenth after an infeasible LCP changes sigma without any
    relaxation -- and near jamming such cut steps are most of the collision-free ones (at
    phi = 0.84, N = 4096: 229 of 247 pairs in the last half of one run straddle a jump
    of more than 2x).  Returns the
    number of pairs used, of pairs left out for a step-size jump (``step_jumps``), the
    fraction with decreasing sigma, the slope of log(-dsigma/dgamma) against log sigma over
    the decreasing ones (2 expected), C = median sigma^2/(-dsigma/dgamma) and those
    ``points`` (sigma, -dsigma/dgamma).
    """
    dg = np.abs(np.asarray(dgamma, float))
    g0 = np.asarray(gamma, float) - np.asarray(dgamma, float)
    s = np.asarray(sigma, float)
    nc = np.asarray(n_coll)
    free = (nc[:-1] == 0) & (nc[1:] == 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = dg[1:] / dg[:-1]
    steady = (ratio <= max_ratio) & (ratio >= 1.0 / max_ratio)
    ok = free & steady
    dsdg = np.diff(s) / np.diff(g0)
    smid = np.sqrt(s[:-1] * s[1:])
    dec = ok & (dsdg < 0)
    out = dict(pairs=int(ok.sum()), step_jumps=int((free & ~steady).sum()),
               decreasing=float(dec.sum() / ok.sum()) if ok.any() else math.nan,
               slope=math.nan, C=math.nan)
    out["points"] = (smid[dec], -dsdg[dec])
    if dec.sum() >= 3:
        out["slope"] = float(np.polyfit(np.log(smid[dec]), np.log(-dsdg[dec]), 1)[0])
        out["C"] = float(np.median(smid[dec] ** 2 / -dsdg[dec]))
    return out


def suspension_fits(run, relaxation=relaxation) -> dict:
    """Averages over the statistics window and the power laws of Figs. 6-7 for one run.

    ``relaxation(gamma, dgamma, sigma, n_coll) -> dict``: the fit of dsigma/dgamma over
    pairs of collision-free steps (:func:`relaxation` unless another is given), applied to
    the rows of the window and stored as ``"relaxation"``; left out when None."""
    ts = run.ts
    if "sigma" not in ts or "strain" not in ts:
        return dict(model="suspension")
    m = window_rows(run)
    out = dict(model="suspension", phi=float(run.model_attrs.get("phi", run.param("phi", math.nan))),
               N=int(run.param("N", 0) or 0), rows=int(m.sum()),
               strain_window=(float(np.min(ts["strain"][m])) if m.any() else math.nan,
                              float(np.max(ts["strain"][m])) if m.any() else math.nan))
    dg = ts.get("dgamma", np.ones_like(ts["sigma"]))
    if "phi" in ts and m.any():
        # a run compressed while it flowed: its statistics belong to the window's phi (the
        # strain-weighted mean if the window still holds part of the compression, which
        # phi_range then shows: set observables.analysis_from_strain past it)
        ph = np.asarray(ts["phi"], float)[m]
        out["phi"] = float(ph[-1]) if ph.min() == ph.max() else _strain_weighted(ph, dg[m])
        out["phi_range"] = (float(ph.min()), float(ph.max()))
    for q in ("sigma", "pressure", "mu", "z", "z_all", "z2"):
        if q in ts and m.any():
            out[q] = _mean_err(ts[q][m], dg[m])
    if m.any() and "collisions" in ts:
        st = ts["strain"][m]
        span = float(st.max() - st.min())
        dc = float(ts["collisions"][m][-1] - ts["collisions"][m][0])
        out["collisions_per_strain"] = dc / span if span > 0 else math.nan
    if relaxation is not None and m.sum() > 4 and "n_coll" in ts:
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


def pooled_points(fits: list[dict], key: str):
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
    """Power laws of Figs. 6b-d over the analysis instants of all runs, and delta_gamma
    sigma (median, spread)."""
    out = {}
    for key in ("relax_frozen", "delta_gamma", "omega_min"):
        x, y, _ = pooled_points(fits, key)
        out[key] = fit_power_law_err(x, y)
        ok = np.isfinite(x) & (x > 0)
        out[key]["sigma_range"] = (float(x[ok].min()), float(x[ok].max())) if ok.any() else (math.nan, math.nan)
    x, y, _ = pooled_points(fits, "delta_gamma")
    ok = np.isfinite(x) & np.isfinite(y)
    out["delta_gamma_sigma"] = (float(np.median(x[ok] * y[ok])), float(np.std(x[ok] * y[ok]))) if ok.any() else (math.nan, math.nan)
    return out


def suspension_across(fits: list[dict]) -> dict:
    """Everything across several suspension runs: :func:`pooled_fits` and
    :func:`across_suspension` in one dict (model "suspension")."""
    out = pooled_fits(fits)
    out.update(across_suspension(fits))
    out["model"] = "suspension"
    return out
