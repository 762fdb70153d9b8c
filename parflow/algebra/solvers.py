"""Linear solves with N: presets, options prefixes, convergence checks (DESIGN §4).

Policy: N's condition number reaches 1e7-1e12 near jamming, where Krylov methods do not
converge; the default is a sparse Cholesky factorisation (CHOLMOD on one rank, MUMPS on
several), its symbolic analysis reused while the pattern of N is unchanged.  Every solve
checks the KSP converged reason *and* the backward error of the result; a failure raises
:class:`SolveError` (or :class:`SingularOperator` when the factorisation breaks down, which
for a bonded network means it has jammed).

A solve whose backward error after the preset's refinements is far above round-off
(> SUSPECT_BERR, where a sound factor gives ~3e-17) is not taken as it is: it is refined
further and, if that does not bring it down, N is factorised afresh (symbolic and numeric)
and solved again; the better result is kept and counted (``CholeskySolver.n_suspect``).
Measured on a 1e5-rod chain: a solve left at 6.7e-9 by one refinement (below
BACKWARD_ERROR_FAIL), which the same N, factorised again, solved to 3.1e-17 -- a CHOLMOD
factor refactorised until its rows passed 2^31 (CHOLMOD_MARK_LIMIT, below, now prevents it).

Options: each solver has a prefix (``tau_``, ``proj_``, ``resp_``, ``spec_``).  Code defaults
are set first, then ``setFromOptions()``, so any PETSc option given in the scene's ``[petsc]``
table or on the command line (which wins) overrides them.
"""
from __future__ import annotations

import ctypes
import gc
import logging
import os
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from petsc4py import PETSc

from ..errors import InputError, collective
from ..schema import key

log = logging.getLogger("parflow")

PRESETS = {
    # name: (refinement steps allowed, relative residual that triggers refinement)
    "direct": dict(max_refine=1, refine_above=1e-10),
    "accurate": dict(max_refine=4, refine_above=1e-14),
    # no factorisation: deflated CG (algebra.deflated.DeflatedSolver; its own tolerances,
    # -tau_defl_* options); these two fields apply to its auxiliary direct factor only
    "deflated": dict(max_refine=1, refine_above=1e-10),
}
BACKWARD_ERROR_FAIL = 1e-8
# A CHOLMOD factor that PETSc refactorises again and again comes out wrong once the rows it
# has factorised pass 2^31: measured on chains, the 21 475th refactorisation at n = 1e5
# (21 475 x 1e5 = 2^31; backward error 1.6e-4, a fresh factor 4e-17) and the 42 950th at
# n = 5e4 (2.0e-4) -- and the chain ensembles' bad solves came every ~6 500 steps (~21 500
# factorisations) of a run.  The cause is guessed, not read in CHOLMOD's source: a 32-bit
# overflow of its workspace mark (cholmod_common.mark grows by n a factorisation).  The
# factor (with its cholmod_common) is rebuilt, analysed and factorised afresh, before
# CHOLMOD_MARK_LIMIT rows: bit-identical results (the same order), one analysis per 2^30 rows.
CHOLMOD_MARK_LIMIT = 2 ** 30
SUSPECT_BERR = 1e-12      # a solve above this after its refinements is refined / refactorised
EXTRA_REFINE = 4          # further refinements of such a solve, while each gains 10x,
ROUNDOFF_BERR = 1e-15     # until this


class SolveError(RuntimeError):
    """A linear solve failed; the message names the solver and its reason."""


class SingularOperator(SolveError):
    """The factorisation of N broke down: N is singular to working precision."""


PARALLEL_FACTORS = ("auto", "replicated", "redundant", "mumps", "threads")
REUSE_FACTOR = ("auto", "on", "off")      # solver.reuse_factor (dynamics.bonded.resolve_reuse)
# "auto" replicates the algebra on every rank up to this many rows of N (the CHOLMOD factor of a
# 2D network with Nc = 1e6 takes ~1 GB); beyond, the distributed MUMPS factorisation
AUTO_REPLICATED_MAX_NC = 2_000_000


