"""Certificates of shear jamming for the contact LCP (DESIGN §5).

The contact LCP  w = S S^T f + q >= 0,  f >= 0,  f . w = 0  (N = S S^T positive semidefinite)
has a solution iff it is feasible, and by Farkas' lemma it is infeasible iff there is a
*compressed self-stress*

    tau >= 0,   S^T tau = 0,   tau . q < 0

(tau >= 0 with N tau <= 0 forces |S^T tau|^2 = tau . N tau <= 0).  With q = b + h/dg:
tau . q = tau . b + tau . h / dg: the tau-weighted gap of the stressed contacts changes at
the affine rate tau . b whatever the particles do (tau . S V = 0 for every V), so it closes
after the strain ``strain_budget`` = tau . h / (-tau . b); a step larger than that is
impossible without overlap.

:func:`compressed_self_stress` finds the most compressed tau by a linear program (HiGHS:
min tau . q s.t. S^T tau = 0, 0 <= tau <= 1), polishes it onto the null space of its
support's S^T (least squares) and states what it proves.  A tau with a residual
r = S^T tau != 0 proves less than infeasibility: for any f >= 0 with w >= 0,
0 <= tau . w = r . V + tau . q, so |V|_2 >= |tau . q| / |r|_2 =: ``v_bound`` -- no solution
with a non-affine velocity below v_bound.  The certificate *holds* when tau . q < 0 and
v_bound exceeds ``v_admissible``, the largest |V|_2 a step could use (the suspension step
passes sqrt(N) min(2 dmax, skin/2)/dg: a faster particle would fail the step's displacement
bounds anyway).

A self-stress that holds to working precision only -- the cluster rigid up to a Rayleigh
quotient |S^T tau|^2/|tau|^2 of ~3e-14 ||N_AA||, so that the LP (S^T tau = 0 to its feasibility
tolerance) finds nothing and the velocity bound is far below the admissible one -- is found by
:func:`near_self_stress` among the lowest eigenvectors of the active contacts' N_AA: a
nonnegative combination tau of those with eigenvalue <= NEAR_NULL ||N_AA||_inf that the flow
compresses (kind "near-null").  Near such a cluster the LCP is feasible in exact arithmetic
only with forces ~ (u . q) / lambda along the unit near-null vector u (4e12 at lambda =
2e-13), beyond what a solve in double precision resolves: measured at N = 1024, phi = 0.84
(sigma = 4e9), every step from 1e-12 up failed with w = -0.13 on 1 950 of the 1 960 active
contacts.

Replicated: every rank solves the same LP (HiGHS is deterministic), no communication.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.optimize import linprog
from scipy.sparse.linalg import ArpackError, ArpackNoConvergence, eigsh, lsqr

# tau components below this (relative to max tau = 1) are dropped from the support
SUPPORT_CUT = 1e-9
# near_self_stress: eigenvectors of N_AA with eigenvalue <= NEAR_NULL ||N_AA||_inf span the
# near self-stresses -- the shift of the active-set solver's singular sets (lcp.ActiveSolver,
# eps = 1e-12): below it the shifted solve and its refinement cannot resolve a mode (the
# measured case's compressed one sits at 4e-14, its two exact ones at 2e-17); NEAR_K of the
# lowest are computed (shift-invert about -NEAR_SHIFT ||N_AA||_inf), twice as many while all
# of them are near-null, up to NEAR_K_MAX (a larger null space: an over-constrained crystal)
NEAR_NULL = 1e-12
NEAR_K = 6
NEAR_K_MAX = 96
NEAR_SHIFT = 1e-10
# ... and it must be loaded: tau . q <= -NEAR_LOADED |tau|_2 |q_A|_2 (a rigid cluster the flow
# does not press on, its gaps closed to 0, has tau . q = 0 up to round-off)
NEAR_LOADED = 1e-9


@dataclass
class Certificate:
    certified: bool          # tau . q < 0 and v_bound >= v_admissible
    tau: np.ndarray          # (n_candidates,) >= 0, max 1 (zeros if the LP found none)
    support: int             # contacts with tau > SUPPORT_CUT
    tau_b: float             # tau . b (b of the flow direction)
    tau_h: float             # tau . gap
    tau_q: float             # tau . q = tau . b + tau . h / dg
    residual: float          # |S^T tau|_2 after polishing
    v_bound: float           # no LCP solution with |V|_2 < v_bound (inf: exact self-stress)
    v_admissible: float      # the |V|_2 a step could use at this dg
    dg: float                # the step the LP was solved for
    lp_status: str           # HiGHS's message
    kind: str = "lp"         # "lp": S^T tau = 0 by the LP; "near-null": N_AA's eigenvectors
    rayleigh: float = 0.0    # |S^T tau|^2 / (|tau|^2 ||N_AA||_inf) (kind "near-null")

    @property
    def strain_budget(self) -> float:
        """Strain at which the stressed cluster's weighted gap closes (tau . h / -tau . b);
        the certificate holds at steps larger than this (inf: the flow does not compress it)."""
        return self.tau_h / -self.tau_b if self.tau_b < 0 else np.inf

    def record(self) -> dict:
        """Scalars for the run file's /jam group (docs/output.md)."""
        return dict(certified=bool(self.certified), support=int(self.support),
                    tau_b=float(self.tau_b), tau_h=float(self.tau_h), tau_q=float(self.tau_q),
                    residual=float(self.residual), v_bound=float(self.v_bound),
                    v_admissible=float(self.v_admissible), dg=float(self.dg),
                    strain_budget=float(self.strain_budget), lp_status=self.lp_status,
                    kind=self.kind, rayleigh=float(self.rayleigh))


