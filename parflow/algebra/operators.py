"""Rigidity matrix S, affine rates b and N = S S^T as distributed PETSc objects (DESIGN §2-§3).

* S (Nc x dN): row alpha = <ij> holds -n_alpha at particle i and +n_alpha at particle j.
  (S V)_alpha is the rate of change of the length of alpha; (S^T tau)_k is the net
  contact force on particle k.
* N = S S^T (Nc x Nc): N_ab = c_ab (n_a . n_b) with c_ab = sum_k s_ak s_bk the signed
  incidence overlap (c_aa = 2; +-1 for two bonds sharing one particle).

Parallel model: "replicated geometry, distributed algebra".  Every rank holds all positions
and unit vectors; rank p owns a contiguous block of rows (bonds) of S and N.  The sparsity
pattern is built once per bond list (networks: for the whole run) and locked, so the factor's
symbolic analysis is reused and only numeric values change from step to step.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from mpi4py import MPI
from petsc4py import PETSc


def row_ownership(n_rows: int, comm) -> tuple[int, int]:
    """Contiguous block of rows owned by this rank (PETSc's default split)."""
    size, rank = comm.getSize(), comm.getRank()
    q, r = divmod(n_rows, size)
    lo = rank * q + min(rank, r)
    return lo, lo + q + (1 if rank < r else 0)


def incidence(n_nodes: int, i: np.ndarray, j: np.ndarray) -> sp.csr_matrix:
    """Signed incidence B (Nc x N): -1 at i, +1 at j."""
    nb = i.shape[0]
    rows = np.repeat(np.arange(nb), 2)
    cols = np.column_stack([i, j]).ravel()
    vals = np.tile([-1.0, 1.0], nb)
    return sp.csr_matrix((vals, (rows, cols)), shape=(nb, n_nodes))


class RigidityOperators:
    """S and N for a fixed list of pairs (i, j) on ``n_nodes`` nodes in ``d`` dimensions.

    ``update(n)`` refreshes the numeric values from the unit vectors n_alpha (all pairs,
    replicated); the PETSc Mats keep their identity and pattern.
    """

    def __init__(self, comm, n_nodes: int, d: int, i: np.ndarray, j: np.ndarray):
        self.comm = comm
        self.n_nodes, self.d = int(n_nodes), int(d)
        self.nc = int(i.shape[0])
        self.lo, self.hi = row_ownership(self.nc, comm)
        lo, hi = self.lo, self.hi
        nloc = hi - lo
        it = PETSc.IntType
        self._i_all, self._j_all = i, j
        self._n, self._s_fresh = None, False
        self.values_stale = False
        self.loaded_n = None       # the unit vectors whose values N holds (and its factor)
        self._scatter_ld = None    # the rods' ends sorted by node (_ends_by_node)
        self._scatter_dd = None    # ... as a table of each node's rods (its double-double form)

        # --- S pattern: each row has 2d entries, columns sorted --------------------------
        comp = np.arange(d)
        cols = np.concatenate([d * i[lo:hi, None] + comp, d * j[lo:hi, None] + comp], axis=1)
        sign = np.concatenate([-np.ones((nloc, d)), np.ones((nloc, d))], axis=1)
        order = np.argsort(cols, axis=1, kind="stable")
        s_cols = np.take_along_axis(cols, order, axis=1)
        # entry k of row a takes component (order[a,k] mod d) of n_a, with the sign of its end
        self._s_src = (np.arange(nloc)[:, None] * d + order % d).ravel()
        self._s_sign = np.take_along_axis(sign, order, axis=1).ravel()
        self._s_indptr = (2 * d * np.arange(nloc + 1)).astype(it)
        self._s_indices = s_cols.ravel().astype(it)

        # --- N pattern: pairs of bonds sharing a particle (rows of |B_loc| |B|^T) ----------
        # c_ab = [j_a = j_b] + [i_a = i_b] - [j_a = i_b] - [i_a = j_b]  (signed overlap)
        B = abs(incidence(self.n_nodes, i, j))
        P = (B[lo:hi] @ B.T).tocsr()
        P.sort_indices()
        rows = np.repeat(np.arange(lo, hi), np.diff(P.indptr))
        cols = P.indices.astype(np.int64)
        self._n_coef = ((j[rows] == j[cols]).astype(float) + (i[rows] == i[cols])
                        - (j[rows] == i[cols]) - (i[rows] == j[cols]))
        self._n_indptr = P.indptr.astype(it)
        self._n_indices = P.indices.astype(it)
        self._n_rows, self._n_cols = rows, cols

        # --- PETSc objects --------------------------------------------------------------
        # On one rank the Mats are built on arrays of their own (MatCreateSeqAIJWithArrays):
        # an update writes the values in place and assembles (which marks them changed for
        # the factorisation), where MatSetValuesCSR inserts row by row -- 6 ms a refresh at
        # Nc = 1e5, measured, a sixth of a chain step at that size.  Several ranks: copies.
        self._seq = comm.getSize() == 1
        s_vals = np.zeros(self._s_indices.shape[0])
        n_vals = self._n_coef.copy()
        if self._seq:
            self._s_vals, self._n_vals = s_vals, n_vals
            self.S = PETSc.Mat().createAIJWithArrays(
                (nloc, d * self.n_nodes), (self._s_indptr, self._s_indices, s_vals), comm=comm)
            self.N = PETSc.Mat().createAIJWithArrays(
                (nloc, self.nc), (self._n_indptr, self._n_indices, n_vals), comm=comm)
        else:
            self.S = PETSc.Mat().createAIJ(size=((nloc, self.nc), (PETSc.DECIDE, d * self.n_nodes)),
                                           csr=(self._s_indptr, self._s_indices, s_vals), comm=comm)
            self.N = PETSc.Mat().createAIJ(size=((nloc, self.nc), (nloc, self.nc)),
                                           csr=(self._n_indptr, self._n_indices, n_vals), comm=comm)
        for M in (self.S, self.N):
            M.setOption(PETSc.Mat.Option.NEW_NONZERO_LOCATION_ERR, True)
        self.N.setOption(PETSc.Mat.Option.SYMMETRIC, True)
        self.N.setOption(PETSc.Mat.Option.SYMMETRY_ETERNAL, True)
        self.tau, self.rhs = self.N.createVecs()
        self.force, _ = self.S.createVecs()        # dN-vector (columns of S)
        self._scatter, self._force_all = PETSc.Scatter.toAll(self.force)
        self._counts = np.array(comm.tompi4py().allgather(nloc))

    # ------------------------------------------------------------------------------------
    def update(self, n: np.ndarray) -> None:
        """Set the values of N from the unit vectors n (Nc x d, all pairs).  S is refreshed
        lazily (``S_at``): the step loop needs only N and the numpy form of S^T."""
        self._n = n
        self.loaded_n = n
        self._s_fresh = False
        self.values_stale = False
        if self._seq:
            self._n_vals[:] = self._values(n)
        else:
            self.N.setValuesCSR(self._n_indptr, self._n_indices, self._values(n))
        self.N.assemble()

    def _values(self, n: np.ndarray) -> np.ndarray:
        """Entries of the local rows of N for unit vectors n: c_ab n_a . n_b."""
        nT = n.T
        dots = nT[0][self._n_rows] * nT[0][self._n_cols]
        for c in range(1, self.d):
            dots += nT[c][self._n_rows] * nT[c][self._n_cols]
        dots *= self._n_coef
        return dots

    def set_unit_vectors(self, n: np.ndarray) -> None:
        """Take n as the current unit vectors (for S^T) without writing N: the Mat keeps the
        values (and the factor) of an earlier configuration -- ``values_stale`` says so."""
        self._n = n
        self._s_fresh = False
        self.values_stale = True

    def matvec_at(self, n: np.ndarray):
        """x -> N(n) x for replicated x (Nc,), replicated out, with N built from the unit
        vectors n in scipy CSR (the PETSc Mat is not touched)."""
        A = sp.csr_matrix((self._values(n), self._n_indices, self._n_indptr),
                          shape=(self.hi - self.lo, self.nc))
        if self.comm.getSize() == 1:
            return lambda x: A @ x
        mpi = self.comm.tompi4py()

        def mv(x):
            out = np.empty(self.nc)
            mpi.Allgatherv(np.ascontiguousarray(A @ x), [out, self._counts])
            return out
        return mv

    def S_at(self) -> PETSc.Mat:
        """S as a distributed PETSc Mat with the values of the last ``update``."""
        if not self._s_fresh:
            n_loc = self._n[self.lo:self.hi]
            vals = n_loc.ravel()[self._s_src] * self._s_sign
            if self._seq:
                self._s_vals[:] = vals
            else:
                self.S.setValuesCSR(self._s_indptr, self._s_indices, vals)
            self.S.assemble()
            self._s_fresh = True
        return self.S

    def ST_numpy(self, tau: np.ndarray) -> np.ndarray:
        """V = S^T tau (replicated tau and unit vectors): (S^T tau)_i = -sum tau n over bonds
        leaving i + sum tau n over bonds arriving at j.  (N, d)."""
        out = np.empty((self.n_nodes, self.d))
        for c in range(self.d):
            f = tau * self._n[:, c]
            out[:, c] = np.bincount(self._j_all, f, self.n_nodes) - \
                np.bincount(self._i_all, f, self.n_nodes)
        return out

    def residual_extended(self, tau: np.ndarray, b: np.ndarray,
                          n: np.ndarray | None = None) -> np.ndarray:
        """r = -b - S S^T tau (replicated, length Nc) for the unit vectors n (default: the
        current ones), in extended precision, rounded to double at the end.

        Near jamming the residual of a solve computed in double is round-off, ~eps ||N||
        ||tau||, and its component along the softest mode u_1 makes the correction from it
        wrong by ~eps cond(N) along u_1 -- the part of tau that carries sigma (docs/solvers.md,
        "The sigma identity near jamming").  Here the cancellation between b and S S^T tau
        happens in numpy's long double where that is wider than double (x86-64: 64-bit
        mantissa, eps 1.1e-19; aarch64 Linux: IEEE quad), and in double-double arithmetic
        (error-free sums and products of doubles, ~1e-32) where it is not (Windows, Apple
        silicon), so one correction with the factor of N brings tau to what double can hold.
        The product is taken with S S^T of the double unit vectors themselves -- the
        operator whose identities (V_na = S^T tau, sigma = |V_na|^2 / Omega = -<tau|b> /
        Omega) are checked -- not with the rounded entries of N."""
        n = self._n if n is None else n
        if not extended_precision_available():
            return self._residual_double_double(tau, b, n)
        order, nodes, starts, _ = self._ends_by_node()
        i, j = self._i_all, self._j_all
        t = np.asarray(tau, dtype=np.longdouble)
        w = np.zeros(self.nc, dtype=np.longdouble)
        u = np.zeros(self.n_nodes, dtype=np.longdouble)
        for c in range(self.d):
            nc_ = n[:, c].astype(np.longdouble)
            f = t * nc_
            # (S^T tau)_c = B^T (tau n_c): + at j, - at i, summed per node
            u[nodes] = np.add.reduceat(np.concatenate([f, -f])[order], starts)
            w += nc_ * (u[j] - u[i])
        return (-np.asarray(b, dtype=np.longdouble) - w).astype(float)

    def _ends_by_node(self):
        """The rods' ends (j: +, then i: -) sorted by node, stably: (order into the 2 Nc ends,
        the nodes with a rod, where each node's run starts, its length).  Built on first use:
        only runs near jamming need it."""
        if self._scatter_ld is None:
            ends = np.concatenate([self._j_all, self._i_all])
            order = np.argsort(ends, kind="stable")
            nodes, starts, counts = np.unique(ends[order], return_index=True, return_counts=True)
            self._scatter_ld = (order, nodes, starts, counts)
        return self._scatter_ld

    def _residual_double_double(self, tau: np.ndarray, b: np.ndarray, n: np.ndarray) -> np.ndarray:
        """:meth:`residual_extended` in double-double arithmetic (for platforms whose long
        double is double): every product split exactly (Dekker), every sum carried as an
        unevaluated pair hi + lo.  The node sums of S^T run over a table of each node's
        incident rods (one column per incidence, zeros beyond a node's degree)."""
        if self._scatter_dd is None:
            nc = self.nc
            order, nodes, starts, counts = self._ends_by_node()
            shape = (nodes.size, int(counts.max()))
            cell = np.ravel_multi_index((np.repeat(np.arange(nodes.size), counts),
                                         np.arange(order.size) - np.repeat(starts, counts)), shape)
            sign = np.where(order < nc, 1.0, -1.0)
            self._scatter_dd = (order % nc, sign, nodes, cell, shape)
        src, sign, nodes, cell, shape = self._scatter_dd
        i, j = self._i_all, self._j_all
        tau = np.asarray(tau, dtype=float)
        wh, wl = np.zeros(self.nc), np.zeros(self.nc)
        uh, ul = np.zeros(self.n_nodes), np.zeros(self.n_nodes)
        for c in range(self.d):
            nc_ = np.ascontiguousarray(n[:, c], dtype=float)
            fh, fl = _two_prod(tau, nc_)
            H, L = np.zeros(shape), np.zeros(shape)
            H.flat[cell] = fh[src] * sign          # (a sign flip is exact)
            L.flat[cell] = fl[src] * sign
            ah, al = H[:, 0].copy(), L[:, 0].copy()
            for k in range(1, shape[1]):            # over the incidences of a node (<= degree)
                ah, al = _dd_add(ah, al, H[:, k], L[:, k])
            uh[nodes], ul[nodes] = ah, al
            dh, dl = _dd_add(uh[j], ul[j], -uh[i], -ul[i])
            ph, pl = _two_prod(nc_, dh)
            wh, wl = _dd_add(wh, wl, ph, pl + nc_ * dl)
        rh, rl = _dd_add(-np.asarray(b, dtype=float), np.zeros(self.nc), -wh, -wl)
        return rh + rl

    @property
    def norm_bound(self) -> float:
        """An upper bound of ||N||_inf, valid for any unit vectors: max_a sum_b |c_ab|."""
        local = float(np.max(np.add.reduceat(np.abs(self._n_coef), self._n_indptr[:-1]))) \
            if self._n_coef.size else 0.0
        return self.comm.tompi4py().allreduce(local, op=_mpi_max())

    def set_local(self, vec: PETSc.Vec, values: np.ndarray) -> PETSc.Vec:
        """Fill a row-distributed Vec from a replicated array of length Nc."""
        vec.setArray(values[self.lo:self.hi])
        return vec

    def gather(self, vec: PETSc.Vec) -> np.ndarray:
        """All entries of a row-distributed Vec on every rank (Nc,)."""
        if self.comm.getSize() == 1:
            return vec.getArray().copy()
        out = np.empty(self.nc)
        self.comm.tompi4py().Allgatherv(vec.getArray(readonly=True), [out, self._counts])
        return out

    def ST(self, tau: PETSc.Vec) -> np.ndarray:
        """V = S^T tau with the distributed S, replicated on every rank as an (N, d) array."""
        self.S_at().multTranspose(tau, self.force)
        self._scatter.scatter(self.force, self._force_all, addv=PETSc.InsertMode.INSERT,
                              mode=PETSc.ScatterMode.FORWARD)
        return self._force_all.getArray().reshape(self.n_nodes, self.d).copy()

    def destroy(self):
        for obj in (self.S, self.N, self.tau, self.rhs, self.force, self._scatter, self._force_all):
            obj.destroy()


def extended_precision_available() -> bool:
    """Whether numpy's long double carries more bits than double (x86-64 Linux: 64-bit
    mantissa; aarch64 Linux: IEEE quad; not on Windows or Apple silicon, where it is double)."""
    return bool(np.finfo(np.longdouble).eps < 1e-18)


_SPLIT = 134217729.0             # 2^27 + 1: Dekker's split of a double into two halves


def _two_sum(a: np.ndarray, b: np.ndarray):
    """s + e = a + b exactly (Knuth)."""
    s = a + b
    bb = s - a
    return s, (a - (s - bb)) + (b - bb)


def _two_prod(a: np.ndarray, b: np.ndarray):
    """p + e = a * b exactly (Dekker; no fused multiply-add needed)."""
    p = a * b
    c = _SPLIT * a
    ah = c - (c - a)
    al = a - ah
    c = _SPLIT * b
    bh = c - (c - b)
    bl = b - bh
    return p, ((ah * bh - p) + ah * bl + al * bh) + al * bl


def _dd_add(ah, al, bh, bl):
    """(ah + al) + (bh + bl) as a normalised double-double pair."""
    s, e = _two_sum(ah, bh)
    e = e + (al + bl)
    hi = s + e
    return hi, e - (hi - s)


def _mpi_max():
    return MPI.MAX


def petsc_version() -> str:
    """The PETSc library's version, e.g. "3.18.5" (for the run file's provenance)."""
    return ".".join(map(str, PETSc.Sys.getVersion()))
