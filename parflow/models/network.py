"""Floppy rod networks in simple shear (paper §III, Figs. 3-5 and 8; DESIGN §6).

The network is built by the WLKM protocol (``network_build``): a jammed soft-disc packing
of ``N`` particles, a rod on every contact, diluted to coordination ``z < 2d``.  It is then
sheared with Lees-Edwards boundaries: the cell h(gamma) = [[Lx, gamma Ly], [0, Ly]] follows
the flow V_f = (y, 0) (the core does this: dh/dgamma = E h); bonds carry their image shifts,
r_a = h (s_j + n_a - s_i), and the affine rate of a rod is b_a = n_a . E r_a = x_a y_a / r_a.

Analyses (at the instants the scene asks for, with the factor of N loaded at that instant):

* point response: for a handful of rods beta, N f = |beta> and V = S^T f (the velocities
  when rod beta alone is made to extend at unit rate).  |V_i| and |f_a| are binned by the
  minimum-image distance from the midpoint of beta and averaged over the rods; the V profile
  is fitted by A exp(-r/l_c) + B exp(-r/l_r) (l_c: the initial decay, l_r: the slow tail).
  <V|V> = f_beta (= f^T N f).
* velocity correlation C(r) = <V_i . V_j> / <V^2> of V_na, pairs binned by minimum-image
  distance up to r_max: exactly, in row blocks (memory O(block), time O(N^2)), or by FFT on
  a grid (time O(N log N); bins below CORR_R_EXACT exact, the others to the grid resolution);
  ``corr_method = "auto"`` picks the FFT above CORR_EXACT_MAX nodes.
* spectrum of N: omega = sqrt(lambda(N)); all of it (dense eigvalsh, Nc <= DENSE_MAX) or
  the lowest ``n_low`` (SLEPc shift-and-invert).

Distances: reduced displacements in a *remapped* cell h_r = h U (U unimodular, tilt
reduced to |h_r[0,1]| <= Lx/2, the Lees-Edwards remapping), minus rint, times h_r.  For
r <= half the smallest height of the cell (the default r_max) this is the true minimum image.
"""
from __future__ import annotations

import math

import numpy as np

from ..geometry import pair_vectors, rigidity_csr, velocity_gradient
from ..observables.correlation import (CORR_EXACT_MAX, CORR_GRID_MAX, CORR_METHODS,  # noqa: F401
                                      correlation, crossing_length)
from ..observables.response import fit_two_exponentials, pick_rods, point_response
from ..algebra.spectrum import omega_from_lambda, on_force_factor
from ..state import Bonds, InputError, Instant, State
from . import network_build as _nb

NAME = "network"
ENGINE = "bonded"
FLOW = "shear"
Z_RANGE = (3.5, 3.98)
DENSE_MAX = 10_000
# the force solve at the end of a step may reuse the step's factor (solver.reuse_factor =
# "auto" above dynamics.bonded.REUSE_AUTO_MIN_NC rods): a 2D network's factor costs ~20-30 solves
FACTOR_REUSE = True
omega_min = None            # the bonded engine's, on its force factor
SPECTRA = ("none", "dense", "low", "auto")

