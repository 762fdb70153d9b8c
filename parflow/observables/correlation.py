"""Velocity correlations C(r) = <V_i . V_j> / <V^2> (paper Figs. 8, 7a; DESIGN §6).

Pairs are binned by minimum-image distance up to r_max: exactly, in row blocks (memory
O(block), time O(N^2)), or by FFT on a grid (time O(N log N); bins below CORR_R_EXACT exact,
the others to the grid resolution); ``method = "auto"`` picks the FFT above CORR_EXACT_MAX
particles.  Distances: reduced displacements in the remapped cell (parflow.geometry) minus
rint, times h_r -- for r up to half the smallest cell height, the true minimum image.
numpy/scipy only; any dimension.
"""
from __future__ import annotations

import itertools
import math

import numpy as np
from scipy import fft
from scipy.fft import next_fast_len
from scipy.spatial import cKDTree

from ..errors import InputError
from ..geometry import MinImage, remapped_cell

CORR_METHODS = ("auto", "exact", "fft")
CORR_EXACT_MAX = 10_000    # nodes: above, corr_method = "auto" uses the FFT
CORR_R_EXACT = 3.0         # a0: C(r) bins below it are exact in the FFT method (contact shells)
CORR_GRID_MAX = 2 ** 24    # points of the FFT grid of C(r), about at most (134 MB a grid)
EMPTY_BIN = 1e-6           # C(r) is NaN in bins holding fewer pairs (CIC counts are fractional)


def min_image_r2(hr: np.ndarray, dsr: list) -> np.ndarray:
    """|h_r (ds - rint(ds))|^2 from the reduced displacements ds (one array per direction,
    modified in place).  The one formula for pair distances of C(r): the exact and the FFT
    method bin a pair identically."""
    d = len(dsr)
    for c in range(d):
        dsr[c] -= np.rint(dsr[c])
    r2 = np.zeros(np.broadcast(*dsr).shape)
    for x in range(d):
        comp = hr[x, 0] * dsr[0]
        for c in range(1, d):
            if hr[x, c] != 0.0:
                comp = comp + hr[x, c] * dsr[c]
        r2 += comp * comp
    return r2


def _dots(VT: np.ndarray, ii, jj) -> np.ndarray:
    """V_i . V_j, component by component (VT: (d, n) velocities)."""
    dots = VT[0][ii] * VT[0][jj]
    for c in range(1, VT.shape[0]):
        dots += VT[c][ii] * VT[c][jj]
    return dots


