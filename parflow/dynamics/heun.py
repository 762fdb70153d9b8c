"""Adaptive strain stepping for bonded models (DESIGN §5).

The quasi-static dynamics is ds/dgamma = h(gamma)^-1 V_na(s, gamma).  Reversing the flow
(gammadot -> -gammadot) integrates the same ODE backwards in gamma.

Step (Heun, second order, first-same-as-last):
    k0 = F(s, gamma)                                 (known from the previous step)
    s1 = s + dg k0                                   (Euler predictor)
    k1 = F(s1, gamma + dg)
    err = |V1 - V0| / max(|V0|, |V1|)                (relative change of V_na over the step)
    accept if err <= tol:  s' = s + dg (k0 + k1) / 2, then project onto the rod constraints
    with the factor of N(s1):  dr = -S^T N^-1 (l - l0), iterated (quasi-Newton; Newton
    steps, N refactorised, where that does not contract: BondedSystem.project)
    the force at the projected point: a fresh factorisation, or (solver.reuse_factor) PCG
    preconditioned by the factor loaded last (the predictor's or the projection's Newton
    point's) -- one factorisation per step instead of two or three.
    next dg = dg * clip(0.9 tol / err, 0.2, 2) (controller "I"), or, controller "PI",
    dg * clip((0.9 tol / err)^0.7 (err_prev / err)^0.4, 0.2, 2) with err_prev the error of
    the previous accepted step (Gustafsson's PI control: it damps the accept/reject cycle
    an "I" control falls into where the step is limited by stability rather than accuracy,
    docs/networks.md) and no growth after a rejection.  Either is then bounded by
    max_dgamma and by the largest non-affine displacement per step
    max_i |V_na,i| dg <= max_displacement.
A step whose factorisation or projection fails is rejected and retried 4x smaller; when dg
falls below min_dgamma the system has jammed (:class:`Jammed`).
A step's error must shrink with the step (err ~ dg for a smooth flow).  When it does not --
three rejections over a decade of dg with err down by less than 2x -- the force at the
step's start is suspect (a bad solve, or a checkpoint that kept one): it is evaluated again
once (:class:`Stall`) and the step retried from its first trial size; a Jammed raised after
that says the error did not shrink.
With stage_rtol > 0 the predictor's force is solved by PCG on the factor at the step's start
(to that relative error of V_na), the projection's Newton steps likewise, and the step's last
force is a fresh factorisation: one factorisation per accepted step (docs/solvers.md).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..algebra.solvers import SingularOperator
from ..schema import POSITIVE, key
from ..state import InputError

# the two L-stable choices of ROS2's g (dynamics.ros2); a scene's value is snapped to the
# nearer one within 1e-6 (ros2_g)
ROS2_GAMMAS = (1.0 + 1.0 / math.sqrt(2.0), 1.0 - 1.0 / math.sqrt(2.0))


def ros2_g(v: float) -> float | None:
    """The L-stable g that ``v`` stands for (within 1e-6), or None."""
    for g in ROS2_GAMMAS:
        if isinstance(v, (int, float)) and abs(v - g) <= 1e-6:
            return g
    return None

CONTROLLERS = ("I", "PI")
INTEGRATORS: dict = {}      # filled at the end of the module


class Jammed(RuntimeError):
    """N became singular (or the constraints cannot be satisfied) within min_dgamma."""


class Stall:
    """Whether the error estimate of one step's rejected trials shrinks with the step."""

    def __init__(self):
        self.trials: list[tuple[float, float]] = []    # (dg, err) of the rejected trials
        self.refreshed = False                         # F0 was evaluated again
        self.note = ""

    def stalled(self, dg: float, err: float) -> bool:
        """Record a rejected trial; True (once per step) if the error has not shrunk."""
        self.trials.append((dg, err))
        (dg0, e0), (dg1, e1) = self.trials[0], self.trials[-1]
        if self.refreshed or len(self.trials) < 3 or not (dg1 <= 0.1 * dg0 and e1 >= 0.5 * e0):
            return False
        self.refreshed = True
        self.note = (f"; the error estimate did not shrink with the step (err {e0:.3g} at dg = "
                     f"{dg0:.3g}, {e1:.3g} at {dg1:.3g}), and the step was retried with the "
                     f"force at its start evaluated again")
        return True


