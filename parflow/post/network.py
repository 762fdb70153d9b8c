"""The network's numbers (paper Figs. 3, 4, 5, 8; DESIGN §6; docs/networks.md).

* the reversed branch: -dsigma/dgamma by finite differences of the recorded series
  (:func:`reverse_branch`) and its fit over sigma in :data:`REVERSE_SIGMA`
  (:func:`fit_reverse_branch`: exponent a, pred. 2, and C of -dsigma/dgamma = sigma^2/C);
* omega_min ~ sigma^x on each branch and C2 = median of omega_min sqrt(sigma) over
  sigma >= :data:`C2_SIGMA_MIN` (:func:`omega_min_fit`);
* the gap omega* of D(omega) (:func:`fit_omega_star`, per instant and per run);
* the point response: the stored two-exponential fits, l_r against sigma;
* across runs, power laws in dz with error bars (:func:`across_fits`).
"""
from __future__ import annotations

import math

import numpy as np

from .fits import fit_power_law, fit_power_law_err, reverse_rows

REVERSE_SIGMA = (1e3, 1e5)        # sigma window of the reversed-branch fit (docs/networks.md)
C2_SIGMA_MIN = 1e3                # C2 = median of omega_min sqrt(sigma) over sigma >= this
OMEGA_STAR_FRACTION = 0.5         # omega* from the integrated D(omega): see fit_omega_star
OMEGA_STAR_PLATEAU = (0.2, 0.4)   # omega window where D(omega) is the plateau level D_p
OMEGA_STAR_BOOT = 200             # bootstrap resamples of the modes (error of omega*)
RESOLVED_FRACTION = 0.5           # l_r counts as measured if below this fraction of r_max


def reverse_branch(strain: np.ndarray, sigma: np.ndarray) -> dict:
    """dsigma/dgamma along a reversed branch by finite differences of the recorded series.

    ``strain``: accumulated |gamma| (the run's ``strain`` column) on the branch, ``sigma``
    the stress.  Between consecutive records k, k+1 (x = strain since the reversal):
        dsigma/dx = (sigma_{k+1} - sigma_k) / (x_{k+1} - x_k)  at sigma_mid = sqrt(sigma_k sigma_{k+1}),
        C_k = -sigma_k sigma_{k+1} (x_{k+1} - x_k) / (sigma_{k+1} - sigma_k) = dx / d(1/sigma),
    so that dsigma/dx = -sigma^2 / C means C_k = C for every k (exactly, for that law)."""
    x = np.asarray(strain, float) - float(strain[0])
    s = np.asarray(sigma, float)
    dx, ds = np.diff(x), np.diff(s)
    ok = dx > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        dsdx = ds[ok] / dx[ok]
        C = -s[:-1][ok] * s[1:][ok] * dx[ok] / ds[ok]
    return dict(x=0.5 * (x[:-1] + x[1:])[ok], sigma=np.sqrt(s[:-1] * s[1:])[ok], dsdg=dsdx, C=C)


def fit_reverse_branch(strain: np.ndarray, sigma: np.ndarray, lo: float, hi: float) -> dict:
    """Over the records of a reversed branch with lo <= sigma <= hi: the exponent of
    -dsigma/dgamma ~ sigma^a (least squares of logs, finite differences; expect a = 2) and
    C from 1/sigma = 1/sigma_0 + x / C (linear least squares), with 1-sigma errors; also the
    median and 16-84 % range of the local C_k."""
    br = reverse_branch(strain, sigma)
    m = (br["sigma"] >= lo) & (br["sigma"] <= hi) & (br["dsdg"] < 0)
    out = dict(n=int(m.sum()), slope=np.nan, slope_err=np.nan, C=np.nan, C_err=np.nan,
               C_median=np.nan, C_p16=np.nan, C_p84=np.nan)
    if m.sum() < 4:
        return out
    X, Y = np.log(br["sigma"][m]), np.log(-br["dsdg"][m])
    p, cov = np.polyfit(X, Y, 1, cov=True)
    out.update(slope=float(p[0]), slope_err=float(np.sqrt(cov[0, 0])))
    x = np.asarray(strain, float) - float(strain[0])
    s = np.asarray(sigma, float)
    w = (s >= lo) & (s <= hi)
    q, cq = np.polyfit(x[w], 1.0 / s[w], 1, cov=True)
    out.update(C=float(1.0 / q[0]), C_err=float(np.sqrt(cq[0, 0]) / q[0] ** 2))
    Ck = br["C"][m]
    out.update(C_median=float(np.median(Ck)), C_p16=float(np.percentile(Ck, 16)),
               C_p84=float(np.percentile(Ck, 84)))
    return out


