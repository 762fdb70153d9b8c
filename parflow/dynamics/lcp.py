"""Contact forces of hard particles (DESIGN §5); the candidate pairs come from
``parflow.geometry.find_candidates``.

* ``solve_lcp``: f >= 0, w = S S^T f + q >= 0, f . w = 0 (q = b + h/dg for the suspension
  step) by block principal pivoting from a warm set, then projected Newton (monotone in
  the QP's objective), with a Lawson-Hanson primal active set as the last resort; each
  inner solve factors the active N_AA (CHOLMOD through PETSc on
  COMM_SELF, or scipy SuperLU), a singular N_AA (self-stress) is shifted and counted.

Replicated: every rank computes the same thing (no communication).
"""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.linalg

from ..algebra.solvers import SelfFactor, SolveError
from ..errors import InputError


# =========================================================================== neighbours

# =========================================================================== operators

# =========================================================================== LCP

@dataclass
class LCPInfo:
    iterations: int = 0        # outer iterations (solves)
    factorizations: int = 0
    singular: int = 0          # factorisations of a singular N_AA (self-stress), regularised
    added: int = 0
    removed: int = 0
    min_w: float = 0.0         # min over candidates of w (>= -tol)
    floor: float = 0.0         # round-off floor of w at the solution, eps ||N||_inf max f
    refined: int = 0           # refinement steps of shifted solves against the true N_AA
    dropped: int = 0           # redundant contacts dropped along an unloaded null vector
    comp: float = 0.0          # max |f_a w_a|
    factor_time: float = 0.0
    bordered: int = 0          # solves by a bordered update of a kept factor (no factorisation)
    newton: int = 0            # projected-Newton iterations (solves each), after block pivoting
    mode: str = "block"        # how it ended: bpp, newton, block / single (Lawson-Hanson)
    mirrored: int = 0          # uphill solves along a near-null vector taken the other way


class LCPFailure(RuntimeError):
    pass


class ContactSolveError(SolveError):
    """The contact step failed without a proof of jamming (no compressed self-stress was
    found): a solver failure, reported as such (one line, run status "failed")."""


FACTORS = ("cholmod", "superlu")
EPS = float(np.finfo(float).eps)
# the pivoting tolerance is at least this many times the round-off floor of w (below):
# w = N f + q cannot be computed more accurately than ~ eps ||N||_inf max f, and a
# tolerance below that makes block pivoting cycle on noise (phi = 0.84: f ~ 1e7)
FLOOR_FACTOR = 64.0
# projected Newton hands over to Lawson-Hanson after this many singular free sets
NEWTON_SINGULAR = 6
# iterative refinement of a shifted solve against N_AA: up to REFINE_STEPS steps while the
# residual falls by REFINE_RATE at least.  A near-singular (not singular) set converges at
# shift / (lambda + shift) per mode, slowly when lambda ~ shift: measured at N = 1024,
# phi = 0.84, sigma = 3e6 (f ~ 1e10), 4 steps that each had to halve the residual left
# w = -0.05 -- a solver failure at every step size on an LCP the LP shows feasible -- and
# 60 at 5 % leave -1.2e-5, within the round-off tolerance (tests/test_suspension.py)
REFINE_RATE = 0.95
REFINE_STEPS = 60               # iterative refinement of a shifted solve against N_AA
# a null vector u of a singular N_AA (inverse iteration on the shifted factor) is taken as
# one if ||N_AA u|| <= NULL_TOL ||N_AA||_inf |u|; its support: entries above SUPPORT max|u|;
# the right-hand side does not load it if |u . rhs| <= UNLOADED |rhs| (measured at phi =
# 0.84, N = 4096: unloaded clusters at 1e-14 - 2e-11, loaded ones at 1e-7 - 1e-2; ActiveSolver.
# _drop_redundant)
NULL_TOL = 1e-10
SUPPORT = 1e-3
UNLOADED = 1e-9
# a direction d is taken as a near-null vector of N if |N d| <= NULL_DIR ||N||_inf |d|
NULL_DIR = 1e-6


