"""Hard-disc suspension in simple shear (affine solvent model; DESIGN §2, §5; issue 4, first slice).

Initial states, the stepping loop, observables and a command line live here; the
neighbour search and the contact LCP are in ``parflow.contacts`` (re-exported).

Binary 50:50 discs, radius ratio 1.4, small *diameter* 1, under Lees-Edwards shear
h(gamma) = [[Lx, gamma Ly], [0, Ly]], V_f = E r with E = [[0, 1], [0, 0]].

One step of strain dg (a "catching-up" scheme, Maury & Venel; Lerner, Düring & Wyart 2013):

* candidate pairs: gap h_a = |r_a| - (R_i + R_j) < skin, found by a cKDTree with periodic
  ``boxsize`` in the orthogonal reference frame of the *remapped* cell (tilt reduced into
  [-Lx/2, Lx/2] by a lattice vector), query radius enlarged by the metric distortion of the
  tilt, then filtered with the true minimum-image distance.  Vectorised, no Python loop.
* contact forces: the LCP over the candidates
      w = N_C f + b_C + h_C/dg >= 0,   f >= 0,   f . w = 0,     N_C = S_C S_C^T,
  i.e. f = argmin_{f >= 0} 1/2 f^T N_C f + f^T q,  q = b + h/dg  (= the NNLS
  min_{f>=0} |S_C^T f + V_f-part|^2 with the gap term).  Solved by a warm-started primal
  active set (Lawson-Hanson with block additions, single additions as the fall-back);
  each inner solve factors the active N_AA (scipy SuperLU on the symmetric matrix, natural
  symmetric ordering -- see docs/suspensions.md for why not PETSc yet).
* a singular N_AA (a state of self-stress among the active contacts) is detected from the
  factor's pivots / the residual and handled by a Tikhonov shift eps ||N|| I (the
  minimum-norm force among the self-stress family, to O(eps)); each event is counted.
* the step: V_na = S_C^T f, s += dg h(gamma+dg)^-1 V_na, gamma += dg.  Using the *end*
  cell makes the pair-vector update exact, r' = r + dg (E r + dV), so the new gap obeys
  |r'| - sigma >= n.r' - sigma = dg w >= 0 (the linearised constraint is conservative):
  overlaps can only come from round-off, the LCP tolerance, or a pair outside the list,
  which the step bound dg (2 R_max + skin + 2 max|V_na|) < skin excludes.

Signs: f > 0 is compression; sigma = |V_na|^2 / Omega; with collisions in the step
|V_na|^2 = -<f|b> - <f|h>/dg exactly (complementarity), so -<f|b>/Omega equals sigma only
when the force-bearing contacts are closed (h = 0).

Everything is replicated numpy/scipy: under MPI each rank runs the same computation and
gets bit-identical results (no PETSc communicator is involved yet).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from .contacts import FACTORS, LCPFailure, LCPInfo, rigidity, solve_lcp  # noqa: F401
from .geometry import Candidates, cell_at, find_candidates, velocity_gradient
from .packing.fire import fire_minimize, remove_rattlers
from .packing.mixture import PHI_J_2D as PHI_J  # the 2D phi_J (shear jamming of the mixture)
from .packing.mixture import RADIUS_RATIO, binary_radii, check_mixture, check_phi
from .packing.pairs import pair_list, wrap01
from .state import InputError, State

DEFAULT_SKIN = 0.3
FIRST_DGAMMA = 1e-4
# a step is at most this many times the last accepted one: after a step had to be cut
# (an infeasible LCP, /10 per retry) the next ones grow back geometrically instead of
# starting again from c/sigma -- near shear jamming that start failed again and again
# (phi = 0.84: up to 600 solves per failed LCP, ~1e-4 strain per minute)
MAX_GROWTH = 4.0


# =========================================================================== initial states

def make_suspension(n: int, phi: float, *, seed: int = 0, ratio: float = RADIUS_RATIO,
                    composition=(0.5, 0.5), inflate: float = 1e-6,
                    max_iter: int = 200_000, tries: int = 5) -> State:
    """Non-overlapping binary discs at packing fraction ``phi`` < phi_J in a square box.

    Uniform random positions, then the soft-disc FIRE minimiser of ``packing.fire`` with
    radii inflated by (1 + ``inflate``) until no (inflated) pair overlaps: the true discs
    then have every gap >= inflate * (R_i + R_j) > 0, verified exactly afterwards.  If the
    minimiser ends in a jammed state (overlaps left: small N jams below phi_J), new random
    positions are drawn, up to ``tries`` times.
    """
    check_phi(phi)
    check_mixture(ratio, composition)
    if not isinstance(n, (int, np.integer)) or n < 16:
        raise InputError(f"suspension: N must be an integer >= 16, got {n!r}")
    rng = np.random.default_rng(seed)
    radii = binary_radii(n, ratio, composition, rng)
    L = float((np.pi * np.sum(radii ** 2) / phi) ** 0.5)
    box = np.array([L, L])
    pl = pair_list(radii * (1.0 + inflate), box, 0.4, "auto")
    if L <= 2.0 * pl.cut:
        raise InputError(f"suspension: N = {n} gives a box of side {L:.3g}: too small, use more discs")
    for attempt in range(tries):
        X = np.ascontiguousarray((rng.random((n, 2)) * box).T)
        X, n_overlap, info = relax_overlaps(X, radii, pl, max_iter)
        if n_overlap == 0:
            break
    else:
        raise InputError(f"suspension: no unjammed configuration of N = {n} discs at phi = {phi} "
                         f"in {tries} tries (small systems jam below phi_J ~ {PHI_J}: "
                         f"use more discs or a lower phi)")
    s = wrap01(X.T / box)
    h0 = np.diag(box)
    state = State(s, h0, velocity_gradient("shear", 2), 0.0, None, radii)
    state.meta.update(model="suspension", phi=float(np.pi * np.sum(radii ** 2) / L ** 2),
                      seed=seed, fire_iterations=info["iterations"], attempts=attempt + 1)
    gap = min_gap(state)
    if gap < 0:
        raise RuntimeError(f"suspension: initial state overlaps by {-gap:.3g}")
    state.meta["initial_min_gap"] = gap
    return state


def relax_overlaps(X: np.ndarray, radii: np.ndarray, pl, max_iter: int):
    """FIRE from the (d, N) positions X on the pair list ``pl`` of the inflated radii, until
    no inflated pair overlaps.  Returns (X, number of pairs of true discs still overlapping --
    or -1 if FIRE did not converge --, FIRE info)."""
    X, info = fire_minimize(X, pl, 1e-12, max_iter=max_iter)
    X = pl.build(X)
    _, r = pl.pair_vectors(X)
    n_overlap = int(np.count_nonzero(r < radii[pl.i] + radii[pl.j]))
    return X, (n_overlap if info["converged"] else -1), info


def from_configuration(positions, radii, box, gamma: float = 0.0) -> State:
    """A State from user positions (N, 2) in a square/rectangular box (Lx, Ly) at strain
    ``gamma``; refuses overlapping discs, non-positive radii and phi >= phi_J."""
    X = np.asarray(positions, dtype=float)
    radii = np.asarray(radii, dtype=float)
    box = np.asarray(box, dtype=float)
    if X.ndim != 2 or X.shape[1] != 2 or radii.shape != (X.shape[0],) or box.shape != (2,):
        raise InputError("suspension: positions must be (N, 2), radii (N,), box (2,)")
    if not (np.all(np.isfinite(X)) and np.all(np.isfinite(radii)) and np.all(box > 0)):
        raise InputError("suspension: positions, radii and box must be finite, box > 0")
    if np.any(radii <= 0):
        raise InputError("suspension: every radius must be > 0")
    h0 = np.diag(box)
    E = velocity_gradient("shear", 2)
    h = cell_at(h0, E, gamma)
    s = X @ np.linalg.inv(h).T
    state = State(s - np.floor(s), h0, E, float(gamma), None, radii.copy())
    phi = float(np.pi * np.sum(radii ** 2) / np.prod(box))
    check_phi(phi)
    state.meta.update(model="suspension", phi=phi)
    c = find_candidates(state.s, radii, state.h, E, 0.0)
    bad = c.gap < 0
    if np.any(bad):
        raise InputError(f"suspension: the configuration has {int(bad.sum())} overlapping "
                         f"pair(s), the largest overlap {-c.gap.min():.3g} a0 (e.g. discs "
                         f"{int(c.i[bad][0])} and {int(c.j[bad][0])}); hard discs must not overlap")
    return state



def min_gap(state: State, skin: float = DEFAULT_SKIN) -> float:
    """Smallest gap |r| - (R_i + R_j) over all pairs within the skin (inf if none)."""
    c = find_candidates(state.s, state.radii, state.h, state.E, skin)
    return float(c.gap.min()) if len(c) else math.inf


# =========================================================================== dynamics

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


class ShearJammed(RuntimeError):
    """The contact LCP is infeasible at every allowed step size: finite-size shear jamming."""


class Suspension:
    """Stepper for a hard-disc suspension state (radii set, no bonds)."""

    def __init__(self, state: State, *, skin: float = DEFAULT_SKIN, c: float = 0.05,
                 dmax: float = 0.01, dg_max: float = 1e-2, dg_min: float = 1e-12,
                 factor: str = "cholmod", collision_gap: float = 1e-4,
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
        self.omega = state.volume
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

    def next_dgamma(self) -> float:
        """The strain step before the checks of the step: min(dg_max, c/sigma, dmax/max|V|,
        MAX_GROWTH x the last accepted step) with sigma and max|V| of the previous step; the
        first step (no sigma yet) is at most
        FIRST_DGAMMA (dense initial states have every gap ~1e-6 a0: a large first step
        makes the cold-start LCP infeasible and costs ~1000 active-set iterations, measured
        at N = 1024, phi = 0.84)."""
        dg = self.dg_max if self.steps > 0 else min(self.dg_max, FIRST_DGAMMA)
        if self.sigma > 0:
            dg = min(dg, self.c / self.sigma)
        if self.vmax > 0:
            dg = min(dg, self.dmax / self.vmax)
        if self.last_dg > 0:
            dg = min(dg, MAX_GROWTH * self.last_dg)
        return dg

    def _keys(self, c: Candidates) -> np.ndarray:
        return c.i * self.state.n + c.j

    def forces(self, c: Candidates, dg: float, direction: int = 1):
        """Contact forces for a step of strain magnitude ``dg`` in ``direction`` (+1 forward,
        -1 reversed flow: the affine rates change sign, b -> -b)."""
        S = rigidity(c, self.state.n)
        q = direction * c.b + c.gap / dg
        warm = np.isin(self._keys(c), self._active_keys)
        f, info = solve_lcp(S, q, warm, factor=self.factor)
        V = (S.T @ f).reshape(self.state.n, self.state.d)
        return S, q, f, V, info, warm

    def step(self, direction: int = 1) -> StepStats:
        """One step of strain magnitude dg (chosen here) in ``direction`` (+1: gamma grows,
        -1: reversed flow, gamma decreases).  V_na is the non-affine velocity per unit
        strain *along the direction of the flow*, so sigma = |V_na|^2 / Omega >= 0 either way."""
        if direction not in (1, -1):
            raise ValueError(f"direction must be +1 or -1, got {direction!r}")
        st = self.state
        t0 = time.perf_counter()
        h = st.h
        c = find_candidates(st.s, st.radii, h, st.E, self.skin)
        t1 = time.perf_counter()
        overlap = float(max(0.0, -c.gap.min())) if len(c) else 0.0
        self.max_overlap = max(self.max_overlap, overlap)
        dg = self.next_dgamma()
        sig_max = 2.0 * float(st.radii.max())
        n_fb = 0
        while True:
            try:
                S, q, f, V, info, warm = self.forces(c, dg, direction)
                n_fb = int(np.count_nonzero(f > 0))
                # an infeasible LCP (a self-stress tau >= 0 with tau . q < 0: a cluster the
                # flow compresses) leaves w < 0 on the regularised active set: overlap
                # dg |w| would grow this step.  Smaller steps give the reopened gaps more
                # weight (h/dg); when no step size helps, the suspension is shear-jammed.
                bad = max(0.0, -info.min_w)
                feasible = (bad <= 1e-8 * max(1.0, float(np.abs(c.b).max()))
                            and dg * bad <= self.overlap_tol)
            except LCPFailure:
                feasible, vmax = False, math.inf
            if feasible:
                vmax = float(np.sqrt(np.einsum("id,id->i", V, V).max()))
                if dg * (sig_max + self.skin + 2 * vmax) < self.skin and dg * vmax <= 2 * self.dmax:
                    break
            else:
                self.infeasible_reductions += 1
            dg *= 0.5 if feasible else 0.1
            if dg < self.dg_min:
                if not feasible:
                    raise ShearJammed(
                        f"suspension: shear-jammed at gamma = {st.gamma:.8g}: the contact "
                        f"problem has no solution without overlap for any step >= "
                        f"{self.dg_min:g} (a state of self-stress among "
                        f"{n_fb} force-bearing "
                        f"contacts that the flow compresses); stress is infinite at this N")
                raise RuntimeError(f"suspension: step size fell below {self.dg_min:g} "
                                   f"(max |V_na| = {vmax:.3g})")
        t2 = time.perf_counter()
        h_new = cell_at(st.h0, st.E, st.gamma + direction * dg)
        st.s = st.s + dg * V @ np.linalg.inv(h_new).T
        st.s -= np.floor(st.s)
        st.gamma += direction * dg
        active = f > 0
        self._active_keys = self._keys(c)[active]
        n_new = int(np.count_nonzero(active & ~warm))
        n_coll = int(np.count_nonzero(active & ~warm & (c.gap > self.collision_gap)))
        self.collisions += n_coll
        self.singular_events += info.singular
        omega = self.omega
        sigma = float(np.einsum("id,id->", V, V)) / omega
        stats = StepStats(st.gamma, dg, sigma, -direction * float(f @ c.b) / omega,
                          -float(f @ c.gap) / dg / omega,
                          float(f @ c.dist) / (st.d * omega), len(c), int(active.sum()),
                          n_new, n_coll, overlap, info,
                          dict(search=t1 - t0, lcp=t2 - t1, update=time.perf_counter() - t2))
        self.sigma, self.vmax, self.last_dg = sigma, vmax, dg
        self.steps += 1
        self.last_f, self.last_c, self.last_V = f, c, V
        return stats

    def checkpoint(self) -> dict:
        """Everything a bit-identical continuation needs: the state, the step-control memory
        (sigma, max |V_na| of the last step) and the warm active set, keyed by (i, j)."""
        st = self.state
        return dict(s=st.s.copy(), h0=st.h0.copy(), gamma=float(st.gamma), radii=st.radii.copy(),
                    sigma=self.sigma, vmax=self.vmax, last_dg=self.last_dg,
                    active_keys=self._active_keys.copy(),
                    steps=self.steps, collisions=self.collisions, max_overlap=self.max_overlap,
                    singular_events=self.singular_events,
                    infeasible_reductions=self.infeasible_reductions,
                    controls=dict(skin=self.skin, c=self.c, dmax=self.dmax, dg_max=self.dg_max,
                                  dg_min=self.dg_min, factor=self.factor,
                                  collision_gap=self.collision_gap,
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
        sim._active_keys = np.array(ck["active_keys"], np.int64)
        sim.steps, sim.collisions = int(ck["steps"]), int(ck["collisions"])
        sim.max_overlap = max(sim.max_overlap, float(ck["max_overlap"]))
        sim.singular_events = int(ck["singular_events"])
        sim.infeasible_reductions = int(ck.get("infeasible_reductions", 0))
        return sim

    def run(self, strain: float, max_steps: int = 10**7, callback=None) -> list[StepStats]:
        """Step until ``strain`` more strain has been applied; returns the per-step stats."""
        out = []
        target = self.state.gamma + strain
        for _ in range(max_steps):
            if self.state.gamma >= target:
                break
            keep = self.dg_max
            self.dg_max = min(self.dg_max, max(target - self.state.gamma, self.dg_min))
            out.append(self.step())
            self.dg_max = keep
            if callback is not None:
                callback(self, out[-1])
        return out


# =========================================================================== observables

def coordination(c: Candidates, f: np.ndarray, n_part: int, d: int = 2,
                 rel: float = 1e-12) -> dict:
    """z of the force-bearing contacts (f > rel max f) with rattlers (< d + 1 force-bearing
    contacts) removed iteratively (DESIGN §5); z_all = 2 N_fb / N without the removal.

    Measured: in flowing states at phi = 0.80-0.82 (z_all ~ 3.3-3.6) the iterative removal
    can cascade through the whole system (N = 1024, phi = 0.82: z = 0, every particle a
    "rattler"; N = 4096: z = 3.31): a particle with 2 contacts is in force balance with
    its drag, so the jammed-packing definition of a rattler is fragile there; z_all is
    reported beside it, and z2: the same iterative removal with fewer than 2 contacts (a
    particle with one contact is not in force balance without drag)."""
    fb = f > rel * (f.max() if f.size else 0.0)
    i, j = c.i[fb], c.j[fb]
    rattler, keep = remove_rattlers(n_part, i, j, d)
    n_nr = int(n_part - rattler.sum())
    nc = int(keep.sum())
    # the milder rule: drop (iteratively) particles with fewer than 2 force-bearing contacts
    r2, k2 = remove_rattlers(n_part, i, j, 1)
    n2 = int(n_part - r2.sum())
    return dict(z=2.0 * nc / n_nr if n_nr else 0.0, n_contacts=nc, n_rattlers=int(rattler.sum()),
                z_all=2.0 * int(fb.sum()) / n_part,
                z2=2.0 * int(k2.sum()) / n2 if n2 else 0.0, n_rattlers2=int(r2.sum()))


def observables(susp: Suspension, stats: StepStats) -> dict:
    z = coordination(susp.last_c, susp.last_f, susp.state.n, susp.state.d)
    return dict(gamma=stats.gamma, sigma=stats.sigma, sigma_fb=stats.sigma_fb,
                pressure=stats.pressure,
                mu=stats.sigma / stats.pressure if stats.pressure > 0 else math.nan,
                **z, max_overlap=susp.max_overlap, collisions=susp.collisions)


def relaxation(gamma: np.ndarray, dgamma: np.ndarray, sigma: np.ndarray,
               n_coll: np.ndarray) -> dict:
    """dsigma/dgamma between collisions, against sigma (paper: dsigma/dgamma = -sigma^2/C).

    Inputs are per-step series (StepStats.gamma is the strain at the *end* of a step; sigma
    was evaluated at its start, gamma - dgamma).  Uses pairs of consecutive steps that are
    both collision-free; the difference quotient is set against the geometric mean of the
    two sigmas, which makes it exact for sigma = 1/(1/sigma_0 + gamma/C).  Returns the number
    of such pairs, the fraction with decreasing sigma, the slope of log(-dsigma/dgamma)
    against log sigma over the decreasing ones (2 expected) and C = median sigma^2/(-dsigma/dgamma).
    """
    g0 = np.asarray(gamma, float) - np.asarray(dgamma, float)
    s = np.asarray(sigma, float)
    nc = np.asarray(n_coll)
    ok = (nc[:-1] == 0) & (nc[1:] == 0)
    dsdg = np.diff(s) / np.diff(g0)
    smid = np.sqrt(s[:-1] * s[1:])
    dec = ok & (dsdg < 0)
    out = dict(pairs=int(ok.sum()), decreasing=float(dec.sum() / ok.sum()) if ok.any() else math.nan,
               slope=math.nan, C=math.nan)
    if dec.sum() >= 3:
        out["slope"] = float(np.polyfit(np.log(smid[dec]), np.log(-dsdg[dec]), 1)[0])
        out["C"] = float(np.median(smid[dec] ** 2 / -dsdg[dec]))
    return out


# =========================================================================== command line

def main(argv=None) -> int:
    """python -m parflow.suspension --N 1024 --phi 0.82 --strain 0.5 [--out file.npz]

    A standalone run (the generic driver ``parflow.shear`` assumes bonds): builds a state,
    shears it, prints a line every ``--every`` steps and optionally saves the time series."""
    import argparse
    import sys
    ap = argparse.ArgumentParser(prog="python -m parflow.suspension", description=main.__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--N", type=int, default=1024)
    ap.add_argument("--phi", type=float, default=0.82)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--strain", type=float, default=0.5)
    ap.add_argument("--c", type=float, default=0.05, help="step bound c/sigma")
    ap.add_argument("--dmax", type=float, default=0.01, help="largest displacement per step")
    ap.add_argument("--skin", type=float, default=DEFAULT_SKIN)
    ap.add_argument("--factor", choices=FACTORS, default="cholmod")
    ap.add_argument("--every", type=int, default=50)
    ap.add_argument("--out", default="")
    a = ap.parse_args(argv)
    try:
        state = make_suspension(a.N, a.phi, seed=a.seed)
        sim = Suspension(state, skin=a.skin, c=a.c, dmax=a.dmax, factor=a.factor)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    rows = []
    t0 = time.perf_counter()

    def report(s, st):
        o = observables(s, st)
        rows.append([o["gamma"], st.dgamma, o["sigma"], o["sigma_fb"], st.gap_work, o["pressure"],
                     o["z_all"], st.n_coll, st.n_active, st.lcp.factorizations, st.lcp.singular,
                     st.overlap])
        if s.steps % a.every == 0:
            print(f"step {s.steps:6d} gamma {o['gamma']:.5f} dg {st.dgamma:.2e} sigma {o['sigma']:.4g} "
                  f"p {o['pressure']:.4g} mu {o['mu']:.3f} z_all {o['z_all']:.3f} "
                  f"coll {st.n_coll} fact {st.lcp.factorizations} max_overlap {s.max_overlap:.1e}",
                  flush=True)

    status = 0
    try:
        sim.run(a.strain, callback=report)
    except ShearJammed as exc:
        print(f"stopped: {exc}", file=sys.stderr)
        status = 3
    wall = time.perf_counter() - t0
    print(f"done: {sim.steps} steps, strain {state.gamma:.4f}, {wall:.1f} s "
          f"({sim.steps / wall:.1f} steps/s, {state.gamma / wall * 3600:.1f} strain/hour), "
          f"max overlap {sim.max_overlap:.2e}, collisions {sim.collisions}, "
          f"singular active sets {sim.singular_events}, "
          f"infeasible step reductions {sim.infeasible_reductions}")
    if a.out:
        from mpi4py import MPI
        if MPI.COMM_WORLD.rank == 0:
            cols = ("gamma dgamma sigma sigma_fb gap_work pressure z_all n_coll n_active "
                    "factorizations singular overlap")
            tmp = a.out + ".part.npz"
            np.savez(tmp, series=np.array(rows), columns=cols, N=a.N, phi=a.phi, seed=a.seed)
            import os
            os.replace(tmp, a.out if a.out.endswith(".npz") else a.out + ".npz")
    return status


if __name__ == "__main__":
    raise SystemExit(main())