PARAMS = {
    # name: (type, default, check, description)
    "N": (int, 4096, lambda v: v >= _nb.MIN_NODES,
          f"number of particles of the packing (>= {_nb.MIN_NODES}); rattlers are dropped"),
    "d": (int, 2, lambda v: v == 2, "2 (3D networks come later)"),
    "z": (float, 3.8, lambda v: Z_RANGE[0] <= v <= Z_RANGE[1],
          f"in [{Z_RANGE[0]}, {Z_RANGE[1]}]: a floppy network needs z < 2d = 4, and the WLKM "
          f"dilution (no node below d + 1 = 3 rods) cannot reliably go below ~3.5"),
    "phi": (float, _nb.DEFAULT_PHI, lambda v: 0.0 < v < 1.0,
            "packing fraction of the seed packing, in (0, 1) (0.86-0.90 gives z0 ~ 4.4-5)"),
    "pressure": (float, 0.0, lambda v: v >= 0.0,
                 ">= 0: target pressure of the packing (0: use phi instead)"),
    "network_file": (str, "", lambda v: True,
                     "network HDF5 file (network_build.save_network) to load; '' generates one"),
    "response_rods": (int, 8, lambda v: v >= 1, "number of rods beta for the point response (>= 1)"),
    "response_dr": (float, 0.5, lambda v: v > 0, "bin width of the point-response profiles (> 0)"),
    "corr_dr": (float, 0.5, lambda v: v > 0, "bin width of C(r) (> 0)"),
    "corr_rmax": (float, 0.0, lambda v: v >= 0,
                  ">= 0: largest distance of C(r) (0: half the smallest height of the cell)"),
    "correlation": (bool, True, lambda v: True, "true/false: compute C(r) at analysis instants"),
    "corr_method": (str, "auto", lambda v: v in CORR_METHODS,
                    f"one of {list(CORR_METHODS)}: C(r) over all pairs (exact, O(N^2)), by FFT on "
                    f"a grid (O(N log N)), or auto: exact up to {CORR_EXACT_MAX} nodes"),
    "corr_spacing": (float, 0.0, lambda v: v >= 0,
                     ">= 0: grid spacing of the FFT C(r) (0: corr_dr / 4, coarser beyond "
                     f"{CORR_GRID_MAX} grid points)"),
    "spectrum": (str, "none", lambda v: v in SPECTRA,
                 f"one of {list(SPECTRA)}: spectrum of N at analysis instants (dense: "
                 f"all of it, Nc <= {DENSE_MAX}; low: the n_low lowest; auto: dense if possible)"),
    "n_low": (int, 10, lambda v: v >= 1, "number of lowest eigenvalues for spectrum = 'low' (>= 1)"),
    "dos_bins": (int, 60, lambda v: v >= 2, "number of log-spaced bins of D(omega) (>= 2)"),
}
# the analysis settings are recorded in State.meta (the run file's /model attributes); the
# analyses read them from the scene (Instant.scene), like every model parameter
_ANALYSIS_KEYS = ("response_rods", "response_dr", "corr_dr", "corr_rmax", "correlation",
                  "corr_method", "corr_spacing", "spectrum", "n_low", "dos_bins")


# --------------------------------------------------------------------------- building

def check_z(z: float, d: int = 2) -> None:
    if not (isinstance(z, (int, float)) and math.isfinite(z)):
        raise InputError(f"model.z must be a finite number, got {z!r}")
    if z >= 2 * d:
        raise InputError(f"model.z = {z:g}: a floppy network needs z < 2d = {2 * d} "
                         f"(z = 2d is isostatic); use z in [{Z_RANGE[0]}, {Z_RANGE[1]}]")
    if z < Z_RANGE[0] or z > Z_RANGE[1]:
        raise InputError(f"model.z = {z:g} is outside [{Z_RANGE[0]}, {Z_RANGE[1]}]: too close "
                         f"to 2d = {2 * d} (dz < 0.02) or below what the WLKM dilution reaches "
                         f"without floppy appendages")


def _defaults(params: dict) -> dict:
    p = {k: v[1] for k, v in PARAMS.items()}
    p.update(params)
    return p


def make(params: dict, seed: int) -> "_nb.Network":
    """The WLKM network the scene describes (generated, not loaded)."""
    p = _defaults(params)
    check_z(p["z"], p["d"])
    if p["pressure"] > 0:
        pk = _nb._pk.make_packing(p["N"], None, d=p["d"], seed=seed, pressure=p["pressure"])
    else:
        pk = _nb._pk.make_packing(p["N"], p["phi"], d=p["d"], seed=seed)
    return _nb.network_from_packing(pk, p["z"], seed=seed)


