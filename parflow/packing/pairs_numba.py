"""The compiled (numba) kernel of the packing pair list: ``NumbaPairs`` and its passes.

One cohesive module, longer than the others of ``parflow.packing``: the cell list, the
FIRE step and update passes, and the class that drives them share one bit-identity
contract with ``pairs.NumpyPairs`` (below), so they are kept together.

Imported only when the numba kernel is chosen (``pairs.pair_list``): numba is optional
(Debian python3-numba) and its import costs ~0.5 s, so this module imports it at its top
and ``pairs`` imports this module at first use.

Neighbour list: CSR rows (``indptr``, ``nbr``, and ``rows``: the row of each entry) with
the neighbours of each particle in ascending index order, built with a periodic cell
list: only the neighbours b > a (the half list in (a, b) order) for the serial pair loop,
or all of them (full list) for the parallel per-particle gather.  A pair is listed when
its minimum-image distance at build time satisfies |dx|^2 < (R_a + R_b + skin)^2,
evaluated with the arithmetic of the numpy kernel, so both kernels list the same pairs.
No image shifts are stored: the image is taken again at every force evaluation, by
comparisons (t > L/2: t - L; t < -L/2: t + L), which gives the build-time image, and the
same bits as adding the numpy kernel's stored shift, as long as every listed pair stays
closer than L/2 - skin to it (``pairs.numba_fits``: L > 2 (cut + skin)).

Forces: the force on a particle is summed over its neighbours in ascending index order,
each term being the same floating-point value as in the numpy kernel (sparse incidence
products with the pairs sorted by (i, j)), so forces are bit-identical to the numpy
kernel, in the pair loop and in the gather for any number of threads.

Reductions (F.v, |F|^2, |v + dt F|^2 over all particles) are sums in blocks of BLOCK
particles, each block summed in index order, then the block sums in block order: a fixed
order that does not depend on the thread count (``pairs.block_sum`` is the numpy twin).

Every function is compiled with error_model="numpy" (IEEE division, no zero-division
checks in the loops) and without fastmath (no reassociation, no fused multiply-add), so
the arithmetic is that of numpy.

2D passes beside the nD ones: the cell search (``_search2`` / ``_search``), the step
(``_step2_*`` / ``_step_nd_*``) and the update (``_update2`` / ``_update``) have d = 2
versions because they are measurably faster; each says by how much (CPU time per call at
N = 40 000, phi = 0.88, same results to the bit; ``benchmarks/bench_packing.py --passes``
measures them).
"""
from __future__ import annotations

import contextlib
import math
import warnings

import numpy as np

from ..errors import InputError
from . import pairs
from .pairs import DEFAULT_THREADS, PairList, numba_fits

with warnings.catch_warnings():          # llvmlite's import-time DeprecationWarning
    warnings.simplefilter("ignore", DeprecationWarning)
    import numba
    from numba import njit, prange

#: Particles per reduction block (fixed: the summation order must not depend on threads).
#: Defined here, not imported: the compiled functions are cached per source file, and numba
#: does not see a change of a global defined in another file.
BLOCK = 4096
assert BLOCK == pairs.BLOCK, "pairs.BLOCK and pairs_numba.BLOCK must be the same"


def set_threads(n: int | None) -> int:
    """Set numba's thread count (None: all numba threads); return the previous count."""
    old = numba.get_num_threads()
    numba.set_num_threads(int(n) if n else numba.config.NUMBA_NUM_THREADS)
    return old


def max_threads() -> int:
    """The most numba threads a kernel may use (NUMBA_NUM_THREADS)."""
    return int(numba.config.NUMBA_NUM_THREADS)


# --------------------------------------------------------------------------- cell list

@njit(cache=True, error_model="numpy", parallel=True)
def _wrap(X, box, Xw, s):  # pragma: no cover - compiled
    """Xw = (X/L - floor(X/L)) L with 1 -> 0 (as pairs.wrap01); s: reduced coords."""
    d, n = X.shape
    for a in prange(n):
        for k in range(d):
            t = X[k, a] / box[k]
            t = t - np.floor(t)
            if t >= 1.0:
                t = 0.0
            s[k, a] = t
            Xw[k, a] = t * box[k]


