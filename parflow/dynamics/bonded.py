"""Force evaluation of a bonded system: geometry -> S, N -> solve N tau = -b -> V_na.

This is the narrow boundary between replicated numpy geometry and distributed PETSc algebra.

Equations (DESIGN §2), with E the velocity gradient and Omega = det h:
    b_alpha  = n_alpha . E r_alpha                    (= (S V_f)_alpha)
    N tau    = -b                                     (force balance + rigid rods, S V = 0)
    V_na     = S^T tau,   V = V_f + V_na
    sigma    = |V_na|^2 / Omega = -<tau|b> / Omega    (two estimates; they agree to ~cond(N) eps)
    p        = sum_alpha tau_alpha l_alpha / (d Omega)
tau > 0 is compression.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..algebra.deflated import force_solver
from ..algebra.operators import RigidityOperators
from ..algebra.solvers import (REUSE_FACTOR, CholeskySolver, SingularOperator, SolveInfo,
                               backward_error, comm_self, resolve_parallel)
from ..geometry import cell_at, pair_geometry
from ..observables import stress
from ..state import State


@dataclass
class Force:
    """Everything known at one configuration after the force solve (replicated arrays)."""

    gamma: float
    h: np.ndarray
    r: np.ndarray        # (Nc, d) pair vectors
    ell: np.ndarray      # (Nc,) lengths
    n: np.ndarray        # (Nc, d) unit vectors
    b: np.ndarray        # (Nc,) affine rates
    tau: np.ndarray      # (Nc,) forces, > 0 compressive
    V_na: np.ndarray     # (N, d) non-affine velocities
    sigma: float         # |V_na|^2 / Omega
    sigma_tb: float      # -<tau|b> / Omega
    pressure: float
    info: SolveInfo

    @property
    def sigma_mismatch(self) -> float:
        return abs(self.sigma - self.sigma_tb) / max(abs(self.sigma), 1e-300)

    @property
    def ds(self) -> np.ndarray:
        """ds/dgamma = h^-1 V_na (the cell carries the affine part)."""
        return self.V_na @ np.linalg.inv(self.h).T


# A force solve with a reused factor (PCG on N(s), preconditioned by the factor of the N
# loaded earlier in the step) is accepted at this backward error -- what the direct
# solve reaches (4e-17 measured at Nc = 1.9e6, sigma = 1.4e4) -- within this many
# iterations; otherwise N(s) is factorised (docs/solvers.md, "Reusing the factor").
REUSE_BERR = 1e-16
REUSE_MAX_IT = 25
# Intermediate force solves of a step (Heun's predictor, RKC's stages and its power
# iteration) with integrator.stage_rtol > 0: PCG on N(s) preconditioned by the factor loaded
# last, to a relative error stage_rtol in the energy norm, ||dtau||_N / ||tau||_N (= the
# relative error of V_na and of ds/dgamma: |S^T x|^2 = x.N x), estimated by the
# preconditioned residual sqrt(r.M^-1 r) (M, the factor, is close to N); within
# STAGE_MAX_IT iterations, or N(s) is factorised there (and serves the stages that follow).
STAGE_MAX_IT = 12
PROJ_RTOL = 1e-8                 # the projection's Newton steps by PCG (project(pcg=True))
# A force whose sigma identity |sigma - sigma_tb| / sigma is above IDENTITY_RTOL (near
# jamming: round-off of the solve along the softest mode, ~1e-15 sigma on networks) is
# corrected from a residual computed in extended precision (RigidityOperators.
# residual_extended), at most IDENTITY_MAX_REFINE times while each gains 10x; the
# correction's own solve: the loaded factor applied once (N loaded at s), or PCG on it to
# IDENTITY_PCG_RTOL (a reused factor).  docs/solvers.md, "The sigma identity near jamming".
IDENTITY_RTOL = 1e-11
IDENTITY_MAX_REFINE = 2
IDENTITY_PCG_RTOL = 1e-6
# solver.reuse_factor = "auto": on for models that ask for it (a 2D network's factor costs
# ~20-30 solves at Nc = 1.9e6) from this many rows of N, and with the "direct" preset only
REUSE_AUTO_MIN_NC = 250_000


def resolve_reuse(reuse: str, n_rows: int, preset: str, model_allows: bool) -> bool:
    """Whether the last force solve of a step reuses the step's factor (see evaluate)."""
    if reuse not in REUSE_FACTOR:
        raise ValueError(f"solver.reuse_factor must be one of {REUSE_FACTOR}, got {reuse!r}")
    if preset == "deflated":
        return False             # no factor to reuse: the deflated CG is its own iteration
    if reuse == "auto":
        return model_allows and preset == "direct" and n_rows >= REUSE_AUTO_MIN_NC
    return reuse == "on"