def check_matches(net: "_nb.Network", params: dict, seed: int, path: str = "") -> None:
    """InputError listing every way a loaded network differs from the scene."""
    p = _defaults(params)
    bad = []
    pinfo = net.info.get("packing", {}) if isinstance(net.info, dict) else {}
    if net.d != p["d"]:
        bad.append(f"d = {net.d} (scene: {p['d']})")
    n_pk = pinfo.get("n")
    if n_pk is not None and int(n_pk) != p["N"]:
        bad.append(f"N = {int(n_pk)} particles (scene: model.N = {p['N']})")
    if abs(net.z - p["z"]) > 1.0 / net.n + 1e-12:
        bad.append(f"z = {net.z:.6g} (scene: model.z = {p['z']:g})")
    if int(net.seed) != int(seed):
        bad.append(f"seed = {net.seed} (scene: seed = {seed})")
    if p["pressure"] > 0:
        pp = pinfo.get("pressure")
        if pp is not None and abs(pp / p["pressure"] - 1) > 0.05:
            bad.append(f"packing pressure = {pp:.4g} (scene: model.pressure = {p['pressure']:g})")
    else:
        ph = pinfo.get("phi")
        if ph is not None and abs(ph - p["phi"]) > 1e-9:
            bad.append(f"packing phi = {ph:.6g} (scene: model.phi = {p['phi']:g})")
    if bad:
        raise InputError(f"model.network_file {path!r} does not match the scene: "
                         + "; ".join(bad) + ". Fix the scene, or set network_file = '' to "
                         "generate the network")


def build(params: dict, seed: int) -> State:
    p = _defaults(params)
    check_z(p["z"], p["d"])
    path = p["network_file"]
    if path:
        net = _nb.load_network(path)
        check_matches(net, p, seed, path)
    else:
        net = make(p, seed)
    return state_from_network(net, p, path)


def state_from_network(net: "_nb.Network", params: dict | None = None, path: str = "") -> State:
    p = _defaults(params or {})
    d = net.d
    bd = net.bonds
    bonds = Bonds(bd.i.copy(), bd.j.copy(), bd.shift.copy(), bd.l0.copy())
    state = State(np.array(net.s, dtype=float), np.array(net.h0, dtype=float),
                  velocity_gradient(FLOW, d), 0.0, bonds)
    info = net.info if isinstance(net.info, dict) else {}
    pinfo = info.get("packing", {})
    meta = dict(model="network", z=float(net.z), z_target=float(p["z"]), dz=2.0 * d - net.z,
                n_nodes=net.n, n_bonds=len(bd), z0=float(net.z0), network_seed=int(net.seed),
                network_file=path, fabric_ratio=float(info.get("fabric_ratio", np.nan)),
                min_degree=int(info.get("min_degree", -1)))
    for k in ("n", "phi", "pressure", "z", "n_rattlers"):
        if k in pinfo:
            meta[f"packing_{k}"] = int(pinfo[k]) if k in ("n", "n_rattlers") else float(pinfo[k])
    if isinstance(info.get("self_stress"), dict):
        meta["self_stresses"] = int(info["self_stress"]["self_stresses"])
    meta.update({k: (int(v) if isinstance(v, bool) else v)
                 for k, v in p.items() if k in _ANALYSIS_KEYS})
    state.meta.update(meta)
    return state


def observables(state: State, F) -> dict:
    """z (fixed), and the fraction of rods in tension (tau < 0)."""
    return dict(z=2.0 * len(state.bonds) / state.n,
                tension_fraction=float(np.count_nonzero(F.tau < 0)) / max(F.tau.size, 1))


def dense_N(n_unit: np.ndarray, bonds: Bonds, n_nodes: int) -> np.ndarray:
    """Dense N = S S^T from the unit vectors (sparse S, vectorised)."""
    S = rigidity_csr(n_unit, bonds.i, bonds.j, n_nodes)
    return (S @ S.T).toarray()


def dense_spectrum(n_unit: np.ndarray, bonds: Bonds, n_nodes: int) -> np.ndarray:
    """All omega = sqrt(lambda(N)), ascending (numpy eigvalsh)."""
    lam = np.linalg.eigvalsh(dense_N(n_unit, bonds, n_nodes))
    return np.sqrt(np.clip(lam, 0.0, None))


def density_of_states(omega: np.ndarray, bins: int) -> tuple[np.ndarray, np.ndarray]:
    """D(omega) normalised to 1 over log-spaced bins from the smallest positive omega to the
    largest: returns (bin edges, D)."""
    pos = omega[omega > 0]
    if pos.size < 2:
        return np.zeros(bins + 1), np.zeros(bins)
    edges = np.geomspace(pos[0] * (1 - 1e-12), pos[-1] * (1 + 1e-12), bins + 1)
    hist, _ = np.histogram(omega, edges)
    return edges, hist / (omega.size * np.diff(edges))


