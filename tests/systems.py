"""Small random bonded systems, dense reference operators and a scene runner for the tests."""
import numpy as np

from parflow.geometry import velocity_gradient
from parflow.state import Bonds, State


def random_bonded_state(n=30, extra=6, flow="shear", gamma=0.3, seed=1, d=2):
    """A random tree on ``n`` nodes plus ``extra`` random bonds, random image shifts in
    {-1, 0, 1}^d, in a non-square cell (generically no state of self-stress)."""
    rng = np.random.default_rng(seed)
    j = np.concatenate([np.arange(1, n), rng.integers(0, n, extra)])
    i = np.concatenate([rng.integers(0, np.arange(1, n)), rng.integers(0, n, extra)])
    i = np.where(i == j, (j + 1) % n, i)
    shift = rng.integers(-1, 2, (i.size, d))
    s = rng.random((n, d))
    h0 = np.diag(np.linspace(5.0, 4.0, d))
    st = State(s, h0, velocity_gradient(flow, d), gamma, Bonds(i, j, shift, np.ones(i.size)))
    r = (s[j] + shift - s[i]) @ st.h.T
    st.bonds.l0 = np.linalg.norm(r, axis=1)
    return st


def dense_operators(st):
    """Dense S, N = S S^T and b = n . E r from first principles (loops are fine here)."""
    bd, h, E = st.bonds, st.h, st.E
    d, N = st.d, st.n
    r = (st.s[bd.j] + bd.shift - st.s[bd.i]) @ h.T
    n = r / np.linalg.norm(r, axis=1)[:, None]
    S = np.zeros((len(bd), d * N))
    for a in range(len(bd)):
        S[a, d * bd.i[a]:d * bd.i[a] + d] -= n[a]
        S[a, d * bd.j[a]:d * bd.j[a] + d] += n[a]
    b = np.einsum("ad,ad->a", n, r @ E.T)
    return S, S @ S.T, b, r, n


def local_rows_dense(mat, ncols):
    """This rank's rows of a PETSc AIJ Mat as a dense array."""
    indptr, indices, data = mat.getValuesCSR()
    lo, hi = mat.getOwnershipRange()
    out = np.zeros((hi - lo, ncols))
    for k in range(hi - lo):
        out[k, indices[indptr[k]:indptr[k + 1]]] = data[indptr[k]:indptr[k + 1]]
    return lo, hi, out


def run_scene(scene, comm=None, **kw):
    """Run a loaded scene through the driver, quietly; returns the run's status."""
    from petsc4py import PETSc

    from parflow.run import Run, setup_logging
    comm = comm or PETSc.COMM_WORLD
    setup_logging(comm, quiet=True)
    return Run(scene, comm, scene["output"]["path"], quiet=True, **kw).execute()


# the tiny suspension scene of the ensemble tests (N = 64, 0.2 strain, analyses every 0.05
# over the last 0.1): format with phi and an [ensemble] table (or "")
SUSPENSION_ENSEMBLE_SCENE = """
title = "suspension ensemble test"
seed = 3
[model]
name = "suspension"
N = 64
phi = {phi}
{ensemble}
[[protocol.leg]]
direction = "forward"
strain = 0.2
[observables]
analysis_from_strain = 0.1
analysis_strain = 0.05
omega_min_every = 0
[output]
path = "unused.h5"
"""
