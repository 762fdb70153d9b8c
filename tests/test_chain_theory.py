"""The chain's self-consistent mode theory (post.chain_theory): its parametric solution against
a direct integration of the linearised mode equations, against a parflow chain in the linear
regime (small eps), its asymptotic exponents 3 and 5/3, and its limits."""
import numpy as np
import pytest
from petsc4py import PETSc
from scipy.integrate import solve_ivp

from parflow.dynamics.bonded import BondedSystem
from parflow.dynamics.heun import Heun, Jammed, StepControl
from parflow.models import chain
from parflow.post import chain_theory as ct


def _slope_at(sol, name, x):
    xs, sl = ct.local_slope(sol, name)
    return float(np.interp(np.log(x), np.log(xs[::-1]), sl[::-1]))


def test_mean_spectrum_normalised():
    for mu in (0, 2, 4):
        P = ct.mean_spectrum(500, 0.1, mu)
        assert P[0] == 0.0 and P.sum() == pytest.approx(0.01, rel=1e-12)
        sol = ct.solve(P, A=np.array([0.0]), lengths=False)
        assert sol["gamma_c"] == pytest.approx(0.005, rel=1e-12)       # eps^2 / 2
        assert sol["x"][0] == pytest.approx(0.005, rel=1e-12)          # A = 0: gamma = 0
    # the expected spectrum is the average of the sample spectra of models.chain
    rng = np.random.default_rng(0)
    Ps = np.mean([ct.sample_spectrum(chain.initial_angles(64, 0.1, 2, rng)) for _ in range(4000)], 0)
    np.testing.assert_allclose(Ps[1:], ct.mean_spectrum(64, 0.1, 2)[1:], rtol=0.12, atol=1e-6)


def test_parametric_solution_equals_mode_ode():
    """(1) solved for A against solve_ivp of dtheta_k/dgamma = -(2 + 4 s_k T) theta_k with
    T = (1 - 2 <theta^2>) / <dtheta^2> from the modes themselves."""
    N = 64
    theta = chain.initial_angles(N, 0.1, 0, np.random.default_rng(3))
    P0 = ct.sample_spectrum(theta)
    sol = ct.solve(P0, lengths=False)
    s = np.sin(np.pi * np.arange(N) / N) ** 2

    def rhs(g, y):                             # y = P_k(gamma)
        T = (1 - 2 * y.sum()) / (4 * (s * y).sum())
        return -2 * (2 + 4 * s * T) * y
    gc = sol["gamma_c"]
    xs = gc * np.array([0.5, 0.1, 1e-2, 1e-3])
    r = solve_ivp(rhs, (0, gc - xs[-1]), P0, method="LSODA", t_eval=gc - xs, rtol=1e-10,
                  atol=1e-16)
    for k, x in enumerate(xs):
        y = r.y[:, k]
        assert y.sum() == pytest.approx(2 * x, rel=1e-5)           # <theta^2> = 2 (gamma_c - gamma)
        d2 = 4 * (s * y).sum()
        assert ct.on_grid(sol, [x], "dtheta2")[0] == pytest.approx(d2, rel=2e-3)
        T = (1 - 2 * y.sum()) / d2
        assert ct.on_grid(sol, [x], "V2")[0] == pytest.approx(T ** 2 * d2, rel=2e-3)


