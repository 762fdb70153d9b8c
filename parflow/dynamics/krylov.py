"""GMRES on replicated numpy vectors (the stage equations of the linearly implicit step).

Every rank holds the whole vector and applies the same operator (whose solves with N are
collective), so every rank computes the same numbers in the same order: the iteration is
deterministic and rank-count independent to the round-off of the operator.

    gmres(A, b, rtol, max_it, space=None, keep_space=False, seed=None)
        -> KrylovResult(x, iterations, residual, converged, ritz, space)
    shifted_space(space, t) -> the Arnoldi relation of I - t (I - A), a ``seed``

Arnoldi with modified Gram-Schmidt, Givens rotations on the Hessenberg matrix, no restart
(the stage equations converge in tens of iterations), x0 = 0; converged when the
recursively updated residual |b - A x| <= rtol |b|.  The true residual of the returned x
is not recomputed (one more operator application): the caller's error control sees the
effect of an inexact stage through its own estimate.

A second system with the same operator can start from the first one's Krylov space
(``space=`` the first result's ``space``, returned with ``keep_space``: its orthonormal basis
Q and Hessenberg matrix H with A Q[:m] = Q[:m+1] H, by construction): x0 = Q[:m] y with y
minimising |b - Q H y| (no product with A), then GMRES on the residual to the same
|b - A x| <= rtol |b|; ``iterations`` counts the new products only, and ``keep_space``
returns the residual system's space (of the same A).  ROS2's two stage equations share W
(integrator.krylov_recycle).

The same system with a shifted operator -- ROS2's stage 1 retried at a shorter step after a
rejection, W' = I - c' L against W = I - c L -- has the same Krylov space: ``seed=`` the
rescaled Arnoldi relation of the first (``shifted_space``) stands for the first iterations
of a fresh GMRES, which goes on with products only beyond them.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class KrylovResult:
    x: np.ndarray
    iterations: int
    residual: float      # |b - A x| / |b| (the recursive estimate)
    converged: bool
    ritz: np.ndarray = None   # eigenvalues of the Hessenberg matrix (complex)
    space: tuple = None       # keep_space: (Q (m+1, n), H (m+1, m)) with A Q[:m] = Q[:m+1] H


def _recycled(space, b: np.ndarray):
    """x0 in span Q[:m] minimising |b - A x0| through A Q[:m] = Q[:m+1] H; (x0, b - A x0)."""
    Q, H = space
    y = np.linalg.lstsq(H, Q @ b, rcond=None)[0]
    return y @ Q[:-1], b - (H @ y) @ Q


def shifted_space(space: tuple, t: float) -> tuple:
    """The Arnoldi relation of A' = I - t (I - A) from A's (``space`` = (Q, H) with
    A Q[:m] = Q[:m+1] H): the same basis, H' = (1 - t) I + t H.  For A = I - c L (ROS2's
    W at a step h, c ~ h) and t = h'/h > 0, A' is W at h': a Krylov space of L does not
    depend on the shift, and Arnoldi on A' from the same b builds this same basis (in exact
    arithmetic), so GMRES on A' seeded with it (``gmres(..., seed=)``) gives a fresh GMRES's
    iterates -- and needs products only beyond the m it already has."""
    Q, H = space
    Hs = t * H
    m = H.shape[1]
    Hs[np.arange(m), np.arange(m)] += 1.0 - t
    return Q, Hs


def gmres(A, b: np.ndarray, rtol: float, max_it: int, space: tuple | None = None,
          keep_space: bool = False, seed: tuple | None = None) -> KrylovResult:
    """Solve A x = b (A: a function of a 1-D array) to the relative residual ``rtol``;
    ``space``: another system's Krylov space of the same A to start from; ``keep_space``:
    return this one's (the module); ``seed``: an Arnoldi relation (Q, H) of this same A
    started from this same b (``shifted_space``), whose m columns stand for the first m
    iterations (no products; ``iterations`` counts the new ones)."""
    nb = float(np.linalg.norm(b))
    if nb == 0.0 or not np.isfinite(nb):
        return KrylovResult(np.zeros_like(b), 0, 0.0 if nb == 0.0 else np.inf, nb == 0.0)
    if space is not None and space[1].shape[1] > 0:
        x0, r = _recycled(space, b)
        nr = float(np.linalg.norm(r))
        if nr <= rtol * nb:
            return KrylovResult(x0, 0, nr / nb, True)
        res = gmres(A, r, rtol * nb / nr, max_it, keep_space=keep_space)
        res.x = res.x + x0
        res.residual *= nr / nb
        return res
    Q = np.empty((max_it + 1, b.size))
    Q[0] = b / nb
    H = np.zeros((max_it + 1, max_it))
    Hraw = np.zeros((max_it + 1, max_it))      # before the rotations: for the Ritz values
    m0 = 0
    if seed is not None:                       # the first m0 columns given (no products)
        m0 = min(seed[1].shape[1], max_it)
        Q[:m0 + 1] = seed[0][:m0 + 1]
        H[:m0 + 1, :m0] = seed[1][:m0 + 1, :m0]
    g = np.zeros(max_it + 1)
    g[0] = nb
    cs, sn = np.zeros(max_it), np.zeros(max_it)
    k, res = 0, 1.0
    for k in range(max_it):
        if k < m0:                                 # a given column
            hk1 = float(H[k + 1, k])
        else:
            w = A(Q[k])
            for i in range(k + 1):                 # modified Gram-Schmidt
                H[i, k] = float(w @ Q[i])
                w -= H[i, k] * Q[i]
            hk1 = float(np.linalg.norm(w))
            H[k + 1, k] = hk1
        Hraw[:k + 2, k] = H[:k + 2, k]
        for i in range(k):                         # earlier rotations on the new column
            t = cs[i] * H[i, k] + sn[i] * H[i + 1, k]
            H[i + 1, k] = -sn[i] * H[i, k] + cs[i] * H[i + 1, k]
            H[i, k] = t
        r = float(np.hypot(H[k, k], H[k + 1, k]))
        if r == 0.0 or not np.isfinite(r):
            return KrylovResult(np.zeros_like(b), max(k + 1 - m0, 0), np.inf, False)
        cs[k], sn[k] = H[k, k] / r, H[k + 1, k] / r
        H[k, k], H[k + 1, k] = r, 0.0
        g[k + 1] = -sn[k] * g[k]
        g[k] = cs[k] * g[k]
        res = abs(g[k + 1]) / nb
        if hk1 == 0.0:                             # x is exact
            Q[k + 1] = 0.0
            break
        if k >= m0:
            Q[k + 1] = w / hk1
        if res <= rtol or k + 1 == max_it:
            break
    m = k + 1
    y = np.linalg.solve(np.triu(H[:m, :m]), g[:m])
    x = y @ Q[:m]
    return KrylovResult(x, max(m - m0, 0), res, bool(res <= rtol), np.linalg.eigvals(Hraw[:m, :m]),
                        (Q[:m + 1], Hraw[:m + 1, :m]) if keep_space else None)
