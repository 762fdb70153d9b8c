"""What is left of the first suspension module: the post-run relaxation fit, until it joins
``parflow.post``.  The suspension itself: ``dynamics.hard_discs`` (the step),
``dynamics.lcp`` (contact forces), ``models.suspension`` (scene, initial states, analyses),
``models.frozen`` (the frozen contact network).
"""
from __future__ import annotations

import math

import numpy as np


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