@njit(cache=True, error_model="numpy")
def _cells(s, nc, with_table):  # pragma: no cover - compiled
    """Counting sort of the particles into cells (numbered x fastest), and (with_table)
    the table of the 3^d neighbour cells of each cell (-1 where an offset repeats a cell:
    fewer than 3 cells along a direction).
    Returns (cell (n,), start (ncell+1,), members (n,), table (ncell, 3^d) or empty)."""
    d, n = s.shape
    ncell = 1
    for k in range(d):
        ncell *= nc[k]
    cell = np.empty(n, np.int64)
    for a in range(n):
        c = 0
        for k in range(d - 1, -1, -1):
            ck = int(s[k, a] * nc[k])
            if ck >= nc[k]:
                ck = nc[k] - 1
            c = c * nc[k] + ck
        cell[a] = c
    start = np.zeros(ncell + 1, np.int64)
    for a in range(n):
        start[cell[a] + 1] += 1
    for c in range(ncell):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    members = np.empty(n, np.int64)
    for a in range(n):
        c = cell[a]
        members[fill[c]] = a
        fill[c] += 1
    n3 = 3 ** d
    table = np.empty((ncell if with_table else 0, n3), np.int64)
    for c in range(table.shape[0]):
        for t in range(n3):
            out = 0
            stride = 1
            rest = c
            tt = t
            for k in range(d):
                ck = rest % nc[k]
                rest //= nc[k]
                o = tt % 3
                tt //= 3
                if nc[k] >= 3:
                    ck = (ck + o - 1) % nc[k]
                elif o < nc[k]:
                    ck = o
                else:
                    out = -1
                    break
                out += ck * stride
                stride *= nc[k]
            table[c, t] = out
    return cell, start, members, table


@njit(cache=True, error_model="numpy", inline="always")
def _listed(Xw, radii, box, ibox, skin, a, b):  # pragma: no cover - compiled
    """The build-time criterion of the numpy kernel, |dx|^2 < (R_a + R_b + skin)^2 with
    the minimum image dx - round(dx/L) L.  (dx * (1/L) may differ from dx/L in the last
    bit; the rounded value can then differ only where |dx| ~ L/2 > cut: never listed.)"""
    d = Xw.shape[0]
    r2 = 0.0
    for k in range(d):
        t = Xw[k, a] - Xw[k, b]
        t -= np.rint(t * ibox[k]) * box[k]
        r2 += t * t
    sig = radii[a] + radii[b]
    sig += skin
    return r2 < sig * sig


@njit(cache=True, error_model="numpy", parallel=True)
def _search(Xw, radii, box, skin, cell, start, members, table, full, indptr, nbr, cnt):  # pragma: no cover
    """Neighbours of each particle a: all b != a (full) or b > a.  With an empty nbr:
    count them into cnt.  Otherwise fill the rows of nbr (starting at indptr), sorted,
    and count the neighbours b > a into cnt."""
    d, n = Xw.shape
    ibox = 1.0 / box
    fill = nbr.shape[0] > 0
    for a in prange(n):
        e0 = indptr[a] if fill else 0
        e = e0
        c0 = cell[a]
        for t in range(table.shape[1]):
            c = table[c0, t]
            if c < 0:
                continue
            for q in range(start[c], start[c + 1]):
                b = members[q]
                if (b > a or (full and b != a)) and _listed(Xw, radii, box, ibox, skin, a, b):
                    if fill:                      # insertion into the sorted row
                        p = e
                        while p > e0 and nbr[p - 1] > b:
                            nbr[p] = nbr[p - 1]
                            p -= 1
                        nbr[p] = b
                    e += 1
        if fill:
            h = 0
            for q in range(e0, e):
                if nbr[q] > a:
                    h += 1
            cnt[a] = h
        else:
            cnt[a] = e


@njit(cache=True, error_model="numpy", inline="always")
def _sort_row(v, e0, e1):  # pragma: no cover - compiled
    """Insertion sort of v[e0:e1] (a few entries)."""
    for p in range(e0 + 1, e1):
        b = v[p]
        q = p
        while q > e0 and v[q - 1] > b:
            v[q] = v[q - 1]
            q -= 1
        v[q] = b


