"""Hard-disc suspension in simple shear as a model of the scene driver (paper §V, Figs. 6-7).

The physics (initial states, contact LCP, the no-overlap step) is in ``parflow.suspension``
and ``parflow.contacts``; the driver runs it through ``engines.ContactEngine``.  This module
holds the scene parameters, the builder, and the analyses at chosen instants:

* the contact-force distribution P(f) of the force-bearing contacts (f / <f>);
* the velocity correlation C(r) of V_na (``network.correlation``: exact pair sum up to 10^4
  discs, FFT on a grid above);
* the **frozen contact network**: the force-bearing contacts become rods at their current
  length (``freeze``).  On it, with the network machinery (``BondedSystem``):
  - omega_min = sqrt(lambda_min(N_fb)) (SLEPc on the force solver's factor);
  - the point response N f = |beta>, V = S^T f, binned by distance, l_c and l_r fits;
  - the distance to jamming delta_gamma: the frozen network is sheared *backwards* (against
    the flow of the current leg) with the Heun integrator of [integrator] until its stress
    has grown by ``delta_gamma_factor`` (or it jams, or ``delta_gamma_max`` strain is used);
    delta_gamma is the strain where 1/sigma extrapolates to 0 from the last two records
    (sigma ~ 1/(delta_gamma - x) near jamming; the strain at which the target was reached is
    stored beside it).  The paper's prediction: delta_gamma ~ 1/sigma.
  The frozen network can carry a state of self-stress (a singular N among the force-bearing
  contacts): then those analyses are NaN with a message, not a failure of the run.
"""
from __future__ import annotations

import math

import numpy as np

from ..observables import correlation as corr
from ..observables import response as resp
from ..packing.mixture import PHI_J_2D as PHI_J
from ..state import Bonds, InputError, State

ENGINE = "contacts"
FLOW = "shear"
FACTORS = ("cholmod", "superlu")

PARAMS = {
    # name: (type, default, check, description)
    "N": (int, 4096, lambda v: v >= 16, "number of discs (>= 16)"),
    "phi": (float, 0.82, lambda v: 0.0 < v < PHI_J,
            f"packing fraction in (0, {PHI_J}): at or above phi_J ~ {PHI_J} hard discs of this "
            f"mixture cannot flow (the paper's range is 0.820-0.840)"),
    "ratio": (float, 1.4, lambda v: v > 0, "radius ratio large/small (> 0)"),
    "small_fraction": (float, 0.5, lambda v: 0.0 <= v <= 1.0,
                       "number fraction of small discs in [0, 1] (the rest are large)"),
    "configuration_file": (str, "", lambda v: True,
                           "'' (generate) or a .npz file with positions (N, 2), radii (N,), "
                           "box (2,) and optionally gamma: the initial configuration"),
    "skin": (float, 0.3, lambda v: v > 0, "candidate-pair skin in a0 (> 0)"),
    "c": (float, 0.05, lambda v: v > 0, "step bound dgamma <= c / sigma (> 0)"),
    "dmax": (float, 0.01, lambda v: v > 0, "largest non-affine displacement per step in a0 (> 0)"),
    "dg_max": (float, 1e-2, lambda v: v > 0, "largest strain step (> 0)"),
    "dg_min": (float, 1e-12, lambda v: v > 0, "smallest strain step before shear jamming is declared (> 0)"),
    "factor": (str, "cholmod", lambda v: v in FACTORS, f"one of {list(FACTORS)}: factorisation of N_AA"),
    "collision_gap": (float, 1e-4, lambda v: v > 0,
                      "a new contact counts as a collision when its gap was above this (a0, > 0)"),
    "force_bins": (int, 40, lambda v: v >= 2, "log-spaced bins of P(f) (>= 2)"),
    "correlation": (bool, True, lambda v: True, "true/false: C(r) at analysis instants"),
    "corr_dr": (float, 0.5, lambda v: v > 0, "bin width of C(r) (> 0)"),
    "corr_rmax": (float, 0.0, lambda v: v >= 0, ">= 0: largest r of C(r) (0: half the cell height)"),
    "response_rods": (int, 8, lambda v: v >= 0, "rods beta of the point response (0: none)"),
    "response_dr": (float, 0.5, lambda v: v > 0, "bin width of the point response (> 0)"),
    "delta_gamma": (bool, True, lambda v: True, "true/false: distance to jamming at analysis instants"),
    "delta_gamma_factor": (float, 1e4, lambda v: v > 1,
                           "stress growth of the frozen network that counts as jammed (> 1)"),
    "delta_gamma_max": (float, 1.0, lambda v: v > 0, "largest backward strain tried (> 0)"),
}
_CONTROL_KEYS = ("skin", "c", "dmax", "dg_max", "dg_min", "factor", "collision_gap")
_ANALYSIS_KEYS = ("force_bins", "correlation", "corr_dr", "corr_rmax", "response_rods",
                  "response_dr", "delta_gamma", "delta_gamma_factor", "delta_gamma_max")