@dataclass
class StepControl:
    """The scene's [integrator] table (``schema``: each key declared once, here)."""
    tol: float = key(0.05, lambda v: 0 < v < 1, "in (0, 1)",
                     "accept a step if |V1 - V0| / |V| <= tol")
    max_displacement: float = key(0.05, *POSITIVE, "largest non-affine displacement per step (a0)")
    max_dgamma: float = key(1e-2, *POSITIVE, "largest strain step")
    min_dgamma: float = key(1e-14, *POSITIVE, "below this step the system is declared jammed")
    initial_dgamma: float = key(1e-4, *POSITIVE, "the first strain step")
    length_tol: float = key(1e-12, *POSITIVE, "rod-length projection tolerance")
    controller: str = key("I", lambda v: v in CONTROLLERS, f"one of {list(CONTROLLERS)}",
                          "step-size control: I (dg ~ tol/err) or PI")
    method: str = key("heun", lambda v: v in INTEGRATORS, "a registered integrator (INTEGRATORS)",
                      "the bonded integrator: heun, rkc or ros2")
    max_stages: int = key(200, lambda v: isinstance(v, int) and 2 <= v <= 200, "an integer in [2, 200]",
                          "rkc: the most stages of one step (2: no stabilisation, a "
                          "second-order two-stage step)")
    stage_rtol: float = key(0.0, lambda v: 0 <= v < 1e-3, "in [0, 1e-3)",
                            "intermediate force solves (predictor, stages) by PCG on the loaded "
                            "factor to this relative error of V_na; 0: a factorisation each "
                            "(ros2: its stage force always by PCG, 0 meaning 1e-6)")
    krylov_rtol: float = key(1e-3, lambda v: 0 < v < 1, "in (0, 1)",
                             "ros2: relative residual of the stage equations (GMRES, each "
                             "iteration one solve with the step's factor)")
    krylov_recycle: bool = key(False, None, "true or false",
                               "ros2: the second stage equation starts from the first one's "
                               "Krylov space (the same W): fewer GMRES iterations")
    ros2_gamma: float = key(ROS2_GAMMAS[0], lambda v: ros2_g(v) is not None,
                            "1.7071068 (1 + 1/sqrt(2)) or 0.2928932 (1 - 1/sqrt(2)): the "
                            "L-stable ROS2",
                            "ros2: the parameter g of W = I - g h J; 1 - 1/sqrt(2) moves R(z)'s "
                            "pole from z = 0.59 to 3.41 (longer steps where a mode grows)")

    def validate(self):
        for name in ("tol", "max_displacement", "max_dgamma", "min_dgamma", "initial_dgamma",
                     "length_tol"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise InputError(f"integrator.{name} must be a positive number, got {v!r}")
        if self.controller not in CONTROLLERS:
            raise InputError(f"integrator.controller must be one of {CONTROLLERS}, got {self.controller!r}")
        if self.min_dgamma >= self.max_dgamma:
            raise InputError("integrator.min_dgamma must be smaller than integrator.max_dgamma")


@dataclass
class StepResult:
    s: np.ndarray
    gamma: float
    F: object            # Force at the new configuration
    dgamma: float        # signed strain increment taken
    next_dgamma: float   # magnitude proposed for the next step
    err: float
    rejected: int
    proj_iter: int
    length_error: float


def vnorm(V) -> float:
    """|V| over an (N, d) array of velocities."""
    return float(np.sqrt(np.einsum("id,id->", V, V)))


class Heun:
    def __init__(self, system, control: StepControl, err_prev: float | None = None):
        self.system = system
        self.c = control
        self.err_prev = err_prev     # error of the last accepted step (PI control; checkpointed)

    def memory(self) -> tuple[dict, dict]:
        """What a checkpoint must keep beyond err_prev for a restart to step exactly as the
        uninterrupted run (arrays, attributes); Heun keeps nothing more."""
        return {}, {}

    def recall(self, ck: dict) -> None:
        """Restore :meth:`memory` from a checkpoint."""

    def growth(self, err: float, rejected: int) -> float:
        """Factor for the next step after an accepted one with error ``err``."""
        c = self.c
        if err == 0:
            g = 2.0
        elif c.controller == "PI" and self.err_prev:
            g = (0.9 * c.tol / err) ** 0.7 * (self.err_prev / err) ** 0.4
        else:
            g = 0.9 * c.tol / err
        g = min(2.0, max(0.2, g))
        return min(g, 1.0) if rejected and c.controller == "PI" else g

    def bound(self, F, dg: float) -> float:
        vmax = float(np.sqrt(np.max(np.einsum("id,id->i", F.V_na, F.V_na)))) if F.V_na.size else 0.0
        if vmax > 0:
            dg = min(dg, self.c.max_displacement / vmax)
        return min(dg, self.c.max_dgamma)

    def trial(self, F0, dg: float, dg_cap: float | None, gamma: float, rejected: int,
              stall: Stall | None = None) -> float:
        """The trial step: ``dg`` bounded (:meth:`bound`, ``dg_cap``); Jammed below min_dgamma."""
        dg = self.bound(F0, dg)
        if dg_cap is not None:
            dg = min(dg, dg_cap)
        if dg < self.c.min_dgamma:
            raise Jammed(f"step size fell below min_dgamma = {self.c.min_dgamma:g} at gamma = "
                         f"{gamma:.12g} after {rejected} rejected steps: the system has jammed"
                         + (stall.note if stall is not None else ""))
        return dg

    def refresh(self, s, gamma):
        """The force at a step's start evaluated again (a fresh factorisation), when the
        step's error does not shrink with the step (:class:`Stall`)."""
        self.system.n_refreshed += 1
        return self.system.evaluate(s, gamma, what="force at the step's start, again")

    def finish(self, s_new, gamma_new):
        """The end of every bonded step: ``s_new`` projected on the rod lengths (with the
        factor loaded last) and the force there; (s, projection iterations, length error, F).
        SingularOperator if either fails (the caller rejects the step)."""
        s_new, it, lerr = self.system.project(s_new, gamma_new, tol=self.c.length_tol,
                                              pcg=self.c.stage_rtol > 0)
        # with stage_rtol the step's last force is always a factorisation: the next step's
        # intermediate solves are preconditioned by the factor at its start (as after a restart)
        return s_new, it, lerr, self.system.evaluate(s_new, gamma_new, what="force",
                                                     reuse=self.c.stage_rtol == 0)

    def step(self, s, gamma, F0, direction: int, dg: float, dg_cap: float | None = None) -> StepResult:
        """One accepted step from (s, gamma) with force F0; ``dg`` is the proposed magnitude,
        ``dg_cap`` an upper bound for this step (e.g. the end of a leg)."""
        sysm, c = self.system, self.c
        rejected = 0
        k0 = F0.ds
        nV0 = vnorm(F0.V_na)
        stall, dg_first = Stall(), dg
        while True:
            dg = self.trial(F0, dg, dg_cap, gamma, rejected, stall)
            h = direction * dg
            try:
                F1 = sysm.evaluate(s + h * k0, gamma + h, what="predictor", rtol=c.stage_rtol,
                                   guess=F0.tau, intermediate=True)
            except SingularOperator:
                rejected += 1
                dg *= 0.25
                continue
            scale = max(nV0, vnorm(F1.V_na))
            err = vnorm(F1.V_na - F0.V_na) / scale if scale > 0 else 0.0
            if not np.isfinite(err) or err > c.tol:
                rejected += 1
                if np.isfinite(err) and stall.stalled(dg, err):
                    F0 = self.refresh(s, gamma)
                    k0, nV0, dg = F0.ds, vnorm(F0.V_na), dg_first
                    continue
                dg *= max(0.2, 0.9 * c.tol / err) if np.isfinite(err) else 0.25
                continue
            try:
                s_new, it, lerr, F = self.finish(s + 0.5 * h * (k0 + F1.ds), gamma + h)
            except SingularOperator:
                rejected += 1
                dg *= 0.25
                continue
            grow = self.growth(err, rejected)
            self.err_prev = err
            return StepResult(s_new, gamma + h, F, h, dg * grow, err, rejected, it, lerr)


# The bonded integrators by name (``[integrator] method``).  An integrator is a class built as
# ``cls(system, control, err_prev=None)`` with ``step(s, gamma, F0, direction, dg, dg_cap)
# -> StepResult`` and an ``err_prev`` attribute (checkpointed; None if it keeps no memory):
# docs/architecture.md, "How to add an integrator".
INTEGRATORS["heun"] = Heun
