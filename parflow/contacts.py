"""Contact geometry and contact forces of hard particles (DESIGN §2, §5).

* ``find_candidates``: pairs with gap < skin under Lees-Edwards shear.  The cell is remapped
  by a lattice vector so that its tilt is in [-Lx/2, Lx/2]; a cKDTree with periodic
  ``boxsize`` in the orthogonal reference frame of that cell finds pairs within the cut
  times the metric distortion of the tilt; true minimum-image distances filter them.
* ``rigidity``: S_C (Nc x dN), -n at i, +n at j.
* ``solve_lcp``: f >= 0, w = S S^T f + q >= 0, f . w = 0 (q = b + h/dg for the suspension
  step) by block principal pivoting from a warm set, with a Lawson-Hanson primal active
  set as the fall-back; each inner solve factors the active N_AA (CHOLMOD through PETSc on
  COMM_SELF, or scipy SuperLU), a singular N_AA (self-stress) is shifted and counted.

Replicated: every rank computes the same thing (no communication).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.spatial import cKDTree

from .state import InputError


# =========================================================================== neighbours

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


def remap(h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lees-Edwards remapping: U unimodular with h_r = h U, tilt |h_r[0,1]| <= Lx/2."""
    k = -np.rint(h[0, 1] / h[0, 0])
    U = np.array([[1.0, k], [0.0, 1.0]])
    return h @ U, U


def find_candidates(s, radii, h, E, skin: float) -> Candidates:
    """All pairs with gap < ``skin`` (minimum image in the remapped cell)."""
    hr, U = remap(h)
    Uinv = np.linalg.inv(U)
    sr = s @ Uinv.T                           # reduced coordinates in the remapped cell
    off = np.floor(sr)
    sr = sr - off
    sr[sr >= 1.0] = 0.0
    Lx, Ly = hr[0, 0], hr[1, 1]
    A = np.diag([Lx, Ly]) @ np.linalg.inv(hr)     # real space -> orthogonal reference frame
    stretch = float(np.linalg.norm(A, 2))
    cut = 2.0 * float(radii.max()) + skin
    if cut * stretch >= 0.5 * min(Lx, Ly):
        raise InputError(f"suspension: the box ({Lx:.3g} x {Ly:.3g}) is too small for the "
                         f"neighbour search (cut {cut:.3g}); use more discs or a smaller skin")
    X = sr * np.array([Lx, Ly])
    tree = cKDTree(X, boxsize=[Lx, Ly])
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


# =========================================================================== operators

def rigidity(c: Candidates, n_part: int) -> sp.csr_matrix:
    """S_C (Nc x d N): -n at i, +n at j (DESIGN §2)."""
    nc, d = len(c), c.n.shape[1]
    rows = np.repeat(np.arange(nc), 2 * d)
    cols = np.concatenate([d * c.i[:, None] + np.arange(d), d * c.j[:, None] + np.arange(d)], axis=1)
    vals = np.concatenate([-c.n, c.n], axis=1)
    return sp.csr_matrix((vals.ravel(), (rows, cols.ravel())), shape=(nc, d * n_part))


# =========================================================================== LCP

@dataclass
class LCPInfo:
    iterations: int = 0        # outer iterations (solves)
    factorizations: int = 0
    singular: int = 0          # factorisations of a singular N_AA (self-stress), regularised
    added: int = 0
    removed: int = 0
    min_w: float = 0.0         # min over candidates of w (>= -tol)
    comp: float = 0.0          # max |f_a w_a|
    factor_time: float = 0.0
    mode: str = "block"


class LCPFailure(RuntimeError):
    pass


FACTORS = ("cholmod", "superlu")


def _petsc():
    from petsc4py import PETSc
    return PETSc


