"""Floppy rod networks from jammed packings (Wyart, Liang, Kabla & Mahadevan, PRL 101,
215501, 2008; DESIGN §7, issue 3).

Protocol
--------
1. A jammed soft-disc packing (``parflow.packing``); rattlers dropped, nodes
   renumbered (the packing's Morton order is kept, so neighbours stay close in memory).
2. A rod on every contact, rest length l0 = its current length, computed exactly as the
   solver will: r = h0 (s_j + n - s_i) (so |r| == l0 to round-off, not to the packing's
   force tolerance).
3. Dilution: repeatedly remove a bond whose two end nodes have the largest summed
   coordination z_i + z_j, uniformly at random among ties (seeded), until
   Nb = round(z N / 2).  The final z = 2 Nb / N is within 1/N of the target.

Invariant (our decision): no node ever drops below d + 1 bonds.  A bond is removable only
if both its ends have degree > d + 1.  In the packing, nodes with <= d contacts are
rattlers; a network node with <= d rods would be a local floppy appendage (degree d:
a hinge whose own motion is slaved, degree 1: dangling, degree 0: isolated) that adds
nothing to the rigidity physics and would pin the lowest modes to trivial local motions.
Consequences: (a) z >= d + 1 is a hard bound (the mean of degrees >= d + 1), and (b) if
the highest-sum bonds all touch a node of degree d + 1, the protocol skips them and
takes the next removable one (the pure max-sum rule could otherwise create degree-d
nodes).  Below z ~ d + 1 + (a few %) dilution can get stuck (every remaining bond
touches a degree-(d+1) node): that is reported as an InputError naming the z reached.

Speed: the dilution is vectorised bucket by bucket (see ``dilute``: the sequential
random max-sum rule is reproduced exactly in distribution as a lexicographically-first
independent set of the top bucket under a random order), so N = 10^6 takes seconds.

Diagnostics (``Network.info``): coordination histogram, fabric tensor <n n> eigenvalues
and their ratio (1 = isotropic), and for Nb <= SELF_STRESS_MAX_BONDS the rank of the dense
rigidity matrix S (Nb x dN): rank == Nb means no state of self-stress (N = S S^T
positive definite).
"""
from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field

import h5py
import numpy as np

from .. import __version__
from ..geometry import rigidity_csr
from ..io import atomic_h5
from ..packing import fire as _pk
from ..state import Bonds, InputError

FORMAT = "parflow-network"
FORMAT_VERSION = 1
#: Networks with at most this many bonds get the dense rank check of S by default.
SELF_STRESS_MAX_BONDS = 3000
#: Fewest nodes a network may have (the packing needs a box > twice the interaction range).
MIN_NODES = 16
#: Default packing fraction of the seed packing (2D): z0 ≈ 4.6-4.7 after rattler removal.
DEFAULT_PHI = 0.88


@dataclass
class Network:
    """A rod network.  s: (N, d) reduced coordinates in [0, 1)^d; h0: (d, d) cell
    (columns are the box vectors; here diag(L)); bonds: parflow.state.Bonds with
    r_ij = h0 (s_j + shift - s_i) and |r_ij| = l0.  z0: coordination of the undiluted
    contact network (non-rattlers); info: diagnostics and provenance."""

    s: np.ndarray
    h0: np.ndarray
    bonds: Bonds
    z0: float
    seed: int
    info: dict = field(default_factory=dict)

    @property
    def n(self) -> int:
        return int(self.s.shape[0])

    @property
    def d(self) -> int:
        return int(self.s.shape[1])

    @property
    def z(self) -> float:
        return 2.0 * len(self.bonds) / self.n

    def bond_vectors(self) -> np.ndarray:
        return bond_vectors(self.s, self.h0, self.bonds)

    def degrees(self) -> np.ndarray:
        return degrees(self.n, self.bonds.i, self.bonds.j)


# --------------------------------------------------------------------------- geometry

