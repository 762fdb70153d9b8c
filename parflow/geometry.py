"""Geometry of the periodic cell: flows, the cell h(gamma), pair vectors, the Lees-Edwards
remap, minimum images and the contact neighbour search (DESIGN §2).  numpy/scipy only,
every rank computes the same thing; any dimension d >= 2.

* The cell follows the flow, dh/dgamma = E h, so h(gamma) = expm(gamma E) h0.  For simple
  shear E = [[0, 1], [0, 0]] this is Lees-Edwards, h = [[Lx, gamma Ly], [0, Ly]]; for planar
  extension E = diag(1, -1).  det h is constant (tr E = 0).
* Bonded pairs: r_ij = h (s_j + n - s_i) with a persistent image shift n (no image search).
* The remap: h_r = h U with U unimodular, each column of h size-reduced against the earlier
  ones (for simple shear: the tilt brought into [-Lx/2, Lx/2]).  Reduced displacements in
  h_r minus rint, times h_r, are true minimum images up to half the smallest cell height.
* Contacts: ``find_candidates`` -- every pair with gap < skin, by a periodic cKDTree in the
  orthogonal frame of the remapped cell, filtered by true minimum-image distances.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.linalg import expm
from scipy.spatial import cKDTree

from .errors import InputError

FLOWS = ("shear", "extension")


def velocity_gradient(flow: str, d: int) -> np.ndarray:
    """E for ``flow`` in ``d`` dimensions: V_f(r) = E r (per unit strain)."""
    if d < 2:
        raise InputError(f"dimension d must be >= 2, got {d}")
    E = np.zeros((d, d))
    if flow == "shear":
        E[0, 1] = 1.0                       # V_f = (y, 0, ...)
    elif flow == "extension":
        E[0, 0], E[1, 1] = 1.0, -1.0        # V_f = (x, -y, 0 ...)
    else:
        raise InputError(f"flow must be one of {FLOWS}, got {flow!r}")
    return E


def cell_at(h0: np.ndarray, E: np.ndarray, gamma: float) -> np.ndarray:
    """h(gamma) = expm(gamma E) h0 (exact for both flows: E is nilpotent or diagonal)."""
    if not np.any(np.diag(np.diag(E)) - E):          # diagonal E
        return np.exp(gamma * np.diag(E))[:, None] * h0
    if not np.any(E @ E):                             # nilpotent of order 2 (shear)
        return h0 + gamma * (E @ h0)
    return expm(gamma * E) @ h0


def pair_vectors(s: np.ndarray, h: np.ndarray, i: np.ndarray, j: np.ndarray,
                 shift: np.ndarray) -> np.ndarray:
    """r_ij = h (s_j + n - s_i), shape (Nb, d).  Computed component by component
    (1-D gathers are much faster than row gathers of an (N, d) array)."""
    d = s.shape[1]
    sT = s.T
    ds = [sT[c][j] - sT[c][i] + shift[:, c] for c in range(d)]
    r = np.empty((i.shape[0], d))
    for a in range(d):
        acc = h[a, 0] * ds[0]
        for b in range(1, d):
            if h[a, b] != 0.0:
                acc += h[a, b] * ds[b]
        r[:, a] = acc
    return r


def pair_geometry(s, h, E, i, j, shift):
    """Pair vectors, lengths, unit vectors n_alpha and affine rates b_alpha = n_alpha . E r_alpha.

    b_alpha is (S V_f)_alpha, the rate of change of the pair length in the affine flow; it is
    computed from r_alpha, never by differencing V_f of raw positions across the boundary.
    """
    r = pair_vectors(s, h, i, j, shift)
    ell = np.sqrt(np.einsum("ad,ad->a", r, r))
    if np.any(ell == 0.0):
        raise InputError("two bonded nodes coincide: the pair direction is undefined")
    n = r / ell[:, None]
    b = np.einsum("ad,ad->a", n, r @ E.T)
    return r, ell, n, b


def rigidity_csr(n_unit: np.ndarray, i: np.ndarray, j: np.ndarray, n_nodes: int) -> sp.csr_matrix:
    """The rigidity matrix S (Nc x d N) as a scipy CSR matrix -- the one serial S of the code
    (``operators.RigidityOperators`` is its distributed PETSc twin): row alpha has -n_alpha
    at node i and +n_alpha at node j, so (S V)_alpha = n_alpha . (V_j - V_i) is the rate of
    change of the pair's length and (S^T tau)_k the net pair force on node k (DESIGN §2)."""
    nc, d = n_unit.shape
    rows = np.repeat(np.arange(nc), 2 * d)
    comp = np.arange(d)
    cols = np.concatenate([d * i[:, None] + comp, d * j[:, None] + comp], axis=1).ravel()
    vals = np.concatenate([-n_unit, n_unit], axis=1).ravel()
    return sp.csr_matrix((vals, (rows, cols)), shape=(nc, d * n_nodes))


# =========================================================================== remap, minimum image