def _cholmod_solve(M: sp.csr_matrix, rhs: np.ndarray) -> np.ndarray | None:
    """x = M^-1 rhs by CHOLMOD through PETSc on COMM_SELF (every rank the same, redundantly);
    None if the factorisation breaks down (M not positive definite to working precision)."""
    PETSc = _petsc()
    it = PETSc.IntType
    A = PETSc.Mat().createAIJ(size=M.shape, csr=(M.indptr.astype(it), M.indices.astype(it), M.data),
                              comm=PETSc.COMM_SELF)
    opts = PETSc.Options()
    if not opts.hasName("contact_mat_cholmod_print"):
        # a singular N_AA is routine here (detected, counted and handled below): keep
        # CHOLMOD from printing "matrix not positive definite" on stderr every time
        opts.setValue("contact_mat_cholmod_print", 0)
    ksp = PETSc.KSP().create(PETSc.COMM_SELF)
    ksp.setOptionsPrefix("contact_")
    ksp.setType(PETSc.KSP.Type.PREONLY)
    pc = ksp.getPC()
    pc.setType(PETSc.PC.Type.CHOLESKY)
    pc.setFactorSolverType("cholmod")
    ksp.setOperators(A)
    ksp.setFromOptions()
    x, b = A.createVecs()
    b.setArray(rhs)
    try:
        ksp.solve(b, x)
        ok = ksp.getConvergedReason() >= 0
        y = x.getArray().copy()
    except PETSc.Error:
        ok, y = False, None
    # pc too: petsc4py defers the destruction of a dropped wrapper to garbage_cleanup(), and
    # the PC holds the factor (measured: ~10 MB leaked per call at N_AA = 2000 without this)
    for o in (ksp, pc, A, x, b):
        o.destroy()
    return y if ok else None


def _superlu_solve(M: sp.csr_matrix, rhs: np.ndarray) -> np.ndarray | None:
    try:
        lu = spla.splu(M.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                       options=dict(SymmetricMode=True))
    except RuntimeError:                       # "Factor is exactly singular"
        return None
    piv = np.abs(lu.U.diagonal())
    if piv.min() <= 1e-13 * piv.max():
        return None
    return lu.solve(rhs)


def solve_active(N: sp.csr_matrix, q: np.ndarray, A: np.ndarray, info: LCPInfo,
                 eps: float = 1e-12, factor: str = "cholmod") -> np.ndarray:
    """Solve N_AA x = -q_A (A: boolean mask).

    A singular N_AA (a state of self-stress among the active contacts: the factorisation
    breaks down, or the residual / the size of x says it is singular to working precision)
    is shifted by eps ||N_AA||_inf I and solved again; the event is counted in
    ``info.singular``.  The shifted solve has components ~ 1/eps along the self-stress:
    negative ones make the active set drop a redundant contact; an all-positive
    self-stress (a jammed cluster) shows up as a huge stress and shrinks the step.
    """
    idx = np.flatnonzero(A)
    x = np.zeros(q.shape[0])
    if idx.size == 0:
        return x
    M = N[idx][:, idx].tocsr()
    rhs = -q[idx]
    t0 = time.perf_counter()
    info.factorizations += 1
    solve = _cholmod_solve if factor == "cholmod" else _superlu_solve
    y = solve(M, rhs)
    norm = float(np.max(np.abs(M).sum(axis=1)))
    if y is not None:
        nr = float(np.linalg.norm(rhs))
        res = float(np.linalg.norm(M @ y - rhs))
        ny = float(np.linalg.norm(y))
        if not (np.isfinite(res) and res <= 1e-8 * max(nr, 1e-300)
                and ny * norm * 1e-12 <= max(nr, 1e-300)):
            y = None
    if y is None:
        info.singular += 1
        shift = eps * max(norm, 1.0)
        Ms = (M + shift * sp.identity(idx.size, format="csr")).tocsr()
        y = solve(Ms, rhs)
        if y is None:
            y = _superlu_solve(Ms, rhs)
        if y is None:
            raise LCPFailure(f"contact LCP: the shifted active N ({idx.size} contacts) "
                             f"could not be factored")
    info.factor_time += time.perf_counter() - t0
    x[idx] = y
    return x


