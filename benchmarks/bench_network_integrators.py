"""Integrators and intermediate solves on a network sheared forward to sigma = 1e6 and back
(the bench_network_shear.py protocol; issue "Numerics built for the near-singular regime").

The network (packing at phi = 0.88, WLKM dilution to z = 3.8, seed 1) is built once and saved;
each case loads it, runs forward until sigma >= 1e6, then reversed until sigma <= 10, with no
analyses and no omega_min.  Cases: Heun and RKC2 at their default tolerance, each with a
factorisation per force solve and with the intermediate solves by PCG on the step's factor
(integrator.stage_rtol = 1e-8); two tight references (Heun tol = max_displacement = 0.005;
RKC2 tol = 5e-4, max_displacement = 0.005, stage_rtol = 1e-10).  Per case: loop wall and CPU
seconds, accepted and rejected steps, factorisations, intermediate PCG solves and iterations,
gamma where sigma first crosses 1e6 and C of the reversed branch, C = dx / d(1/sigma) between
sigma = 1e5 and 1e3 (x: strain since the reversal; the secant does not depend on where the
steps fell), each against both references.

    python benchmarks/bench_network_integrators.py [--n 4096] [--cases heun,rkc,...]
    -> docs/benchmarks/network_integrators.json (one record per N and rank count)
"""
from __future__ import annotations

import argparse
import os
import resource
import sys
import time

import petsc4py

petsc4py.init(sys.argv[:1])
import h5py  # noqa: E402
import numpy as np  # noqa: E402
from petsc4py import PETSc  # noqa: E402

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from parflow.algebra.solvers import set_blas_threads  # noqa: E402
from parflow.run import Run, setup_logging  # noqa: E402
from parflow.scene import load_scene  # noqa: E402

import results  # noqa: E402  (benchmarks/results.py)
from common import (FORWARD_AND_BACK, FORWARD_RESOLVED_AND_BACK,  # noqa: E402  (benchmarks/common.py)
                    FORWARD_SPLIT_AND_BACK, network_file)

CASES = {
    "heun": 'method = "heun"',
    "heun_stages": 'method = "heun"\nstage_rtol = 1e-8',
    "rkc": 'method = "rkc"\ntol = 0.05',
    "rkc_stages": 'method = "rkc"\ntol = 0.05\nstage_rtol = 1e-8',
    "rkc_2stages": 'method = "rkc"\ntol = 0.05\nmax_stages = 2',
    # the linearly implicit ROS2 (dynamics.ros2): its stage equations by GMRES on the step's
    # factor, its stage force by PCG on it
    "ros2": 'method = "ros2"\ntol = 0.05',
    "ros2_fast": 'method = "ros2"\ntol = 0.2',
    "ros2_loose": 'method = "ros2"\ntol = 0.2\nkrylov_rtol = 1e-2',
    "heun_fast": 'method = "heun"\ntol = 0.2\nmax_displacement = 0.2',
    "ref_heun": 'method = "heun"\ntol = 0.005\nmax_displacement = 0.005',
    "ref_rkc": 'method = "rkc"\ntol = 5e-4\nmax_displacement = 0.005\nstage_rtol = 1e-10',
    # tighter still, to see which reference has converged (not in the default --cases)
    "ref_heun_tighter": 'method = "heun"\ntol = 0.001\nmax_displacement = 0.001',
    "ref_rkc_tighter": 'method = "rkc"\ntol = 5e-5\nmax_displacement = 0.001\nstage_rtol = 1e-11',
}
# RKC2 for the forward leg up to sigma = SPLIT, Heun (the legs' own integrator keys) from there
# through the turn and back: RKC2's error in the stiff modes, which the reversed flow amplifies,
# is relaxed by Heun's steps before the turn (docs/benchmarks.md "Integrators on a network")
SPLIT_CASES = {
    "rkc_heun_1e5": ('method = "rkc"\ntol = 0.05', 1e5, 'method = "heun"'),
    "rkc_heun_1e4": ('method = "rkc"\ntol = 0.05', 1e4, 'method = "heun"'),
    "rkc_heun_3e4": ('method = "rkc"\ntol = 0.05', 3e4, 'method = "heun"'),
    "rkc_heun_3e5": ('method = "rkc"\ntol = 0.05', 3e5, 'method = "heun"'),
    "rkc_heun_1e3": ('method = "rkc"\ntol = 0.05', 1e3, 'method = "heun"'),
    "rkc_heun_1e5_stages": ('method = "rkc"\ntol = 0.05\nstage_rtol = 1e-8', 1e5, 'method = "heun"'),
    # ROS2 toward jamming, Heun on the reversed leg (where the stiff modes grow: an L-stable
    # step would damp them)
    "ros2_heun": ('method = "ros2"\ntol = 0.05', 1e6, 'method = "heun"'),
    "ros2_fast_heun": ('method = "ros2"\ntol = 0.2', 1e6, 'method = "heun"'),
    "ros2_fast_heun_stages": ('method = "ros2"\ntol = 0.2', 1e6, 'method = "heun", stage_rtol = 1e-8'),
    "ros2_fastd_heun": ('method = "ros2"\ntol = 0.2\nmax_displacement = 0.2', 1e6,
                        'method = "heun", tol = 0.2, max_displacement = 0.2'),
}
# the same with the second stage from the first one's Krylov space (integrator.krylov_recycle)
for _name in ("ros2_heun", "ros2_fast_heun", "ros2_fastd_heun"):
    _scene, _split, _near = SPLIT_CASES[_name]
    SPLIT_CASES[f"{_name}_recycle"] = (_scene + "\nkrylov_recycle = true", _split, _near)
