"""Reference outputs that hold behaviour fixed while the code is restructured.

Small variants of every scene family (chain, network, suspension), each with a forward and a
reversed leg, omega_min and analyses on, are run through the driver; their run files are
kept in ``tests/reference/NAME.npz`` (every dataset and attribute of the run file, by
path, volatile ones such as wall times left out) and ``tests/test_reference.py`` compares a fresh run with them,
column by column and array by array.

Regenerate (only when a change of behaviour is intended, and say so in the commit):

    . scripts/env.sh && .venv/bin/python tests/reference_runs.py

Each reference records the CPU kernels it was made with (:func:`kernels`, e.g. ``openblas
Haswell, numpy AVX2``): another OpenBLAS core sums in another order, and the runs differ at
round-off (which the chain grows to 1e-3), so the comparison first checks that the kernels
are the same (scripts/env.sh pins them on x86-64).
"""
from __future__ import annotations

import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
REFERENCE_DIR = os.path.join(HERE, "reference")

_OUT = '[output]\npath = "{path}"\ncheckpoint_every = 7\n'

SCENES = {
    "chain": """
seed = 11
[model]
name = "chain"
N = 200
epsilon = 0.1
mu = 0
[[protocol.leg]]
direction = "forward"
V2_above = 1e6
[[protocol.leg]]
direction = "reverse"
strain = 0.004
V2_below = 1.0
[observables]
analysis_quantity = "V2"
analysis_per_decade = 1
omega_min_every = 20
snapshot_every = 50
""" + _OUT,
    "network": """
seed = 7
[model]
name = "network"
N = 128
z = 3.8
response_rods = 3
spectrum = "dense"
[[protocol.leg]]
direction = "forward"
sigma_above = 1e4
[[protocol.leg]]
direction = "reverse"
sigma_below = 20
strain = 0.05
[observables]
analysis_quantity = "sigma"
analysis_per_decade = 1
omega_min_every = 10
snapshot_every = 40
""" + _OUT,
    "suspension": """
seed = 3
[model]
name = "suspension"
N = 128
phi = 0.80
response_rods = 2
[[protocol.leg]]
direction = "forward"
strain = 0.05
[[protocol.leg]]
direction = "reverse"
strain = 0.02
[observables]
analysis_strain = 0.025
omega_min_every = 5
snapshot_every = 5
""" + _OUT,
}

# columns and attributes that measure the machine, not the physics
VOLATILE = {"wall", "wall_seconds", "created", "git_commit", "versions", "loadavg_end",
            "restarted", "restart_git_commit", "scene", "scene_settings", "petsc_options",
            "t_lcp", "t_search", "t_update", "parflow_version"}


def run(name: str, path: str) -> str:
    """Run reference scene ``name`` into ``path`` (every rank of COMM_WORLD); its status."""
    from petsc4py import PETSc

    from parflow.run import Run, setup_logging
    from parflow.scene import load_scene
    scene = load_scene(SCENES[name].format(path=path), f"<reference {name}>")
    comm = PETSc.COMM_WORLD
    setup_logging(comm, quiet=True)
    return Run(scene, comm, path, quiet=True).execute()


def flatten(f) -> dict:
    """Every dataset and numeric attribute of an open run file, by path (volatile ones out)."""
    import h5py
    out = {}

    def visit(name, obj):
        if isinstance(obj, h5py.Dataset) and name.split("/")[-1] not in VOLATILE:
            out[name] = obj[()]
        for k, v in obj.attrs.items():
            if k not in VOLATILE:
                out[f"{name}@{k}"] = v
    for k, v in f.attrs.items():
        if k not in VOLATILE:
            out[f"@{k}"] = v
    f.visititems(visit)
    return out


def differences(ref: dict, new: dict) -> dict:
    """Largest relative difference per entry (0.0: bit-identical; inf: changed shape/type)."""
    diffs = {}
    for key in sorted(set(ref) | set(new)):
        if key not in ref or key not in new:
            diffs[key] = float("inf")
            continue
        a, b = np.asarray(ref[key]), np.asarray(new[key])
        if a.shape != b.shape:
            diffs[key] = float("inf")
        elif a.dtype.kind in "fc" or b.dtype.kind in "fc":
            a, b = a.astype(float), b.astype(float)
            same = (a == b) | (np.isnan(a) & np.isnan(b))
            if same.all():
                diffs[key] = 0.0
            else:
                scale = np.maximum(np.abs(a), np.abs(b))
                with np.errstate(invalid="ignore", divide="ignore"):
                    rel = np.where(same, 0.0, np.abs(a - b) / np.where(scale > 0, scale, 1.0))
                diffs[key] = float(np.nanmax(np.where(np.isnan(rel), np.inf, rel)))
        else:
            diffs[key] = 0.0 if np.array_equal(a, b) else float("inf")
    return diffs


def reference_path(name: str) -> str:
    return os.path.join(REFERENCE_DIR, f"{name}.npz")


def load_reference(name: str) -> dict:
    with np.load(reference_path(name), allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


KERNELS_KEY = "_kernels"     # the CPU kernels a reference was recorded with (not a run entry)


def kernels() -> str:
    """The kernels of this process's arithmetic (``parflow.provenance.kernels``): a reference
    holds bit for bit only where the same ones run (scripts/env.sh pins them)."""
    from parflow.provenance import kernels as k
    return k()


def main() -> int:
    import tempfile

    import h5py
    os.makedirs(REFERENCE_DIR, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        for name in SCENES:
            path = os.path.join(tmp, f"{name}.h5")
            status = run(name, path)
            with h5py.File(path, "r") as f:
                flat = flatten(f)
            flat[KERNELS_KEY] = np.array(kernels())
            np.savez_compressed(reference_path(name), **flat)
            print(f"{name}: {status}, {len(flat)} entries -> {os.path.relpath(reference_path(name))}")
    return 0


if __name__ == "__main__":
    import petsc4py
    petsc4py.init(sys.argv[:1])
    sys.exit(main())
