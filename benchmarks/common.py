"""What the network benchmarks share: the shear protocol of bench_network_shear.py (a network
forward to sigma = 1e6 and reversed until sigma <= 10) as a scene template, and the network,
built once per size and saved."""
from __future__ import annotations

import os

# the benchmarks' network (its file from network_file below), {n} and {network} to fill
NETWORK_MODEL = """
seed = 1
[model]
name = "network"
N = {n}
z = 3.8
phi = 0.88
network_file = "{network}"
"""
# {settings}: the case's own tables ([integrator], [solver], ...)
FORWARD_AND_BACK = NETWORK_MODEL + """[[protocol.leg]]
direction = "forward"
sigma_above = 1e6
[[protocol.leg]]
direction = "reverse"
sigma_below = 10
sigma_above = 1e7
strain = 1.0
{settings}
[output]
path = "{path}"
"""

# the forward leg in two: to sigma = {split}, then to the turn (its integrator line follows)
FORWARD_IN_TWO = """[[protocol.leg]]
direction = "forward"
sigma_above = {split:g}
[[protocol.leg]]
direction = "forward"
sigma_above = 1e6
"""
# the protocol with the forward leg split at sigma = {split}: the scene's [integrator]
# ({settings}) up to there, the legs' own integrator keys ({near}, a TOML inline table's
# contents) from there on, through the turn and the reversed leg
FORWARD_SPLIT_AND_BACK = NETWORK_MODEL + FORWARD_IN_TWO + """integrator = {{ {near} }}
[[protocol.leg]]
direction = "reverse"
sigma_below = 10
sigma_above = 1e7
strain = 1.0
integrator = {{ {near} }}
{settings}
[output]
path = "{path}"
"""


# the forward leg's last part, from sigma = {split}, and the reversed leg's first {rstrain} in
# steps of at most {h} ("the turn resolved"); {rkeys}: more keys for the reversed legs (", ..."),
# {rlast}: the last reversed leg's integrator table line (or "")
FORWARD_RESOLVED_AND_BACK = NETWORK_MODEL + FORWARD_IN_TWO + """integrator = {{ max_dgamma = {h:g} }}
[[protocol.leg]]
direction = "reverse"
sigma_below = 10
sigma_above = 1e7
strain = {rstrain:g}
integrator = {{ max_dgamma = {h:g}{rkeys} }}
[[protocol.leg]]
direction = "reverse"
sigma_below = 10
sigma_above = 1e7
strain = 1.0
{rlast}
{settings}
[output]
path = "{path}"
"""


def network_file(folder: str, n: int, comm) -> str:
    """The N-node network of the benchmarks (packing at phi = 0.88, WLKM dilution to z = 3.8,
    seed 1) in ``folder``, built by rank 0 if it is not there yet; collective."""
    path = os.path.join(folder, f"network_N{n}.h5")
    if comm.getRank() == 0 and not os.path.exists(path):
        import time

        from parflow.models.network_build import network_from_packing, save_network
        from parflow.packing.fire import make_packing
        t = time.perf_counter()
        save_network(path, network_from_packing(make_packing(n, phi=0.88, seed=1), 3.8, seed=1))
        print(f"network N = {n}: {time.perf_counter() - t:.1f} s", flush=True)
    comm.tompi4py().Barrier()
    return path
