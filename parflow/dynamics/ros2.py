"""A linearly implicit integrator for the stiff bonded flow: the two-stage Rosenbrock-W method
ROS2 (Verwer, Spee, Blom & Hundsdorfer 1999), ``[integrator] method = "ros2"``.

Why: near jamming the Jacobian J of ds/dgamma = F(s) has a real spectrum reaching ~ -13 sigma
(rods under the soft mode's large forces turning back into line: the geometric stiffness
tau / l; measured on an N = 4 096 network, docs/solvers.md "A linearly implicit step"),
while the flow itself changes on strains ~ 1 / (0.1 sigma).  An explicit step is bounded by
the first (Heun: dg |lambda| <= 2), an L-stable one only by the second.

One step of size h = direction * dg from s with F0 = F(s) (N factorised at s):
    W   = I - g h J,   g = 1 + 1/sqrt(2)        (J at s: BondedSystem.linearised;
                                                  integrator.ros2_gamma: or 1 - 1/sqrt(2))
    W k1 = F0
    W k2 = F(s + h k1, gamma + h) - 2 k1
    s'  = s + h (3/2 k1 + 1/2 k2),  projected on the rod lengths (with the factor at s)
    err = |h/2 (k1 + k2)| / (dg max(|V0|, |V1|))      (against the linearly implicit Euler
          step s + h k1, in real space, relative to the step's displacement: the measure of
          Heun's error, to which it reduces for a slow flow, times 1.2)
    accept if err <= tol; the next dg from err as Heun's (controller I or PI, max_dgamma,
    max_displacement).
ROS2 is of order 2 for any W (a W-method), so J need not be exact: each stage equation is
solved by GMRES (dynamics.krylov) to the relative residual ``krylov_rtol``, each product J u
one solve with the factor at s (with ``krylov_recycle`` the second stage starts from the
first stage's Krylov space: dynamics.krylov; a trial step rejected for its growth or its
error leaves its stage-1 Krylov space to the next, shorter trial, whose W differs only by
the shift: krylov.shifted_space).  The stage force F(s + h k1) is a PCG on that factor to
``stage_rtol`` (STAGE_RTOL if the key is 0: the stage force enters the solution directly);
should the PCG fall back to a factorisation there, the factor of stage 1 is loaded again
for the second stage (W must be the same in both).  The end of the step s + h (3/2 k1 + 1/2
k2) is factorised, projected on the rod lengths with that factor (a few quasi-Newton
iterations: it is nearly Newton's matrix), and the force at the projected point solved by PCG
on it to round-off; that factor serves the next step's W (J is taken at the next step's start,
its solves with the factor of a configuration ~tol h^2 away: a W-method allows it).  Measured
on an N = 40 000 network, 40 steps from sigma = 1e4: 31.6 s against 44.4 s with the factor
at the projected point (half the PCG iterations, 41 factorisations against 69).  A step whose GMRES does not converge in KRYLOV_MAX_IT iterations, or
whose projection fails, is rejected and retried 4x smaller.
Growing modes: ROS2 is accurate for h lambda <= 0 of any size, but its stability function
R(z) = (1 - (2g - 1) z) / (1 - g z)^2 has a pole at z = 1/g = 0.59 and follows e^z only
for z = h lambda <~ 0.2 on the growing side.  A reversed flow turns the stiff modes into
growing ones (rate ~ 13 sigma: the buckling that the reversed branch is made of), and an
error estimate built from two such stages does not see it.  So the Ritz values mu of W
from stage 1's GMRES (mu = 1 - g h lambda) give the fastest growth rate lambda_+ of the
step; a step with h lambda_+ > GROWTH_MAX is rejected, and every step is bounded by
dg <= 0.9 GROWTH_MAX / lambda_+ (lambda_+ the larger of the rate measured and RATE_RELAX
times the one before: a short step's Krylov space, converged in an iteration or two, does
not see the growth; checkpointed).  Toward jamming
lambda_+ is small (8.7e4 at sigma = 1e6 against -1.3e7 for the stiff modes, N = 4 096):
the bound does not bite; on a reversed leg it makes ROS2 as slow as an explicit step, and
Heun is the cheaper choice there (per-leg integrator keys).
The other L-stable g, 1 - 1/sqrt(2) (``ros2_gamma``; R(z) = (1 + (sqrt(2) - 1) z) /
(1 - g z)^2, order 2 as well): R's pole moves to z = 3.41, R follows e^z to 2.4 % up to
z = growth_limit(g) ~ 0.8 (4x GROWTH_MAX), the linear error constant is 34x smaller, and
W = I - g h J is better conditioned for the stiff modes (fewer GMRES iterations); the stiff
modes are damped with R ~ -4.8/z (a sign change a step) instead of R ~ -0.83/z.  Its error
estimate, against the linearly implicit Euler step of the same g, is (2g - 1) h^2 J F / 2 for
a slow flow, 5.8x smaller than Verwer's: the same accuracy needs a ~5x smaller tol
(docs/solvers.md).
Rod lengths and the sigma identity: as every bonded step.
Cost of a step: one factorisation, the stage PCG, 2 x (GMRES iterations) solves and the
projection's solves; measured in docs/benchmarks.md ("Integrators on a network").
"""
from __future__ import annotations

