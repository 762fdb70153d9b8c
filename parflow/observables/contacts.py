"""Contact statistics of hard-particle packings and suspensions: which contacts bear force,
the coordination z with rattlers removed, the force distribution P(f).  numpy only.
"""
from __future__ import annotations

import math

import numpy as np

from ..packing.fire import remove_rattlers


FORCE_BEARING_REL = 1e-12    # a contact bears force when f > FORCE_BEARING_REL * max f


def force_bearing(f: np.ndarray, rel: float = FORCE_BEARING_REL) -> np.ndarray:
    """The contacts that bear force: f > rel * max f (all False for no contact)."""
    return f > rel * (float(f.max()) if f.size else 0.0)


def coordination(c, f: np.ndarray, n_part: int, d: int = 2,
                 rel: float = FORCE_BEARING_REL) -> dict:
    """z of the force-bearing contacts (f > rel max f) with rattlers (< d + 1 force-bearing
    contacts) removed iteratively (DESIGN §5); z_all = 2 N_fb / N without the removal.

    Measured: in flowing states at phi = 0.80-0.82 (z_all ~ 3.3-3.6) the iterative removal
    can cascade through the whole system (N = 1024, phi = 0.82: z = 0, every particle a
    "rattler"; N = 4096: z = 3.31): a particle with 2 contacts is in force balance with
    its drag, so the jammed-packing definition of a rattler is fragile there; z_all is
    reported beside it, and z2: the same iterative removal with fewer than 2 contacts (a
    particle with one contact is not in force balance without drag)."""
    fb = force_bearing(f, rel)
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


def force_distribution(f: np.ndarray, bins: int) -> dict:
    """P(f/<f>) of the force-bearing contacts on log-spaced bins from 1e-4 to 1e2."""
    fb = f[force_bearing(f)]
    out = dict(edges=np.geomspace(1e-4, 1e2, bins + 1), P=np.full(bins, np.nan), mean=math.nan)
    if fb.size:
        x = fb / fb.mean()
        hist, _ = np.histogram(x, out["edges"])
        out.update(P=hist / (x.size * np.diff(out["edges"])), mean=float(fb.mean()))
    return out