def test_against_a_parflow_chain_in_the_linear_regime(comm):
    """A parflow chain (N = 100, eps = 0.02: linear) against the theory for its own initial
    angles: <V^2> and <dtheta^2> at the same gamma_c - gamma, over five decades of <V^2>."""
    st = chain.build(dict(N=100, epsilon=0.02, mu=0), seed=7)
    r = (st.s[st.bonds.j] + st.bonds.shift - st.s[st.bonds.i]) @ st.h.T
    theta = np.arctan2(r[:, 1], r[:, 0])
    sol = ct.solve(ct.sample_spectrum(theta), lengths=False)
    gc = st.meta["gamma_c"]
    sysm = BondedSystem(PETSc.COMM_WORLD, st)
    integ = Heun(sysm, StepControl(tol=0.01))
    s, g, F, dg = st.s, 0.0, sysm.evaluate(st.s, 0.0), 1e-6
    rows = []
    try:
        for _ in range(3000):
            R = integ.step(s, g, F, +1, dg)
            s, g, F, dg = R.s, R.gamma, R.F, R.next_dgamma
            V2 = float(np.sum(F.V_na ** 2) / st.n)
            rows.append((gc - g, V2, float(np.mean(chain._dtheta(F.n) ** 2))))
            if V2 > 1e8:
                break
    except Jammed:
        pass
    sysm.destroy()
    x, V2, d2 = np.array(rows).T
    assert V2[-1] > 1e7
    ok = x < 0.5 * gc                    # past the first transient (nonlinear at O(eps^2))
    np.testing.assert_allclose(V2[ok], ct.on_grid(sol, x[ok], "V2"), rtol=0.03)
    np.testing.assert_allclose(d2[ok], ct.on_grid(sol, x[ok], "dtheta2"), rtol=0.03)


@pytest.mark.parametrize("mu, x, tol", [(0, 1e-4, 0.03), (2, 1e-6, 0.01)])
def test_asymptotic_exponents(mu, x, tol):
    """Local slopes of the N = 10^4 solution (mean spectrum) approach -(3+mu)/(1+mu) for
    <V^2>, +(3+mu)/(1+mu) for <dtheta^2>, -1 for <thetadot^2>, while l_corr << N; and the
    values approach the continuum law of ct.asymptotic."""
    sol = ct.solve(ct.mean_spectrum(10000, 0.1, mu), lengths=False)
    asy = ct.asymptotic(mu, 0.1)
    p = (3 + mu) / (1 + mu)
    assert _slope_at(sol, "V2", x) == pytest.approx(-p, abs=tol * p)
    assert _slope_at(sol, "dtheta2", x) == pytest.approx(p, abs=tol * p)
    assert _slope_at(sol, "thetadot2", x) == pytest.approx(-1.0, abs=0.05)
    assert ct.on_grid(sol, [x], "V2")[0] == pytest.approx(float(asy["V2"](x)), rel=0.03)
    assert asy["exponents"]["V2"] == -p and asy["exponents"]["l_corr"] == -1 / (1 + mu)


def test_correlation_length_exponent_mu0():
    """l_corr ~ x^-1 (mu = 0) in the scaling window (l_corr from 14 to 140 << N / 60: the sum
    over modes is an integral), from the theory's own C(n); beyond it, finite size flattens it."""
    A = np.geomspace(1e2, 1e4, 5)
    sol = ct.solve(ct.mean_spectrum(100000, 0.1, 0), A=A)
    slope = np.polyfit(np.log(sol["x"]), np.log(sol["l_corr"]), 1)[0]
    assert slope == pytest.approx(-1.0, abs=0.01)
    big = ct.solve(ct.mean_spectrum(2000, 0.1, 0), A=A)
    assert np.polyfit(np.log(big["x"]), np.log(big["l_corr"]), 1)[0] > -0.9
    # the same 1/e rule as the model's correlation length
    C = ct.correlation(ct.mean_spectrum(2000, 0.1, 0), 1e3)
    assert ct.correlation_length(C) == pytest.approx(chain.correlation_length(C), rel=1e-12)


def test_finite_size_limit():
    """Once only the longest mode is left, T -> 1 / (8 sin^2(pi/N) x): <V^2> ~ x^-1."""
    N = 50
    sol = ct.solve(ct.mean_spectrum(N, 0.1, 0), lengths=False)
    x = sol["x"][-1]
    assert x < 1e-12
    assert sol["T"][-1] * 8 * np.sin(np.pi / N) ** 2 * x == pytest.approx(1.0, rel=1e-3)
    assert _slope_at(sol, "V2", 1e-9) == pytest.approx(-1.0, abs=1e-3)
    np.testing.assert_allclose(sol["theta2"], 2 * sol["x"], rtol=1e-12)


