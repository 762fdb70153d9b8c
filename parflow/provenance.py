"""Provenance of a run file: the git commit of the code and the versions of what it ran on."""
from __future__ import annotations

import ctypes
import functools
import importlib
import os
import subprocess
import sys

import h5py
import numpy as np
import scipy
from mpi4py import MPI

from . import __version__
from .algebra.operators import petsc_version


@functools.lru_cache(maxsize=None)
def git_commit() -> str:
    """The checkout's HEAD (``-dirty`` if modified), read once per process: the code a process
    runs is what it imported, so the samples an ensemble starts later record the commit of
    the process's start, not a HEAD that moved meanwhile."""
    here = os.path.dirname(os.path.abspath(__file__))
    try:
        out = subprocess.run(["git", "-C", here, "rev-parse", "HEAD"], capture_output=True,
                             text=True, timeout=5)
        dirty = subprocess.run(["git", "-C", here, "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=5).stdout.strip()
        return out.stdout.strip() + ("-dirty" if dirty else "") if out.returncode == 0 else "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def kernels() -> str:
    """The CPU kernels the arithmetic ran on: OpenBLAS's core (its dgemm sums in a core's own
    order) and numpy's SIMD extensions in use (scripts/env.sh pins both; docs/conventions.md
    "The same numbers on every machine"), e.g. ``openblas Haswell, numpy AVX2``."""
    try:
        lib = ctypes.CDLL("libopenblas.so.0")
        lib.openblas_get_corename.restype = ctypes.c_char_p
        core = lib.openblas_get_corename().decode()
    except (OSError, AttributeError):
        core = "none"
    simd = []
    for where in ("numpy._core._multiarray_umath", "numpy.core._multiarray_umath"):
        try:      # numpy-private (numpy._core from numpy 2 on)
            m = importlib.import_module(where)
            simd = [k for k in m.__cpu_dispatch__ if m.__cpu_features__.get(k)]
            break
        except (ImportError, AttributeError):
            continue
    top = next((k for k in reversed(simd) if k.startswith("AVX512")), None) or \
        ("AVX2" if "AVX2" in simd else (simd[-1] if simd else "baseline"))
    return f"openblas {core}, numpy {top}"


def versions() -> str:
    """parflow, python, numpy, scipy, h5py, PETSc, MPI (and slepc4py) versions, one line.
    (Imported here, when a run starts: h5py, scipy and mpi4py are not needed before.)"""

    v = dict(parflow=__version__, python=sys.version.split()[0], numpy=np.__version__,
             scipy=scipy.__version__, h5py=h5py.__version__,
             petsc=petsc_version(), mpi=MPI.Get_library_version().split("\n")[0])
    v["kernels"] = kernels()
    try:   # the package version only: importing slepc4py.SLEPc would initialise SLEPc
        import slepc4py  # on this rank alone and make the ranks' finalisation diverge
        v["slepc4py"] = slepc4py.__version__
    except ImportError:
        pass
    return "; ".join(f"{k}={x}" for k, x in v.items())