def _size_reduction(h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """h_r = h U and the unimodular integer U: each column of h size-reduced against the
    earlier ones, from the last pair back (upper-triangular h: |h_r[m, k]| <= h[m, m] / 2
    for m < k)."""
    hr = np.array(h, dtype=float)
    d = hr.shape[0]
    U = np.eye(d)
    for k in range(1, d):                       # loops over dimensions only
        for m in range(k - 1, -1, -1):
            q = np.rint(hr[m, k] / hr[m, m])
            hr[:, k] -= q * hr[:, m]
            U[:, k] -= q * U[:, m]
    return hr, U


def remapped_cell(h: np.ndarray) -> np.ndarray:
    """h_r = h U (U unimodular): the cell with every column size-reduced against the
    earlier ones.  For simple shear this is the Lees-Edwards remapping of the tilt into
    [-Lx/2, Lx/2]."""
    return _size_reduction(h)[0]


def remap(h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(h U, U) with U the unimodular integer matrix of :func:`remapped_cell`; h U is
    computed by the product (the contact search's frame), equal to remapped_cell(h) up to
    the last bit."""
    U = _size_reduction(h)[1]
    return h @ U, U


def min_image_radius(h: np.ndarray) -> float:
    """Half the smallest distance between opposite faces of the (remapped) cell: below it,
    the reduced rint convention gives the true minimum image."""
    hr = remapped_cell(h)
    vol = abs(np.linalg.det(hr))
    inv = np.linalg.inv(hr)
    # height along column k = vol / |face normal| = 1 / |row k of h^-1|
    return 0.5 * float(np.min(1.0 / np.linalg.norm(inv, axis=1))) if vol > 0 else 0.0


class MinImage:
    """Minimum-image displacements in a (sheared) periodic cell h.

    Positions are given as reduced coordinates of h (unwrapped, any integers); they are
    expressed in the remapped cell h_r, displacements are reduced by rint there, and
    mapped back to real space with h_r."""

    def __init__(self, h: np.ndarray):
        self.h = np.asarray(h, dtype=float)
        self.hr = remapped_cell(self.h)
        self.to_r = np.linalg.solve(self.hr, self.h)       # s_r = h_r^-1 h s
        self.rmax = min_image_radius(self.h)

    def reduced(self, s: np.ndarray) -> np.ndarray:
        """(n, d) reduced coordinates in h_r, wrapped into [0, 1)."""
        sr = s @ self.to_r.T
        return sr - np.floor(sr)

    def vectors(self, dsr: np.ndarray) -> np.ndarray:
        """Real minimum-image vectors from reduced (h_r) displacements (..., d)."""
        dsr = dsr - np.rint(dsr)
        return dsr @ self.hr.T


# =========================================================================== contact candidates

@dataclass
class Candidates:
    """Candidate pairs (i < j) and their geometry in the current cell."""

    i: np.ndarray
    j: np.ndarray
    shift: np.ndarray      # (Nc, d) integer image shifts in the state's frame: r = h (s_j + n - s_i)
    r: np.ndarray          # (Nc, d)
    dist: np.ndarray
    n: np.ndarray          # unit vectors
    gap: np.ndarray        # |r| - (R_i + R_j)
    b: np.ndarray          # n . E r

    def __len__(self):
        return int(self.i.shape[0])


def find_candidates(s, radii, h, E, skin: float) -> Candidates:
    """All pairs with gap < ``skin`` (minimum image in the remapped cell), in any d.  The
    tree works in the orthogonal frame diag(L) h_r^-1 of the remapped cell (L: its
    diagonal) and searches within the cut times that frame's distortion."""
    hr, U = remap(h)
    Uinv = np.linalg.inv(U)
    sr = s @ Uinv.T                           # reduced coordinates in the remapped cell
    off = np.floor(sr)
    sr = sr - off
    sr[sr >= 1.0] = 0.0
    L = np.diag(hr).copy()
    A = np.diag(L) @ np.linalg.inv(hr)     # real space -> orthogonal reference frame
    stretch = float(np.linalg.norm(A, 2))
    cut = 2.0 * float(radii.max()) + skin
    if cut * stretch >= 0.5 * float(L.min()):
        raise InputError(f"suspension: the box ({' x '.join(f'{x:.3g}' for x in L)}) is too small "
                         f"for the neighbour search (cut {cut:.3g}); use more discs or a smaller skin")
    X = sr * L
    tree = cKDTree(X, boxsize=L)
    pairs = tree.query_pairs(cut * stretch * (1 + 1e-12), output_type="ndarray")
    i, j = pairs[:, 0].astype(np.int64), pairs[:, 1].astype(np.int64)
    sw = np.where(i > j)                       # i < j
    i[sw], j[sw] = j[sw], i[sw]
    ds = sr[j] - sr[i]
    nr = -np.rint(ds)
    r = (ds + nr) @ hr.T
    dist = np.sqrt(np.einsum("ad,ad->a", r, r))
    gap = dist - radii[i] - radii[j]
    keep = gap < skin
    i, j, nr, r, dist, gap = i[keep], j[keep], nr[keep], r[keep], dist[keep], gap[keep]
    order = np.lexsort((j, i))
    i, j, nr, r, dist, gap = i[order], j[order], nr[order], r[order], dist[order], gap[order]
    # shift in the state's frame: s_j + n - s_i = U (sr_j + nr - sr_i) with sr = U^-1 s - off
    shift = np.rint((nr + off[i] - off[j]) @ U.T).astype(np.int64)
    n = r / dist[:, None]
    b = np.einsum("ad,ad->a", n, r @ E.T)
    return Candidates(i, j, shift, r, dist, n, gap, b)