class BondedSystem:
    """Operators and solvers for a state with persistent bonds (chain, network)."""

    def __init__(self, comm, state: State, preset: str = "direct", parallel: str = "auto",
                 reuse_factor: bool = False):
        if state.bonds is None:
            raise ValueError("BondedSystem needs a state with bonds")
        state.bonds.validate(state.n)
        self.state = state
        bd = state.bonds
        self.parallel = resolve_parallel(parallel, len(bd), comm.getSize())
        if preset == "deflated" and parallel == "auto" and self.parallel == "replicated" \
                and comm.getSize() > 1:
            # the deflated CG runs on the row-distributed N; a direct factor, when one is
            # asked for (SLEPc's first space, the spectra's shift-and-invert), is gathered and
            # factorised by CHOLMOD (beyond AUTO_REPLICATED_MAX_NC rows: MUMPS, as resolved)
            self.parallel = "redundant"
        # the communicator of the algebra: COMM_SELF when every rank holds the whole system
        if self.parallel in ("replicated", "threads") and comm.getSize() > 1:
            comm = comm_self()
        self.comm = comm
        self.ops = RigidityOperators(comm, state.n, state.d, bd.i, bd.j)
        # the preset chooses the solver: CHOLMOD/MUMPS Cholesky, or the deflated CG
        # (algebra.deflated: no factorisation in a step)
        self.tau_solver = force_solver(self.ops.N, "tau_", preset,
                                       self.parallel if preset == "deflated" else parallel)
        self.tau_solver.norm_bound = self.ops.norm_bound
        if preset == "deflated":
            self.tau_solver.set_factor(self.ops.S_at)     # N = S S^T: the accurate coarse solve
        # The projection reuses the force solver (same N: no second factorisation; with the
        # deflated preset, a deflated solve per projection iteration, to the same accuracy).
        self.proj_solver = self.tau_solver
        self._x = self.ops.tau.duplicate()   # solution of other solves with N
        self.n_factor = 0          # numeric (re)factorisations requested
        self.reuse_factor = bool(reuse_factor)
        self.n_reused = 0          # force solves done with a reused factor
        self.n_reuse_failed = 0    # ... that fell back to a factorisation
        self.n_stage_pcg = 0       # intermediate solves (stage_rtol) on the loaded factor
        self.n_stage_failed = 0    # ... that fell back to a factorisation
        self.pcg_iterations = 0    # PCG iterations of both kinds
        self.n_refreshed = 0       # forces at a step's start evaluated again (heun.Stall)
        self.n_jvp = 0             # Jacobian-vector products (a solve each; ros2's stages)
        self.n_identity_refined = 0  # forces corrected in extended precision (IDENTITY_RTOL)
        self.krylov_iterations = 0  # GMRES iterations of ros2's stage equations
        self._pattern = None       # the fixed sparse patterns of linearised() (built on demand)

    @property
    def omega(self) -> float:
        return self.state.volume

    def geometry(self, s: np.ndarray, gamma: float):
        st, bd = self.state, self.state.bonds
        h = cell_at(st.h0, st.E, gamma)
        r, ell, n, b = pair_geometry(s, h, st.E, bd.i, bd.j, bd.shift)
        return h, r, ell, n, b

    def load(self, n: np.ndarray) -> None:
        """Put the values of S and N for unit vectors n into the PETSc Mats."""
        self.ops.update(n)
        self.n_factor += 1

    def evaluate(self, s: np.ndarray, gamma: float, what: str = "force", reuse: bool = False,
                 rtol: float = 0.0, guess: np.ndarray | None = None,
                 max_it: int | None = None, intermediate: bool = False) -> Force:
        """Solve N tau = -b at configuration (s, gamma); leaves N loaded at (s, gamma) --
        except with ``reuse`` (and reuse_factor on): then N(s) tau = -b is solved by PCG
        preconditioned by the factor already loaded (a nearby configuration's, e.g. the
        step's predictor), and the Mat keeps that configuration's values until ``sync()``.
        If the PCG does not reach REUSE_BERR in REUSE_MAX_IT iterations, N(s) is factorised.
        ``rtol`` > 0 (an intermediate solve of a step): the same PCG to the relative
        energy-norm error ``rtol`` (STAGE_MAX_IT iterations, then a factorisation), started
        from ``guess`` (tau of a nearby configuration, e.g. the previous stage's); ``max_it``
        replaces STAGE_MAX_IT.  A force whose sigma identity is off by more than IDENTITY_RTOL
        is corrected in extended precision (:meth:`_refine_identity`) -- unless it is
        ``intermediate`` (a stage of a step: not recorded, and its tau's ~1e-9 error along the
        soft mode is far below the step's own) or solved only to ``rtol``."""
        h, r, ell, n, b = self.geometry(s, gamma)
        tau = None
        if rtol > 0 and self.n_factor > 0 and self.stage_pcg_possible:
            tau, info = self._solve_reused(n, -b, what, rtol=rtol, guess=guess, max_it=max_it)
        elif reuse and self.reuse_factor and self.n_factor > 0:
            tau, info = self._solve_reused(n, -b, what)
        if tau is None:
            self.load(n)
            ops = self.ops
            ops.set_local(ops.rhs, -b)
            info = self.tau_solver.solve(ops.rhs, ops.tau, what)
            tau = ops.gather(ops.tau)
        else:
            self.ops.set_unit_vectors(n)
        F = self._force(gamma, h, r, ell, n, b, tau, info)
        if not intermediate and rtol == 0 and F.sigma_mismatch > IDENTITY_RTOL \
                and self.stage_pcg_possible:
            F = self._refine_identity(F, what)
        return F

    def _refine_identity(self, F: Force, what: str) -> Force:
        """F with tau corrected from residuals in extended precision until the sigma
        identity is within IDENTITY_RTOL (see there); F itself where that gains nothing.
        The correction solves N(s) x = r with the
        factor: loaded at s (applied once: x needs only a few correct digits, its size is the
        identity's error), or of a nearby configuration (PCG on it to IDENTITY_PCG_RTOL)."""
        best = F
        for _ in range(IDENTITY_MAX_REFINE):
            r = self.ops.residual_extended(best.tau, best.b, best.n)
            if self.ops.values_stale:
                x, _ = self._solve_reused(best.n, r, what + " (identity)",
                                          rtol=IDENTITY_PCG_RTOL, tally=False)
                if x is None:
                    return best
            else:
                x = self._apply(r, what + " (identity)")
            G = self._force(best.gamma, best.h, best.r, best.ell, best.n, best.b,
                            best.tau + x, best.info)
            if not G.sigma_mismatch * 10 <= best.sigma_mismatch:
                return best
            best = G
            self.n_identity_refined += 1
            if best.sigma_mismatch <= IDENTITY_RTOL:
                break
        return best

    def evaluate_reusing(self, s: np.ndarray, gamma: float, what: str = "force") -> Force:
        """:meth:`evaluate` with the solve by PCG on the factor loaded (to REUSE_BERR, or N(s)
        factorised there), whatever ``solver.reuse_factor`` says: for an integrator that
        loaded a factor near s on purpose (dynamics.ros2).  Without a factor (the deflated
        CG) a plain :meth:`evaluate`."""
        if not self.stage_pcg_possible:
            return self.evaluate(s, gamma, what)
        saved, self.reuse_factor = self.reuse_factor, self.n_factor > 0
        try:
            return self.evaluate(s, gamma, what, reuse=True)
        finally:
            self.reuse_factor = saved

    def force_from_tau(self, s: np.ndarray, gamma: float, tau: np.ndarray) -> Force:
        """The Force at (s, gamma) for known rod forces tau (a restart from a checkpoint that
        stored them: the same numbers as the run that wrote it, without a solve); N is
        loaded at (s, gamma)."""
        h, r, ell, n, b = self.geometry(s, gamma)
        if tau.shape != b.shape:
            raise ValueError(f"tau has {tau.shape} entries, the system {b.shape} rods")
        self.load(n)
        return self._force(gamma, h, r, ell, n, b, np.array(tau, dtype=float), SolveInfo())

    def _force(self, gamma, h, r, ell, n, b, tau, info) -> Force:
        V_na = self.ops.ST_numpy(tau)
        omega = self.omega
        return Force(gamma, h, r, ell, n, b, tau, V_na, stress.sigma(V_na, omega),
                     stress.sigma_tb(tau, b, omega), stress.pressure(tau, ell, omega, self.state.d),
                     info)

    @property
    def stage_pcg_possible(self) -> bool:
        """Whether the force solver holds a factor to precondition with (not the deflated CG)."""
        return hasattr(self.tau_solver, "apply")

    def _solve_reused(self, n: np.ndarray, rhs: np.ndarray, what: str, rtol: float = 0.0,
                      guess: np.ndarray | None = None, max_it: int | None = None,
                      tally: bool = True):
        """PCG for N(n) x = rhs, preconditioned by the loaded factor; (x, SolveInfo) when the
        backward error reaches REUSE_BERR (``rtol`` = 0) or the estimated relative error in
        the energy norm reaches ``rtol``, (None, None) otherwise.  For the backward error the
        true residual is recomputed every iteration (it is what that test looks at); the
        energy-norm test uses the recursive one.  ``tally`` False: the solve is not counted
        as a reused or stage solve (its iterations are, in pcg_iterations)."""
        A = self.ops.matvec_at(n)
        nb = float(np.linalg.norm(rhs))
        norm_n = self.tau_solver.norm_bound
        if max_it is None:
            max_it = STAGE_MAX_IT if rtol > 0 else REUSE_MAX_IT
        if guess is not None and rtol > 0:
            x = np.array(guess, dtype=float)
            r = rhs - A(x)
        else:
            x = np.zeros_like(rhs)
            r = rhs.copy()
        z = self._apply(r, what)
        p = z.copy()
        rz = float(r @ z)
        best = np.inf
        for it in range(1, max_it + 1):
            Ap = A(p)
            pAp = float(p @ Ap)
            if not (np.isfinite(pAp) and pAp > 0):
                break
            x += (rz / pAp) * p
            # the true residual for the backward error; the recursive one is enough for the
            # energy-norm test of an intermediate solve (rtol >> round-off)
            r = r - (rz / pAp) * Ap if rtol > 0 else rhs - A(x)
            nr = float(np.linalg.norm(r))
            berr = backward_error(nr, float(np.linalg.norm(x)), nb, norm_n)
            self.pcg_iterations += 1
            if rtol == 0 and berr <= REUSE_BERR:
                self.n_reused += 1
                return x, SolveInfo(0, nr / nb if nb > 0 else nr, berr, it)
            if not np.isfinite(berr) or berr > 1e3 * best:
                break                    # diverging (loss of orthogonality)
            best = min(best, berr)
            z = self._apply(r, what)
            rz_new = float(r @ z)
            # ||e||_N^2 ~ r.M^-1 r against ||x||_N^2 = x.N x ~ x.rhs
            if rtol > 0 and abs(rz_new) <= rtol * rtol * abs(float(x @ rhs)):
                if tally:
                    self.n_stage_pcg += 1
                return x, SolveInfo(0, nr / nb if nb > 0 else nr, berr, it)
            p = z + (rz_new / rz) * p
            rz = rz_new
        if tally and rtol > 0:
            self.n_stage_failed += 1
        elif tally:
            self.n_reuse_failed += 1
        return None, None

    def _apply(self, r: np.ndarray, what: str) -> np.ndarray:
        """The loaded factor applied to a replicated vector."""
        self.ops.set_local(self.ops.rhs, r)
        self.tau_solver.apply(self.ops.rhs, self._x, what + " (reused factor)")
        return self.ops.gather(self._x)

    def ensure_loaded(self, F: Force) -> None:
        """Make N (and its factor, at the next solve) hold the configuration of ``F`` --
        after a step whose trial configurations were factorised (a failed PCG's fallback)."""
        if self.ops.loaded_n is not F.n:
            self.load(F.n)

    def linearised(self, F: Force) -> "Linearised":
        """u -> J u, the Jacobian of ds/dgamma = h^-1 V_na(s) at the configuration of ``F``
        (at fixed gamma), each product one solve with N's factor there (see
        :class:`Linearised`).  N must be loaded at F (:meth:`ensure_loaded`)."""
        if self._pattern is None:
            self._pattern = _LinearPattern(self.state)
        return Linearised(self, F, self._pattern)

    def sync(self) -> None:
        """Make the Mat hold N at the current configuration again (after a reused-factor
        evaluate): solves that follow -- spectra, point responses -- need the exact N."""
        if self.ops.values_stale:
            self.load(self.ops._n)

    def solve_N(self, rhs: np.ndarray, solver: CholeskySolver | None = None, what="") -> np.ndarray:
        """x = N^-1 rhs with the currently loaded N (replicated in and out)."""
        solver = solver or self.proj_solver
        self.ops.set_local(self.ops.rhs, rhs)
        solver.solve(self.ops.rhs, self._x, what)
        return self.ops.gather(self._x)

    def ST(self, x: np.ndarray) -> np.ndarray:
        """S^T x for a replicated x (numpy, with the loaded unit vectors)."""
        return self.ops.ST_numpy(x)

    def project(self, s: np.ndarray, gamma: float, tol: float = 1e-13, max_iter: int = 30,
                max_refactor: int = 6, pcg: bool = False):
        """Restore rod lengths: dr = -S^T N^-1 (l - l0), iterated until max|l - l0| <= tol
        (absolute, in a0).  Quasi-Newton with the loaded factor (the predictor's) while it
        contracts the error at least 4x per iteration; otherwise a Newton step: N is
        refactorised at the current point -- or, if the error grew, at the previous (better)
        point, which is restored.  Near jamming the predictor's N differs from N at the
        corrected point along its softest modes and the quasi-Newton iteration diverges for
        all but small steps; Newton converges there (at most ``max_refactor`` refactorisations).
        With ``pcg`` the Newton steps solve N(s) x = -g by PCG on the loaded factor (to
        PROJ_RTOL; a refactorisation only if that PCG fails).
        Returns (s, iterations, final error).  Raises SingularOperator if it does not
        converge (the constraints cannot be met: the system has jammed, or the step is too
        large)."""
        st, bd = self.state, self.state.bonds
        h = cell_at(st.h0, st.E, gamma)
        hinv = np.linalg.inv(h)
        # lengths computed from r = h (s_j + n - s_i) carry a round-off ~ eps |h| |s|:
        # the tolerance cannot be tighter than that (a box of 1e4 a0 gives ~1e-12 a0)
        tol = max(tol, 8 * np.finfo(float).eps * np.abs(h).max() * max(1.0, np.abs(s).max()))
        prev = None                      # (s, g, n, err) of the previous iterate
        refactors = 0
        newton = False                   # pcg: Newton steps by PCG from here on
        for it in range(max_iter + 1):
            r, ell, n, _ = pair_geometry(s, h, st.E, bd.i, bd.j, bd.shift)
            g = ell - bd.l0
            err = float(np.max(np.abs(g)))
            if err <= tol:
                return s, it, err
            if it == max_iter or not np.isfinite(err):
                break
            if prev is not None and err > 0.25 * prev[3]:
                if refactors == max_refactor:
                    break
                if not err < prev[3]:             # grew: back to the better point
                    s, g, n, err = prev
                if pcg:
                    newton = True
                else:
                    self.load(n)                  # Newton: N at this point
                refactors += 1
            prev = (s, g, n, err)
            x = self._solve_reused(n, -g, "projection", rtol=PROJ_RTOL)[0] if newton else None
            if x is None:
                if newton:                        # the PCG failed: factorise here
                    self.load(n)
                x = self.solve_N(-g, what="projection")
            else:
                self.ops.set_unit_vectors(n)      # S^T below: at this point's unit vectors
            s = s + self.ST(x) @ hinv.T
        raise SingularOperator(f"projection on the rod constraints did not converge "
                               f"(max |l - l0| = {err:.3e} after {it} iterations, "
                               f"{refactors} refactorisations)")

    def destroy(self):
        self.tau_solver.destroy()
        self._x.destroy()
        self.ops.destroy()



