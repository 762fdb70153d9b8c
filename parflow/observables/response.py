"""Point response of a rod network (paper §III.C, Fig. 8; DESIGN §6).

For a rod beta, N f = |beta> and V = S^T f: the velocities when rod beta alone is made to
extend at unit rate (<V|V> = f_beta = f^T N f).  |V_i| and |f_a| are binned by the
minimum-image distance from the midpoint of beta and averaged over a handful of rods; the V
profile is fitted by A exp(-r/l_c) + B exp(-r/l_r) (l_c: the initial decay, l_r: the slow
tail).  The solves go through the object passed as ``system`` (anything with
``solve_N(rhs, what=...)`` and ``ST(f)``, e.g. dynamics' BondedSystem with its factor of N
loaded): this module itself is numpy/scipy only.
"""
from __future__ import annotations

import numpy as np
from scipy.optimize import curve_fit

from ..geometry import MinImage
from ..state import Bonds


def bond_midpoints(s: np.ndarray, bonds: Bonds) -> np.ndarray:
    """Reduced coordinates of rod midpoints: s_i + (s_j + n - s_i) / 2."""
    return s[bonds.i] + 0.5 * (s[bonds.j] + bonds.shift - s[bonds.i])


def spread_points(k: int, d: int) -> np.ndarray:
    """k points spread over [0, 1)^d (a Kronecker/Fibonacci lattice), deterministic."""
    alpha = np.sqrt(np.array([2.0, 3.0, 5.0, 7.0][:d - 1]))
    first = (np.arange(k) + 0.5) / k
    rest = np.mod(np.outer(np.arange(k) + 0.5, alpha), 1.0)
    return np.column_stack([first, rest])


def pick_rods(s: np.ndarray, h: np.ndarray, bonds: Bonds, k: int) -> np.ndarray:
    """k distinct rods whose midpoints are nearest to k points spread over the cell."""
    mi = MinImage(h)
    mid = mi.reduced(bond_midpoints(s, bonds))
    targets = spread_points(k, s.shape[1])
    out = []
    for t in targets:                           # a handful of rods, vectorised over bonds
        dist = np.einsum("ad,ad->a", *(2 * [mi.vectors(mid - t)]))
        if out:
            dist[np.array(out)] = np.inf
        out.append(int(np.argmin(dist)))
    return np.array(out, dtype=np.int64)


def _distances(mi: MinImage, pts: np.ndarray, centre: np.ndarray) -> np.ndarray:
    v = mi.vectors(pts - centre)
    return np.sqrt(np.einsum("ad,ad->a", v, v))


def point_response(system, s: np.ndarray, h: np.ndarray, bonds: Bonds, rods: np.ndarray,
                   dr: float, rmax: float | None = None) -> dict:
    """Average point response of ``rods``: N f = |beta>, V = S^T f (loaded factor of N).

    Returns dict(r, V_mean, V_rms, f_mean, counts_V, counts_f, VV) with profiles binned
    by minimum-image distance from the rod's midpoint, averaged over rods (all nodes or
    rods in a bin of all rods pooled), and VV the per-rod <V|V> = |V|^2."""
    mi = MinImage(h)
    rmax = mi.rmax if rmax is None else min(rmax, mi.rmax)
    nbins = max(1, int(rmax / dr))         # whole bins within the minimum-image radius
    sr = mi.reduced(s)
    mid = mi.reduced(bond_midpoints(s, bonds))
    nc = len(bonds)
    acc = np.zeros((5, nbins))                 # sum|V|, sum|V|^2, n_V, sum|f|, n_f
    VV, fb = [], []
    for beta in rods:                          # a handful of solves with the loaded factor
        e = np.zeros(nc)
        e[beta] = 1.0
        f = system.solve_N(e, what="point response")
        V = system.ST(f)
        rn = _distances(mi, sr, mid[beta])
        rb = _distances(mi, mid, mid[beta])
        kn = (rn / dr).astype(np.int64)
        kb = (rb / dr).astype(np.int64)
        okn, okb = kn < nbins, kb < nbins
        absV = np.sqrt(np.einsum("id,id->i", V, V))
        acc[0] += np.bincount(kn[okn], absV[okn], nbins)
        acc[1] += np.bincount(kn[okn], absV[okn] ** 2, nbins)
        acc[2] += np.bincount(kn[okn], None, nbins)
        acc[3] += np.bincount(kb[okb], np.abs(f[okb]), nbins)
        acc[4] += np.bincount(kb[okb], None, nbins)
        VV.append(float(np.einsum("id,id->", V, V)))
        fb.append(float(f[beta]))
    with np.errstate(invalid="ignore", divide="ignore"):
        out = dict(r=(np.arange(nbins) + 0.5) * dr, V_mean=acc[0] / acc[2],
                   V_rms=np.sqrt(acc[1] / acc[2]), f_mean=acc[3] / acc[4],
                   counts_V=acc[2], counts_f=acc[4], VV=np.array(VV), f_beta=np.array(fb))
    return out