@dataclass
class SolverOptions:
    """The scene's [solver] table (``schema``)."""
    preset: str = key("direct", lambda v: v in PRESETS, f"one of {sorted(PRESETS)}",
                      "the force solve: direct with its refinement, or deflated CG (docs/solvers.md)")
    parallel: str = key("auto", lambda v: v in PARALLEL_FACTORS, f"one of {list(PARALLEL_FACTORS)}",
                        "how several ranks share the algebra")
    reuse_factor: str = key("auto", lambda v: v in REUSE_FACTOR, f"one of {list(REUSE_FACTOR)}",
                            "a step's last force by PCG on its predictor's factor")


def set_blas_threads(n: int) -> int | None:
    """Set the number of threads of the BLAS that CHOLMOD's supernodal factorisation calls
    (OpenBLAS, through libblas.so.3: Debian's alternative; scripts/env.sh starts it at
    OPENBLAS_NUM_THREADS = 1).  Returns the previous number, None (nothing done) when the BLAS
    has no such control."""
    for name in ("libblas.so.3", "libopenblas.so.0"):
        try:
            lib = ctypes.CDLL(name)
            get, put = lib.openblas_get_num_threads, lib.openblas_set_num_threads
        except (OSError, AttributeError):
            continue
        prev = int(get())
        put(int(n))
        return prev
    return None


def use_cores(n: int) -> tuple[int, int | None]:
    """Let this process compute on up to ``n`` cores (solver.parallel = "threads"): widen its
    core binding to the whole node (mpirun binds each rank to one core) and give the BLAS
    min(n, cores now allowed) threads.  Returns (threads given, the BLAS's previous count, or
    None when it has no such control -- then nothing was set)."""
    try:
        os.sched_setaffinity(0, range(os.cpu_count() or 1))
    except (OSError, AttributeError):
        pass
    threads = max(1, min(n, len(os.sched_getaffinity(0))))
    return threads, set_blas_threads(threads)


def resolve_parallel(parallel: str, n_rows: int, comm_size: int) -> str:
    """The multi-rank strategy actually used for a system of ``n_rows`` rows of N.

    * ``replicated``: every rank assembles and factorises the whole N with CHOLMOD on its own
      (PETSc objects on COMM_SELF): no communication at all in a step; each rank holds the
      whole factor.  Measured on 2 cores it is the fastest choice for every size tried
      (docs/solvers.md), because a force evaluation is a handful of latency-bound steps.
    * ``redundant``: distributed N gathered onto every rank and factorised there (PCREDUNDANT).
    * ``mumps``: the distributed MUMPS Cholesky (for N too large for one rank's memory).
    * ``threads``: resolved before the run is built (``shear``): the whole run on rank 0 with
      one BLAS thread per rank, the other ranks idle -- here it only ever meets one rank.
    """
    if parallel not in PARALLEL_FACTORS:
        raise ValueError(f"solver.parallel must be one of {PARALLEL_FACTORS}, got {parallel!r}")
    if parallel == "threads":
        return "threads"          # on one rank (shear: the other ranks wait): as replicated
    if comm_size == 1:
        return "replicated"
    if parallel == "auto":
        return "replicated" if n_rows <= AUTO_REPLICATED_MAX_NC else "mumps"
    return parallel


def configure_cholesky(ksp, prefix: str, parallel: str = "mumps") -> None:
    """Code defaults for a direct solve with ``ksp`` (before its setFromOptions()).

    One rank (or a replicated system, on COMM_SELF): preonly + Cholesky with CHOLMOD.  Several
    ranks: ``parallel = "mumps"``, the distributed MUMPS Cholesky; ``"redundant"``, the matrix
    gathered on every rank and factorised there by CHOLMOD (PCREDUNDANT).
    Options already in the database (scene or command line) win over these defaults.
    """
    if parallel not in PARALLEL_FACTORS:
        raise ValueError(f"solver.parallel must be one of {PARALLEL_FACTORS}, got {parallel!r}")
    if ksp.getComm().getSize() > 1 and parallel in ("auto", "replicated", "threads"):
        raise ValueError(f"parallel = {parallel!r} on a communicator of several ranks: resolve it "
                         f"with resolve_parallel() and build the operators on COMM_SELF")
    ksp.setType(PETSc.KSP.Type.PREONLY)
    pc = ksp.getPC()
    if ksp.getComm().getSize() == 1 or parallel == "mumps":
        pc.setType(PETSc.PC.Type.CHOLESKY)
        pc.setFactorSolverType("cholmod" if ksp.getComm().getSize() == 1 else "mumps")
        return
    pc.setType(PETSc.PC.Type.REDUNDANT)
    db = PETSc.Options()
    for name, value in (("redundant_ksp_type", "preonly"), ("redundant_pc_type", "cholesky"),
                        ("redundant_pc_factor_mat_solver_type", "cholmod")):
        if not db.hasName(prefix + name):
            db.setValue(prefix + name, value)


