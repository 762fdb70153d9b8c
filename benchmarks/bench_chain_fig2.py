"""Wall time of the paper's Fig. 2 chain run (runs/fig2_chain_mu0.toml: N = 10^4, forward to
<V^2> = 1e8, then reversed) on 1 rank and under mpirun -n 2 (target: <= 2 minutes on 2 cores),
and of the embedded default scene.  Writes docs/benchmarks/chain_fig2.json.

    python benchmarks/bench_chain_fig2.py [--ranks 1,2]
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time

import h5py

import results  # noqa: E402  (benchmarks/results.py)

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")


def run(scene: str | None, ranks: int, out: str) -> dict:
    cmd = [sys.executable, "-m", "parflow.shear"] + ([scene] if scene else []) + \
          ["--output", out, "--overwrite", "--quiet", "--no-plots"]
    if ranks > 1:
        cmd = [shutil.which("mpirun") or "mpirun", "-n", str(ranks)] + cmd
    t = time.perf_counter()
    subprocess.run(cmd, check=True, cwd=ROOT)
    wall = time.perf_counter() - t
    with h5py.File(out) as f:
        return dict(scene=scene or "<default>", ranks=ranks, wall_seconds=round(wall, 2),
                    steps=int(f.attrs["steps"]), status=str(f.attrs["status"]),
                    solver=str(f.attrs["solver"]), loop_seconds=round(float(f.attrs["wall_seconds"]), 2))


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--ranks", default="1,2")
    args = p.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for scene in ("runs/fig2_chain_mu0.toml", None):
            for ranks in [int(x) for x in args.ranks.split(",")]:
                row = run(scene, ranks, os.path.join(tmp, "run.h5"))
                rows.append(row)
                print(row, flush=True)
    data = dict(benchmark="Fig. 2 chain run and default scene: wall time", rows=rows,
                date=time.strftime("%Y-%m-%d %H:%M:%S"), load_before=os.getloadavg(),
                cpus=os.cpu_count())
    results.write("chain_fig2", data)


if __name__ == "__main__":
    main()
