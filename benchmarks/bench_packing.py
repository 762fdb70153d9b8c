"""Benchmark: jammed packing + WLKM network build (issue 3).

    OMP_NUM_THREADS=1 python benchmarks/bench_packing.py            # N = 4096, 40 000
    python benchmarks/bench_packing.py --sizes 4096 40000 100000
    python benchmarks/bench_packing.py --large                      # adds N = 10^6

Each N runs in a fresh subprocess so that its peak RSS (resource.getrusage ru_maxrss) is
its own.  Results (N, FIRE iterations, seconds wall and CPU, peak RSS, z0, z, ...) go to
docs/benchmarks/packing.json (rewritten after every run; --append keeps earlier
results; the load average is recorded because
the machine may be shared: CPU seconds are the steadier number).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def one(n: int, phi: float, z: float, seed: int, kernel: str) -> dict:
    sys.path.insert(0, str(ROOT))
    import numpy as np
    import scipy
    from parflow.models import network_build as nb
    from parflow.models import packing as pk

    load0 = os.getloadavg()
    r0 = resource.getrusage(resource.RUSAGE_SELF)
    t0 = time.perf_counter()
    p = pk.make_packing(n, phi, seed=seed, kernel=kernel)
    t1 = time.perf_counter()
    r1 = resource.getrusage(resource.RUSAGE_SELF)
    net = nb.network_from_packing(p, z, seed=seed, check_self_stress=False)
    t2 = time.perf_counter()
    r2 = resource.getrusage(resource.RUSAGE_SELF)
    cpu = lambda a, b: (b.ru_utime + b.ru_stime) - (a.ru_utime + a.ru_stime)  # noqa: E731
    return dict(
        N=n, phi=phi, z_target=z, seed=seed, kernel=p.info["kernel"],
        iterations=p.iterations,
        packing_seconds=round(t1 - t0, 3), packing_cpu_seconds=round(cpu(r0, r1), 3),
        network_seconds=round(t2 - t1, 3), network_cpu_seconds=round(cpu(r1, r2), 3),
        total_seconds=round(t2 - t0, 3), total_cpu_seconds=round(cpu(r0, r2), 3),
        ms_per_iteration=round(1e3 * (t1 - t0) / max(p.iterations, 1), 3),
        neighbour_list_builds=p.info["n_builds"],
        neighbour_list_seconds=round(p.info["build_time"], 3),
        peak_rss_mb=round(r2.ru_maxrss / 1024.0, 1),
        z0=round(p.z, 4), z=round(net.z, 6), n_nodes=net.n, n_bonds=len(net.bonds),
        n_rattlers=int(p.rattler.sum()), pressure=p.pressure,
        max_force=p.max_force, force_scale=p.force_scale, ftol=p.ftol,
        fabric_ratio=round(net.info["fabric_ratio"], 4),
        min_degree=net.info["min_degree"],
        loadavg_at_start=[round(x, 2) for x in load0],
        numpy=np.__version__, scipy=scipy.__version__,
    )


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[4096, 40000])
    ap.add_argument("--large", action="store_true", help="also N = 10^6")
    ap.add_argument("--phi", type=float, default=0.88)
    ap.add_argument("--z", type=float, default=3.8)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--kernel", nargs="+", default=["auto"], choices=["auto", "numpy", "numba"],
                    help="force kernel(s) to time (numba: optional compiled pair loop)")
    ap.add_argument("--out", default=str(ROOT / "docs" / "benchmarks" / "packing.json"))
    ap.add_argument("--append", action="store_true",
                    help="keep the results already in --out and add these")
    ap.add_argument("--one", type=int, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.one:
        print(json.dumps(one(a.one, a.phi, a.z, a.seed, a.kernel[0])))
        return 0
    sizes = list(a.sizes) + ([1_000_000] if a.large else [])
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
    out = Path(a.out)
    results = json.loads(out.read_text())["results"] if a.append and out.exists() else []
    for n in sizes:
        for kernel in a.kernel:
            cmd = [sys.executable, __file__, "--one", str(n), "--phi", str(a.phi),
                   "--z", str(a.z), "--seed", str(a.seed), "--kernel", kernel]
            res = json.loads(subprocess.run(cmd, env=env, check=True, capture_output=True,
                                            text=True).stdout.strip().splitlines()[-1])
            results.append(res)
            print(f"N={n:>8d} {res['kernel']:>5s}  iterations={res['iterations']:>6d}  packing "
                  f"{res['packing_seconds']:8.2f} s (cpu {res['packing_cpu_seconds']:.2f})  network "
                  f"{res['network_seconds']:6.2f} s  total {res['total_seconds']:8.2f} s  peak RSS "
                  f"{res['peak_rss_mb']:.0f} MB  z0={res['z0']}  z={res['z']}  "
                  f"load {res['loadavg_at_start'][0]}", flush=True)
            _write(out, argv, results)           # after every run: a killed run keeps the rest
    print(f"wrote {out}")
    return 0


def _write(out: Path, argv, results):
    doc = dict(benchmark="packing + WLKM network (parflow issue 3)",
               command=" ".join(["python3", "benchmarks/bench_packing.py"] + list(argv or sys.argv[1:])),
               machine=dict(platform=platform.platform(), processor=platform.processor() or platform.machine(),
                            cpus=os.cpu_count(), python=platform.python_version()),
               date=time.strftime("%Y-%m-%d %H:%M:%S"),
               results=results)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(doc, indent=2) + "\n")
    os.replace(tmp, out)


if __name__ == "__main__":
    sys.exit(main())
