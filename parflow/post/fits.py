"""Fits shared by every model: log-binning, power laws (with and without error bars), the
divergence point of a power law, the fit window near a divergence, and the branches of a
run (forward and reversed rows).

Power laws are fitted by least squares in log-log after log-binning (:data:`BINS_PER_DECADE`
bins a decade, so that the crowded points near a divergence do not dominate), over the last
:data:`FIT_DECADES` decades of gamma_c - gamma above :data:`DGAMMA_GUARD` times the typical
|dgamma| near the end of the branch.

A *run* here is what ``parflow.plot.load_run`` returns: ``run.ts`` (timeseries name -> 1-D
array), ``run.analysis`` (one dict per analysis instant, tagged with its ``direction``,
``leg`` and ``row``), ``run.model_attrs``, ``run.scene`` and ``run.param(name)``.  Only numpy
is used.
"""
from __future__ import annotations

import math

import numpy as np

FIT_DECADES = 2.0                 # power-law fits use the last 2 decades of gamma_c - gamma
DGAMMA_GUARD = 10.0               # ... and only points with gamma_c - gamma > 10 typical |dgamma|
DIVERGENCE_DECADES = 2.0          # gamma_c fit: the top 2 decades of <V^2> on the branch
BINS_PER_DECADE = 8               # log-binning before power-law fits (even weight per decade)


def log_bin(x, y, per_decade: int = BINS_PER_DECADE):
    """Geometric means of x and y in logarithmic bins of x (positive finite points only).
    Gives each decade of x the same weight in a least-squares fit, however the points are
    spaced (adaptive steps crowd the points near a divergence)."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    ok = np.isfinite(x) & np.isfinite(y) & (x > 0) & (y > 0)
    lx, ly = np.log10(x[ok]), np.log10(y[ok])
    if lx.size == 0:
        return np.array([]), np.array([])
    k = np.floor(lx * per_decade).astype(np.int64)
    keys, inv = np.unique(k, return_inverse=True)
    cnt = np.bincount(inv)
    bx = np.bincount(inv, lx) / cnt
    by = np.bincount(inv, ly) / cnt
    return 10.0 ** bx, 10.0 ** by


def fit_power_law(x, y, xmin: float | None = None, xmax: float | None = None,
                  per_decade: int | None = None) -> tuple[float, float]:
    """Least-squares fit of y = prefactor * x**exponent in log-log, over the positive finite
    points with xmin <= x <= xmax.  With ``per_decade`` the points are first log-binned
    (:func:`log_bin`).  Returns (exponent, prefactor); (nan, nan) with fewer than 3 points
    or less than 0.1 decade of x."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    ok = np.isfinite(x) & np.isfinite(y) & (x > 0) & (y > 0)
    if xmin is not None:
        ok &= x >= xmin
    if xmax is not None:
        ok &= x <= xmax
    x, y = x[ok], y[ok]
    if per_decade:
        x, y = log_bin(x, y, per_decade)
    if x.size < 3 or np.log10(x.max() / x.min()) < 0.1:
        return float("nan"), float("nan")
    slope, icept = np.polyfit(np.log(x), np.log(y), 1)
    return float(slope), float(np.exp(icept))


