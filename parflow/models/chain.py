"""Periodic chain of N rigid rods in planar extension (paper §II, Fig. 2).

The chain is a network whose nodes have degree 2: node k sits at r_k, rod k joins node k to
node k+1 (the last rod joins node N-1 to the image of node 0 one box length along x).  It is
driven by planar extension V_f = (x, -y) through the general matrix machinery (S, N, tau);
the printed angle equations are not used.

Initial angles theta_k (k = 0..N-1) have the power spectrum g(q) = eps^2 c_mu sin(pi q)^mu,
q = m/N, with c_mu normalising <theta^2> = eps^2; mu = 0 is a random walk, even mu only.  The
chain is then rotated so that sum sin(theta) = 0 (closure along x).  The chain is straight
(jammed) when Lx = N a0:  gamma_c = ln(N / Lx(0)) ~ eps^2 / 2.
"""
from __future__ import annotations

import numpy as np

from ..geometry import velocity_gradient
from ..observables import stress
from ..state import Bonds, InputError, Instant, State

NAME = "chain"
ENGINE = "bonded"
FLOW = "extension"
FACTOR_REUSE = False
omega_min = None            # the bonded engine's, on its force factor
PARAMS = {
    # name: (type, default, check, description)
    "N": (int, 10000, lambda v: v >= 3, "number of rods (>= 3)"),
    "epsilon": (float, 0.1, lambda v: 0 < v < 1.0, "rms initial angle eps (0 < eps < 1)"),
    "mu": (int, 0, lambda v: v >= 0 and v % 2 == 0, "spectral exponent mu (even, >= 0)"),
}


def initial_angles(N: int, eps: float, mu: int, rng: np.random.Generator) -> np.ndarray:
    q = np.arange(N) / N
    g = np.sin(np.pi * q) ** mu if mu > 0 else np.ones(N)
    xi = rng.standard_normal(N) + 1j * rng.standard_normal(N)
    theta = np.fft.ifft(np.sqrt(g) * xi).real
    theta *= eps / np.sqrt(np.mean(theta ** 2))
    # closure: rotate the whole chain so that sum sin(theta) = 0
    theta -= np.arctan2(np.sin(theta).sum(), np.cos(theta).sum())
    return theta


def build(params: dict, seed: int) -> State:
    N, eps, mu = params["N"], params["epsilon"], params["mu"]
    rng = np.random.default_rng(seed)
    theta = initial_angles(N, eps, mu, rng)
    t = np.column_stack([np.cos(theta), np.sin(theta)])
    r = np.vstack([np.zeros(2), np.cumsum(t, axis=0)[:-1]])
    Lx = float(t[:, 0].sum())
    if Lx >= N * (1 - 1e-12):
        raise InputError("the initial chain is already straight: increase epsilon")
    h0 = np.diag([Lx, Lx])                 # Ly is arbitrary: no rod crosses the y boundary
    s = r @ np.linalg.inv(h0).T
    i = np.arange(N)
    j = (i + 1) % N
    shift = np.zeros((N, 2), dtype=np.int64)
    shift[-1, 0] = 1
    state = State(s, h0, velocity_gradient(FLOW, 2), 0.0, Bonds(i, j, shift, np.ones(N)))
    state.meta.update(model="chain", gamma_c=float(np.log(N / Lx)), Lx0=Lx,
                      eps2_over_2=eps ** 2 / 2, dtheta2_0=float(np.mean(_dtheta(t) ** 2)))
    return state


def _dtheta(n: np.ndarray) -> np.ndarray:
    """Delta theta_k = theta_k - theta_{k-1} (wrapped to (-pi, pi]), from unit vectors."""
    nm = np.roll(n, 1, axis=0)
    return np.arctan2(nm[:, 0] * n[:, 1] - nm[:, 1] * n[:, 0], np.einsum("ad,ad->a", nm, n))


def observables(state: State, F) -> dict:
    """<V^2> = |V_na|^2 / N, <Delta theta^2>, <thetadot^2> (thetadot of the total velocity)."""
    V2 = stress.V2(F.V_na)
    bd = state.bonds
    dV = F.r @ state.E.T + F.V_na[bd.j] - F.V_na[bd.i]         # relative velocity of rod ends
    thetadot = (F.n[:, 0] * dV[:, 1] - F.n[:, 1] * dV[:, 0]) / F.ell
    return dict(V2=V2, dtheta2=float(np.mean(_dtheta(F.n) ** 2)),
                thetadot2=float(np.mean(thetadot ** 2)))


def velocity_correlation(V: np.ndarray) -> np.ndarray:
    """C(n) = <V_k . V_{k+n}> / <V^2> along the chain, n = 0..N/2 (periodic, by FFT)."""
    f = np.fft.rfft(V, axis=0)
    c = np.fft.irfft(np.sum(np.abs(f) ** 2, axis=1), n=V.shape[0])
    return c[: V.shape[0] // 2 + 1] / c[0]


def correlation_length(C: np.ndarray) -> float:
    """l_corr: first n where C(n) drops below 1/e (linear interpolation)."""
    below = np.nonzero(C < np.exp(-1))[0]
    if below.size == 0:
        return float("nan")
    k = below[0]
    return float(k - 1 + (C[k - 1] - np.exp(-1)) / (C[k - 1] - C[k]))


def response_length(profile: np.ndarray, floor: float = 1e-10) -> float:
    """l_r from an exponential fit of |tau_n| / |tau_0| against n, over the range where the
    profile is above ``floor`` and has decayed by at most 1e-6."""
    p = np.abs(profile) / abs(profile[0])
    n = np.arange(p.size)
    ok = (p > max(floor, 1e-6)) & (n > 0)
    if ok.sum() < 3:
        return float("nan")
    slope = np.polyfit(n[ok], np.log(p[ok]), 1)[0]
    return float(-1.0 / slope) if slope < 0 else float("nan")


def analyses(at: Instant, rods: int = 8) -> dict:
    """C(n), the point response of one elongated rod (averaged over ``rods`` rods), and the
    lengths fitted from them.  Uses the factor of N loaded at this configuration."""
    system, state, F = at.system, at.state, at.F
    N = state.n
    C = velocity_correlation(F.V_na)
    half = N // 2 + 1
    prof = np.zeros(half)
    betas = np.linspace(0, N, rods, endpoint=False).astype(int)
    for beta in betas:                     # a handful of solves with the loaded factor
        e = np.zeros(N)
        e[beta] = 1.0
        tau = system.solve_N(e, what="point response")
        t = np.roll(tau, -beta)
        prof += 0.5 * (np.abs(t[:half]) + np.abs(np.roll(t[::-1], 1)[:half]))
    prof /= len(betas)
    return dict(arrays=dict(C_n=C, tau_response=prof),
                scalars=dict(l_corr=correlation_length(C), l_r=response_length(prof)))
