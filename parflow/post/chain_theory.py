"""The self-consistent mode theory of the rigid chain (paper §II) for a finite chain: numbers
to set against the measured <V^2>, <dtheta^2>, <thetadot^2> and l_corr (post.chain) at the same
N, eps, mu.

Linearised about the straight chain, with a uniform tension T = -tau > 0, the angle equation
(DESIGN §2, the corrected one)

    dtheta_a/dgamma = -sin 2theta_a - tau_{a+1} sin dtheta_{a+1} + tau_{a-1} sin dtheta_a

becomes dtheta/dgamma = -2 theta + T (theta_{a+1} - 2 theta_a + theta_{a-1}); each Fourier mode
k (q = k/N, s_k = sin^2(pi q)) decays on its own,

    theta_k(gamma) = theta_k(0) exp(-2 gamma - 4 s_k A(gamma)),   A(gamma) = int_0^gamma T,

and the tension is fixed by the rod lengths: the box Lx = Lx0 e^gamma equals sum cos theta =
N exp(-<theta^2>/2) (Gaussian angles), so <theta^2>(gamma) = 2 x, x = gamma_c - gamma,
gamma_c = <theta^2>_0 / 2.  With the power of mode k, P_k(gamma) = |theta_k|^2 / N^2
(sum_k P_k = <theta^2>), this is the self-consistent equation

    sum_k P_k(0) exp(-4 gamma - 8 s_k A) = 2 (gamma_c - gamma),                           (1)

or, differentiated, T = dA/dgamma = (1 - 2<theta^2>) / <dtheta^2>, <dtheta^2> = 4 sum s_k P_k:
the tension equation N tau = -b averaged over the chain at the same order.  (1) is solved
parametrically: for each A, x follows from x = G(A) e^{-4 (gamma_c - x)} / 2 (G(A) =
sum P_k(0) e^{-8 s_k A}; a contraction, 4x << 1), and every observable is explicit:

    <theta^2> = 2x,   <dtheta^2> = 4 sum s_k P_k,   T = (1 - 4x) / <dtheta^2>,
    <V^2> = |V_na|^2 / N = T^2 <dtheta^2>       (V_na at node k = T (n_k - n_{k-1}): its y part),
    <thetadot^2> = sum (2 + 4 s_k T)^2 P_k,
    C(n) = sum s_k P_k cos(2 pi k n / N) / sum s_k P_k   (the correlation of those velocities),
    l_corr: where C(n) first drops below 1/e (as models.chain.correlation_length),
    l_r = <dtheta^2>^(-1/2).

P_k(0) is either the ensemble's (g(q) = sin(pi q)^mu normalised to eps^2, the k = 0 mode
removed by the closure; :func:`mean_spectrum`) or one sample's initial angles
(:func:`sample_spectrum`).  For g ~ q^mu at small q and l_corr << N the sums become integrals
and give the asymptotic laws of :func:`asymptotic` (exponents (3+mu)/(1+mu): 3 and 5/3); once
l_corr reaches N the longest mode k = 1 is left alone and T -> 1 / (8 s_1 x) (exponent -1).

numpy and scipy only.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.special import gamma as Gamma

CHUNK = 2 ** 22            # modes x grid points evaluated at once (memory ~ 32 MB a block)


def mean_spectrum(N: int, eps: float, mu: int) -> np.ndarray:
    """Expected initial mode powers P_k = <|theta_k|^2> / N^2 of models.chain.initial_angles:
    proportional to sin(pi k/N)^mu, sum eps^2, with P_0 = 0 (the closure removes the mean)."""
    q = np.arange(N) / N
    g = np.sin(np.pi * q) ** mu if mu > 0 else np.ones(N)
    g[0] = 0.0
    return eps ** 2 * g / g.sum()


def sample_spectrum(theta: np.ndarray) -> np.ndarray:
    """P_k = |fft(theta)_k|^2 / N^2 of one chain's angles (sum = <theta^2>), P_0 set to 0."""
    theta = np.asarray(theta, float)
    P = np.abs(np.fft.fft(theta)) ** 2 / theta.size ** 2
    P[0] = 0.0
    return P


def _modes(N: int) -> np.ndarray:
    return np.sin(np.pi * np.arange(N) / N) ** 2


