"""Communicators for ensembles (``parflow.ensemble``): COMM_WORLD split into groups of ranks,
each group a PETSc communicator of its own, and a barrier that waits without spinning.

Here because only ``algebra/`` touches petsc4py (docs/architecture.md, tests/test_layers.py).
"""
from __future__ import annotations

import time

from mpi4py import MPI
from petsc4py import PETSc


def world():
    """PETSc's COMM_WORLD."""
    return PETSc.COMM_WORLD


def split_world(ranks_per_group: int):
    """COMM_WORLD cut into consecutive groups of ``ranks_per_group`` ranks (world ranks
    g*r .. g*r + r - 1 form group g).  Collective on COMM_WORLD; the world size must be a
    multiple of ``ranks_per_group`` (checked by the caller).  Returns (the group's PETSc
    communicator, g, number of groups)."""
    w = MPI.COMM_WORLD
    g = w.Get_rank() // ranks_per_group
    sub = w.Split(color=g, key=w.Get_rank())
    return PETSc.Comm(sub), g, w.Get_size() // ranks_per_group


def idle_barrier(comm, poll_seconds: float = 0.05) -> None:
    """A barrier on ``comm`` that sleeps while it waits (an ensemble's ranks that ran out of
    samples wait here for the others; MPI_Barrier would busy-poll and take their cores)."""
    c = comm.tompi4py()
    if c.Get_size() == 1:
        return
    req = c.Ibarrier()
    while not req.Test():
        time.sleep(poll_seconds)


def max_over(comm, value):
    """The largest ``value`` over the ranks of ``comm`` (collective)."""
    return comm.tompi4py().allreduce(value, op=MPI.MAX)
