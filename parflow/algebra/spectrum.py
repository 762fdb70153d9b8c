"""Low spectrum of N with SLEPc (DESIGN §4).

The eigenvalues of N = S S^T are omega^2 (the non-zero spectrum of the stiffness S^T S of the
equivalent spring network), so omega_min = sqrt(lambda_min(N)).

Krylov-Schur, Hermitian, shift-and-invert at target 0 on a Cholesky factor (prefix ``spec_``;
CHOLMOD on one rank, MUMPS on several).  ``-spec_bv_reproducible_random`` is set by default
so that 1 and 2 ranks start from the same vector.  SLEPc is imported only when a scene asks for
spectra.
"""
from __future__ import annotations

import numpy as np
from petsc4py import PETSc

from ..errors import InputError
from .solvers import SolveError, configure_cholesky, set_from_options


class SpectrumError(SolveError):
    pass


class LowSpectrum:
    """k lowest eigenpairs of a symmetric positive (semi-)definite PETSc Mat."""

    def __init__(self, A, k: int = 1, prefix: str = "spec_", tol: float = 1e-10,
                 max_it: int = 500, parallel: str = "mumps", ksp=None):
        """``ksp``: an existing KSP whose operator is ``A`` with a direct factor (the force
        solver's): the shift-and-invert at target 0 then reuses its factorisation instead of
        factorising A again.  Otherwise the ST gets its own KSP (prefix ``spec_st_``)."""
        from slepc4py import SLEPc      # at first use: SLEPc is initialised only when asked for
        if k < 1:
            raise ValueError(f"number of eigenpairs k must be >= 1, got {k}")
        self.A, self.k, self.prefix = A, int(k), prefix
        comm = A.getComm()
        opts = PETSc.Options()
        if not opts.hasName(prefix + "bv_reproducible_random"):
            opts.setValue(prefix + "bv_reproducible_random", "true")
        eps = SLEPc.EPS().create(comm)
        eps.setOptionsPrefix(prefix)
        eps.setOperators(A)
        eps.setProblemType(SLEPc.EPS.ProblemType.HEP)
        eps.setType(SLEPc.EPS.Type.KRYLOVSCHUR)
        eps.setDimensions(self.k, PETSc.DECIDE, PETSc.DECIDE)
        eps.setTarget(0.0)
        eps.setWhichEigenpairs(SLEPc.EPS.Which.TARGET_MAGNITUDE)
        eps.setTolerances(tol, max_it)
        st = eps.getST()
        st.setType(SLEPc.ST.Type.SINVERT)
        self._shared = ksp is not None
        if ksp is not None:
            st.setKSP(ksp)
        else:
            configure_cholesky(st.getKSP(), prefix + "st_", parallel)
        eps.setFromOptions()
        self.eps = eps

    def solve(self, vectors: bool = False):
        """Return (eigenvalues ascending, list of eigenvector Vecs or None)."""
        # The values of A change between calls (same Mat object): setting the operators
        # again makes the spectral transformation refactor A.
        self.eps.setOperators(self.A)
        try:
            self.eps.solve()
        except PETSc.Error as exc:
            raise SpectrumError(f"{self.prefix}eigensolve failed (factorisation of N at target 0: "
                                f"N is singular?): {exc}") from None
        nconv = self.eps.getConverged()
        if nconv < self.k:
            raise SpectrumError(f"{self.prefix}eigensolve: only {nconv} of {self.k} eigenpairs "
                                f"converged (reason {self.eps.getConvergedReason()}); "
                                f"raise -{self.prefix}eps_max_it or -{self.prefix}eps_ncv")
        vals, vecs = [], []
        for m in range(nconv):
            if vectors:
                v, _ = self.A.createVecs()
                vals.append(self.eps.getEigenpair(m, v).real)
                vecs.append(v)
            else:
                vals.append(self.eps.getEigenvalue(m).real)
        order = np.argsort(vals)[: self.k]
        vals = np.asarray(vals)[order]
        return vals, ([vecs[o] for o in order] if vectors else None)

    def destroy(self):
        if self._shared:
            # destroying the ST resets its KSP (KSPReset drops the factor and the operators):
            # hand it a private KSP first, so the shared solver stays usable
            dummy = PETSc.KSP().create(self.A.getComm())
            self.eps.getST().setKSP(dummy)
            dummy.destroy()
        self.eps.destroy()