def roundoff_floor(N, f: np.ndarray) -> float:
    """eps ||N||_inf max|f|: the accuracy to which w = N f + q can be known."""
    if f.size == 0:
        return 0.0
    norm = float(np.max(np.abs(N).sum(axis=1))) if N.shape[0] else 0.0
    return EPS * norm * float(np.max(np.abs(f)))


def _solution_ok(res: np.ndarray, x_A: np.ndarray, rhs: np.ndarray, norm: float,
                 res_tol: float) -> bool:
    """A solution x_A of M x = rhs with residual ``res`` is accepted if the relative residual
    is <= ``res_tol`` and x is not blown up by a near-singular M (|x| |M| 1e-12 <= |rhs|)."""
    nr = max(float(np.linalg.norm(rhs)), 1e-300)
    r = float(np.linalg.norm(res))
    return bool(np.isfinite(r) and r <= res_tol * nr
                and float(np.linalg.norm(x_A)) * norm * 1e-12 <= nr)


def _mirrored(N, w: np.ndarray, f: np.ndarray, z: np.ndarray, norm: float, A: np.ndarray,
              info: "LCPInfo") -> np.ndarray:
    """z, the solve on the set A from the point f (w = N f + q), or its mirror 2 f - z when
    z - f points uphill (w . (z - f) > 0) along a near-null vector of N (|N (z - f)| <=
    NULL_DIR ||N||_inf |z - f|) and the mirror leaves a force of A negative.

    An exact solve on the set (x = 0 off it) gives w . d = -d . N d <= 0.  A solve on a set
    made singular by an added contact k -- a self-stress u of the set with u . q = u_k w_k
    != 0, which has no solution -- leaves a multiple of u of arbitrary sign when the
    singularity is not caught; the shifted solve puts it downhill.  The mirror moves along
    u the way that loads k and lowers phi linearly (N u = 0), to the first contact of u's
    other sign that reaches zero: the exchange the singular set calls for.  A mirror with no
    negative force would be a compressed self-stress, which is for the certificate to
    prove, not for a solve that may just be inaccurate: z is kept.  Seen near jamming as
    projected Newton stopping at its first step (no descent) and Lawson-Hanson adding and
    dropping the same contact until it gives up.  Measured on the LCPs of 60 steps from
    the recorded N = 8192, phi = 0.8409 state (tests/reference/creeping_state.npz; 86 LCPs,
    each with the budget the step gave it): 14 give up instead of 23, 72 s instead of 77;
    on those of 150 flowing steps at phi = 0.840, N = 4096 (156 LCPs): 2 instead of 5 in
    the same time; where both solve, V = S^T f agrees to 1.5e-10."""
    d = z - f
    if not float(w @ d) > 0:
        return z
    if not float(np.linalg.norm(N @ d)) <= NULL_DIR * norm * float(np.linalg.norm(d)):
        return z
    m = 2.0 * f - z
    if not np.any(A & (m < 0)):
        return z
    info.mirrored += 1
    return m