def insert_options(options: dict[str, object], cmdline: set[str] | None = None) -> None:
    """Insert ``{name: value}`` (names without the dash) into PETSc's options database,
    skipping names that the command line already set (the command line wins)."""
    db = PETSc.Options()
    for name, value in options.items():
        name = name.lstrip("-")
        if cmdline and name in cmdline:
            continue
        if isinstance(value, bool):
            value = "true" if value else "false"
        db.setValue(name, str(value))


# the options prefixes of parflow's PETSc/SLEPc objects: (kind, what it solves)
PREFIXES = {"tau_": ("ksp", "force solver (N tau = b)"),
            "contact_": ("ksp", "contact solver (suspension LCP)"),
            "spec_": ("eps", "eigensolver (omega_min, spectra)")}
_SCRATCH = "parflowcheck_"
_OUTPUT_OPTIONS = ("monitor", "view", "log", "draw")     # printing options: not checked


def petsc_message(exc: Exception) -> str:
    """PETSc's own explanation of an error, on one line (the last line of its traceback,
    which petsc4py carries in the exception text; e.g. "Unable to find requested PC type
    nonsense")."""
    lines = [ln.strip() for ln in str(exc).splitlines()]
    lines = [ln.split("] ", 1)[1] if ln.startswith("[") and "] " in ln else ln for ln in lines]
    lines = [ln for ln in lines if ln and "() at " not in ln and not ln.startswith("error code")]
    return lines[-1] if lines else str(exc).strip()


def options_under(prefix: str) -> dict[str, str | None]:
    """The options in PETSc's database whose names begin with ``prefix`` (without dash)."""
    return {k: v for k, v in PETSc.Options().getAll().items() if k.startswith(prefix)}


def _rejected(prefix: str, exc: Exception, cmdline: set[str] | None = None, shown: str | None = None):
    """InputError naming the options given under ``prefix`` that PETSc rejected (those whose
    value PETSc's message quotes; else all of them) and what PETSc said."""
    msg = petsc_message(exc)
    given = {k: v for k, v in options_under(prefix).items()
             if not any(w in k for w in _OUTPUT_OPTIONS)}
    named = {k: v for k, v in given.items() if v not in (None, "") and
             any(v == word.strip(".,:;()'\"") for word in msg.split())} or given
    where = ""
    if cmdline is not None:
        src = {("command line" if k in cmdline else "scene's [petsc] table") for k in named}
        where = f" ({' and '.join(sorted(src))})" if src else ""
    opts = ", ".join(f"-{k}" + ("" if v in (None, "") else f" {v}") for k, v in sorted(named.items()))
    what = PREFIXES.get(prefix, ("", shown or "solver"))[1]
    return InputError(f"PETSc rejected option{'s' if len(named) > 1 else ''} {opts or prefix + '*'}"
                      f"{where} of the {what}: {msg}; fix or drop "
                      f"{'them' if len(named) > 1 else 'it'}")


def set_from_options(obj, prefix: str) -> None:
    """``obj.setFromOptions()`` (a KSP or an EPS with options prefix ``prefix``); an option
    value PETSc rejects becomes an InputError naming the option (collective: every rank
    parses the same options database at the same call)."""
    try:
        obj.setFromOptions()
    except PETSc.Error as exc:
        raise _rejected(prefix, exc) from None


