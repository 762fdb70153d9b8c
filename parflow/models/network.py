"""Floppy rod networks in simple shear (paper §III, Figs. 3-5 and 8; DESIGN §6).

The network is built by the WLKM protocol (``network_build``): a jammed soft-disc packing
of ``N`` particles, a rod on every contact, diluted to coordination ``z < 2d``.  It is then
sheared with Lees-Edwards boundaries: the cell h(gamma) = [[Lx, gamma Ly], [0, Ly]] follows
the flow V_f = (y, 0) (the core does this: dh/dgamma = E h); bonds carry their image shifts,
r_a = h (s_j + n_a - s_i), and the affine rate of a rod is b_a = n_a . E r_a = x_a y_a / r_a.

Analyses (at the instants the scene asks for, with the factor of N loaded at that instant):

* point response: for a handful of rods beta, N f = |beta> and V = S^T f (the velocities
  when rod beta alone is made to extend at unit rate).  |V_i| and |f_a| are binned by the
  minimum-image distance from the midpoint of beta and averaged over the rods; the V profile
  is fitted by A exp(-r/l_c) + B exp(-r/l_r) (l_c: the initial decay, l_r: the slow tail).
  <V|V> = f_beta (= f^T N f).
* velocity correlation C(r) = <V_i . V_j> / <V^2> of V_na, pairs binned by minimum-image
  distance up to r_max: exactly, in row blocks (memory O(block), time O(N^2)), or by FFT on
  a grid (time O(N log N); bins below CORR_R_EXACT exact, the others to the grid resolution);
  ``corr_method = "auto"`` picks the FFT above CORR_EXACT_MAX nodes.
* spectrum of N: omega = sqrt(lambda(N)); all of it (dense eigvalsh, Nc <= DENSE_MAX) or
  the lowest ``n_low`` (SLEPc shift-and-invert).

Distances: reduced displacements in a *remapped* cell h_r = h U (U unimodular, tilt
reduced to |h_r[0,1]| <= Lx/2, the Lees-Edwards remapping), minus rint, times h_r.  For
r <= half the smallest height of the cell (the default r_max) this is the true minimum image.
"""
from __future__ import annotations

import itertools
import math

import numpy as np

from ..geometry import MinImage, pair_vectors, remapped_cell, velocity_gradient
from ..state import Bonds, InputError, State
from . import network_build as _nb

FLOW = "shear"
Z_RANGE = (3.5, 3.98)
DENSE_MAX = 10_000
# the force solve at the end of a step may reuse the step's factor (solver.reuse_factor =
# "auto" above system.REUSE_AUTO_MIN_NC rods): a 2D network's factor costs ~20-30 solves
FACTOR_REUSE = True
CORR_METHODS = ("auto", "exact", "fft")
CORR_EXACT_MAX = 10_000    # nodes: above, corr_method = "auto" uses the FFT
CORR_R_EXACT = 3.0         # a0: C(r) bins below it are exact in the FFT method (contact shells)
CORR_GRID_MAX = 2 ** 24    # points of the FFT grid of C(r), about at most (134 MB a grid)
EMPTY_BIN = 1e-6           # C(r) is NaN in bins holding fewer pairs (CIC counts are fractional)
SPECTRA = ("none", "dense", "low", "auto")