def _sums(P, s, A, weights):
    """sum_k w(s_k) P_k exp(-8 s_k A) for each A and each weight power in ``weights``
    (s_k^p), chunked over A so that a block holds at most CHUNK numbers."""
    nz = P > 0
    P, s = P[nz], s[nz]
    out = np.empty((len(weights), A.size))
    step = max(1, CHUNK // max(P.size, 1))
    for a in range(0, A.size, step):            # blocks of the grid, not particles
        e = P[None, :] * np.exp(-8.0 * np.outer(A[a:a + step], s))
        for i, p in enumerate(weights):
            out[i, a:a + step] = e @ (s ** p)
    return out


def solve(P0: np.ndarray, A: np.ndarray | None = None, lengths: bool = True) -> dict:
    """Solve (1) for the initial mode powers ``P0`` (length N) on a grid of A = int T dgamma.

    Returns arrays ordered by decreasing x = gamma_c - gamma: ``A``, ``x``, ``gamma``,
    ``theta2``, ``dtheta2``, ``T``, ``V2``, ``thetadot2``, ``l_r`` and (``lengths``) ``l_corr``;
    and ``gamma_c`` = <theta^2>_0 / 2."""
    P0 = np.asarray(P0, float)
    N = P0.size
    s = _modes(N)
    gc = 0.5 * float(P0.sum())
    if A is None:
        smin = s[1]
        # from A ~ 0 to where even the longest mode has decayed by e^-60
        A = np.concatenate([[0.0], np.geomspace(1e-4, 8.0 / smin, 600)])
    A = np.asarray(A, float)
    G, G1, G2 = _sums(P0, s, A, (0, 1, 2))
    x = 0.5 * G * math.exp(-4.0 * gc)
    for _ in range(8):                          # x = G e^{-4 (gc - x)} / 2, contraction 4x
        x = 0.5 * G * np.exp(-4.0 * (gc - x))
    fac = np.exp(-4.0 * (gc - x))               # e^{-4 gamma}
    dtheta2 = 4.0 * fac * G1
    T = (1.0 - 4.0 * x) / dtheta2
    thetadot2 = fac * (4.0 * G + 16.0 * T * G1 + 16.0 * T ** 2 * G2)
    out = dict(A=A, x=x, gamma=gc - x, theta2=2.0 * x, dtheta2=dtheta2, T=T,
               V2=T ** 2 * dtheta2, thetadot2=thetadot2, l_r=dtheta2 ** -0.5, gamma_c=gc, N=N)
    if lengths:
        out["l_corr"] = np.array([correlation_length(correlation(P0, a, s)) for a in A])
    return out


def correlation(P0: np.ndarray, A: float, s: np.ndarray | None = None) -> np.ndarray:
    """C(n), n = 0..N/2, of the node velocities T (n_k - n_{k-1}) at A (by FFT)."""
    s = _modes(P0.size) if s is None else s
    w = s * P0 * np.exp(-8.0 * s * A)
    c = np.fft.ifft(w).real
    return c[: P0.size // 2 + 1] / c[0]


def correlation_length(C: np.ndarray) -> float:
    """First n where C(n) drops below 1/e, linearly interpolated (the rule of
    models.chain.correlation_length, applied to the theory's C(n))."""
    below = np.nonzero(C < math.exp(-1))[0]
    if below.size == 0:
        return float("nan")
    k = below[0]
    return float(k - 1 + (C[k - 1] - math.exp(-1)) / (C[k - 1] - C[k]))


def on_grid(sol: dict, x: np.ndarray, name: str) -> np.ndarray:
    """``sol[name]`` at the strains-to-jamming ``x`` (log-log interpolation; NaN outside)."""
    xs, ys = sol["x"][::-1], sol[name][::-1]
    ok = (xs > 0) & np.isfinite(ys) & (ys > 0)
    xs, ys = xs[ok], ys[ok]
    x = np.asarray(x, float)
    y = np.exp(np.interp(np.log(x), np.log(xs), np.log(ys), left=np.nan, right=np.nan))
    return np.where((x >= xs[0]) & (x <= xs[-1]), y, np.nan)


def local_slope(sol: dict, name: str) -> tuple[np.ndarray, np.ndarray]:
    """d ln(name) / d ln x along the solution (central differences), at the grid's x."""
    x, y = sol["x"], sol[name]
    ok = (x > 0) & (y > 0) & np.isfinite(y)
    lx, ly = np.log(x[ok]), np.log(y[ok])
    return x[ok], np.gradient(ly, lx)


def asymptotic(mu: int, eps: float, gamma_c: float | None = None) -> dict:
    """The continuum (N -> infinity) solution of (1) for g ~ sin(pi q)^mu as x -> 0:
    <theta^2> = a A^{-(1+mu)/2} with a = eps^2 c_mu Gamma((1+mu)/2) / (pi 8^{(1+mu)/2}) e^{-4 gamma_c},
    c_mu = 1 / mean(sin^mu) = sqrt(pi) Gamma(1+mu/2) / Gamma((1+mu)/2).  So A = (a / 2x)^{1/nu},
    nu = (1+mu)/2, <dtheta^2> = -(1/2) d<theta^2>/dA = nu x / A and T = 1/<dtheta^2> = -dA/dx.

    Returns the exponents against x ((3+mu)/(1+mu) for <dtheta^2>, its negative for <V^2>,
    -1/(1+mu) for l_corr) and functions of x: A, <dtheta^2>, T, V2 (= T to O(x)), l_r."""
    gc = eps ** 2 / 2 if gamma_c is None else gamma_c
    nu = (1.0 + mu) / 2.0
    c_mu = math.sqrt(math.pi) * Gamma(1 + mu / 2) / Gamma(nu)
    a = eps ** 2 * c_mu * Gamma(nu) / (math.pi * 8.0 ** nu) * math.exp(-4.0 * gc)

    def A(x):
        return (a / (2.0 * np.asarray(x, float))) ** (1.0 / nu)

    def dtheta2(x):
        # 4 sum s P e^{-8sA} = -(1/2) d/dA sum P e^{-8sA} = (1/2) nu <theta^2> / A
        x = np.asarray(x, float)
        return 0.5 * nu * 2.0 * x / A(x)

    def T(x):
        return 1.0 / dtheta2(x)

    p = (3.0 + mu) / (1.0 + mu)
    return dict(exponents=dict(V2=-p, dtheta2=p, thetadot2=-1.0, l_corr=-1.0 / (1.0 + mu),
                               l_r=-p / 2),
                A=A, dtheta2=dtheta2, T=T, V2=T, l_r=lambda x: dtheta2(x) ** -0.5)
