"""Speed of the hard-disc suspension (issue 4 target: 300 % strain at N = 4096, phi = 0.82 in
<= 20 minutes on 2 cores; how phi = 0.84 scales and what bounds it).

Runs the Figs. 6-7 scenes (runs/fig6_suspension_phi*.toml, N = 4096, 4.0 strain with
analyses over the last 1.0), or reads run files that already exist (``--from-runs``), and
writes docs/benchmarks/suspension.json: wall time of the step loop, strain per hour over the
first 3.0 strain (no analyses there), per-step breakdown (neighbour search, LCP of which
factorisations, position update), factorisations and active-set iterations per step,
singular active sets, collisions, and the machine's load when each run ended.

    python benchmarks/bench_suspension.py --from-runs out/fig6_suspension_phi0.8*.h5
    python benchmarks/bench_suspension.py --phi 0.820,0.830,0.840 [--ranks 1]

The step-size trade (``--dmax``: the largest non-affine displacement per step, model.dmax)
runs one scene at each dmax and writes docs/benchmarks/suspension_dmax.json: speed, steps,
retries, and the step-error indicators -- the share of sigma from gaps closed within a step
(gap work; it vanishes with the step), mu = sigma/p and sigma's medians over strain windows:

    python benchmarks/bench_suspension.py --dmax 0.04,0.02,0.01,0.005 --phi 0.840 \
        --seed 2 --strain 0.12
    python benchmarks/bench_suspension.py --dmax 0.04,0.02,0.01,0.005 --phi 0.820 \
        --seed 1 --strain 1.5 --from-strain 0.5

Where a long run's wall time goes by stress (``--by-sigma``: run files that exist, e.g. the
flowing phi = 0.840 seeds; rows at the final packing fraction only): for each bin of sigma,
the steps, strain and wall time there, seconds per unit strain, ms per step and the mean
step; writes docs/benchmarks/suspension_by_sigma.json:

    python benchmarks/bench_suspension.py --by-sigma out/suspension_phi0.840_flowing_seed*.h5
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time

import h5py
import numpy as np

import results  # noqa: E402  (benchmarks/results.py)

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")


def summarise(path: str, transient: float = 3.0) -> dict:
    """Timings of one suspension run file."""
    with h5py.File(path) as f:
        ts = {k: f["timeseries"][k][()] for k in f["timeseries"]}
        a = dict(f.attrs)
        n_an = len(f["analysis"]) if "analysis" in f else 0
        phi = float(f["model"].attrs.get("phi", np.nan))
    strain, wall = ts["strain"], ts["wall"]
    m = (ts["step"] > 0) & (strain <= transient + 1e-12)
    k = np.flatnonzero(m)
    status = str(a["status"])
    if status == "interrupted" or (status == "failed" and "KeyboardInterrupt" in str(a.get("message", ""))):
        status = "stopped by hand"
    elif status == "running":
        status = "still running"
    rec = dict(file=os.path.relpath(path, ROOT), status=status, phi=round(phi, 5), loadavg_end=[float(x) for x in a.get("loadavg_end", [])],
               n_ranks=int(a["n_ranks"]), steps=int(a.get("steps", ts["step"][-1])),
               strain=float(strain[-1]), loop_seconds=round(float(a.get("wall_seconds", wall[-1])), 1),
               max_overlap=float(a.get("max_overlap", np.nan)),
               singular_events=int(a.get("singular_events", 0)),
               collisions=int(a.get("collisions", 0)), analyses=n_an)
    if k.size > 1:
        x0, x1 = float(strain[k[0] - 1]), float(strain[k[-1]])
        t = float(wall[k[-1]] - wall[k[0] - 1])
        rec.update(window_strain=round(x1 - x0, 4), window_seconds=round(t, 1),
                   strain_per_hour=round((x1 - x0) / t * 3600, 2),
                   minutes_per_300pc=round(3.0 / ((x1 - x0) / t) / 60, 1),
                   steps_per_second=round(k.size / t, 2),
                   mean_dgamma=float(np.mean(np.abs(ts["dgamma"][k]))),
                   ms_search=round(1e3 * float(np.mean(ts["t_search"][k])), 2),
                   ms_lcp=round(1e3 * float(np.mean(ts["t_lcp"][k])), 2),
                   ms_update=round(1e3 * float(np.mean(ts["t_update"][k])), 2),
                   ms_other=round(1e3 * (t / k.size - float(np.mean(ts["t_search"][k] + ts["t_lcp"][k]
                                                                    + ts["t_update"][k]))), 2),
                   factorizations_per_step=round(float(np.mean(ts["factorizations"][k])), 2),
                   factorizations_max=int(np.max(ts["factorizations"][k])),
                   lcp_iterations_per_step=round(float(np.mean(ts["lcp_iterations"][k])), 2),
                   collisions_per_step=round(float(np.mean(ts["n_coll"][k])), 2),
                   active_per_step=round(float(np.mean(ts["n_active"][k])), 1),
                   singular_steps=int(np.count_nonzero(ts["singular"][k])))
    return rec


def step_error(path: str, from_strain: float = 0.0, windows: int = 3) -> dict:
    """Step-size indicators of a suspension run past ``from_strain``: the gap work's share of
    sigma (strain-weighted), medians of sigma over ``windows`` equal strain windows, medians of
    mu and pressure, infeasible retries, mean step, and the run's dmax."""
    with h5py.File(path) as f:
        ts = {k: f["timeseries"][k][()] for k in f["timeseries"]}
        retries = int(f.attrs.get("infeasible_reductions", -1))
        dmax = float(f["model"].attrs["dmax"])
    g = ts["strain"]
    m = (ts["step"] > 0) & (g > from_strain)
    dg, sig = ts["dgamma"][m], ts["sigma"][m]
    edges = np.linspace(from_strain, float(g[-1]), windows + 1)
    med = [float(np.median(ts["sigma"][m & (g > a) & (g <= b)])) for a, b in zip(edges, edges[1:])]
    return dict(dmax=dmax, from_strain=from_strain, steps_measured=int(m.sum()),
                gap_work_share=round(float(-np.sum(ts["gap_work"][m] * dg) / np.sum(sig * dg)), 4),
                sigma_mean=round(float(np.sum(sig * dg) / np.sum(dg)), 2),
                sigma_window_medians=[round(x, 1) for x in med],
                pressure_mean=round(float(np.sum(ts["pressure"][m] * dg) / np.sum(dg)), 2),
                mu_median=round(float(np.median(ts["mu"][m])), 4),
                mean_dgamma_measured=float(np.mean(dg)), infeasible_retries=retries,
                max_overlap=float(np.max(ts["max_overlap"])))