PARAMS = {
    # name: (type, default, check, description)
    "N": (int, 4096, lambda v: v >= _nb.MIN_NODES,
          f"number of particles of the packing (>= {_nb.MIN_NODES}); rattlers are dropped"),
    "d": (int, 2, lambda v: v == 2, "2 (3D networks come later)"),
    "z": (float, 3.8, lambda v: Z_RANGE[0] <= v <= Z_RANGE[1],
          f"in [{Z_RANGE[0]}, {Z_RANGE[1]}]: a floppy network needs z < 2d = 4, and the WLKM "
          f"dilution (no node below d + 1 = 3 rods) cannot reliably go below ~3.5"),
    "phi": (float, _nb.DEFAULT_PHI, lambda v: 0.0 < v < 1.0,
            "packing fraction of the seed packing, in (0, 1) (0.86-0.90 gives z0 ~ 4.4-5)"),
    "pressure": (float, 0.0, lambda v: v >= 0.0,
                 ">= 0: target pressure of the packing (0: use phi instead)"),
    "network_file": (str, "", lambda v: True,
                     "network HDF5 file (network_build.save_network) to load; '' generates one"),
    "response_rods": (int, 8, lambda v: v >= 1, "number of rods beta for the point response (>= 1)"),
    "response_dr": (float, 0.5, lambda v: v > 0, "bin width of the point-response profiles (> 0)"),
    "corr_dr": (float, 0.5, lambda v: v > 0, "bin width of C(r) (> 0)"),
    "corr_rmax": (float, 0.0, lambda v: v >= 0,
                  ">= 0: largest distance of C(r) (0: half the smallest height of the cell)"),
    "correlation": (bool, True, lambda v: True, "true/false: compute C(r) at analysis instants"),
    "corr_method": (str, "auto", lambda v: v in CORR_METHODS,
                    f"one of {list(CORR_METHODS)}: C(r) over all pairs (exact, O(N^2)), by FFT on "
                    f"a grid (O(N log N)), or auto: exact up to {CORR_EXACT_MAX} nodes"),
    "corr_spacing": (float, 0.0, lambda v: v >= 0,
                     ">= 0: grid spacing of the FFT C(r) (0: corr_dr / 4, coarser beyond "
                     f"{CORR_GRID_MAX} grid points)"),
    "spectrum": (str, "none", lambda v: v in SPECTRA,
                 f"one of {list(SPECTRA)}: spectrum of N at analysis instants (dense: "
                 f"all of it, Nc <= {DENSE_MAX}; low: the n_low lowest; auto: dense if possible)"),
    "n_low": (int, 10, lambda v: v >= 1, "number of lowest eigenvalues for spectrum = 'low' (>= 1)"),
    "dos_bins": (int, 60, lambda v: v >= 2, "number of log-spaced bins of D(omega) (>= 2)"),
}
# the analysis settings travel with the state (State.meta), so a restart keeps them
_ANALYSIS_KEYS = ("response_rods", "response_dr", "corr_dr", "corr_rmax", "correlation",
                  "corr_method", "corr_spacing", "spectrum", "n_low", "dos_bins")


# --------------------------------------------------------------------------- building

def check_z(z: float, d: int = 2) -> None:
    if not (isinstance(z, (int, float)) and math.isfinite(z)):
        raise InputError(f"model.z must be a finite number, got {z!r}")
    if z >= 2 * d:
        raise InputError(f"model.z = {z:g}: a floppy network needs z < 2d = {2 * d} "
                         f"(z = 2d is isostatic); use z in [{Z_RANGE[0]}, {Z_RANGE[1]}]")
    if z < Z_RANGE[0] or z > Z_RANGE[1]:
        raise InputError(f"model.z = {z:g} is outside [{Z_RANGE[0]}, {Z_RANGE[1]}]: too close "
                         f"to 2d = {2 * d} (dz < 0.02) or below what the WLKM dilution reaches "
                         f"without floppy appendages")


def _defaults(params: dict) -> dict:
    p = {k: v[1] for k, v in PARAMS.items()}
    p.update(params)
    return p


def make(params: dict, seed: int) -> "_nb.Network":
    """The WLKM network the scene describes (generated, not loaded)."""
    p = _defaults(params)
    check_z(p["z"], p["d"])
    if p["pressure"] > 0:
        pk = _nb._pk.make_packing(p["N"], None, d=p["d"], seed=seed, pressure=p["pressure"])
    else:
        pk = _nb._pk.make_packing(p["N"], p["phi"], d=p["d"], seed=seed)
    return _nb.network_from_packing(pk, p["z"], seed=seed)


def check_matches(net: "_nb.Network", params: dict, seed: int, path: str = "") -> None:
    """InputError listing every way a loaded network differs from the scene."""
    p = _defaults(params)
    bad = []
    pinfo = net.info.get("packing", {}) if isinstance(net.info, dict) else {}
    if net.d != p["d"]:
        bad.append(f"d = {net.d} (scene: {p['d']})")
    n_pk = pinfo.get("n")
    if n_pk is not None and int(n_pk) != p["N"]:
        bad.append(f"N = {int(n_pk)} particles (scene: model.N = {p['N']})")
    if abs(net.z - p["z"]) > 1.0 / net.n + 1e-12:
        bad.append(f"z = {net.z:.6g} (scene: model.z = {p['z']:g})")
    if int(net.seed) != int(seed):
        bad.append(f"seed = {net.seed} (scene: seed = {seed})")
    if p["pressure"] > 0:
        pp = pinfo.get("pressure")
        if pp is not None and abs(pp / p["pressure"] - 1) > 0.05:
            bad.append(f"packing pressure = {pp:.4g} (scene: model.pressure = {p['pressure']:g})")
    else:
        ph = pinfo.get("phi")
        if ph is not None and abs(ph - p["phi"]) > 1e-9:
            bad.append(f"packing phi = {ph:.6g} (scene: model.phi = {p['phi']:g})")
    if bad:
        raise InputError(f"model.network_file {path!r} does not match the scene: "
                         + "; ".join(bad) + ". Fix the scene, or set network_file = '' to "
                         "generate the network")


