"""One strain step of a hard-disc suspension in simple shear (affine solvent model; DESIGN §2, §5).

A "catching-up" scheme (Maury & Venel; Lerner, Düring & Wyart 2013), for a strain step dg:

* candidate pairs: gap h_a = |r_a| - (R_i + R_j) < skin (``geometry.find_candidates``:
  minimum image in the Lees-Edwards-remapped cell, vectorised).
* contact forces: the LCP over the candidates (``dynamics.lcp.solve_lcp``)
      w = N_C f + b_C + h_C/dg >= 0,   f >= 0,   f . w = 0,     N_C = S_C S_C^T,
  i.e. f = argmin_{f >= 0} 1/2 f^T N_C f + f^T q,  q = b + h/dg.  A singular N_AA (a state
  of self-stress among the active contacts) is regularised and counted.
* the step: V_na = S_C^T f, s += dg h(gamma+dg)^-1 V_na, gamma += dg.  Using the *end*
  cell makes the pair-vector update exact, r' = r + dg (E r + dV), so the new gap obeys
  |r'| - sigma >= n.r' - sigma = dg w >= 0 (the linearised constraint is conservative):
  overlaps can only come from round-off, the LCP tolerance, or a pair outside the list,
  which the step bound dg (2 R_max + skin + 2 max|V_na|) < skin excludes.

Compression while shearing (``compress_rate`` > 0): the discs swell, R_i = R0_i sqrt(phi/phi0),
phi growing by compress_rate per unit strain applied until it reaches ``compress_to``.  In the
step the gaps are those at the end radii, q = b + (h - dR)/dg, so the constraint stays
conservative; sigma = sigma_fb + gap_work holds with the gap work of the end gaps (the work
of swelling against the contact forces included).

Step size: min(dg_max, c/sigma, dmax/max|V|, MAX_GROWTH x the last step, the leg's cap);
an infeasible LCP divides it by 10 (a first try above the last step is first retried at the
last step's size), an oversized displacement by 2; below dg_min with an
infeasible LCP the suspension is declared shear-jammed (:class:`ShearJammed`) only if a
compressed self-stress proves it (``dynamics.jamming``), else the step is a solver failure
(:class:`~parflow.dynamics.lcp.ContactSolveError`).

Signs: f > 0 is compression; sigma = |V_na|^2 / Omega; with collisions in the step
|V_na|^2 = -<f|b> - <f|h>/dg exactly (complementarity), so sigma = sigma_fb + gap_work
(``observables.stress``).

Replicated numpy/scipy: every rank computes the same thing (bit-identical on every rank).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from ..geometry import Candidates, cell_at, find_candidates, rigidity_csr, velocity_gradient
from ..observables import stress
from ..state import State
from .jamming import compressed_self_stress, near_self_stress
from .lcp import EPS, FACTORS, FLOOR_FACTOR, ContactSolveError, LCPFailure, LCPInfo, solve_lcp

DEFAULT_SKIN = 0.3
# a gap within GAP_ROUNDOFF eps ||h||_inf of zero (the round-off of positions in the cell h)
# is a closed contact: the step's LCP and its certificate see it as exactly 0.  Measured at
# phi = 0.8409, N = 8192 (||h|| = 108): the closed contacts' gaps reach 2.1 eps ||h|| (median
# 0.2, 49 % negative).  Taken as they are, every closed contact at a gap of -eps was a
# violation of w >= 0 of eps/dg that the pivoting chased through singular active sets
# (43 solves, 12 of them singular, at dg = 1e-10), and every step from 1e-8 to 1e-6 failed
# in the solver (the LP finding them feasible): that state crept on at 1e-10 a step for
# hours.  With the closed gaps at 0 the same LCPs end in 1-4 solves up to dg = 1e-7, 17 at
# 1e-6, and the state moves on at ~1e-6 a step
GAP_ROUNDOFF = 4.0
FIRST_DGAMMA = 1e-4
# a step is at most this many times the last accepted one: after a step had to be cut
# (an infeasible LCP, /10 per retry) the next ones grow back geometrically instead of
# starting again from c/sigma -- near shear jamming that start failed again and again
# (phi = 0.84: up to 600 solves per failed LCP, ~1e-4 strain per minute)
MAX_GROWTH = 4.0
# when no step down to dg_min is accepted and jamming is not proved, up to UPWARD_TRIES
# steps above the first one tried, each UPWARD_FACTOR x the last (an LCP can be infeasible
# at small steps only: overlapping gaps weigh -h/dg; and a step may fail for the solver's
# sake at one size and not at another)
UPWARD_FACTOR = 4.0
# an infeasible LCP retries the step at RETRY_FACTOR x its size -- except a first try above
# the last accepted step (grown by up to MAX_GROWTH), which is retried at the last step's
# size first.  Measured 2026-12-06 (benchmarks/bench_lcp.py --retry, which switches
# RETRY_AT_LAST off to compare; 120 s of stepping, two rounds each): near a jam (the N = 8192
# state of tests/reference/creeping_state.npz, a third of the first tries failing) 1.6e-4
# strain against 1.0e-4, median step 1.4e-6 against 3.2e-7; flowing at phi = 0.840 (N =
# 4096, retries in ~0.4 % of the steps) 2 and 7 % less strain, within the timing noise (the
# same trajectory's two rounds differ by 6 %)
RETRY_FACTOR = 0.1
RETRY_AT_LAST = True
# The first two tries of a step get a budget of LCP_SOLVES_FIRST solves (solve_lcp's
# max_solves); the later tries (a step cut twice, the upward search) get LCP_SOLVES.
# Measured at phi = 0.8407, N = 4096 (659 LCPs of 600 steps): the 25 LCPs that gave up
# (after 600 solves, or 20 singular sets) took 26 % of the LCP time, 2.2-4.6 s each, and in
# 24 of 25 the retry at dg/10 succeeded in 0.03-0.5 s; of the LCPs that succeeded, 3 in 634
# needed more than 150 solves (0.2 % of the steps of three runs at 0.840 needed more than
# 200).  Dropping the Lawson-Hanson phase on those tries as well was faster there but not
# from rest (docs/suspensions.md "An LCP that cycles")
LCP_SOLVES_FIRST = 150
LCP_SOLVES = 600
UPWARD_TRIES = 4
# A step that fails at every size tried without a proof of jamming, an LCP having given up
# on the way, is taken again once with a last-resort budget (:class:`LCPGaveUp`) before the run fails: measured 2026-12-05, N =
# 8192 compressed while flowing (sample 0 of runs/ensemble_jams_N8192_compress_to_phiJ.toml,
# phi = 0.84158, sigma = 8.8e8) the LCP gave up at every step tried (after 336 solves, 21 on
# singular active sets) with the LP finding no compressed self-stress; with 5 000 solves and
# 400 singular sets the same step was accepted at its first size (dg = 4e-12)
LCP_SOLVES_LAST = 5000
SINGULAR_LAST = 400
# a compressed self-stress proved at a larger step than the smallest one declares the
# suspension jammed if the strain left before its gaps close is at most this (issue target:
# the declared strain within 1e-8 of the certificate's budget)
JAM_BUDGET = 1e-8


def gap_roundoff(h: np.ndarray) -> float:
    """The gaps' round-off in the cell ``h`` (GAP_ROUNDOFF eps ||h||_inf): a gap within it of
    zero is a closed contact, neither open nor overlapping."""
    return GAP_ROUNDOFF * EPS * float(np.abs(h).sum(axis=1).max())


def swollen_radii(radii0: np.ndarray, area: float, phi: float) -> np.ndarray:
    """The radii of discs swollen from ``radii0`` (in a cell of ``area``) to packing fraction
    ``phi``: R = R0 sqrt(phi / phi0), phi0 = pi sum R0^2 / area -- how a suspension that is
    compressed while it flows grows its discs (``Suspension``, ``compress_rate``)."""
    phi0 = float(np.pi * np.sum(radii0 ** 2) / area)
    return radii0 * math.sqrt(phi / phi0)


def min_gap(state: State, skin: float = DEFAULT_SKIN) -> float:
    """Smallest gap |r| - (R_i + R_j) over all pairs within the skin (inf if none)."""
    c = find_candidates(state.s, state.radii, state.h, state.E, skin)
    return float(c.gap.min()) if len(c) else math.inf


@dataclass
class StepStats:
    gamma: float
    dgamma: float
    sigma: float            # |V_na|^2 / Omega
    sigma_fb: float         # -<f|b> / Omega
    gap_work: float         # -<f|h>/dg / Omega (nonzero when a collision closes a gap)
    pressure: float         # sum f |r| / (d Omega)
    n_candidates: int
    n_active: int
    n_new: int              # contacts carrying force that did not in the previous step
    n_coll: int             # collisions: new force-bearing contacts whose gap was > collision_gap
    overlap: float          # largest overlap among the candidates at the start of the step
    lcp: LCPInfo
    times: dict = field(default_factory=dict)


class LCPGaveUp(ContactSolveError):
    """No step size was accepted because the contact LCPs gave up, and no compressed
    self-stress proves jamming: a solver failure (after the last-resort budget, see
    :meth:`Suspension.step`)."""


class ShearJammed(RuntimeError):
    """The contact LCP is infeasible at every allowed step size, *proved* by a compressed
    self-stress (``dynamics.jamming``): finite-size shear jamming.  ``certificate``: the
    record of the proof (support, tau.b, tau.q, strain budget, gamma, the steps tried)."""

    def __init__(self, message: str, certificate: dict | None = None,
                 tau: np.ndarray | None = None, pairs: tuple | None = None):
        super().__init__(message)
        self.certificate = certificate or {}
        self.tau = tau                  # tau on its support
        self.pairs = pairs              # (i, j) of the support's contacts


class Suspension:
    """Stepper for a hard-disc suspension state (radii set, no bonds)."""

    # the step controls: keyword arguments of __init__, keys of the model's [model] table
    CONTROLS = ("skin", "c", "dmax", "dg_max", "dg_min", "factor", "collision_gap",
                "compress_rate", "compress_to")

    def __init__(self, state: State, *, skin: float = DEFAULT_SKIN, c: float = 0.05,
                 dmax: float = 0.01, dg_max: float = 1e-2, dg_min: float = 1e-12,
                 factor: str = "cholmod", collision_gap: float = 1e-4,
                 compress_rate: float = 0.0, compress_to: float = 0.0,
                 overlap_tol: float = 1e-12):
        if state.radii is None:
            raise InputError("suspension: the state has no radii")
        if not np.any(state.E[0, 1]) or np.any(state.E @ state.E):
            raise InputError("suspension: only simple shear (E = [[0,1],[0,0]]) is implemented")
        self.state = state
        self.skin, self.c, self.dmax, self.dg_max, self.dg_min = skin, c, dmax, dg_max, dg_min
        if factor not in FACTORS:
            raise InputError(f"suspension: factor must be one of {FACTORS}, got {factor!r}")
        self.factor = factor
        # persistent contacts reopen by O(dg^2 |V|^2 / r) ~ 1e-8-1e-5 a0 per step (the step
        # moves particles along straight lines); a collision is a contact that did not carry
        # force in the previous step and closes a gap larger than collision_gap
        self.collision_gap = collision_gap
        # largest overlap a step may create through an unsatisfied constraint (w < 0)
        self.overlap_tol = overlap_tol
        self.infeasible_reductions = 0
        self.upward_searches = 0       # steps that searched above their first size
        self.last_resorts = 0          # steps taken again with the last-resort LCP budget
        self._last_resort = False
        self.omega = state.volume
        # compression while shearing: the discs swell, R_i = R0_i sqrt(phi / phi0), so that
        # phi grows by compress_rate per unit strain applied until it reaches compress_to
        # (in the cell's frame this is an affine compression the solvent follows: the
        # growth adds no non-affine velocity of its own, it only closes gaps)
        self.radii0 = np.array(state.radii, float)
        self.phi0 = float(np.pi * np.sum(self.radii0 ** 2) / self.omega) if state.d == 2 else math.nan
        self.phi = self.phi0
        if not (math.isfinite(compress_rate) and compress_rate >= 0):
            raise InputError(f"suspension: compress_rate must be >= 0, got {compress_rate!r}")
        if compress_rate > 0 and not self.phi0 < compress_to:
            raise InputError(f"suspension: compress_to = {compress_to:g} must lie above the "
                             f"initial packing fraction {self.phi0:.6g} when compress_rate > 0")
        self.compress_rate, self.compress_to = float(compress_rate), float(compress_to)
        self.max_overlap = max(0.0, -min_gap(state))
        self.sigma = 0.0
        self.vmax = 0.0
        self.steps = 0
        self.collisions = 0
        self.singular_events = 0
        self._active_keys = np.zeros(0, np.int64)
        self.last_dg = 0.0             # the last accepted step (0: none yet)
        self.last_f = None
        self.last_c = None

    def next_dgamma(self, cap: float | None = None) -> float:
        """The strain step before the checks of the step: min(dg_max, c/sigma, dmax/max|V|,
        MAX_GROWTH x the last accepted step, ``cap``) with sigma and max|V| of the previous
        step (``cap``: the strain left in the leg, never below dg_min); the first step (no
        sigma yet) is at most
        FIRST_DGAMMA (dense initial states have every gap ~1e-6 a0: a large first step
        makes the cold-start LCP infeasible and costs ~1000 active-set iterations, measured
        at N = 1024, phi = 0.84)."""
        dg_max = self.dg_max if cap is None else min(self.dg_max, max(cap, self.dg_min))
        dg = dg_max if self.steps > 0 else min(dg_max, FIRST_DGAMMA)
        if self.sigma > 0:
            dg = min(dg, self.c / self.sigma)
        if self.vmax > 0:
            dg = min(dg, self.dmax / self.vmax)
        if self.last_dg > 0:
            dg = min(dg, MAX_GROWTH * self.last_dg)
        return dg

    def _keys(self, c: Candidates) -> np.ndarray:
        return c.i * self.state.n + c.j

    @property
    def compressing(self) -> bool:
        """True while the discs still swell toward compress_to."""
        return self.compress_rate > 0 and self.phi < self.compress_to

    def _phi_after(self, dg: float) -> float:
        """The packing fraction after a step of strain magnitude ``dg``."""
        if not self.compressing:
            return self.phi
        return min(self.compress_to, self.phi + self.compress_rate * dg)

    def _swell(self, dg: float) -> float:
        """How much every radius grows in a step ``dg``, per unit R0: R_i' - R_i = k R0_i."""
        phi1 = self._phi_after(dg)
        if phi1 == self.phi:
            return 0.0
        return math.sqrt(phi1 / self.phi0) - math.sqrt(self.phi / self.phi0)

    def set_phi(self, phi: float) -> None:
        """Swell (or shrink) the discs to packing fraction ``phi``: R = R0 sqrt(phi / phi0)."""
        self.phi = float(phi)
        self.state.radii = swollen_radii(self.radii0, self.omega, self.phi)
        self.state.meta["phi"] = self.phi

    def gaps(self, c: Candidates) -> np.ndarray:
        """The candidates' gaps, those within the positions' round-off of zero (GAP_ROUNDOFF
        eps ||h||_inf) set to 0: the gaps the step's LCP and its certificate use."""
        tol = gap_roundoff(self.state.h)
        return np.where(np.abs(c.gap) <= tol, 0.0, c.gap)

    def end_gaps(self, c: Candidates, dg: float) -> np.ndarray:
        """The candidates' gaps (:meth:`gaps`) with the radii at the end of a step ``dg``."""
        gap, k = self.gaps(c), self._swell(dg)
        return gap if k == 0.0 else gap - k * (self.radii0[c.i] + self.radii0[c.j])

    def forces(self, c: Candidates, dg: float, direction: int = 1, first: bool = False):
        """Contact forces for a step of strain magnitude ``dg`` in ``direction`` (+1 forward,
        -1 reversed flow: the affine rates change sign, b -> -b).  ``first``: one of the first
        tries of a step, whose LCP gives up sooner (after LCP_SOLVES_FIRST solves)."""
        S = rigidity_csr(c.n, c.i, c.j, self.state.n)
        q = direction * c.b + self.end_gaps(c, dg) / dg
        warm = np.isin(self._keys(c), self._active_keys)
        if self._last_resort:
            budget = dict(max_solves=LCP_SOLVES_LAST, max_singular=SINGULAR_LAST)
        else:
            budget = dict(max_solves=LCP_SOLVES_FIRST if first else LCP_SOLVES)
        f, info = solve_lcp(S, q, warm, factor=self.factor, **budget)
        V = (S.T @ f).reshape(self.state.n, self.state.d)
        return S, q, f, V, info, warm

    def probe(self, direction: int = 1):
        """Contact forces at the current configuration for the step the stepper would take
        next, without moving: (candidates, f, V_na, dg).  An LCP that fails gets a smaller
        step, as in :meth:`step`, and the last-resort budget as there (the first row of a run,
        also on a restart, and what analyses look at)."""
        return self._with_last_resort(self._probe, direction)

    def _probe(self, direction: int):
        """The probe of :meth:`probe`, at the present LCP budget."""
        st = self.state
        c = find_candidates(st.s, st.radii, st.h, st.E, self.skin)
        dg0 = dg = self.next_dgamma()
        while True:
            try:
                _, _, f, V, _, _ = self.forces(c, dg, direction)
                return c, f, V, dg
            except LCPFailure as exc:
                dg *= 0.1
                if dg < self.dg_min:
                    raise LCPGaveUp(
                        f"suspension: the contact LCP failed at gamma = {st.gamma:.10g} for "
                        f"every step from {dg0:.3g} down to dg_min = {self.dg_min:g}"
                        f"{self._budget_note} "
                        f"(last: {exc}): a solver failure") from None

    def step(self, direction: int = 1, cap: float | None = None) -> StepStats:
        """One step of strain magnitude dg (chosen here, at most ``cap``) in ``direction``
        (+1: gamma grows, -1: reversed flow, gamma decreases).  V_na is the non-affine
        velocity per unit strain *along the direction of the flow*, so sigma = |V_na|^2 /
        Omega >= 0 either way.  A step that fails at every size without a proof of jamming,
        one or more of its LCPs having given up, is taken again from its start with
        the last-resort budget (LCP_SOLVES_LAST solves, SINGULAR_LAST singular sets; counted
        in ``last_resorts``) before :class:`LCPGaveUp` ends the run."""
        if direction not in (1, -1):
            raise ValueError(f"direction must be +1 or -1, got {direction!r}")
        return self._with_last_resort(self._step, direction, cap)

    @property
    def _budget_note(self) -> str:
        """What a failure message adds when the last-resort budget was in use."""
        return " (with the last-resort budget too)" if self._last_resort else ""

    def _with_last_resort(self, attempt, *args):
        """``attempt(*args)``; if it raises :class:`LCPGaveUp`, once more with the
        last-resort LCP budget (counted in ``last_resorts``)."""
        try:
            return attempt(*args)
        except LCPGaveUp:
            self.last_resorts += 1
            self._last_resort = True
            try:
                return attempt(*args)
            finally:
                self._last_resort = False

    def _step(self, direction: int, cap: float | None) -> StepStats:
        """The step of :meth:`step` (the state is changed only once a size is accepted)."""
        st = self.state
        t0 = time.perf_counter()
        h = st.h
        c = find_candidates(st.s, st.radii, h, st.E, self.skin)
        t1 = time.perf_counter()
        overlap = float(max(0.0, -c.gap.min())) if len(c) else 0.0
        self.max_overlap = max(self.max_overlap, overlap)
        dg = self.next_dgamma(cap)
        sig_max = 2.0 * float(st.radii.max())
        tried, why, upward, cert = [], "", None, None
        gave_up = False                 # an LCP of this step gave up (LCPFailure)
        active_of = {}                  # step size tried -> the active set of its LCP
        while True:
            try:
                S, q, f, V, info, warm = self.forces(c, dg, direction,
                                                     first=len(tried) < 2 and upward is None)
                active_of[dg] = f > 0
                # an infeasible LCP (a self-stress tau >= 0 with tau . q < 0: a cluster the
                # flow compresses) leaves w < 0 on the regularised active set: overlap
                # dg |w| would grow this step.  Smaller steps give the reopened gaps more
                # weight (h/dg); when no step size helps, the suspension is shear-jammed.
                # accepted on what matters: the overlap the step can create (dg |w|), and w
                # and complementarity to the LCP's accuracy -- 1e-8 max(1, |b|), or the
                # round-off floor eps ||N|| max f when f is large (near singular sets, where
                # an absolute test rejected solvable steps: false jams at phi = 0.84).  The
                # shift's own error on w, 1e-12 ||N|| max f, is ~70x the floor tolerance
                # 64 eps ||N|| max f: a shifted solution that refinement cannot correct (a
                # compressed self-stress, q not in range N_AA) is still rejected
                bad = max(0.0, -info.min_w)
                w_tol = max(1e-8 * max(1.0, float(np.abs(c.b).max())), FLOOR_FACTOR * info.floor)
                feasible = (bad <= w_tol and dg * bad <= self.overlap_tol
                            and info.comp <= w_tol * max(1.0, float(f.max(initial=0.0))))
                if not feasible:
                    why = (f"min w = {info.min_w:.3g}, overlap dg |w| = {dg * bad:.3g} "
                           f"at dg = {dg:.3g}")
            except LCPFailure as exc:
                feasible, vmax, why = False, math.inf, f"{exc} at dg = {dg:.3g}"
                gave_up = True
            if feasible:
                vmax = float(np.sqrt(np.einsum("id,id->i", V, V).max()))
                swell = 2.0 * self._swell(dg) * float(self.radii0.max())
                if (dg * (sig_max + self.skin + 2 * vmax) + swell < self.skin
                        and dg * vmax <= 2 * self.dmax):
                    break
            else:
                self.infeasible_reductions += 1
            tried.append(dg)
            if upward is not None:          # the search above the first step tried
                if feasible:                # (the displacement bounds: larger won't do)
                    upward = []
                if not upward:
                    self._jam_or_fail(cert, c, direction, tried, why, gave_up, active_of)
                dg = upward.pop(0)
                continue
            if not feasible and len(tried) == 1 and RETRY_AT_LAST and 0 < self.last_dg < dg:
                # a first try above the last accepted step failed: that step again (taken
                # from a nearby state a step ago) before cutting by RETRY_FACTOR
                dg = self.last_dg
            else:
                dg *= 0.5 if feasible else RETRY_FACTOR
            if dg < self.dg_min and not feasible and tried[-1] > self.dg_min:
                dg = self.dg_min            # the smallest step is tried before giving up
            if dg < self.dg_min:
                if feasible:
                    raise ContactSolveError(
                        f"suspension: step size fell below dg_min = {self.dg_min:g} at gamma "
                        f"= {st.gamma:.10g} (max |V_na| = {vmax:.3g}: the displacement bounds)")
                cert = self._certify(c, direction, tried)
                if cert.certified and cert.tau_b < 0:
                    self._jammed(cert, c, tried)
                # not proved for every step: larger ones than the first may have a solution
                # (a self-stress the flow does not compress, tau.b >= 0, is only infeasible
                # below -tau.h / tau.b; a solver failure at small steps, h/dg large)
                upward = self._larger_steps(tried, cert, cap)
                self.upward_searches += 1
                if not upward:
                    self._jam_or_fail(cert, c, direction, tried, why, gave_up, active_of)
                dg = upward.pop(0)
        t2 = time.perf_counter()
        h_new = cell_at(st.h0, st.E, st.gamma + direction * dg)
        st.s = st.s + dg * V @ np.linalg.inv(h_new).T
        st.s -= np.floor(st.s)
        st.gamma += direction * dg
        gap_end = self.end_gaps(c, dg)
        phi1 = self._phi_after(dg)
        if phi1 != self.phi:
            self.set_phi(phi1)
        active = f > 0
        self._active_keys = self._keys(c)[active]
        n_new = int(np.count_nonzero(active & ~warm))
        n_coll = int(np.count_nonzero(active & ~warm & (c.gap > self.collision_gap)))
        self.collisions += n_coll
        self.singular_events += info.singular
        omega = self.omega
        sigma = stress.sigma(V, omega)
        stats = StepStats(st.gamma, dg, sigma, stress.sigma_tb(f, c.b, omega, direction),
                          stress.gap_work(f, gap_end, dg, omega),
                          stress.pressure(f, c.dist, omega, st.d), len(c), int(active.sum()),
                          n_new, n_coll, overlap, info,
                          dict(search=t1 - t0, lcp=t2 - t1, update=time.perf_counter() - t2))
        self.sigma, self.vmax, self.last_dg = sigma, vmax, dg
        self.steps += 1
        self.last_f, self.last_c, self.last_V = f, c, V
        return stats

    def _jam_or_fail(self, cert, c: Candidates, direction: int, tried: list, why: str,
                     gave_up: bool, active_of: dict):
        """No step was accepted and the smallest one is not proved infeasible.  If the LP at
        the largest step tried proves a compressed self-stress the flow compresses (tau.b <
        0) whose strain budget -- the strain left before the stressed cluster's gaps close
        -- is at most JAM_BUDGET, the suspension is jammed within that strain (the steps
        below the budget are feasible in exact arithmetic, but near such a cluster the
        active-set solve cannot resolve them: measured at N = 1024, phi = 0.84, a budget of
        1.8e-10 with every step from 1e-12 to 1e-9 failing).  Failing that, a compressed
        self-stress to working precision among the near-null eigenvectors of the active
        contacts of the largest step solved (``jamming.near_self_stress``), with tau.b < 0 and
        the same budget rule; else a solver failure."""
        def proofs():
            yield cert if cert.dg == max(tried) else self._certify(c, direction, tried, max(tried))
            # a self-stress that holds to working precision only (the LP needs S^T tau = 0 to
            # its tolerance): among the near-null eigenvectors of the active N_AA of the
            # largest step whose LCP returned (dynamics.jamming.near_self_stress)
            if active_of:
                dg = max(active_of)
                yield self._certify(c, direction, tried, dg, active=active_of[dg])

        for proof in proofs():
            if proof.certified and proof.tau_b < 0 and proof.strain_budget <= JAM_BUDGET:
                self._jammed(proof, c, tried)
        self._failed(cert, tried, why, gave_up)

    def _certify(self, c: Candidates, direction: int, tried: list, dg: float | None = None,
                 active: np.ndarray | None = None):
        """The LP certificate (``dynamics.jamming``) at step ``dg`` (default: the smallest
        step tried), and its record for the run file; with ``active`` (the active set of
        that step's LCP) the near-null one of that set's N_AA instead."""
        st = self.state
        dg = tried[-1] if dg is None else dg
        S = rigidity_csr(c.n, c.i, c.j, st.n)
        v_adm = math.sqrt(st.n) * min(2 * self.dmax, 0.5 * self.skin) / dg
        # swelling discs close every gap at the rate (R_i' + R_j' - R_i - R_j) / dg: part of
        # the affine closing rate b (q = b + h/dg as the LCP's)
        gap = self.gaps(c)
        b = direction * c.b - (gap - self.end_gaps(c, dg)) / dg
        if active is None:
            cert = compressed_self_stress(S, b, gap, dg, v_adm)
        else:
            cert = near_self_stress(S, active, b, gap, dg, v_adm)
        cert.rec = dict(cert.record(), gamma=float(st.gamma), direction=int(direction),
                        dg_min=float(self.dg_min), n_candidates=len(c))
        if self.compressing:
            # tau.b above holds the swelling; the shear's own share says whether the flow
            # alone compresses the self-stress (shear jamming) or only the swelling does
            cert.rec.update(phi=self.phi, tau_b_shear=float(cert.tau @ (direction * c.b)))
        return cert

    def _larger_steps(self, tried: list, cert, cap: float | None) -> list:
        """Steps above the first one tried, x UPWARD_FACTOR each, up to UPWARD_TRIES of them
        and within min(dg_max, c/sigma, dmax/max|V|, cap) (the growth cap lifted); above
        2 (-tau.h / tau.b) when the LP found a self-stress the flow decompresses."""
        bound = self.dg_max if cap is None else min(self.dg_max, max(cap, self.dg_min))
        if self.sigma > 0:
            bound = min(bound, self.c / self.sigma)
        if self.vmax > 0:
            bound = min(bound, self.dmax / self.vmax)
        lo = max(tried)
        if cert.tau_q < 0 and cert.tau_b > 0:
            lo = max(lo, -cert.tau_h / cert.tau_b)
        out = [lo * UPWARD_FACTOR ** k for k in range(1, UPWARD_TRIES + 1)]
        out = [d for d in out if d <= bound]
        if not out and lo < bound:
            out = [bound]
        return out

    def _jammed(self, cert, c: Candidates, tried: list):
        """Raise :class:`ShearJammed` with the proof: tau >= 0, S^T tau = 0 (kind "lp"; to
        working precision, kind "near-null"), tau.q < 0 at the step it was found at, and
        tau.b < 0 (then tau.q < 0 at every larger step as well)."""
        rec = dict(cert.rec, dg_tried=np.array(tried, float))
        P = np.flatnonzero(cert.tau > 0)
        if cert.dg <= min(tried):
            what = f"no step >= {self.dg_min:g} without overlap"
        else:                       # proved at a larger step (_jam_or_fail)
            what = (f"no step beyond the strain budget {cert.strain_budget:.3g} without "
                    f"overlap (the steps below it failed in the solver)")
        kind = "shear-jammed"
        if "tau_b_shear" in rec:
            kind = "shear-jammed" if rec["tau_b_shear"] < 0 else "jammed by the compression"
            what += (f" while the discs swell (phi = {rec['phi']:.6g}; the shear's share of "
                     f"tau.b: {rec['tau_b_shear']:.4g})")
        proof = ("by a compressed self-stress" if cert.kind == "lp" else
                 f"to working precision by a compressed near-self-stress (|S^T tau|^2 / |tau|^2 "
                 f"= {cert.rayleigh:.2g} ||N_AA||)")
        raise ShearJammed(
            f"suspension: {kind} at gamma = {self.state.gamma:.10g}: {what}, proved "
            f"{proof} on "
            f"{cert.support} contacts (tau.b = {cert.tau_b:.4g}, tau.q = {cert.tau_q:.4g} at "
            f"dg = {cert.dg:.3g}, strain budget {cert.strain_budget:.3g}); stress is infinite "
            f"at this N", certificate=rec, tau=cert.tau[P], pairs=(c.i[P], c.j[P]))

    def _failed(self, cert, tried: list, why: str, gave_up: bool):
        """No step was accepted and jamming is not proved: a solver failure (LCPGaveUp if an
        LCP of the step, ``gave_up``, gave up)."""
        # the last-resort budget can only help where an LCP gave up: where every try was
        # solved and rejected (w < 0: overlap), more solves change nothing
        raise (LCPGaveUp if gave_up else ContactSolveError)(
            f"suspension: the contact LCP failed at gamma = {self.state.gamma:.10g} for every "
            f"step tried ({', '.join(f'{d:.3g}' for d in tried)}; last: {why}), but it is not "
            f"proved infeasible for every step (LP at dg = {cert.dg:.3g}: certified = "
            f"{cert.certified}, min tau.q = {cert.tau_q:.3g}, tau.b = {cert.tau_b:.3g}, "
            f"v_bound = {cert.v_bound:.3g} vs {cert.v_admissible:.3g}; {cert.lp_status}): a "
            f"solver failure{self._budget_note}, not shear jamming")

    def run(self, strain: float, max_steps: int = 10**7, callback=None) -> list[StepStats]:
        """Step forward until ``strain`` more strain has been applied (the last step capped
        to land on it); the per-step stats.  For tests and benchmarks: runs of a scene go
        through the driver (``parflow.shear``)."""
        out = []
        target = self.state.gamma + strain
        for _ in range(max_steps):
            if self.state.gamma >= target:
                break
            out.append(self.step(1, target - self.state.gamma))
            if callback is not None:
                callback(self, out[-1])
        return out

    def checkpoint(self) -> dict:
        """Everything a bit-identical continuation needs: the state, the step-control memory
        (sigma, max |V_na| of the last step) and the warm active set, keyed by (i, j)."""
        st = self.state
        return dict(s=st.s.copy(), h0=st.h0.copy(), gamma=float(st.gamma), radii=self.radii0.copy(),
                    sigma=self.sigma, vmax=self.vmax, last_dg=self.last_dg, phi=self.phi,
                    active_keys=self._active_keys.copy(),
                    steps=self.steps, collisions=self.collisions, max_overlap=self.max_overlap,
                    singular_events=self.singular_events,
                    infeasible_reductions=self.infeasible_reductions,
                    upward_searches=self.upward_searches, last_resorts=self.last_resorts,
                    controls=dict(skin=self.skin, c=self.c, dmax=self.dmax, dg_max=self.dg_max,
                                  dg_min=self.dg_min, factor=self.factor,
                                  collision_gap=self.collision_gap,
                                  compress_rate=self.compress_rate,
                                  compress_to=self.compress_to,
                                  overlap_tol=self.overlap_tol))

    @classmethod
    def restore(cls, ck: dict) -> "Suspension":
        state = State(np.array(ck["s"], float), np.array(ck["h0"], float),
                      velocity_gradient("shear", 2), float(ck["gamma"]), None,
                      np.array(ck["radii"], float))
        state.meta["model"] = "suspension"
        sim = cls(state, **ck["controls"])
        sim.sigma, sim.vmax = float(ck["sigma"]), float(ck["vmax"])
        sim.last_dg = float(ck.get("last_dg", 0.0))
        if "phi" in ck and float(ck["phi"]) != sim.phi:
            sim.set_phi(float(ck["phi"]))       # the radii of a run that compresses
        sim._active_keys = np.array(ck["active_keys"], np.int64)
        sim.steps, sim.collisions = int(ck["steps"]), int(ck["collisions"])
        sim.max_overlap = max(sim.max_overlap, float(ck["max_overlap"]))
        sim.singular_events = int(ck["singular_events"])
        sim.infeasible_reductions = int(ck.get("infeasible_reductions", 0))
        sim.upward_searches = int(ck.get("upward_searches", 0))
        sim.last_resorts = int(ck.get("last_resorts", 0))
        return sim