class _LinearPattern:
    """The sparse patterns of :class:`Linearised` for a fixed bond list (replicated scipy
    CSR, built once): B maps node displacements v (N d) to pair displacements v_j - v_i
    (Nc d); S-shaped rows (Nc x N d: -a_alpha at i, +a_alpha at j) for S and Q; the
    rod-diagonal d x d blocks (Nc d x Nc d) of the geometric stiffness."""

    def __init__(self, state: State):
        bd, d, nn = state.bonds, state.d, state.n
        nc = len(bd)
        comp = np.arange(d)
        ci, cj = d * bd.i[:, None] + comp, d * bd.j[:, None] + comp        # (Nc, d)
        self.B = sp.csr_matrix((np.tile([-1.0, 1.0], nc * d),
                                np.stack([ci.ravel(), cj.ravel()], axis=1).ravel(),
                                2 * np.arange(nc * d + 1)), shape=(nc * d, nn * d))
        self.BT = self.B.T.tocsr()
        self.s_indices = np.concatenate([ci, cj], axis=1).ravel()
        self.s_indptr = 2 * d * np.arange(nc + 1)
        rows = np.arange(nc * d).reshape(nc, d)
        self.k_indices = np.repeat(rows, d, axis=0).ravel()                # row a of rod: its d columns
        self.k_indptr = d * np.arange(nc * d + 1)
        self.shape_s = (nc, nn * d)
        self.shape_k = (nc * d, nc * d)

    def rows_S(self, a: np.ndarray) -> sp.csr_matrix:
        """The S-shaped matrix with rows -a_alpha at node i and +a_alpha at node j."""
        return sp.csr_matrix((np.concatenate([-a, a], axis=1).ravel(), self.s_indices,
                              self.s_indptr), shape=self.shape_s)


