"""Ensemble throughput (docs/ensembles.md): two samples of a chain scene on two ranks
(``mpirun -n 2 python -m parflow.shear scene --samples 2``) against the same two samples run
one after the other on one rank (``--samples 2``, serial), against one sample alone
(``--samples 1``) and against a plain run of the scene (no ensemble).

    python benchmarks/bench_ensemble.py [--N 30000] [--V2 1e7] [--queue 6] # -> docs/benchmarks/ensemble.json
    python benchmarks/bench_ensemble.py --max-steps 1500   # -> docs/benchmarks/ensemble_equal_work.json

Target (the ensemble issue): 2 samples on 2 ranks in <= 1.05x the wall time of one sample
alone, i.e. >= 1.9x the throughput of running them one by one.  The two samples have
different seeds, so their step counts differ: the comparison that does not depend on that is
the throughput ratio (serial one-by-one wall / 2-rank wall, the same work).  The overhead per
sample is the job's wall time minus the time inside the sample's own run loop
(``wall_seconds`` of its file), and the ensemble's own cost is the K = 1 job's wall time
minus the plain run's.  CPU seconds of each job (every rank) show the work apart from how
the machine was shared.  The machine's load average is recorded: on 2 cores shared with other
jobs the ranks do not get a core each.

``--max-steps S``: every run stops after S steps (status ``budget``, a finished sample), so
the samples do equal work whatever their seeds: the throughput ratio then measures what the
ensemble machinery and the sharing of the machine cost, without the unequal samples.
"""
from __future__ import annotations

import argparse
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time

import h5py

import results

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

SCENE = """\
title = "ensemble benchmark: chain N={N}, forward to <V^2> = {V2:g}"
seed = 1
[model]
name = "chain"
N = {N}
epsilon = 0.1
mu = 0
[[protocol.leg]]
direction = "forward"
V2_above = {V2:g}
"""


CPU = []      # CPU seconds (user + system, every process of the job) of each timed command


def timed(cmd) -> float:
    """Wall seconds of ``cmd``; its CPU seconds (children's rusage, the ranks included: mpirun
    waits for them) are appended to CPU."""
    env = dict(os.environ, PYTHONPATH=ROOT)
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.monotonic()
    res = subprocess.run(cmd, capture_output=True, text=True, env=env)
    dt = time.monotonic() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    CPU.append(r1.ru_utime - r0.ru_utime + r1.ru_stime - r0.ru_stime)
    if res.returncode != 0:
        sys.exit(f"bench_ensemble: {' '.join(cmd)} failed ({res.returncode}):\n{res.stderr}")
    return dt


