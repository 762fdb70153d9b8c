"""A stabilised explicit integrator for the stiff bonded flow: second-order
Runge-Kutta-Chebyshev (RKC2; van der Houwen & Sommeijer 1980, Sommeijer, Shampine & Verwer
1998), ``[integrator] method = "rkc"``.

Why: near jamming the fast modes of ds/dgamma = F(s) relax like a diffusion whose constant
grows with <V^2> (the chain) -- stiff, with the Jacobian's spectrum spread along the negative
real axis.  Heun's stability interval there is [-2, 0]: its step is bounded by stability,
not accuracy (DESIGN §5).  RKC2 with s stages is stable on [-beta(s), 0], beta ~ 0.65 s^2
(damping 2/13): s force evaluations buy a step s^2 times longer than one Heun evaluation can.

One step of size h = direction * dg from (s, gamma) with F0 = F(s):
    rho   ~ |lambda_max| of dF/ds (nonlinear power iteration on differences of F, refreshed
            every REFRESH steps, after a rejection, and when the step grows past what rho
            was estimated for)
    s     = 1 + ceil(sqrt(1.54 dg rho * SAFETY)), at least 2
    Y0 = s;  Y1 = Y0 + mu~_1 h F0
    Yj = (1 - mu_j - nu_j) Y0 + mu_j Y(j-1) + nu_j Y(j-2) + mu~_j h F(Y(j-1)) + gamma~_j h F0
    (the Chebyshev recursion, coefficients below), s' = Ys, projected on the rod lengths
    with the last stage's factor (as Heun), and F1 = F(s') (reused as the next F0).
    Computed as increments dj = Yj - Y0 (the same recursion without the Y0 term), so that
    no |s|-sized terms with cancelling coefficients are rounded: formed from the states, the
    round-off was 10x Heun's seed of the chain's reversal (docs/chain.md "What seeds it").
    error estimate (embedded, first order): est = 0.8 (Y0 - Ys) + 0.4 h (F0 + F1), measured
    like Heun's error as a displacement relative to the step's displacement:
    err = |h^-1-free est in real space| / (dg max(|V0|, |V1|)) -- accepted if err <= tol, and
    the next dg = dg * clip(0.8 (tol / err)^(1/2), 0.2, 4) (the error of a step goes like
    dg^2 in this measure), then bounded as Heun's by max_dgamma and max_displacement.
    A rejected step shrinks dg and doubles the rho the stage count assumes (the power
    iteration may have underestimated it), relaxed by 2 % per accepted step.
Intermediate solves: with integrator.stage_rtol > 0 the stages, F1 and the power iteration
solve N tau = -b by PCG on the factor loaded last (the step's start), each started from the
previous stage's tau (dynamics.bonded, STAGE_MAX_IT); the step's last force is a fresh
factorisation.
Rod lengths and sigma identity: as every bonded step (projection, and sigma computed from the
final force solve).
Not for reversed networks: on an N = 4 096 network RKC2 agrees with Heun on sigma(gamma)
forward (gamma at sigma = 1e6 to 1e-10) but its reversed branch's C is 7-9 % above Heun's at
every tolerance tried: the reversed branch depends on what seeds the reversal, and unseeded
that is each integrator's own error (turn states 7e-7 a0 apart reverse differently); with
the reversal seeded (leg key perturb = 3e-4) Heun and RKC2 agree per seed to 2.5 %
(docs/benchmarks.md, "Integrators on a network").  It does not converge to Heun's with the
step: the reversed flow picks its branch by the seed's projection on its fastest growing
modes (along the direction separating the two methods' turn states, by its sign), and
RKC2's error at the turn -- even held to two stages, in steps of 1e-8 -- lies on the other
side from Heun's, its direction fixed as the step shrinks (Heun's own C is not converged
either: it changes branch below steps of 5e-9; benchmarks/bench_turn_seed.py, "What selects
a network's reversed branch").
"""
from __future__ import annotations

import math

import numpy as np

from ..algebra.solvers import SingularOperator
from .heun import INTEGRATORS, Heun, Stall, StepResult, vnorm

EPS_DAMP = 2.0 / 13.0        # damping of the Chebyshev polynomial (stability margin)
SAFETY = 1.2                 # on the spectral-radius estimate
REFRESH = 20                 # steps between spectral-radius estimates
MAX_STAGES = 200
POWER_ITERS = 6
BOOST_MAX = 64.0
BOOST_RELAX = 0.98


