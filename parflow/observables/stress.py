"""Stress, pressure and velocity fluctuations: one function per quantity, its equation in
its docstring (DESIGN §2).  Plain numpy on replicated arrays; tau > 0 is compression.

Bonded systems have two estimates of the shear stress, which agree to ~cond(N) eps:
sigma = |V_na|^2 / Omega and sigma_tb = -<tau|b> / Omega.  For hard contacts with gaps
closing within a step (q = b + gap/dgamma in the LCP), complementarity gives
|V_na|^2 = -<f|b> - <f|gap>/dgamma, i.e. sigma = sigma_fb + gap_work.
"""
from __future__ import annotations

import numpy as np


def sq_norm(V: np.ndarray) -> float:
    """|V|^2 = sum_i V_i . V_i over an (N, d) array."""
    return float(np.einsum("id,id->", V, V))


def sigma(V_na: np.ndarray, omega: float) -> float:
    """sigma = |V_na|^2 / Omega: the dissipation per unit volume and strain rate."""
    return sq_norm(V_na) / omega


def sigma_tb(tau: np.ndarray, b: np.ndarray, omega: float, direction: int = 1) -> float:
    """sigma_tb = -direction <tau|b> / Omega (b: affine rates of the pairs for the forward
    flow; direction = -1 on a reversed leg, where the flow is -b)."""
    return -direction * float(tau @ b) / omega


def gap_work(f: np.ndarray, gap: np.ndarray, dgamma: float, omega: float) -> float:
    """gap_work = -<f|gap> / dgamma / Omega: the share of |V_na|^2/Omega spent closing gaps
    within the step (hard contacts; zero for rods)."""
    return -float(f @ gap) / dgamma / omega


def pressure(tau: np.ndarray, length: np.ndarray, omega: float, d: int) -> float:
    """p = sum_alpha tau_alpha l_alpha / (d Omega)."""
    return float(tau @ length) / (d * omega)


def V2(V_na: np.ndarray) -> float:
    """<V^2> = |V_na|^2 / N (for the chain, = -<tau|b>/N)."""
    return sq_norm(V_na) / V_na.shape[0]