def bond_vectors(s: np.ndarray, h0: np.ndarray, bonds: Bonds) -> np.ndarray:
    """r_ij = h0 (s_j + n - s_i), (Nb, d); same operations as parflow.geometry.pair_vectors."""
    ds = s[bonds.j] - s[bonds.i]
    ds += bonds.shift
    return ds @ h0.T


def degrees(n: int, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    return np.bincount(i, minlength=n) + np.bincount(j, minlength=n)


def coordination_histogram(n: int, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """counts[k] = number of nodes with k bonds."""
    return np.bincount(degrees(n, i, j))


def fabric(vectors: np.ndarray):
    """Fabric tensor <n n^T> over bonds: (eigenvalues ascending, ratio min/max)."""
    nvec = vectors / np.linalg.norm(vectors, axis=1)[:, None]
    f = nvec.T @ nvec / nvec.shape[0]
    ev = np.linalg.eigvalsh(f)
    return ev, float(ev[0] / ev[-1])


def rigidity_matrix_dense(s: np.ndarray, h0: np.ndarray, bonds: Bonds) -> np.ndarray:
    """Dense S (Nb x dN): row a has +n_a at node j and -n_a at node i (DESIGN §2)."""
    r = bond_vectors(s, h0, bonds)
    nvec = r / np.linalg.norm(r, axis=1)[:, None]
    nb, d = nvec.shape
    S = np.zeros((nb, d * s.shape[0]))
    rows = np.arange(nb)
    for k in range(d):                                  # loop over dimensions only
        S[rows, d * bonds.j + k] += nvec[:, k]
        S[rows, d * bonds.i + k] -= nvec[:, k]
    return S


def rigidity_matrix_sparse(s: np.ndarray, h0: np.ndarray, bonds: Bonds):
    """S as a scipy CSR matrix (Nb x dN) at the reference cell (``geometry.rigidity_csr``)."""
    r = bond_vectors(s, h0, bonds)
    return rigidity_csr(r / np.linalg.norm(r, axis=1)[:, None], bonds.i, bonds.j, s.shape[0])


def self_stress_check(s: np.ndarray, h0: np.ndarray, bonds: Bonds) -> dict:
    """Dense rank of S from the eigenvalues of N = S S^T (Nb x Nb, formed sparsely, then
    numpy eigvalsh: 4x cheaper than an SVD of S at Nb = 3000).  rank = number of
    eigenvalues above lambda_max * Nb * eps; self_stresses = Nb - rank (0 means N is
    positive definite).  A self-stress gives an eigenvalue at round-off (~1e-13), while
    the smallest genuine one of these floppy networks is ~1e-5 even at z = 3.98
    (sigma_min = sqrt(lambda_min) ~ 2e-3-5e-3 measured at N = 1000), so the gap is wide."""
    S = rigidity_matrix_sparse(s, h0, bonds)
    N = (S @ S.T).toarray()
    lam = np.linalg.eigvalsh(N)
    tol = lam[-1] * N.shape[0] * np.finfo(float).eps
    rank = int(np.count_nonzero(lam > tol))
    return dict(rank=rank, n_bonds=int(N.shape[0]), self_stresses=int(N.shape[0] - rank),
                lambda_min=float(lam[0]), lambda_max=float(lam[-1]),
                sigma_min=float(np.sqrt(max(lam[0], 0.0))), rank_tol=float(tol))


# --------------------------------------------------------------------------- dilution

def dilute(n: int, i: np.ndarray, j: np.ndarray, n_bonds_target: int, d: int,
           rng: np.random.Generator, return_order: bool = False):
    """WLKM dilution: boolean mask of the bonds kept (and, if ``return_order``, the
    indices of the removed bonds in removal order).

    Sequential rule: remove a bond with the largest z_i + z_j among removable bonds (both
    ends of degree > d + 1), uniformly at random among ties, until ``n_bonds_target``
    bonds are left.  Raises InputError if no removable bond is left before that.

    Implementation (vectorised, exact in distribution): keys only decrease, so the
    sequential process empties the top bucket T (key k_max) before touching key
    k_max - 1, and inside T it picks uniformly among the bonds whose key is still k_max;
    removing a bond lowers the key of every bond sharing one of its nodes.  Uniform
    sequential picking with that invalidation is the same as drawing a uniformly random
    order of T and keeping a bond iff no earlier kept bond shares a node with it: the
    lexicographically-first maximal independent set, computed by rounds of "keep every
    bond that ranks first at both its nodes, drop the bonds touching kept nodes"
    (O(log |T|) rounds).  If fewer removals are needed than T provides, the first ones in
    the random order are taken, exactly where the sequential process would stop.  The
    number of buckets processed is at most the initial k_max - 2(d + 1) (~ 10)."""
    nb = int(i.shape[0])
    n_remove = nb - int(n_bonds_target)
    keep = np.ones(nb, dtype=bool)
    order_out = []
    if n_remove <= 0:
        return (keep, np.zeros(0, dtype=np.int64)) if return_order else keep
    thr = d + 1
    deg = degrees(n, i, j)
    removed = 0
    live = np.arange(nb)              # alive bonds that may still be removable
    while removed < n_remove:
        # degrees only decrease: a bond that is not removable now never will be
        li, lj = i[live], j[live]
        ok = keep[live] & (deg[li] > thr) & (deg[lj] > thr)
        live, li, lj = live[ok], li[ok], lj[ok]
        if live.shape[0] == 0:
            z_reached = 2.0 * (nb - removed) / n
            raise InputError(
                f"network: dilution stopped at z = {z_reached:.4f} before the target "
                f"z = {2.0 * n_bonds_target / n:.4f}: every remaining bond touches a node "
                f"with d + 1 = {thr} bonds, and removing it would leave a node with <= d "
                f"bonds (a floppy appendage); use a target z >= {z_reached:.3f}")
        key = deg[li] + deg[lj]
        top = live[key == key.max()]
        cand = top[rng.permutation(top.shape[0])]          # random order = rank
        chosen = _lex_first_mis(n, i[cand], j[cand])       # positions in cand, rank order
        take = cand[chosen[: n_remove - removed]]
        keep[take] = False
        deg -= degrees(n, i[take], j[take])
        order_out.append(take)
        removed += take.shape[0]
    if return_order:
        return keep, np.concatenate(order_out)
    return keep


def _lex_first_mis(n: int, a: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Bonds (a_k, c_k), ranked by k: the greedy (lexicographically first) set of bonds
    with pairwise distinct nodes.  Returns the selected k, ascending."""
    m = a.shape[0]
    alive = np.arange(m)
    selected = []
    used = np.zeros(n, dtype=bool)
    while alive.shape[0]:
        aa, cc = a[alive], c[alive]
        ends = np.concatenate([aa, cc])
        ranks = np.concatenate([alive, alive])
        o = np.lexsort((ranks, ends))                       # by node, then rank
        e_s = ends[o]
        first = np.ones(e_s.shape[0], dtype=bool)
        first[1:] = e_s[1:] != e_s[:-1]
        best = np.empty(n, dtype=np.int64)
        best[e_s[first]] = ranks[o][first]                  # lowest rank at each node
        win = (best[aa] == alive) & (best[cc] == alive)
        sel = alive[win]
        selected.append(sel)
        used[a[sel]] = True
        used[c[sel]] = True
        alive = alive[~win & ~used[aa] & ~used[cc]]
    out = np.concatenate(selected)
    out.sort()
    return out


# --------------------------------------------------------------------------- building

def _check_target(z: float, d: int):
    if not (isinstance(z, (int, float, np.floating, np.integer)) and math.isfinite(z)):
        raise InputError(f"network: target z must be a finite number, got {z!r}")
    if z >= 2 * d:
        raise InputError(
            f"network: target z = {z:g}: a floppy network needs z < 2d = {2 * d} in {d}D: "
            f"z = 2d is isostatic/rigid; use z in [3.5, 3.98] (2D)")
    if z < d + 1:
        raise InputError(
            f"network: target z = {z:g} is below d + 1 = {d + 1}: the dilution keeps every "
            f"node with at least d + 1 bonds (fewer would make floppy appendages or "
            f"dangling parts), so the mean coordination cannot go below d + 1; "
            f"use z >= {d + 1} (typically 3.5-3.98 in 2D)")


def network_from_packing(packing: _pk.Packing, z: float, *, seed: int = 0,
                         check_self_stress: bool | None = None) -> Network:
    """Build the WLKM network of target coordination ``z`` from a packing.

    ``seed`` drives the random choice among ties.  ``check_self_stress``: dense rank check
    of S (default: when Nb <= SELF_STRESS_MAX_BONDS)."""
    t0 = time.perf_counter()
    d = packing.d
    _check_target(z, d)
    keep_node = ~packing.rattler
    n = int(keep_node.sum())
    if n < MIN_NODES:
        raise InputError(f"network: only {n} non-rattler nodes: use a packing with "
                         f"N >= {MIN_NODES} particles (and phi above jamming)")
    new_id = np.full(packing.n, -1, dtype=np.int64)
    new_id[keep_node] = np.arange(n)
    i = new_id[packing.contacts_i]
    j = new_id[packing.contacts_j]
    shift = packing.contacts_shift.astype(np.int64)
    if np.any(i < 0) or np.any(j < 0):
        raise InputError("network: the packing lists a contact on a rattler")
    z0 = 2.0 * i.shape[0] / n
    nb_target = int(round(z * n / 2.0))
    if nb_target >= i.shape[0]:
        raise InputError(
            f"network: target z = {z:g} is not below the packing's z0 = {z0:.4f}: "
            f"use a denser packing (larger phi) or a smaller z")
    rng = np.random.default_rng([int(seed), 0x5EED])
    keep = dilute(n, i, j, nb_target, d, rng)
    s = packing.reduced[keep_node]
    h0 = np.diag(packing.box.astype(float))
    bi, bj, bs = i[keep], j[keep], shift[keep]
    tmp = Bonds(bi, bj, bs, np.ones(bi.shape[0]))
    l0 = np.linalg.norm(bond_vectors(s, h0, tmp), axis=1)
    bonds = Bonds(bi, bj, bs, l0)
    bonds.validate(n)
    net = Network(s=s, h0=h0, bonds=bonds, z0=z0, seed=int(seed))
    net.info = diagnostics(net, check_self_stress)
    net.info.update(
        z_target=float(z), n_removed=int(i.shape[0] - bi.shape[0]),
        build_seconds=time.perf_counter() - t0,
        packing=dict(n=packing.n, phi=packing.phi, pressure=packing.pressure,
                     z=packing.z, n_rattlers=int(packing.rattler.sum()),
                     iterations=packing.iterations, max_force=packing.max_force,
                     force_scale=packing.force_scale, ftol=packing.ftol, seed=packing.seed))
    return net


def diagnostics(net: Network, check_self_stress: bool | None = None) -> dict:
    deg = net.degrees()
    ev, ratio = fabric(net.bond_vectors())
    out = dict(coordination_histogram=np.bincount(deg), min_degree=int(deg.min()),
               fabric_eigenvalues=ev, fabric_ratio=ratio, z=net.z)
    if check_self_stress is None:
        check_self_stress = len(net.bonds) <= SELF_STRESS_MAX_BONDS
    if check_self_stress:
        out["self_stress"] = self_stress_check(net.s, net.h0, net.bonds)
    return out


def make_network(n: int, z: float, *, phi: float = DEFAULT_PHI, d: int = 2, seed: int = 0,
                 check_self_stress: bool | None = None, **packing_kwargs) -> Network:
    """Packing of ``n`` particles at ``phi`` (seeded by ``seed``), then the WLKM network
    of target coordination ``z``.  Extra keyword arguments go to make_packing."""
    if not isinstance(n, (int, np.integer)) or n < MIN_NODES:
        raise InputError(f"network: N = {n!r} is too small: use N >= {MIN_NODES}")
    _check_target(z, d)
    pk = _pk.make_packing(n, phi, d=d, seed=seed, **packing_kwargs)
    return network_from_packing(pk, z, seed=seed, check_self_stress=check_self_stress)


# --------------------------------------------------------------------------- HDF5

def save_network(path: str, net: Network) -> None:
    """Write ``net`` to HDF5, whole or not at all (``io.atomic_h5``)."""
    with atomic_h5(os.fspath(path)) as f:
        f.attrs["format"] = FORMAT
        f.attrs["format_version"] = FORMAT_VERSION
        f.attrs["parflow_version"] = __version__
        f.attrs["d"] = net.d
        f.attrs["n_nodes"] = net.n
        f.attrs["n_bonds"] = len(net.bonds)
        f.attrs["z"] = net.z
        f.attrs["z0"] = net.z0
        f.attrs["seed"] = net.seed
        f.create_dataset("s", data=net.s)
        f.create_dataset("h0", data=net.h0)
        g = f.create_group("bonds")
        g.create_dataset("i", data=net.bonds.i)
        g.create_dataset("j", data=net.bonds.j)
        g.create_dataset("shift", data=net.bonds.shift)
        g.create_dataset("l0", data=net.bonds.l0)
        _write_info(f.create_group("info"), net.info)


def _write_info(g, info: dict):
    for k, v in info.items():
        if isinstance(v, dict):
            _write_info(g.create_group(k), v)
        elif isinstance(v, np.ndarray):
            g.create_dataset(k, data=v)
        elif isinstance(v, (list, tuple)):
            g.create_dataset(k, data=np.asarray(v))
        elif v is None:
            continue
        else:
            g.attrs[k] = v


def _read_info(g) -> dict:
    out = {k: (v.item() if isinstance(v, np.generic) else v) for k, v in g.attrs.items()}
    for k, v in g.items():
        out[k] = _read_info(v) if isinstance(v, h5py.Group) else v[()]
    return out


def load_network(path: str) -> Network:
    """Read and validate a network written by save_network.  Any problem (missing file,
    not HDF5, not a parflow network, unknown version, inconsistent arrays, rest lengths
    that do not match the geometry) is an InputError saying what is wrong."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise InputError(f"network file {path!r} does not exist")
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise InputError(f"{path!r} is not a parflow network: not a readable HDF5 file ({e})") from None
    with f:
        fmt = f.attrs.get("format")
        if isinstance(fmt, bytes):
            fmt = fmt.decode()
        if fmt != FORMAT:
            raise InputError(f"{path!r} is not a parflow network (format attribute "
                             f"{fmt!r}, expected {FORMAT!r})")
        ver = int(f.attrs.get("format_version", -1))
        if ver != FORMAT_VERSION:
            raise InputError(f"{path!r}: network format version {ver} is not supported "
                             f"(this parflow reads version {FORMAT_VERSION})")
        try:
            s = np.asarray(f["s"][()], dtype=float)
            h0 = np.asarray(f["h0"][()], dtype=float)
            g = f["bonds"]
            bonds = Bonds(g["i"][()], g["j"][()], g["shift"][()], g["l0"][()])
            z0 = float(f.attrs["z0"])
            seed = int(f.attrs["seed"])
            info = _read_info(f["info"]) if "info" in f else {}
        except KeyError as e:
            raise InputError(f"{path!r}: corrupt parflow network, missing {e}") from None
    if s.ndim != 2 or h0.shape != (s.shape[1], s.shape[1]) or bonds.shift.shape[1] != s.shape[1]:
        raise InputError(f"{path!r}: corrupt parflow network: inconsistent shapes "
                         f"s {s.shape}, h0 {h0.shape}, shift {bonds.shift.shape}")
    bonds.validate(s.shape[0])
    ell = np.linalg.norm(bond_vectors(s, h0, bonds), axis=1)
    err = float(np.max(np.abs(ell - bonds.l0) / bonds.l0))
    if not err <= 1e-12:
        raise InputError(f"{path!r}: corrupt parflow network: rest lengths differ from the "
                         f"node geometry by up to {err:.3g} (relative)")
    return Network(s=s, h0=h0, bonds=bonds, z0=z0, seed=seed, info=info)