def sample_info(folder: str, k: int) -> dict:
    with h5py.File(os.path.join(folder, "ensemble.h5")) as f:
        cpu = float(f["cpu_seconds"][k])          # the sample's own CPU (its rank)
    with h5py.File(os.path.join(folder, f"sample_{k:04d}.h5")) as f:
        return dict(steps=int(f.attrs["steps"]), wall_seconds=float(f.attrs["wall_seconds"]),
                    sample_cpu_seconds=cpu, seed=int(f.attrs["sample_seed"]))


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--N", type=int, default=30000)
    ap.add_argument("--V2", type=float, default=1e7)
    ap.add_argument("--queue", type=int, default=0, help="also K samples (a queue: K/2 per "
                    "rank) on 2 ranks against the same K one by one; 0: not run")
    ap.add_argument("--bind-to", default="none", help="mpirun --bind-to (none: the ranks may "
                    "move to a free core, which matters on a machine shared with other jobs)")
    ap.add_argument("--max-steps", type=int, default=0, help="stop every run after this many "
                    "steps (equal work per sample); 0: the scene's own end")
    ap.add_argument("--note", default="", help="how the machine was shared (recorded)")
    args = ap.parse_args()
    py = sys.executable
    mpirun = shutil.which("mpirun") or "mpirun"
    d = tempfile.mkdtemp(prefix="bench_ensemble_")
    try:
        scene = os.path.join(d, "scene.toml")
        with open(scene, "w") as fh:
            fh.write(SCENE.format(N=args.N, V2=args.V2))
        opts = ["--quiet", "--no-plots"] + (["--max-steps", str(args.max_steps)] if args.max_steps else [])
        shear = [py, "-m", "parflow.shear", scene]
        load0 = os.getloadavg()
        t_one = timed(shear + ["--samples", "1", "--output", os.path.join(d, "one")] + opts)
        plain_scene = os.path.join(d, "plain.toml")      # sample 0 as a plain run
        with open(plain_scene, "w") as fh:
            fh.write(SCENE.format(N=args.N, V2=args.V2).replace(
                "seed = 1", f"seed = {sample_info(os.path.join(d, 'one'), 0)['seed']}"))
        t_plain = timed([py, "-m", "parflow.shear", plain_scene, "--output",
                         os.path.join(d, "plain.h5")] + opts)
        CPU[0], CPU[1] = CPU[1], CPU[0]                  # (plain first, as in the record)
        t_serial = timed(shear + ["--samples", "2", "--output", os.path.join(d, "serial")] + opts)
        t_two = timed([mpirun, "-n", "2", "--bind-to", args.bind_to] + shear + ["--samples", "2", "--output",
                                                     os.path.join(d, "two")] + opts)
        queue = None
        if args.queue > 0:
            K = args.queue
            t_qs = timed(shear + ["--samples", str(K), "--output", os.path.join(d, "qserial")] + opts)
            t_q2 = timed([mpirun, "-n", "2", "--bind-to", args.bind_to] + shear + [
                "--samples", str(K), "--output", os.path.join(d, "qtwo")] + opts)
            qs = [sample_info(os.path.join(d, "qserial"), k) for k in range(K)]
            q2 = [sample_info(os.path.join(d, "qtwo"), k) for k in range(K)]
            queue = dict(samples=K, serial_job_seconds=t_qs, serial_cpu_seconds=CPU[4],
                         two_ranks_job_seconds=t_q2, two_ranks_cpu_seconds=CPU[5],
                         throughput_ratio=t_qs / t_q2,
                         steps=[s["steps"] for s in qs],
                         same_steps_on_two_ranks=[s["steps"] for s in q2] == [s["steps"] for s in qs],
                         sample_cpu_ratio_two_ranks_vs_serial=sum(
                             s["sample_cpu_seconds"] for s in q2) / sum(s["sample_cpu_seconds"] for s in qs))
        load1 = os.getloadavg()
        one = sample_info(os.path.join(d, "one"), 0)
        serial = [sample_info(os.path.join(d, "serial"), k) for k in range(2)]
        two = [sample_info(os.path.join(d, "two"), k) for k in range(2)]
    finally:
        shutil.rmtree(d, ignore_errors=True)
    longest = max(s["wall_seconds"] for s in serial)
    overhead_one = t_one - one["wall_seconds"]
    # CPU model of an unshared machine (each rank a core of its own; a CPU-bound rank's wall
    # time is its CPU time): a job is its fixed CPU (start-up, index, summary) + its longest
    # sample; 2 samples on 2 ranks against the longer of the two alone, and against both
    # one by one
    fixed = CPU[1] - one["sample_cpu_seconds"]
    alone = fixed + max(s["sample_cpu_seconds"] for s in serial)
    cpu_two = fixed + max(s["sample_cpu_seconds"] for s in two)
    cpu_serial = fixed + sum(s["sample_cpu_seconds"] for s in serial)
    data = dict(
        date=time.strftime("%Y-%m-%d %H:%M"),
        scene=dict(model="chain", N=args.N, V2_above=args.V2, max_steps=args.max_steps),
        machine=dict(cores=os.cpu_count(), load_before=load0, load_after=load1, note=args.note),
        mpirun_bind_to=args.bind_to,
        plain_run=dict(job_seconds=t_plain, cpu_seconds=CPU[0]),
        one_sample=dict(job_seconds=t_one, cpu_seconds=CPU[1], **one),
        serial_two=dict(job_seconds=t_serial, cpu_seconds=CPU[2], samples=serial),
        two_ranks_two=dict(job_seconds=t_two, cpu_seconds=CPU[3], samples=two),
        throughput_ratio=t_serial / t_two,
        wall_ratio_vs_longest_sample=t_two / (overhead_one + longest),
        cpu_model=dict(fixed_cpu_seconds=fixed, two_ranks_wall_estimate=cpu_two,
                       longer_sample_alone_estimate=alone,
                       throughput_ratio=cpu_serial / cpu_two,
                       wall_ratio_vs_longer_sample=cpu_two / alone,
                       sample_cpu_ratio_two_ranks_vs_serial=[
                           t["sample_cpu_seconds"] / s["sample_cpu_seconds"] for t, s in zip(two, serial)],
                       note="unshared machine, each rank a core: wall = CPU (a model, not a "
                            "measurement)"),
        queue=queue,
        overhead_per_sample_seconds=overhead_one,
        ensemble_machinery_seconds=t_one - t_plain,
        target=dict(throughput_ratio_at_least=1.9, wall_ratio_at_most=1.05),
    )
    out = results.write("ensemble_equal_work" if args.max_steps else "ensemble", data)
    if queue:
        print(f"queue of {queue['samples']} samples: one by one {queue['serial_job_seconds']:.1f} s, "
              f"on 2 ranks {queue['two_ranks_job_seconds']:.1f} s: throughput "
              f"x{queue['throughput_ratio']:.2f}")
    print(f"one sample alone {t_one:.1f} s ({one['steps']} steps, {one['wall_seconds']:.1f} s in "
          f"the run loop); 2 samples one by one {t_serial:.1f} s; 2 samples on 2 ranks "
          f"{t_two:.1f} s: throughput x{data['throughput_ratio']:.2f}, wall ratio against the "
          f"longer sample alone {data['wall_ratio_vs_longest_sample']:.3f}; overhead per sample "
          f"{overhead_one:.2f} s (the ensemble's own {t_one - t_plain:+.2f} s); CPU s: plain "
          f"{CPU[0]:.1f}, one {CPU[1]:.1f}, serial two {CPU[2]:.1f}, 2 ranks two {CPU[3]:.1f} (CPU "
          f"model: throughput x{cpu_serial / cpu_two:.2f}, wall ratio {cpu_two / alone:.3f}); load "
          f"{load0[0]:.1f} -> {load1[0]:.1f}; wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