def build(params: dict, seed: int) -> State:
    p = _defaults(params)
    check_z(p["z"], p["d"])
    path = p["network_file"]
    if path:
        net = _nb.load_network(path)
        check_matches(net, p, seed, path)
    else:
        net = make(p, seed)
    return state_from_network(net, p, path)


def state_from_network(net: "_nb.Network", params: dict | None = None, path: str = "") -> State:
    p = _defaults(params or {})
    d = net.d
    bd = net.bonds
    bonds = Bonds(bd.i.copy(), bd.j.copy(), bd.shift.copy(), bd.l0.copy())
    state = State(np.array(net.s, dtype=float), np.array(net.h0, dtype=float),
                  velocity_gradient(FLOW, d), 0.0, bonds)
    info = net.info if isinstance(net.info, dict) else {}
    pinfo = info.get("packing", {})
    meta = dict(model="network", z=float(net.z), z_target=float(p["z"]), dz=2.0 * d - net.z,
                n_nodes=net.n, n_bonds=len(bd), z0=float(net.z0), network_seed=int(net.seed),
                network_file=path, fabric_ratio=float(info.get("fabric_ratio", np.nan)),
                min_degree=int(info.get("min_degree", -1)))
    for k in ("n", "phi", "pressure", "z", "n_rattlers"):
        if k in pinfo:
            meta[f"packing_{k}"] = int(pinfo[k]) if k in ("n", "n_rattlers") else float(pinfo[k])
    if isinstance(info.get("self_stress"), dict):
        meta["self_stresses"] = int(info["self_stress"]["self_stresses"])
    meta.update({k: (int(v) if isinstance(v, bool) else v)
                 for k, v in p.items() if k in _ANALYSIS_KEYS})
    state.meta.update(meta)
    return state


def observables(state: State, F) -> dict:
    """z (fixed), and the fraction of rods in tension (tau < 0)."""
    return dict(z=2.0 * len(state.bonds) / state.n,
                tension_fraction=float(np.count_nonzero(F.tau < 0)) / max(F.tau.size, 1))


# --------------------------------------------------------------------------- geometry
# (the cell, the remap and minimum images: parflow.geometry)

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


# --------------------------------------------------------------------------- analyses

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
    from scipy.optimize import curve_fit
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


def _min_image_r2(hr: np.ndarray, dsr: list) -> np.ndarray:
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
        r2 = _min_image_r2(mi.hr, [srT[c][cols][None, :] - srT[c][a:b, None] for c in range(d)])
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
    from scipy.fft import next_fast_len
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
    from scipy.spatial import cKDTree
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
            r2 = _min_image_r2(mi.hr, [srT[c][j] - srT[c][i] for c in range(d)])
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
    from scipy import fft
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
        r2 = _min_image_r2(mi.hr, [sub[k] / M[k] for k in range(d)])
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


def sparse_S(n_unit: np.ndarray, i: np.ndarray, j: np.ndarray, n_nodes: int):
    """S (Nc x dN, scipy CSR) of rods between nodes i and j with unit vectors ``n_unit``:
    (S V)_alpha = n_alpha . (V_j - V_i)."""
    import scipy.sparse as sp
    nc, d = n_unit.shape
    rows = np.repeat(np.arange(nc), 2 * d)
    comp = np.arange(d)
    cols = np.concatenate([d * i[:, None] + comp, d * j[:, None] + comp], axis=1).ravel()
    vals = np.concatenate([-n_unit, n_unit], axis=1).ravel()
    return sp.csr_matrix((vals, (rows, cols)), shape=(nc, d * n_nodes))


def dense_N(n_unit: np.ndarray, bonds: Bonds, n_nodes: int) -> np.ndarray:
    """Dense N = S S^T from the unit vectors (sparse S, vectorised)."""
    S = sparse_S(n_unit, bonds.i, bonds.j, n_nodes)
    return (S @ S.T).toarray()


def dense_spectrum(n_unit: np.ndarray, bonds: Bonds, n_nodes: int) -> np.ndarray:
    """All omega = sqrt(lambda(N)), ascending (numpy eigvalsh)."""
    lam = np.linalg.eigvalsh(dense_N(n_unit, bonds, n_nodes))
    return np.sqrt(np.clip(lam, 0.0, None))


