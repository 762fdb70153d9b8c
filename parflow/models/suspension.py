"""Hard-disc suspension in simple shear as a model of the scene driver (paper §V, Figs. 6-7).

The step (contact LCP, the no-overlap step) is in ``dynamics.hard_discs`` and
``dynamics.lcp``; the driver runs it through ``dynamics.engines.ContactEngine``.  This module
holds the scene parameters, the initial states (random non-overlapping discs relaxed by FIRE,
or a user configuration), and the analyses at chosen instants:

* the contact-force distribution P(f) of the force-bearing contacts (f / <f>);
* the velocity correlation C(r) of V_na (``observables.correlation``: exact pair sum up to
  10^4 discs, FFT on a grid above);
* the **frozen contact network** (``models.frozen``): the force-bearing contacts become rods
  at their current length.  On it, with the bonded machinery (``BondedSystem``):
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
import os

import numpy as np

from ..dynamics.hard_discs import Suspension, gap_roundoff, min_gap
from ..dynamics.lcp import FACTORS
from ..geometry import cell_at, find_candidates, velocity_gradient
from ..observables import correlation as corr
from ..observables import response as resp
from ..observables import stress
from ..observables.contacts import coordination, force_bearing, force_distribution
from ..packing.fire import fire_minimize
from ..packing.mixture import PHI_J_2D as PHI_J
from ..packing.mixture import RADIUS_RATIO, binary_radii, check_mixture, check_phi
from ..packing.pairs import pair_list, wrap01
from ..algebra.solvers import SolveError
from ..algebra.spectrum import omega_min_on
from ..state import InputError, Instant, State
from . import frozen as fz

NAME = "suspension"
ENGINE = "contacts"
FLOW = "shear"
FACTOR_REUSE = False

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
    "compress_rate": (float, 0.0, lambda v: 0.0 <= v <= 1.0,
                      "packing fraction gained per unit strain while the suspension flows, in "
                      "[0, 1] (0: fixed phi; the discs swell until phi = compress_to)"),
    "compress_to": (float, 0.0, lambda v: v == 0.0 or 0.0 < v < PHI_J,
                    f"packing fraction where the compression stops, in (phi, {PHI_J}) (0: none)"),
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
_ANALYSIS_KEYS = ("force_bins", "correlation", "corr_dr", "corr_rmax", "response_rods",
                  "response_dr", "delta_gamma", "delta_gamma_factor", "delta_gamma_max")


def _defaults(params: dict) -> dict:
    p = {k: v[1] for k, v in PARAMS.items()}
    p.update(params)
    return p


def build(params: dict, seed: int) -> State:
    p = _defaults(params)
    if p["dg_min"] >= p["dg_max"]:
        raise InputError("model.dg_min must be smaller than model.dg_max")
    if (p["compress_rate"] > 0) != (p["compress_to"] > 0):
        raise InputError("model.compress_rate and model.compress_to go together: set both "
                         "(compression while shearing) or neither")
    if p["compress_rate"] > 0 and not p["compress_to"] > p["phi"]:
        raise InputError(f"model.compress_to = {p['compress_to']:g} must be above model.phi = "
                         f"{p['phi']:g} (the packing fraction the flow starts from)")
    check_mixture(p["ratio"], (p["small_fraction"], 1.0 - p["small_fraction"]))
    if p["configuration_file"]:
        state = load_configuration(p["configuration_file"], p)
    else:
        state = make_suspension(p["N"], p["phi"], seed=seed, ratio=p["ratio"],
                                composition=(p["small_fraction"], 1.0 - p["small_fraction"]))
    state.meta.update(model="suspension", phi_target=float(p["phi"]), ratio=float(p["ratio"]),
                      small_fraction=float(p["small_fraction"]))
    # (the compression keys only when the run compresses: a run at fixed phi records what
    # it recorded before they existed)
    skip = ("compress_rate", "compress_to") if p["compress_rate"] == 0 else ()
    state.meta.update({k: (int(v) if isinstance(v, bool) else v) for k, v in p.items()
                       if k in Suspension.CONTROLS + _ANALYSIS_KEYS and k not in skip})
    return state


# --------------------------------------------------------------------------- initial states

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
    ``gamma``; refuses overlapping discs (beyond the positions' round-off,
    ``hard_discs.gap_roundoff``), non-positive radii and phi >= phi_J."""
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
    # a contact closed to the positions' round-off (a state written by a run: its closed
    # contacts sit at gaps of +- a few eps ||h||) is a contact, not an overlap
    tol = gap_roundoff(state.h)
    bad = c.gap < -tol
    if np.any(bad):
        raise InputError(f"suspension: the configuration has {int(bad.sum())} overlapping "
                         f"pair(s), the largest overlap {-c.gap.min():.3g} a0 (e.g. discs "
                         f"{int(c.i[bad][0])} and {int(c.j[bad][0])}; overlaps up to the "
                         f"positions' round-off {tol:.2g} a0 count as contacts); hard discs "
                         f"must not overlap")
    return state