def check_options(cmdline: set[str] | None = None, prefixes=tuple(PREFIXES)) -> None:
    """Parse the options given for each of parflow's solver prefixes (scene [petsc] table and
    command line, already in PETSc's database) on scratch objects of this rank, before a run
    allocates or writes anything: an unknown type, an unparsable number or a factorisation
    package that is not installed is an InputError naming the option and what PETSc said.

    The options are copied to a scratch prefix, so the real solvers still mark them as used
    (the "set but not used" warning is unchanged); the scratch KSP is a CG (not PREONLY, which
    skips the KSP options) with the code's Cholesky/CHOLMOD default, set up on a 4 x 4 SPD
    matrix so that the factorisation package is looked up.  Call on one rank (``collective``)."""
    db = PETSc.Options()
    for prefix in prefixes:
        given = {k: v for k, v in options_under(prefix).items()
                 if not any(w in k for w in _OUTPUT_OPTIONS)}
        if not given:
            continue
        kind = PREFIXES.get(prefix, ("ksp", ""))[0]
        scratch = _SCRATCH + prefix
        for k, v in given.items():
            db.setValue(scratch + k[len(prefix):], v)
        objs = []
        try:
            if kind == "eps":
                try:
                    from slepc4py import SLEPc    # at first use: only when asked for
                except ImportError:
                    continue
                eps = SLEPc.EPS().create(PETSc.COMM_SELF)
                objs.append(eps)
                eps.setOptionsPrefix(scratch)
                eps.setProblemType(SLEPc.EPS.ProblemType.HEP)
                eps.setType(SLEPc.EPS.Type.KRYLOVSCHUR)
                st = eps.getST()
                st.setType(SLEPc.ST.Type.SINVERT)
                configure_cholesky(st.getKSP(), scratch + "st_", "mumps")
                eps.setFromOptions()
                ksp = st.getKSP()
            else:
                ksp = PETSc.KSP().create(PETSc.COMM_SELF)
                objs.append(ksp)
                ksp.setOptionsPrefix(scratch)
                configure_cholesky(ksp, scratch, "mumps")
                ksp.setType(PETSc.KSP.Type.CG)
                ksp.setFromOptions()
            A = PETSc.Mat().createAIJ([4, 4], nnz=3, comm=PETSc.COMM_SELF)
            objs.append(A)
            for r in range(4):
                A.setValue(r, r, 4.0)
                if r:
                    A.setValue(r, r - 1, -1.0)
                    A.setValue(r - 1, r, -1.0)
            A.assemble()
            ksp.setOperators(A)
            ksp.setUp()
        except PETSc.Error as exc:
            raise _rejected(prefix, exc, cmdline) from None
        finally:
            for o in objs:
                o.destroy()
            for k in list(db.getAll()):
                if k.startswith(_SCRATCH):
                    db.delValue(k)


def check_options_on(comm, cmdline: set[str] | None = None) -> None:
    """:func:`check_options` on rank 0, its InputError raised on every rank (SLEPc, which
    eigensolver options need, is initialised on every rank at start-up: cli.init_petsc)."""
    collective(comm, check_options, cmdline)


@dataclass
class SolveInfo:
    reason: int = 0
    residual: float = 0.0         # ||rhs - N x|| / ||rhs||
    backward_error: float = 0.0   # ||rhs - N x|| / (||N|| ||x|| + ||rhs||)
    refinements: int = 0          # iterative refinements; for a solve with a reused factor,
                                  # the PCG iterations (BondedSystem.evaluate)


