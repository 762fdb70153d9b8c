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
exceeds 0.1, interpolated in log between the rows around it
(``parflow.post.chain.reversal_departure``).  If the reversed flow amplifies a seed at a rate lambda, the
departure is x0 + ln(1/eta) / lambda: converged *given eta* when every integrator agrees at
that eta, and the unseeded runs tell which eta each integrator's own error amounts to.

With ``--resolved-turn`` the forward leg is split too: forward to <V^2> = TAIL_V2 as in the
scene, then on to the turn (<V^2> = 1e8) with steps of at most MAX_DG.  The reversed flow
amplifies at lambda ~ 4 <V^2> ~ 4e8 per unit strain what the forward flow damps at the same
rate, so an error the last forward steps make in the fast modes (RKC2 steps there are
2-6e-7, lambda h ~ 80-250: the stabilised step damps those modes, not as exp(-lambda h), and the
error control, which sees a damped mode as small, lets it pass) is a seed that the reversal
grows; with lambda h <= 0.2 on both sides of the turn that seed is gone and what is left is
the state's own round-off.  Rows carry ``turn`` = "scene" or "resolved".

Writes docs/benchmarks/departure.json.

    python benchmarks/bench_departure.py [--runs rkc:0.001:0,1e-8,... ;heun:0.01:0,1e-6]
                                         [--resolved-turn]
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

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from parflow.post.chain import reversal_departure as departure  # noqa: E402
from parflow.scene import DEFAULT_SCENE  # noqa: E402

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
RESOLVE, MAX_DG = 2e-7, 5e-10
TAIL_V2 = 9e7                   # --resolved-turn: the forward leg's last part, from this <V^2>
FORWARD_LEG = """[[protocol.leg]]
direction = "forward"
V2_above = 1e8
"""
SPLIT_FORWARD = f"""[[protocol.leg]]
direction = "forward"
V2_above = {TAIL_V2:g}
[[protocol.leg]]
direction = "forward"
V2_above = 1e8
integrator = {{ max_dgamma = {MAX_DG:g} }}
"""
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


RESOLVED_RUNS = ("rkc:0.001:0,1e-15,1e-14,1e-13,1e-12,1e-10,1e-8;rkc:0.0001:0;rkc:0.00001:0;"
                 "heun:0.01:0;heun:0.001:0;ros2:0.02:0;ros2:0.002:0")
DEFAULT_RUNS = ("rkc:0.001:0,1e-10,1e-9,1e-8,1e-7,1e-6;rkc:0.0003:0,1e-8,1e-6;rkc:0.0001:0,1e-8;"
                "rkc:0.00003:0;"
                "heun:0.01:0,1e-8,1e-6;heun:0.002:0,1e-6")


def run(method: str, tol: float, eta: float, out: str, resolved: bool = False) -> dict:
    assert REVERSE_LEG in DEFAULT_SCENE and FORWARD_LEG in DEFAULT_SCENE
    scene = out[:-3] + ".toml"
    text = DEFAULT_SCENE.replace(REVERSE_LEG, SPLIT_REVERSE.format(eta=eta))
    if resolved:
        text = text.replace(FORWARD_LEG, SPLIT_FORWARD)
    with open(scene, "w") as fh:
        fh.write(text)
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
    fw = d["direction"] > 0
    return dict(method=method, tol=tol, eta=eta, turn="resolved" if resolved else "scene",
                status=status, steps=steps,
                wall_seconds=round(wall, 2), departure_strain=departure(d, interpolate=True),
                first_reverse_step=float(abs(d["dgamma"][rv][0])) if rv.any() else float("nan"),
                last_forward_step=float(d["dgamma"][fw][-1]) if fw.any() else float("nan"))


def key(r: dict) -> tuple:
    return r["method"], r["tol"], r["eta"], r.get("turn", "scene")


def seed_law(rows: list, turn: str, eta_range: tuple) -> dict | None:
    """x = x0 + s log10(1e-6 / eta) from the seeded runs of ``turn`` of the (method, tol)
    group with the most etas > 0 in ``eta_range`` (where the seed, not the integrator, sets
    the departure)."""
    seeded = [r for r in rows if r["eta"] > 0 and r.get("turn", "scene") == turn
              and eta_range[0] <= r["eta"] <= eta_range[1]]
    if not seeded:
        return None
    best = max({(r["method"], r["tol"]) for r in seeded},
               key=lambda k: sum(1 for r in seeded if (r["method"], r["tol"]) == k))
    pts = [(np.log10(1e-6 / r["eta"]), r["departure_strain"]) for r in seeded
           if (r["method"], r["tol"]) == best]
    if len(pts) < 2:
        return None
    x, y = np.array(pts).T
    slope, x0 = np.polyfit(x, y, 1)
    return dict(method=best[0], tol=best[1], eta_range=list(eta_range), x0_at_1e6=float(x0),
                per_decade=float(slope), rate_lambda=float(1 / (slope / np.log(10))))


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--runs", default=DEFAULT_RUNS,
                   help="method:tol:eta,eta,... groups separated by ';'")
    p.add_argument("--resolved-turn", action="store_true",
                   help=f"forward steps <= {MAX_DG:g} from <V^2> = {TAIL_V2:g} to the turn "
                        f"(default runs: {RESOLVED_RUNS})")
    a = p.parse_args()
    if a.resolved_turn and a.runs == DEFAULT_RUNS:
        a.runs = RESOLVED_RUNS
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
            row = run(m, float(t), float(e), os.path.join(tmp, f"{m}_{t}_{e}.h5"),
                      a.resolved_turn)
            row["date"] = time.strftime("%Y-%m-%d %H:%M")
            rows.append(row)
            print(f"{m} tol {t} eta {float(e):g} turn {row['turn']}: departure "
                  f"{row['departure_strain']:.4g} ({row['steps']} steps, {row['wall_seconds']} s)",
                  flush=True)
    new = {key(r) for r in rows}
    rows = [r for r in old if key(r) not in new] + rows
    results.write("departure", dict(
        scene=f"embedded default (Fig. 2 chain, N = 1e4); reversed leg: the first {RESOLVE:g} "
              f"strain with max_dgamma = {MAX_DG:g} and perturb = eta; turn \"resolved\": the "
              f"forward leg from <V^2> = {TAIL_V2:g} to the turn with max_dgamma = {MAX_DG:g}",
        date=time.strftime("%Y-%m-%d %H:%M"), loadavg=list(os.getloadavg()), rows=rows,
        fit=seed_law(rows, "scene", (1e-8, 1e-6)),
        fit_resolved=seed_law(rows, "resolved", (1e-13, 1e-8))))


if __name__ == "__main__":
    main()