def solve_lcp(S: sp.csr_matrix, q: np.ndarray, warm: np.ndarray | None = None,
              tol: float | None = None, max_iter: int = 200, bpp_max: int = 30,
              bpp_patience: int = 3, factor: str = "cholmod") -> tuple[np.ndarray, LCPInfo]:
    """f >= 0, w = S S^T f + q >= -tol, f . w = 0 by a warm-started active set.

    Phase 0: block principal pivoting from the warm set (``bpp_max`` = 0 skips it).

    Phase 1: solve on the warm set, drop contacts whose force comes out negative, repeat.
    Phase 2 (Lawson-Hanson): add violated constraints (w < -tol) -- all at once ("block")
    while that makes progress, one at a time (the most violated) after 50 iterations --
    and keep f feasible by the ratio test when a force would become negative.
    """
    if factor not in FACTORS:
        raise InputError(f"suspension: factor must be one of {FACTORS}, got {factor!r}")
    nc = q.shape[0]
    info = LCPInfo()
    if nc == 0:
        return np.zeros(0), info
    if tol is None:
        tol = 1e-10 * max(1.0, float(np.max(np.abs(q[q < 0])) if np.any(q < 0) else 1.0))
    N = (S @ S.T).tocsr()
    A = np.zeros(nc, bool) if warm is None else warm.copy()
    f = np.zeros(nc)
    # phase 0: block principal pivoting (Judice & Pires) from the warm set; it exchanges
    # every infeasible index at once and usually ends in 1-3 solves, but it can cycle:
    # after ``bpp_patience`` iterations without fewer infeasibilities, fall back.
    best, stale = np.inf, 0
    for _ in range(bpp_max):
        info.iterations += 1
        z = solve_active(N, q, A, info, factor=factor)
        w = N @ z + q
        F = A & (z < 0)
        G = ~A & (w < -tol)
        n_inf = int(F.sum() + G.sum())
        if n_inf == 0:
            np.maximum(z, 0.0, out=z)
            info.mode = "bpp"
            info.min_w = float(w.min())
            info.comp = float(np.max(np.abs(z * w)))
            return z, info
        if n_inf < best:
            best, stale = n_inf, 0
        else:
            stale += 1
            if stale >= bpp_patience:
                break
        info.added += int(G.sum())
        info.removed += int(F.sum())
        A = (A & ~F) | G
    # phase 1
    while A.any():
        info.iterations += 1
        z = solve_active(N, q, A, info, factor=factor)
        neg = A & (z <= 0)
        if not neg.any():
            f = z
            break
        A &= ~neg
        info.removed += int(neg.sum())
    # phase 2
    for it in range(max_iter):
        w = N @ f + q
        viol = ~A & (w < -tol)
        if not viol.any():
            break
        if it < 50:
            A |= viol
            info.added += int(viol.sum())
        else:
            info.mode = "single"
            k = int(np.argmin(np.where(viol, w, np.inf)))
            A[k] = True
            info.added += 1
        while True:
            info.iterations += 1
            z = solve_active(N, q, A, info, factor=factor)
            neg = A & (z <= 0)
            if not neg.any():
                f = z
                break
            # ratio test from the feasible f towards z
            fa, za = f[neg], z[neg]
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = np.where(fa > 0, fa / (fa - za), 0.0)
            alpha = float(ratio.min())
            f = f + alpha * (z - f)
            drop = np.zeros(nc, bool)
            drop[np.flatnonzero(neg)[ratio <= alpha * (1 + 1e-12)]] = True   # blocking
            f[drop] = 0.0
            np.maximum(f, 0.0, out=f)
            A &= ~drop
            info.removed += int(drop.sum())
    else:
        raise LCPFailure(f"contact LCP: no convergence in {max_iter} active-set iterations "
                         f"({int(A.sum())} active of {nc})")
    w = N @ f + q
    info.min_w = float(w.min())
    info.comp = float(np.max(np.abs(f * w))) if nc else 0.0
    return f, info
