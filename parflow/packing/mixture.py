"""The binary mixture of parflow's packings and suspensions: the one place of its constants.

Binary mixture of small and large particles, radius ratio RADIUS_RATIO = 1.4, 50:50 by
number unless told otherwise, small-particle *diameter* SMALL_DIAMETER = 1 (the unit of
length).  PHI_J: the jamming packing fraction of the 50:50 mixture by dimension (quench
protocol); the 2D value 0.843 is also the shear-jamming packing fraction the suspension is
bounded by (PHI_J_2D).

Used by the soft-sphere packings (``parflow.packing.fire``), the hard-disc suspension
(``models.suspension``, ``dynamics.hard_discs``) and ``prepare``.  numpy only.
"""
from __future__ import annotations

import math

import numpy as np

from ..errors import InputError

SMALL_DIAMETER = 1.0
RADIUS_RATIO = 1.4
#: Jamming packing fraction of the binary 50:50, ratio-1.4 mixture (quench protocol).
PHI_J = {2: 0.843, 3: 0.648}
#: phi_J in 2D: the (shear-)jamming packing fraction of the hard-disc suspension.
PHI_J_2D = PHI_J[2]


def phi_j(d: int) -> float:
    """phi_J of the mixture in d dimensions (the 3D value above 3D: no measurement there)."""
    return PHI_J.get(d, PHI_J[3])


def binary_radii(n: int, ratio: float = RADIUS_RATIO, composition=(0.5, 0.5),
                 rng: np.random.Generator | None = None, *,
                 n_small: int | None = None) -> np.ndarray:
    """Radii of a binary mixture: small diameter 1, large diameter ``ratio``; ``composition``
    = (fraction small, fraction large).  The first ``n_small`` (default round(n x fraction
    small)) are small, the rest large; randomly labelled if ``rng`` is given (one
    ``rng.permutation(n)``).

    ``n_small`` exists for the packing generator, which has always made n // 2 particles
    small: for odd n with n // 2 odd (n = 3, 7, 11, ...) that is one fewer than round(n / 2)
    (round half to even), and changing it would change those packings."""
    check_mixture(ratio, composition)
    if n_small is None:
        n_small = int(round(n * composition[0]))
    r = np.full(n, 0.5 * SMALL_DIAMETER * ratio)
    r[:n_small] = 0.5 * SMALL_DIAMETER
    if rng is not None:
        r = r[rng.permutation(n)]
    return r


def check_mixture(ratio, composition) -> None:
    """InputError unless ``ratio`` is a finite number > 0 and ``composition`` two fractions
    >= 0 summing to 1."""
    if not (isinstance(ratio, (int, float, np.floating)) and math.isfinite(ratio)) or ratio <= 0:
        raise InputError(f"suspension: radius ratio must be a finite number > 0, got {ratio!r}")
    comp = np.asarray(composition, dtype=float)
    if comp.shape != (2,) or np.any(~np.isfinite(comp)) or np.any(comp < 0):
        raise InputError(f"suspension: composition must be two fractions >= 0 "
                         f"(small, large), got {composition!r}")
    if abs(comp.sum() - 1.0) > 1e-12:
        raise InputError(f"suspension: composition fractions must sum to 1, got "
                         f"{list(comp)} (sum {comp.sum():.6g})")


def check_phi(phi) -> None:
    """InputError unless 0 < phi < phi_J (2D): the packing fractions where hard discs flow."""
    if not (isinstance(phi, (int, float, np.floating)) and math.isfinite(phi)) or phi <= 0:
        raise InputError(f"suspension: packing fraction phi must be a number > 0, got {phi!r}")
    if phi >= PHI_J_2D:
        raise InputError(
            f"suspension: phi = {phi:g} is at or above the jamming packing fraction "
            f"phi_J ~ {PHI_J_2D} of this mixture: hard discs there cannot flow (the stress is "
            f"infinite; any non-overlapping configuration is jammed or nearly so). "
            f"Use phi < {PHI_J_2D} (the paper's range is 0.820-0.840)")


def ball_volume(d: int, r):
    """Volume of a d-ball of radius r (elementwise): pi^(d/2) / Gamma(d/2 + 1) r^d."""
    return math.pi ** (d / 2) / math.gamma(d / 2 + 1) * np.asarray(r, dtype=float) ** d


def box_side(radii: np.ndarray, phi: float, d: int) -> float:
    """Side of the cubic periodic box giving packing fraction phi."""
    return float((ball_volume(d, radii).sum() / phi) ** (1.0 / d))


def packing_fraction(radii: np.ndarray, box) -> float:
    """Packing fraction of balls of ``radii`` in the box of sides ``box`` (d,)."""
    d = np.size(box)
    return float(ball_volume(d, radii).sum() / np.prod(box))