CELL_BLOCK = 64      # cells per task of the cell-list search


@njit(cache=True, error_model="numpy", inline="always")
def _image(t, L, h):  # pragma: no cover - compiled
    """The minimum image of a coordinate difference t by comparisons (h = L/2)."""
    t = t - L if t > h else t
    return t + L if t < -h else t


@njit(cache=True, error_model="numpy", inline="always")
def _near2(xa, ya, ra, a, bx, by, br, bb, k, L0, L1, h0, h1, skin, full):  # pragma: no cover
    """1 if candidate k of the stencil buffer is a listed neighbour of particle a, else 0
    (branch-free): |dx|^2 < (R_a + R_b + skin)^2, summed (R_a + R_b) + skin as the numpy
    kernel, and b > a (half list) or b != a (full list).  The count and the fill pass of
    _search2 share it: inlined, the two passes run as fast as with the body written out
    in each (measured at N = 40 000, one thread: count 2.82 ms, fill 4.99 ms, against
    2.83 and 4.98 ms written out)."""
    dx = _image(xa - bx[k], L0, h0)
    dy = _image(ya - by[k], L1, h1)
    sig = ra + br[k]
    sig += skin
    b = bb[k]
    return np.int64(dx * dx + dy * dy < sig * sig) * np.int64((b > a) | (full & (b != a)))


@njit(cache=True, error_model="numpy", parallel=True)
def _search2(Xw, radii, box, skin, cell, start, members, nc, full, indptr, nbr, cnt):  # pragma: no cover
    """d = 2 version of _search, cell by cell: the candidates of a cell (the particles
    of its 3 x 3 stencil: cells are numbered x fastest, so each stencil row is one
    contiguous range of the cell-sorted particles, or two across the periodic x
    boundary) are copied once into a small buffer, then tested against each particle of
    the cell in one branch-free loop.  The image is taken by comparisons (t > L/2:
    t - L; t < -L/2: t + L), which equals t - round(t/L) L except where |t| ~ L/2 >
    cut + skin: such pairs are never listed.
    Kept beside _search: count + fill of the half list take 8.3 ms here against 16.6 ms
    with _search (N = 40 000, phi = 0.88, one thread)."""
    L0, L1 = box[0], box[1]
    h0, h1 = 0.5 * L0, 0.5 * L1
    nx, ny = nc[0], nc[1]
    ncell = nx * ny
    fill = nbr.shape[0] > 0
    nrow = 3 if ny >= 3 else ny
    n = Xw.shape[1]
    xs = np.empty(n)                              # coordinates and radii in cell order
    ys = np.empty(n)
    rs = np.empty(n)
    for q in prange(n):
        b = members[q]
        xs[q] = Xw[0, b]
        ys[q] = Xw[1, b]
        rs[q] = radii[b]
    nblock = (ncell + CELL_BLOCK - 1) // CELL_BLOCK
    cap = 0                                       # 9 x the largest cell occupancy
    for c in range(ncell):
        cap = max(cap, start[c + 1] - start[c])
    cap *= 9
    for blk in prange(nblock):
        bx = np.empty(cap)
        by = np.empty(cap)
        br = np.empty(cap)
        bb = np.empty(cap, np.int64)
        for c in range(blk * CELL_BLOCK, min(ncell, (blk + 1) * CELL_BLOCK)):
            if start[c] == start[c + 1]:
                continue
            cx = c % nx
            cy = c // nx
            m = 0
            for ry in range(nrow):
                row = ((cy + ry - 1) % ny if ny >= 3 else ry) * nx
                if nx < 3:
                    lo1, hi1, lo2, hi2 = start[row], start[row + nx], 0, 0
                elif cx == 0:
                    lo1, hi1, lo2, hi2 = start[row], start[row + 2], start[row + nx - 1], start[row + nx]
                elif cx == nx - 1:
                    lo1, hi1, lo2, hi2 = start[row + nx - 2], start[row + nx], start[row], start[row + 1]
                else:
                    lo1, hi1, lo2, hi2 = start[row + cx - 1], start[row + cx + 2], 0, 0
                for seg in range(2):
                    lo = lo1 if seg == 0 else lo2
                    hi = hi1 if seg == 0 else hi2
                    for q in range(lo, hi):
                        bx[m] = xs[q]
                        by[m] = ys[q]
                        br[m] = rs[q]
                        bb[m] = members[q]
                        m += 1
            for qa in range(start[c], start[c + 1]):
                a = members[qa]
                xa = xs[qa]
                ya = ys[qa]
                ra = rs[qa]
                if not fill:                      # count pass
                    e = 0
                    for k in range(m):
                        e += _near2(xa, ya, ra, a, bx, by, br, bb, k, L0, L1, h0, h1, skin, full)
                    cnt[a] = e
                    continue
                e0 = indptr[a]                    # fill pass
                e1 = indptr[a + 1]
                e = e0
                for k in range(m):
                    ok = _near2(xa, ya, ra, a, bx, by, br, bb, k, L0, L1, h0, h1, skin, full)
                    if e < e1:                    # branch-free append
                        nbr[e] = bb[k]
                    e += ok
                _sort_row(nbr, e0, e)
                h = 0
                for q in range(e0, e):
                    h += nbr[q] > a
                cnt[a] = h