def _bcast(system, value):
    comm = system.comm
    if comm.getSize() == 1:
        return value
    return comm.tompi4py().bcast(value, root=0)


def analyses(at: Instant) -> dict:
    """Point response, C(r) and the spectrum of N at the current configuration.

    ``at.state`` must carry the current positions (state.s at F.gamma): checked against F.r."""
    system, state, F = at.system, at.state, at.F
    meta = at.scene["model"]
    bd, s, h = state.bonds, state.s, F.h
    mism = float(np.max(np.abs(pair_vectors(s, h, bd.i, bd.j, bd.shift) - F.r)))
    if not mism <= 1e-8 * max(1.0, float(np.abs(h).max())):
        raise RuntimeError(f"network.analyses: the positions given do not match the force "
                           f"evaluation (pair vectors differ by {mism:.3g}): the driver must pass "
                           f"the current state")
    # the factor in the solver may belong to a rejected trial step (e.g. after Jammed):
    # reload N at this configuration (one numeric refactorisation at the next solve)
    system.load(F.n)
    arrays, scalars = {}, {}
    # (a) point response
    rods = pick_rods(s, h, bd, int(meta["response_rods"]))
    pr = point_response(system, s, h, bd, rods, float(meta["response_dr"]))
    fit = fit_two_exponentials(pr["r"], pr["V_mean"], pr["counts_V"])
    fit_f = fit_two_exponentials(pr["r"], pr["f_mean"], pr["counts_f"])
    arrays.update(resp_r=pr["r"], resp_V=pr["V_mean"], resp_V_rms=pr["V_rms"],
                  resp_f=pr["f_mean"], resp_counts_V=pr["counts_V"], resp_counts_f=pr["counts_f"],
                  resp_rods=rods, resp_VV=pr["VV"])
    scalars.update({f"resp_{k}": v for k, v in fit.items()})
    scalars.update({f"resp_f_{k}": v for k, v in fit_f.items()})
    scalars["VV"] = float(np.mean(pr["VV"]))
    scalars["VV_err"] = float(np.std(pr["VV"]) / np.sqrt(len(pr["VV"])))
    # (b) velocity correlation of V_na
    if meta["correlation"]:
        # computed on rank 0 and broadcast: identical on every rank, one copy of the grid
        cr = None
        if system.comm.getRank() == 0:
            cr = correlation(s, h, F.V_na, float(meta["corr_dr"]), float(meta["corr_rmax"]),
                             str(meta["corr_method"]), float(meta["corr_spacing"]))
        cr = _bcast(system, cr)
        arrays.update(corr_r=cr["r"], corr_C=cr["C"], corr_counts=cr["counts"])
        scalars["corr_length"] = crossing_length(cr["r"], cr["C"], counts=cr["counts"])
        scalars["corr_method"] = cr["method"]
        if cr["method"] == "fft":
            scalars.update(corr_eps=float(cr["eps"]),
                           corr_r_exact=cr["n_exact"] * float(meta["corr_dr"]))
    # (c) spectrum
    mode = meta["spectrum"]
    if mode == "auto":
        mode = "dense" if len(bd) <= DENSE_MAX else "low"
    if mode == "dense":
        if len(bd) > DENSE_MAX:
            raise InputError(f"model.spectrum = 'dense' needs Nc <= {DENSE_MAX} (Nc = {len(bd)}): "
                             f"use 'low' or 'auto'")
        omega = dense_spectrum(F.n, bd, state.n) if system.comm.getRank() == 0 else None
        omega = _bcast(system, omega)
        edges, D = density_of_states(omega, int(meta["dos_bins"]))
        arrays.update(omega=omega, dos_edges=edges, dos=D)
        scalars["omega_min_dense"] = float(omega[0])
    elif mode == "low":
        spec = on_force_factor(system, int(meta["n_low"]))    # no second factorisation
        try:
            lam, _ = spec.solve()
        finally:
            spec.destroy()
        omega = omega_from_lambda(lam)
        arrays.update(omega_low=omega)
        scalars["omega_min_low"] = float(omega[0])
    return dict(arrays=arrays, scalars=scalars)
