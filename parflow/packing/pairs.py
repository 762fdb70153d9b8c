"""Verlet pair lists and force kernels of the FIRE packing generator (``packing.fire``).

A pair list holds the pairs (i < j) of particles closer than R_i + R_j + skin at its last
build, sorted by (i, j), and computes from positions X (d, N) -- unwrapped between rebuilds
-- the harmonic forces F_j = +c r_ij, F_i = -c r_ij, c = max(1 - r/sigma, 0) / (sigma r),
sigma = R_i + R_j, and the vector work of a FIRE iteration.  The image of a pair is fixed
at build time (r_ij = X_j - X_i + S_ij); it stays the minimum image while particles move
less than skin/2, which the caller checks (``max_displacement``).

Two kernels, one class each, with the same interface (``PairList``):

* ``NumpyPairs`` (always available): cKDTree candidates (periodic ``boxsize``), then a
  sparse incidence matrix B (+1 at j, -1 at i): pair vectors B @ x + S, forces B^T @ (c r).
* ``NumbaPairs`` (``pairs_numba``; optional, Debian python3-numba): a periodic cell list,
  and each FIRE iteration in two compiled passes over the particles -- forces fused with
  the reductions P = F.v, |F|, |v + dt F|, max|F_i|, then the velocity mixing, position
  update and max|v_i| in one loop.  With one thread (the default) the force pass is a pair
  loop over the half list; with ``threads`` > 1 a per-particle gather over the full list,
  parallel over particles (each pair computed from both ends).

Both list the same pairs, sum the force on each particle over its neighbours in ascending
index order with the same floating-point terms, and sum the reductions in a fixed order
(blocks of BLOCK particles, then the blocks in order: ``block_sum``), so the two kernels
and any thread count give bit-identical forces and packings for a given seed (tested).
``pair_list(kernel=...)`` picks the class.

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
"""
from __future__ import annotations

import contextlib
import importlib.util
import time
import warnings

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from ..errors import InputError

KERNELS = ("numpy", "numba")
#: numba threads of the compiled kernel unless told otherwise (see the module docstring).
DEFAULT_THREADS = 1
#: Particles per reduction block: F.v, |F|^2, |v|^2 are summed in index order within
#: blocks of this size, then over the blocks in order (pairs_numba.BLOCK is the same).
BLOCK = 4096


def have_numba() -> bool:
    """Whether the optional compiled kernel can be used (Debian: python3-numba)."""
    return importlib.util.find_spec("numba") is not None


def wrap01(s: np.ndarray) -> np.ndarray:
    """s - floor(s) in [0, 1) (a new array): reduced coordinates wrapped into the box."""
    s = s - np.floor(s)
    s[s >= 1.0] = 0.0          # floor(-tiny) + ... can round up to exactly 1
    return s