def build_list(X, radii, box, skin, cut, full):
    """Wrap X into the box and build the sorted CSR neighbour list.

    full=True: every neighbour of each particle (for the per-particle gather); False: only
    the neighbours b > a (the half list in (a, b) order, for the pair scatter).
    Returns (Xw, indptr, rows, nbr, hptr): wrapped positions (d, N); row pointers (N+1,);
    row and neighbour index of each entry (int32); hptr (N+1,): offsets of each row's
    part b > a in the half list (hptr is indptr when full=False)."""
    d, n = X.shape
    Xw = np.empty((d, n))
    s = np.empty((d, n))
    _wrap(X, box, Xw, s)
    # cells no smaller than cut (1 + 1e-8): every pair closer than cut is in adjacent cells
    nc = np.maximum(np.floor(box / (cut * (1.0 + 1e-8))), 1).astype(np.int64)
    cell, start, members, table = _cells(s, nc, d != 2)
    cnt = np.empty(n, np.int64)
    indptr = np.zeros(n + 1, np.int64)

    def search(nbr):                    # empty nbr: count into cnt; else fill the rows
        if d == 2:
            _search2(Xw, radii, box, float(skin), cell, start, members, nc, full, indptr,
                     nbr, cnt)
        else:
            _search(Xw, radii, box, float(skin), cell, start, members, table, full, indptr,
                    nbr, cnt)

    search(np.empty(0, np.int32))
    np.cumsum(cnt, out=indptr[1:])
    nbr = np.empty(int(indptr[-1]), np.int32)
    search(nbr)
    rows = np.repeat(np.arange(n, dtype=np.int32), np.diff(indptr))
    if not full:
        return Xw, indptr, rows, nbr, indptr
    hptr = np.zeros(n + 1, np.int64)
    np.cumsum(cnt, out=hptr[1:])
    return Xw, indptr, rows, nbr, hptr


# --------------------------------------------------------------------------- FIRE step
#
# Pair term of the numpy kernel for a listed pair (i < j): r = X_j - X_i + S_ij with the
# build-time image S_ij = -round(dx/L) L; c = max(1 - |r| s, 0) s / |r|, s = 1/(R_i + R_j);
# F_j += c r, F_i -= c r.  Here the image is re-taken at every step by comparisons
# (t > L/2: t - L; t < -L/2: t + L), which gives the same bits as adding S_ij because
# every listed pair stays closer than L/2 - skin to its build-time image.  The pair terms
# of a chunk of rows are computed first (a branch-free loop the compiler vectorises),
# then added in order.

CHUNK = 256          # rows whose pair terms are computed in one vectorised loop