SCENE_DMAX = """title = "dmax trade: N = {n}, phi = {phi}, seed {seed}, dmax = {dmax}"
seed = {seed}
[model]
name = "suspension"
N = {n}
phi = {phi}
dmax = {dmax}
[[protocol.leg]]
direction = "forward"
strain = {strain}
[observables]
omega_min_every = 0
[output]
path = "{out}"
progress_seconds = 60
"""


def dmax_trade(a) -> None:
    """The suspension from rest (the Figs. 6-7 preparation, no analyses) at each dmax of
    ``a.dmax``, or the files given with --from-runs; docs/benchmarks/suspension_dmax.json."""
    if a.from_runs is None:
        paths = []
        for d in a.dmax.split(","):
            out = os.path.join(ROOT, "out", f"bench_suspension_phi{a.phi}_dmax{d}.h5")
            scene = out[:-3] + ".toml"
            with open(scene, "w") as fh:
                fh.write(SCENE_DMAX.format(n=a.n, phi=a.phi, seed=a.seed, dmax=float(d),
                                           strain=a.strain, out=out))
            run(scene, out, a.ranks)
            paths.append(out)
        cmd = (f"python3 benchmarks/bench_suspension.py --dmax {a.dmax} --phi {a.phi} "
               f"--n {a.n} --seed {a.seed} --strain {a.strain} --from-strain {a.from_strain}")
    else:
        paths = a.from_runs
        cmd = ("python3 benchmarks/bench_suspension.py --dmax - --from-strain "
               f"{a.from_strain} --from-runs " + " ".join(paths))
    recs = []
    for x in paths:
        r = summarise(x, transient=np.inf)
        r.update(step_error(x, a.from_strain))
        recs.append(r)
    recs.sort(key=lambda r: (r["phi"], -r["dmax"]))
    name = "suspension_dmax" if a.name is None else a.name
    old = {}
    if os.path.exists(results.path(name)):
        with open(results.path(name)) as fh:
            old = json.load(fh)
    sets = [s for s in old.get("sets", []) if s.get("command") != cmd]
    sets.append(dict(command=cmd, date=time.strftime("%Y-%m-%d %H:%M:%S"),
                     loadavg=list(os.getloadavg()), results=recs))
    data = dict(benchmark="hard-disc suspension, N = 4096: the step-size trade (model.dmax)",
                note="one sample a dmax: the flow is chaotic, so the trajectories differ "
                     "after a few steps; speeds of runs that shared the 2 cores with other jobs "
                     "(see loadavg_end) are upper bounds on the time",
                sets=sets)
    print(results.write(name, data))


