"""The deflated force solve: conjugate gradients on N with its softest modes projected out.

Near jamming N = S S^T has a few isolated soft modes (lambda_1 ~ 1e-7 against lambda_2 ~ 1e-4
and lambda_max ~ 6 on a 2D network at sigma ~ 1e4): preconditioned CG on N stalls, CG on N
with those modes deflated converges in an iteration count that no longer depends on sigma
(docs/solvers.md, "The deflated solve").

With W (Nc x k) spanning (approximately) the k lowest eigenvectors of N, E = W^T N W and
P = I - N W E^-1 W^T (DEF1 of Tang, Nabben, Vuik & Erlangga 2009):

    x = W E^-1 W^T b + (I - W E^-1 W^T N) y,    where  P N y = P b

P N is symmetric positive semi-definite with the soft modes removed; it is solved by PETSc's
CG (options prefix ``tau_``: ``-tau_ksp_*``, ``-tau_pc_*`` reach it) with a preconditioner
built from N itself (ICC(0) on one rank, block Jacobi with ICC(0) blocks on several).  With
N = S S^T known (``set_factor``), E, W^T N y and the true residual b - S (S^T x) are formed
from S^T, which keeps the soft mode's coefficient -- the one that carries sigma near
jamming -- accurate to ~eps / sqrt(lambda_1) rather than eps ||N|| / lambda_1.  Every solve
checks that residual, its backward error and the error along W, refines while they are above
the preset's levels, and raises :class:`SolveError` naming the reason (PETSc's, the
iterations) when CG does not converge.  W's accuracy changes the iteration count; the result
only through the refinement's tolerances (tests/test_deflated.py).

The deflation space: the k lowest eigenvectors of N from SLEPc (``spectrum.LowSpectrum``,
options prefix ``tau_defl_``) at the first solve; afterwards refreshed without SLEPc, by one
step of subspace inverse iteration with the deflated solver itself (Z = N^-1 W, Rayleigh-Ritz
on [W, Z]) when the iteration count has grown by ``growth`` over its value after the last
refresh, or every ``refresh_every`` solves.  Everything is on the row-distributed N: W and N W
are (local rows x k) numpy blocks, each product with W^T one allreduce of k numbers.
"""
from __future__ import annotations

import numpy as np
from petsc4py import PETSc
from scipy.linalg import LinAlgError, cho_factor, cho_solve

from ..errors import InputError
from .solvers import (BACKWARD_ERROR_FAIL, PRESETS, CholeskySolver, SingularOperator, SolveError,
                      SolveInfo, backward_error, reason_name, set_from_options, vec_norms)

# the deflated preset (each overridable by -tau_defl_NAME): k deflation vectors; CG's rtol
# (relative to ||b||) and max_it; refine_above, the backward error, and soft_tol, the error
# along the deflation space, that trigger a refinement (a second deflated CG on the residual,
# at most max_refine); the refresh rules (growth of the iterations, every n solves)
DEFAULTS = dict(k=4, rtol=1e-13, max_it=10_000, refine_above=4e-16, max_refine=2,
                soft_tol=1e-12, growth=1.5, refresh_every=0)
# the direct solve reaches a backward error ||b - N x|| / (||N|| ||x|| + ||b||) of 3e-17 to
# 4e-17 (Nc = 7.8e3 to 1.9e6): a deflated solve that ends above this is a SolveError
BERR_TARGET = 1e-14


class _DeflatedOperator:
    """The shell Mat y = P N x + c W W^T x = N x - N W E^-1 W^T N x + c W W^T x (petsc4py
    python context).  P N is symmetric, maps onto the complement of W and vanishes on W; the
    term c W W^T (c = 2, N's diagonal) makes the operator definite on W too, where P N is
    round-off, which CG otherwise meets as an indefinite direction once converged far enough.
    Its right-hand sides P b have no W component, so neither has the solution."""

    def __init__(self, solver: "DeflatedSolver"):
        self.s = solver

    def mult(self, mat, x, y):
        s = self.s
        s.A.mult(x, y)
        if s.k_active:
            ya, xa = y.getArray(), x.getArray(readonly=True)
            c = s.WT(np.column_stack([ya, xa]))          # one allreduce of 2k numbers
            ya -= s.AW @ s.coarse(c[:, 0]) - s.shift * (s.W @ c[:, 1])