def load_configuration(path: str, p: dict) -> State:
    """A user configuration (.npz: positions, radii, box[, gamma]); refused if it does not
    match the scene (N, phi to 1e-6) or if discs overlap (``from_configuration``)."""
    if not os.path.isfile(path):
        if "{sample}" in path:
            raise InputError(f"model.configuration_file {path!r} holds {{sample}}, which only an "
                             f"ensemble fills in (one file per sample): run it with --samples K "
                             f"or name one file")
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
    state = from_configuration(data["positions"], data["radii"], data["box"],
                               float(data.get("gamma", 0.0)))
    bad = []
    if state.n != p["N"]:
        bad.append(f"N = {state.n} (scene: model.N = {p['N']})")
    if abs(state.meta["phi"] - p["phi"]) > 1e-6:
        bad.append(f"phi = {state.meta['phi']:.8g} (scene: model.phi = {p['phi']:g})")
    if bad:
        raise InputError(f"model.configuration_file {path!r} does not match the scene: "
                         + "; ".join(bad))
    state.meta.update(configuration_file=path, initial_min_gap=min_gap(state))
    return state


def observables(state: State, F) -> dict:
    """Per step: sigma_fb = -dir <f|b>/Omega, p = sum f |r| / (d Omega), mu = sigma / p, and
    the coordination z (force-bearing contacts, rattlers removed; z_all, z2 beside it)."""
    fb_sigma = stress.sigma_tb(F.f, F.c.b, F.omega, F.direction)
    p = stress.pressure(F.f, F.c.dist, F.omega, state.d)
    z = coordination(F.c, F.f, state.n, state.d)
    return dict(sigma_fb=fb_sigma, pressure=p, mu=F.sigma / p if p > 0 else float("nan"), **z)


def omega_min(at: Instant) -> float:
    """omega_min of the suspension at this instant: that of its frozen contact network
    (NaN if it carries a state of self-stress)."""
    return fz.frozen_omega_min(at.comm, at.state, at.F, at.scene)


# --------------------------------------------------------------------------- analyses

def analyses(at: Instant) -> dict:
    """P(f), C(r) and, on the frozen contact network, sigma, omega_min, the point response
    and delta_gamma, at the configuration of ``at.F`` (a probe of the current state)."""
    comm, state, F, scene, direction = at.comm, at.state, at.F, at.scene, at.direction
    meta = scene["model"]
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
    frozen = fz.freeze(state, F)
    system = fz.frozen_system(comm, frozen, scene)
    scalars.update(frozen_error="", frozen_sigma=math.nan, frozen_omega_min=math.nan)
    try:
        Fz = system.evaluate(frozen.s, frozen.gamma, what="frozen contacts")
        scalars["frozen_sigma"] = Fz.sigma
        scalars["frozen_n_rods"] = len(frozen.bonds)
        scalars["frozen_omega_min"] = omega_min_on(system)
        if meta["response_rods"] > 0:
            bd = frozen.bonds
            rods = resp.pick_rods(s, h, bd, meta["response_rods"])
            pr = resp.point_response(system, s, h, bd, rods, meta["response_dr"])
            fit = resp.fit_two_exponentials(pr["r"], pr["V_mean"], pr["counts_V"])
            arrays.update(resp_r=pr["r"], resp_V=pr["V_mean"], resp_counts_V=pr["counts_V"],
                          resp_f=pr["f_mean"], resp_rods=rods, resp_VV=pr["VV"])
            scalars.update({f"resp_{k}": v for k, v in fit.items()})
            scalars["VV"] = float(np.mean(pr["VV"]))
        scalars.update(fz.relaxation_rate(system, frozen, Fz, direction, scene))
        system.load(Fz.n)            # back to the configuration of the instant
        if meta["delta_gamma"]:
            dg = fz.delta_gamma(system, frozen, Fz, direction, scene, meta["delta_gamma_factor"],
                                meta["delta_gamma_max"])
            arrays.update(dg.pop("arrays"))
            scalars.update(dg)
    except SolveError as exc:
        # a state of self-stress among the force-bearing contacts: N_fb is singular
        scalars["frozen_error"] = f"{type(exc).__name__}: {exc}"
    finally:
        system.destroy()
    return dict(arrays=arrays, scalars=scalars)