SIGMA_EDGES = (0.0, 100.0, 200.0, 400.0, 1e3, 1e4, np.inf)


def by_sigma(path: str, edges=SIGMA_EDGES) -> dict:
    """The wall time of one suspension run file by bins of sigma, over the rows at its final
    packing fraction (compress_to when the scene compresses, else every step).  A step's wall
    time is the difference of the recorded clock; the clock restarts with each sitting (a
    restart), where the first row's own clock is its time."""
    with h5py.File(path, "r") as f:
        ts = {k: f["timeseries"][k][()] for k in f["timeseries"]}
        a = dict(f.attrs)
        phi_final = float(f["model"].attrs.get("phi", np.nan))
        n_discs = int(f["initial/s"].shape[0]) if "initial/s" in f else 0
    wall, step = ts["wall"], ts["step"]
    dw = np.diff(wall, prepend=0.0)
    dw = np.where(dw < 0, wall, dw)
    rows = step > 0
    if "phi" in ts:
        rows &= ts["phi"] >= float(np.max(ts["phi"])) - 1e-12
        phi_final = float(np.max(ts["phi"]))
    dg, sig = np.abs(ts["dgamma"]), ts["sigma"]
    strain, seconds = float(dg[rows].sum()), float(dw[rows].sum())
    bins = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        b = rows & (sig > lo) & (sig <= hi)
        n = int(b.sum())
        if n == 0:
            continue
        s, w = float(dg[b].sum()), float(dw[b].sum())
        bins.append(dict(sigma_lo=lo, sigma_hi=hi, steps=n, strain=s, seconds=round(w, 1),
                         s_per_strain=w / s, ms_per_step=1e3 * w / n, mean_dgamma=s / n,
                         strain_share=s / strain, wall_share=w / seconds,
                         lcp_share=float(ts["t_lcp"][b].sum()) / w,
                         factorizations_per_step=float(np.mean(ts["factorizations"][b]))))
    return dict(file=os.path.relpath(path, ROOT), status=str(a.get("status", "")),
                phi=round(phi_final, 5), N=n_discs, steps=int(rows.sum()),
                strain=strain, seconds=round(seconds, 1), strain_per_hour=3600 * strain / seconds,
                sigma_median=float(np.median(sig[rows])), bins=bins)


