"""What a flush of the run file costs as the file grows: the old scheme (copy FILE, append,
rename: ``RunWriter(shadow=False)``) against the twin-file scheme (append to the twin in
place, rename, append again to the old FILE: ``RunWriter``).  Synthetic run files of an
N-node network (initial state; s, V_na: N x 2; tau: 2N rods): rounds of three flushes, one
that grows the file (200 rows of 25 columns, a snapshot, the checkpoint replaced), a timed
flush (200 rows) and a checkpoint's flush (200 rows, the checkpoint); each timed against the
file's size.  Both schemes fsync what they publish.  Writes
docs/benchmarks/flush.json.

    python benchmarks/bench_flush.py [--folder out/bench_flush] [--sizes 100000,1000000]
                                     [--flushes 24,10]
"""
from __future__ import annotations

import argparse
import os
import shutil
import sys
import time

import numpy as np

import results  # noqa: E402  (benchmarks/results.py)

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
sys.path.insert(0, ROOT)

COLUMNS = 25
ROWS = 200


def series(folder: str, n: int, flushes: int, shadow: bool) -> list[dict]:
    """``flushes`` rounds, each of three flushes timed: ``grow`` (rows, a snapshot and the
    checkpoint: the file grows by one snapshot), ``rows`` (200 rows only: a timed flush) and
    ``checkpoint`` (200 rows and the checkpoint: a checkpoint's flush)."""
    from parflow.io import RunWriter
    path = os.path.join(folder, f"{'twin' if shadow else 'copy'}_{n}.h5")
    rng = np.random.default_rng(1)
    w = RunWriter(path, shadow=shadow)
    w.create(dict(status="running", scene="x = 1\n" * 50),
             {"initial": (dict(s=rng.random((n, 2)), h0=np.eye(2), E=np.eye(2),
                               bonds=dict(i=np.arange(2 * n), j=np.arange(2 * n),
                                          shift=np.zeros((2 * n, 2), dtype=np.int64),
                                          l0=np.ones(2 * n))), {})})
    out, step = [], 0
    for k in range(flushes):
        for kind in ("grow", "rows", "checkpoint"):
            for _ in range(ROWS):
                w.append({f"q{c}": float(step) for c in range(COLUMNS)} | dict(step=step))
                step += 1
            s, tau = rng.random((n, 2)), rng.random(2 * n)
            batch = ROWS * (COLUMNS + 1) * 8
            if kind == "grow":
                w.add_group(f"snapshots/{step - 1:08d}", dict(s=s, V_na=rng.random((n, 2)), tau=tau),
                            dict(step=step - 1))
                batch += 2 * s.nbytes + tau.nbytes
            if kind != "rows":
                w.set_checkpoint(dict(s=s, tau=tau), dict(step=step - 1, n_rows=step))
                batch += s.nbytes + tau.nbytes
            size = os.path.getsize(path)
            copies = w.copies
            t = time.perf_counter()
            w.flush()
            dt = time.perf_counter() - t
            out.append(dict(scheme="twin" if shadow else "copy", N=n, round=k, kind=kind,
                            file_mb=round(size / 1e6, 2), batch_mb=round(batch / 1e6, 3),
                            seconds=round(dt, 4), copied=w.copies > copies,
                            disk_mb=round(sum(os.path.getsize(p) for p in (path, w.tmp)
                                              if os.path.exists(p)) / 1e6, 1)))
            print(out[-1], flush=True)
    w.close(status="complete")
    os.remove(path)
    return out


def summary(rows: list[dict]) -> list[dict]:
    """Per N, scheme and kind of flush (whole copies left out for the twin: its first
    flush): the median seconds over the first and the last third of the rounds (small and
    large file), and the least-squares slope of seconds against file size (s per GB)."""
    out = []
    for key in sorted({(r["N"], r["kind"], r["scheme"]) for r in rows}):
        rs = [r for r in rows if (r["N"], r["kind"], r["scheme"]) == key
              and not (r["scheme"] == "twin" and r["copied"])]
        x = np.array([r["file_mb"] for r in rs]) / 1e3
        y = np.array([r["seconds"] for r in rs])
        third = max(1, len(rs) // 3)
        out.append(dict(N=key[0], kind=key[1], scheme=key[2], flushes=len(rs),
                        batch_mb=rs[-1]["batch_mb"],
                        file_mb_small=float(np.median(x[:third])) * 1e3,
                        file_mb_large=float(np.median(x[-third:])) * 1e3,
                        seconds_small=float(np.median(y[:third])),
                        seconds_large=float(np.median(y[-third:])),
                        seconds_per_gb=round(float(np.polyfit(x, y, 1)[0]), 3) if len(rs) > 2 else None,
                        disk_mb_last=rs[-1]["disk_mb"]))
    return out


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--folder", default=os.path.join(ROOT, "out", "bench_flush"))
    p.add_argument("--sizes", default="100000,1000000")
    p.add_argument("--flushes", default="24,10")
    args = p.parse_args()
    os.makedirs(args.folder, exist_ok=True)
    rows = []
    for n, k in zip([int(x) for x in args.sizes.split(",")], [int(x) for x in args.flushes.split(",")]):
        for shadow in (False, True):
            rows += series(args.folder, n, k, shadow)
    fs_type = "?"
    with open("/proc/mounts") as fh:      # the file system under the folder (longest mount point)
        best = ""
        for line in fh:
            dev, mnt, typ = line.split()[:3]
            if os.path.abspath(args.folder).startswith(mnt) and len(mnt) > len(best):
                best, fs_type = mnt, f"{typ} ({dev})"
    data = dict(benchmark="run-file flush cost against file size: copy-every-flush vs twin file",
                folder=os.path.relpath(os.path.abspath(args.folder), ROOT), fs=fs_type,
                rows=rows, summary=summary(rows), date=time.strftime("%Y-%m-%d %H:%M:%S"),
                load=os.getloadavg(), cpus=os.cpu_count())
    results.write("flush", data)
    shutil.rmtree(args.folder, ignore_errors=True)
    for s in data["summary"]:
        print(s)


if __name__ == "__main__":
    main()
