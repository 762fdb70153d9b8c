"""Benchmark: jammed packing + WLKM network build (issue 3).

    OMP_NUM_THREADS=1 python benchmarks/bench_packing.py            # N = 4096, 40 000
    python benchmarks/bench_packing.py --sizes 4096 40000 100000
    python benchmarks/bench_packing.py --large                      # adds N = 10^6
    python benchmarks/bench_packing.py --sizes 1000000 --kernel numba --threads 1 --append \
        --save-network out/network_N1e6_z3.8.h5 --progress out/bench_packing_1e6.log

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


def one(n: int, phi: float, z: float, seed: int, kernel: str, threads: int | None = None,
        save_network: str | None = None, progress: str | None = None) -> dict:
    sys.path.insert(0, str(ROOT))
    import numpy as np
    import scipy
    from parflow.models import network_build as nb
    from parflow.models import packing as pk

    trace = _Progress(progress, n) if progress else None
    load0 = os.getloadavg()
    r0 = resource.getrusage(resource.RUSAGE_SELF)
    t0 = time.perf_counter()
    p = pk.make_packing(n, phi, seed=seed, kernel=kernel, threads=threads, trace=trace)
    t1 = time.perf_counter()
    r1 = resource.getrusage(resource.RUSAGE_SELF)
    net = nb.network_from_packing(p, z, seed=seed, check_self_stress=False)
    t2 = time.perf_counter()
    r2 = resource.getrusage(resource.RUSAGE_SELF)
    if save_network:
        Path(save_network).parent.mkdir(parents=True, exist_ok=True)
        nb.save_network(save_network, net)
    cpu = lambda a, b: (b.ru_utime + b.ru_stime) - (a.ru_utime + a.ru_stime)  # noqa: E731
    return dict(
        N=n, phi=phi, z_target=z, seed=seed, kernel=_label(p.info["kernel"], p.info.get("threads")),
        threads=p.info.get("threads"), iterations=p.iterations,
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
        loadavg_at_end=[round(x, 2) for x in os.getloadavg()],
        numpy=np.__version__, scipy=scipy.__version__, numba=_numba_version(),
        git_commit=_git_commit(),
        **({"network_file": save_network} if save_network else {}),
    )


def _label(kernel, threads):
    """Kernel name for the tables: "numba (2 threads)" when more than one thread ran."""
    return f"{kernel} ({threads} threads)" if threads and threads > 1 else kernel


def _git_commit():
    try:
        return subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"],
                              capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None


def _numba_version():
    try:
        import numba
    except ImportError:
        return None
    return numba.__version__


class _Progress(list):
    """make_packing trace that appends a line (iteration, max|F|, <f_c>, seconds, load)
    to a log file every ``every`` FIRE iterations."""

    def __init__(self, path: str, n: int, every: int = 2000):
        super().__init__()
        self.path, self.every, self.t0 = path, every, time.perf_counter()
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        with open(path, "a") as fh:
            fh.write(f"# N = {n}: iteration max|F| <f_c> wall_seconds load1\n")

    def append(self, item):
        it, fmax, fscale = item
        if it % self.every == 0:
            with open(self.path, "a") as fh:
                fh.write(f"{it} {fmax:.4e} {fscale:.4e} {time.perf_counter() - self.t0:.1f} "
                         f"{os.getloadavg()[0]:.2f}\n")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[4096, 40000])
    ap.add_argument("--large", action="store_true", help="also N = 10^6")
    ap.add_argument("--phi", type=float, default=0.88)
    ap.add_argument("--z", type=float, default=3.8)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--kernel", nargs="+", default=["auto"], choices=["auto", "numpy", "numba"],
                    help="force kernel(s) to time (numba: optional compiled pair loop)")
    ap.add_argument("--threads", type=int, default=None,
                    help="numba threads for the numba kernel (default: packing's default)")
    ap.add_argument("--save-network", default=None,
                    help="write the network of the (single) N run to this HDF5 file")
    ap.add_argument("--progress", default=None,
                    help="append FIRE progress lines to this file")
    ap.add_argument("--out", default=str(ROOT / "docs" / "benchmarks" / "packing.json"))
    ap.add_argument("--append", action="store_true",
                    help="keep the results already in --out and add these")
    ap.add_argument("--one", type=int, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.one:
        print(json.dumps(one(a.one, a.phi, a.z, a.seed, a.kernel[0], a.threads,
                             a.save_network, a.progress)))
        return 0
    sizes = list(a.sizes) + ([1_000_000] if a.large else [])
    if a.save_network and len(sizes) * len(a.kernel) != 1:
        ap.error("--save-network needs exactly one N and one kernel")
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
    out = Path(a.out)
    results = json.loads(out.read_text())["results"] if a.append and out.exists() else []
    for n in sizes:
        for kernel in a.kernel:
            cmd = [sys.executable, __file__, "--one", str(n), "--phi", str(a.phi),
                   "--z", str(a.z), "--seed", str(a.seed), "--kernel", kernel]
            for flag, val in (("--threads", a.threads), ("--save-network", a.save_network),
                              ("--progress", a.progress)):
                if val is not None:
                    cmd += [flag, str(val)]
            res = json.loads(subprocess.run(cmd, env=env, check=True, capture_output=True,
                                            text=True).stdout.strip().splitlines()[-1])
            results.append(res)
            print(f"N={n:>8d} {res['kernel']:>5s} threads={res['threads']}  "
                  f"iterations={res['iterations']:>6d}  packing "
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
