"""Jammed soft-disc packings: the seed of the network model (DESIGN §7, issue 3).

Binary 50:50 mixture, radius ratio 1.4, small-particle *diameter* = 1 (the unit of
length), in a periodic box whose side is fixed by the packing fraction phi.  Pair
potential: harmonic repulsion U = 1/2 sum (1 - r_ij/sigma_ij)^2 over overlapping pairs,
sigma_ij = R_i + R_j.  The force unit is therefore eps/a0 with eps = 1 (the stiffness
scale); a typical contact force is the typical relative overlap 1 - r/sigma.

Minimiser: FIRE (Bitzek et al., PRL 97, 170201, 2006) with the standard parameters
(N_min = 5, f_inc = 1.1, f_dec = 0.5, alpha_start = 0.1, f_alpha = 0.99), unit masses,
semi-implicit Euler, the half-step back-off of FIRE 2.0 (Guénolé et al. 2020) on P <= 0,
dt_0 = 0.1 and dt_max = 0.5 (dt_max = 1 is past the stability limit of the stiffest
pair, ~2/omega_max, and costs 10x more iterations: measured).

Convergence: max_i |F_i| < ftol * <f_c>, where <f_c> is the mean contact-force magnitude
(a *relative* tolerance, so it means the same at every pressure).  See DEFAULT_FTOL for
the choice and what it does to the contact network.

Performance (no Python loop over particles or pairs): positions are stored as (d, N)
arrays in Morton (Z-curve) order for cache locality; a Verlet pair list (skin ``skin`` =
0.4 by default) is rebuilt only when the largest displacement since the last build may
exceed skin/2 (a running bound sum dt max_i|v_i| is checked first, the exact displacement
only when the bound trips).  The pairs i < j are kept sorted by (i, j).
Kernels: "numpy" finds the pairs with cKDTree (periodic boxsize) and turns the list into a
sparse incidence matrix B (+1 at j, -1 at i): pair vectors B @ x + shift, forces
B^T @ (c r).  "numba" (optional, Debian python3-numba; packing_numba) builds the list with
a periodic cell list and does each FIRE iteration in two compiled passes over the
particles: forces fused with the reductions P = F.v, |F|, |v + dt F|, max|F_i|, then the
velocity mixing, position update and max|v_i| in one loop.  With one thread (the default)
the force pass is a pair loop over the half list; with ``threads`` > 1 it is a
per-particle gather over the full list, parallel over particles (each pair computed from
both ends).  In every case the force on a particle is summed over its neighbours in
ascending index order with the same floating-point terms, and the reductions are summed
in a fixed order (blocks of BLOCK particles, then the blocks in order), so the two
kernels and any thread count give bit-identical forces and packings for a given seed.
Measured (docs/benchmarks/packing.json; phi = 0.88, seed 1, one thread; shared 2-core
machine with a load average of 3.5-6 from other jobs, so CPU seconds are the steadier
number): N = 4096: 5 566 FIRE iterations, 1.2 s wall, 0.7 s CPU (numpy kernel: 1.9 s);
N = 40 000: 13 089 iterations, 12.9 s wall, 11.4 s CPU, 1.0 ms per iteration (numpy
kernel: 41 s; the previous cKDTree + pair-loop numba kernel: 26.8 s, 2.0 ms); N = 10^5:
14 945 iterations, 32 s wall, 31 s CPU, 2.1 ms per iteration (previous: 5.1 ms);
N = 10^6: 76 201 iterations, 2 529 s wall (42 min), 2 234 s CPU, 33 ms per iteration
(previous: 49.5 ms) of which 202 s in 639 list builds (previous: 837 s in 697 cKDTree
builds), peak RSS 0.80 GB; the network build then takes 1.7 s.  Two threads give the
same packings but took 248 s instead of 12.9 s at N = 40 000 on the loaded machine (the
threads wait for each other at every parallel pass when the cores are shared), hence
DEFAULT_THREADS = 1.
FIRE needs ~6e3 (N = 4096), ~1.3e4-1.8e4 (4e4), ~1.5e4-2.4e4 (1e5) and ~7.6e4-9e4 (1e6)
iterations; the count varies by +-30 % from seed to seed (the glassy relaxation before
the convergent tail dominates it).

Contacts are reported with integer image shifts n in reduced coordinates s = x/L in
[0, 1)^d: r_ij = L * (s_j + n - s_i)   (DESIGN §2, h = diag(L)).
"""
from __future__ import annotations

import contextlib
import math
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from ..state import InputError