import math

import numpy as np

from ..algebra.solvers import SingularOperator
from ..state import InputError
from .heun import INTEGRATORS, Heun, Stall, StepResult, ros2_g, vnorm
from .krylov import gmres, shifted_space

GAMMA = 1.0 + 1.0 / math.sqrt(2.0)
# why a trial step is rejected (ROS2.rejections; the run file's rejected_* attributes)
REJECTION_CAUSES = ("error", "growth", "solve", "projection")
# The stage force by PCG on the step's factor when integrator.stage_rtol = 0: its error
# enters the step as ~ h |dF| / 2, i.e. a relative 5e-7 of the step's displacement (the
# step's own error is held at tol ~ 0.05), within STAGE_MAX_IT PCG iterations (6-13 at
# 1e-10 on an N = 40 000 network at dg sigma <= 0.1, 36 at 0.3; two thirds of that at 1e-6)
STAGE_RTOL = 1e-6
STAGE_MAX_IT = 30
KRYLOV_MAX_IT = 150
GROWTH_MAX = 0.2             # the largest h lambda of a growing mode a step may take
# ... for another g (integrator.ros2_gamma): the z where |R(z) e^-z - 1| is what it is at
# GROWTH_MAX for Verwer's g (2.4 %): growth_limit
RATE_RELAX = 0.9             # the growth rate remembered, relaxed by this a measurement


def stability(z, g: float = GAMMA):
    """R(z) of ROS2 with the parameter g: (1 + (1 - 2g) z + (g^2 - 2g + 1/2) z^2) / (1 - g z)^2
    (L-stable for g = 1 +- 1/sqrt(2), where the z^2 term vanishes)."""
    z = np.asarray(z) * 1.0                  # real or complex
    return (1.0 + (1.0 - 2.0 * g) * z + (g * g - 2.0 * g + 0.5) * z * z) / (1.0 - g * z) ** 2


def growth_limit(g: float) -> float:
    """The largest h lambda > 0 a step with parameter g may take: GROWTH_MAX for Verwer's g,
    otherwise the z in (0, 1/g) where R(z) e^-z departs from 1 as much as Verwer's R does at
    GROWTH_MAX (bisection; R e^-z - 1 is monotone there for both L-stable g)."""
    if g == GAMMA:
        return GROWTH_MAX
    dev = abs(float(stability(GROWTH_MAX)) * math.exp(-GROWTH_MAX) - 1.0)
    lo, hi = 0.0, 0.95 / g
    if abs(float(stability(hi, g)) * math.exp(-hi) - 1.0) <= dev:
        return hi
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        if abs(float(stability(mid, g)) * math.exp(-mid) - 1.0) <= dev:
            lo = mid
        else:
            hi = mid
    return lo


