"""What selects a network's reversed branch when the reversal is not seeded: the integrator's
own error at the turn, by its direction (docs/benchmarks.md "What selects a network's
reversed branch", after "Integrators on a network").

The network of bench_network_integrators.py (N = 4 096, z = 3.8) is sheared forward with Heun
to sigma = 5e5, then to sigma >= 1e6 (the turn) in steps of at most h (the *window*) with
Heun or with RKC2 held to two stages (``max_stages = 2``: both second-order two-stage steps),
h = 1e-8 and 5e-9; then

* the turn states: the rms and largest node displacement between the RKC2 and the Heun
  state at each h, how it scales with h, and the cosine between the two h's differences (a
  fixed direction if the difference is each method's leading local error, ~h^2);
* the window decides: every combination of approach (to 5e5) and window integrator (h =
  1e-8), each reversed with Heun (steps <= 1e-8 for the first 1e-6 of strain, then Heun's
  defaults): C = dx / d(1/sigma) between sigma = 1e5 and 1e3 on the reversed branch;
* the seed's direction: the Heun turn state (h = 1e-8) displaced by c x (RKC2's turn state -
  Heun's) before the same reversal, c = 0, +-1, +-10 (c = 1 is RKC2's turn state itself, on
  Heun's trajectory).  The displacement goes through the engine's ``perturb`` (replaced here,
  in this process only: the scene's ``perturb`` key draws a random vector instead), then the
  rod lengths are restored as for any seed.

* the resolution (``--part resolution``): the window and the reversal's first 1e-6 both in
  steps <= h, unseeded, h = 1e-8 ... 1.25e-9 for Heun and 1e-8, 2.5e-9 for RKC2: does each
  method's C stay with h, and how does its departure move (a seed ~h^2 moves it by
  ln 4 / rate per halving)?

Writes docs/benchmarks/network_turn_seed.json (``--part resolution`` adds its rows to the
file's other parts, ``--part states`` writes those and keeps the resolution rows).

    python benchmarks/bench_turn_seed.py [--n 4096] [--part all|states|resolution]
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import time

import h5py
import numpy as np

import results  # noqa: E402  (benchmarks/results.py)
from common import FORWARD_IN_TWO, NETWORK_MODEL, network_file  # noqa: E402  (benchmarks/common.py)

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
sys.path.insert(0, ROOT)

from petsc4py import PETSc  # noqa: E402

from bench_network_integrators import reverse_C  # noqa: E402
from parflow.dynamics import engines  # noqa: E402
from parflow.post.chain import reversal_departure  # noqa: E402
from parflow.run import Run  # noqa: E402
from parflow.scene import load_scene  # noqa: E402

SPLIT = 5e5
WINDOW = {"heun": 'method = "heun"',
          "rkc2": 'method = "rkc", max_stages = 2, tol = 0.05'}
APPROACH = {"heun": 'method = "heun"',
            "rkc2": 'method = "rkc"\nmax_stages = 2\ntol = 0.05'}
SEEDS = (0.0, 1.0, -1.0, 10.0, -10.0)
RESOLUTION = (("heun", 1e-8), ("heun", 5e-9), ("heun", 2.5e-9), ("heun", 1.25e-9),
              ("rkc2", 1e-8), ("rkc2", 2.5e-9))
# forward with the approach's integrator to sigma = SPLIT, then in steps <= {h} to the turn
FORWARD = FORWARD_IN_TWO + """integrator = {{ {window}, max_dgamma = {h:g} }}
"""
# the reversal: Heun, resolved for the first 1e-6 of strain; {perturb}: a seed line or ""
BACK = """[[protocol.leg]]
direction = "reverse"
sigma_below = 10
sigma_above = 1e7
strain = 1e-6
{perturb}integrator = {{ method = "heun", max_dgamma = 1e-8 }}
[[protocol.leg]]
direction = "reverse"
sigma_below = 10
sigma_above = 1e7
strain = 1.0
integrator = {{ method = "heun" }}
"""
TAIL = """[integrator]
{approach}
[output]
path = "{path}"
"""


def execute(text: str, path: str) -> dict:
    """Run the scene ``text`` writing ``path``; its time series and last checkpoint state."""
    if os.path.exists(path):
        os.remove(path)
    t = time.perf_counter()
    status = Run(load_scene(text), PETSc.COMM_SELF, path, quiet=True).execute()
    with h5py.File(path) as f:
        ts = f["timeseries"]
        d = {k: ts[k][:] for k in ("gamma", "sigma", "V2", "direction", "strain", "leg")}
        d["s"] = f["checkpoint/s"][:]
    d["status"], d["wall"] = status, time.perf_counter() - t
    return d


def departure(d) -> float:
    """Strain after the turn where the reversed branch first differs by 10 % from the forward
    one at the same gamma (sigma and <V^2> alike: the cell's area is fixed)."""
    return reversal_departure(d, level=math.log(1.1))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=4096)
    ap.add_argument("--folder", default=os.path.join(ROOT, "out", "bench_network_integrators"))
    ap.add_argument("--part", choices=("all", "states", "resolution"), default="all")
    args = ap.parse_args()
    os.makedirs(args.folder, exist_ok=True)
    network = network_file(args.folder, args.n, PETSc.COMM_SELF)
    model = NETWORK_MODEL.format(n=args.n, network=network)
    load_start = os.getloadavg()
    old = {}
    if os.path.exists(results.path("network_turn_seed")):
        import json
        with open(results.path("network_turn_seed")) as fh:
            old = json.load(fh)

    def case(name, window, h, back="", approach="heun"):
        """Forward (the approach's integrator to SPLIT, then ``window`` in steps <= h), then
        ``back`` (the reversal, or nothing); the run's columns and final state."""
        path = os.path.join(args.folder, f"turn_seed_{name}_N{args.n}.h5")
        return execute(model + FORWARD.format(split=SPLIT, window=WINDOW[window], h=h) + back
                       + TAIL.format(approach=APPROACH[approach], path=path), path)

    resolution = old.get("resolution", [])
    if args.part in ("all", "resolution"):
        resolution = []
        for w, h in RESOLUTION:
            back = BACK.replace("max_dgamma = 1e-8", f"max_dgamma = {h:g}")
            d = case(f"res_{w}_{h:g}", w, h, back.format(perturb=""))
            resolution.append(dict(window=w, h=h, status=d["status"], C=reverse_C(d),
                                   departure=departure(d),
                                   gamma_turn=float(d["gamma"][d["direction"] > 0][-1]),
                                   date=time.strftime("%Y-%m-%d %H:%M:%S")))
            print(f"resolution: {resolution[-1]}", flush=True)
    if args.part == "resolution":
        if not old:
            raise SystemExit("--part resolution adds to an existing network_turn_seed.json: "
                             "run --part states (or all) first")
        old["resolution"] = resolution
        results.write("network_turn_seed", old)
        print(f"wrote {results.path('network_turn_seed')}")
        return

    # 1. the turn states
    turns, windows = {}, []
    for h in (1e-8, 5e-9):
        for w in ("heun", "rkc2"):
            d = case(f"{w}_{h:g}", w, h)
            win = d["leg"] == d["leg"].max()
            turns[(w, h)] = d["s"]
            windows.append(dict(window=w, h=h, status=d["status"], steps=int(win.sum()),
                                strain=float(d["strain"][win][-1] - d["strain"][~win][-1]),
                                gamma_turn=float(d["gamma"][-1]), sigma_turn=float(d["sigma"][-1])))
            print(f"turn, window {w}, h = {h:g}: {windows[-1]}", flush=True)
    diffs = {}
    for h in (1e-8, 5e-9):
        n = np.linalg.norm(turns[("rkc2", h)] - turns[("heun", h)], axis=1)
        diffs[h] = (turns[("rkc2", h)] - turns[("heun", h)]).ravel()
        windows.append(dict(window="rkc2 - heun", h=h, rms=float(np.sqrt(np.mean(n ** 2))),
                            max=float(n.max()), participation=float((n ** 2).sum() ** 2 / (n ** 4).sum())))
    a, b = diffs[1e-8], diffs[5e-9]
    scaling = dict(ratio=float(np.linalg.norm(a) / np.linalg.norm(b)),
                   cosine=float(a @ b / np.linalg.norm(a) / np.linalg.norm(b)))
    print(f"RKC2 - Heun at the turn: |d(1e-8)| / |d(5e-9)| = {scaling['ratio']:.2f}, cosine "
          f"{scaling['cosine']:.4f}", flush=True)

    # 2. the window decides (approach x window, h = 1e-8, Heun reversal)
    cross = []
    for ap_ in ("heun", "rkc2"):
        for w in ("heun", "rkc2"):
            d = case(f"cross_{ap_}_{w}", w, 1e-8, BACK.format(perturb=""), approach=ap_)
            cross.append(dict(approach=ap_, window=w, status=d["status"], C=reverse_C(d),
                              departure=departure(d)))
            print(f"approach {ap_}, window {w}: {cross[-1]}", flush=True)

    # 3. the seed's direction: Heun's turn state + c (RKC2's - Heun's), h = 1e-8
    vec = turns[("rkc2", 1e-8)] - turns[("heun", 1e-8)]
    scale = [0.0]

    def along(self, rms, seed, leg):       # in place of the random seed of ``perturb``
        return self.displace(scale[0] * vec)

    random_seed, engines.BondedEngine.perturb = engines.BondedEngine.perturb, along
    seeded = []
    try:
        for c in SEEDS:
            scale[0] = c
            d = case(f"seed_{c:g}", "heun", 1e-8, BACK.format(perturb="perturb = 1e-30\n"))
            seeded.append(dict(c=c, status=d["status"], C=reverse_C(d), departure=departure(d)))
            print(f"seed c = {c:g}: {seeded[-1]}", flush=True)
    finally:
        engines.BondedEngine.perturb = random_seed
    results.write("network_turn_seed", dict(
        benchmark="bench_turn_seed.py", n=args.n, split=SPLIT, date=time.strftime("%Y-%m-%d %H:%M:%S"),
        load_start=load_start, windows=windows, scaling=scaling, cross=cross, seeded=seeded,
        resolution=resolution))
    print(f"wrote {results.path('network_turn_seed')}")


if __name__ == "__main__":
    main()
