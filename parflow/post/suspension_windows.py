"""Is a suspension run stationary?  Its averages in consecutive windows of equal strain.

    python -m parflow.post.suspension_windows RUN.h5 [RUN.h5 ...] [--width 1.0]
        [--from-strain X] [--to-strain Y] [--json OUT]

The paper sheared its suspensions 300 % before it collected statistics, and a run's
statistics window (``observables.analysis_from_strain``) takes the state past it for
stationary.  This checks it: the forward steps of each run from ``--from-strain`` (default:
the first row at the run's final phi -- where a run compressed while it flowed reached
``compress_to`` -- or its first row) to ``--to-strain`` (default: its end), cut into windows
of ``--width`` strain (a last window shorter than half a width joins the one before).  Per
window: sigma, the pressure p, mu = sigma/p and z2 averaged with each step weighted by its
strain, each with its block error (as ``post.suspension.suspension_fits`` averages its
statistics window), and the median sigma of the steps.  Per run: the same over the whole
range, and the drift of each quantity -- the slope of a straight line through the window
means, weighted by their errors, per unit strain, with its error (three windows or more).
Several runs: the whole-range means averaged over the runs, with their standard error over
runs (the seed-to-seed scatter, which at phi = 0.840 exceeds the error within one run).

Exit status 2 with one line on stderr for a missing or unreadable file, a run that is not a
suspension, or a range that holds no steps.
"""
from __future__ import annotations

import argparse
import math
import sys

import numpy as np

from .ensemble import final_phi_row, mean_sem
from .network_across_ensembles import missing_path, print_and_save
from .runs import load
from .suspension import _mean_err, forward_steps

QUANTITIES = ("sigma", "pressure", "mu", "z2")


def start_strain(ts) -> float:
    """The strain (at the end of the step) of the first row at the run's final phi, or of the
    first row without a phi column."""
    strain = np.asarray(ts["strain"], float)
    phi = ts.get("phi")
    row = final_phi_row(phi, float(phi[-1])) if phi is not None and len(phi) else 0
    return float(strain[row or 0])


def _averages(ts, m: np.ndarray) -> dict:
    dg = np.abs(np.asarray(ts.get("dgamma", np.ones(len(m))), float))
    out = dict(steps=int(m.sum()), strain=float(dg[m].sum()))
    for q in QUANTITIES:
        if q in ts:
            mean, err = _mean_err(np.asarray(ts[q], float)[m], dg[m])
            out[q] = (mean, err)
    out["sigma_median"] = float(np.median(np.asarray(ts["sigma"], float)[m]))
    return out


def drift(centres, means, errs) -> tuple[float, float]:
    """Slope and its error of the straight line through (centres, means) weighted by 1/errs²
    (NaN with fewer than three points or an error that is not positive)."""
    c, y, e = (np.asarray(v, float) for v in (centres, means, errs))
    ok = np.isfinite(c) & np.isfinite(y) & np.isfinite(e) & (e > 0)
    if ok.sum() < 3:
        return math.nan, math.nan
    c, y, w = c[ok], y[ok], 1.0 / e[ok] ** 2
    cm = np.sum(w * c) / np.sum(w)
    sxx = float(np.sum(w * (c - cm) ** 2))
    if not sxx > 0:
        return math.nan, math.nan
    return float(np.sum(w * (c - cm) * y) / sxx), 1.0 / math.sqrt(sxx)


def run_windows(path: str, width: float = 1.0, from_strain: float | None = None,
                to_strain: float | None = None) -> dict:
    """The windows of one run file (the module docstring); ValueError for a run that is not
    a suspension or a range without steps."""
    if not width > 0:
        raise ValueError(f"--width must be > 0, got {width}")
    run = load(path)
    if run.model != "suspension":
        raise ValueError(f"{path}: a {run.model or 'unknown'} run, not a suspension")
    ts = run.ts
    if "sigma" not in ts or "strain" not in ts or not len(ts["strain"]):
        raise ValueError(f"{path}: no time series of sigma and strain")
    strain = np.asarray(ts["strain"], float)
    lo = start_strain(ts) if from_strain is None else float(from_strain)
    hi = float(strain[-1]) if to_strain is None else min(float(to_strain), float(strain[-1]))
    fwd = forward_steps(ts)
    inside = fwd & (strain > lo) & (strain <= hi)
    if not inside.any():
        raise ValueError(f"{path}: no forward steps between strain {lo:g} and {hi:g} (the run "
                         f"ends at {float(strain[-1]):g})")
    n = max(1, int(math.floor((hi - lo) / width + 0.5)))       # a short last window joins
    edges = lo + width * np.arange(n + 1, dtype=float)
    edges[-1] = hi
    windows = []
    for a, b in zip(edges[:-1], edges[1:]):
        m = fwd & (strain > a) & (strain <= b)
        if m.any():
            windows.append(dict(lo=float(a), hi=float(b), **_averages(ts, m)))
    whole = dict(lo=lo, hi=hi, **_averages(ts, inside))
    centres = [0.5 * (w["lo"] + w["hi"]) for w in windows]
    drifts = {}
    for q in QUANTITIES:
        if q in whole:
            s, e = drift(centres, [w[q][0] for w in windows], [w[q][1] for w in windows])
            drifts[q] = dict(slope=s, err=e)
    return dict(path=path, status=str(run.attrs.get("status", "")),
                N=int(run.param("N", 0) or 0),
                phi=float(ts["phi"][-1]) if "phi" in ts else float(run.param("phi", math.nan)),
                windows=windows, whole=whole, drift=drifts)


