"""Benchmark: jammed packing + WLKM network build (issue 3).

    OMP_NUM_THREADS=1 python benchmarks/bench_packing.py            # N = 4096, 40 000
    python benchmarks/bench_packing.py --sizes 4096 40000 100000
    python benchmarks/bench_packing.py --large                      # adds N = 10^6
    python benchmarks/bench_packing.py --sizes 1000000 --kernel numba --threads 1 --append \
        --save-network out/network_N1e6_z3.8.h5 --progress out/bench_packing_1e6.log
    python benchmarks/bench_packing.py --passes                     # 2D vs nD passes, N = 40 000

Each N runs in a fresh subprocess so that its peak RSS (resource.getrusage ru_maxrss) is
its own.  Results (N, FIRE iterations, seconds wall and CPU, peak RSS, z0, z, ...) go to
docs/benchmarks/packing.json (rewritten after every run; --append keeps earlier
results; the load average is recorded because
the machine may be shared: CPU seconds are the steadier number).

--passes [N] times each d = 2 pass of the compiled kernel (parflow/packing/pairs_numba.py)
against its nD twin on one random state of N (default 40 000) discs at --phi, one
numba thread, CPU milliseconds per call (min and median over rounds), checks that both give
the same bits, and prints the table (nothing written): the measurement that decides which
2D passes are kept.
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
    from parflow.packing import fire as pk

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


def passes(n: int, phi: float, seed: int, rounds: int = 9) -> list[tuple]:
    """(pass, 2D ms, nD ms, same bits) per pass; see the module docstring (--passes)."""
    sys.path.insert(0, str(ROOT))
    import numpy as np
    from parflow.packing import fire, pairs
    nbk = pairs.numba_kernels()
    rng = np.random.default_rng(seed)
    radii = fire.binary_radii(n, rng=rng)
    box = np.full(2, fire.box_side(radii, phi, 2))
    s = rng.random((n, 2))
    order = fire.morton_order(s)
    s, radii = s[order], radii[order]
    X = np.ascontiguousarray((s * box).T)
    old = nbk.set_threads(1)
    half = pairs.pair_list(radii, box, 0.4, "numba", 1)
    Xh = half.build(X.copy())
    full = pairs.pair_list(radii, box, 0.4, "numba", 1)
    full.full = True                             # the gather's full list, run on one thread
    Xf = full.build(X.copy())
    V = 0.01 * (rng.random(Xh.shape) - 0.5)
    F = np.empty_like(Xh)
    w, wf = half._work, full._work
    nc = np.maximum(np.floor(box / (half.cut * (1.0 + 1e-8))), 1).astype(np.int64)
    sw, ss = np.empty_like(Xh), np.empty_like(Xh)
    nbk._wrap(Xh, box, sw, ss)
    cell, start, members, table = nbk._cells(ss, nc, True)
    cnt, ptr = np.empty(n, np.int64), half.indptr.copy()
    nbr, none = np.empty(int(ptr[-1]), np.int32), np.empty(0, np.int32)
    Xu, Vu = Xh.copy(), V.copy()

    def search(fn, arg):
        def run():
            fn(sw, radii, box, 0.4, cell, start, members, arg, False, ptr, none, cnt)
            fn(sw, radii, box, 0.4, cell, start, members, arg, False, ptr, nbr, cnt)
        return run

    def update(fn):
        return lambda: fn(Xu, Vu, F, 1e-6, 5e-7, False, True, 0.9, 0.01, w.part1)

    cases = [
        ("cell search (count + fill)", search(nbk._search2, nc), search(nbk._search, table),
         lambda: (nbr.copy(), cnt.copy())),
        ("step, pair loop (half list)",
         lambda: nbk._step2_scatter(Xh, V, F, radii, half.hptr, half.rows, half.nbr, box, 0.1,
                                    w.part, w.tx, w.ty, w.ts),
         lambda: nbk._step_nd_scatter(Xh, V, F, radii, half.indptr, half.nbr, box, 0.1, w.part,
                                      False),
         lambda: (F.copy(), w.part.copy())),
        ("step, gather (full list)",
         lambda: nbk._step2_gather(Xf, V, F, radii, full.indptr, full.rows, full.nbr, box, 0.1,
                                   wf.part, wf.scratch),
         lambda: nbk._step_nd_gather(Xf, V, F, radii, full.indptr, full.nbr, box, 0.1, wf.part,
                                     True),
         lambda: (F.copy(), wf.part.copy())),
        ("update", update(nbk._update2), update(nbk._update), lambda: (w.part1.copy(),)),
    ]
    rows = []
    try:
        for name, f2, fn, result in cases:
            out = []
            for f in (f2, fn):
                Xu[:], Vu[:] = Xh, V                 # the update works in place: same start
                f()
                out.append(result() + (Xu.copy(), Vu.copy()))
            same = all(np.array_equal(x, y) for x, y in zip(*out))
            rows.append((name, _times(f2, rounds), _times(fn, rounds), same))
    finally:
        nbk.set_threads(old)
    return rows


def _times(fn, rounds: int, inner: int = 5):
    """(min, median) CPU milliseconds per call of fn over ``rounds`` rounds."""
    import numpy as np
    t = []
    for _ in range(rounds):
        c0 = time.process_time()
        for _ in range(inner):
            fn()
        t.append((time.process_time() - c0) / inner * 1e3)
    return float(np.min(t)), float(np.median(t))


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
    ap.add_argument("--passes", type=int, nargs="?", const=40000, metavar="N",
                    help="time the 2D passes of the compiled kernel against the nD ones on N "
                         "discs (default 40 000)")
    ap.add_argument("--one", type=int, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.passes:
        n = a.passes
        print(f"N = {n}, phi = {a.phi}, one numba thread: CPU ms per call (min / median)")
        for name, t2, tn, same in passes(n, a.phi, a.seed):
            print(f"  {name:28s} 2D {t2[0]:7.3f} / {t2[1]:7.3f}   nD {tn[0]:7.3f} / {tn[1]:7.3f}"
                  f"   nD/2D {tn[0] / t2[0]:4.2f}   same bits: {same}")
        return 0
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