@njit(cache=True, error_model="numpy")
def _terms2(x, y, radii, rows, nbr, e0, e1, tx, ty, ts, L0, L1):  # pragma: no cover
    """Pair terms c r of the list entries e0 <= e < e1 (entry e: a = rows[e], b = nbr[e],
    r = image of X_b - X_a; the force on b is +c r) into tx, ty[e - e0]: a gather loop,
    then a branch-free loop over contiguous arrays that the compiler vectorises."""
    m = e1 - e0
    for q in range(m):
        e = np.uint64(e0 + q)
        a = np.uint64(rows[e])
        b = np.uint64(nbr[e])
        tx[q] = x[b] - x[a]
        ty[q] = y[b] - y[a]
        ts[q] = radii[a] + radii[b]
    h0 = 0.5 * L0
    h1 = 0.5 * L1
    for q in range(m):
        dx = tx[q]
        dx = dx - L0 if dx > h0 else dx
        dx = dx + L0 if dx < -h0 else dx
        dy = ty[q]
        dy = dy - L1 if dy > h1 else dy
        dy = dy + L1 if dy < -h1 else dy
        s = 1.0 / ts[q]
        r = np.sqrt(dx * dx + dy * dy)
        o = max(1.0 - r * s, 0.0)
        c = o * s / r
        tx[q] = c * dx
        ty[q] = c * dy


@njit(cache=True, error_model="numpy", inline="always")
def _reduce2(fx, fy, vx, vy, c0, c1, dtp, acc):  # pragma: no cover - compiled
    """acc += (F.V, |F|^2, |V + dtp F|^2) over particles c0 <= a < c1, in order;
    acc[3] = max(acc[3], max |F_a|^2)."""
    s_fv = acc[0]
    s_ff = acc[1]
    s_w = acc[2]
    m_ff = acc[3]
    for a in range(c0, c1):
        ga = fx[a]
        gb = fy[a]
        va = vx[a]
        vb = vy[a]
        s_fv += ga * va + gb * vb
        t = ga * ga + gb * gb
        s_ff += t
        if t > m_ff:
            m_ff = t
        wx = va + dtp * ga
        wy = vb + dtp * gb
        s_w += wx * wx + wy * wy
    acc[0] = s_fv
    acc[1] = s_ff
    acc[2] = s_w
    acc[3] = m_ff


@njit(cache=True, error_model="numpy")
def _step2_scatter(X, V, F, radii, hptr, rows, nbr, box, dtp, part, tx, ty, ts):  # pragma: no cover
    """d = 2, serial: pair loop over the half list in (i, j) order.  F_a is final once
    the pairs of row a are done, so the FIRE reductions are taken chunk by chunk.
    Kept beside _step_nd_scatter: 0.60 ms against 1.61 ms per call (N = 40 000)."""
    n = X.shape[1]
    x, y, vx, vy, fx, fy = X[0], X[1], V[0], V[1], F[0], F[1]
    L0, L1 = box[0], box[1]
    fx[:] = 0.0
    fy[:] = 0.0
    nb = (n + BLOCK - 1) // BLOCK
    for blk in range(nb):
        acc = part[blk]
        acc[:] = 0.0
        a1 = min(n, (blk + 1) * BLOCK)
        for c0 in range(blk * BLOCK, a1, CHUNK):
            c1 = min(a1, c0 + CHUNK)
            e0 = hptr[c0]
            e1 = hptr[c1]
            _terms2(x, y, radii, rows, nbr, e0, e1, tx, ty, ts, L0, L1)
            for q in range(e1 - e0):
                e = np.uint64(e0 + q)
                a = np.uint64(rows[e])
                b = np.uint64(nbr[e])
                u = tx[q]
                w = ty[q]
                fx[a] -= u
                fy[a] -= w
                fx[b] += u
                fy[b] += w
            _reduce2(fx, fy, vx, vy, c0, c1, dtp, acc)


