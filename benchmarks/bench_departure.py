"""Reversibility of the Fig. 2 chain: the strain after the reversal at which the reversed
branch departs from the forward one, against a seeded displacement at the turn.

The embedded default scene (N = 10^4, eps = 0.1, mu = 0, forward to <V^2> = 1e8, then
reversed), its reversed leg split in two: the first RESOLVE strain with steps of at most
MAX_DG (the leg's own integrator keys: the departure is resolved whatever the integrator's
steps) and ``perturb = eta`` -- at the turn every node is displaced by a Gaussian vector of
rms eta a0 per coordinate (seeded), the rod lengths restored -- then the rest of the
reversed leg as in the scene.  For each
integrator and tolerance, and each eta (0: no displacement, the integrator's own error is
the only seed), the departure strain: where |ln V2_rev - ln V2_fwd| at the same gamma first
exceeds 0.1, interpolated in log between the rows around it (``bench_stiff.departure``).  If the reversed flow amplifies a seed at a rate lambda, the
departure is x0 + ln(1/eta) / lambda: converged *given eta* when every integrator agrees at
that eta, and the unseeded runs tell which eta each integrator's own error amounts to.
Writes docs/benchmarks/departure.json.

    python benchmarks/bench_departure.py [--runs rkc:0.001:0,1e-8,... ;heun:0.01:0,1e-6]
    (rows of other runs already in the JSON are kept)
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

import h5py
import numpy as np

import results  # noqa: E402  (benchmarks/results.py)
from bench_stiff import departure  # noqa: E402

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from parflow.scene import DEFAULT_SCENE  # noqa: E402

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
RESOLVE, MAX_DG = 2e-7, 5e-10
REVERSE_LEG = """[[protocol.leg]]
direction = "reverse"
strain = 0.02
V2_below = 1.0
"""
SPLIT_REVERSE = f"""[[protocol.leg]]
direction = "reverse"
strain = {RESOLVE:g}
V2_below = 1.0
perturb = {{eta!r}}
integrator = {{{{ max_dgamma = {MAX_DG:g} }}}}
[[protocol.leg]]
direction = "reverse"
strain = {0.02 - RESOLVE!r}
V2_below = 1.0
"""


DEFAULT_RUNS = ("rkc:0.001:0,1e-10,1e-9,1e-8,1e-7,1e-6;rkc:0.0003:0,1e-8,1e-6;rkc:0.0001:0,1e-8;"
                "rkc:0.00003:0;"
                "heun:0.01:0,1e-8,1e-6;heun:0.002:0,1e-6")


def run(method: str, tol: float, eta: float, out: str) -> dict:
    assert REVERSE_LEG in DEFAULT_SCENE
    scene = out[:-3] + ".toml"
    with open(scene, "w") as fh:
        fh.write(DEFAULT_SCENE.replace(REVERSE_LEG, SPLIT_REVERSE.format(eta=eta)))
    cmd = [sys.executable, "-m", "parflow.shear", scene, "--output", out, "--overwrite", "--quiet",
           "--no-plots", "--set", f"integrator.method={method}", "--set", f"integrator.tol={tol}"]
    t = time.perf_counter()
    subprocess.run(cmd, check=True, cwd=ROOT)
    wall = time.perf_counter() - t
    with h5py.File(out) as f:
        ts = f["timeseries"]
        d = {k: ts[k][:] for k in ("gamma", "V2", "direction", "dgamma")}
        status, steps = str(f.attrs["status"]), int(f.attrs["steps"])
    rv = d["direction"] < 0
    return dict(method=method, tol=tol, eta=eta, status=status, steps=steps,
                wall_seconds=round(wall, 2), departure_strain=departure(d, interpolate=True),
                first_reverse_step=float(abs(d["dgamma"][rv][0])) if rv.any() else float("nan"))


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--runs", default=DEFAULT_RUNS,
                   help="method:tol:eta,eta,... groups separated by ';'")
    a = p.parse_args()
    tmp = tempfile.mkdtemp(prefix="parflow-departure-")
    rows = []
    old = []                     # rows of an earlier run of other (method, tol, eta) stay
    if os.path.exists(results.path("departure")):
        import json
        with open(results.path("departure")) as fh:
            old = json.load(fh).get("rows", [])
    for group in a.runs.split(";"):
        m, t, etas = group.split(":")
        for e in etas.split(","):
            row = run(m, float(t), float(e), os.path.join(tmp, f"{m}_{t}_{e}.h5"))
            row["date"] = time.strftime("%Y-%m-%d %H:%M")
            rows.append(row)
            print(f"{m} tol {t} eta {float(e):g}: departure {row['departure_strain']:.4g} "
                  f"({row['steps']} steps, {row['wall_seconds']} s)", flush=True)
    new = {(r["method"], r["tol"], r["eta"]) for r in rows}
    rows = [r for r in old if (r["method"], r["tol"], r["eta"]) not in new] + rows
    # the law x = x0 + s log10(1e-6 / eta) from the seeded runs of the group with the most etas
    # > 0 (where the seed, not the integrator, sets the departure: the runs that agree)
    fit = None
    seeded = [r for r in rows if r["eta"] > 0]
    if seeded:
        best = max({(r["method"], r["tol"]) for r in seeded},
                   key=lambda k: sum(1 for r in seeded if (r["method"], r["tol"]) == k))
        pts = [(np.log10(1e-6 / r["eta"]), r["departure_strain"]) for r in seeded
               if (r["method"], r["tol"]) == best and 1e-8 <= r["eta"] <= 1e-6]
        if len(pts) >= 2:
            x, y = np.array(pts).T
            slope, x0 = np.polyfit(x, y, 1)
            fit = dict(method=best[0], tol=best[1], eta_range=[1e-8, 1e-6], x0_at_1e6=float(x0),
                       per_decade=float(slope), rate_lambda=float(1 / (slope / np.log(10))))
    results.write("departure", dict(
        scene=f"embedded default (Fig. 2 chain, N = 1e4); reversed leg: the first {RESOLVE:g} "
              f"strain with max_dgamma = {MAX_DG:g} and perturb = eta",
        date=time.strftime("%Y-%m-%d %H:%M"), loadavg=list(os.getloadavg()), rows=rows, fit=fit))


if __name__ == "__main__":
    main()