def _omega_star_once(w: np.ndarray, nc: int, fraction: float, plateau) -> tuple:
    """omega* of one sorted spectrum (see fit_omega_star): (omega*, D_p, omega_c)."""
    a, b = plateau
    n_pl = np.searchsorted(w, b, "left") - np.searchsorted(w, a, "left")
    Dp = n_pl / (nc * (b - a))
    if not Dp > 0:
        return float("nan"), float(Dp), float("nan")
    j = np.arange(w.size)                       # modes below w[j] (ties do not matter)
    line = fraction * Dp * w
    # the crossing must be reached before the top of the plateau window
    if np.searchsorted(w, b, "left") / nc < fraction * Dp * b:
        return float("nan"), float(Dp), float("nan")
    below = np.nonzero((j / nc < line) & (w < b))[0]
    if below.size == 0:
        return float("nan"), float(Dp), float("nan")
    wc = float(w[below[-1]])
    return (1.0 - fraction) * wc, float(Dp), wc


def fit_omega_star(omega, fraction: float = OMEGA_STAR_FRACTION,
                   plateau: tuple = OMEGA_STAR_PLATEAU, n_boot: int = OMEGA_STAR_BOOT,
                   seed: int = 0) -> dict:
    """The gap omega* of the spectrum {omega_k} of N (all Nc of them: the ``omega`` dataset).

    Definition.  D_p is the plateau level of D(omega) (normalised to 1 over the Nc modes):
    the fraction of modes in the window ``plateau`` divided by its width.  F(omega) is the
    fraction of modes below omega (the integrated D).  omega_c is the largest omega at which
    the integrated D is still below ``fraction`` times the integral of the plateau,
    F(omega) < fraction * D_p * omega, and

        omega* = (1 - fraction) * omega_c.

    Why this one: for a sharp gap (D = 0 below omega_g, D_p above) F = D_p (omega - omega_g)
    and omega* = omega_g exactly, for any fraction; for any D(omega) = D_p g(omega/omega_g)
    omega* is proportional to omega_g, so the exponent of omega* against dz does not depend
    on the choice (a fixed fraction of *all* modes, or D = D_p/2 on fixed-width bins, would
    add a dz-independent offset or resolution).  It counts modes instead of binning them
    (about fraction * D_p * omega_c * Nc modes lie below omega_c: ~50 at dz = 0.1, Nc ~ 8000),
    and a few modes inside the gap (the soft mode near jamming) move it by a few % only.
    The plateau window must lie above the gap and below the rise of D(omega) towards its
    maximum (omega ~ 2): (0.2, 0.4) for the 2D networks here, which puts the crossing
    below 0.4, i.e. omega* < 0.2 (NaN otherwise).

    Error: standard deviation over ``n_boot`` bootstrap resamples of the modes (fixed seed:
    reproducible).  It treats the modes as independent draws, which overstates the noise
    of a spectrum (eigenvalues repel): an upper bound.

    Returns dict(omega_star, err, D_plateau, omega_c, fraction, plateau, n_modes)."""
    w = np.asarray(omega, float)
    w = np.sort(w[np.isfinite(w)])
    nc = w.size
    out = dict(omega_star=np.nan, err=np.nan, D_plateau=np.nan, omega_c=np.nan,
               fraction=float(fraction), plateau=tuple(plateau), n_modes=int(nc))
    if nc < 10 or not 0 < fraction < 1:
        return out
    ws, Dp, wc = _omega_star_once(w, nc, fraction, plateau)
    out.update(omega_star=ws, D_plateau=Dp, omega_c=wc)
    if np.isfinite(ws) and n_boot > 1:
        rng = np.random.default_rng(seed)
        boot = np.array([_omega_star_once(np.sort(w[rng.integers(0, nc, nc)]), nc, fraction,
                                          plateau)[0] for _ in range(n_boot)])
        boot = boot[np.isfinite(boot)]
        if boot.size > 1:
            out["err"] = float(np.std(boot, ddof=1))
    return out