def _polish(S: sp.csr_matrix, tau: np.ndarray, sweeps: int = 3) -> np.ndarray:
    """tau moved onto the null space of S_P^T on its support P (minimum-norm least-squares
    correction; components that turn negative are cut and the correction redone)."""
    tau = tau.copy()
    for _ in range(sweeps):
        P = np.flatnonzero(tau > SUPPORT_CUT * max(tau.max(), 1e-300))
        if P.size == 0:
            return np.zeros_like(tau)
        StP = S[P].T.tocsr()
        r = StP @ tau[P]
        if not np.linalg.norm(r) > 0:
            break
        delta = lsqr(StP, r, atol=1e-16, btol=1e-16, conlim=1e14, iter_lim=20 * P.size)[0]
        t = np.zeros_like(tau)
        t[P] = np.maximum(tau[P] - delta, 0.0)
        tau = t
    return tau


def compressed_self_stress(S: sp.csr_matrix, b: np.ndarray, gap: np.ndarray, dg: float,
                           v_admissible: float) -> Certificate:
    """The most compressed self-stress of the candidates at step ``dg`` (q = b + gap/dg;
    ``b`` of the flow direction, i.e. direction * b_C) by the LP min tau . q, S^T tau = 0,
    0 <= tau <= 1, polished and judged as the module docstring says."""
    nc = S.shape[0]
    q = b + gap / dg
    if nc == 0:
        return _unproved(nc, dg, v_admissible, "no candidates")
    qs = float(np.abs(q).max()) or 1.0               # scaled objective: HiGHS tolerances
    res = linprog(q / qs, A_eq=S.T.tocsr(), b_eq=np.zeros(S.shape[1]), bounds=(0.0, 1.0),
                  method="highs", options=dict(primal_feasibility_tolerance=1e-10,
                                               dual_feasibility_tolerance=1e-10))
    if res.status != 0 or res.x is None or not res.fun < 0:
        return _unproved(nc, dg, v_admissible, str(res.message))
    tau = _polish(S, np.clip(res.x, 0.0, 1.0))
    if not tau.max() > 0:
        return _unproved(nc, dg, v_admissible, str(res.message))
    cert = _measured(S, tau, b, gap, dg, v_admissible, str(res.message))
    cert.certified = bool(cert.tau_q < 0 and cert.v_bound >= v_admissible)
    return cert


def _unproved(nc: int, dg: float, v_admissible: float, status: str, **kind) -> Certificate:
    """Nothing proved at step ``dg`` (``status`` says why): tau = 0 over the ``nc``
    candidates."""
    return Certificate(False, np.zeros(nc), 0, 0.0, 0.0, 0.0, 0.0, 0.0, v_admissible, dg, status,
                       **kind)