class CholeskySolver:
    """KSP on a fixed Mat with a Cholesky factor; refactors when the Mat's values change."""

    def __init__(self, A: PETSc.Mat, prefix: str, preset: str = "direct", parallel: str = "mumps"):
        if preset not in PRESETS:
            raise ValueError(f"solver preset must be one of {sorted(PRESETS)}, got {preset!r}")
        self.A = A
        self.prefix = prefix
        self.preset = PRESETS[preset]
        comm = A.getComm()
        ksp = PETSc.KSP().create(comm)
        ksp.setOptionsPrefix(prefix)
        configure_cholesky(ksp, prefix, parallel)
        ksp.setOperators(A)
        set_from_options(ksp, prefix)
        self.ksp = ksp
        self.r, _ = A.createVecs()
        self.dx, _ = A.createVecs()
        self.info = SolveInfo()
        # ||A||_inf (or an upper bound of it) for the backward error; None: computed once
        self.norm_bound = None
        self.n_suspect = 0        # solves left above SUSPECT_BERR by the preset's refinements
        self.n_refactorised = 0   # ... and still above it after EXTRA_REFINE more
        self.n_rebuilt = 0        # factors rebuilt before CHOLMOD's mark overflows
        self._state = None        # the Mat's state at the last factorisation
        self._marks = 0           # rows factorised since the factor was built
        self._cholmod = None      # whether the factor package is CHOLMOD (known at first use)

    @property
    def package(self) -> str:
        pc = self.ksp.getPC()
        if pc.getType() == PETSc.PC.Type.REDUNDANT:
            db = PETSc.Options()
            return "redundant-" + (db.getString(self.prefix + "redundant_pc_factor_mat_solver_type", "") or "petsc")
        try:
            return pc.getFactorSolverType() or "petsc"
        except PETSc.Error:
            return "none"

    def resolved_options(self) -> dict[str, str]:
        """The options in effect for this solver (code defaults as overridden)."""
        pc = self.ksp.getPC()
        p = self.prefix
        return {f"{p}ksp_type": self.ksp.getType(), f"{p}pc_type": pc.getType(),
                f"{p}pc_factor_mat_solver_type": self.package}

    def describe(self) -> str:
        pc = self.ksp.getPC()
        return f"{self.ksp.getType()}+{pc.getType()}({self.package})"

    def _fresh_factor(self) -> None:
        """Discard the factor: the next solve analyses and factorises afresh."""
        self.ksp.getPC().reset()
        self.ksp.setOperators(self.A)
        self._marks = 0

    def _ksp_solve(self, rhs, x, what):
        state = self.A.stateGet()
        if state != self._state:                 # this solve refactorises
            self._state = state
            if self._cholmod is None:
                self._cholmod = self.package.endswith("cholmod")
            if self._cholmod:
                n = self.A.getSize()[0]
                if self._marks + n > CHOLMOD_MARK_LIMIT:    # CHOLMOD_MARK_LIMIT, above
                    self._fresh_factor()
                    self.n_rebuilt += 1
                self._marks += n
        try:
            self.ksp.solve(rhs, x)
        except PETSc.Error as exc:
            raise SingularOperator(f"{self.prefix}solve: factorisation failed ({exc}); "
                                   f"N is singular to working precision") from None
        reason = self.ksp.getConvergedReason()
        if reason < 0:
            name = reason_name(reason)
            if name in ("DIVERGED_PCSETUP_FAILED", "DIVERGED_PC_FAILED", "DIVERGED_NANORINF"):
                raise SingularOperator(f"{self.prefix}solve ({what}): the Cholesky factorisation "
                                       f"failed ({name}); N is singular to working precision")
            raise SolveError(f"{self.prefix}solve ({what}) did not converge: {name}")
        return reason

    def apply(self, rhs: PETSc.Vec, x: PETSc.Vec, what: str = "") -> None:
        """x = F^-1 rhs with the current factor F, nothing else (no residual check, no
        refinement): the preconditioner of an outer iteration that checks its own residual."""
        self._ksp_solve(rhs, x, what)

    def _refine(self, rhs, x, what, max_refine: int, refined: int = 0, extra: bool = False):
        """Iterative refinement of x (rhs - A x solved with the current factor) until the
        relative residual is below the preset's refine_above or ``max_refine`` steps were
        taken in all (counting the ``refined`` ones before); ``extra`` (a suspect solve):
        until the backward error reaches ROUNDOFF_BERR, ``max_refine``, or a step gains less
        than 10x (that step undone).  (rel, berr, refinements)."""
        best = None
        while True:
            self.A.mult(x, self.r)
            self.r.aypx(-1.0, rhs)              # r = rhs - A x
            nr, nb, nx = vec_norms(self.r, rhs, x)
            rel = nr / nb if nb > 0 else nr
            berr = backward_error(nr, nx, nb, self.norm_bound)
            if extra:
                if best is not None and not berr < 0.1 * best[1]:
                    x.axpy(-1.0, self.dx)       # the last step did not help: undo it
                    return best[0], best[1], refined - 1
                if berr <= ROUNDOFF_BERR or refined >= max_refine:
                    return rel, berr, refined
                best = (rel, berr)
            elif rel <= self.preset["refine_above"] or refined >= max_refine:
                return rel, berr, refined
            self._ksp_solve(self.r, self.dx, what)
            x.axpy(1.0, self.dx)
            refined += 1

    def solve(self, rhs: PETSc.Vec, x: PETSc.Vec, what: str = "") -> SolveInfo:
        """x = A^-1 rhs with residual check and iterative refinement as the preset asks; a
        result still far off round-off (SUSPECT_BERR) is refined further and, failing that,
        solved again with a fresh factorisation (the module's doc)."""
        if self.norm_bound is None:
            self.norm_bound = self.A.norm(PETSc.NormType.INFINITY)
        reason = self._ksp_solve(rhs, x, what)
        rel, berr, refinements = self._refine(rhs, x, what, self.preset["max_refine"])
        if not berr <= SUSPECT_BERR:
            self.n_suspect += 1
            rel, berr, refinements = self._refine(rhs, x, what, refinements + EXTRA_REFINE,
                                                  refinements, extra=True)
        if not berr <= SUSPECT_BERR:
            self.n_refactorised += 1
            before, n_before = berr, refinements
            kept = x.copy()
            self._fresh_factor()                # analysed and factorised again
            try:
                reason = self._ksp_solve(rhs, x, what + ", refactorised")
                again = self._refine(rhs, x, what, self.preset["max_refine"])
            except SingularOperator:
                again = (np.inf, np.inf, 0)
            if again[1] < berr:
                rel, berr, refinements = again
            else:
                kept.copy(x)
            kept.destroy()
            log.warning("WARNING: %s%s: backward error %.1e after %d refinement(s); a fresh "
                        "factorisation gives %.1e%s", self.prefix,
                        f"solve ({what})" if what else "solve", before, n_before, again[1],
                        "" if again[1] <= berr else " (not better: the first result kept)")
        if not np.isfinite(berr) or berr > BACKWARD_ERROR_FAIL:
            raise SingularOperator(f"{self.prefix}solve ({what}): backward error {berr:.2e} after "
                                   f"{refinements} refinement(s); N is singular to working precision")
        self.info = SolveInfo(reason, rel, berr, refinements)
        return self.info

    def destroy(self):
        for o in (self.ksp, self.r, self.dx):
            o.destroy()