def _defaults(params: dict) -> dict:
    p = {k: v[1] for k, v in PARAMS.items()}
    p.update(params)
    return p


def build(params: dict, seed: int) -> State:
    from .. import suspension as su
    p = _defaults(params)
    if p["dg_min"] >= p["dg_max"]:
        raise InputError("model.dg_min must be smaller than model.dg_max")
    su.check_mixture(p["ratio"], (p["small_fraction"], 1.0 - p["small_fraction"]))
    if p["configuration_file"]:
        state = load_configuration(p["configuration_file"], p)
    else:
        state = su.make_suspension(p["N"], p["phi"], seed=seed, ratio=p["ratio"],
                                   composition=(p["small_fraction"], 1.0 - p["small_fraction"]))
    state.meta.update(model="suspension", phi_target=float(p["phi"]), ratio=float(p["ratio"]),
                      small_fraction=float(p["small_fraction"]))
    state.meta.update({k: (int(v) if isinstance(v, bool) else v) for k, v in p.items()
                       if k in _CONTROL_KEYS + _ANALYSIS_KEYS})
    return state


def load_configuration(path: str, p: dict) -> State:
    """A user configuration (.npz: positions, radii, box[, gamma]); refused if it does not
    match the scene (N, phi to 1e-6) or if discs overlap (``suspension.from_configuration``)."""
    import os

    from .. import suspension as su
    if not os.path.isfile(path):
        raise InputError(f"model.configuration_file {path!r} does not exist")
    try:
        with np.load(path) as z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError) as exc:
        raise InputError(f"model.configuration_file {path!r} is not a .npz file: {exc}") from None
    missing = [k for k in ("positions", "radii", "box") if k not in data]
    if missing:
        raise InputError(f"model.configuration_file {path!r} lacks {', '.join(missing)} "
                         f"(needs positions (N, 2), radii (N,), box (2,), optionally gamma)")
    state = su.from_configuration(data["positions"], data["radii"], data["box"],
                                  float(data.get("gamma", 0.0)))
    bad = []
    if state.n != p["N"]:
        bad.append(f"N = {state.n} (scene: model.N = {p['N']})")
    if abs(state.meta["phi"] - p["phi"]) > 1e-6:
        bad.append(f"phi = {state.meta['phi']:.8g} (scene: model.phi = {p['phi']:g})")
    if bad:
        raise InputError(f"model.configuration_file {path!r} does not match the scene: "
                         + "; ".join(bad))
    state.meta.update(configuration_file=path, initial_min_gap=su.min_gap(state))
    return state


def _meta(meta: dict, keys) -> dict:
    out = {}
    for k in keys:
        v = meta.get(k, PARAMS[k][1])
        typ = PARAMS[k][0]
        out[k] = bool(v) if typ is bool else (str(v) if typ is str else typ(v))
    return out


def controls(meta: dict) -> dict:
    """Keyword arguments of ``suspension.Suspension`` from the state's meta."""
    return _meta(meta, _CONTROL_KEYS)


def restore_dict(state: State, ck: dict) -> dict:
    """The ``Suspension.restore`` dict from the run file's initial state and checkpoint."""
    return dict(s=ck["s"], h0=state.h0, gamma=ck["gamma"], radii=state.radii,
                sigma=ck["sigma"], vmax=ck["vmax"], last_dg=ck.get("dgamma", 0.0),
                active_keys=ck["active_keys"],
                steps=ck["steps"], collisions=ck["collisions"], max_overlap=ck["max_overlap"],
                singular_events=ck["singular_events"],
                infeasible_reductions=ck["infeasible_reductions"], controls=controls(state.meta))


# --------------------------------------------------------------------------- frozen network

def force_bearing(f: np.ndarray, rel: float = 1e-12) -> np.ndarray:
    return f > rel * (float(f.max()) if f.size else 0.0)


def freeze(state: State, F, rel: float = 1e-12) -> State:
    """The force-bearing contacts of ``F`` (engines.ContactForce at the current configuration)
    as rods at their current length: a bonded State at the same positions and strain."""
    fb = force_bearing(F.f, rel)
    c = F.c
    if not np.any(fb):
        raise InputError("suspension: no force-bearing contact to freeze")
    bonds = Bonds(c.i[fb], c.j[fb], c.shift[fb], c.dist[fb])
    return State(np.array(state.s, float), state.h0.copy(), state.E.copy(), float(F.gamma),
                 bonds, None, dict(model="frozen contacts"))


def _frozen_system(comm, frozen: State, scene: dict):
    from ..dynamics.bonded import BondedSystem
    return BondedSystem(comm, frozen, scene["solver"]["preset"], scene["solver"]["parallel"])