class DeflatedSolver:
    """Deflated preconditioned CG for N x = b on the distributed N (same interface as
    :class:`solvers.CholeskySolver`: ``solve``, ``info``, ``norm_bound``, ``describe``,
    ``resolved_options``, ``destroy``; ``ksp`` is a direct factor of N built on first use,
    for the shift-and-invert of omega_min and the analyses' spectra)."""

    def __init__(self, A: PETSc.Mat, prefix: str = "tau_", parallel: str = "redundant",
                 k: int | None = None, deflate: bool = True):
        self.A, self.prefix, self.parallel = A, prefix, parallel
        self.comm = A.getComm()
        self.mpi = self.comm.tompi4py()
        db = PETSc.Options()
        opt = dict(DEFAULTS)
        for name, default in DEFAULTS.items():
            get = db.getInt if isinstance(default, int) else db.getReal
            try:
                opt[name] = get(f"{prefix}defl_{name}", default)
            except PETSc.Error:
                raise InputError(f"PETSc option -{prefix}defl_{name} "
                                 f"{db.getString(prefix + 'defl_' + name, '')!r} of the deflated "
                                 f"solver: not {'an integer' if isinstance(default, int) else 'a number'}"
                                 ) from None
        if k is not None:
            opt["k"] = int(k)
        if opt["k"] < 0 or opt["max_it"] < 1 or opt["max_refine"] < 0 or not opt["growth"] > 1:
            raise InputError(f"deflated solver options (-{prefix}defl_*): need k >= 0, max_it >= 1, "
                             f"max_refine >= 0, growth > 1; got {opt}")
        self.opt = opt
        self.deflate = bool(deflate) and opt["k"] > 0
        self.k = opt["k"] if self.deflate else 0
        self.lo, self.hi = A.getOwnershipRange()
        nloc = self.hi - self.lo
        self.W = np.zeros((nloc, 0))
        self.AW = np.zeros((nloc, 0))
        self.ritz = np.zeros(0)
        self._E = None
        self._S_of, self._f, self.STW = None, None, None
        self.shift = 2.0
        self.op = PETSc.Mat().createPython(A.getSizes(), _DeflatedOperator(self), comm=self.comm)
        self.op.setUp()
        ksp = PETSc.KSP().create(self.comm)
        ksp.setOptionsPrefix(prefix)
        ksp.setType(PETSc.KSP.Type.CG)
        ksp.setNormType(PETSc.KSP.NormType.UNPRECONDITIONED)
        ksp.setTolerances(rtol=opt["rtol"], atol=0.0, max_it=opt["max_it"])
        pc = ksp.getPC()
        if self.comm.getSize() == 1:
            pc.setType(PETSc.PC.Type.ICC)
        else:
            pc.setType(PETSc.PC.Type.BJACOBI)
            if not db.hasName(prefix + "sub_pc_type"):
                db.setValue(prefix + "sub_pc_type", "icc")
        ksp.setOperators(self.op, A)
        set_from_options(ksp, prefix)
        self._rtol = ksp.getTolerances()[0]      # -tau_ksp_rtol wins over the preset's
        self.opt["rtol"] = self._rtol
        self.cg = ksp
        self.r, self.y = A.createVecs()
        self.rhs, self.dx = A.createVecs()
        self.info = SolveInfo()
        self.norm_bound = None
        self.n_solves = 0
        self.iterations = []          # CG iterations of every solve (refinements summed)
        self.n_refresh = 0            # refreshes of the deflation space (SLEPc or inverse iteration)
        self.base_it = None           # iterations of the first solve after the last refresh
        self.soft_error = 0.0         # of the last solve (see solve)
        self._since_refresh = 0
        self._stale = True            # the space needs computing (no vectors yet)
        self._direct = None

    # ------------------------------------------------------------------ small dense algebra
    @property
    def k_active(self) -> int:
        return self.W.shape[1]

    def WT(self, v_local: np.ndarray, M: np.ndarray | None = None) -> np.ndarray:
        """(M^T v) for a local block M (default W), summed over the ranks (v: one vector, or
        the columns of a block)."""
        M = self.W if M is None else M
        out = M.T @ v_local
        return self.mpi.allreduce(out) if self.comm.getSize() > 1 else out

    def coarse(self, c: np.ndarray) -> np.ndarray:
        """E^-1 c (E = W^T N W, its Cholesky factor)."""
        return cho_solve(self._E, c)

    def _gram(self, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
        G = X.T @ Y
        return self.mpi.allreduce(G) if self.comm.getSize() > 1 else G

    def _matmult_block(self, X: np.ndarray) -> np.ndarray:
        """N X for a local block X (nloc x m), column by column with the PETSc Mat."""
        out = np.empty_like(X)
        for c in range(X.shape[1]):
            self.rhs.setArray(X[:, c])
            self.A.mult(self.rhs, self.r)
            out[:, c] = self.r.getArray(readonly=True)
        return out

    def _set_space(self, X: np.ndarray) -> None:
        """Take the span of the local block X as the deflation space (orthonormalised: W^T W
        = I, by Cholesky QR twice); computes N W and E for the loaded N."""
        for _ in range(2):
            G = self._gram(X, X)
            L = np.linalg.cholesky(G + 1e-300 * np.eye(len(G)))
            X = np.linalg.solve(L, X.T).T
        self.W = np.ascontiguousarray(X)
        self._update_coarse()

    def set_factor(self, S_of) -> None:
        """N = S S^T, ``S_of()`` the current S (a PETSc Mat with N's row layout): E = W^T N W
        is then formed as (S^T W)^T (S^T W), and W^T N y as (S^T W)^T (S^T y).  Near jamming
        E holds lambda_1 ~ 1e-8 or less: from N W it carries a relative error ~ eps ||N|| /
        lambda_1 (1e-8), from S^T W ~ eps / sqrt(lambda_1) -- the soft mode's coefficient,
        which carries sigma, is then as accurate as the direct solve makes it."""
        self._S_of = S_of
        self._f = None

    def _ST_block(self, X: np.ndarray) -> np.ndarray:
        """S^T X for a local block X (rows of N), local rows of the result."""
        S = self._S_of()
        if self._f is None:
            self._f, _ = S.createVecs()
        out = []
        for c in range(X.shape[1]):
            self.rhs.setArray(X[:, c])
            S.multTranspose(self.rhs, self._f)
            out.append(self._f.getArray(readonly=True).copy())
        return np.column_stack(out)

    def _update_coarse(self) -> None:
        """N W and the Cholesky factor of E = W^T N W for the N loaded now."""
        if not self.k_active:
            return
        self.AW = self._matmult_block(self.W)
        if self._S_of is not None:
            self.STW = self._ST_block(self.W)
            E = self._gram(self.STW, self.STW)
        else:
            E = self._gram(self.W, self.AW)
        E = 0.5 * (E + E.T)
        try:
            self._E = cho_factor(E)
        except LinAlgError:
            raise SingularOperator(f"{self.prefix}deflated solve: the coarse matrix W^T N W is not "
                                   f"positive definite; N is singular to working precision") from None

    # ------------------------------------------------------------------ the deflation space
    def compute_space(self) -> np.ndarray:
        """The k lowest eigenpairs of the loaded N from SLEPc (prefix ``tau_defl_``; by default
        shift-and-invert on a factor of its own): sets W, returns the eigenvalues."""
        from .spectrum import LowSpectrum  # noqa: PLC0415  (SLEPc is loaded only when needed)
        spec = LowSpectrum(self.A, k=self.k, prefix=self.prefix + "defl_", parallel=self.parallel)
        try:
            lam, vecs = spec.solve(vectors=True)
        finally:
            spec.destroy()
        X = np.column_stack([v.getArray(readonly=True).copy() for v in vecs])
        for v in vecs:
            v.destroy()
        self._set_space(X)
        self.ritz = np.asarray(lam)
        self.n_refresh += 1
        self._stale = False
        self.base_it, self._since_refresh = None, 0
        return self.ritz

    def refresh(self, tol: float = 1e-8) -> np.ndarray:
        """One step of subspace inverse iteration with this solver: Z = N^-1 W (deflated CG,
        to ``tol``), Rayleigh-Ritz of N on [W, Z]; W becomes the k lowest Ritz vectors.
        No SLEPc, no factorisation.  Returns the Ritz values."""
        if not self.k_active:
            return self.compute_space()
        Z = np.empty_like(self.W)
        self._rtol = tol
        try:
            for c in range(self.k_active):
                self.rhs.setArray(self.W[:, c])
                self._deflated_cg(self.rhs, self.y, "refresh of the deflation space")
                Z[:, c] = self.y.getArray(readonly=True)
        finally:
            self._rtol = self.opt["rtol"]
        Q = np.hstack([self.W, Z])
        for _ in range(2):
            G = self._gram(Q, Q)
            w, U = np.linalg.eigh(0.5 * (G + G.T))
            keep = w > 1e-14 * w.max()
            Q = Q @ (U[:, keep] / np.sqrt(w[keep]))
        AQ = self._matmult_block(Q)
        H = self._gram(Q, AQ)
        theta, Y = np.linalg.eigh(0.5 * (H + H.T))
        self._set_space(Q @ Y[:, :self.k])
        self.ritz = theta[:self.k]
        self.n_refresh += 1
        self.base_it, self._since_refresh = None, 0
        return self.ritz

    # ------------------------------------------------------------------ solves
    def _deflated_cg(self, b: PETSc.Vec, x: PETSc.Vec, what: str) -> int:
        """x = N^-1 b by CG on P N y = P b (rhs and result in PETSc Vecs); the iterations."""
        ba = b.getArray(readonly=True)
        if self.k_active:
            c = self.coarse(self.WT(ba))
            self.r.setArray(ba - self.AW @ c)          # P b
        else:
            self.r.setArray(ba)
        nb, npb = vec_norms(b, self.r)
        # CG's test is relative to its right-hand side P b: make it relative to b
        self.cg.setTolerances(rtol=min(0.1, self._rtol * nb / max(npb, 1e-300)))
        x.set(0.0)
        try:
            self.cg.solve(self.r, x)
        except PETSc.Error as exc:
            raise SingularOperator(f"{self.prefix}deflated solve ({what}): the preconditioner "
                                   f"failed ({exc}); N is singular to working precision") from None
        reason, its = self.cg.getConvergedReason(), self.cg.getIterationNumber()
        if reason < 0:
            name = reason_name(reason)
            where = (f"with {self.k_active} deflation vector(s)" if self.k_active
                     else "without deflation")
            if name in ("DIVERGED_PCSETUP_FAILED", "DIVERGED_PC_FAILED", "DIVERGED_NANORINF",
                        "DIVERGED_INDEFINITE_PC", "DIVERGED_INDEFINITE_MAT"):
                raise SingularOperator(f"{self.prefix}deflated CG ({what}) failed: {name} after "
                                       f"{its} iterations {where}; N is singular to working "
                                       f"precision")
            raise SolveError(f"{self.prefix}deflated CG ({what}) did not converge: {name} after "
                             f"{its} iterations {where} (residual "
                             f"{self.cg.getResidualNorm():.2e}, rtol {self.opt['rtol']:.0e}); "
                             f"N is too ill-conditioned for this solver: deflate more modes "
                             f"(-{self.prefix}defl_k) or use the direct preset")
        if self.k_active:
            if self._S_of is not None:
                WNy = self._gram(self.STW, self._ST_block(x.getArray(readonly=True)[:, None]))[:, 0]
            else:
                WNy = self.WT(x.getArray(readonly=True), self.AW)
            xa = x.getArray()
            xa += self.W @ (c - self.coarse(WNy))
        return its

    def solve(self, rhs: PETSc.Vec, x: PETSc.Vec, what: str = "") -> SolveInfo:
        """x = N^-1 rhs for the loaded N: deflated CG, the true residual checked, refined as
        the preset asks; SolveError if CG does not converge or the result is not accurate."""
        if self.norm_bound is None:
            self.norm_bound = self.A.norm(PETSc.NormType.INFINITY)
        if self.deflate and self._stale:
            self.compute_space()
        elif self.k_active:
            self._update_coarse()
        its = self._deflated_cg(rhs, x, what)
        refinements = 0
        cb = self.coarse(self.WT(rhs.getArray(readonly=True))) if self.k_active else None
        while True:
            self._residual(rhs, x)
            nr, nb, nx = vec_norms(self.r, rhs, x)
            rel = nr / nb if nb > 0 else nr
            berr = backward_error(nr, nx, nb, self.norm_bound)
            # the error along the deflation space, relative to x's part there: ||E^-1 W^T r||
            # / ||E^-1 W^T b||.  The backward error hides it (near jamming an error 1e-8 in
            # the soft mode's coefficient leaves a residual lambda_1 1e-8 |x|: berr ~ 1e-17)
            soft = 0.0
            if self.k_active:
                cr = self.coarse(self.WT(self.r.getArray(readonly=True)))
                soft = float(np.linalg.norm(cr) / max(np.linalg.norm(cb), 1e-300))
            self.soft_error = soft
            if (berr <= self.opt["refine_above"] and soft <= self.opt["soft_tol"]) \
                    or refinements >= self.opt["max_refine"]:
                break
            self.r.copy(self.dx)
            its += self._deflated_cg(self.dx, self.y, what + " (refinement)")
            x.axpy(1.0, self.y)
            refinements += 1
        if not np.isfinite(berr) or berr > BACKWARD_ERROR_FAIL:
            raise SingularOperator(f"{self.prefix}deflated solve ({what}): backward error "
                                   f"{berr:.2e} after {refinements} refinement(s); N is singular "
                                   f"to working precision")
        if berr > BERR_TARGET:
            raise SolveError(f"{self.prefix}deflated solve ({what}) did not reach the direct "
                             f"solve's accuracy: relative residual {rel:.2e}, backward error "
                             f"{berr:.2e} after {refinements} refinement(s) and {its} iterations")
        self.n_solves += 1
        self.iterations.append(its)
        self._schedule_refresh(its)
        self.info = SolveInfo(0, rel, berr, its)
        return self.info

    def _residual(self, rhs: PETSc.Vec, x: PETSc.Vec) -> None:
        """self.r = rhs - N x; with N = S S^T known (``set_factor``) as rhs - S (S^T x): near
        jamming S^T x (the velocities, ~ sqrt(lambda_1) |x|) is formed to eps relative, so
        the residual along the soft modes is ~1e4 times more accurate than from N x, and a
        refinement corrects the soft mode's coefficient (as for least squares by the
        semi-normal equations)."""
        if self._S_of is None:
            self.A.mult(x, self.r)
        else:
            S = self._S_of()
            if self._f is None:
                self._f, _ = S.createVecs()
            S.multTranspose(x, self._f)
            S.mult(self._f, self.r)
        self.r.aypx(-1.0, rhs)

    def _schedule_refresh(self, its: int) -> None:
        """Refresh the space for the next solve when the iterations have grown by ``growth``
        since the first solve after the last refresh, or every ``refresh_every`` solves."""
        if not self.deflate:
            return
        self._since_refresh += 1
        if self.base_it is None:
            self.base_it = max(its, 1)
            return
        every = self.opt["refresh_every"]
        if its > self.opt["growth"] * self.base_it or (every and self._since_refresh >= every):
            self.refresh()

    # ------------------------------------------------------------------ CholeskySolver's face
    @property
    def ksp(self) -> PETSc.KSP:
        """A direct factor of N (built on first use, prefix ``tau_direct_``): what the
        spectra's shift-and-invert needs (omega_min, the analyses)."""
        if self._direct is None:
            self._direct = CholeskySolver(self.A, self.prefix + "direct_", "direct", self.parallel)
            self._direct.norm_bound = self.norm_bound
        return self._direct.ksp

    @property
    def package(self) -> str:
        pc = self.cg.getPC()
        return f"{pc.getType()}"

    def describe(self) -> str:
        pc = self.cg.getPC()
        sub = ""
        if pc.getType() == PETSc.PC.Type.BJACOBI:
            sub = "/" + (PETSc.Options().getString(self.prefix + "sub_pc_type", "") or "ilu")
        return f"deflated cg+{pc.getType()}{sub}, {self.k} deflation vector(s)"

    def resolved_options(self) -> dict[str, str]:
        p = self.prefix
        return {f"{p}ksp_type": self.cg.getType(), f"{p}pc_type": self.cg.getPC().getType(),
                f"{p}defl_k": str(self.k)}

    def destroy(self):
        for o in (self.cg, self.op, self.r, self.y, self.rhs, self.dx, self._f):
            if o is not None:
                o.destroy()
        if self._direct is not None:
            self._direct.destroy()
            self._direct = None



def force_solver(A: PETSc.Mat, prefix: str, preset: str, parallel: str):
    """The solver of N x = b the preset names: :class:`DeflatedSolver` for ``"deflated"``,
    else the direct :class:`solvers.CholeskySolver`."""
    if preset not in PRESETS:
        raise ValueError(f"solver preset must be one of {sorted(PRESETS)}, got {preset!r}")
    if preset == "deflated":
        return DeflatedSolver(A, prefix, parallel)
    return CholeskySolver(A, prefix, preset, parallel)