@njit(cache=True, error_model="numpy", parallel=True)
def _step2_gather(X, V, F, radii, indptr, rows, nbr, box, dtp, part, scratch):  # pragma: no cover
    """d = 2, parallel over blocks of particles: per-particle gather over the full list
    (each pair term computed twice, once from each end: for b < a the term with
    r = X_b - X_a is exactly minus the pair-loop term), summed over b in ascending order.
    Kept beside _step_nd_gather: 1.06 ms against 2.77 ms per call (N = 40 000, one
    thread)."""
    n = X.shape[1]
    x, y, vx, vy, fx, fy = X[0], X[1], V[0], V[1], F[0], F[1]
    L0, L1 = box[0], box[1]
    nb = (n + BLOCK - 1) // BLOCK
    for blk in prange(nb):
        tx = np.empty(scratch)
        ty = np.empty(scratch)
        ts = np.empty(scratch)
        acc = part[blk]
        acc[:] = 0.0
        a1 = min(n, (blk + 1) * BLOCK)
        for c0 in range(blk * BLOCK, a1, CHUNK):
            c1 = min(a1, c0 + CHUNK)
            e0 = indptr[c0]
            e1 = indptr[c1]
            _terms2(x, y, radii, rows, nbr, e0, e1, tx, ty, ts, L0, L1)
            fx[c0:c1] = 0.0
            fy[c0:c1] = 0.0
            for q in range(e1 - e0):
                a = np.uint64(rows[np.uint64(e0 + q)])
                fx[a] -= tx[q]
                fy[a] -= ty[q]
            _reduce2(fx, fy, vx, vy, c0, c1, dtp, acc)


def _step_nd_py(X, V, F, radii, indptr, nbr, box, dtp, part, full):  # pragma: no cover
    """Any d, scalar: gather over the full list (full=True, compiled parallel) or pair
    loop over the half list (full=False, compiled serial)."""
    d, n = X.shape
    nb = (n + BLOCK - 1) // BLOCK
    if not full:
        F[:, :] = 0.0
    for blk in prange(nb):
        s_fv = 0.0
        s_ff = 0.0
        s_w = 0.0
        m_ff = 0.0
        for a in range(blk * BLOCK, min(n, (blk + 1) * BLOCK)):
            ra = radii[a]
            if full:
                for k in range(d):
                    F[k, a] = 0.0
            for e in range(indptr[a], indptr[a + 1]):
                b = nbr[e]
                r2 = 0.0
                for k in range(d):
                    t = _image(X[k, b] - X[k, a], box[k], 0.5 * box[k])
                    r2 += t * t
                s = 1.0 / (ra + radii[b])
                r = np.sqrt(r2)
                o = max(1.0 - r * s, 0.0)
                c = o * s / r
                for k in range(d):
                    t = c * _image(X[k, b] - X[k, a], box[k], 0.5 * box[k])
                    F[k, a] -= t
                    if not full:
                        F[k, b] += t
            fv = F[0, a] * V[0, a]
            ff = F[0, a] * F[0, a]
            w = V[0, a] + dtp * F[0, a]
            w = w * w
            for k in range(1, d):
                fv += F[k, a] * V[k, a]
                ff += F[k, a] * F[k, a]
                u = V[k, a] + dtp * F[k, a]
                w += u * u
            s_fv += fv
            s_ff += ff
            s_w += w
            if ff > m_ff:
                m_ff = ff
        part[blk, 0] = s_fv
        part[blk, 1] = s_ff
        part[blk, 2] = s_w
        part[blk, 3] = m_ff


_step_nd_gather = njit(cache=True, error_model="numpy", parallel=True)(_step_nd_py)
_step_nd_scatter = njit(cache=True, error_model="numpy")(_step_nd_py)


@njit(cache=True, error_model="numpy")
def _sum_parts(part):  # pragma: no cover - compiled
    fv = 0.0
    ff = 0.0
    w = 0.0
    m = 0.0
    for blk in range(part.shape[0]):
        fv += part[blk, 0]
        ff += part[blk, 1]
        w += part[blk, 2]
        if part[blk, 3] > m:
            m = part[blk, 3]
    return fv, ff, w, m