# the same with ROS2's other L-stable g = 1 - 1/sqrt(2) (integrator.ros2_gamma): the pole of
# R(z) at z = 3.41 instead of 0.59, so a growing mode bounds the step ~4x later
LOW_G = "\nros2_gamma = 0.2928932188134524"
for _name in ("ros2_heun", "ros2_fast_heun", "ros2_fastd_heun"):
    _scene, _split, _near = SPLIT_CASES[_name]
    SPLIT_CASES[f"{_name}_lowg"] = (_scene + LOW_G, _split, _near)
# ... at the tolerances that give the error of Verwer's g at 0.05 and 0.2 (the error estimate
# of g = 1 - 1/sqrt(2), against its own linearly implicit Euler step, is 5.8x smaller for a
# slow flow: (2g - 1) h^2 J F / 2)
SPLIT_CASES["ros2_heun_lowg_tol01"] = ('method = "ros2"\ntol = 0.01' + LOW_G, 1e6, 'method = "heun"')
SPLIT_CASES["ros2_fastm_heun_lowg"] = ('method = "ros2"\ntol = 0.2\nmax_displacement = 0.1' + LOW_G, 1e6,
                                       'method = "heun"')
SPLIT_CASES["ros2_fastd_heun_lowg_tol035"] = ('method = "ros2"\ntol = 0.035\nmax_displacement = 0.2' + LOW_G,
                                              1e6, 'method = "heun", tol = 0.2, max_displacement = 0.2')
for _name, (_scene, _split, _near) in SPLIT_CASES.items():
    CASES[_name] = f"{_scene}; to sigma = {_split:g}, then {_near}".replace("\n", "; ")
# the reversed leg seeded: perturb = ETA a0 at the turn with perturb_seed k (the leg's keys),
# Heun and RKC2 at their defaults, ROS2 (tol 0.2) forward with Heun reversed -- does the seed
# or the integrator select the branch?
PERTURB_ETA, PERTURB_SEEDS = 3e-4, (1, 2, 3, 4)
PERTURB_CASES = {f"{m}_seeded_{k}": (m, k) for m in ("heun", "rkc", "ros2_fast_heun")
                 for k in PERTURB_SEEDS}
for _name, (_m, _k) in PERTURB_CASES.items():
    CASES[_name] = CASES[_m] + f"; reversed leg: perturb = {PERTURB_ETA:g}, perturb_seed = {_k}"