def run(scene: str, out: str, ranks: int) -> None:
    cmd = [sys.executable, "-m", "parflow.shear", scene, "--output", out, "--overwrite",
           "--quiet", "--no-plots"]
    if ranks > 1:
        cmd = [shutil.which("mpirun") or "mpirun", "-n", str(ranks)] + cmd
    subprocess.run(cmd, check=True, cwd=ROOT)


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--from-runs", nargs="*", default=None, help="summarise these run files")
    p.add_argument("--phi", default="0.820,0.830,0.840")
    p.add_argument("--ranks", type=int, default=1)
    p.add_argument("--dmax", default=None,
                   help="comma-separated dmax values: the step-size trade (one --phi)")
    p.add_argument("--seed", type=int, default=1, help="with --dmax: the scene's seed")
    p.add_argument("--n", type=int, default=4096, help="with --dmax: number of discs")
    p.add_argument("--strain", type=float, default=0.12, help="with --dmax: strain run")
    p.add_argument("--from-strain", type=float, default=0.0,
                   help="with --dmax: the indicators are taken past this strain")
    p.add_argument("--name", default=None, help="with --dmax: the JSON's name "
                   "(default suspension_dmax)")
    p.add_argument("--by-sigma", nargs="+", metavar="RUN",
                   help="the wall time of these run files by bins of sigma (rows at the final "
                        "phi); writes docs/benchmarks/suspension_by_sigma.json")
    a = p.parse_args()
    if a.by_sigma:
        missing = [x for x in a.by_sigma if not os.path.exists(x)]
        if missing:
            print(f"bench_suspension: no such run file {missing[0]!r}", file=sys.stderr)
            sys.exit(2)
        recs = [by_sigma(x) for x in sorted(a.by_sigma)]
        for r in recs:
            print(r["file"], f"{r['strain']:.3f} strain, {r['strain_per_hour']:.2f} strain/h")
            for b in r["bins"]:
                print(f"  sigma in ({b['sigma_lo']:g}, {b['sigma_hi']:g}]: {b['steps']} steps, "
                      f"{b['s_per_strain']:.0f} s per unit strain, {b['ms_per_step']:.0f} ms a step")
        data = dict(benchmark="suspension wall time by sigma", date=time.strftime("%Y-%m-%d %H:%M:%S"),
                    command="python3 benchmarks/bench_suspension.py --by-sigma " + " ".join(
                        os.path.relpath(x, ROOT) for x in sorted(a.by_sigma)),
                    runs=recs)
        print(results.write("suspension_by_sigma", data))
        return
    if a.dmax is not None:
        if "," in a.phi and a.from_runs is None:
            p.error("--dmax takes one --phi, e.g. --phi 0.840")
        dmax_trade(a)
        return
    load0 = os.getloadavg()
    if a.from_runs is None:
        paths = []
        for phi in a.phi.split(","):
            scene = os.path.join(ROOT, "runs", f"fig6_suspension_phi{phi}.toml")
            out = os.path.join(ROOT, "out", f"bench_suspension_phi{phi}.h5")
            run(scene, out, a.ranks)
            paths.append(out)
        cmd = f"python3 benchmarks/bench_suspension.py --phi {a.phi} --ranks {a.ranks}"
    else:
        paths = a.from_runs
        cmd = "python3 benchmarks/bench_suspension.py --from-runs " + " ".join(
            os.path.relpath(x, ROOT) for x in paths)
    recs = [summarise(x) for x in sorted(paths)]
    data = dict(benchmark="hard-disc suspension, N = 4096 (parflow issue 4)", command=cmd,
                date=time.strftime("%Y-%m-%d %H:%M:%S"), loadavg=list(load0),
                note=("from-runs: the runs were made while other jobs shared the 2 cores; "
                      "see the load average" if a.from_runs is not None else ""),
                results=recs)
    print(results.write("suspension", data))


if __name__ == "__main__":
    main()
