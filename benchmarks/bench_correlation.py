"""Velocity correlation C(r) = <V_i.V_j>/<V^2>: the exact O(N^2) pair sum against the FFT
method (parflow.models.network.velocity_correlation / velocity_correlation_fft).

Systems: N nodes at random (density 0.74, the networks' density) in a cell sheared by
gamma = 0.7 (Lees-Edwards remapping in play), velocities a sum of 30 plane waves periodic in
the cell (correlated over a few a0) plus white noise, so that C(r) has structure to get
wrong; and, with --run-file, the non-affine velocities V_na of a network run (its initial
state and its checkpoint, one force solve each), which have the contact shells of a real
network.  Bins of 0.5 a0 up to half the smallest cell height, as in the analyses.

Each measurement runs in a fresh subprocess; its peak RSS (VmHWM, reset just before the call)
and its RSS before the call (data loaded) are recorded.  Deviations FFT - exact are over the bins
holding >= 100 pairs.  Writes docs/benchmarks/correlation.json (records with the same
system, N, method and scheme are replaced).

    python benchmarks/bench_correlation.py                  # N = 4096, 40 000 both; 10^6 FFT
    python benchmarks/bench_correlation.py --sizes 4096 --no-large
    python benchmarks/bench_correlation.py --run-file out/fig8_network_N40000.h5 --sizes
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
sys.path.insert(0, ROOT)
import results  # noqa: E402  (benchmarks/results.py)

DR = 0.5
MIN_PAIRS = 100


def random_system(n: int, seed: int = 1, gamma: float = 0.7):
    rng = np.random.default_rng(seed)
    L = np.sqrt(n / 0.74)
    h = np.array([[L, gamma * L], [0.0, L]])
    s = rng.random((n, 2))
    x = s @ h.T
    V = 0.5 * rng.standard_normal((n, 2))
    for _ in range(30):
        k = 2 * np.pi * np.linalg.solve(h.T, rng.integers(-5, 6, 2).astype(float))
        V += rng.standard_normal(2)[None, :] * np.cos(x @ k + 2 * np.pi * rng.random())[:, None]
    return s, h, V


def run_file_systems(path: str):
    """(label, s, h, V_na) at the initial state and at the checkpoint of a network run."""
    import h5py
    import petsc4py
    petsc4py.init(sys.argv[:1])
    from petsc4py import PETSc
    from parflow.state import Bonds, State
    from parflow.dynamics.bonded import BondedSystem
    out = []
    with h5py.File(path, "r") as f:
        g, b = f["initial"], f["initial/bonds"]
        st = State(g["s"][()], g["h0"][()], g["E"][()], 0.0,
                   Bonds(b["i"][()], b["j"][()], b["shift"][()], b["l0"][()]))
        cases = [("initial", g["s"][()], 0.0)]
        if "checkpoint" in f:
            cases.append(("checkpoint", f["checkpoint/s"][()],
                          float(f["checkpoint"].attrs["gamma"])))
        for label, s, gamma in cases:
            sysm = BondedSystem(PETSc.COMM_SELF, st)
            F = sysm.evaluate(s, gamma)
            out.append((f"{os.path.basename(path)}, {label} (γ = {gamma:.3f}, σ = {F.sigma:.3g})",
                        s, F.h, F.V_na))
            sysm.destroy()
    return out


def _status_mb(key: str) -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def _reset_peak() -> float:
    """Reset this process's peak RSS (VmHWM; ru_maxrss would keep the parent's, which
    survives exec) to the current RSS, and return that (MB)."""
    with open("/proc/self/clear_refs", "w") as fh:
        fh.write("5")
    return _status_mb("VmRSS")


def one(data: str, method: str, scheme: str, spacing: str, out: str) -> dict:
    """Time one C(r) of the system in ``data`` (npz: s, h, V); C and counts go to ``out``."""
    from parflow.observables import correlation as corr
    d = np.load(data)
    s, h, V = d["s"], d["h"], d["V"]
    rss0 = _reset_peak()
    c0, t0 = time.process_time(), time.perf_counter()
    if method == "exact":
        res = corr.velocity_correlation(s, h, V, DR)
    else:
        res = corr.velocity_correlation_fft(s, h, V, DR, spacing=float(spacing), scheme=scheme)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    peak = _status_mb("VmHWM")
    np.savez(out, C=res["C"], counts=res["counts"])
    rec = dict(N=int(len(s)), method=method, seconds=round(wall, 3), cpu_seconds=round(cpu, 3),
               peak_rss_mb=round(peak, 1), rss_before_mb=round(rss0, 1), bins=int(res["C"].size),
               load=[round(x, 2) for x in os.getloadavg()])
    if method == "fft":
        rec.update(scheme=scheme, grid=[int(m) for m in res["grid"]],
                   eps=round(float(res["eps"]), 4),
                   spacing=round(float(spacing) if float(spacing) > 0
                                 else corr.corr_spacing(h, DR), 4),
                   default_spacing=float(spacing) <= 0,
                   r_exact=res["n_exact"] * DR)
    return rec


def deviation(ex: dict, ff: dict, r_exact: float) -> dict:
    r = (np.arange(ex["C"].size) + 0.5) * DR
    ok = ex["counts"] >= MIN_PAIRS
    far = ok & (r > r_exact)
    dC = np.abs(ff["C"] - ex["C"])
    dn = np.abs(ff["counts"] / np.where(ok, ex["counts"], 1) - 1)
    return dict(max_dC=float(np.max(dC[ok])), max_dC_beyond_r_exact=float(np.max(dC[far])),
                rms_dC_beyond_r_exact=float(np.sqrt(np.mean(dC[far] ** 2))),
                r_of_max_dC=float(r[ok][np.argmax(dC[ok])]),
                max_rel_dcounts_beyond_r_exact=float(np.max(dn[far])),
                exact_bins_identical=bool(np.array_equal(ff["counts"][r < r_exact],
                                                         ex["counts"][r < r_exact])))


def _key(r: dict) -> tuple:
    return r["system"], r["N"], r["method"], r.get("scheme"), r.get("spacing")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="*", default=[4096, 40000],
                    help="random systems timed with both methods")
    ap.add_argument("--large", type=int, nargs="*", default=[1_000_000],
                    help="random systems timed with the FFT only")
    ap.add_argument("--no-large", action="store_true")
    ap.add_argument("--schemes", nargs="+", default=["cic", "ngp"], choices=["cic", "ngp"])
    ap.add_argument("--run-file", nargs="*", default=[],
                    help="network run files (initial state, checkpoint)")
    ap.add_argument("--spacings", type=float, nargs="*", default=[0.2838],
                    help="extra grid spacings (CIC) for the systems that have the exact C(r) "
                         "(default: the spacing the default grid has at N = 10^6)")
    ap.add_argument("--one", nargs=5, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.one:
        print(json.dumps(one(*a.one)))
        return 0
    tmp = tempfile.mkdtemp(prefix="bench_correlation_")
    try:
        return _run(a, tmp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _run(a, tmp: str) -> int:
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    systems = [("random, γ = 0.7", n, True) for n in a.sizes]
    systems += [] if a.no_large else [("random, γ = 0.7", n, False) for n in a.large]
    jobs = []                                  # (label, npz, with exact)
    for label, n, exact in systems:
        path = os.path.join(tmp, f"random_{n}.npz")
        s, h, V = random_system(n)
        np.savez(path, s=s, h=h, V=V)
        jobs.append((label, path, exact))
    for rf in a.run_file:
        for label, s, h, V in run_file_systems(rf):
            path = os.path.join(tmp, f"run_{len(jobs)}.npz")
            np.savez(path, s=s, h=h, V=V)
            jobs.append((label, path, True))
    data = {"benchmark": "velocity correlation C(r): exact pair sum vs FFT", "records": []}
    if os.path.exists(results.path("correlation")):
        with open(results.path("correlation")) as fh:
            data = json.load(fh)
    for label, path, exact in jobs:
        recs, res = [], {}
        runs = ([("exact", "-", 0.0)] if exact else []) + [("fft", sc, 0.0) for sc in a.schemes]
        runs += [("fft", "cic", sp) for sp in a.spacings] if exact else []
        for method, scheme, spacing in runs:
            out = path.replace(".npz", f"_{method}_{scheme}_{spacing}.npz")
            cmd = [sys.executable, os.path.abspath(__file__), "--one", path, method, scheme,
                   str(spacing), out]
            rec = json.loads(subprocess.run(cmd, env=env, check=True, capture_output=True,
                                            text=True).stdout.strip().splitlines()[-1])
            rec["system"] = label
            res[(method, scheme, spacing)] = dict(np.load(out))
            rec["_key"] = (method, scheme, spacing)
            recs.append(rec)
        for rec in recs:
            k = rec.pop("_key")
            if rec["method"] == "fft" and ("exact", "-", 0.0) in res:
                rec.update(deviation(res[("exact", "-", 0.0)], res[k], rec["r_exact"]))
            print(rec, flush=True)
            data["records"] = [r for r in data["records"] if _key(r) != _key(rec)] + [rec]
        data["date"] = time.strftime("%Y-%m-%d %H:%M:%S")
        data["machine"] = dict(platform=platform.platform(), cpus=os.cpu_count(),
                               python=platform.python_version(), numpy=np.__version__)
        data["bin_width"] = DR
        data["min_pairs"] = MIN_PAIRS
        results.write("correlation", data)   # after every system: a killed run keeps the rest
    print(results.path("correlation"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