# the turn resolved: steps <= h from sigma = split to the turn and for the reversed leg's first
# rstrain (the legs' max_dgamma), the scene's integrator elsewhere (or, for the reversed legs,
# the integrator keys given): does the turn's resolution decide the reversed branch, as it does
# for the chain (docs/chain.md "What seeds it")?
RESOLVED_CASES = {
    "heun_turn": ('method = "heun"', 5e5, 1e-8, 1e-6, ""),
    "heun_turn_5e-9": ('method = "heun"', 5e5, 5e-9, 1e-6, ""),
    "ros2_turn": ('method = "ros2"\ntol = 0.05', 5e5, 1e-8, 1e-6, ""),
    "rkc_turn": ('method = "rkc"\ntol = 0.05', 5e5, 1e-8, 1e-6, ""),
    "rkc_turn_2e5": ('method = "rkc"\ntol = 0.05', 2e5, 1e-8, 1e-6, ""),
    "rkc_turn_1e-5": ('method = "rkc"\ntol = 0.05', 5e5, 1e-8, 1e-5, ""),
    "rkc_turn_heun": ('method = "rkc"\ntol = 0.05', 5e5, 1e-8, 1e-6, 'method = "heun"'),
}
for _name, (_scene, _split, _h, _rs, _rk) in RESOLVED_CASES.items():
    CASES[_name] = (f"{_scene}; steps <= {_h:g} from sigma = {_split:g} to the turn and for "
                    f"the first {_rs:g} reversed" + (f"; reversed: {_rk}" if _rk else "")
                    ).replace("\n", "; ")
DEFAULT_CASES = ("heun", "heun_stages", "rkc", "rkc_stages", "rkc_2stages", "ref_heun", "ref_rkc")
C_WINDOW = (1e5, 1e3)


def reverse_C(d) -> float:
    """C = dx / d(1/sigma) between sigma = C_WINDOW[0] and C_WINDOW[1] on the reversed branch."""
    rv = d["direction"] < 0
    x = d["strain"][rv] - d["strain"][rv][0]
    inv = 1.0 / d["sigma"][rv]

    def x_at(v):
        k = int(np.argmax(inv >= v))
        return x[k - 1] + (v - inv[k - 1]) * (x[k] - x[k - 1]) / (inv[k] - inv[k - 1])
    hi, lo = C_WINDOW
    return float((x_at(1 / lo) - x_at(1 / hi)) / (1 / lo - 1 / hi))


