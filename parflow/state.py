"""The simulation state: reduced positions, cell, bonds, strain.

Conventions (docs/conventions.md, DESIGN §2):

* ``h`` (d x d): columns are the periodic box vectors; r = h . s.
* The cell is a pure function of the signed strain coordinate ``gamma``:
  h(gamma) = expm(gamma E) . h0.  Reversing the flow means integrating the same
  quasi-static ODE ds/dgamma = h^-1 V_na backwards in gamma.
* Bonds are persistent: (i, j, image shift n, rest length l0) and
  r_ij = h . (s_j + n - s_i).
"""
from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np

from .errors import InputError, Terminated  # noqa: F401  (raised here; imported from here by many)
from .geometry import cell_at


class StopSignals:
    """SIGINT/SIGTERM, taken at step boundaries.

    Outside a run loop a signal raises at once (KeyboardInterrupt / :class:`Terminated`).
    Inside ``with STOPS.deferred():`` the handler only records it, and the loop calls
    :meth:`check` between steps: the exception is raised there, on every rank at the same
    step (one allreduce when there are several ranks), so that the checkpoint written on the
    way out is the state after a whole step and matches the last time-series row.  A second
    signal while one is pending raises at once, mid-step (``mid_step``: no checkpoint is
    written then; on several ranks the run aborts, since the ranks may be anywhere).
    """

    CODES = {1: KeyboardInterrupt, 2: Terminated}

    def __init__(self):
        self.depth = 0
        self.pending = 0

    def _exception(self, code: int, mid_step: bool, collective: bool) -> BaseException:
        # SIGUSR2/SIGUSR1 stand for SIGINT/SIGTERM under mpirun, which forwards only those
        exc = self.CODES[code]("signal SIGINT (or SIGUSR2)" if code == 1 else "signal SIGTERM (or SIGUSR1)")
        exc.mid_step, exc.collective = mid_step, collective
        return exc

    def handle(self, code: int) -> None:
        if self.depth == 0 or self.pending:
            self.pending = 0
            raise self._exception(code, mid_step=self.depth > 0, collective=False)
        self.pending = max(self.pending, code)

    @contextmanager
    def deferred(self):
        self.depth += 1
        try:
            yield self
        finally:
            self.depth -= 1
            if self.depth == 0:
                self.pending = 0   # came during the last step: the run has ended anyway

    def check(self, comm=None) -> None:
        code = self.pending
        if comm is not None and comm.getSize() > 1:
            from mpi4py import MPI      # (several ranks only: mpi4py is loaded then)
            code = comm.tompi4py().allreduce(code, op=MPI.MAX)
        if code:
            self.pending = 0
            raise self._exception(code, mid_step=False, collective=True)


STOPS = StopSignals()


@dataclass
class Bonds:
    """Persistent rods.  ``i``, ``j``: node indices; ``shift``: (Nb, d) integer image
    shifts; ``l0``: rest lengths."""

    i: np.ndarray
    j: np.ndarray
    shift: np.ndarray
    l0: np.ndarray

    def __post_init__(self):
        self.i = np.ascontiguousarray(self.i, dtype=np.int64)
        self.j = np.ascontiguousarray(self.j, dtype=np.int64)
        self.shift = np.ascontiguousarray(self.shift, dtype=np.int64)
        self.l0 = np.ascontiguousarray(self.l0, dtype=np.float64)
        nb = self.i.shape[0]
        if self.j.shape != (nb,) or self.l0.shape != (nb,) or self.shift.ndim != 2 \
                or self.shift.shape[0] != nb:
            raise InputError("bonds: i, j, l0 must have length Nb and shift shape (Nb, d)")

    def __len__(self) -> int:
        return int(self.i.shape[0])

    def validate(self, n_nodes: int) -> None:
        if len(self) == 0:
            raise InputError("the network has no bonds")
        if self.i.min() < 0 or self.j.min() < 0 or max(self.i.max(), self.j.max()) >= n_nodes:
            raise InputError(f"bond node index out of range [0, {n_nodes})")
        self_loop = (self.i == self.j) & ~np.any(self.shift, axis=1)
        if np.any(self_loop):
            raise InputError(f"{int(self_loop.sum())} bond(s) join a node to itself")
        if np.any(self.i == self.j):
            raise InputError("a bond joins a node to its own periodic image: its row of S "
                             "would be zero (make the box larger)")
        if not np.all(np.isfinite(self.l0)) or np.any(self.l0 <= 0):
            raise InputError("bond rest lengths must be finite and positive")


@dataclass
class State:
    """Everything that evolves in a run.

    s:      (N, d) reduced coordinates (not wrapped for bonded models).
    h0:     (d, d) cell at gamma = 0.
    E:      (d, d) velocity gradient of the flow (per unit strain).
    gamma:  signed strain coordinate; h = expm(gamma E) h0.
    bonds:  persistent rods (bonded models).
    radii:  particle radii (suspensions; None for bonded models).
    """

    s: np.ndarray
    h0: np.ndarray
    E: np.ndarray
    gamma: float = 0.0
    bonds: Bonds | None = None
    radii: np.ndarray | None = None
    meta: dict = field(default_factory=dict)

    @property
    def d(self) -> int:
        return int(self.s.shape[1])

    @property
    def n(self) -> int:
        return int(self.s.shape[0])

    @property
    def h(self) -> np.ndarray:
        return cell_at(self.h0, self.E, self.gamma)

    @property
    def volume(self) -> float:
        return float(abs(np.linalg.det(self.h0)))

    def to_groups(self) -> dict:
        """The run file's /initial group (and any saved state): s, h0, E, bonds/{i, j, shift,
        l0}, radii -- the one mapping between a State and HDF5 (``from_groups`` reads it)."""
        arrays = dict(s=self.s, h0=self.h0, E=self.E)
        if self.bonds is not None:
            bd = self.bonds
            arrays["bonds"] = dict(i=bd.i, j=bd.j, shift=bd.shift, l0=bd.l0)
        if self.radii is not None:
            arrays["radii"] = self.radii
        return arrays

    @classmethod
    def from_groups(cls, g: dict, gamma: float = 0.0, meta: dict | None = None) -> "State":
        """The State of a group written by ``to_groups`` (a dict of arrays, as
        ``io.load_group`` gives it), at strain ``gamma``."""
        bonds = None
        if "bonds" in g:
            bd = g["bonds"]
            bonds = Bonds(bd["i"], bd["j"], bd["shift"], bd["l0"])
        return cls(g["s"], g["h0"], g["E"], gamma, bonds, g.get("radii"), meta=dict(meta or {}))

    def copy(self) -> "State":
        return State(self.s.copy(), self.h0.copy(), self.E.copy(), float(self.gamma),
                     None if self.bonds is None else Bonds(self.bonds.i.copy(), self.bonds.j.copy(),
                                                           self.bonds.shift.copy(), self.bonds.l0.copy()),
                     None if self.radii is None else self.radii.copy(), dict(self.meta))


@dataclass(frozen=True)
class Instant:
    """What every analysis and instant hook of a model gets (``models.base``): one instant
    of a run.

    comm:      the run's PETSc communicator
    state:     the State at this instant (current s and gamma)
    F:         the forces there (bonded: dynamics.bonded.Force; contacts: engines.ContactForce)
    system:    bonded models: the BondedSystem, N loaded at this configuration; else None
    scene:     the run's scene (``scene["model"]`` holds the model's parameters)
    direction: the flow direction of the current leg (+1 forward, -1 reversed)
    """

    comm: object
    state: State
    F: object
    system: object | None
    scene: dict
    direction: int = 1