def vec_norms(*vecs) -> list[float]:
    """2-norms of several Vecs with one reduction."""
    local = np.array([float(np.dot(a, a)) for a in (v.getArray(readonly=True) for v in vecs)])
    comm = vecs[0].getComm()
    if comm.getSize() > 1:
        local = comm.tompi4py().allreduce(local)
    return list(np.sqrt(local))


def backward_error(nr: float, nx: float, nb: float, norm_bound: float) -> float:
    """Normwise backward error of a solve of N x = b: ||b - N x|| / (||N|| ||x|| + ||b||)
    from the norms of the residual, x and b and a bound of ||N|| (0 for b = 0)."""
    return nr / (norm_bound * nx + nb) if nb > 0 else 0.0


def reason_name(reason: int) -> str:
    for k, v in vars(PETSc.KSP.ConvergedReason).items():
        if v == reason and not k.startswith("_"):
            return k
    return str(reason)


def unused_options() -> list[str]:
    """Names of options in PETSc's database that no object has queried (PetscOptionsLeftGet,
    reached through ctypes: petsc4py has no binding for it).  Empty if unavailable."""
    try:
        path = next(line.split()[-1] for line in open("/proc/self/maps")
                    if "libpetsc" in line and ".so" in line)
        lib = ctypes.CDLL(path)
        pint = ctypes.c_int64 if np.dtype(PETSc.IntType).itemsize == 8 else ctypes.c_int32
        n = pint(0)
        names = ctypes.POINTER(ctypes.c_char_p)()
        vals = ctypes.POINTER(ctypes.c_char_p)()
        if lib.PetscOptionsLeftGet(None, ctypes.byref(n), ctypes.byref(names), ctypes.byref(vals)):
            return []
        out = [names[k].decode() for k in range(n.value)]
        lib.PetscOptionsLeftRestore(None, ctypes.byref(n), ctypes.byref(names), ctypes.byref(vals))
        return out
    except (OSError, StopIteration, AttributeError):
        return []


# =========================================================================== one-rank factors