def fit_power_law_err(x, y, yerr=None) -> dict:
    """Least squares of log y = log A + p log x over the positive finite points, weighted by
    (y / yerr)^2 when ``yerr`` is given.

    Returns dict(exponent, err, prefactor, chi2, dof, n).  ``err`` is one standard deviation
    from the covariance of the fit; with error bars it is multiplied by sqrt(chi2/dof) when
    that exceeds 1 (the points scatter more than their error bars say), without them it is
    the usual residual-based error.  NaN with fewer than 2 points (err: fewer than 3 without
    error bars)."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    e = np.full(x.shape, np.nan) if yerr is None else np.asarray(yerr, float)
    ok = np.isfinite(x) & np.isfinite(y) & (x > 0) & (y > 0)
    if yerr is not None:
        ok &= np.isfinite(e) & (e > 0)
    out = dict(exponent=np.nan, err=np.nan, prefactor=np.nan, chi2=np.nan, dof=0,
               n=int(ok.sum()))
    if ok.sum() < 2 or np.ptp(np.log(x[ok])) == 0:
        return out
    X, Y = np.log(x[ok]), np.log(y[ok])
    w = (y[ok] / e[ok]) ** 2 if yerr is not None else np.ones(X.size)
    A = np.column_stack([np.ones_like(X), X])
    M = A.T @ (w[:, None] * A)
    cov = np.linalg.inv(M)
    c0, p = cov @ (A.T @ (w * Y))
    res = Y - (c0 + p * X)
    chi2 = float(np.sum(w * res ** 2))
    dof = X.size - 2
    if yerr is None:
        err = math.sqrt(chi2 / dof * cov[1, 1]) if dof > 0 else float("nan")
    else:
        err = math.sqrt(cov[1, 1] * max(1.0, chi2 / dof if dof > 0 else 1.0))
    out.update(exponent=float(p), err=float(err), prefactor=float(np.exp(c0)), chi2=chi2,
               dof=int(dof))
    return out


def fit_divergence_point(gamma, y, exponent: float, decades: float = DIVERGENCE_DECADES,
                         skip: float = 0.0) -> float:
    """Where y ~ |gamma_c - gamma|**exponent (exponent < 0) diverges: y**(1/exponent) is then
    linear in gamma and vanishes at gamma_c.  Fitted over the points whose y lies between
    10**-(skip + decades) and 10**-skip times the largest y.  Returns nan if it cannot be
    fitted."""
    gamma, y = np.asarray(gamma, float), np.asarray(y, float)
    ok = np.isfinite(gamma) & np.isfinite(y) & (y > 0)
    if ok.sum() < 3 or not exponent < 0:
        return float("nan")
    g, y = gamma[ok], y[ok]
    top = y.max()
    sel = (y >= top * 10.0 ** (-(skip + decades))) & (y <= top * 10.0 ** (-skip))
    if sel.sum() < 3 or np.ptp(g[sel]) == 0:
        return float("nan")
    a, b = np.polyfit(g[sel], y[sel] ** (1.0 / exponent), 1)
    return float(-b / a) if a != 0 else float("nan")


def fit_window(x, dgamma_typical: float = 0.0, decades: float = FIT_DECADES):
    """(xmin, xmax): the last ``decades`` decades of x > 0 above DGAMMA_GUARD * dgamma
    (fewer if the data span fewer)."""
    x = np.asarray(x, float)
    ok = np.isfinite(x) & (x > 0) & (x >= DGAMMA_GUARD * dgamma_typical)
    if not ok.any():
        return float("nan"), float("nan")
    lo = float(x[ok].min())
    return lo, min(lo * 10.0 ** decades, float(x[ok].max()))


def segments(direction) -> list[tuple[int, int, int]]:
    """Contiguous runs of equal direction: (start, stop, direction), rows [start, stop)."""
    d = np.asarray(direction)
    if d.size == 0:
        return []
    cut = np.nonzero(np.diff(d) != 0)[0] + 1
    starts = np.r_[0, cut]
    stops = np.r_[cut, d.size]
    return [(int(a), int(b), int(d[a])) for a, b in zip(starts, stops)]


def forward_rows(run) -> slice | None:
    """The first forward branch (first contiguous rows with direction +1)."""
    for a, b, d in segments(run.ts.get("direction", np.ones(len(run.ts.get("step", [])), int))):
        if d > 0:
            return slice(a, b)
    return None


def reverse_rows(run) -> tuple[slice, float] | None:
    """The first reverse branch (direction -1) and the turning strain gamma_turn (the last
    gamma before it; its own first gamma if the run starts in reverse)."""
    if "direction" not in run.ts:
        return None
    for a, b, d in segments(run.ts["direction"]):
        if d < 0:
            g = run.ts["gamma"]
            return slice(a, b), float(g[a - 1] if a > 0 else g[a])
    return None


def forward_instants(run) -> list[dict]:
    """The analysis instants on the first forward branch (with a finite gamma)."""
    fw = forward_rows(run)
    if fw is None:
        return []
    return [a for a in run.analysis if "row" in a and fw.start <= a["row"] < fw.stop
            and np.isfinite(a.get("gamma", np.nan))]


def typical_dgamma(dg, tail: float = 0.1) -> float:
    """Median |dgamma| over the last ``tail`` fraction (at least 5) of the steps of a branch:
    the step size where the branch approaches its divergence."""
    dg = np.abs(np.asarray(dg, float))
    dg = dg[np.isfinite(dg) & (dg > 0)]
    if not dg.size:
        return 0.0
    k = max(5, int(math.ceil(tail * dg.size)))
    return float(np.median(dg[-k:]))
