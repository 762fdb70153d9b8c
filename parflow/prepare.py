"""Prepare a suspension configuration from a saved run: compress a flowing state.

    python -m parflow.prepare compress RUN.h5 --phi 0.840 --out out/conf.npz [--from checkpoint]
    python -m parflow.prepare compress ENSEMBLE_FOLDER --phi 0.840 --out 'out/conf_{sample}.npz'

A hard-disc state taken from a run (its checkpoint, or its initial state) is compressed to a
higher packing fraction at fixed radii: the box and the positions are scaled affinely, and
the overlaps this creates (a relative compression of (phi_0/phi)^(1/2), 0.3 % from 0.835 to
0.840) are removed by the same FIRE minimisation with radii inflated by 1e-6 that builds the
initial states (``suspension.make_suspension``), started from the compressed positions
instead of random ones.  The structure the flow built is kept up to those small moves.  The
result is an .npz for a scene's ``model.configuration_file`` (positions, radii, box, gamma = 0)
with what it was made from (source file, step, strain, phi_0, FIRE iterations, smallest gap).

The state must sit at a strain where the Lees-Edwards cell is a rectangle again
(gamma * Ly / Lx an integer: the end of a leg of integer strain, e.g. the 3.0 + 1.0 of the
Fig. 6 scenes), since the minimiser works in a rectangular periodic box.

An ensemble's output folder compresses every sample file in it, into one .npz per sample
(``{sample}`` in --out: the 4-digit index); an ensemble scene whose
``model.configuration_file`` holds ``{sample}`` then starts sample k from file k
(``parflow.ensemble``; docs/ensembles.md).  The files are written one by one (each whole, by a
rename); a sample whose compressed state does not relax (it is jammed at that phi) is
reported and the others go on (exit 1 if some failed, 2 if all did).
"""
from __future__ import annotations

import argparse
import os
import sys

import numpy as np

from .ensemble import SAMPLE_FIELD
from .dynamics.hard_discs import swollen_radii
from .geometry import MinImage, cell_at, velocity_gradient
from .io import RunFile, check_output_path
from .models import suspension as su
from .packing.pairs import pair_list
from .post.ensemble import sample_files
from .state import InputError


def rectangular_positions(s: np.ndarray, h0: np.ndarray, gamma: float) -> np.ndarray:
    """Positions (N, 2) in the rectangular box diag(h0) of a state at strain ``gamma`` whose
    sheared cell is a rectangle again (gamma * Ly / Lx an integer)."""
    Lx, Ly = float(h0[0, 0]), float(h0[1, 1])
    if abs(h0[0, 1]) > 0 or abs(h0[1, 0]) > 0:
        raise InputError("prepare: the run's reference cell is not rectangular")
    k = gamma * Ly / Lx
    if abs(k - round(k)) > 1e-9:
        raise InputError(f"prepare: the state is at strain gamma = {gamma:.10g}, where the "
                         f"Lees-Edwards cell is not a rectangle (gamma * Ly / Lx = {k:.6g} is not "
                         f"an integer); take a state at the end of a leg of integer strain, or "
                         f"the initial state (--from initial)")
    h = cell_at(h0, velocity_gradient("shear", 2), gamma)
    r = s @ h.T
    box = np.array([Lx, Ly])
    return r - np.floor(r / box) * box


def compress(X: np.ndarray, radii: np.ndarray, box: np.ndarray, phi: float,
             inflate: float = 1e-6, max_iter: int = 2_000_000) -> tuple[np.ndarray, np.ndarray, dict]:
    """Positions X (N, 2) of non-overlapping discs in ``box``, compressed at fixed radii to
    packing fraction ``phi`` and relaxed until no pair of discs inflated by (1 + inflate)
    overlaps.  Returns (positions, box, info).  InputError if phi is not above the current
    packing fraction, or if the compressed state does not relax (it is jammed at phi)."""
    su.check_phi(phi)
    phi0 = float(np.pi * np.sum(radii ** 2) / np.prod(box))
    if not phi > phi0:
        raise InputError(f"prepare: --phi {phi} is not above the state's packing fraction "
                         f"{phi0:.6g} (compress only)")
    scale = np.sqrt(phi0 / phi)
    box1 = box * scale
    X1 = np.ascontiguousarray((X * scale).T)
    pl = pair_list(radii * (1.0 + inflate), box1, 0.4, "auto")
    X1, n_overlap, info = su.relax_overlaps(X1, radii, pl, max_iter)
    if n_overlap != 0:
        left = "FIRE did not converge" if n_overlap < 0 else f"{n_overlap} overlapping pairs"
        raise InputError(f"prepare: the state compressed to phi = {phi} does not relax to a "
                         f"non-overlapping one ({left} after {info['iterations']} FIRE "
                         f"iterations): it is jammed there")
    pos = (X1.T - np.floor(X1.T / box1) * box1)
    return pos, box1, dict(phi0=phi0, fire_iterations=int(info["iterations"]),
                           rms_move=float(np.sqrt(np.mean(np.sum(
                               MinImage(np.diag(box1)).vectors((pos - X * scale) / box1) ** 2,
                               axis=1)))))