class ROS2(Heun):
    """ROS2 steps of the bonded flow (see the module); same interface as Heun."""

    def __init__(self, system, control, err_prev=None):
        super().__init__(system, control, err_prev)
        self.g = ros2_g(control.ros2_gamma)
        if self.g is None:                # (a scene's value is checked on loading)
            raise InputError(f"integrator.ros2_gamma = {control.ros2_gamma!r}: must be "
                             f"1 + 1/sqrt(2) or 1 - 1/sqrt(2), the L-stable ROS2")
        self.growth_max = growth_limit(self.g)
        self.rate_plus = 0.0         # the fastest growth rate measured (per unit strain)
        self.krylov_failed = 0
        self.rejections = dict.fromkeys(REJECTION_CAUSES, 0)
        self.w_n = None              # unit vectors of the factor this integrator loaded last
        self.w_at = None             # (s, gamma) of that factor, when not the step's own end
        self.pending = None          # such a (s, gamma) from a checkpoint, to load again

    def memory(self) -> tuple[dict, dict]:
        """The growth rate, and where the factor the next step works with was taken when that
        is not the current configuration (the unprojected end of the last step): a restart
        loads the same factor and steps bit for bit as the uninterrupted run."""
        own = self.w_at is not None and self.system.ops.loaded_n is self.w_n
        arrays = dict(ros2_factor_s=self.w_at[0]) if own else {}
        attrs = dict(ros2_rate_plus=self.rate_plus)
        if own:
            attrs["ros2_factor_gamma"] = self.w_at[1]
        return arrays, attrs

    def recall(self, ck: dict) -> None:
        if "ros2_rate_plus" in ck:
            self.rate_plus = float(ck["ros2_rate_plus"])
        if "ros2_factor_s" in ck and "ros2_factor_gamma" in ck:
            self.pending = (np.array(ck["ros2_factor_s"], dtype=float), float(ck["ros2_factor_gamma"]))

    def bound(self, F, dg: float) -> float:
        dg = super().bound(F, dg)
        return min(dg, 0.9 * self.growth_max / self.rate_plus) if self.rate_plus > 0 else dg

    def _stage(self, W, rhs: np.ndarray, shape, space=None, keep_space=False, seed=None):
        """GMRES on W x = rhs (from the Krylov ``space`` of the same W, if given; ``seed``:
        the Arnoldi relation of this W from this rhs, ``krylov.gmres``): (x, Ritz values,
        its own Krylov space if ``keep_space``), or (None, None, None) if it did not
        converge."""
        res = gmres(W, rhs.ravel(), self.c.krylov_rtol, KRYLOV_MAX_IT, space=space,
                    keep_space=keep_space, seed=seed)
        self.system.krylov_iterations += res.iterations
        if not res.converged:
            self.krylov_failed += 1
            return None, None, None
        return res.x.reshape(shape), res.ritz, res.space

    def _w_factor(self, F0):
        """The unit vectors of the factor W's products solve with: N at the start F0, or at the
        unprojected end of the previous step (this integrator's own, still loaded); loaded."""
        sysm = self.system
        if self.pending is not None:                 # a restart: the factor the run had
            s_f, g_f = self.pending
            self.pending = None
            n = sysm.geometry(s_f, g_f)[3]
            sysm.load(n)
            self.w_n, self.w_at = n, (s_f, g_f)
        elif sysm.ops.loaded_n is not F0.n and sysm.ops.loaded_n is not self.w_n:
            sysm.load(F0.n)
        if sysm.ops.loaded_n is F0.n:
            self.w_n, self.w_at = F0.n, None
        return sysm.ops.loaded_n

    def _finish(self, s_end, gamma_end):
        """N factorised at the unprojected end s_end (ROS2 leaves it ~tol h^2 off the rod
        lengths), the projection by quasi-Newton with that factor (it converges in a few
        iterations: the factor is nearly Newton's), the force at the projected point by PCG on
        it to round-off (REUSE_BERR; factorised there if that fails).  The factor stays for the
        next step's W (a W-method takes any J; F0 itself is exact).  (s, iterations, length
        error, F); SingularOperator if the projection fails."""
        sysm, c = self.system, self.c
        n_end = sysm.geometry(s_end, gamma_end)[3]
        sysm.load(n_end)
        s_new, it, lerr = sysm.project(s_end, gamma_end, tol=c.length_tol, pcg=True)
        F = sysm.evaluate_reusing(s_new, gamma_end, what="force")
        if sysm.ops.loaded_n is n_end:
            self.w_n, self.w_at = n_end, (s_end, gamma_end)
        else:                                         # refactorised on the way: take F's own
            if sysm.ops.loaded_n is not F.n:
                sysm.load(F.n)
            self.w_n, self.w_at = F.n, None
        return s_new, it, lerr, F

    def step(self, s, gamma, F0, direction: int, dg: float, dg_cap: float | None = None) -> StepResult:
        sysm, c = self.system, self.c
        rejected = 0
        nV0 = vnorm(F0.V_na)
        stall, dg_first = Stall(), dg
        stage_rtol = c.stage_rtol if c.stage_rtol > 0 else STAGE_RTOL
        lin = None
        k1_space = None         # a rejected trial's stage-1 Krylov space and its h (below)
        w_n = self._w_factor(F0)
        while True:
            dg = self.trial(F0, dg, dg_cap, gamma, rejected, stall)
            h = direction * dg
            if sysm.ops.loaded_n is not w_n:        # a trial step factorised elsewhere
                sysm.load(w_n)
            if lin is None:
                lin = sysm.linearised(F0)
            W = lambda x, h=h, g=self.g: x - (g * h) * lin(x)          # noqa: E731
            # stage 1 after a rejection: the same J and right-hand side, only h changed, and
            # a Krylov space of J does not depend on the shift -- the rejected trial's
            # Arnoldi relation, rescaled, is this W's (krylov.shifted_space): its products
            # are not made again (a growth rejection at N = 10^6 cost ~6 s of solves)
            seed = shifted_space(k1_space[0], h / k1_space[1]) if k1_space is not None else None
            k1_space = None
            try:
                k1, ritz, space = self._stage(W, F0.ds, s.shape, keep_space=True, seed=seed)
                if k1 is None:
                    raise SingularOperator("ROS2 stage 1: GMRES did not converge")
                # growth: mu = 1 - g h lambda < 1 (see the module)
                hl = float(np.max((1.0 - ritz.real) / self.g, initial=0.0))
                self.rate_plus = max(hl / dg, RATE_RELAX * self.rate_plus)
                if hl > self.growth_max:
                    rejected += 1
                    self.rejections["growth"] += 1
                    dg *= 0.9 * self.growth_max / hl
                    k1_space = (space, h)
                    continue
                F1 = sysm.evaluate(s + h * k1, gamma + h, what="ROS2 stage", rtol=stage_rtol,
                                   guess=F0.tau, max_it=STAGE_MAX_IT, intermediate=True)
                if sysm.ops.loaded_n is not w_n:    # the stage's PCG fell back: W as in stage 1
                    sysm.load(w_n)
                k2, _, _ = self._stage(W, F1.ds - 2.0 * k1, s.shape,
                                       space if c.krylov_recycle else None)
                if k2 is None:
                    raise SingularOperator("ROS2 stage 2: GMRES did not converge")
            except SingularOperator:
                rejected += 1
                self.rejections["solve"] += 1
                dg *= 0.25
                continue
            scale = dg * max(nV0, vnorm(F1.V_na))
            est = (0.5 * h) * (k1 + k2) @ F0.h.T
            err = vnorm(est) / scale if scale > 0 else 0.0
            if not np.isfinite(err) or err > c.tol:
                rejected += 1
                self.rejections["error"] += 1
                if np.isfinite(err) and stall.stalled(dg, err):
                    F0 = self.refresh(s, gamma)
                    nV0, dg, lin = vnorm(F0.V_na), dg_first, None
                    self.w_n, self.w_at = F0.n, None
                    w_n = F0.n
                    continue
                dg *= max(0.2, 0.9 * c.tol / err) if np.isfinite(err) else 0.25
                k1_space = (space, h)
                continue
            space = None                            # m vectors of the state's size: not kept
            try:
                s_new, it, lerr, F = self._finish(s + h * (1.5 * k1 + 0.5 * k2), gamma + h)
            except SingularOperator:
                rejected += 1
                self.rejections["projection"] += 1
                dg *= 0.25
                continue
            grow = self.growth(err, rejected)
            self.err_prev = err
            return StepResult(s_new, gamma + h, F, h, dg * grow, err, rejected, it, lerr)


INTEGRATORS["ros2"] = ROS2
