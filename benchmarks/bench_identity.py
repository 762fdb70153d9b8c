"""The direct force solve near jamming, with and without its correction in extended precision.

At the network states of ``bench_deflated.py`` (the configuration where sigma first passes
each decade, 10 ... --top; out/bench_deflated/states_N{n}.npz, made once): the direct CHOLMOD
solve with the factor alone (``bonded.IDENTITY_RTOL`` lifted) and as the code runs it (tau
corrected from a residual in long double while the sigma identity is above IDENTITY_RTOL),
against the deflated CG (k = 4), which does not lose the soft mode to round-off (docs/solvers.md).
Per state: the sigma identity |sigma - sigma_tb| / sigma of each, tau's relative difference
from the deflated solve's, the corrections taken, and the wall time of one force evaluation
(factorisation + solve) with and without them, and of the extended residual alone.

    python benchmarks/bench_identity.py --n 4096            # to sigma = 1e8
    python benchmarks/bench_identity.py --n 40000 --top 1e6
    -> docs/benchmarks/identity.json (one record per N)
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import petsc4py

petsc4py.init(sys.argv[:1])
import numpy as np  # noqa: E402
from petsc4py import PETSc  # noqa: E402

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from parflow.algebra.operators import extended_precision_available  # noqa: E402
from parflow.dynamics import bonded  # noqa: E402
from parflow.dynamics.bonded import BondedSystem  # noqa: E402
from parflow.models import get_model  # noqa: E402
from parflow.scene import load_scene  # noqa: E402

import results  # noqa: E402  (benchmarks/results.py)
from bench_deflated import SCENE, states  # noqa: E402


def rel(a, b):
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


def best_of(fn, repeat=3):
    """Least wall time of fn() over ``repeat`` calls, and its last result."""
    ts = []
    for _ in range(repeat):
        t = time.perf_counter()
        res = fn()
        ts.append(time.perf_counter() - t)
    return float(min(ts)), res


def at_state(state, s, gamma):
    st = state.copy()
    st.s, st.gamma = s, gamma
    direct = BondedSystem(PETSc.COMM_SELF, st, "direct", "auto")
    saved = bonded.IDENTITY_RTOL

    def plain():                                     # factorisation + solve (+ corrections)
        return direct.evaluate(s, gamma)

    try:
        bonded.IDENTITY_RTOL = np.inf                # the factor alone
        t0, F0 = best_of(plain)
    finally:
        bonded.IDENTITY_RTOL = saved
    k0 = direct.n_identity_refined
    t1, F1 = best_of(plain)
    corrections = (direct.n_identity_refined - k0) / 3
    t_res, _ = best_of(lambda: direct.ops.residual_extended(F1.tau, F1.b, F1.n))
    direct.destroy()
    defl = BondedSystem(PETSc.COMM_SELF, st, "deflated", "auto")
    Fd = defl.evaluate(s, gamma)
    defl.destroy()
    return dict(sigma=F1.sigma, mismatch_factor=F0.sigma_mismatch, mismatch_corrected=F1.sigma_mismatch,
                mismatch_deflated=Fd.sigma_mismatch, tau_factor_vs_deflated=rel(F0.tau, Fd.tau),
                tau_corrected_vs_deflated=rel(F1.tau, Fd.tau), tau_corrected_vs_factor=rel(F1.tau, F0.tau),
                corrections=corrections, seconds_factor=t0, seconds_corrected=t1,
                seconds_residual=t_res)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=4096)
    ap.add_argument("--top", type=float, default=1e8)
    ap.add_argument("--folder", default=os.path.join("out", "bench_deflated"))
    args = ap.parse_args()
    if PETSc.COMM_WORLD.getSize() > 1:
        sys.exit("bench_identity.py runs on one rank (the solves it compares are serial)")
    if not extended_precision_available():
        sys.exit("numpy's long double is double on this platform: there is no correction to measure")
    os.makedirs(args.folder, exist_ok=True)
    S = states(args.folder, args.n, args.top)
    network = os.path.join(args.folder, f"network_N{args.n}.h5")
    scene = load_scene(SCENE.format(n=args.n, network=network, top=args.top, folder=args.folder))
    state = get_model("network").build(scene["model"], 1)
    rows = []
    for m in range(len(S["sigma"])):
        row = at_state(state, S["s"][m], float(S["gamma"][m]))
        rows.append(row)
        print(f"sigma {row['sigma']:9.3e}  identity: factor {row['mismatch_factor']:.1e}, corrected "
              f"{row['mismatch_corrected']:.1e} ({row['corrections']:.0f}), deflated "
              f"{row['mismatch_deflated']:.1e} | tau vs deflated: factor "
              f"{row['tau_factor_vs_deflated']:.1e}, corrected {row['tau_corrected_vs_deflated']:.1e}"
              f" | {1e3 * row['seconds_factor']:.1f} -> {1e3 * row['seconds_corrected']:.1f} ms "
              f"(residual {1e3 * row['seconds_residual']:.1f} ms)", flush=True)
    p = results.path("identity")
    old = {}
    if os.path.exists(p):
        with open(p) as fh:
            old = json.load(fh)
    recs = [r for r in old.get("records", []) if r["n"] != args.n]
    recs.append(dict(n=args.n, nc=len(state.bonds), date=time.strftime("%Y-%m-%d %H:%M:%S"),
                     load_end=os.getloadavg(), identity_rtol=bonded.IDENTITY_RTOL,
                     long_double_eps=float(np.finfo(np.longdouble).eps), rows=rows))
    results.write("identity", dict(benchmark="the direct force solve near jamming: the factor "
                                             "alone against the correction in extended precision",
                                   records=sorted(recs, key=lambda r: r["n"])))


if __name__ == "__main__":
    main()