def velocity_correlation(s: np.ndarray, h: np.ndarray, V: np.ndarray, dr: float,
                         rmax: float | None = None, block: int = 2_000_000) -> dict:
    """C(r) = <V_i . V_j>_{|r_ij| in bin} / <V^2> over pairs i < j (minimum image), binned
    by ``dr`` up to ``rmax`` (default and upper bound: half the smallest cell height).

    Row blocks of about ``block`` pairs: memory O(block), time O(N^2).  Returns dict(r,
    C, counts, sum_VV) (C is NaN in empty bins)."""
    mi = MinImage(h)
    rmax = mi.rmax if rmax is None or rmax <= 0 else min(rmax, mi.rmax)
    nbins = max(1, int(rmax / dr))         # whole bins within the minimum-image radius
    n, d = s.shape
    sr = mi.reduced(s)
    V = np.asarray(V, dtype=float)
    V2 = float(np.einsum("id,id->", V, V)) / n
    srT, VT = np.ascontiguousarray(sr.T), np.ascontiguousarray(V.T)
    sums = np.zeros(nbins)
    counts = np.zeros(nbins)
    rows = max(1, block // max(n, 1))
    for a in range(0, n, rows):                # row blocks; pairs (i, j > i)
        b = min(n, a + rows)
        cols = slice(a + 1, n)
        if a + 1 >= n:
            break
        r2 = min_image_r2(mi.hr, [srT[c][cols][None, :] - srT[c][a:b, None] for c in range(d)])
        dots = _dots(VT, (slice(a, b), None), (None, cols))
        # keep j > i only: in the block, column k (j = a + 1 + k) with row q (i = a + q)
        jj = np.arange(a + 1, n)[None, :]
        ii = np.arange(a, b)[:, None]
        k = np.sqrt(r2) / dr
        keep = (jj > ii) & (k < nbins)
        kk = k[keep].astype(np.int64)
        sums += np.bincount(kk, dots[keep], nbins)
        counts += np.bincount(kk, None, nbins)
    with np.errstate(invalid="ignore", divide="ignore"):
        C = sums / counts / V2 if V2 > 0 else np.full(nbins, np.nan)
    return dict(r=(np.arange(nbins) + 0.5) * dr, C=C, counts=counts, sum_VV=sums, V2=V2)


def corr_spacing(h: np.ndarray, dr: float) -> float:
    """Default grid spacing of the FFT C(r): dr / 4, coarser if that grid would have more than
    CORR_GRID_MAX points (spacing (Omega / CORR_GRID_MAX)^(1/d))."""
    vol = abs(float(np.linalg.det(h)))
    return max(0.25 * dr, (vol / CORR_GRID_MAX) ** (1.0 / h.shape[0]))


def correlation_grid(h: np.ndarray, spacing: float) -> tuple[int, ...]:
    """Points per direction of the FFT grid of C(r): the remapped cell h_r divided into
    M_k >= |column k of h_r| / spacing parts (rounded up to a fast FFT length, >= 4)."""
    hr = remapped_cell(h)
    return tuple(max(4, next_fast_len(int(math.ceil(float(np.linalg.norm(hr[:, k])) / spacing)),
                                      real=True)) for k in range(hr.shape[0]))


def grid_resolution(h: np.ndarray, M, scheme: str = "ngp") -> float:
    """eps: bound on |r_grid - r_ij|, the distance between the separation a pair is binned at
    and its true minimum-image separation.  One grid cell per reduced component for NGP
    (each node moves by < 1/2 cell), two for CIC (each node is spread over its cell's
    corners); eps is the longest diagonal of that box, max_c |h_r diag(1/M) c|."""
    hr = remapped_cell(h)
    cell = hr / np.asarray(M, float)[None, :]
    d = hr.shape[0]
    corners = np.array(list(np.ndindex(*(2,) * d)), float) * 2 - 1      # {-1, 1}^d
    diag = float(np.max(np.linalg.norm(corners @ cell.T, axis=1)))
    return diag * (2.0 if scheme == "cic" else 1.0)


class _Deposit:
    """Deposition of per-node weights on the grid of reduced points g / M: NGP puts w_i on
    the nearest point, CIC on the 2^d corners of the enclosing cell with multilinear weights.
    The grid indices and corner weights are computed once for the d + 1 fields."""

    def __init__(self, sr: np.ndarray, M, scheme: str):
        self.M = tuple(int(m) for m in M)
        self.size = int(np.prod(self.M))
        u = sr * np.asarray(self.M, float)
        d = len(self.M)
        if scheme == "ngp":
            g = np.floor(u + 0.5).astype(np.int64)
            self.flat = np.ravel_multi_index(tuple(g[:, k] % self.M[k] for k in range(d)), self.M)
            self.base = None
            return
        g0 = np.floor(u).astype(np.int64)
        f = u - g0
        flats, base = [], []
        for corner in np.ndindex(*(2,) * d):   # 2^d corners: a loop over dimensions only
            wc = np.ones(len(sr))
            for k, c in enumerate(corner):
                wc *= f[:, k] if c else 1.0 - f[:, k]
            base.append(wc)
            flats.append(np.ravel_multi_index(tuple((g0[:, k] + c) % self.M[k]
                                                    for k, c in enumerate(corner)), self.M))
        self.flat, self.base = np.concatenate(flats), np.concatenate(base)

    def __call__(self, w: np.ndarray) -> np.ndarray:
        if self.base is None:
            return np.bincount(self.flat, w, self.size).reshape(self.M)
        return np.bincount(self.flat, self.base * np.tile(w, self.base.size // w.size),
                           self.size).reshape(self.M)


def _self_term(sr: np.ndarray, M, w: np.ndarray, scheme: str) -> dict:
    """The i = j part of the grid autocorrelation sum_g rho(g) rho(g + D), rho = deposit of w:
    {D: sum_i w_i^2 prod_k a_k(i, D_k)}.  NGP: all at D = 0, sum_i w_i^2.  CIC (weights
    1 - f, f along each direction): a(0) = (1 - f)^2 + f^2, a(+-1) = f (1 - f)."""
    d = sr.shape[1]
    w2 = w * w
    if scheme == "ngp":
        return {(0,) * d: float(np.sum(w2))}
    f = sr * np.asarray(M, float)
    f -= np.floor(f)
    a = {0: (1.0 - f) ** 2 + f ** 2, 1: f * (1.0 - f), -1: f * (1.0 - f)}
    out = {}
    for D in itertools.product((-1, 0, 1), repeat=d):       # 3^d offsets
        prod = w2.copy()
        for k, Dk in enumerate(D):
            prod *= a[Dk][:, k]
        out[D] = float(np.sum(prod))
    return out


def _near_sums(mi: MinImage, sr: np.ndarray, VT: np.ndarray, nbins_exact: int, dr: float,
               chunk: int = 1_000_000) -> tuple[np.ndarray, np.ndarray]:
    """sum V_i.V_j and the number of pairs i < j in the bins k < nbins_exact, exactly (the
    pairs closer than nbins_exact * dr <= the minimum-image radius, with k = floor(r_ij / dr)
    computed as in ``velocity_correlation``).

    A k-d tree of the nodes in the remapped cell (x = h_r s_r, s_r in [0, 1)^d) is queried
    against itself (image n = 0, i < j) and against the images x + h_r n of the nodes within
    the cut-off of the cell, for n in {-1, 0, 1}^d with first non-zero component > 0 (each
    unordered pair is found once, as (i, j, n) or (j, i, -n)).  O(N) pairs, processed in
    chunks of ``chunk``."""
    n, d = sr.shape
    sums, counts = np.zeros(nbins_exact), np.zeros(nbins_exact)
    if nbins_exact <= 0 or n < 2:
        return sums, counts
    rc = nbins_exact * dr
    reach = rc * (1.0 + 1e-9) + 1e-12          # a little beyond: the tree rounds differently
    srT = np.ascontiguousarray(sr.T)
    tree = cKDTree(sr @ mi.hr.T)
    found = [tree.query_pairs(reach, output_type="ndarray")]
    margin = rc * np.linalg.norm(np.linalg.inv(mi.hr), axis=1)      # reduced distance to faces
    for shift in itertools.product((-1, 0, 1), repeat=d):             # 3^d images: dimensions only
        nz = [c for c in shift if c != 0]
        if not nz or nz[0] < 0:
            continue
        img = sr + np.array(shift, float)
        near = np.nonzero(np.all((img >= -margin) & (img <= 1.0 + margin), axis=1))[0]
        if near.size:
            m = tree.sparse_distance_matrix(cKDTree(img[near] @ mi.hr.T), reach,
                                            output_type="ndarray")
            found.append(np.column_stack([m["i"], near[m["j"]]]))
    for ij in found:
        for a in range(0, len(ij), chunk):
            i, j = ij[a:a + chunk, 0], ij[a:a + chunk, 1]
            r2 = min_image_r2(mi.hr, [srT[c][j] - srT[c][i] for c in range(d)])
            k = (np.sqrt(r2) / dr).astype(np.int64)
            keep = (k < nbins_exact) & (i != j)
            i, j, k = i[keep], j[keep], k[keep]
            sums += np.bincount(k, _dots(VT, i, j), nbins_exact)
            counts += np.bincount(k, None, nbins_exact)
    return sums, counts


def velocity_correlation_fft(s: np.ndarray, h: np.ndarray, V: np.ndarray, dr: float,
                             rmax: float | None = None, spacing: float | None = None,
                             scheme: str = "cic", r_exact: float = CORR_R_EXACT,
                             slab: int = 1_000_000) -> dict:
    """C(r) of ``velocity_correlation`` by FFT: O(N + G log G) time, O(N + G) memory for a
    grid of G points (G ~ cell area / spacing^2, at most ~CORR_GRID_MAX by default).

    V and unit weights are deposited on a regular grid of M_1 x ... x M_d points over the
    remapped cell h_r (``scheme`` "ngp": nearest grid point, "cic": cloud in cell; grid
    spacing ``spacing``, default ``corr_spacing(h, dr)``).  Their periodic autocorrelations
    (d + 1 real FFTs)
        A_VV(D) = sum_c sum_g V_c(g) V_c(g + D) = sum_{i,j} V_i.V_j,   A_n(D) = sum_g n(g) n(g + D)
    sum over the ordered pairs (i, j) at grid offset D; the i = j terms (``_self_term``) are
    subtracted exactly, each offset is given its minimum-image length |h_r (D/M - rint(D/M))|
    and binned by ``dr`` as in the exact function, and both sums are halved (unordered
    pairs).  A pair is binned at a distance within eps = ``grid_resolution`` of its true one,
    so each bin agrees with the exact one up to the pairs within eps of its edges.

    The bins below ``r_exact`` (rounded down to a bin edge) are exact: the pairs closer than
    that are found by a k-d tree (``_near_sums``, O(N) pairs) and summed directly; there the
    pair density has the sharp contact shells that the grid would blur.

    Returns the dict of ``velocity_correlation`` plus grid (M), eps, scheme, n_exact (the
    number of exact bins)."""
    if scheme not in ("ngp", "cic"):
        raise InputError(f"velocity_correlation_fft: scheme must be 'ngp' or 'cic', got {scheme!r}")
    mi = MinImage(h)
    rmax = mi.rmax if rmax is None or rmax <= 0 else min(rmax, mi.rmax)
    nbins = max(1, int(rmax / dr))
    spacing = corr_spacing(h, dr) if spacing is None or spacing <= 0 else float(spacing)
    n, d = s.shape
    sr = mi.reduced(s)
    V = np.asarray(V, dtype=float)
    VT = np.ascontiguousarray(V.T)
    V2 = float(np.einsum("id,id->", V, V)) / n
    M = correlation_grid(h, spacing)
    fields = {"n": [np.ones(n)], "VV": list(VT)}
    deposit = _Deposit(sr, M, scheme)
    power = {}
    for name, ws in fields.items():            # d + 1 forward FFTs, one grid at a time
        for w in ws:
            F = fft.rfftn(deposit(w))
            if name in power:
                power[name] += F.real ** 2
            else:
                power[name] = F.real ** 2
            power[name] += F.imag ** 2
            del F
    del deposit
    A = {}
    for name, ws in fields.items():
        A[name] = fft.irfftn(power.pop(name), s=M)
        for w in ws:                           # i = j: sum_c V_c^2 = |V_i|^2 (or 1), spread
            for D, v in _self_term(sr, M, w, scheme).items():
                A[name][tuple(Dk % Mk for Dk, Mk in zip(D, M))] -= v
    if scheme == "ngp":
        A["n"] = np.rint(A["n"])               # NGP pair counts per offset are integers
    # bin the offsets that can lie within R = nbins dr: |D_k / M_k| <= R |row k of h_r^-1|
    R = nbins * dr
    rows = np.linalg.norm(np.linalg.inv(mi.hr), axis=1)
    idx = []
    for k in range(d):
        m = min(M[k] // 2, int(math.ceil(R * rows[k] * M[k])) + 1)
        idx.append(np.unique(np.arange(-m, m + 1) % M[k]))
    sums, counts = np.zeros(nbins), np.zeros(nbins)
    step = max(1, slab // max(1, int(np.prod([len(i) for i in idx[1:]]))))
    for a in range(0, len(idx[0]), step):      # slabs of offsets along the first direction
        sub = np.ix_(*([idx[0][a:a + step]] + idx[1:]))
        r2 = min_image_r2(mi.hr, [sub[k] / M[k] for k in range(d)])
        kb = (np.sqrt(r2) / dr).astype(np.int64)
        keep = kb < nbins
        kk = kb[keep]
        sums += np.bincount(kk, A["VV"][sub][keep], nbins)
        counts += np.bincount(kk, A["n"][sub][keep], nbins)
    del A
    sums *= 0.5
    counts *= 0.5
    # the short-range bins, exactly
    n_exact = min(nbins, int(max(r_exact, 0.0) / dr))
    if n_exact > 0:
        sums[:n_exact], counts[:n_exact] = _near_sums(mi, sr, VT, n_exact, dr)
    with np.errstate(invalid="ignore", divide="ignore"):
        C = np.where(counts > EMPTY_BIN, sums / counts / V2, np.nan) if V2 > 0 \
            else np.full(nbins, np.nan)
    return dict(r=(np.arange(nbins) + 0.5) * dr, C=C, counts=counts, sum_VV=sums, V2=V2,
                grid=np.array(M), eps=grid_resolution(h, M, scheme), scheme=scheme,
                n_exact=n_exact)


def correlation(s: np.ndarray, h: np.ndarray, V: np.ndarray, dr: float, rmax: float | None = None,
                method: str = "auto", spacing: float | None = None) -> dict:
    """C(r) by ``method``: "exact" (``velocity_correlation``, O(N^2) time), "fft"
    (``velocity_correlation_fft``, O(N log N), bins below CORR_R_EXACT exact, the others
    within the grid resolution), "auto": exact up to CORR_EXACT_MAX nodes, FFT above.
    The result carries method (and for the FFT grid, eps, n_exact)."""
    if method not in CORR_METHODS:
        raise InputError(f"C(r) method must be one of {list(CORR_METHODS)}, got {method!r}")
    if method == "auto":
        method = "exact" if s.shape[0] <= CORR_EXACT_MAX else "fft"
    if method == "exact":
        out = velocity_correlation(s, h, V, dr, rmax)
    else:
        out = velocity_correlation_fft(s, h, V, dr, rmax, spacing=spacing)
    out["method"] = method
    return out


def crossing_length(r: np.ndarray, C: np.ndarray, level: float = math.exp(-1),
                    counts: np.ndarray | None = None, min_count: int = 50) -> float:
    """First r where C (starting at C(0) = 1) falls below ``level`` (linear interpolation
    from the previous bin, or from (0, 1) if it is the first), over the bins holding at
    least ``min_count`` pairs (nodes are not hard discs: a few pairs come closer than the
    contact distance, and such sparse bins are noise)."""
    ok = np.isfinite(C)
    if counts is not None:
        ok &= counts >= min_count
    rr = np.concatenate([[0.0], r[ok]])
    cc = np.concatenate([[1.0], C[ok]])
    below = np.nonzero(cc < level)[0]
    if below.size == 0:
        return float("nan")
    k = below[0]
    return float(rr[k - 1] + (cc[k - 1] - level) / (cc[k - 1] - cc[k]) * (rr[k] - rr[k - 1]))