KERNELS = ("numpy", "numba")
#: numba threads of the compiled kernel unless told otherwise (see the module docstring).
DEFAULT_THREADS = 1


def have_numba() -> bool:
    """Whether the optional compiled kernel can be used (Debian: python3-numba)."""
    import importlib.util
    return importlib.util.find_spec("numba") is not None


SMALL_DIAMETER = 1.0
RADIUS_RATIO = 1.4
#: Jamming packing fraction of the binary 50:50, ratio-1.4 mixture (quench protocol).
PHI_J = {2: 0.843, 3: 0.648}

#: Default relative force tolerance: max|F_i| < DEFAULT_FTOL * <f_c>.  Measured by
#: minimising to 1e-2, 1e-3, ... 1e-11 in turn and comparing the non-rattler contact set
#: with the final one: N = 4096, phi = 0.86: 139 contacts differ at 1e-2, 7 at 1e-3, none
#: from 1e-4 down; N = 40 000, phi = 0.87: 1336 at 1e-2, 261 at 1e-3, 13 at 1e-4, 8 at
#: 1e-5, none from 1e-6 down (z = 4.58804 from 1e-6 to 1e-11).  Going from 1e-6 to 1e-9
#: costs ~10 % more iterations (the cost is in the glassy relaxation before the tail).
#: 1e-9 keeps three decades of margin over the point where the graph freezes.  A relative
#: 1e-12 is not reachable: the round-off floor of max|F| is ~eps*L (see force_floor),
#: 4e-14 at N = 4096 vs <f_c> ~ 5e-3.
DEFAULT_FTOL = 1e-9


@dataclass
class FireParams:
    """FIRE parameters (Bitzek et al. 2006 defaults; dt in units with m = 1, k <= 1)."""

    dt0: float = 0.1
    dt_max: float = 0.5
    n_min: int = 5
    f_inc: float = 1.1
    f_dec: float = 0.5
    alpha0: float = 0.1
    f_alpha: float = 0.99


@dataclass
class Packing:
    """A minimised soft-disc packing.

    positions: (N, d) in [0, L)^d;  radii: (N,);  box: (d,) box sides L (h = diag(box)).
    contacts_i, contacts_j, contacts_shift: force-bearing contacts between non-rattlers
        (i < j), with integer image shifts so that r_ij = box * (s_j + n - s_i).
    rattler: (N,) bool, particles removed iteratively for having < d + 1 contacts.
    pressure: virial pressure p = sum_c f_c r_c / (d V) over all contacts.
    z: mean contact number of the non-rattlers (2 Nc / N_nonrattler).
    phi: packing fraction;  energy: total U;  max_force: max_i |F_i| at the end;
    force_scale: mean contact force <f_c>;  iterations: FIRE iterations (all stages).
    """

    positions: np.ndarray
    radii: np.ndarray
    box: np.ndarray
    contacts_i: np.ndarray
    contacts_j: np.ndarray
    contacts_shift: np.ndarray
    rattler: np.ndarray
    pressure: float
    z: float
    phi: float
    energy: float
    max_force: float
    force_scale: float
    iterations: int
    seed: int
    ftol: float
    info: dict = field(default_factory=dict)

    @property
    def d(self) -> int:
        return int(self.positions.shape[1])

    @property
    def n(self) -> int:
        return int(self.positions.shape[0])

    @property
    def reduced(self) -> np.ndarray:
        """Reduced coordinates s = x / L in [0, 1)^d."""
        return _wrap01(self.positions / self.box)

    @property
    def n_contacts(self) -> int:
        return int(self.contacts_i.shape[0])

    def contact_vectors(self) -> np.ndarray:
        """(Nc, d) pair vectors r_ij = L (s_j + n - s_i) of the reported contacts."""
        s = self.reduced
        return self.box * (s[self.contacts_j] + self.contacts_shift - s[self.contacts_i])


# --------------------------------------------------------------------------- geometry

def ball_volume(d: int, r):
    return math.pi ** (d / 2) / math.gamma(d / 2 + 1) * np.asarray(r, dtype=float) ** d