def load_run_state(path: str, which: str = "checkpoint"):
    """(s, h0, gamma, radii, step) of a suspension run file's checkpoint or initial state."""
    with RunFile(path) as run:
        init = run.initial()
        if "radii" not in init:
            raise InputError(f"prepare: {path!r} is not a suspension run (no initial/radii)")
        h0, radii = init["h0"], init["radii"]
        if which == "initial":
            return init["s"], h0, 0.0, radii, 0
        if not run.has_checkpoint:
            raise InputError(f"prepare: {path!r} has no checkpoint (use --from initial)")
        ck = run.checkpoint()
        if "phi" in ck:             # a run that compressed while shearing: the swollen radii
            radii = swollen_radii(radii, abs(np.linalg.det(h0)), float(ck["phi"]))
        return ck["s"], h0, float(ck["gamma"]), radii, int(ck["step"])


def ensemble_runs(folder: str) -> list[tuple[int, str]]:
    """(index, path) of the sample files of an ensemble folder (``FOLDER/ensemble.h5``)."""
    if not os.path.isfile(os.path.join(folder, "ensemble.h5")):
        raise InputError(f"prepare: {folder!r} is a directory but not an ensemble folder (no "
                         f"ensemble.h5): give a run file or an ensemble's output folder")
    out = sample_files(folder)
    if not out:
        raise InputError(f"prepare: the ensemble folder {folder!r} holds no sample file")
    return out


def _compress_one(run: str, phi: float, out: str, overwrite: bool, which: str) -> str:
    """Compress the state of one run file into ``out`` (.npz, written whole by a rename);
    the line that reports it.  InputError for bad input, OSError if it cannot be written."""
    s, h0, gamma, radii, step = load_run_state(run, which)
    if os.path.exists(out) and os.path.exists(run) and os.path.samefile(run, out):
        raise InputError(f"prepare: --out {out!r} is the run file itself")
    check_output_path(out, overwrite, "--out")
    X = rectangular_positions(s, h0, gamma)
    box = np.array([h0[0, 0], h0[1, 1]])
    pos, box1, info = compress(X, radii, box, phi)
    state = su.from_configuration(pos, radii, box1, 0.0)    # checks: no overlap, phi < phi_J
    gap = su.min_gap(state)
    tmp = out[:-4] + ".part.npz"
    try:
        np.savez(tmp, positions=pos, radii=radii, box=box1, gamma=0.0, source=os.path.abspath(run),
                 source_state=which, source_step=step, source_gamma=gamma, phi0=info["phi0"],
                 phi=state.meta["phi"], fire_iterations=info["fire_iterations"],
                 rms_move=info["rms_move"], min_gap=gap)
        os.replace(tmp, out)
    except OSError:                     # checked above; the disk can still fill up
        if os.path.exists(tmp):
            os.remove(tmp)
        raise
    return (f"{out}: N = {len(radii)}, phi {info['phi0']:.6g} -> {state.meta['phi']:.6g} "
            f"(from the {which} of {run}, step {step}, gamma = {gamma:.6g}); "
            f"{info['fire_iterations']} FIRE iterations, rms move {info['rms_move']:.3g} a0, "
            f"smallest gap {gap:.3g} a0")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m parflow.prepare", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("compress", help="compress a run's state to a higher packing fraction")
    c.add_argument("run", help="a suspension run file (HDF5, from python -m parflow.shear), or "
                   "an ensemble's output folder (every sample file in it)")
    c.add_argument("--phi", type=float, required=True, help="target packing fraction")
    c.add_argument("--out", required=True, help="output .npz (a scene's model.configuration_file); "
                   "missing folders are created; for an ensemble folder it must hold {sample}, "
                   "replaced by each sample's 4-digit index")
    c.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    c.add_argument("--from", dest="which", choices=("checkpoint", "initial"), default="checkpoint",
                   help="the run's state to start from (default: its checkpoint, the last state)")
    a = ap.parse_args(argv)
    try:
        if not a.out.endswith(".npz") or not os.path.basename(a.out)[:-4]:
            raise InputError(f"prepare: --out must be a file name ending in .npz, got {a.out!r}")
        if not np.isfinite(a.phi):
            raise InputError(f"prepare: --phi must be a finite number, got {a.phi}")
        if os.path.isdir(a.run):
            if SAMPLE_FIELD not in a.out:
                raise InputError(f"prepare: {a.run!r} is an ensemble folder: --out must hold "
                                 f"{SAMPLE_FIELD} (one file per sample), got {a.out!r}")
            jobs = [(path, a.out.replace(SAMPLE_FIELD, f"{k:04d}"))
                    for k, path in ensemble_runs(a.run)]
        elif SAMPLE_FIELD in a.out:
            raise InputError(f"prepare: --out {a.out!r} holds {SAMPLE_FIELD}, which is for an "
                             f"ensemble folder; {a.run!r} is not one")
        else:
            jobs = [(a.run, a.out)]
        if len(jobs) == 1:
            print(_compress_one(jobs[0][0], a.phi, jobs[0][1], a.overwrite, a.which), flush=True)
            return 0
        failed = []
        for run, out in jobs:        # an ensemble: a sample that does not relax is reported
            try:
                print(_compress_one(run, a.phi, out, a.overwrite, a.which), flush=True)
            except InputError as exc:
                failed.append(f"{os.path.basename(run)}: {str(exc).removeprefix('prepare: ')}")
        if failed:
            print(f"parflow.prepare: error: {len(failed)} of {len(jobs)} samples not compressed "
                  f"(their start files are missing: the ensemble records those samples as "
                  f"failed): " + "; ".join(failed), file=sys.stderr)
            return 2 if len(failed) == len(jobs) else 1
    except InputError as exc:
        print(f"parflow.prepare: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"parflow.prepare: error: cannot write {getattr(exc, 'filename', None) or a.out!r}: "
              f"{exc.strerror or exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