class Linearised:
    """The Jacobian J of the bonded flow ds/dgamma = h^-1 V_na(s) at one configuration, as a
    product u -> J u for the linearly implicit step (dynamics.ros2).

    With v = h u the node displacements, and at fixed gamma (DESIGN §2 for S, N, tau, b):
        dn_alpha   = (1 - n n^T)(v_j - v_i) / l_alpha                (unit vectors turn)
        f          = dS^T tau = sum_alpha tau_alpha (+-dn_alpha)      = G v   (geometric stiffness)
        d(N tau)   = -db:   N dtau = -(S (f + E v) + dS (V_f + V_na))
        dV_na      = f - S^T N^-1 (S (f + E v) + Q v),   (Q v)_alpha = dn_alpha . (E r_alpha + V_na,j - V_na,i)
    and J u = h^-1 dV_na: one solve with N's factor a product.  Near jamming its spectrum is
    real and spread down to ~ -13 sigma (rods under the large forces of the soft mode turning
    back into line: G ~ tau / l), while the flow itself changes on strains ~ 1 / (0.1 sigma):
    the stiffness that bounds an explicit step (docs/solvers.md, "A linearly implicit step")."""

    def __init__(self, system: BondedSystem, F: Force, pattern: _LinearPattern):
        st = system.state
        self.system, self.d, self.nn = system, st.d, st.n
        self.h, self.hinv, self.ET = F.h, np.linalg.inv(F.h), st.E.T
        n, ell, tau = F.n, F.ell, F.tau
        d = st.d
        proj = np.eye(d)[None] - n[:, :, None] * n[:, None, :]              # (Nc, d, d)
        self.K = sp.csr_matrix((((tau / ell)[:, None, None] * proj).ravel(), pattern.k_indices,
                                pattern.k_indptr), shape=pattern.shape_k)
        bd = st.bonds
        vp = F.r @ st.E.T + F.V_na[bd.j] - F.V_na[bd.i]
        q = np.einsum("aij,aj->ai", proj, vp) / ell[:, None]
        self.S = pattern.rows_S(n)
        self.ST = self.S.T.tocsr()
        self.Q = pattern.rows_S(q)
        self.B, self.BT = pattern.B, pattern.BT
        self.direct = system.stage_pcg_possible      # a factor to apply (not the deflated CG)

    def __call__(self, u: np.ndarray) -> np.ndarray:
        """J u for u flat (N d,) in reduced coordinates; flat out."""
        shape = (self.nn, self.d)
        v = (u.reshape(shape) @ self.h.T).ravel()
        f = self.BT @ (self.K @ (self.B @ v))
        rhs = self.S @ (f + (v.reshape(shape) @ self.ET).ravel()) + self.Q @ v
        sysm = self.system
        x = sysm._apply(rhs, "Jacobian product") if self.direct else \
            sysm.solve_N(rhs, what="Jacobian product")
        sysm.n_jvp += 1
        dv = f - self.ST @ x
        return (dv.reshape(shape) @ self.hinv.T).ravel()