def block_sum(t: np.ndarray) -> float:
    """Sum of t (n,) in the fixed order of the compiled kernel: each block of BLOCK
    entries in index order, then the block sums in order (cumsum is sequential)."""
    n = t.shape[0]
    nb = -(-n // BLOCK)
    buf = np.zeros(nb * BLOCK)
    buf[:n] = t
    part = 0.0 + np.cumsum(buf.reshape(nb, BLOCK), axis=1)[:, -1]
    return float(0.0 + np.cumsum(part)[-1])


def sq_norms(A: np.ndarray) -> np.ndarray:
    """|A_a|^2 per column of A (d, N), summed over k in order (as the compiled kernel)."""
    t = A[0] * A[0]
    for k in range(1, A.shape[0]):
        t += A[k] * A[k]
    return t


def numba_fits(radii: np.ndarray, box, skin: float) -> bool:
    """Whether the box is large enough for the compiled kernel, which re-takes the minimum
    image at every step: it needs |r_ij| < cut + skin < L/2 for every listed pair."""
    cut = 2.0 * float(radii.max()) + float(skin)
    return not np.asarray(box, dtype=float).min() <= 2.0 * (cut + float(skin))


def pair_list(radii: np.ndarray, box, skin: float, kernel: str = "auto",
              threads: int | None = None) -> PairList:
    """The pair list of ``kernel``: "numpy", "numba", or "auto" (numba if installed and
    the box is large enough for it, else numpy).  ``threads``: numba threads (default
    DEFAULT_THREADS; ignored by the numpy kernel)."""
    asked = kernel
    if kernel == "auto":
        kernel = "numba" if have_numba() else "numpy"
    if kernel not in KERNELS:
        raise InputError(f"packing: kernel must be 'auto' or one of {KERNELS}, got {kernel!r}")
    if kernel == "numba" and not have_numba():
        raise InputError("packing: kernel='numba' needs numba (Debian: apt-get install "
                         "python3-numba); use kernel='numpy'")
    if kernel == "numba" and (asked == "numba" or numba_fits(radii, box, skin)):
        return numba_kernels().NumbaPairs(radii, box, skin, threads)
    return NumpyPairs(radii, box, skin)


def numba_kernels():
    """The module of the compiled kernel, imported at first use: numba is optional, and
    importing it (llvmlite) costs ~0.5 s that the numpy kernel should not pay."""
    with warnings.catch_warnings():          # llvmlite's import-time DeprecationWarning
        warnings.simplefilter("ignore", DeprecationWarning)
        from . import pairs_numba            # (numba: optional, ~0.5 s to import)
    return pairs_numba


class PairList:
    """Interface of a Verlet pair list and its force kernel (module docstring).

    Attributes: radii (N,), box (d,), skin, cut = 2 max R + skin, kernel ("numpy" or
    "numba"), threads (None for numpy), n_builds, build_time, X0 (positions at the last
    build); i, j, S, isig: the listed pairs i < j in (i, j) order, their build-time image
    shifts (d, p) and 1/sigma."""

    kernel = ""

    def __init__(self, radii: np.ndarray, box, skin: float):
        self.radii = radii
        self.box = np.asarray(box, dtype=float)
        self.skin = float(skin)
        self.cut = 2.0 * float(radii.max()) + self.skin
        self.threads = None
        self.n_builds = 0
        self.build_time = 0.0
        self._half = None

    def threads_set(self):
        """Context in which the kernel runs with its thread count (no-op without threads)."""
        return contextlib.nullcontext()

    def build(self, X: np.ndarray) -> np.ndarray:
        """Wrap X into the box, rebuild the list; return the wrapped X."""
        t0 = time.perf_counter()
        X = self._build(X)
        self.X0 = X.copy()
        self.n_builds += 1
        self.build_time += time.perf_counter() - t0
        return X

    def _build(self, X: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def _set_half(self, X, i, j):
        L = self.box[:, None]
        dx = X[:, j] - X[:, i]
        self._half = (i, j, np.ascontiguousarray(-(np.round(dx / L) * L)),
                      1.0 / (self.radii[i] + self.radii[j]))

    def _get_half(self):
        return self._half

    i = property(lambda self: self._get_half()[0])
    j = property(lambda self: self._get_half()[1])
    S = property(lambda self: self._get_half()[2])
    isig = property(lambda self: self._get_half()[3])

    def max_displacement(self, X: np.ndarray) -> float:
        """max_a |X_a - X0_a| since the last build."""
        raise NotImplementedError

    def pair_vectors(self, X: np.ndarray):
        """(R (d, p), |R| (p,)): pair vectors r_ij = X_j - X_i + S_ij of the listed pairs."""
        raise NotImplementedError

    def overlaps(self, X: np.ndarray):
        """(overlap max(1 - r/sigma, 0), 1/sigma) of the listed pairs in (i, j) order."""
        raise NotImplementedError

    def forces(self, X: np.ndarray, F: np.ndarray) -> np.ndarray:
        """Forces (d, N) into F; returns the per-pair overlap 1 - r/sigma clipped at 0."""
        raise NotImplementedError

    def step(self, X, V, F, dtp):
        """Forces into F and the FIRE reductions over particles, in the fixed block order:
        returns (F.V, |F|^2, |V + dtp F|^2, max_a |F_a|^2)."""
        raise NotImplementedError

    def update(self, X, V, F, dt, backoff, c1, beta):
        """FIRE update in place: [backoff: X -= dt/2 V; V = 0]; V += dt F;
        [beta is not None: V *= c1; V += beta F]; X += dt V.  Returns max_a |V_a|^2."""
        raise NotImplementedError


class NumpyPairs(PairList):
    """The numpy kernel: cKDTree candidates, sparse incidence matrix B (+1 at j, -1 at i),
    pair vectors B @ x + S, forces B^T @ (c r)."""

    kernel = "numpy"

    def _build(self, X):
        d, n = X.shape
        L = self.box[:, None]
        X = wrap01(X / L) * L
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

    def max_displacement(self, X):
        dX = X - self.X0
        return float(np.sqrt(sq_norms(dX).max()))

    def pair_vectors(self, X):
        i, j, S, _ = self._get_half()
        R = np.empty((X.shape[0], i.shape[0]))
        for k in range(X.shape[0]):                # loop over dimensions only
            R[k] = self.B @ X[k]
        R += S
        r = np.sqrt(np.einsum("kp,kp->p", R, R))
        return R, r

    def overlaps(self, X):
        _, r = self.pair_vectors(X)
        ov = 1.0 - r * self.isig
        np.maximum(ov, 0.0, out=ov)
        return ov, self.isig

    def forces(self, X, F):
        R, r = self.pair_vectors(X)
        ov = 1.0 - r * self.isig
        np.maximum(ov, 0.0, out=ov)
        c = ov * self.isig / r                 # F_j = +c r_ij, F_i = -c r_ij
        for k in range(X.shape[0]):
            F[k] = self.BT @ (c * R[k])
        return ov

    def step(self, X, V, F, dtp):
        self.forces(X, F)
        fv = F[0] * V[0]
        U = V[0] + dtp * F[0]
        w = U * U
        for k in range(1, X.shape[0]):
            fv += F[k] * V[k]
            U = V[k] + dtp * F[k]
            w += U * U
        ff = sq_norms(F)
        return block_sum(fv), block_sum(ff), block_sum(w), float(ff.max())

    def update(self, X, V, F, dt, backoff, c1, beta):
        h = 0.5 * dt
        if backoff:
            X -= h * V
            V[:] = 0.0
        V += dt * F
        if beta is not None:
            V *= c1
            V += beta * F
        X += dt * V
        return float(sq_norms(V).max())