def rkc_coefficients(s: int):
    """(mu~_1, [mu_j], [nu_j], [mu~_j], [gamma~_j], j = 2..s) of RKC2 with s stages."""
    w0 = 1.0 + EPS_DAMP / s ** 2
    T = np.zeros(s + 1)       # T_j(w0), T'_j(w0), T''_j(w0) by the Chebyshev recursion
    dT = np.zeros(s + 1)
    d2T = np.zeros(s + 1)
    T[0], T[1] = 1.0, w0
    dT[1] = 1.0
    for j in range(2, s + 1):                       # stages only: a few hundred at most
        T[j] = 2 * w0 * T[j - 1] - T[j - 2]
        dT[j] = 2 * T[j - 1] + 2 * w0 * dT[j - 1] - dT[j - 2]
        d2T[j] = 4 * dT[j - 1] + 2 * w0 * d2T[j - 1] - d2T[j - 2]
    w1 = dT[s] / d2T[s]
    b = np.zeros(s + 1)
    b[2:] = d2T[2:] / dT[2:] ** 2
    b[0] = b[1] = b[2]
    a = 1.0 - b * T
    mut1 = b[1] * w1
    mu, nu, mut, gt = [], [], [], []
    for j in range(2, s + 1):
        mu.append(2 * b[j] * w0 / b[j - 1])
        nu.append(-b[j] / b[j - 2])
        mut.append(2 * b[j] * w1 / b[j - 1])
        gt.append(-a[j - 1] * mut[-1])
    return mut1, mu, nu, mut, gt


def stages_for(dg: float, rho: float, max_stages: int = MAX_STAGES) -> int:
    return int(min(max_stages, max(2, 1 + math.ceil(math.sqrt(1.54 * dg * rho * SAFETY)))))