class ActiveSolver:
    """x with N_AA x_A = -q_A, x = 0 off A, for the sequence of active sets an LCP solve visits.

    A set A0 is factorised (the *base*); a later set A = A0 - R + B is solved with that factor
    by bordering the base system: the rows R lose their equation and get x_R = 0 through a
    multiplier, the rows B are appended, and the k x k Schur complement (k = |R| + |B|)

        Sig = D - C^T N00^-1 C,   C = [N_{0B}, -E_R],   D = [[N_BB, 0], [0, 0]]

    is solved densely (LU: Sig is indefinite).  N00^-1 C is computed once per index that
    enters R or B (one pair of triangular solves) and kept while the base lives.  A new base
    is factorised when k exceeds ``max_border`` or when the bordered solution fails the
    residual test after one refinement (a near-singular Sig: a state of self-stress among the
    contacts of B).  Block pivoting and the Lawson-Hanson active set change a few contacts
    per iteration, so one factorisation serves many iterations (measured at phi = 0.84,
    N = 4096: docs/benchmarks.md).

    A singular N_AA (self-stress; the factorisation breaks down, or the residual / the size of
    x says it is singular to working precision) is shifted by eps ||N_AA||_inf I and solved
    again, counted in ``info.singular``.  The shifted solve has components ~ 1/eps along the
    self-stress: negative ones make the active set drop a redundant contact; an all-positive
    self-stress (a jammed cluster) shows up as a huge stress and shrinks the step.
    """

    def __init__(self, N: sp.csr_matrix, q: np.ndarray, info: LCPInfo, factor: str = "cholmod",
                 eps: float = 1e-12, max_border: int = 80):
        self.N, self.q, self.info = N, q, info
        self.eps, self.max_border = eps, max_border
        self.nc = q.shape[0]
        self.kind = factor             # the factorisation in use (CHOLMOD -> SuperLU, below)
        self.base = None
        self._rowsum = np.asarray(abs(N).sum(axis=1)).ravel()

    # ------------------------------------------------------------------ fresh factorisation
    def _factorise(self, M: sp.csr_matrix, rhs: np.ndarray):
        """(factor of M, M^-1 rhs or None if the factorisation broke down)."""
        fac = SelfFactor(M, self.kind)
        y = fac.solve(rhs)
        if y is None and self.kind == "cholmod":
            # a CHOLMOD factorisation that breaks down leaks its partial factor (PETSc 3.18:
            # ~0.4 MB at 7 600 rows, measured; 5 GB in 80 minutes at phi = 0.84): the rest of
            # this LCP factorises with SuperLU, which reports a singular matrix cleanly
            self.kind = "superlu"
        return fac, y

    def _fresh(self, A: np.ndarray, idx: np.ndarray) -> np.ndarray:
        info, N = self.info, self.N
        self.release()
        M = N[idx][:, idx].tocsr()
        rhs = -self.q[idx]
        norm = float(np.max(np.abs(M).sum(axis=1)))
        t0 = time.perf_counter()
        info.factorizations += 1
        fac, y = self._factorise(M, rhs)
        x = np.zeros(self.nc)
        if y is not None and _solution_ok(M @ y - rhs, y, rhs, norm, 1e-8):
            pos = np.full(self.nc, -1, np.int64)
            pos[idx] = np.arange(idx.size)
            cap = 2 * self.max_border
            # C, Z column-major: a block of new columns is contiguous for the multi-right-
            # hand-side solve; Z is written before it is read; the nonzeros of each column
            # of C (a row of N, or one -1) are kept for G = C^T Z
            self.base = dict(mask=A.copy(), idx=idx, pos=pos, fac=fac, y0=y, slot={}, m=0,
                             C=np.zeros((idx.size, cap), order="F"),
                             Z=np.empty((idx.size, cap), order="F"),
                             G=np.zeros((cap, cap)), g0=np.zeros(cap), nz=[])
            info.factor_time += time.perf_counter() - t0
            x[idx] = y
            return x
        fac.destroy()
        info.singular += 1
        shift = self.eps * max(norm, 1.0)
        Ms = (M + shift * sp.identity(idx.size, format="csr")).tocsr()
        fac, y = self._factorise(Ms, rhs)
        if y is None and fac.kind == "cholmod":      # broke down: SuperLU from now on
            fac.destroy()
            fac, y = self._factorise(Ms, rhs)
        if y is not None:
            y = self._refine(M, fac, rhs, y)
            y = self._drop_redundant(M, fac, rhs, y, norm)
        fac.destroy()
        info.factor_time += time.perf_counter() - t0
        if y is None:
            raise LCPFailure(f"contact LCP: the shifted active N ({idx.size} contacts) "
                             f"could not be factored")
        x[idx] = y
        return x

    def _drop_redundant(self, M, fac, rhs: np.ndarray, y: np.ndarray, norm: float) -> np.ndarray:
        """A singular N_AA whose null vector u (a self-stress of the active contacts) the
        right-hand side does not load (|u . rhs| <= UNLOADED |rhs|: the flow does not press
        on that over-constrained cluster) has the exact solutions y_r + t u, y_r = y - (u.y) u
        (the shifted, refined solve's part on the range of N_AA).  Of them take the one where
        the first contact of u's support reaches zero force as t moves away from y_r (the
        direction leaving fewer negative forces; a ratio test keeps the others of the support
        >= 0): that contact is redundant, with f = 0 and w = 0, so the pivoting drops it
        (projected Newton, Lawson-Hanson), and the next set -- and the next step's warm set
        -- is no longer singular along u.  Without this the refined minimum-norm solution
        shares the force among the cluster's contacts and the set stays singular.  A loaded u
        is left to the pivoting: the shifted solve puts ~ (u . rhs)/shift along it, the
        contacts of one sign leave the set, and a compressed self-stress (u >= 0 loaded in
        compression) goes on to the certificate (a jam); so is a u that is not a null vector
        to NULL_TOL (several null vectors are met one per singular solve).  u: two steps of
        inverse iteration with the shifted factor (it amplifies the null space by ~ 1/shift).
        Kept only if its residual is within the round-off of the new forces or as small as
        y's; else y."""
        n = y.size
        if n < 2:
            return y
        # a fixed start vector (the same on every rank and every run): not orthogonal to u
        u = np.cos(np.arange(1, n + 1) * 0.7548776662466927) + 1.5
        for _ in range(2):
            u = fac.solve(u)
            if u is None:
                return y
            nu = float(np.linalg.norm(u))
            if not (np.isfinite(nu) and nu > 0):
                return y
            u /= nu
        if not float(np.linalg.norm(M @ u)) <= NULL_TOL * norm:
            return y                                          # not singular along one vector
        if not abs(float(u @ rhs)) <= UNLOADED * float(np.linalg.norm(rhs)):
            return y                                          # loaded: the pivoting's
        y_r = y - float(u @ y) * u
        big = SUPPORT * float(np.abs(u).max())
        best = None
        for v in (u, -u):
            cand = np.flatnonzero((v > big) & (y_r > 0))      # x = y_r - t v, t >= 0
            if cand.size == 0:
                continue
            ratio = y_r[cand] / v[cand]
            j = int(np.argmin(ratio))
            x = y_r - float(ratio[j]) * v
            x[cand[j]] = 0.0
            neg = int(np.count_nonzero(x < 0))
            if best is None or neg < best[0]:
                best = (neg, x)
        if best is None:
            return y
        x = best[1]
        res = float(np.linalg.norm(M @ x - rhs))
        floor = FLOOR_FACTOR * EPS * norm * float(np.abs(x).max()) * np.sqrt(n)
        if not res <= max(floor, float(np.linalg.norm(M @ y - rhs))):
            return y
        self.info.dropped += 1
        return x

    def _refine(self, M, fac, rhs: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Iterative refinement of the shifted solution against the true M = N_AA:
        y += (M + shift)^-1 (rhs - M y) while the residual falls (REFINE_RATE).  The
        shift's error, shift |y| on w (4e-8 at f ~ 1e4, phi = 0.84), goes away on the range
        of M; a component of rhs on a self-stress u (inconsistent) stays in the residual,
        and the iteration stops (it would only grow y along u)."""
        r = rhs - M @ y
        rn = float(np.linalg.norm(r))
        for _ in range(REFINE_STEPS):
            if not rn > 0:
                break
            dy = fac.solve(r)
            if dy is None:
                break
            y2 = y + dy
            r2 = rhs - M @ y2
            rn2 = float(np.linalg.norm(r2))
            self.info.refined += 1
            if not rn2 <= REFINE_RATE * rn:
                break
            y, r, rn = y2, r2, rn2
        return y

    # ------------------------------------------------------------------ bordered update
    def _columns(self, keys: np.ndarray) -> np.ndarray | None:
        """Slots of the border keys (-1 - i for an index i of R, i for an index i of B) in
        the kept C0 = [C columns] and Z0 = N00^-1 C0 (base space); new ones are solved for
        (one multi-right-hand-side solve) and G = C0^T Z0 extended."""
        bs = self.base
        slot = bs["slot"]
        new = np.array([k for k in keys.tolist() if k not in slot], np.int64)
        if new.size:
            idx, pos, m = bs["idx"], bs["pos"], bs["m"]
            if m + new.size > bs["C"].shape[1]:
                return None
            C = bs["C"][:, m:m + new.size]
            isr = new < 0
            C[pos[-1 - new[isr]], np.flatnonzero(isr)] = -1.0
            nz = [None] * new.size
            for j in np.flatnonzero(isr).tolist():
                nz[j] = (np.array([pos[-1 - new[j]]]), np.array([-1.0]))
            if np.any(~isr):
                Nb = self.N[new[~isr]][:, idx].tocsr()
                C[:, ~isr] = Nb.toarray().T
                for r, j in enumerate(np.flatnonzero(~isr).tolist()):
                    a, b = Nb.indptr[r], Nb.indptr[r + 1]
                    nz[j] = (Nb.indices[a:b], Nb.data[a:b])
            Zn = bs["fac"].solve(C)
            if Zn is None:
                return None
            bs["Z"][:, m:m + new.size] = Zn
            m2 = m + new.size
            # G = C0^T N00^-1 C0 is symmetric: the new columns and their mirror (C0 is
            # sparse: ~10 nonzeros a column)
            bs["nz"].extend(nz)
            rows = [r for r, _ in bs["nz"]]
            CT = sp.csr_matrix((np.concatenate([v for _, v in bs["nz"]]), np.concatenate(rows),
                                np.concatenate([[0], np.cumsum([r.size for r in rows])])),
                               shape=(m2, idx.size))
            Gn = CT @ Zn
            bs["G"][:m2, m:m2] = Gn
            bs["G"][m:m2, :m2] = Gn.T
            bs["g0"][m:m2] = C.T @ bs["y0"]
            for k, key in enumerate(new.tolist()):
                slot[key] = m + k
            bs["m"] = m2
        return np.array([slot[k] for k in keys.tolist()], np.int64)

    def _apply(self, rhs: np.ndarray, v0: np.ndarray, Ctv0: np.ndarray, R, B, sl,
               lu) -> np.ndarray | None:
        """The bordered solution (nc-space) for right-hand side ``rhs`` (nc-space, rows of A
        used), v0 = N00^-1 rhs_0 (base space) and Ctv0 = C_sel^T v0:
        (D - C^T Z) y = [0 ; rhs_B] - C^T v0;  x0 = v0 - Z y,  x_B = y_B,  x_R = 0."""
        bs = self.base
        t = -Ctv0
        t[R.size:] += rhs[B]
        y = scipy.linalg.lu_solve(lu, t, check_finite=False)
        if not np.all(np.isfinite(y)):
            return None                       # Sig singular: a self-stress among the border
        ym = np.zeros(bs["m"])
        ym[sl] = y
        x = np.zeros(self.nc)
        x[bs["idx"]] = v0 - bs["Z"][:, :bs["m"]] @ ym
        x[R] = 0.0
        x[B] = y[R.size:]
        return x

    def _bordered(self, A: np.ndarray) -> np.ndarray | None:
        bs = self.base
        R = np.flatnonzero(bs["mask"] & ~A)
        B = np.flatnonzero(A & ~bs["mask"])
        if R.size + B.size == 0:
            x = np.zeros(self.nc)
            x[bs["idx"]] = bs["y0"]
            return x
        if R.size + B.size > self.max_border:
            return None
        sl = self._columns(np.concatenate([-1 - R, B]))
        if sl is None:
            return None
        N, q = self.N, self.q
        nR = R.size
        Sig = -bs["G"][np.ix_(sl, sl)]
        if B.size:
            Sig[nR:, nR:] += N[B][:, B].toarray()
        if not np.all(np.isfinite(Sig)):
            return None
        with warnings.catch_warnings():       # a singular Sig is detected below
            warnings.simplefilter("ignore", scipy.linalg.LinAlgWarning)
            lu = scipy.linalg.lu_factor(Sig, check_finite=False)
        rhs = -q
        x = self._apply(rhs, bs["y0"], bs["g0"][sl].copy(), R, B, sl, lu)
        if x is None:
            return None
        # residuals through the whole N (x = 0 off A); ||N_AA||_inf bounded by N's row sums
        A_idx = np.flatnonzero(A)
        norm = float(self._rowsum[A_idx].max())
        res = (N @ x)[A_idx] - rhs[A_idx]
        if not _solution_ok(res, x[A_idx], rhs[A_idx], norm, 1e-12):
            # one step of iterative refinement through the same factors
            r = np.zeros(self.nc)
            r[A_idx] = -res
            v0 = bs["fac"].solve(np.ascontiguousarray(r[bs["idx"]]))
            if v0 is None:
                return None
            dx = self._apply(r, v0, bs["C"][:, sl].T @ v0, R, B, sl, lu)
            if dx is None:
                return None
            x = x + dx
            res = (N @ x)[A_idx] - rhs[A_idx]
            if not _solution_ok(res, x[A_idx], rhs[A_idx], norm, 1e-8):
                return None
        self.info.bordered += 1
        return x

    # ------------------------------------------------------------------ public
    def solve(self, A: np.ndarray) -> np.ndarray:
        idx = np.flatnonzero(A)
        if idx.size == 0:
            return np.zeros(self.nc)
        if self.base is not None:
            x = self._bordered(A)
            if x is not None:
                return x
        return self._fresh(A, idx)

    def release(self):
        if self.base is not None:
            self.base["fac"].destroy()
            self.base = None


def solve_lcp(S: sp.csr_matrix, q: np.ndarray, warm: np.ndarray | None = None,
              tol: float | None = None, max_iter: int = 200, bpp_max: int = 2,
              bpp_patience: int = 3, factor: str = "cholmod", max_solves: int = 600,
              max_singular: int = 20, newton_max: int = 150) -> tuple[np.ndarray, LCPInfo]:
    """f >= 0, w = S S^T f + q >= -tol, f . w = 0 by a warm-started active set.

    Phase 0: block principal pivoting from the warm set, at most ``bpp_max`` solves (0
    skips it; the default 2 -- the warm set and one exchange -- because near jamming block
    pivoting swings between sets: measured at phi = 0.84, N = 4096, letting it run (30)
    costs 1.2-1.5x more than handing over after 2; equal at phi = 0.82, where it ends in 2).

    Phase 1 (mode "newton"): projected Newton from the warm set's solution
    (:func:`_projected_newton`; ``newton_max`` = 0 skips it).

    Phase 2 (Lawson-Hanson, mode "block"/"single", if phase 1 did not end): solve on the
    set, drop contacts whose force comes out negative, repeat; add violated constraints
    (w < -tol) -- all at once while that makes progress, one at a time (the most violated)
    after 50 iterations -- and keep f feasible by the ratio test.

    Gives up (:class:`LCPFailure`) after ``max_solves`` solves or ``max_singular`` singular
    active sets: an LCP that has no solution (a state of self-stress that q compresses, for
    which a smaller strain step is the cure) otherwise cycles through shifted factorisations
    for a minute (measured at phi = 0.84, N = 4096: the solvable ones took <= 215 solves).
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
    act = ActiveSolver(N, q, info, factor)
    try:
        return _pivot(N, q, act, info, warm, tol, max_iter, bpp_max, bpp_patience,
                      max_solves, max_singular, newton_max)
    finally:
        act.release()


def _pivot(N, q, act: ActiveSolver, info: LCPInfo, warm, tol: float, max_iter: int,
           bpp_max: int, bpp_patience: int, max_solves: int, max_singular: int,
           newton_max: int) -> tuple[np.ndarray, LCPInfo]:
    """The pivoting of :func:`solve_lcp` (every solve through ``act``)."""
    nc = q.shape[0]

    norm = float(act._rowsum.max())

    def tol_of(z):
        """The pivoting tolerance for w at forces z: ``tol``, or the round-off floor of w
        (FLOOR_FACTOR eps ||N||_inf max z) if that is larger."""
        return max(tol, FLOOR_FACTOR * EPS * norm * float(np.max(np.abs(z), initial=0.0)))

    def solve(A):
        if info.iterations >= max_solves or info.singular > max_singular:
            raise LCPFailure(f"contact LCP: given up after {info.iterations} solves, "
                             f"{info.singular} of them on a singular active set "
                             f"({int(A.sum())} active of {nc})")
        info.iterations += 1
        return act.solve(A)

    A = np.zeros(nc, bool) if warm is None else warm.copy()
    f = np.zeros(nc)
    # phase 0: block principal pivoting (Judice & Pires) from the warm set; it exchanges
    # every infeasible index at once and ends in 1-3 solves away from jamming, but it can
    # cycle: after ``bpp_max`` solves, or ``bpp_patience`` without fewer infeasibilities,
    # hand over.
    best, stale, first = np.inf, 0, None
    for _ in range(bpp_max):
        z = solve(A)
        w = N @ z + q
        if first is None:
            first = z
        F = A & (z < 0)
        G = ~A & (w < -tol_of(z))
        n_inf = int(F.sum() + G.sum())
        if n_inf == 0:
            np.maximum(z, 0.0, out=z)
            info.mode = "bpp"
            return _solved(info, z, w, norm)
        if n_inf < best:
            best, stale = n_inf, 0
        else:
            stale += 1
            if stale >= bpp_patience:
                break
        info.added += int(G.sum())
        info.removed += int(F.sum())
        A = (A & ~F) | G
    # phase 1: projected Newton (Bertsekas) from the warm set's solution, monotone in the
    # objective phi(f) = 1/2 f.N f + q.f, so it cannot cycle where block pivoting does
    if newton_max > 0 and first is not None:
        out = _projected_newton(N, q, solve, info, np.maximum(first, 0.0), tol_of, norm,
                                newton_max)
        if out is not None:
            return out
    # phase 2 (Lawson-Hanson): drop negative forces from the set, then add violated constraints
    while A.any():
        z = solve(A)
        neg = A & (z <= 0)
        if not neg.any():
            f = z
            break
        A &= ~neg
        info.removed += int(neg.sum())
    for it in range(max_iter):
        w = N @ f + q
        viol = ~A & (w < -tol_of(f))
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
            z = _mirrored(N, N @ f + q, f, solve(A), norm, A, info)
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
    return _solved(info, f, N @ f + q, norm)


def _solved(info: LCPInfo, f: np.ndarray, w: np.ndarray, norm: float):
    """(f, info) with the solution's min w, complementarity max |f w| and round-off floor
    eps ||N||_inf max f recorded in info."""
    info.min_w = float(w.min())
    info.comp = float(np.max(np.abs(f * w)))
    info.floor = EPS * norm * float(np.max(f, initial=0.0))
    return f, info


def _projected_newton(N, q, solve, info: LCPInfo, f: np.ndarray, tol_of, norm: float,
                      max_iter: int) -> tuple[np.ndarray, LCPInfo] | None:
    """Projected Newton (Bertsekas 1982, with epsilon = 0) for min phi(f) = 1/2 f.N f + q.f
    over f >= 0, from a feasible f: the free set F = {f > 0} | {w < -tol}, z the minimiser on
    the face F (one active-set solve, x = 0 off F), and the projected path max(f + a (z - f), 0)
    with a = 1, 1/2, ... until phi decreases (Armijo).  Every blocking force leaves the set
    at once, as in block pivoting, but phi never increases, so it does not cycle.  Done
    when a full step lands on z >= 0 with no violated constraint off F.  Where the Armijo
    step stops short of the path's first bend (a soft mode of N_FF makes z - f huge), the
    step goes to that bend instead and drops the blocking contacts (a ratio test), and the
    next set adds nothing.  Measured on 60-step samples of LCPs at phi = 0.84, N = 4096
    (benchmarks/bench_lcp.py, docs/benchmarks.md): 10-14 Newton solves per LCP where
    block pivoting and Lawson-Hanson took 35-300 on the hard ones.  None after
    ``max_iter`` iterations, more than NEWTON_SINGULAR singular free sets, or no descent
    (the Lawson-Hanson phases follow)."""
    w = N @ f + q
    phi = 0.5 * float(f @ (w + q))
    done, bad, dropped = False, 0, False
    for _ in range(max_iter):
        t = tol_of(f)
        if done and not np.any((f == 0) & (w < -t)):
            np.maximum(f, 0.0, out=f)
            info.mode = "newton"
            return _solved(info, f, w, norm)
        # after a ratio-test step the set is first made feasible (no additions: they would
        # bring the dropped contacts straight back), as in Lawson-Hanson
        F = (f > 0) if dropped else (f > 0) | (w < -t)
        singular = info.singular
        z = solve(F)
        info.newton += 1
        if info.singular > singular:
            bad += 1
            if bad > NEWTON_SINGULAR:
                return None                 # a self-stress among the added contacts
        z = _mirrored(N, w, f, z, norm, F, info)
        done = not np.any(F & (z < 0))
        if done:
            # z >= 0 minimises phi on the face F, so phi(z) <= phi(f) (up to the solve's
            # round-off, which an Armijo test would take for an ascent): step to it
            fn = np.maximum(z, 0.0)
            _count(info, f, fn)
            f, w = fn, N @ fn + q
            phi = 0.5 * float(f @ (w + q))
            dropped = False
            continue
        d = z - f
        a = 1.0
        # phi is known to ~eps (|f.w| + |f.q|): a step that changes it by less is not judged
        slack = 64 * EPS * (abs(float(f @ w)) + abs(float(f @ q)))
        for _ in range(40):
            fn = np.maximum(f + a * d, 0.0)
            wn = N @ fn + q
            phin = 0.5 * float(fn @ (wn + q))
            if phin <= phi + 1e-4 * float(w @ (fn - f)) + slack:
                break
            a *= 0.5
        else:
            a = 0.0
        # the projected path bends at the first force that reaches zero; when the Armijo step
        # stops short of that point (a soft mode: d huge along it), step there instead and
        # drop the blocking contacts (Lawson-Hanson's ratio test): phi decreases on the face
        # F up to z, so this too is a descent step, and the set changes
        neg = F & (z < 0)                   # not empty: z < 0 somewhere on F
        fa, za = f[neg], z[neg]
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(fa > 0, fa / (fa - za), 0.0)
        a_rt = float(ratio.min())
        dropped = a < a_rt
        if dropped:
            fn = f + a_rt * d
            fn[np.flatnonzero(neg)[ratio <= a_rt * (1 + 1e-12)]] = 0.0
            np.maximum(fn, 0.0, out=fn)
            wn = N @ fn + q
            phin = 0.5 * float(fn @ (wn + q))
        elif a == 0.0:
            return None                     # no descent along the path nor to its bend
        _count(info, f, fn)
        f, w, phi = fn, wn, phin
    return None


def _count(info: LCPInfo, f: np.ndarray, fn: np.ndarray) -> None:
    """Contacts that gained / lost their force between f and fn, into info.added/removed."""
    was, now = f > 0, fn > 0
    info.added += int(np.count_nonzero(now & ~was))
    info.removed += int(np.count_nonzero(was & ~now))