def init_slepc() -> None:
    """Initialise SLEPc on every rank at start-up (cli.init_petsc), not where omega_min first
    asks for it: SLEPc's finalisation at interpreter exit is collective on COMM_WORLD, and a
    SLEPc started on some ranks only hangs the exit (solver.parallel = "threads": omega_min
    on rank 0 alone; rank 0 hung in finalisation, the others in MPI_Finalize).  ~10 ms."""
    try:
        from slepc4py import SLEPc  # noqa: F401
    except ImportError:             # (omega_min then fails where it is asked for)
        pass


def omega_from_lambda(lam: np.ndarray) -> np.ndarray:
    """omega = sqrt(lambda), with round-off negatives clipped to 0."""
    return np.sqrt(np.clip(lam, 0.0, None))


def on_force_factor(system, k: int = 1) -> "LowSpectrum":
    """The k lowest eigenpairs of a bonded system's N by shift-and-invert at 0 on the force
    solver's factor (already loaded at the configuration): no second factorisation of N."""
    return LowSpectrum(system.ops.N, k=k, parallel=system.parallel, ksp=system.tau_solver.ksp)


def lowest_omega(spec: "LowSpectrum") -> float:
    """omega_min = sqrt(lambda_min) from a solve of ``spec``."""
    lam, _ = spec.solve()
    return float(omega_from_lambda(lam[:1])[0])


def omega_min_on(system) -> float:
    """omega_min of a bonded system's loaded N, on the force solver's factor."""
    spec = on_force_factor(system, 1)
    try:
        return lowest_omega(spec)
    finally:
        spec.destroy()


def omega_min(A, k: int = 1) -> float:
    sp = LowSpectrum(A, k=k)
    try:
        lam, _ = sp.solve()
    finally:
        sp.destroy()
    return float(omega_from_lambda(lam[:1])[0])


def slice_interval(A, wmin: float, wmax: float) -> np.ndarray:
    """Every eigenvalue of the symmetric positive semi-definite ``A`` in [wmin^2, wmax^2],
    ascending, by SLEPc spectrum slicing (Krylov-Schur, shift-and-invert on MUMPS with its
    inertia; options prefix ``spec_``)."""
    from slepc4py import SLEPc      # at first use: SLEPc is initialised only when asked for
    eps = SLEPc.EPS().create(A.getComm())
    eps.setOptionsPrefix("spec_")
    eps.setOperators(A)
    eps.setProblemType(SLEPc.EPS.ProblemType.HEP)
    eps.setType(SLEPc.EPS.Type.KRYLOVSCHUR)
    eps.setWhichEigenpairs(SLEPc.EPS.Which.ALL)
    # the lower end slightly below wmin^2 (and below 0 for wmin = 0: N is positive definite)
    lo = wmin ** 2 * (1 - 1e-9) if wmin > 0 else -1e-10 * wmax ** 2
    eps.setInterval(lo, wmax ** 2)
    st = eps.getST()
    st.setType(SLEPc.ST.Type.SINVERT)
    ksp = st.getKSP()
    ksp.setType(PETSc.KSP.Type.PREONLY)
    pc = ksp.getPC()
    pc.setType(PETSc.PC.Type.CHOLESKY)
    pc.setFactorSolverType("mumps")
    opts = PETSc.Options()
    if not opts.hasName("spec_st_mat_mumps_icntl_13"):
        opts.setValue("spec_st_mat_mumps_icntl_13", 1)     # inertia needs the full factor
    try:
        set_from_options(eps, "spec_")
    except InputError:
        eps.destroy()
        raise
    try:
        eps.solve()
    except PETSc.Error as exc:
        eps.destroy()
        raise SpectrumError(f"spectrum slicing failed: {exc}") from None
    n = eps.getConverged()
    lam = np.sort(np.array([eps.getEigenvalue(m).real for m in range(n)]))
    eps.destroy()
    return lam