class Work:
    """Scratch arrays of the step kernels."""

    def __init__(self, n):
        self.part = np.empty(((n + BLOCK - 1) // BLOCK, 4))
        self.part1 = np.empty((n + BLOCK - 1) // BLOCK)
        self.tx = self.ty = self.ts = np.empty(0)
        self.scratch = 0

    def chunk(self, indptr):
        """Scratch for the pair terms of CHUNK consecutive rows."""
        m = int(np.max(indptr[CHUNK:] - indptr[:-CHUNK])) if indptr.shape[0] > CHUNK else int(indptr[-1])
        self.scratch = m
        if self.tx.shape[0] < m:
            m = int(1.25 * m) + 16
            self.tx = np.empty(m)
            self.ty = np.empty(m)
            self.ts = np.empty(m)


def fire_step(X, V, F, radii, indptr, rows, nbr, box, dtp, full, work):
    """Forces into F; returns (F.V, |F|^2, |V + dtp F|^2, max_a |F_a|^2)."""
    if X.shape[0] != 2:
        (_step_nd_gather if full else _step_nd_scatter)(X, V, F, radii, indptr, nbr, box,
                                                         dtp, work.part, full)
    elif full:
        _step2_gather(X, V, F, radii, indptr, rows, nbr, box, dtp, work.part, work.scratch)
    else:
        _step2_scatter(X, V, F, radii, indptr, rows, nbr, box, dtp, work.part,
                       work.tx, work.ty, work.ts)
    return _sum_parts(work.part)


@njit(cache=True, error_model="numpy", parallel=True)
def _update(X, V, F, dt, h, backoff, mix, c1, beta, part):  # pragma: no cover - compiled
    """The FIRE velocity mixing and position update, element by element:
    [backoff: X -= h V; V = 0];  V += dt F;  [mix: V *= c1; V += beta F];  X += dt V.
    part[blk] = max |V_a|^2 over the block."""
    d, n = X.shape
    nb = (n + BLOCK - 1) // BLOCK
    for blk in prange(nb):
        m = 0.0
        for a in range(blk * BLOCK, min(n, (blk + 1) * BLOCK)):
            v2 = 0.0
            for k in range(d):
                x = X[k, a]
                v = V[k, a]
                f = F[k, a]
                if backoff:
                    x = x - h * v
                    v = 0.0
                v = v + dt * f
                if mix:
                    v = v * c1
                    v = v + beta * f
                x = x + dt * v
                X[k, a] = x
                V[k, a] = v
                if k == 0:
                    v2 = v * v
                else:
                    v2 += v * v
            if v2 > m:
                m = v2
        part[blk] = m


@njit(cache=True, error_model="numpy", parallel=True)
def _update2(X, V, F, dt, h, backoff, mix, c1, beta, part):  # pragma: no cover - compiled
    """d = 2 version of _update (a loop the compiler vectorises).  Kept beside _update:
    0.10 ms against 0.19 ms per call (N = 40 000)."""
    n = X.shape[1]
    x, y, vx, vy, fx, fy = X[0], X[1], V[0], V[1], F[0], F[1]
    nb = (n + BLOCK - 1) // BLOCK
    for blk in prange(nb):
        m = 0.0
        for a in range(blk * BLOCK, min(n, (blk + 1) * BLOCK)):
            xa = x[a]
            ya = y[a]
            va = vx[a]
            vb = vy[a]
            ga = fx[a]
            gb = fy[a]
            if backoff:
                xa = xa - h * va
                ya = ya - h * vb
                va = 0.0
                vb = 0.0
            va = va + dt * ga
            vb = vb + dt * gb
            if mix:
                va = va * c1
                vb = vb * c1
                va = va + beta * ga
                vb = vb + beta * gb
            x[a] = xa + dt * va
            y[a] = ya + dt * vb
            vx[a] = va
            vy[a] = vb
            t = va * va + vb * vb
            m = t if t > m else m
        part[blk] = m


def fire_update(X, V, F, dt, h, backoff, mix, c1, beta, part):
    (_update2 if X.shape[0] == 2 else _update)(X, V, F, dt, h, backoff, mix, c1, beta, part)
    return float(part.max())


@njit(cache=True, error_model="numpy", parallel=True)
def _max_disp2(X, X0, part):  # pragma: no cover - compiled
    d, n = X.shape
    nb = (n + BLOCK - 1) // BLOCK
    for blk in prange(nb):
        m = 0.0
        for a in range(blk * BLOCK, min(n, (blk + 1) * BLOCK)):
            t = X[0, a] - X0[0, a]
            r2 = t * t
            for k in range(1, d):
                t = X[k, a] - X0[k, a]
                r2 += t * t
            if r2 > m:
                m = r2
        part[blk] = m


def max_displacement2(X, X0, part):
    _max_disp2(X, X0, part)
    return float(part.max())


@njit(cache=True, error_model="numpy", parallel=True)
def _overlaps(X, radii, indptr, nbr, hptr, box, ov, isig):  # pragma: no cover - compiled
    """Overlap max(1 - r/sigma, 0) and 1/sigma of every listed pair a < b, in (a, b) order."""
    d, n = X.shape
    for a in prange(n):
        h = hptr[a]
        for e in range(indptr[a], indptr[a + 1]):
            b = nbr[e]
            if b <= a:
                continue
            r2 = 0.0
            for k in range(d):
                t = X[k, b] - X[k, a]
                t -= np.rint(t / box[k]) * box[k]
                r2 += t * t
            s = 1.0 / (radii[a] + radii[b])
            r = np.sqrt(r2)
            ov[h] = max(1.0 - r * s, 0.0)
            isig[h] = s
            h += 1


def pair_overlaps(X, radii, indptr, nbr, hptr, box):
    p = int(hptr[-1])
    ov = np.empty(p)
    isig = np.empty(p)
    _overlaps(X, radii, indptr, nbr, hptr, box, ov, isig)
    return ov, isig


# --------------------------------------------------------------------------- the pair list

class NumbaPairs(PairList):
    """The compiled kernel of ``pairs.PairList``: periodic cell list; with one thread a
    pair loop over the half list, with ``threads`` > 1 a per-particle gather over the full
    list, parallel over particles; the FIRE vector work fused into its passes (step,
    update).  Bit-identical to ``pairs.NumpyPairs`` (module docstring)."""

    kernel = "numba"

    def __init__(self, radii: np.ndarray, box, skin: float, threads: int | None = None):
        super().__init__(radii, box, skin)
        if not numba_fits(radii, self.box, self.skin):
            raise InputError(f"packing: kernel='numba' needs a box side > 2 (cut + skin) "
                             f"= {2 * (self.cut + self.skin):.3g}; use kernel='numpy'")
        self.threads = int(threads) if threads else DEFAULT_THREADS
        if not 1 <= self.threads <= max_threads():
            raise InputError(f"packing: threads must be in 1..{max_threads()} "
                             f"(NUMBA_NUM_THREADS), got {threads!r}")
        # one thread: pair loop over the half list; more: per-particle gather over the
        # full list (each pair computed from both ends), parallel over particles
        self.full = self.threads > 1
        self._work = Work(radii.shape[0])

    @contextlib.contextmanager
    def threads_set(self):
        old = set_threads(self.threads)
        try:
            yield
        finally:
            set_threads(old)

    def _build(self, X):
        X, self.indptr, self.rows, self.nbr, self.hptr = build_list(
            X, self.radii, self.box, self.skin, self.cut, self.full)
        self._work.chunk(self.indptr)
        self._half = None                          # i, j, S, isig built when asked for
        return X

    def _get_half(self):
        if self._half is None:                     # the upper half of the CSR list
            n = self.indptr.shape[0] - 1
            rows = np.repeat(np.arange(n, dtype=np.int64), np.diff(self.indptr))
            m = self.nbr > rows
            self._set_half(self.X0, rows[m], self.nbr[m].astype(np.int64))
        return self._half

    def max_displacement(self, X):
        return math.sqrt(max_displacement2(X, self.X0, self._work.part1))

    def pair_vectors(self, X):
        i, j, S, _ = self._get_half()
        R = X[:, j] - X[:, i]
        R += S
        r = np.sqrt(np.einsum("kp,kp->p", R, R))
        return R, r

    def overlaps(self, X):
        return pair_overlaps(X, self.radii, self.indptr, self.nbr, self.hptr, self.box)

    def forces(self, X, F):
        self.step(X, np.zeros_like(X), F, 0.0)
        return self.overlaps(X)[0]

    def step(self, X, V, F, dtp):
        return fire_step(X, V, F, self.radii, self.indptr, self.rows, self.nbr, self.box,
                         float(dtp), self.full, self._work)

    def update(self, X, V, F, dt, backoff, c1, beta):
        mix = beta is not None
        return fire_update(X, V, F, dt, 0.5 * dt, bool(backoff), mix, float(c1),
                           float(beta) if mix else 0.0, self._work.part1)