def analyse(paths, width: float = 1.0, from_strain: float | None = None,
            to_strain: float | None = None) -> dict:
    runs = [run_windows(p, width, from_strain, to_strain) for p in paths]
    across = {}
    if len(runs) > 1:
        for q in QUANTITIES:
            v = [r["whole"][q][0] for r in runs if q in r["whole"]]
            if len(v) > 1:
                mean, sem, _ = mean_sem(v)
                across[q] = (float(mean), float(sem))
    return dict(width=width, runs=runs, across=across)


def _fmt(v: tuple) -> str:
    mean, err = v
    return f"{mean:.4g} ± {err:.2g}"


def format_table(res: dict) -> list[str]:
    lines = []
    for r in res["runs"]:
        lines.append(f"{r['path']} (N = {r['N']}, phi = {r['phi']:.4f}, {r['status']}): "
                     f"windows of {res['width']:g} strain")
        lines.append("  strain        steps  " + "  ".join(f"{q:>18s}" for q in QUANTITIES)
                     + "  median sigma")
        for w in r["windows"] + [dict(r["whole"], whole=True)]:
            span = f"{w['lo']:.2f}-{w['hi']:.2f}" + (" all" if w.get("whole") else "")
            lines.append(f"  {span:12s} {w['steps']:6d}  "
                         + "  ".join(f"{_fmt(w[q]) if q in w else '':>18s}" for q in QUANTITIES)
                         + f"  {w['sigma_median']:12.4g}")
        d = [f"{q} {v['slope']:+.3g} ± {v['err']:.2g}" for q, v in r["drift"].items()
             if math.isfinite(v["slope"])]
        lines.append("  drift per unit strain: " + ("; ".join(d) if d else
                                                    "n/a (fewer than three windows)"))
    if res["across"]:
        lines.append(f"across {len(res['runs'])} runs (whole ranges; standard error over runs): "
                     + "; ".join(f"{q} {_fmt(v)}" for q, v in res["across"].items()))
    return lines


def command_line(argv, prog: str, description: str, more=None):
    """(args, :func:`analyse` of them) for a command line of runs and windows, ``more(ap)``
    adding its own arguments (shared with ``plot.suspension_windows``); (args, None) after
    one line on stderr for a missing file, one that is not a suspension run or a bad range
    (the command lines then exit 2)."""
    ap = argparse.ArgumentParser(prog=prog, description=description)
    ap.add_argument("paths", nargs="+", metavar="RUN", help="suspension run files (.h5)")
    ap.add_argument("--width", type=float, default=1.0, help="strain per window (default 1)")
    ap.add_argument("--from-strain", type=float, default=None,
                    help="start of the first window (default: where the run reached its final "
                    "phi)")
    ap.add_argument("--to-strain", type=float, default=None,
                    help="end of the last window (default: the end of the run)")
    if more is not None:
        more(ap)
    args = ap.parse_args(argv)
    name = prog.rsplit(".", 1)[-1]
    if missing_path(args.paths, name):
        return args, None
    try:
        return args, analyse(args.paths, args.width, args.from_strain, args.to_strain)
    except ValueError as e:                 # InputError (not a run file) is one too
        print(f"{name}: {e}", file=sys.stderr)
        return args, None


def main(argv=None) -> int:
    args, res = command_line(
        argv, "python -m parflow.post.suspension_windows",
        "A suspension run's averages in windows of equal strain, and their drift: is it "
        "stationary?",
        lambda ap: ap.add_argument("--json", metavar="OUT", help="write the result as JSON"))
    if res is None:
        return 2
    print_and_save(res, format_table, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