def network_dz(run) -> float:
    """dz = 2d - z (model attribute, else from the scene's z)."""
    dz = run.model_attrs.get("dz")
    if dz is not None and np.isfinite(dz):
        return float(dz)
    z = run.model_attrs.get("z", run.param("z"))
    d = int(run.param("d", 2) or 2)
    return 2.0 * d - float(z) if z is not None else float("nan")


def network_z(run) -> float:
    """z of the network (model attribute, else the scene's target)."""
    z = run.model_attrs.get("z", run.param("z"))
    return float(z) if z is not None else float("nan")


def network_seed(run):
    """The run's seed (the scene's, else the network's)."""
    return run.scene.get("seed", run.model_attrs.get("network_seed"))


def network_reverse_fit(run, window: tuple = REVERSE_SIGMA) -> dict | None:
    """dsigma/dgamma on the first reversed branch (:func:`reverse_branch`) and the fit of
    :func:`fit_reverse_branch` over ``window`` of sigma; None without a reversed branch."""
    rv = reverse_rows(run)
    if rv is None or "sigma" not in run.ts or "strain" not in run.ts:
        return None
    rows, _ = rv
    strain, sigma = run.ts["strain"][rows], run.ts["sigma"][rows]
    if strain.size < 3:
        return None
    out = fit_reverse_branch(strain, sigma, *window)
    out["window"] = tuple(window)
    out["branch"] = reverse_branch(strain, sigma)
    return out


def omega_min_fit(run, sigma_min: float = C2_SIGMA_MIN) -> dict | None:
    """omega_min ~ sigma^x on each branch and C2 = omega_min sqrt(sigma) (median and
    16-84 %) over the records with sigma >= sigma_min; None without omega_min."""
    ts = run.ts
    if "omega_min" not in ts or "sigma" not in ts:
        return None
    w, s = np.asarray(ts["omega_min"], float), np.asarray(ts["sigma"], float)
    d = ts["direction"] if "direction" in ts else np.ones(w.size, int)
    ok = np.isfinite(w) & np.isfinite(s) & (w > 0) & (s > 0)
    if not ok.any():
        return None
    out = dict(sigma_min=sigma_min)
    for sgn, name in ((1, "forward"), (-1, "reverse")):
        m = ok & (d == sgn) & (s >= sigma_min)
        out[name] = fit_power_law(s[m], w[m]) + (int(m.sum()),)
    m = ok & (s >= sigma_min)
    c2 = w[m] * np.sqrt(s[m])
    if c2.size:
        out.update(C2=float(np.median(c2)), C2_p16=float(np.percentile(c2, 16)),
                   C2_p84=float(np.percentile(c2, 84)), n=int(c2.size))
    else:
        out.update(C2=np.nan, C2_p16=np.nan, C2_p84=np.nan, n=0)
    return out


def spectrum_instants(run) -> list[dict]:
    """Analysis instants holding the full spectrum (``omega``) or a binned D(omega)."""
    return [a for a in run.analysis if "omega" in a or ("dos" in a and "dos_edges" in a)]


def omega_star_fits(run) -> dict | None:
    """fit_omega_star at every instant with the full spectrum, and the run's value: the mean
    over the instants, with error sqrt(mean(err^2) + std^2) (the instants share the network,
    so their errors are not divided by sqrt(n); the spread with strain is added)."""
    inst = [a for a in run.analysis if "omega" in a]
    if not inst:
        return None
    per = []
    for a in inst:
        f = fit_omega_star(a["omega"])
        f.update(sigma=float(a.get("sigma", np.nan)), gamma=float(a.get("gamma", np.nan)),
                 direction=int(a.get("direction", 1)), step=int(a.get("step", -1)))
        per.append(f)
    v = np.array([p["omega_star"] for p in per])
    e = np.array([p["err"] for p in per])
    ok = np.isfinite(v)
    out = dict(instants=per, omega_star=np.nan, err=np.nan, n=int(ok.sum()))
    if ok.any():
        spread = float(np.std(v[ok], ddof=1)) if ok.sum() > 1 else 0.0
        e2 = float(np.nanmean(e[ok] ** 2)) if np.isfinite(e[ok]).any() else 0.0
        out.update(omega_star=float(np.mean(v[ok])), err=math.sqrt(e2 + spread ** 2),
                   spread=spread)
    return out