ENSEMBLE_SCENE = """
title = "chain theory ensemble test"
seed = 3
[model]
name = "chain"
N = 100
epsilon = 0.02
mu = {mu}
[integrator]
method = "rkc"
tol = 0.003
[[protocol.leg]]
direction = "forward"
V2_above = 1e6
[observables]
analysis_quantity = "V2"
analysis_per_decade = 2
[output]
path = "unused.h5"
"""


@pytest.mark.serial_only        # launches its own parflow.shear process
@pytest.mark.parametrize("mu", [0, 2])
def test_ensemble_against_theory(tmp_path, mu):
    """plot.chain_theory.compare on a 3-sample ensemble at eps = 0.02 (linear): the samples'
    mean <V^2> and <dtheta^2> equal the per-seed theory averaged, within 4 %, past the first
    transient; its data exponents are the summary's (the same fit, the same windows)."""
    import subprocess
    import sys

    from parflow.plot.chain_theory import compare
    scene = tmp_path / "e.toml"
    scene.write_text(ENSEMBLE_SCENE.format(mu=mu))
    out = tmp_path / "ens"
    subprocess.run([sys.executable, "-m", "parflow.shear", str(scene), "--samples", "3",
                    "--output", str(out), "--quiet", "--no-plots"], check=True)
    r = compare(str(out))
    assert r["n_samples"] == 3
    x = r["x"]
    for q in ("V2", "dtheta2"):
        m, s, n = r["data"][q]
        tm = r["theory_sample"][q][0]
        ok = (n == 3) & np.isfinite(tm) & (x < 0.5 * 0.02 ** 2 / 2)
        assert ok.sum() > 10
        np.testing.assert_allclose(m[ok], tm[ok], rtol=0.04)
    fits = r["summary"]["fits"]["forward.attr.V2.exponent"]
    e = r["exponents"]["V2"]["data"]
    assert e["mean"] == pytest.approx(float(fits["mean"]), rel=1e-9)


def test_split_transverse_and_longitudinal(comm):
    """chain_split.split: |V_na|^2 = V_x^2 + V_y^2; in the linear regime (eps = 0.02)
    the velocity is transverse and the tension uniform, as the theory has them; at eps = 0.1,
    mu = 2 the longitudinal part and the tension's spread are O(1) in the crossover."""
    from parflow.chain_split import split
    lin = split(100, 0.02, 0, 7, fractions=(0.2, 0.02))
    for row in lin:
        assert row["V2"] == pytest.approx(row["Vx2"] + row["Vy2"], rel=1e-12)
        assert row["Vx2"] < 0.02 * row["V2"]
        assert row["tension_std"] < 0.1 * row["tension"]
        assert row["V2"] == pytest.approx(row["theory_V2"], rel=0.03)
    big = split(300, 0.1, 2, 1, fractions=(0.2,))[0]
    assert big["Vx2"] > 0.3 * big["V2"] and big["tension_std"] > 0.3 * big["tension"]


@pytest.mark.serial_only
@pytest.mark.parametrize("args, says", [
    (["-5", "0.1", "0", "1"], "N = -5"),
    (["100", "-0.1", "0", "1"], "EPS = -0.1"),
    (["100", "0.1", "1", "1"], "MU = 1"),
    (["100", "0.1", "0", "-1"], "SEED = -1"),
    (["100", "0.1", "0", "1", "--tol", "-1"], "--tol"),
    (["100", "0.1", "0", "1", "--fractions", "abc"], "--fractions 'abc'"),
    (["100", "0.1", "0", "1", "--fractions", "0.1,0.5"], "decreasing"),
])
def test_chain_split_refuses_bad_input_with_one_line(args, says, capsys):
    """python -m parflow.chain_split: a bad argument is one line naming it, exit 2 (the chain
    model's own checks for N, EPS, MU), before any chain is built."""
    from parflow.chain_split import main
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and says in err[0], err
