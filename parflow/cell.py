"""Periodic cell, flows and pair geometry (DESIGN §2).

The cell follows the flow, dh/dgamma = E h, so h(gamma) = expm(gamma E) h0.
For simple shear E = [[0, 1], [0, 0]] this is Lees-Edwards, h = [[Lx, gamma Ly], [0, Ly]];
for planar extension E = diag(1, -1).  det h is constant (tr E = 0).
"""
from __future__ import annotations

import numpy as np
from scipy.linalg import expm

from .state import InputError

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


def min_image(dr_reduced: np.ndarray) -> np.ndarray:
    """Minimum image of reduced displacement vectors (valid for |tilt| <= L/2 cells)."""
    return dr_reduced - np.rint(dr_reduced)
