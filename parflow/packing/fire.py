"""Jammed soft-sphere packings by FIRE: the seed of the network model and of the suspension's
initial states (DESIGN §7, issue 3).

Binary 50:50 mixture (``packing.mixture``: radius ratio 1.4, small-particle *diameter* = 1,
the unit of length) in a periodic box whose side is fixed by the packing fraction phi.
Pair potential: harmonic repulsion U = 1/2 sum (1 - r_ij/sigma_ij)^2 over overlapping
pairs, sigma_ij = R_i + R_j.  The force unit is therefore eps/a0 with eps = 1 (the
stiffness scale); a typical contact force is the typical relative overlap 1 - r/sigma.

Minimiser: FIRE (Bitzek et al., PRL 97, 170201, 2006) with the standard parameters
(N_min = 5, f_inc = 1.1, f_dec = 0.5, alpha_start = 0.1, f_alpha = 0.99), unit masses,
semi-implicit Euler, the half-step back-off of FIRE 2.0 (Guénolé et al. 2020) on P <= 0,
dt_0 = 0.1 and dt_max = 0.5 (dt_max = 1 is past the stability limit of the stiffest
pair, ~2/omega_max, and costs 10x more iterations: measured).

Convergence: max_i |F_i| < ftol * <f_c>, where <f_c> is the mean contact-force magnitude
(a *relative* tolerance, so it means the same at every pressure).  See DEFAULT_FTOL for
the choice and what it does to the contact network.

Performance (no Python loop over particles or pairs): positions are stored as (d, N)
arrays in Morton (Z-curve) order for cache locality; a Verlet pair list (``packing.pairs``,
skin ``skin`` = 0.4 by default) is rebuilt only when the largest displacement since the
last build may exceed skin/2 (a running bound sum dt max_i|v_i| is checked first, the
exact displacement only when the bound trips).  The two kernels of the pair list (numpy,
numba) give bit-identical packings; their measured costs are in ``packing.pairs``.
FIRE needs ~6e3 (N = 4096), ~1.3e4-1.8e4 (4e4), ~1.5e4-2.4e4 (1e5) and ~7.6e4-9e4 (1e6)
iterations; the count varies by +-30 % from seed to seed (the glassy relaxation before
the convergent tail dominates it).

Contacts are reported with integer image shifts n in reduced coordinates s = x/L in
[0, 1)^d: r_ij = L * (s_j + n - s_i)   (DESIGN §2, h = diag(L)).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from . import mixture
from .mixture import binary_radii, box_side
from .pairs import PairList, pair_list, wrap01

#: Default relative force tolerance: max|F_i| < DEFAULT_FTOL * <f_c>.  Measured by
#: minimising to 1e-2, 1e-3, ... 1e-11 in turn and comparing the non-rattler contact set
#: with the final one: N = 4096, phi = 0.86: 139 contacts differ at 1e-2, 7 at 1e-3, none
#: from 1e-4 down; N = 40 000, phi = 0.87: 1336 at 1e-2, 261 at 1e-3, 13 at 1e-4, 8 at
#: 1e-5, none from 1e-6 down (z = 4.58804 from 1e-6 to 1e-11).  Going from 1e-6 to 1e-9
#: costs ~10 % more iterations (the cost is in the glassy relaxation before the tail).
#: 1e-9 keeps three decades of margin over the point where the graph freezes.  A relative
#: 1e-12 is not reachable: the round-off floor of max|F| is ~eps*L (see force_floor),
#: 4e-14 at N = 4096 vs <f_c> ~ 5e-3.
DEFAULT_FTOL = 1e-9


@dataclass
class FireParams:
    """FIRE parameters (Bitzek et al. 2006 defaults; dt in units with m = 1, k <= 1)."""

    dt0: float = 0.1
    dt_max: float = 0.5
    n_min: int = 5
    f_inc: float = 1.1
    f_dec: float = 0.5
    alpha0: float = 0.1
    f_alpha: float = 0.99


@dataclass
class Packing:
    """A minimised soft-disc packing.

    positions: (N, d) in [0, L)^d;  radii: (N,);  box: (d,) box sides L (h = diag(box)).
    contacts_i, contacts_j, contacts_shift: force-bearing contacts between non-rattlers
        (i < j), with integer image shifts so that r_ij = box * (s_j + n - s_i).
    rattler: (N,) bool, particles removed iteratively for having < d + 1 contacts.
    pressure: virial pressure p = sum_c f_c r_c / (d V) over all contacts.
    z: mean contact number of the non-rattlers (2 Nc / N_nonrattler).
    phi: packing fraction;  energy: total U;  max_force: max_i |F_i| at the end;
    force_scale: mean contact force <f_c>;  iterations: FIRE iterations (all stages).
    """

    positions: np.ndarray
    radii: np.ndarray
    box: np.ndarray
    contacts_i: np.ndarray
    contacts_j: np.ndarray
    contacts_shift: np.ndarray
    rattler: np.ndarray
    pressure: float
    z: float
    phi: float
    energy: float
    max_force: float
    force_scale: float
    iterations: int
    seed: int
    ftol: float
    info: dict = field(default_factory=dict)

    @property
    def d(self) -> int:
        return int(self.positions.shape[1])

    @property
    def n(self) -> int:
        return int(self.positions.shape[0])

    @property
    def reduced(self) -> np.ndarray:
        """Reduced coordinates s = x / L in [0, 1)^d."""
        return wrap01(self.positions / self.box)

    @property
    def n_contacts(self) -> int:
        return int(self.contacts_i.shape[0])

    def contact_vectors(self) -> np.ndarray:
        """(Nc, d) pair vectors r_ij = L (s_j + n - s_i) of the reported contacts."""
        s = self.reduced
        return self.box * (s[self.contacts_j] + self.contacts_shift - s[self.contacts_i])


# --------------------------------------------------------------------------- initial state

def morton_order(s: np.ndarray, bits: int | None = None) -> np.ndarray:
    """Permutation sorting points s in [0,1)^d (N, d) along a Z-order curve."""
    n, d = s.shape
    if bits is None:
        bits = max(1, min(63 // d, int(math.ceil(math.log2(max(n, 2)) / d)) + 1))
    c = np.minimum((s * (1 << bits)).astype(np.int64), (1 << bits) - 1)
    key = np.zeros(n, dtype=np.int64)
    for b in range(bits):                      # loop over bits, vectorised over points
        for k in range(d):
            key |= ((c[:, k] >> b) & 1) << (b * d + k)
    return np.argsort(key, kind="stable")


# --------------------------------------------------------------------------- FIRE

def fire_minimize(X, pl: PairList, ftol: float, *, params: FireParams | None = None,
                  max_iter: int = 2_000_000, trace: list | None = None,
                  trace_every: int = 100):
    """Minimise the harmonic energy from (d, N) positions X with FIRE.

    Stops when max_i |F_i| < max(ftol * <f_c>, force_floor(box)) (<f_c>: mean contact
    force over overlapping pairs), or when no pair overlaps (F = 0 exactly: an unjammed
    state).  Returns (X, info) with info = dict(iterations, max_force, force_scale,
    converged).  ``trace``, if given, receives (iteration, max|F|, <f_c>) every
    ``trace_every`` steps.

    One iteration is two passes over the particles: pl.step (forces, P = F.v, |F|,
    |v + dt F| for the dt that P > 0 would give, max|F_a|) and pl.update (velocity mixing,
    position update, max|v_a|).  The list is rebuilt when the running bound
    sum dt max_a|v_a| on the displacement, then the exact displacement, exceeds skin/2.
    """
    with pl.threads_set():
        return _fire(X, pl, ftol, params or FireParams(), max_iter, trace, trace_every)


def _fire(X, pl, ftol, p, max_iter, trace, trace_every):
    X = pl.build(X)
    F = np.empty_like(X)
    V = np.zeros_like(X)
    dt, alpha, n_pos = p.dt0, p.alpha0, 0
    bound = 0.0                                   # running bound on the displacement
    half_skin = 0.5 * pl.skin
    floor = force_floor(pl.box)
    dt_plus = min(dt * p.f_inc, p.dt_max) if n_pos + 1 > p.n_min else dt
    power, ff, w, ffmax = pl.step(X, V, F, dt_plus)
    fscale = _force_scale(*pl.overlaps(X))
    it = 0
    converged = False
    while True:
        if not math.isfinite(ff):
            raise RuntimeError(f"packing: non-finite forces at FIRE iteration {it} "
                               "(coincident particles?)")
        fmax = math.sqrt(ffmax)
        if trace is not None and it % trace_every == 0:
            trace.append((it, fmax, fscale))
        if it % 200 == 0 or fmax < max(ftol * fscale, floor):
            fscale = _force_scale(*pl.overlaps(X))
            if fmax < max(ftol * fscale, floor) or fscale == 0.0:
                converged = True
                break
        if it >= max_iter:
            break
        fnorm = math.sqrt(ff)
        if power > 0.0:
            n_pos += 1
            if n_pos > p.n_min:
                dt = min(dt * p.f_inc, p.dt_max)
                alpha *= p.f_alpha
            vnorm = math.sqrt(w)                  # |v + dt F|: dt == dt_plus here
            backoff = False
        else:
            n_pos = 0
            dt *= p.f_dec
            alpha = p.alpha0
            vnorm = dt * fnorm                    # v = 0 + dt F after the back-off
            backoff = True                        # FIRE 2.0: X -= dt/2 v, v = 0
        beta = alpha * vnorm / fnorm if fnorm > 0.0 else None
        vmax2 = pl.update(X, V, F, dt, backoff, 1.0 - alpha, beta)
        bound += dt * math.sqrt(vmax2)
        it += 1
        if bound > half_skin:
            disp = pl.max_displacement(X)
            if disp > half_skin:
                X = pl.build(X)
                disp = 0.0
            bound = disp
        dt_plus = min(dt * p.f_inc, p.dt_max) if n_pos + 1 > p.n_min else dt
        power, ff, w, ffmax = pl.step(X, V, F, dt_plus)
    return X, dict(iterations=it, max_force=math.sqrt(ffmax), force_scale=fscale,
                   converged=converged)


def force_floor(box) -> float:
    """Round-off floor of max|F|: coordinates of size L carry absolute errors ~eps L, so
    forces (stiffness <= 1) cannot be resolved below ~eps L.  Measured floor at L = 70:
    4e-14; we use 16 eps L (2.5e-13 at L = 70, 4e-12 at N = 10^6)."""
    return 16.0 * np.finfo(float).eps * float(np.max(box))


def _force_scale(ov: np.ndarray, isig: np.ndarray) -> float:
    """Mean contact-force magnitude (1 - r/sigma)/sigma over overlapping pairs."""
    m = ov > 0.0
    k = int(np.count_nonzero(m))
    return float((ov[m] * isig[m]).sum() / k) if k else 0.0


# --------------------------------------------------------------------------- contacts

def remove_rattlers(n: int, i: np.ndarray, j: np.ndarray, d: int):
    """Iteratively drop particles with fewer than d + 1 contacts.

    Returns (rattler mask (n,), kept-contact mask (len(i),)).  Each sweep is vectorised;
    the number of sweeps is the depth of the rattler cascade (a handful)."""
    keep = np.ones(i.shape[0], dtype=bool)
    rattler = np.zeros(n, dtype=bool)
    while True:
        deg = np.bincount(i[keep], minlength=n) + np.bincount(j[keep], minlength=n)
        new = (deg < d + 1) & ~rattler
        if not new.any():
            return rattler, keep
        rattler |= new
        keep &= ~(rattler[i] | rattler[j])


def _contacts(X, pl: PairList):
    """Overlapping pairs of the current list: i, j, pair vectors (d, Nc), overlap."""
    R, r = pl.pair_vectors(X)
    ov = 1.0 - r * pl.isig
    m = ov > 0.0
    return pl.i[m], pl.j[m], R[:, m], ov[m], pl.isig[m]


# --------------------------------------------------------------------------- driver

def _check_inputs(n, phi, d, pressure, ftol, skin):
    if not isinstance(d, (int, np.integer)) or d < 2:
        raise InputError(f"packing: d must be an integer >= 2, got {d!r}")
    if not isinstance(n, (int, np.integer)) or n < 2 * (d + 1):
        raise InputError(f"packing: N = {n!r} particles is too small: use N >= {2 * (d + 1)}")
    if phi is not None and not (0.0 < phi < 1.0):
        raise InputError(f"packing: phi must be in (0, 1), got {phi!r}")
    if pressure is not None and not (pressure > 0.0 and math.isfinite(pressure)):
        raise InputError(f"packing: target pressure must be finite and > 0, got {pressure!r}")
    if not (ftol > 0.0):
        raise InputError(f"packing: ftol must be > 0, got {ftol!r}")
    if not (0.0 < skin <= 1.0):
        raise InputError(f"packing: skin must be in (0, 1] (units of the small diameter), got {skin!r}")


def make_packing(n: int, phi: float | None = None, *, d: int = 2, seed: int = 0,
                 pressure: float | None = None, ftol: float = DEFAULT_FTOL,
                 skin: float = 0.4, max_iter: int = 2_000_000,
                 pressure_rtol: float = 0.02, fire: FireParams | None = None,
                 trace: list | None = None, kernel: str = "auto",
                 threads: int | None = None) -> Packing:
    """Jammed packing of ``n`` soft discs (d = 2) or spheres at packing fraction ``phi``.

    Protocol: uniform random positions (numpy Generator seeded with ``seed``; the same
    seed gives a bit-identical packing on the same machine) at ``phi``, then FIRE to
    max|F| < ftol * <f_c>, then iterative rattler removal.

    If ``pressure`` is given, phi is adjusted (affine rescaling + re-minimisation, secant
    steps on p(phi), which is linear near jamming for harmonic discs) until the virial
    pressure is within ``pressure_rtol`` of the target; ``phi`` is then only the first
    guess (default: phi_J + 2 p, from p ~ 0.5 (phi - phi_J) measured in 2D).

    ``kernel``: "numpy" (always available), "numba" (compiled cell list and FIRE passes,
    needs python3-numba) or "auto" (numba if installed).  ``threads``: numba threads
    (default DEFAULT_THREADS = 1; at most NUMBA_NUM_THREADS).  Both kernels, with any
    thread count, do the same floating-point operations in the same order, so they give
    bit-identical forces and hence the same packing for a given seed (tested);
    info["kernel"] and info["threads"] record what ran.

    Raises InputError if the minimised state has no contacts (phi below jamming).
    """
    _check_inputs(n, phi, d, pressure, ftol, skin)
    phi_j = mixture.phi_j(d)
    if phi is None:
        if pressure is None:
            raise InputError("packing: give phi (packing fraction) or pressure")
        phi = min(phi_j + 2.0 * pressure, 0.95)
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    # n // 2 small (not binary_radii's default round(n / 2)): see binary_radii
    radii = binary_radii(n, n_small=n // 2)
    L = box_side(radii, phi, d)
    box = np.full(d, L)
    s = rng.random((n, d))
    order = morton_order(s)
    # random 50:50 labelling, then spatial (Morton) order: the labels stay random in space
    radii = radii[rng.permutation(n)]
    s = s[order]
    radii = radii[order]
    if box.min() <= 2.0 * (2.0 * radii.max() + 2.0 * skin):
        raise InputError(
            f"packing: N = {n} gives a box of side {L:.3g}, not larger than twice the "
            f"interaction range plus skin {2.0 * radii.max() + 2.0 * skin:.3g}: use a larger N")
    pl = pair_list(radii, box, skin, kernel, threads)
    X = np.ascontiguousarray((s * box).T)
    X, info = fire_minimize(X, pl, ftol, params=fire, max_iter=max_iter, trace=trace)
    iterations = info["iterations"]
    stages = [dict(phi=phi, iterations=info["iterations"])]
    if not info["converged"]:
        raise RuntimeError(f"packing: FIRE did not converge in {max_iter} iterations "
                           f"(max|F| = {info['max_force']:.3g}, <f_c> = {info['force_scale']:.3g})")
    if pressure is not None:
        X, pl, box, phi, info, more = _to_pressure(X, pl, radii, box, phi, pressure,
                                                   pressure_rtol, ftol, fire, max_iter, d)
        iterations += sum(st["iterations"] for st in more)
        stages += more
    return _finish(X, pl, radii, box, phi, seed, ftol, iterations, info,
                   dict(stages=stages, n_builds=pl.n_builds, build_time=pl.build_time,
                        wall_time=time.perf_counter() - t0, skin=skin, kernel=pl.kernel,
                        threads=pl.threads))


def _pressure(X, pl: PairList, d: int) -> float:
    _, _, R, ov, isig = _contacts(X, pl)
    r = np.sqrt(np.einsum("kp,kp->p", R, R))
    return float((ov * isig * r).sum() / (d * np.prod(pl.box)))


def _to_pressure(X, pl, radii, box, phi, target, rtol, ftol, fire, max_iter, d):
    """Secant iteration on phi for p(phi) = target, re-minimising after each rescale."""
    stages = []
    phi_j = mixture.phi_j(d)
    p = _pressure(X, pl, d)
    hist = [(phi, p)]
    info = None
    for _ in range(40):
        if p > 0 and abs(p / target - 1.0) < rtol:
            break
        pts = [h for h in hist if h[1] > 0]
        if len(pts) >= 2:
            (f1, p1), (f2, p2) = pts[-2], pts[-1]
            slope = (p2 - p1) / (f2 - f1) if f2 != f1 else 0.5
            if not slope > 0:
                slope = 0.5
            new = f2 + (target - p2) / slope
        elif pts:
            f2, p2 = pts[-1]
            new = f2 + (target - p2) / 0.5
        else:                       # unjammed: compress
            new = phi + max(0.005, 0.5 * (phi_j - phi) + 2 * target)
        new = float(np.clip(new, phi - 0.05, phi + 0.05))
        new = min(new, 0.99)
        scale = (phi / new) ** (1.0 / d)
        box = box * scale
        X = X * scale
        radii_pl = pair_list(radii, box, pl.skin, pl.kernel, pl.threads)
        radii_pl.n_builds, radii_pl.build_time = pl.n_builds, pl.build_time
        pl = radii_pl
        phi = new
        X, info = fire_minimize(X, pl, ftol, params=fire, max_iter=max_iter)
        if not info["converged"]:
            raise RuntimeError("packing: FIRE did not converge while adjusting the pressure")
        p = _pressure(X, pl, d)
        hist.append((phi, p))
        stages.append(dict(phi=phi, pressure=p, iterations=info["iterations"]))
    else:
        raise RuntimeError(f"packing: pressure {target:g} not reached in 40 rescalings "
                           f"(last phi = {phi:.6f}, p = {p:.4g})")
    if info is None:
        _, info = X, dict(iterations=0, max_force=np.nan, force_scale=np.nan, converged=True)
        F = np.empty_like(X)
        ov = pl.forces(X, F)
        info["max_force"] = float(np.sqrt(np.einsum("kn,kn->n", F, F).max()))
        info["force_scale"] = _force_scale(ov, pl.isig)
    return X, pl, box, phi, info, stages


def _finish(X, pl, radii, box, phi, seed, ftol, iterations, info, extra) -> Packing:
    d, n = X.shape
    L = box[:, None]
    s = wrap01(X / L)                             # (d, N) reduced
    i, j, R, ov, isig = _contacts(X, pl)
    if i.shape[0] == 0:
        raise InputError(
            f"packing at phi={phi:.4f} has no contacts after minimisation; phi_J ≈ "
            f"{mixture.phi_j(d)} for this mixture: use phi > {mixture.phi_j(d) + 0.01:.3f} "
            f"(z0 ≈ 4.4-5 needs phi ≈ 0.86-0.90 in 2D)")
    r = np.sqrt(np.einsum("kp,kp->p", R, R))
    fc = ov * isig
    pressure = float((fc * r).sum() / (d * np.prod(box)))
    energy = 0.5 * float(np.dot(ov, ov))
    rattler, keep = remove_rattlers(n, i, j, d)
    if rattler.all():
        raise InputError(
            f"packing at phi={phi:.4f} has no rigid (non-rattler) contact network after "
            f"minimisation; phi_J ≈ {mixture.phi_j(d)} for this mixture: use phi > "
            f"{mixture.phi_j(d) + 0.01:.3f}")
    ci, cj, Rk = i[keep], j[keep], R[:, keep]
    # integer image shifts for the wrapped reduced coordinates
    shift = np.round(Rk / L - (s[:, cj] - s[:, ci])).astype(np.int64).T
    n_nr = int(n - rattler.sum())
    F = np.empty_like(X)
    pl.forces(X, F)
    weak = int(np.count_nonzero(fc[keep] < 100.0 * info["max_force"]))
    extra = dict(extra)
    extra.update(weak_contacts=weak, n_rattlers=int(rattler.sum()),
                 energy_per_particle=energy / n)
    return Packing(
        positions=np.ascontiguousarray((s * L).T), radii=radii, box=np.asarray(box, float),
        contacts_i=ci, contacts_j=cj, contacts_shift=shift, rattler=rattler,
        pressure=pressure, z=2.0 * ci.shape[0] / n_nr, phi=float(phi), energy=energy,
        max_force=info["max_force"], force_scale=info["force_scale"], iterations=int(iterations),
        seed=int(seed), ftol=float(ftol), info=extra)