class SelfFactor:
    """A factorisation of one symmetric matrix on one rank, kept for repeated solves (the
    contact LCP's active N_AA): CHOLMOD through PETSc on COMM_SELF (options prefix
    ``contact_``), or scipy's SuperLU.  ``solve`` returns None if the factorisation broke
    down (a singular N_AA is routine there: detected and handled by the caller)."""

    def __init__(self, M: sp.csr_matrix, factor: str):
        self.kind, self.lu, self.ksp, self.factored, self.F = factor, None, None, False, None
        if factor == "superlu":
            try:
                self.lu = spla.splu(M.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                                    options=dict(SymmetricMode=True))
            except RuntimeError:                       # "Factor is exactly singular"
                return
            piv = np.abs(self.lu.U.diagonal())
            if piv.min() <= 1e-13 * piv.max():
                self.lu = None
            return
        it = PETSc.IntType
        self.A = PETSc.Mat().createAIJ(size=M.shape, csr=(M.indptr.astype(it), M.indices.astype(it),
                                                          M.data), comm=PETSc.COMM_SELF)
        opts = PETSc.Options()
        if not opts.hasName("contact_mat_cholmod_print"):
            # a singular N_AA is routine here (detected, counted and handled): keep CHOLMOD
            # from printing "matrix not positive definite" on stderr every time
            opts.setValue("contact_mat_cholmod_print", 0)
        if not opts.hasName("contact_mat_cholmod_factor"):
            # simplicial LDL^T: on the contact matrices (2-D, ~7 nonzeros a row) 21 % less
            # LCP time than CHOLMOD's automatic choice (supernodal there) at N = 4096,
            # phi = 0.84, the same iterations (docs/benchmarks/lcp_factors.json)
            opts.setValue("contact_mat_cholmod_factor", "simplicial")
        self.ksp = ksp = PETSc.KSP().create(PETSc.COMM_SELF)
        ksp.setOptionsPrefix("contact_")
        ksp.setType(PETSc.KSP.Type.PREONLY)
        self.pc = pc = ksp.getPC()
        pc.setType(PETSc.PC.Type.CHOLESKY)
        pc.setFactorSolverType("cholmod")
        ksp.setOperators(self.A)
        ksp.setFromOptions()
        self.x, self.b = self.A.createVecs()

    def solve(self, rhs: np.ndarray) -> np.ndarray | None:
        """M^-1 rhs for one right-hand side (1-D) or several (the columns of a 2-D array)."""
        if self.kind == "superlu":
            return None if self.lu is None else self.lu.solve(rhs)
        if rhs.ndim == 2:
            if not self.factored and self.solve(np.ascontiguousarray(rhs[:, 0])) is None:
                return None                     # the first solve factorises: did it break down?
            n, k = rhs.shape
            B = PETSc.Mat().createDense((n, k), array=np.asfortranarray(rhs), comm=PETSc.COMM_SELF)
            X = PETSc.Mat().createDense((n, k), comm=PETSc.COMM_SELF)
            X.setUp()
            if self.F is None:
                # kept and destroyed with the rest: a dropped wrapper would hold the factor
                # until PETSc.garbage_cleanup()
                self.F = self.pc.getFactorMatrix()
            try:
                self.F.matSolve(B, X)
                out = X.getDenseArray().copy()
            except PETSc.Error:
                out = None
            B.destroy()
            X.destroy()
            return out
        self.b.setArray(rhs)
        try:                                   # the first solve factorises
            self.ksp.solve(self.b, self.x)
        except PETSc.Error:
            return None
        if self.ksp.getConvergedReason() < 0:
            return None
        self.factored = True
        return self.x.getArray().copy()

    def destroy(self):
        if self.ksp is not None:
            # pc too: petsc4py defers the destruction of a dropped wrapper to
            # garbage_cleanup(), and the PC holds the factor (~10 MB at N_AA = 2000)
            for o in (self.ksp, self.pc, self.A, self.x, self.b, self.F):
                if o is not None:
                    o.destroy()
            self.ksp = self.F = None


# =========================================================================== plumbing

def collective_cleanup(comm=None, self_too: bool = False) -> None:
    """Destroy, on every rank at the same point, the PETSc objects that Python's garbage
    collector released (petsc4py defers their collective destruction; each may hold a
    factor).  Left to interpreter shutdown, the ranks reach it in different states and MPI
    hangs.  Collective on ``comm`` (default COMM_WORLD); ``self_too``: COMM_SELF's first."""
    gc.collect()
    if self_too:
        PETSc.garbage_cleanup(PETSc.COMM_SELF)
    if comm is None:
        PETSc.garbage_cleanup()
    else:
        PETSc.garbage_cleanup(comm)


def all_options() -> dict:
    """Every option in PETSc's database (recorded in the run file)."""
    return PETSc.Options().getAll()


def comm_self():
    """PETSc's COMM_SELF (the algebra of a system every rank holds whole)."""
    return PETSc.COMM_SELF