def response_instants(run) -> list[dict]:
    """Analysis instants holding a point-response profile."""
    return [a for a in run.analysis if "resp_V" in a and "resp_r" in a]


def response_fits(run) -> dict | None:
    """Per analysis instant: the stored two-exponential fit of the V profile (l_c, l_r, A,
    B), whether l_r is resolved (finite and below RESOLVED_FRACTION of the largest r of the
    profile: the tail decays by at least e^2 within it), and the
    collapse variables l_r/sqrt(sigma) and B sqrt(sigma) (constant if V(r) sqrt(sigma) is a
    function of r/sqrt(sigma) in the tail); the exponent of l_r against sigma over the
    resolved instants."""
    inst = response_instants(run)
    if not inst:
        return None
    rows = []
    for a in inst:
        r = np.asarray(a["resp_r"], float)
        rmax = float(r[-1] + (r[1] - r[0]) / 2) if r.size > 1 else float("nan")
        s = float(a.get("sigma", np.nan))
        lc, lr = float(a.get("resp_l_c", np.nan)), float(a.get("resp_l_r", np.nan))
        B = float(a.get("resp_B", np.nan))
        res = bool(np.isfinite(lr) and lr < RESOLVED_FRACTION * rmax)
        rows.append(dict(sigma=s, direction=int(a.get("direction", 1)), l_c=lc, l_r=lr,
                         A=float(a.get("resp_A", np.nan)), B=B, rmax=rmax, resolved=res,
                         lr_over_sqrt_sigma=lr / math.sqrt(s) if res and s > 0 else np.nan,
                         B_sqrt_sigma=B * math.sqrt(s) if res and s > 0 else np.nan,
                         VV=float(a.get("VV", np.nan))))
    res = [x for x in rows if x["resolved"]]
    fit = fit_power_law_err([x["sigma"] for x in res], [x["l_r"] for x in res])
    return dict(instants=rows, l_r_vs_sigma=fit)


def network_fits(run) -> dict:
    """Every network number the figures show (keys absent when their data are)."""
    out: dict = dict(model="network", z=network_z(run), dz=network_dz(run), seed=network_seed(run),
                     N=run.param("N"), path=run.path)
    rv = network_reverse_fit(run)
    if rv is not None:
        out["reverse"] = rv
    om = omega_min_fit(run)
    if om is not None:
        out["omega_min"] = om
    ost = omega_star_fits(run)
    if ost is not None:
        out["omega_star"] = ost
    rf = response_fits(run)
    if rf is not None:
        out["response"] = rf
    return out


def across_fits(fits: list[dict]) -> dict:
    """Power laws across runs (one value per run): C(dz) of the reversed branch (pred.
    exponent -1/2), C2(dz) (pred. 1/2), omega*(dz) (pred. 1), by fit_power_law_err.

    C and C2 are fitted unweighted (their error is the scatter between networks: the fit
    error of C and the 16-84 % range of C2 are far smaller than the seed-to-seed scatter, so
    as weights they would let a few runs decide); omega* is weighted by its error (bootstrap
    over the modes and spread over the run's spectra: see omega_star_fits)."""
    def collect(get):
        dz, y, e = [], [], []
        for f in fits:
            v = get(f)
            if v is not None and np.isfinite(v[0]):
                dz.append(f["dz"]), y.append(v[0]), e.append(v[1])
        return np.array(dz), np.array(y), np.array(e, float)

    out = {}
    spec = dict(
        C=(lambda f: (f["reverse"]["C"], f["reverse"]["C_err"]) if "reverse" in f else None,
           -0.5, False),
        C2=(lambda f: (f["omega_min"]["C2"], (f["omega_min"]["C2_p84"]
                                              - f["omega_min"]["C2_p16"]) / 2)
            if "omega_min" in f else None, 0.5, False),
        omega_star=(lambda f: (f["omega_star"]["omega_star"], f["omega_star"]["err"])
                    if "omega_star" in f else None, 1.0, True))
    for key, (get, pred, weighted) in spec.items():
        dz, y, e = collect(get)
        if np.unique(dz).size < 2:
            continue
        e = np.where(np.isfinite(e) & (e > 0), e, np.nan)
        use = weighted and np.isfinite(e).all()
        fit = fit_power_law_err(dz, y, e if use else None)
        out[key] = dict(dz=dz, value=y, err=e, fit=fit, predicted=pred, weighted=bool(use))
    return out
