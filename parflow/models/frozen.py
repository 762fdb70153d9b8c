"""The frozen contact network of a suspension: its force-bearing contacts as rods at their
current length (paper §V).  On it, with the bonded machinery (``dynamics.bonded``):

* omega_min = sqrt(lambda_min(N_fb)) (SLEPc on the force solver's factor);
* dsigma/dgamma between collisions (``relaxation_rate``): the frozen contacts are the
  suspension's constraints until a contact opens or a new one closes;
* the distance to jamming delta_gamma (``delta_gamma``): the frozen network sheared
  *backwards* with the Heun integrator until its stress has grown by a factor (or it jams);
  delta_gamma is where 1/sigma extrapolates to 0 from the last two records.
The frozen network can carry a state of self-stress (a singular N): callers get a SolveError.
"""
from __future__ import annotations

import math

import numpy as np

from ..dynamics.bonded import BondedSystem
from ..dynamics.heun import Heun, Jammed, StepControl
from ..observables.contacts import FORCE_BEARING_REL, force_bearing
from ..algebra.solvers import SolveError
from ..algebra.spectrum import omega_min_on
from ..state import Bonds, InputError, State


def freeze(state: State, F, rel: float = FORCE_BEARING_REL) -> State:
    """The force-bearing contacts of ``F`` (engines.ContactForce at the current configuration)
    as rods at their current length: a bonded State at the same positions and strain."""
    fb = force_bearing(F.f, rel)
    c = F.c
    if not np.any(fb):
        raise InputError("suspension: no force-bearing contact to freeze")
    bonds = Bonds(c.i[fb], c.j[fb], c.shift[fb], c.dist[fb])
    return State(np.array(state.s, float), state.h0.copy(), state.E.copy(), float(F.gamma),
                 bonds, None, dict(model="frozen contacts"))


def frozen_system(comm, frozen: State, scene: dict):
    return BondedSystem(comm, frozen, scene["solver"]["preset"], scene["solver"]["parallel"])


def frozen_omega_min(comm, state: State, F, scene: dict) -> float:
    """omega_min of the frozen contact network (NaN if it carries a state of self-stress)."""
    frozen = freeze(state, F)
    system = frozen_system(comm, frozen, scene)
    try:
        system.evaluate(frozen.s, frozen.gamma, what="frozen contacts")
        return omega_min_on(system)
    except SolveError:
        return float("nan")
    finally:
        system.destroy()


def _heun(system, scene: dict):
    """The step control of the scene's [integrator] and a Heun stepper on ``system``."""
    control = StepControl(**scene["integrator"])
    return control, Heun(system, control)


def delta_gamma(system, frozen: State, F0, direction: int, scene: dict, factor: float,
                max_strain: float, max_steps: int = 20_000) -> dict:
    """Shear the frozen network against ``direction`` until sigma >= factor * sigma_0."""
    control, integ = _heun(system, scene)
    s, g, F = frozen.s, frozen.gamma, F0
    sigma0 = F.sigma
    target = factor * sigma0
    xs, sig = [0.0], [sigma0]
    dg, x, how = control.initial_dgamma, 0.0, "target"
    try:
        while F.sigma < target:
            if x >= max_strain:
                how = "max_strain"
                break
            if len(xs) > max_steps:
                how = "max_steps"
                break
            res = integ.step(s, g, F, -direction, dg, dg_cap=max_strain - x + 1e-15)
            s, g, F, dg = res.s, res.gamma, res.F, res.next_dgamma
            x += abs(res.dgamma)
            xs.append(x)
            sig.append(F.sigma)
    except Jammed:
        how = "jammed"
    xs, sig = np.array(xs), np.array(sig)
    dgam = math.nan
    if len(xs) >= 2 and sig[-1] > sig[-2] and how in ("target", "jammed"):
        # 1/sigma linear in x near jamming: extrapolate the last two records to 1/sigma = 0
        a, b = 1.0 / sig[-2], 1.0 / sig[-1]
        dgam = float(xs[-1] + b * (xs[-1] - xs[-2]) / (a - b))
    return dict(delta_gamma=dgam, delta_gamma_reached=float(xs[-1]), delta_gamma_steps=len(xs) - 1,
                delta_gamma_stop=how, frozen_sigma_end=float(sig[-1]),
                arrays=dict(dg_x=xs, dg_sigma=sig))


def relaxation_rate(system, frozen: State, F0, direction: int, scene: dict,
                    rel: float = 1e-3, steps: int = 4) -> dict:
    """dsigma/dgamma of the suspension between collisions, at this instant: the frozen
    contacts are the suspension's constraints until a contact opens or a new one closes, so
    the derivative of the frozen network's sigma along the flow (``direction``) is the
    suspension's.  ``steps`` Heun steps of strain rel / sigma_0 each; the derivative at 0
    from a quadratic fit of sigma(x).  C = sigma_0^2 / (-dsigma/dgamma) (paper: constant)."""
    _, integ = _heun(system, scene)
    s, g, F = frozen.s, frozen.gamma, F0
    sigma0 = F.sigma
    h = rel / max(sigma0, 1e-300)
    xs, sig = [0.0], [sigma0]
    try:
        for _ in range(steps):
            res = integ.step(s, g, F, direction, h, dg_cap=h)
            s, g, F = res.s, res.gamma, res.F
            xs.append(xs[-1] + abs(res.dgamma))
            sig.append(F.sigma)
    except Jammed:
        pass
    out = dict(relax_dsdg=math.nan, relax_C=math.nan, relax_sigma=sigma0)
    if len(xs) >= 3:
        p = np.polyfit(np.array(xs), np.array(sig), min(2, len(xs) - 2))
        dsdg = float(p[-2])
        out.update(relax_dsdg=dsdg, relax_C=float(sigma0 ** 2 / -dsdg) if dsdg < 0 else math.nan)
    return out
