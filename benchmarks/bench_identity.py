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

--protocol: instead, the network runs the forward-and-back protocol of
bench_network_shear.py (forward to sigma = 1e6, back to 10; default presets, one process)
twice, with the correction off (IDENTITY_RTOL lifted) and on, alternately in the same
conditions: wall time, steps, factorisations, corrections, the largest sigma identity, and
how far the two runs' sigma(gamma) and gamma at sigma = 1e6 differ.
    python benchmarks/bench_identity.py --n 40000 --protocol
    -> docs/benchmarks/identity.json, "protocol" records
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
from common import FORWARD_AND_BACK, network_file  # noqa: E402  (benchmarks/common.py)


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


def store(kind: str, record: dict) -> None:
    """Put ``record`` (with its date and the load) into docs/benchmarks/identity.json under
    ``kind`` ("records": the states, "protocol": the whole runs), replacing one of the same N."""
    p = results.path("identity")
    old = {}
    if os.path.exists(p):
        with open(p) as fh:
            old = json.load(fh)
    record.update(date=time.strftime("%Y-%m-%d %H:%M:%S"), load_end=os.getloadavg())
    recs = [r for r in old.get(kind, []) if r["n"] != record["n"]] + [record]
    old[kind] = sorted(recs, key=lambda r: r["n"])
    old["benchmark"] = ("the direct force solve near jamming: the factor alone against the "
                        "correction in extended precision")
    results.write("identity", old)


def protocol_run(folder, n, network, corrected):
    """One forward-and-back run; the correction off unless ``corrected``."""
    import h5py  # noqa: PLC0415

    from parflow.run import Run, setup_logging  # noqa: PLC0415
    path = os.path.join(folder, f"identity_protocol_{'on' if corrected else 'off'}.h5")
    scene = load_scene(FORWARD_AND_BACK.format(n=n, network=network, path=path, settings=""))
    setup_logging(PETSc.COMM_WORLD, quiet=True)
    saved = bonded.IDENTITY_RTOL
    if not corrected:
        bonded.IDENTITY_RTOL = np.inf
    try:
        t = time.perf_counter()
        status = Run(scene, PETSc.COMM_WORLD, path, quiet=True).execute()
        wall = time.perf_counter() - t
    finally:
        bonded.IDENTITY_RTOL = saved
    with h5py.File(path) as f:
        ts = f["timeseries"]
        d = {k: ts[k][:] for k in ("gamma", "sigma", "direction", "sigma_mismatch", "rejected")}
        attrs = {k: int(f.attrs.get(k, 0)) for k in ("n_factorisations", "n_identity_refined")}
        status = str(f.attrs["status"])
    fw = d["direction"] > 0
    return dict(corrected=corrected, status=status, wall_seconds=wall, steps=int(len(d["gamma"]) - 1),
                forward_steps=int(fw.sum()), rejected=int(d["rejected"].sum()),
                max_identity=float(np.nanmax(d["sigma_mismatch"])),
                gamma_1e6=results.crossing(d["gamma"][fw], d["sigma"][fw], 1e6), **attrs), d


def protocol(args):
    folder = args.folder
    network = network_file(folder, args.n, PETSc.COMM_WORLD)
    rows, series = [], {}
    for corrected in (False, True, False, True)[:2 * args.repeat]:
        row, d = protocol_run(folder, args.n, network, corrected)
        rows.append(row)
        series[corrected] = d
        print(f"correction {'on ' if corrected else 'off'}: {row['status']}, {row['wall_seconds']:.1f} s, "
              f"{row['steps']} steps ({row['rejected']} rejected), {row['n_factorisations']} "
              f"factorisations, {row['n_identity_refined']} corrections, identity <= "
              f"{row['max_identity']:.1e}, gamma(1e6) = {row['gamma_1e6']:.9f}", flush=True)
    off, on = series[False], series[True]
    fo, fn = off["direction"] > 0, on["direction"] > 0
    g = on["gamma"][fn]
    g = g[(g >= off["gamma"][fo][0]) & (g <= off["gamma"][fo][-1])]
    err = np.max(np.abs(np.interp(g, off["gamma"][fo], np.log(off["sigma"][fo]))
                        - np.interp(g, on["gamma"][fn], np.log(on["sigma"][fn]))))
    store("protocol", dict(n=args.n, rows=rows, forward_log_sigma_difference=float(err)))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=4096)
    ap.add_argument("--top", type=float, default=1e8)
    ap.add_argument("--folder", default=os.path.join("out", "bench_deflated"))
    ap.add_argument("--protocol", action="store_true",
                    help="the forward-and-back run with the correction off and on")
    ap.add_argument("--repeat", type=int, default=1, help="--protocol: pairs of runs")
    args = ap.parse_args()
    if PETSc.COMM_WORLD.getSize() > 1:
        sys.exit("bench_identity.py runs on one rank (the solves it compares are serial)")
    if not extended_precision_available():
        sys.exit("numpy's long double is double on this platform: there is no correction to measure")
    os.makedirs(args.folder, exist_ok=True)
    if args.protocol:
        return protocol(args)
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
    store("records", dict(n=args.n, nc=len(state.bonds), identity_rtol=bonded.IDENTITY_RTOL,
                          long_double_eps=float(np.finfo(np.longdouble).eps), rows=rows))


if __name__ == "__main__":
    main()