def density_of_states(omega: np.ndarray, bins: int) -> tuple[np.ndarray, np.ndarray]:
    """D(omega) normalised to 1 over log-spaced bins from the smallest positive omega to the
    largest: returns (bin edges, D)."""
    pos = omega[omega > 0]
    if pos.size < 2:
        return np.zeros(bins + 1), np.zeros(bins)
    edges = np.geomspace(pos[0] * (1 - 1e-12), pos[-1] * (1 + 1e-12), bins + 1)
    hist, _ = np.histogram(omega, edges)
    return edges, hist / (omega.size * np.diff(edges))


def _bcast(system, value):
    comm = system.comm
    if comm.getSize() == 1:
        return value
    return comm.tompi4py().bcast(value, root=0)


def analyses(system, state: State, F) -> dict:
    """Point response, C(r) and the spectrum of N at the current configuration.

    ``state`` must carry the current positions (state.s at F.gamma): checked against F.r."""
    meta = {k: state.meta.get(k, PARAMS[k][1]) for k in _ANALYSIS_KEYS}
    bd, s, h = state.bonds, state.s, F.h
    mism = float(np.max(np.abs(pair_vectors(s, h, bd.i, bd.j, bd.shift) - F.r)))
    if not mism <= 1e-8 * max(1.0, float(np.abs(h).max())):
        raise RuntimeError(f"network.analyses: the positions given do not match the force "
                           f"evaluation (pair vectors differ by {mism:.3g}): the driver must pass "
                           f"the current state")
    # the factor in the solver may belong to a rejected trial step (e.g. after Jammed):
    # reload N at this configuration (one numeric refactorisation at the next solve)
    system.load(F.n)
    arrays, scalars = {}, {}
    # (a) point response
    rods = pick_rods(s, h, bd, int(meta["response_rods"]))
    pr = point_response(system, s, h, bd, rods, float(meta["response_dr"]))
    fit = fit_two_exponentials(pr["r"], pr["V_mean"], pr["counts_V"])
    fit_f = fit_two_exponentials(pr["r"], pr["f_mean"], pr["counts_f"])
    arrays.update(resp_r=pr["r"], resp_V=pr["V_mean"], resp_V_rms=pr["V_rms"],
                  resp_f=pr["f_mean"], resp_counts_V=pr["counts_V"], resp_counts_f=pr["counts_f"],
                  resp_rods=rods, resp_VV=pr["VV"])
    scalars.update({f"resp_{k}": v for k, v in fit.items()})
    scalars.update({f"resp_f_{k}": v for k, v in fit_f.items()})
    scalars["VV"] = float(np.mean(pr["VV"]))
    scalars["VV_err"] = float(np.std(pr["VV"]) / np.sqrt(len(pr["VV"])))
    # (b) velocity correlation of V_na
    if meta["correlation"]:
        # computed on rank 0 and broadcast: identical on every rank, one copy of the grid
        cr = None
        if system.comm.getRank() == 0:
            cr = correlation(s, h, F.V_na, float(meta["corr_dr"]), float(meta["corr_rmax"]),
                             str(meta["corr_method"]), float(meta["corr_spacing"]))
        cr = _bcast(system, cr)
        arrays.update(corr_r=cr["r"], corr_C=cr["C"], corr_counts=cr["counts"])
        scalars["corr_length"] = crossing_length(cr["r"], cr["C"], counts=cr["counts"])
        scalars["corr_method"] = cr["method"]
        if cr["method"] == "fft":
            scalars.update(corr_eps=float(cr["eps"]),
                           corr_r_exact=cr["n_exact"] * float(meta["corr_dr"]))
    # (c) spectrum
    mode = meta["spectrum"]
    if mode == "auto":
        mode = "dense" if len(bd) <= DENSE_MAX else "low"
    if mode == "dense":
        if len(bd) > DENSE_MAX:
            raise InputError(f"model.spectrum = 'dense' needs Nc <= {DENSE_MAX} (Nc = {len(bd)}): "
                             f"use 'low' or 'auto'")
        omega = dense_spectrum(F.n, bd, state.n) if system.comm.getRank() == 0 else None
        omega = _bcast(system, omega)
        edges, D = density_of_states(omega, int(meta["dos_bins"]))
        arrays.update(omega=omega, dos_edges=edges, dos=D)
        scalars["omega_min_dense"] = float(omega[0])
    elif mode == "low":
        from ..spectrum import LowSpectrum, omega_from_lambda
        spec = LowSpectrum(system.ops.N, k=int(meta["n_low"]), parallel=system.parallel)
        try:
            lam, _ = spec.solve()
        finally:
            spec.destroy()
        omega = omega_from_lambda(lam)
        arrays.update(omega_low=omega)
        scalars["omega_min_low"] = float(omega[0])
    return dict(arrays=arrays, scalars=scalars)


# --------------------------------------------------------------------------- post-processing

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