class RKC(Heun):
    """RKC2 steps of the bonded flow (see the module); same interface as Heun."""

    def __init__(self, system, control, err_prev=None):
        super().__init__(system, control, err_prev)
        self.rho = None              # spectral radius estimate of dF/ds (per unit strain)
        self.rho_dg = 0.0            # the largest step it was estimated for
        self.v = None                # its eigenvector (warm start)
        self.since = 0
        self.boost = 1.0             # on rho: doubled by a rejection, relaxed by accepted steps
        self.evaluations = 0

    def memory(self) -> tuple[dict, dict]:
        if self.rho is None:
            return {}, {}
        return dict(rkc_v=self.v), dict(rkc_rho=self.rho, rkc_rho_dg=self.rho_dg, rkc_since=self.since,
                                        rkc_boost=self.boost)

    def recall(self, ck: dict) -> None:
        if "rkc_rho" in ck:
            self.rho, self.rho_dg = float(ck["rkc_rho"]), float(ck["rkc_rho_dg"])
            self.since, self.v = int(ck["rkc_since"]), np.array(ck["rkc_v"], dtype=float)
            self.boost = float(ck.get("rkc_boost", 1.0))

    def _F(self, s, gamma, what, near=None):
        """F at (s, gamma); ``near``: a Force at a nearby configuration (its tau starts the
        PCG of an intermediate solve, stage_rtol > 0)."""
        self.evaluations += 1
        return self.system.evaluate(s, gamma, what=what, rtol=self.c.stage_rtol,
                                    guess=None if near is None else near.tau, intermediate=True)

    def spectral_radius(self, s, gamma, F0) -> float:
        """|lambda_max| of dF/ds at (s, gamma) by a nonlinear power iteration on finite
        differences of F (POWER_ITERS force evaluations)."""
        k0 = F0.ds
        scale = max(float(np.sqrt(np.mean(s * s))), 1e-8)
        v = self.v if self.v is not None else np.random.default_rng(0).standard_normal(s.shape)
        v = v / np.linalg.norm(v)
        rho = 0.0
        for _ in range(POWER_ITERS):
            eps = 1e-7 * scale * math.sqrt(s.size)
            Fv = self._F(s + eps * v, gamma, "spectral radius", near=F0).ds
            w = (Fv - k0) / eps
            nw = float(np.linalg.norm(w))
            if not np.isfinite(nw) or nw == 0:
                break
            rho, v = nw, w / nw
        self.v = v
        return rho

    def step(self, s, gamma, F0, direction: int, dg: float, dg_cap: float | None = None) -> StepResult:
        c = self.c
        rejected = 0
        nV0 = vnorm(F0.V_na)
        stall, dg_first = Stall(), dg
        while True:
            dg = self.trial(F0, dg, dg_cap, gamma, rejected, stall)
            if self.rho is None or self.since >= REFRESH or rejected or dg > 1.5 * self.rho_dg:
                try:
                    self.rho = self.spectral_radius(s, gamma, F0)
                except SingularOperator:
                    self.rho = self.rho or 0.0
                self.rho_dg, self.since = dg, 0
            n_st = stages_for(dg, self.rho * self.boost, c.max_stages)
            h = direction * dg
            try:
                Ys, F1, d = self._stages(s, gamma, F0, h, n_st)
            except SingularOperator:
                rejected += 1
                dg *= 0.25
                continue
            est = 0.4 * h * (F0.ds + F1.ds) - 0.8 * d      # d = Ys - s, not rounded
            r_est = est @ F1.h.T
            scale = dg * max(nV0, vnorm(F1.V_na))
            err = float(np.linalg.norm(r_est)) / scale if scale > 0 else 0.0
            if not np.isfinite(err) or err > c.tol:
                rejected += 1
                # a power iteration approaches rho from below, slowly where the top of the
                # spectrum is dense (a long chain: a diffusion): a rejection may be an unstable
                # step, so the next stage count assumes a twice larger rho.  (Boosting only
                # rejections with err > 8 tol: networks 1 271 -> 706 factorisations, but the
                # Fig. 2 chain 361 -> 425 trial steps; RKC is not for networks anyway,
                # docs/benchmarks.md "Integrators on a network".)
                self.boost = min(self.boost * 2.0, BOOST_MAX)
                if np.isfinite(err) and stall.stalled(dg, err):
                    F0 = self.refresh(s, gamma)
                    nV0, dg = vnorm(F0.V_na), dg_first
                    continue
                dg *= max(0.2, 0.8 * math.sqrt(c.tol / err)) if np.isfinite(err) and err > 0 else 0.25
                continue
            try:
                s_new, it, lerr, F = self.finish(Ys, gamma + h)
            except SingularOperator:
                rejected += 1
                dg *= 0.25
                continue
            self.since += 1
            self.boost = max(1.0, self.boost * BOOST_RELAX)
            self.err_prev = err
            grow = min(4.0, max(0.2, 0.8 * math.sqrt(c.tol / err))) if err > 0 else 4.0
            if rejected:
                grow = min(grow, 1.0)
            return StepResult(s_new, gamma + h, F, h, dg * grow, err, rejected, it, lerr)

    def _stages(self, s, gamma, F0, h, n_st):
        """Ys, F(Ys) and Ys - s of one RKC2 step with n_st stages (F evaluated at the
        stages)."""
        mut1, mu, nu, mut, gt = rkc_coefficients(n_st)
        k0 = F0.ds
        # the stages as increments d_j = Y_j - s: Y_j = (1 - mu - nu) s + mu Y_j-1 + nu Y_j-2
        # + ... is d_j = mu d_j-1 + nu d_j-2 + ..., the same in exact arithmetic, but it does
        # not round |s|-sized terms whose coefficients (~2 and ~-1) cancel
        d_prev2, d_prev = np.zeros_like(s), mut1 * h * k0
        # stage abscissae c_j (for gamma): c_1 = mu~_1, then the same recursion on c
        c_prev2, c_prev = 0.0, mut1
        F = F0
        for j in range(2, n_st + 1):               # the stages (sequential by nature)
            F = self._F(s + d_prev, gamma + c_prev * h, "RKC stage", near=F)
            m, n_, mt, g = mu[j - 2], nu[j - 2], mut[j - 2], gt[j - 2]
            d = m * d_prev + n_ * d_prev2 + mt * h * F.ds + g * h * k0
            cj = m * c_prev + n_ * c_prev2 + mt + g
            d_prev2, d_prev, c_prev2, c_prev = d_prev, d, c_prev, cj
        Ys = s + d_prev
        F1 = self._F(Ys, gamma + h, "RKC end", near=F)
        return Ys, F1, d_prev


INTEGRATORS["rkc"] = RKC
