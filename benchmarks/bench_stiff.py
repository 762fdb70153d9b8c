"""The stiff chain: Heun against the stabilised explicit RKC2 and the linearly implicit ROS2
integrators on the paper's Fig. 2
scene (the embedded default scene: N = 10^4, eps = 0.1, mu = 0, forward to <V^2> = 1e8, then
reversed), each against a tight reference (Heun, tol = 0.002).  Per run: accepted and
rejected steps, factorisations, wall time, the forward branch's largest |d ln <V^2>| against
the reference at the same strain, and the strain after the reversal at which the reversed
branch departs from the forward one (|ln V2_rev - ln V2_fwd| > 0.1 at the same gamma).
Writes docs/benchmarks/stiff.json.

    python benchmarks/bench_stiff.py [--runs heun:0.05,rkc:0.001,ros2:0.01:200:low,...]
                                     [--reference heun:0.002]
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

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
sys.path.insert(0, ROOT)
from parflow.post.chain import reversal_departure as departure  # noqa: E402


LOW_G = 1.0 - 2.0 ** -0.5       # ROS2's other L-stable g (integrator.ros2_gamma)


def run(method: str, tol: float, out: str, max_stages: int = 200, g: float | None = None) -> dict:
    cmd = [sys.executable, "-m", "parflow.shear", "--output", out, "--overwrite", "--quiet",
           "--no-plots", "--set", f"integrator.method={method}", "--set", f"integrator.tol={tol}",
           "--set", f"integrator.max_stages={max_stages}"]
    if g is not None:
        cmd += ["--set", f"integrator.ros2_gamma={g!r}"]
    t = time.perf_counter()
    subprocess.run(cmd, check=True, cwd=ROOT)
    wall = time.perf_counter() - t
    with h5py.File(out) as f:
        ts = f["timeseries"]
        d = {k: ts[k][:] for k in ("gamma", "V2", "direction", "rejected", "step")}
        return dict(method=method, tol=tol, max_stages=max_stages,
                    **({"ros2_gamma": g} if g is not None else {}), status=str(f.attrs["status"]),
                    steps=int(f.attrs["steps"]), rejected=int(d["rejected"].sum()),
                    factorisations=int(f.attrs.get("n_factorisations", -1)),
                    krylov_iterations=int(f.attrs.get("krylov_iterations", 0)),
                    pcg_iterations=int(f.attrs.get("pcg_iterations", 0)),
                    wall_seconds=round(wall, 2), gamma_c=float(f["model"].attrs["gamma_c"])), d


def forward_error(d, ref) -> float:
    f, fr = d["direction"] > 0, ref["direction"] > 0
    g, v = d["gamma"][f], d["V2"][f]
    ok = (g > ref["gamma"][fr][1]) & (g < ref["gamma"][fr][-2])
    vr = np.exp(np.interp(g[ok], ref["gamma"][fr], np.log(ref["V2"][fr])))
    return float(np.max(np.abs(np.log(v[ok] / vr))))


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--runs", default="heun:0.05,heun:0.01,rkc:0.01,rkc:0.003,rkc:0.001,rkc:0.003:2,"
                                     "ros2:0.05,ros2:0.02,ros2:0.01:200:low,ros2:0.005:200:low",
                   help="method:tol[:max_stages[:low]] ... (low: ROS2 with g = 1 - 1/sqrt(2))")
    p.add_argument("--reference", default="heun:0.002")
    a = p.parse_args()
    tmp = tempfile.mkdtemp(prefix="parflow-stiff-")
    m, t = a.reference.split(":")
    ref_row, ref = run(m, float(t), os.path.join(tmp, "ref.h5"))
    ref_row.update(departure_strain=departure(ref))
    rows = []
    for spec in a.runs.split(","):
        m, t, *ms = spec.split(":")
        if len(ms) > 1 and ms[1] != "low":
            raise SystemExit(f"--runs {spec}: the fourth field is 'low' or nothing")
        row, d = run(m, float(t), os.path.join(tmp, f"{m}_{t}_{''.join(ms)}.h5"),
                     int(ms[0]) if ms else 200, LOW_G if len(ms) > 1 else None)
        row.update(forward_max_dlnV2=forward_error(d, ref), departure_strain=departure(d))
        rows.append(row)
        print(row, flush=True)
    out = results.write("stiff", dict(scene="embedded default (Fig. 2 chain, N = 1e4)",
                                      reference=ref_row, runs=rows))
    print("wrote", out)


if __name__ == "__main__":
    main()