def _omega_min(system) -> float:
    """omega_min of the loaded N, on the force solver's factor (shift-and-invert at 0)."""
    from ..spectrum import LowSpectrum, omega_from_lambda
    spec = LowSpectrum(system.ops.N, k=1, parallel=system.parallel, ksp=system.tau_solver.ksp)
    try:
        lam, _ = spec.solve()
    finally:
        spec.destroy()
    return float(omega_from_lambda(lam[:1])[0])


def frozen_omega_min(comm, state: State, F, scene: dict) -> float:
    """omega_min of the frozen contact network (NaN if it carries a state of self-stress)."""
    from ..solvers import SolveError
    frozen = freeze(state, F)
    system = _frozen_system(comm, frozen, scene)
    try:
        system.evaluate(frozen.s, frozen.gamma, what="frozen contacts")
        return _omega_min(system)
    except SolveError:
        return float("nan")
    finally:
        system.destroy()


def _heun(system, scene: dict):
    """The step control of the scene's [integrator] and a Heun stepper on ``system``."""
    from ..dynamics.heun import Heun, StepControl
    control = StepControl(**scene["integrator"])
    return control, Heun(system, control)


def delta_gamma(system, frozen: State, F0, direction: int, scene: dict, factor: float,
                max_strain: float, max_steps: int = 20_000) -> dict:
    """Shear the frozen network against ``direction`` until sigma >= factor * sigma_0."""
    from ..dynamics.heun import Jammed
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
    from ..dynamics.heun import Jammed
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


def force_distribution(f: np.ndarray, bins: int) -> dict:
    """P(f/<f>) of the force-bearing contacts on log-spaced bins from 1e-4 to 1e2."""
    fb = f[force_bearing(f)]
    out = dict(edges=np.geomspace(1e-4, 1e2, bins + 1), P=np.full(bins, np.nan), mean=math.nan)
    if fb.size:
        x = fb / fb.mean()
        hist, _ = np.histogram(x, out["edges"])
        out.update(P=hist / (x.size * np.diff(out["edges"])), mean=float(fb.mean()))
    return out


# --------------------------------------------------------------------------- analyses

def analyses(comm, state: State, F, scene: dict, direction: int = 1) -> dict:
    """P(f), C(r) and, on the frozen contact network, sigma, omega_min, the point response
    and delta_gamma, at the configuration of ``F`` (a probe of the current state)."""
    from ..solvers import SolveError
    meta = _meta(state.meta, _ANALYSIS_KEYS)
    s, h = np.asarray(state.s, float), F.h
    arrays, scalars = {}, {}
    pf = force_distribution(F.f, meta["force_bins"])
    arrays.update(force_edges=pf["edges"], force_P=pf["P"])
    scalars.update(force_mean=pf["mean"], n_force_bearing=int(np.count_nonzero(force_bearing(F.f))))
    if meta["correlation"]:
        cr = corr.correlation(s, h, F.V_na, meta["corr_dr"], meta["corr_rmax"])   # exact / FFT by N
        scalars["corr_method"] = cr["method"]
        arrays.update(corr_r=cr["r"], corr_C=cr["C"], corr_counts=cr["counts"])
        scalars["corr_length"] = corr.crossing_length(cr["r"], cr["C"], counts=cr["counts"])
    frozen = freeze(state, F)
    system = _frozen_system(comm, frozen, scene)
    scalars.update(frozen_error="", frozen_sigma=math.nan, frozen_omega_min=math.nan)
    try:
        Fz = system.evaluate(frozen.s, frozen.gamma, what="frozen contacts")
        scalars["frozen_sigma"] = Fz.sigma
        scalars["frozen_n_rods"] = len(frozen.bonds)
        scalars["frozen_omega_min"] = _omega_min(system)
        if meta["response_rods"] > 0:
            bd = frozen.bonds
            rods = resp.pick_rods(s, h, bd, meta["response_rods"])
            pr = resp.point_response(system, s, h, bd, rods, meta["response_dr"])
            fit = resp.fit_two_exponentials(pr["r"], pr["V_mean"], pr["counts_V"])
            arrays.update(resp_r=pr["r"], resp_V=pr["V_mean"], resp_counts_V=pr["counts_V"],
                          resp_f=pr["f_mean"], resp_rods=rods, resp_VV=pr["VV"])
            scalars.update({f"resp_{k}": v for k, v in fit.items()})
            scalars["VV"] = float(np.mean(pr["VV"]))
        scalars.update(relaxation_rate(system, frozen, Fz, direction, scene))
        system.load(Fz.n)            # back to the configuration of the instant
        if meta["delta_gamma"]:
            dg = delta_gamma(system, frozen, Fz, direction, scene, meta["delta_gamma_factor"],
                             meta["delta_gamma_max"])
            arrays.update(dg.pop("arrays"))
            scalars.update(dg)
    except SolveError as exc:
        # a state of self-stress among the force-bearing contacts: N_fb is singular
        scalars["frozen_error"] = f"{type(exc).__name__}: {exc}"
    finally:
        system.destroy()
    return dict(arrays=arrays, scalars=scalars)