def fit_two_exponentials(r: np.ndarray, P: np.ndarray, counts: np.ndarray | None = None):
    """Fit log P(r) = log(A e^{-r/l_c} + B e^{-r/l_r}), l_c < l_r, over the bins with data.

    Returns dict(l_c, l_c_err, l_r, l_r_err, A, B, rms) (NaN where the fit fails); the
    errors are one standard deviation from the covariance of the least-squares fit (scaled
    by the residual), i.e. they measure how well two exponentials describe the profile.
    A tail that does not decay within the data (fitted l_r > 10 r_max) gives l_r = inf
    (and a profile that does not decay at all, l_c = l_r = inf)."""
    nan = dict(l_c=np.nan, l_c_err=np.nan, l_r=np.nan, l_r_err=np.nan, A=np.nan, B=np.nan,
               rms=np.nan)
    ok = np.isfinite(P) & (P > 0)
    if counts is not None:
        ok &= counts > 0
    r, y = r[ok], np.log(P[ok])
    if r.size < 6:
        return nan
    # starting values: the initial slope (first third) and the tail slope (last half)
    n3 = max(3, r.size // 3)
    s1 = np.polyfit(r[:n3], y[:n3], 1)[0]
    s2, c2 = np.polyfit(r[r.size // 2:], y[r.size // 2:], 1)
    lc0 = -1.0 / s1 if s1 < 0 else 1.0
    lr0 = -1.0 / s2 if s2 < 0 else 10.0 * (r[-1] - r[0])
    lr0 = max(lr0, 2 * lc0)

    def model(x, la, lc, lb, dl):
        # l_r = l_c + dl > l_c;  amplitudes as logs
        return np.logaddexp(la - x / lc, lb - x / (lc + dl))

    p0 = [y[0] + r[0] / lc0, lc0, c2, lr0 - lc0]
    try:
        popt, pcov = curve_fit(model, r, y, p0=p0, maxfev=20000,
                               bounds=([-np.inf, 1e-3, -np.inf, 1e-6], [np.inf, np.inf, np.inf, np.inf]))
    except (RuntimeError, ValueError):
        return nan
    la, lc, lb, dl = popt
    err = np.sqrt(np.clip(np.diag(pcov), 0, None)) if np.all(np.isfinite(pcov)) else np.full(4, np.nan)
    lr_err = float(np.sqrt(max(pcov[1, 1] + pcov[3, 3] + 2 * pcov[1, 3], 0.0))) \
        if np.all(np.isfinite(pcov)) else np.nan
    rms = float(np.sqrt(np.mean((model(r, *popt) - y) ** 2)))
    l_r = float(lc + dl)
    if lc > 10.0 * r[-1]:
        # no decay at all within the box (a flat profile): neither length is measurable
        return dict(nan, l_c=float("inf"), l_r=float("inf"), rms=rms)
    if l_r > 10.0 * r[-1]:
        # the tail does not decay within the box (l_r beyond the system size): not measurable
        l_r, lr_err = float("inf"), float("nan")
    return dict(l_c=float(lc), l_c_err=float(err[1]), l_r=l_r, l_r_err=lr_err,
                A=float(np.exp(la)), B=float(np.exp(lb)), rms=rms)
