"""One chain's <V^2> split along and across the chain, against the self-consistent theory
(docs/chain.md, "Seed averages and the self-consistent theory").

    python -m parflow.chain_split N EPS MU SEED [--tol 0.003] [--fractions 0.5,0.2,...]

A command (it runs a chain: models, dynamics), not a figure: plot/ and post/ read run files
only (tests/test_plot.py).
"""
from __future__ import annotations

import argparse
import sys

import numpy as np

from .cli import init_petsc, run_main
from .post import chain_theory as ct


def split(N: int, eps: float, mu: int, seed: int, tol: float = 0.003,
          fractions=(0.5, 0.2, 0.1, 0.04, 0.02, 0.01, 0.004, 0.002, 0.001, 4e-4)) -> list:
    """One chain (models.chain, ``seed``) driven forward with RKC2 (``tol``), stopped at
    x = gamma_c - gamma = fraction * gamma_c: where its <V^2> = |V_na|^2 / N sits, split into
    the longitudinal <V_x^2> and transverse <V_y^2> parts, against the theory for its own
    initial angles (which has only the transverse part, T (sin theta_k - sin theta_{k-1}));
    the rods' tension, mean and spread (the theory's is uniform); 1 / <dtheta^2>."""
    # (here, not at the top: these load PETSc, which main() initialises first)
    from .algebra.comm import world
    from .dynamics.bonded import BondedSystem
    from .dynamics.heun import Jammed, StepControl
    from .dynamics.rkc import RKC
    from .models import chain
    st = chain.build(dict(N=N, epsilon=eps, mu=mu), seed=seed)
    r = (st.s[st.bonds.j] + st.bonds.shift - st.s[st.bonds.i]) @ st.h.T
    sol = ct.solve(ct.sample_spectrum(np.arctan2(r[:, 1], r[:, 0])), lengths=False)
    gc = st.meta["gamma_c"]
    marks = [f * gc for f in fractions]
    sysm = BondedSystem(world(), st)
    integ = RKC(sysm, StepControl(tol=tol, method="rkc"))
    s, g, F, dg = st.s, 0.0, sysm.evaluate(st.s, 0.0), 1e-5
    rows = []
    try:
        while marks:
            R = integ.step(s, g, F, +1, dg, dg_cap=max(gc - g - marks[0], 1e-16))
            s, g, F, dg = R.s, R.gamma, R.F, R.next_dgamma
            x = gc - g
            if x <= marks[0] * (1 + 1e-9):
                marks.pop(0)
                V = F.V_na
                rows.append(dict(x=x, V2=float(np.mean(np.sum(V ** 2, axis=1))),
                                 Vx2=float(np.mean(V[:, 0] ** 2)), Vy2=float(np.mean(V[:, 1] ** 2)),
                                 theory_V2=float(ct.on_grid(sol, [x], "V2")[0]),
                                 tension=float(-F.tau.mean()), tension_std=float(F.tau.std()),
                                 inv_dtheta2=float(1.0 / np.mean(chain._dtheta(F.n) ** 2))))
            dg = min(dg, 0.5 * x)
    except Jammed:
        pass
    finally:
        sysm.destroy()
    return rows


def check_args(N: int, eps: float, mu: int, seed: int, tol: float, fractions: str) -> tuple:
    """The fractions as floats, or InputError naming the bad argument: N, EPS and MU by the
    chain model's own checks (``models.chain.PARAMS``, as a scene's [model] table), SEED >= 0,
    0 < tol < 1, fractions in (0, 1) and decreasing."""
    # (here, not at the top: the models package loads PETSc, which main() initialises first)
    from .models.chain import PARAMS
    from .state import InputError
    for name, arg, value in (("N", "N", N), ("epsilon", "EPS", eps), ("mu", "MU", mu)):
        if not PARAMS[name][2](value):
            raise InputError(f"{arg} = {value!r}: {PARAMS[name][3]}")
    if seed < 0:
        raise InputError(f"SEED = {seed}: a seed is an integer >= 0")
    if not 0 < tol < 1:
        raise InputError(f"--tol {tol}: the RKC2 tolerance must lie in (0, 1), e.g. 0.003")
    try:
        fr = tuple(float(v) for v in fractions.split(","))
    except ValueError:
        raise InputError(f"--fractions {fractions!r}: give numbers separated by commas, "
                         "e.g. 0.5,0.1,0.01") from None
    if not all(0 < f < 1 for f in fr) or any(b >= a for a, b in zip(fr, fr[1:])):
        raise InputError(f"--fractions {fractions!r}: each x / gamma_c must lie in (0, 1), "
                         "in decreasing order")
    return fr


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m parflow.chain_split", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("N", type=int)
    p.add_argument("eps", type=float)
    p.add_argument("mu", type=int)
    p.add_argument("seed", type=int)
    p.add_argument("--tol", type=float, default=0.003, help="RKC2 tolerance")
    p.add_argument("--fractions", default="0.5,0.2,0.1,0.04,0.02,0.01,0.004,0.002,0.001,4e-4",
                   help="where to stop, x / gamma_c, comma separated, decreasing")
    a = p.parse_args(argv)
    init_petsc([])

    def body():
        fr = check_args(a.N, a.eps, a.mu, a.seed, a.tol, a.fractions)
        print(f"N = {a.N}, eps = {a.eps}, mu = {a.mu}, seed = {a.seed}, RKC2 tol = {a.tol}")
        for row in split(a.N, a.eps, a.mu, a.seed, tol=a.tol, fractions=fr):
            print("  " + "  ".join(f"{k}={v:.3e}" for k, v in row.items()), flush=True)

    return run_main("parflow.chain_split", body)


if __name__ == "__main__":
    sys.exit(main())