def binary_radii(n: int) -> np.ndarray:
    """50:50 mixture: the first n//2 small (R = 1/2), the rest large (R = 0.7)."""
    r = np.full(n, 0.5 * SMALL_DIAMETER * RADIUS_RATIO)
    r[: n // 2] = 0.5 * SMALL_DIAMETER
    return r


def box_side(radii: np.ndarray, phi: float, d: int) -> float:
    """Side of the cubic periodic box giving packing fraction phi."""
    return float((ball_volume(d, radii).sum() / phi) ** (1.0 / d))


def packing_fraction(radii: np.ndarray, box) -> float:
    d = np.size(box)
    return float(ball_volume(d, radii).sum() / np.prod(box))


def _wrap01(s: np.ndarray) -> np.ndarray:
    s = s - np.floor(s)
    s[s >= 1.0] = 0.0          # floor(-tiny) + ... can round up to exactly 1
    return s


def morton_order(s: np.ndarray, bits: int | None = None) -> np.ndarray:
    """Permutation sorting points s in [0,1)^d (N, d) along a Z-order curve."""
    n, d = s.shape
    if bits is None:
        bits = max(1, min(63 // d, int(math.ceil(math.log2(max(n, 2)) / d)) + 1))
    c = np.minimum((s * (1 << bits)).astype(np.int64), (1 << bits) - 1)
    key = np.zeros(n, dtype=np.int64)
    for b in range(bits):                      # loop over bits, vectorised over points
        for k in range(d):
            key |= ((c[:, k] >> b) & 1) << (b * d + k)
    return np.argsort(key, kind="stable")


# --------------------------------------------------------------------------- pair list

#: Particles per reduction block: F.v, |F|^2, |v|^2 are summed in index order within
#: blocks of this size, then over the blocks in order (packing_numba.BLOCK is the same).
BLOCK = 4096


def _block_sum(t: np.ndarray) -> float:
    """Sum of t (n,) in the fixed order of the compiled kernel: each block of BLOCK
    entries in index order, then the block sums in order (cumsum is sequential)."""
    n = t.shape[0]
    nb = -(-n // BLOCK)
    buf = np.zeros(nb * BLOCK)
    buf[:n] = t
    part = 0.0 + np.cumsum(buf.reshape(nb, BLOCK), axis=1)[:, -1]
    return float(0.0 + np.cumsum(part)[-1])


class _PairList:
    """Verlet pair list and force kernels.  X is (d, N), unwrapped between rebuilds; the
    image of a pair is fixed at build time (r_ij = X_j - X_i + S_ij), which stays the
    minimum image while particles move less than skin/2.

    The pairs (i < j) are sorted by (i, j).  Both kernels list the same pairs and sum
    the force on each particle over its neighbours in ascending index order with the
    same floating-point terms, so their forces are bit-identical:
    "numpy": cKDTree candidates, sparse incidence matrix B (+1 at j, -1 at i), pair
    vectors B @ x + S and forces B^T @ (c r);
    "numba" (packing_numba): periodic cell list; with one thread a pair loop over the half
    list, with ``threads`` > 1 a per-particle gather over the full list, parallel over
    particles.  The numba kernel also fuses the FIRE vector work into its passes (step,
    update)."""

    def __init__(self, radii: np.ndarray, box: np.ndarray, skin: float,
                 kernel: str = "numpy", threads: int | None = None):
        kernel_arg = kernel
        if kernel == "auto":
            kernel = "numba" if have_numba() else "numpy"
        if kernel not in KERNELS:
            raise InputError(f"packing: kernel must be 'auto' or one of {KERNELS}, got {kernel!r}")
        if kernel == "numba" and not have_numba():
            raise InputError("packing: kernel='numba' needs numba (Debian: apt-get install "
                             "python3-numba); use kernel='numpy'")
        self.radii = radii
        self.box = np.asarray(box, dtype=float)
        self.skin = float(skin)
        self.cut = 2.0 * float(radii.max()) + self.skin
        # the compiled kernel re-takes the minimum image at every step: it needs
        # |r_ij| < cut + skin < L/2 for every listed pair
        small = self.box.min() <= 2.0 * (self.cut + self.skin)
        if kernel == "numba" and small:
            if kernel_arg == "numba":
                raise InputError(f"packing: kernel='numba' needs a box side > 2 (cut + skin) "
                                 f"= {2 * (self.cut + self.skin):.3g}; use kernel='numpy'")
            kernel = "numpy"
        self.kernel = kernel
        self.n_builds = 0
        self.build_time = 0.0
        self.threads = None
        if kernel == "numba":
            self._nb = _import_kernels()
            self.threads = int(threads) if threads else DEFAULT_THREADS
            if not 1 <= self.threads <= self._nb.max_threads():
                raise InputError(f"packing: threads must be in 1..{self._nb.max_threads()} "
                                 f"(NUMBA_NUM_THREADS), got {threads!r}")
            # one thread: pair loop over the half list; more: per-particle gather over
            # the full list (each pair computed from both ends), parallel over particles
            self.full = self.threads > 1
            self._work = self._nb.Work(radii.shape[0])
        self._half = None

    @contextlib.contextmanager
    def threads_set(self):
        """Run the compiled kernels with ``self.threads`` numba threads inside the block."""
        if self.kernel != "numba":
            yield
            return
        old = self._nb.set_threads(self.threads)
        try:
            yield
        finally:
            self._nb.set_threads(old)

    # ------------------------------------------------------------------ build
    def build(self, X: np.ndarray) -> np.ndarray:
        """Wrap X into the box, rebuild the list; return the wrapped X."""
        t0 = time.perf_counter()
        if self.kernel == "numba":
            X, self.indptr, self.rows, self.nbr, self.hptr = self._nb.build(
                X, self.radii, self.box, self.skin, self.cut, self.full)
            self._work.chunk(self.indptr)
            self._half = None                      # i, j, S, isig built when asked for
        else:
            X = self._build_numpy(X)
        self.X0 = X.copy()
        self.n_builds += 1
        self.build_time += time.perf_counter() - t0
        return X

    def _build_numpy(self, X):
        d, n = X.shape
        L = self.box[:, None]
        X = _wrap01(X / L) * L
        tree = cKDTree(X.T, boxsize=self.box, balanced_tree=False, compact_nodes=False)
        # a hair above cut: the kept pairs are decided by the test below alone
        pairs = tree.query_pairs(self.cut * (1.0 + 1e-9), output_type="ndarray")
        i = np.ascontiguousarray(pairs[:, 0], dtype=np.int64)
        j = np.ascontiguousarray(pairs[:, 1], dtype=np.int64)
        keep = self._keep(X, i, j)
        i, j = i[keep], j[keep]
        order = np.argsort(i * n + j)              # (i, j) order; i < j from query_pairs
        i, j = i[order], j[order]
        self._set_half(X, i, j)
        p = i.shape[0]
        # B (p x n): row a has -1 at i_a and +1 at j_a (i < j: columns sorted)
        cols = np.empty(2 * p, dtype=np.int64)
        cols[0::2], cols[1::2] = i, j
        vals = np.empty(2 * p)
        vals[0::2], vals[1::2] = -1.0, 1.0
        self.B = sp.csr_matrix((vals, cols, np.arange(0, 2 * p + 1, 2)), shape=(p, n))
        self.BT = self.B.T.tocsr()
        return X

    def _keep(self, X, i, j):
        """Build-time criterion |dx|^2 < (R_i + R_j + skin)^2 (minimum image)."""
        L = self.box[:, None]
        dx = X[:, j]
        dx -= X[:, i]
        dx -= np.round(dx / L) * L
        sig = self.radii[i] + self.radii[j]
        sig += self.skin
        return np.einsum("kp,kp->p", dx, dx) < sig * sig

    def _set_half(self, X, i, j):
        L = self.box[:, None]
        dx = X[:, j] - X[:, i]
        self._half = (i, j, np.ascontiguousarray(-(np.round(dx / L) * L)),
                      1.0 / (self.radii[i] + self.radii[j]))

    def _get_half(self):
        if self._half is None:                     # numba: the upper half of the CSR list
            n = self.indptr.shape[0] - 1
            rows = np.repeat(np.arange(n, dtype=np.int64), np.diff(self.indptr))
            m = self.nbr > rows
            self._set_half(self.X0, rows[m], self.nbr[m].astype(np.int64))
        return self._half

    i = property(lambda self: self._get_half()[0])
    j = property(lambda self: self._get_half()[1])
    S = property(lambda self: self._get_half()[2])
    isig = property(lambda self: self._get_half()[3])

    # ------------------------------------------------------------------ geometry
    def max_displacement(self, X: np.ndarray) -> float:
        if self.kernel == "numba":
            return math.sqrt(self._nb.max_displacement2(X, self.X0, self._work.part1))
        dX = X - self.X0
        return float(np.sqrt(_sq_norms(dX).max()))

    def pair_vectors(self, X: np.ndarray):
        i, j, S, _ = self._get_half()
        if self.kernel == "numba":
            R = X[:, j] - X[:, i]
        else:
            R = np.empty((X.shape[0], i.shape[0]))
            for k in range(X.shape[0]):            # loop over dimensions only
                R[k] = self.B @ X[k]
        R += S
        r = np.sqrt(np.einsum("kp,kp->p", R, R))
        return R, r

    def overlaps(self, X: np.ndarray):
        """(overlap max(1 - r/sigma, 0), 1/sigma) of the listed pairs in (i, j) order."""
        if self.kernel == "numba":
            return self._nb.overlaps(X, self.radii, self.indptr, self.nbr, self.hptr, self.box)
        _, r = self.pair_vectors(X)
        ov = 1.0 - r * self.isig
        np.maximum(ov, 0.0, out=ov)
        return ov, self.isig

    # ------------------------------------------------------------------ forces
    def forces(self, X: np.ndarray, F: np.ndarray) -> np.ndarray:
        """Forces (d, N) into F; returns the per-pair overlap 1 - r/sigma clipped at 0."""
        if self.kernel == "numba":
            self.step(X, np.zeros_like(X), F, 0.0)
            return self.overlaps(X)[0]
        R, r = self.pair_vectors(X)
        ov = 1.0 - r * self.isig
        np.maximum(ov, 0.0, out=ov)
        c = ov * self.isig / r                 # F_j = +c r_ij, F_i = -c r_ij
        for k in range(X.shape[0]):
            F[k] = self.BT @ (c * R[k])
        return ov

    def step(self, X, V, F, dtp):
        """Forces into F and the FIRE reductions over particles, in the fixed block order:
        returns (F.V, |F|^2, |V + dtp F|^2, max_a |F_a|^2)."""
        if self.kernel == "numba":
            return self._nb.step(X, V, F, self.radii, self.indptr, self.rows, self.nbr, self.box,
                                 float(dtp), self.full, self._work)
        self.forces(X, F)
        fv = F[0] * V[0]
        U = V[0] + dtp * F[0]
        w = U * U
        for k in range(1, X.shape[0]):
            fv += F[k] * V[k]
            U = V[k] + dtp * F[k]
            w += U * U
        ff = _sq_norms(F)
        return _block_sum(fv), _block_sum(ff), _block_sum(w), float(ff.max())

    def update(self, X, V, F, dt, backoff, c1, beta):
        """FIRE update in place: [backoff: X -= dt/2 V; V = 0]; V += dt F;
        [beta is not None: V *= c1; V += beta F]; X += dt V.  Returns max_a |V_a|^2."""
        h = 0.5 * dt
        if self.kernel == "numba":
            mix = beta is not None
            return self._nb.update(X, V, F, dt, h, bool(backoff), mix, float(c1),
                                   float(beta) if mix else 0.0, self._work.part1)
        if backoff:
            X -= h * V
            V[:] = 0.0
        V += dt * F
        if beta is not None:
            V *= c1
            V += beta * F
        X += dt * V
        return float(_sq_norms(V).max())


def _sq_norms(A: np.ndarray) -> np.ndarray:
    """|A_a|^2 per column of A (d, N), summed over k in order (as the compiled kernel)."""
    t = A[0] * A[0]
    for k in range(1, A.shape[0]):
        t += A[k] * A[k]
    return t


def _import_kernels():
    import warnings
    with warnings.catch_warnings():          # llvmlite's import-time DeprecationWarning
        warnings.simplefilter("ignore", DeprecationWarning)
        from . import packing_numba
    return packing_numba


# --------------------------------------------------------------------------- FIRE

def fire_minimize(X, pl: _PairList, ftol: float, *, params: FireParams | None = None,
                  max_iter: int = 2_000_000, trace: list | None = None,
                  trace_every: int = 100):
    """Minimise the harmonic energy from (d, N) positions X with FIRE.

    Stops when max_i |F_i| < max(ftol * <f_c>, force_floor(box)) (<f_c>: mean contact
    force over overlapping pairs), or when no pair overlaps (F = 0 exactly: an unjammed
    state).  Returns (X, info) with info = dict(iterations, max_force, force_scale,
    converged).  ``trace``, if given, receives (iteration, max|F|, <f_c>) every
    ``trace_every`` steps.

    One iteration is two passes over the particles: pl.step (forces, P = F.v, |F|,
    |v + dt F| for the dt that P > 0 would give, max|F_a|) and pl.update (velocity mixing,
    position update, max|v_a|).  The list is rebuilt when the running bound
    sum dt max_a|v_a| on the displacement, then the exact displacement, exceeds skin/2.
    """
    with pl.threads_set():
        return _fire(X, pl, ftol, params or FireParams(), max_iter, trace, trace_every)


def _fire(X, pl, ftol, p, max_iter, trace, trace_every):
    X = pl.build(X)
    F = np.empty_like(X)
    V = np.zeros_like(X)
    dt, alpha, n_pos = p.dt0, p.alpha0, 0
    bound = 0.0                                   # running bound on the displacement
    half_skin = 0.5 * pl.skin
    floor = force_floor(pl.box)
    dt_plus = min(dt * p.f_inc, p.dt_max) if n_pos + 1 > p.n_min else dt
    power, ff, w, ffmax = pl.step(X, V, F, dt_plus)
    fscale = _force_scale(*pl.overlaps(X))
    it = 0
    converged = False
    while True:
        if not math.isfinite(ff):
            raise RuntimeError(f"packing: non-finite forces at FIRE iteration {it} "
                               "(coincident particles?)")
        fmax = math.sqrt(ffmax)
        if trace is not None and it % trace_every == 0:
            trace.append((it, fmax, fscale))
        if it % 200 == 0 or fmax < max(ftol * fscale, floor):
            fscale = _force_scale(*pl.overlaps(X))
            if fmax < max(ftol * fscale, floor) or fscale == 0.0:
                converged = True
                break
        if it >= max_iter:
            break
        fnorm = math.sqrt(ff)
        if power > 0.0:
            n_pos += 1
            if n_pos > p.n_min:
                dt = min(dt * p.f_inc, p.dt_max)
                alpha *= p.f_alpha
            vnorm = math.sqrt(w)                  # |v + dt F|: dt == dt_plus here
            backoff = False
        else:
            n_pos = 0
            dt *= p.f_dec
            alpha = p.alpha0
            vnorm = dt * fnorm                    # v = 0 + dt F after the back-off
            backoff = True                        # FIRE 2.0: X -= dt/2 v, v = 0
        beta = alpha * vnorm / fnorm if fnorm > 0.0 else None
        vmax2 = pl.update(X, V, F, dt, backoff, 1.0 - alpha, beta)
        bound += dt * math.sqrt(vmax2)
        it += 1
        if bound > half_skin:
            disp = pl.max_displacement(X)
            if disp > half_skin:
                X = pl.build(X)
                disp = 0.0
            bound = disp
        dt_plus = min(dt * p.f_inc, p.dt_max) if n_pos + 1 > p.n_min else dt
        power, ff, w, ffmax = pl.step(X, V, F, dt_plus)
    return X, dict(iterations=it, max_force=math.sqrt(ffmax), force_scale=fscale,
                   converged=converged)


def force_floor(box) -> float:
    """Round-off floor of max|F|: coordinates of size L carry absolute errors ~eps L, so
    forces (stiffness <= 1) cannot be resolved below ~eps L.  Measured floor at L = 70:
    4e-14; we use 16 eps L (2.5e-13 at L = 70, 4e-12 at N = 10^6)."""
    return 16.0 * np.finfo(float).eps * float(np.max(box))


def _force_scale(ov: np.ndarray, isig: np.ndarray) -> float:
    """Mean contact-force magnitude (1 - r/sigma)/sigma over overlapping pairs."""
    m = ov > 0.0
    k = int(np.count_nonzero(m))
    return float((ov[m] * isig[m]).sum() / k) if k else 0.0


# --------------------------------------------------------------------------- contacts

def remove_rattlers(n: int, i: np.ndarray, j: np.ndarray, d: int):
    """Iteratively drop particles with fewer than d + 1 contacts.

    Returns (rattler mask (n,), kept-contact mask (len(i),)).  Each sweep is vectorised;
    the number of sweeps is the depth of the rattler cascade (a handful)."""
    keep = np.ones(i.shape[0], dtype=bool)
    rattler = np.zeros(n, dtype=bool)
    while True:
        deg = np.bincount(i[keep], minlength=n) + np.bincount(j[keep], minlength=n)
        new = (deg < d + 1) & ~rattler
        if not new.any():
            return rattler, keep
        rattler |= new
        keep &= ~(rattler[i] | rattler[j])


def _contacts(X, pl: _PairList):
    """Overlapping pairs of the current list: i, j, pair vectors (d, Nc), overlap."""
    R, r = pl.pair_vectors(X)
    ov = 1.0 - r * pl.isig
    m = ov > 0.0
    return pl.i[m], pl.j[m], R[:, m], ov[m], pl.isig[m]


# --------------------------------------------------------------------------- driver

def _check_inputs(n, phi, d, pressure, ftol, skin):
    if not isinstance(d, (int, np.integer)) or d < 2:
        raise InputError(f"packing: d must be an integer >= 2, got {d!r}")
    if not isinstance(n, (int, np.integer)) or n < 2 * (d + 1):
        raise InputError(f"packing: N = {n!r} particles is too small: use N >= {2 * (d + 1)}")
    if phi is not None and not (0.0 < phi < 1.0):
        raise InputError(f"packing: phi must be in (0, 1), got {phi!r}")
    if pressure is not None and not (pressure > 0.0 and math.isfinite(pressure)):
        raise InputError(f"packing: target pressure must be finite and > 0, got {pressure!r}")
    if not (ftol > 0.0):
        raise InputError(f"packing: ftol must be > 0, got {ftol!r}")
    if not (0.0 < skin <= 1.0):
        raise InputError(f"packing: skin must be in (0, 1] (units of the small diameter), got {skin!r}")


def _phi_j(d: int) -> float:
    return PHI_J.get(d, PHI_J[3])


def make_packing(n: int, phi: float | None = None, *, d: int = 2, seed: int = 0,
                 pressure: float | None = None, ftol: float = DEFAULT_FTOL,
                 skin: float = 0.4, max_iter: int = 2_000_000,
                 pressure_rtol: float = 0.02, fire: FireParams | None = None,
                 trace: list | None = None, kernel: str = "auto",
                 threads: int | None = None) -> Packing:
    """Jammed packing of ``n`` soft discs (d = 2) or spheres at packing fraction ``phi``.

    Protocol: uniform random positions (numpy Generator seeded with ``seed``; the same
    seed gives a bit-identical packing on the same machine) at ``phi``, then FIRE to
    max|F| < ftol * <f_c>, then iterative rattler removal.

    If ``pressure`` is given, phi is adjusted (affine rescaling + re-minimisation, secant
    steps on p(phi), which is linear near jamming for harmonic discs) until the virial
    pressure is within ``pressure_rtol`` of the target; ``phi`` is then only the first
    guess (default: phi_J + 2 p, from p ~ 0.5 (phi - phi_J) measured in 2D).

    ``kernel``: "numpy" (always available), "numba" (compiled cell list and FIRE passes,
    needs python3-numba) or "auto" (numba if installed).  ``threads``: numba threads
    (default DEFAULT_THREADS = 1; at most NUMBA_NUM_THREADS).  Both kernels, with any
    thread count, do the same floating-point operations in the same order, so they give
    bit-identical forces and hence the same packing for a given seed (tested);
    info["kernel"] and info["threads"] record what ran.

    Raises InputError if the minimised state has no contacts (phi below jamming).
    """
    _check_inputs(n, phi, d, pressure, ftol, skin)
    phi_j = _phi_j(d)
    if phi is None:
        if pressure is None:
            raise InputError("packing: give phi (packing fraction) or pressure")
        phi = min(phi_j + 2.0 * pressure, 0.95)
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    radii = binary_radii(n)
    L = box_side(radii, phi, d)
    box = np.full(d, L)
    s = rng.random((n, d))
    order = morton_order(s)
    # random 50:50 labelling, then spatial (Morton) order: the labels stay random in space
    radii = radii[rng.permutation(n)]
    s = s[order]
    radii = radii[order]
    if box.min() <= 2.0 * (2.0 * radii.max() + 2.0 * skin):
        raise InputError(
            f"packing: N = {n} gives a box of side {L:.3g}, not larger than twice the "
            f"interaction range plus skin {2.0 * radii.max() + 2.0 * skin:.3g}: use a larger N")
    pl = _PairList(radii, box, skin, kernel, threads)
    X = np.ascontiguousarray((s * box).T)
    X, info = fire_minimize(X, pl, ftol, params=fire, max_iter=max_iter, trace=trace)
    iterations = info["iterations"]
    stages = [dict(phi=phi, iterations=info["iterations"])]
    if not info["converged"]:
        raise RuntimeError(f"packing: FIRE did not converge in {max_iter} iterations "
                           f"(max|F| = {info['max_force']:.3g}, <f_c> = {info['force_scale']:.3g})")
    if pressure is not None:
        X, pl, box, phi, info, more = _to_pressure(X, pl, radii, box, phi, pressure,
                                                   pressure_rtol, ftol, fire, max_iter, d)
        iterations += sum(st["iterations"] for st in more)
        stages += more
    return _finish(X, pl, radii, box, phi, seed, ftol, iterations, info,
                   dict(stages=stages, n_builds=pl.n_builds, build_time=pl.build_time,
                        wall_time=time.perf_counter() - t0, skin=skin, kernel=pl.kernel,
                        threads=pl.threads))


def _pressure(X, pl: _PairList, d: int) -> float:
    _, _, R, ov, isig = _contacts(X, pl)
    r = np.sqrt(np.einsum("kp,kp->p", R, R))
    return float((ov * isig * r).sum() / (d * np.prod(pl.box)))


def _to_pressure(X, pl, radii, box, phi, target, rtol, ftol, fire, max_iter, d):
    """Secant iteration on phi for p(phi) = target, re-minimising after each rescale."""
    stages = []
    phi_j = _phi_j(d)
    p = _pressure(X, pl, d)
    hist = [(phi, p)]
    info = None
    for _ in range(40):
        if p > 0 and abs(p / target - 1.0) < rtol:
            break
        pts = [h for h in hist if h[1] > 0]
        if len(pts) >= 2:
            (f1, p1), (f2, p2) = pts[-2], pts[-1]
            slope = (p2 - p1) / (f2 - f1) if f2 != f1 else 0.5
            if not slope > 0:
                slope = 0.5
            new = f2 + (target - p2) / slope
        elif pts:
            f2, p2 = pts[-1]
            new = f2 + (target - p2) / 0.5
        else:                       # unjammed: compress
            new = phi + max(0.005, 0.5 * (phi_j - phi) + 2 * target)
        new = float(np.clip(new, phi - 0.05, phi + 0.05))
        new = min(new, 0.99)
        scale = (phi / new) ** (1.0 / d)
        box = box * scale
        X = X * scale
        radii_pl = _PairList(radii, box, pl.skin, pl.kernel, pl.threads)
        radii_pl.n_builds, radii_pl.build_time = pl.n_builds, pl.build_time
        pl = radii_pl
        phi = new
        X, info = fire_minimize(X, pl, ftol, params=fire, max_iter=max_iter)
        if not info["converged"]:
            raise RuntimeError("packing: FIRE did not converge while adjusting the pressure")
        p = _pressure(X, pl, d)
        hist.append((phi, p))
        stages.append(dict(phi=phi, pressure=p, iterations=info["iterations"]))
    else:
        raise RuntimeError(f"packing: pressure {target:g} not reached in 40 rescalings "
                           f"(last phi = {phi:.6f}, p = {p:.4g})")
    if info is None:
        _, info = X, dict(iterations=0, max_force=np.nan, force_scale=np.nan, converged=True)
        F = np.empty_like(X)
        ov = pl.forces(X, F)
        info["max_force"] = float(np.sqrt(np.einsum("kn,kn->n", F, F).max()))
        info["force_scale"] = _force_scale(ov, pl.isig)
    return X, pl, box, phi, info, stages


def _finish(X, pl, radii, box, phi, seed, ftol, iterations, info, extra) -> Packing:
    d, n = X.shape
    L = box[:, None]
    s = _wrap01(X / L)                            # (d, N) reduced
    i, j, R, ov, isig = _contacts(X, pl)
    if i.shape[0] == 0:
        raise InputError(
            f"packing at phi={phi:.4f} has no contacts after minimisation; phi_J ≈ "
            f"{_phi_j(d)} for this mixture: use phi > {_phi_j(d) + 0.01:.3f} "
            f"(z0 ≈ 4.4-5 needs phi ≈ 0.86-0.90 in 2D)")
    r = np.sqrt(np.einsum("kp,kp->p", R, R))
    fc = ov * isig
    pressure = float((fc * r).sum() / (d * np.prod(box)))
    energy = 0.5 * float(np.dot(ov, ov))
    rattler, keep = remove_rattlers(n, i, j, d)
    if rattler.all():
        raise InputError(
            f"packing at phi={phi:.4f} has no rigid (non-rattler) contact network after "
            f"minimisation; phi_J ≈ {_phi_j(d)} for this mixture: use phi > "
            f"{_phi_j(d) + 0.01:.3f}")
    ci, cj, Rk = i[keep], j[keep], R[:, keep]
    # integer image shifts for the wrapped reduced coordinates
    shift = np.round(Rk / L - (s[:, cj] - s[:, ci])).astype(np.int64).T
    n_nr = int(n - rattler.sum())
    F = np.empty_like(X)
    pl.forces(X, F)
    weak = int(np.count_nonzero(fc[keep] < 100.0 * info["max_force"]))
    extra = dict(extra)
    extra.update(weak_contacts=weak, n_rattlers=int(rattler.sum()),
                 energy_per_particle=energy / n)
    return Packing(
        positions=np.ascontiguousarray((s * L).T), radii=radii, box=np.asarray(box, float),
        contacts_i=ci, contacts_j=cj, contacts_shift=shift, rattler=rattler,
        pressure=pressure, z=2.0 * ci.shape[0] / n_nr, phi=float(phi), energy=energy,
        max_force=info["max_force"], force_scale=info["force_scale"], iterations=int(iterations),
        seed=int(seed), ftol=float(ftol), info=extra)