def _measured(S: sp.csr_matrix, tau: np.ndarray, b: np.ndarray, gap: np.ndarray, dg: float,
              v_admissible: float, status: str, **kind) -> Certificate:
    """The Certificate of a candidate ``tau`` >= 0 (scaled here to max 1): its support,
    tau . b, tau . gap, tau . q, |S^T tau|_2 and the velocity bound; ``certified`` is left
    False for the caller's criterion."""
    tau = tau / tau.max()
    tq = float(tau @ (b + gap / dg))
    resid = float(np.linalg.norm(S.T @ tau))
    v_bound = np.inf if resid == 0 else (-tq / resid if tq < 0 else 0.0)
    return Certificate(False, tau, int(np.count_nonzero(tau > SUPPORT_CUT)), float(tau @ b),
                       float(tau @ gap), tq, resid, float(v_bound), float(v_admissible), dg,
                       status, **kind)


def near_self_stress(S: sp.csr_matrix, active: np.ndarray, b: np.ndarray, gap: np.ndarray,
                     dg: float, v_admissible: float) -> Certificate:
    """A compressed self-stress of the ``active`` contacts that holds to working precision:
    the lowest NEAR_K eigenpairs of N_AA = S_A S_A^T, those with eigenvalue <= NEAR_NULL
    ||N_AA||_inf, and of their span the tau = U c >= 0 (max 1) with the least tau . q (a
    small LP in c).  ``certified``: tau . q < -NEAR_LOADED |tau| |q_A| and its Rayleigh quotient
    |S^T tau|^2 / |tau|^2 <= NEAR_NULL ||N_AA||_inf (kind "near-null"); tau, b, gap over all
    candidates as in :func:`compressed_self_stress` (v_bound is reported, not required)."""
    nc = S.shape[0]
    q = b + gap / dg
    def none(status):
        return _unproved(nc, dg, v_admissible, status, kind="near-null", rayleigh=np.inf)

    A = np.flatnonzero(active)
    if A.size < 2:
        return none("fewer than two active contacts")
    SA = S[A]
    M = (SA @ SA.T).tocsc()
    norm = float(np.max(np.abs(M).sum(axis=1)))
    k = NEAR_K
    v0 = np.cos(np.arange(1, A.size + 1) * 0.7548776662466927) + 1.5
    while True:
        k = min(k, A.size - 1)
        try:
            lam, U = eigsh(M, k=k, sigma=-NEAR_SHIFT * norm, which="LM", v0=v0)
        except (ArpackError, ArpackNoConvergence, RuntimeError) as exc:
            return none(f"eigenvectors of N_AA: {exc}")
        if np.any(lam > NEAR_NULL * norm) or k >= min(NEAR_K_MAX, A.size - 1):
            break
        k *= 2
    U = U[:, lam <= NEAR_NULL * norm]
    if U.shape[1] == 0:
        return none(f"no eigenvalue of N_AA below {NEAR_NULL:g} ||N_AA|| (lowest "
                    f"{float(lam.min()) / norm:.2g})")
    qa = q[A]
    res = linprog(U.T @ qa / (float(np.abs(qa).max()) or 1.0),
                  A_ub=np.vstack([-U, U]), b_ub=np.concatenate([np.zeros(A.size), np.ones(A.size)]),
                  bounds=(None, None), method="highs")
    status = f"{U.shape[1]} near-null eigenvector(s) of N_AA; {res.message}"
    if res.status != 0 or res.x is None or not res.fun < 0:
        return none(status)
    tau = np.zeros(nc)
    tau[A] = np.maximum(U @ res.x, 0.0)
    if not tau.max() > 0:
        return none(status)
    cert = _measured(S, tau, b, gap, dg, v_admissible, status, kind="near-null")
    cert.rayleigh = cert.residual ** 2 / float(cert.tau @ cert.tau) / norm
    loaded = cert.tau_q < -NEAR_LOADED * float(np.linalg.norm(cert.tau)) * float(np.linalg.norm(qa))
    cert.certified = bool(loaded and cert.rayleigh <= NEAR_NULL)
    return cert