def run(folder, n, network, case):
    comm = PETSc.COMM_WORLD
    path = os.path.join(folder, f"{case}_N{n}.h5")
    if comm.getRank() == 0 and os.path.exists(path):
        os.remove(path)
    comm.tompi4py().Barrier()
    base, seed = PERTURB_CASES.get(case, (case, None))
    if base in RESOLVED_CASES:
        settings, split, h, rstrain, rkeys = RESOLVED_CASES[base]
        text = FORWARD_RESOLVED_AND_BACK.format(
            n=n, network=network, path=path, split=split, h=h, rstrain=rstrain,
            rkeys=f", {rkeys}" if rkeys else "", rlast=f"integrator = {{ {rkeys} }}" if rkeys else "",
            settings="[integrator]\n" + settings)
    elif base in SPLIT_CASES:
        settings, split, near = SPLIT_CASES[base]
        text = FORWARD_SPLIT_AND_BACK.format(n=n, network=network, path=path, split=split,
                                             near=near, settings="[integrator]\n" + settings)
    else:
        text = FORWARD_AND_BACK.format(n=n, network=network, path=path,
                                       settings="[integrator]\n" + CASES[base])
    if seed is not None:
        text = text.replace('direction = "reverse"', f'direction = "reverse"\nperturb = '
                            f'{PERTURB_ETA!r}\nperturb_seed = {seed}')
    scene = load_scene(text)
    setup_logging(comm, quiet=True)
    comm.tompi4py().Barrier()
    t, c = time.perf_counter(), time.process_time()
    status = Run(scene, comm, path, quiet=True).execute()
    wall, cpu = time.perf_counter() - t, time.process_time() - c
    comm.tompi4py().Barrier()
    with h5py.File(path) as f:
        ts = f["timeseries"]
        d = {k: ts[k][:] for k in ("gamma", "sigma", "direction", "wall", "rejected", "strain")}
        counters = {k: int(f.attrs.get(k, 0)) for k in ("n_factorisations", "n_stage_pcg",
                                                         "n_stage_failed", "pcg_iterations",
                                                         "krylov_iterations")}
    fw = d["direction"] > 0
    row = dict(case=case, integrator=CASES[case].replace("\n", "; "), status=status,
               date=time.strftime("%Y-%m-%d %H:%M:%S"),
               wall_seconds=wall, cpu_seconds=cpu, loop_seconds=float(d["wall"][-1] - d["wall"][0]),
               steps_forward=int(fw.sum() - 1), steps_reverse=int((~fw).sum()),
               rejected=int(d["rejected"].sum()), **counters,
               gamma_1e6=results.crossing(d["gamma"][fw], d["sigma"][fw], 1e6), C=reverse_C(d))
    return row


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=4096)
    ap.add_argument("--cases", default=",".join(DEFAULT_CASES))
    ap.add_argument("--folder", default=os.path.join("out", "bench_network_integrators"))
    ap.add_argument("--json", default="network_integrators",
                    help="the results file under docs/benchmarks/ (another name: a run beside one "
                         "that writes the default, to be merged by hand)")
    ap.add_argument("--blas-threads", type=int, default=1,
                    help="BLAS threads for CHOLMOD on one rank (2: both cores on one factor, "
                         "as solver.parallel = \"threads\" does; a record of its own)")
    args = ap.parse_args()
    cases = args.cases.split(",")
    if not set(cases) <= set(CASES):
        raise SystemExit(f"--cases: a subset of {list(CASES)}")
    comm = PETSc.COMM_WORLD
    rank, size = comm.getRank(), comm.getSize()
    threads = args.blas_threads
    if threads != 1:
        if size > 1:
            raise SystemExit("--blas-threads: on one rank")
        if set_blas_threads(threads) is None:
            raise SystemExit("--blas-threads: this BLAS has no thread control")
    os.makedirs(args.folder, exist_ok=True)
    network = network_file(args.folder, args.n, comm)
    load_start = os.getloadavg()

    def same(r):             # a record of this N, rank count and BLAS threads
        return r["n"] == args.n and r["ranks"] == size and r.get("blas_threads", 1) == threads
    rows = []
    if rank == 0:        # the rows of earlier runs of this N and rank count (other cases) stay
        import json
        p = results.path(args.json)
        old = {}
        if os.path.exists(p):
            with open(p) as fh:
                old = json.load(fh)
        prev = [r for r in old.get("records", []) if same(r)]
        kept = [r for r in (prev[0]["rows"] if prev else []) if r["case"] not in cases]
    else:
        old, kept = {}, []
    for case in cases:
        rows.append(run(args.folder, args.n, network, case))
        r = rows[-1]
        if rank == 0:
            print(f"{case:12s}: {r['status']}, loop {r['loop_seconds']:.1f} s (CPU {r['cpu_seconds']:.1f} s), "
                  f"steps {r['steps_forward']} + {r['steps_reverse']}, rejected {r['rejected']}, "
                  f"factorisations {r['n_factorisations']}, PCG solves {r['n_stage_pcg']} "
                  f"({r['pcg_iterations']} iterations), gamma_1e6 {r['gamma_1e6']:.10f}, C {r['C']:.4f}",
                  flush=True)
    rows = kept + rows
    ref = {r["case"]: r for r in rows}
    for r in rows:
        for name in ("ref_heun", "ref_rkc"):           # NaN without that reference
            g, c = (ref[name]["gamma_1e6"], ref[name]["C"]) if name in ref else (np.nan, np.nan)
            r[f"dgamma_{name}"] = r["gamma_1e6"] - g
            r[f"dC_{name}"] = r["C"] / c - 1
    if rank == 0:
        recs = [r for r in old.get("records", []) if not same(r)]
        recs.append(dict(n=args.n, ranks=size, blas_threads=threads, date=time.strftime("%Y-%m-%d %H:%M:%S"),
                         load_start=load_start, load_end=os.getloadavg(),
                         peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                         c_window=C_WINDOW, rows=rows))
        results.write(args.json, dict(
            benchmark="network forward to sigma = 1e6 and back: integrators and intermediate solves",
            records=recs))
        for r in rows:
            print(f"{r['case']:12s}: dgamma vs ref_heun {r['dgamma_ref_heun']:+.1e}, ref_rkc "
                  f"{r['dgamma_ref_rkc']:+.1e}; dC/C vs ref_heun {r['dC_ref_heun']:+.3f}, ref_rkc "
                  f"{r['dC_ref_rkc']:+.3f}", flush=True)


if __name__ == "__main__":
    main()
