"""Statistics of an ensemble folder (``parflow.ensemble``, docs/ensembles.md): the summary
file ``FOLDER/summary.h5``, computed from the sample files ``FOLDER/sample_NNNN.h5``.

Only samples whose file says complete, jammed or budget enter the statistics (the others are
listed with their status).  For each quantity: the per-sample values (NaN where a sample has
none), and over the finite ones the mean, the standard error s / sqrt(n) (s the sample
standard deviation, ddof = 1; NaN for n < 2) and the count n.

* ``scalars/NAME``: the last time-series row of each sample (``final_sigma``, ``final_V2``,
  ``final_gamma``, ``final_strain``, ``steps``, ...).
* ``fits/NAME``: each sample's fitted numbers (``post.chain.chain_fits``,
  ``post.network.network_fits``), flattened to names like ``forward.attr.V2.0`` (an
  exponent) -- each with mean and standard error over the samples.
* ``curves/NAME``: curves on a common grid (``x``): per sample (rows), the mean, standard
  error and count at each grid point (a sample counts where the grid lies inside its own
  range): ``sigma_leg{L}`` against the strain since the start of leg L (every model),
  ``V2_forward`` against gamma_c - gamma on the chain's forward leg (log grid, log-log
  interpolation), ``dsigma_dgamma_reverse`` (|dsigma/dgamma|, finite differences of
  ``post.network.reverse_branch``) against sigma on a network's first reversed leg (log grid);
  ``profile_NAME``: the model's profiles (:data:`PROFILES`: the chain's C(n) and point
  response, the network's C(r) and point responses V(r), f(r)) at each sample's last analysis
  instant on its first forward leg, on a linear grid; a suspension's P(f/<f>), C(r) and
  point responses (:data:`SUSPENSION_PROFILES`) as each sample's mean over the analysis
  instants of its statistics window (steady flow: every instant there is a sample of it).
* ``ensemble_fits/NAME``: numbers fitted to the averaged curves, with jackknife errors
  (leave one sample out, refit: err^2 = (n - 1)/n sum_i (f_i - mean f_i)^2): the chain's
  <V^2> exponent against gamma_c - gamma; ``jamming_rate``, shear jams per unit strain with
  its Poisson error (:func:`jamming_rate`).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import re
import sys
import tomllib

import numpy as np

from ..io import atomic_h5, open_hdf5
from .chain import chain_fits
from .fits import (BINS_PER_DECADE, fit_power_law, fit_window, forward_instants, forward_rows,
                   reverse_rows)
from .network import network_fits, reverse_branch
from .suspension import suspension_fits, window_instants
from .runs import Run, load

SUMMARY_FORMAT = "parflow-ensemble-summary-1"
DONE = ("complete", "jammed", "budget")
GRID_POINTS = 128


def suspension_numbers(run) -> dict:
    """A suspension sample's numbers for the summary: the averages of ``suspension_fits``
    over its statistics window (sigma, pressure, the stress ratio mu = sigma/p, z, z_all,
    z2) as {mean, err} (err: block-average error within the run), collisions per strain,
    and the power-law fits of its analysis instants (delta_gamma, omega_min against sigma)."""
    f = suspension_fits(run)
    out = {}
    for q, name in (("sigma", "sigma"), ("pressure", "pressure"), ("mu", "stress_ratio"),
                    ("z", "z"), ("z_all", "z_all"), ("z2", "z2")):
        if q in f:
            out[name] = dict(mean=f[q][0], err=f[q][1])
    for q in ("collisions_per_strain", "rows", "instants"):
        if q in f:
            out[q] = f[q]
    for q in ("delta_gamma", "omega_min", "relax_frozen"):
        if isinstance(f.get(q), dict):
            out[q] = f[q]
    for q in ("resp_l_c", "corr_length"):          # medians over the window's instants
        if q in f:
            out[q] = dict(median=f[q][0], err=f[q][1])
    dgs = delta_gamma_sigma(*f["delta_gamma_points"]) if "delta_gamma_points" in f else None
    if dgs is not None:
        out["delta_gamma_sigma"] = dgs
    return out


def delta_gamma_sigma(sigma, delta_gamma) -> dict | None:
    """delta_gamma * sigma of the frozen contact network (constant if delta_gamma ~ 1/sigma,
    the paper's Fig. 7) over the analysis instants of the statistics window (the
    ``delta_gamma_points`` of ``suspension_fits``): mean, its error s / sqrt(n) over the
    instants, and n.  None without such instants."""
    v = np.asarray(delta_gamma, float) * np.asarray(sigma, float)
    v = v[np.isfinite(v)]
    if not v.size:
        return None
    err = float(v.std(ddof=1) / math.sqrt(v.size)) if v.size > 1 else math.nan
    return dict(mean=float(v.mean()), err=err, n=int(v.size))


FITS = {"chain": chain_fits, "network": network_fits, "suspension": suspension_numbers}
FINAL_COLUMNS = ("gamma", "strain", "sigma", "V2", "step")


# one sample file in memory: post.runs.Run, read by post.runs.load
SampleRun = Run
load_sample = load


def sample_files(folder: str) -> list[tuple[int, str]]:
    """(index, path) of the sample files in ``folder``, by index."""
    out = []
    for name in os.listdir(folder):
        m = re.fullmatch(r"sample_(\d+)\.h5", name)
        if m:
            out.append((int(m.group(1)), os.path.join(folder, name)))
    return sorted(out)


def is_ensemble(folder: str) -> bool:
    """Whether ``folder`` is an ensemble folder (holds its index ensemble.h5)."""
    return os.path.isfile(os.path.join(folder, "ensemble.h5"))


def find_sources(paths, suffix: str | None = None) -> tuple[list[str], list[str]]:
    """(ensemble folders, files named ``*suffix``) among ``paths`` and, for a folder that is
    not an ensemble, among its entries (sorted); no files without ``suffix``.  Of the
    ``.json`` files found in a folder (not named as a path), those that hold a JSON object
    without a ``kind`` -- no sample table of any model: e.g. the ``--json`` result of an
    analysis written beside the ensemble folders -- are passed over; a file named as a path
    is always returned (and must then be a table)."""
    folders, files = [], []

    def take(p, named):
        if is_ensemble(p):
            folders.append(p)
        elif suffix is not None and p.endswith(suffix) and os.path.isfile(p):
            if named or not _is_result_json(p):
                files.append(p)
    for p in paths:
        if is_ensemble(p) or not os.path.isdir(p):
            take(p, True)
        else:
            for q in sorted(os.listdir(p)):
                take(os.path.join(p, q), False)
    return folders, files


def _is_result_json(path: str) -> bool:
    """Whether ``path`` holds a JSON object without a ``kind`` (see :func:`find_sources`)."""
    if not path.endswith(".json"):
        return False
    try:
        with open(path) as fh:
            doc = json.load(fh)
    except (OSError, ValueError):
        return False
    return isinstance(doc, dict) and "kind" not in doc


def nan_floats(values) -> np.ndarray:
    """A float array from a JSON list in which NaN was written as null."""
    return np.array([math.nan if u is None else u for u in values], float)


def read_table(path: str, kind: str, version: int, what: str) -> dict:
    """The JSON document of a sample table at ``path`` of ``kind`` and ``version``;
    ValueError naming the file when it cannot be read, is of another kind (``what``: e.g.
    "suspension sample table") or of another version."""
    try:
        with open(path) as fh:
            doc = json.load(fh)
    except (OSError, ValueError) as e:
        raise ValueError(f"{path}: not a readable JSON sample table ({e})") from None
    if not isinstance(doc, dict) or doc.get("kind") != kind:
        raise ValueError(f"{path}: not a {what} (kind "
                         f"{doc.get('kind') if isinstance(doc, dict) else None!r})")
    if doc.get("version") != version:
        raise ValueError(f"{path}: sample table version {doc.get('version')!r}, this parflow "
                         f"reads {version}")
    return doc


def check_poolable(sources) -> None:
    """Sources (label, scene text, sample seeds) that may be pooled into one ensemble: the
    same scene apart from its seed, title, [ensemble] and [output] (:func:`scene_protocol`),
    and no sample seed twice (negative seeds: unknown, not compared); ValueError naming the
    two sources otherwise."""
    (first, text, _), seen = sources[0], {}
    proto = scene_protocol(text)
    for label, scene, seeds in sources:
        if label != first and (proto is None or scene_protocol(scene) != proto):
            raise ValueError(f"{first} and {label} are not the same scene (apart from its "
                             "seed): pass one of them")
        for seed in seeds:
            if seed in seen and seed >= 0:
                raise ValueError(f"{seen[seed]} and {label} hold the same sample (seed "
                                 f"{seed}): pass one of them")
            seen[seed] = label


def finished_samples(folder: str, model: str):
    """(run, row) for each sample of ``folder`` whose file loads, is of ``model`` and says
    complete, jammed or budget (:data:`DONE`); row = its index, seed, status and last step.
    A damaged sample file does not enter (as in the summary)."""
    for k, path in sample_files(folder):
        try:
            r = load_sample(path)
        except Exception:
            continue
        status = str(r.attrs.get("status", ""))
        if status not in DONE or r.model != model:
            continue
        yield r, dict(sample=k, seed=int(r.attrs.get("sample_seed", -1)), status=status,
                      steps=int(r.ts["step"][-1]) if len(r.ts.get("step", [])) else 0)


# ---------------------------------------------------------------------------------------
# statistics
# ---------------------------------------------------------------------------------------
def mean_sem(values) -> tuple:
    """Mean, standard error (ddof = 1) and count over axis 0, finite values only."""
    v = np.asarray(values, float)
    ok = np.isfinite(v)
    n = ok.sum(axis=0)
    s1 = np.where(ok, v, 0.0).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(n > 0, s1 / np.maximum(n, 1), np.nan)
        dev = np.where(ok, v - mean, 0.0)
        var = np.where(n > 1, (dev ** 2).sum(axis=0) / np.maximum(n - 1, 1), np.nan)
        sem = np.sqrt(var / np.maximum(n, 1))
    return mean, sem, n


def jackknife(estimate, n: int) -> tuple[float, float]:
    """``estimate(keep)`` on all n samples and with each left out (``keep`` a boolean
    mask); returns (the estimate on all, its jackknife standard error; NaN for n < 2 or when
    a leave-one-out estimate is not finite)."""
    full = float(estimate(np.ones(n, bool)))
    if n < 2:
        return full, float("nan")
    loo = np.array([estimate(np.arange(n) != i) for i in range(n)], float)
    if not np.all(np.isfinite(loo)):
        return full, float("nan")
    return full, float(np.sqrt((n - 1) / n * np.sum((loo - loo.mean()) ** 2)))


def on_grid(x, y, grid, log: bool = False):
    """y(x) interpolated onto ``grid`` (NaN outside the range of x); ``log``: in log-log."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    ok = np.isfinite(x) & np.isfinite(y)
    if log:
        ok &= (x > 0) & (y > 0)
    x, y = x[ok], y[ok]
    out = np.full(len(grid), np.nan)
    if x.size < 2:
        return out
    order = np.argsort(x, kind="stable")
    x, y = x[order], y[order]
    if log:
        x, y, g = np.log(x), np.log(y), np.log(grid)
    else:
        g = np.asarray(grid, float)
    inside = (g >= x[0]) & (g <= x[-1])
    out[inside] = np.interp(g[inside], x, y)
    return np.exp(out) if log else out


SKIP_FITS = ("theory", "mu", "model", "N", "seed", "path")   # constants, not measurements


def _flatten(d, prefix="") -> dict:
    """The finite numbers of a nested fits dict, by dotted name ('/' written '_over_', e.g.
    ``lengths.dtheta2^-1_over_2.exponent``): a pair is (exponent, prefactor) of a power law,
    or (lo, hi) of a ``window``; other tuples by position."""
    out = {}
    if isinstance(d, dict):
        items = [(k, v) for k, v in d.items() if not (prefix == "" and k in SKIP_FITS)]
    elif len(d) == 2:
        items = zip(("lo", "hi") if prefix.endswith("window.") else ("exponent", "prefactor"), d)
    else:
        items = enumerate(d)
    for k, v in items:
        name = f"{prefix}{k}".replace("/", "_over_")      # an HDF5 name: no '/'
        if isinstance(v, (dict, tuple)):
            out.update(_flatten(v, name + "."))
        elif isinstance(v, (bool, np.bool_)):
            continue
        elif isinstance(v, (int, float, np.integer, np.floating)) and math.isfinite(float(v)):
            out[name] = float(v)
    return out


def _leg_curves(runs) -> dict:
    """sigma against the strain since the start of each leg, on a linear grid."""
    out = {}
    legs = sorted({int(x) for r in runs for x in np.unique(r.ts.get("leg", []))})
    for L in legs:
        xs, ys = [], []
        for r in runs:
            if "leg" not in r.ts or "sigma" not in r.ts or "strain" not in r.ts:
                xs.append(None), ys.append(None)
                continue
            rows = np.nonzero(r.ts["leg"] == L)[0]
            if rows.size < 2:
                xs.append(None), ys.append(None)
                continue
            st = r.ts["strain"][rows]
            xs.append(st - st[0]), ys.append(r.ts["sigma"][rows])
        top = max((float(np.nanmax(x)) for x in xs if x is not None), default=0.0)
        if top <= 0:
            continue
        grid = np.linspace(0.0, top, GRID_POINTS)
        vals = np.array([on_grid(x, y, grid) if x is not None else np.full(GRID_POINTS, np.nan)
                         for x, y in zip(xs, ys)])
        out[f"sigma_leg{L}"] = dict(x=grid, values=vals, xlabel=f"strain since the start of leg {L}",
                                    ylabel="sigma", xscale="linear", yscale="log")
    return out


def _log_grid(xs) -> np.ndarray | None:
    pos = [x[np.isfinite(x) & (x > 0)] for x in xs if x is not None]
    pos = [p for p in pos if p.size]
    if not pos:
        return None
    lo, hi = min(float(p.min()) for p in pos), max(float(p.max()) for p in pos)
    if not hi > lo:
        return None
    return np.geomspace(lo, hi, GRID_POINTS)


def _chain_curve(runs) -> dict:
    """<V^2> against gamma_c - gamma on the forward leg (gamma_c: each sample's exact one)."""
    xs, ys = [], []
    for r in runs:
        fw = forward_rows(r)
        gc = float(r.model_attrs.get("gamma_c", np.nan))
        if fw is None or not np.isfinite(gc) or "V2" not in r.ts:
            xs.append(None), ys.append(None)
            continue
        xs.append(gc - r.ts["gamma"][fw]), ys.append(r.ts["V2"][fw])
    grid = _log_grid(xs)
    if grid is None:
        return {}
    vals = np.array([on_grid(x, y, grid, log=True) if x is not None else np.full(len(grid), np.nan)
                     for x, y in zip(xs, ys)])
    return {"V2_forward": dict(x=grid, values=vals, xlabel="gamma_c - gamma", ylabel="<V^2>",
                               xscale="log", yscale="log")}


def network_curves(runs) -> dict:
    """dsigma/dgamma against sigma on the first reversed leg."""
    xs, ys = [], []
    for r in runs:
        rv = reverse_rows(r)
        if rv is None or "sigma" not in r.ts or "strain" not in r.ts or rv[0].stop - rv[0].start < 3:
            xs.append(None), ys.append(None)
            continue
        b = reverse_branch(r.ts["strain"][rv[0]], r.ts["sigma"][rv[0]])
        xs.append(b["sigma"]), ys.append(np.abs(b["dsdg"]))
    grid = _log_grid(xs)
    if grid is None:
        return {}
    vals = np.array([on_grid(x, y, grid, log=True) if x is not None else np.full(len(grid), np.nan)
                     for x, y in zip(xs, ys)])
    return {"dsigma_dgamma_reverse": dict(x=grid, values=vals, xlabel="sigma",
                                          ylabel="|dsigma/dgamma| (reversed leg)",
                                          xscale="log", yscale="log")}


# profiles at an analysis instant: model -> (array, its abscissa or None for the index, label)
PROFILES = {
    "chain": (("C_n", None, "C(n)"), ("tau_response", None, "point response |tau|(n)")),
    "network": (("corr_C", "corr_r", "C(r)"), ("resp_V", "resp_r", "point response V(r)"),
                ("resp_f", "resp_r", "point response f(r)")),
}


def _profiles_on_grid(xs, ys, have, scale: str = "linear"):
    """(grid, rows): the profiles (x, y) of the samples (None: a sample without one) on a
    grid over the ranges of ``have`` (their abscissae of >= 2 points), linear or logarithmic,
    with as many points as the longest (at most GRID_POINTS)."""
    lo, hi = min(float(x.min()) for x in have), max(float(x.max()) for x in have)
    npts = max(min(GRID_POINTS, max(x.size for x in have)), 2)
    grid = np.geomspace(lo, hi, npts) if scale == "log" else np.linspace(lo, hi, npts)
    vals = np.array([on_grid(x, y, grid) if x is not None else np.full(grid.size, np.nan)
                     for x, y in zip(xs, ys)])
    return grid, vals


def _profile_curves(runs, model) -> dict:
    """The model's profiles (C(r), the point response) at each sample's last analysis
    instant on its first forward leg (the one nearest jamming), on a common linear grid."""
    out = {}
    for name, xname, label in PROFILES.get(model, ()):
        xs, ys = [], []
        for r in runs:
            inst = [a for a in forward_instants(r) if name in a]
            if not inst:
                xs.append(None), ys.append(None)
                continue
            y = np.asarray(inst[-1][name], float)
            x = np.arange(y.size, dtype=float) if xname is None else np.asarray(inst[-1][xname], float)
            xs.append(x), ys.append(y)
        have = [x for x in xs if x is not None and x.size >= 2]
        if not have:
            continue
        grid, vals = _profiles_on_grid(xs, ys, have)
        out[f"profile_{name}"] = dict(x=grid, values=vals, ylabel=label,
                                      xlabel="n (rods)" if xname is None else "r",
                                      xscale="linear", yscale="linear")
    return out


# a suspension's profiles (array, abscissa, label, axis scales): in steady flow each sample's
# profile is the mean over the analysis instants of its statistics window; P(f/<f>) is on
# log bins (abscissa: the bins' geometric centres)
SUSPENSION_PROFILES = (("force_P", "force_edges", "P(f/<f>)", "log"),
                       ("corr_C", "corr_r", "C(r)", "linear"),
                       ("resp_V", "resp_r", "point response V(r)", "linear"),
                       ("resp_f", "resp_r", "point response f(r)", "linear"))


def _shared_prefix(xs) -> int | None:
    """The length of the abscissae's common part when each is the start of the longest (the
    same bins cut at different ranges: C(r) and the point response stop at the sheared
    cell's inscribed radius, which changes with the strain), else None."""
    longest = max(xs, key=len)
    if all(np.array_equal(x, longest[:x.size]) for x in xs):
        return min(x.size for x in xs)
    return None


def _window_mean_profile(run, name: str, xname: str):
    """(x, y): the mean of profile ``name`` over the statistics window's instants (NaN bins
    ignored) on the bins they share, or (None, None) without such instants."""
    inst = [a for a in window_instants(run) if name in a and xname in a]
    xs = [np.asarray(a[xname], float) for a in inst]
    m = _shared_prefix(xs) if xs else None
    if not m:
        return None, None
    if xname == "force_edges":                    # bin edges -> geometric centres
        ys = np.array([np.asarray(a[name], float)[:m - 1] for a in inst])
        x = np.sqrt(xs[0][:m - 1] * xs[0][1:m])
    else:
        ys = np.array([np.asarray(a[name], float)[:m] for a in inst])
        x = xs[0][:m]
    count = np.sum(np.isfinite(ys), axis=0)
    y = np.full(x.size, np.nan)
    y[count > 0] = np.nansum(ys, axis=0)[count > 0] / count[count > 0]
    return x, y


def suspension_profiles(runs) -> dict:
    """P(f/<f>), C(r) and the point responses, each sample's window mean (rows of
    ``values``) on a common grid: the bins the samples share when their abscissae agree
    (the same scene), else a linear (P(f): logarithmic) grid over their ranges."""
    out = {}
    for name, xname, label, scale in SUSPENSION_PROFILES:
        xs, ys = zip(*[_window_mean_profile(r, name, xname) for r in runs]) if runs else ((), ())
        have = [x for x in xs if x is not None and x.size >= 2]
        if not have:
            continue
        m = _shared_prefix(have) if len(have) == len(xs) else None
        if m:
            grid, vals = have[0][:m], np.array([y[:m] for y in ys])
        else:
            grid, vals = _profiles_on_grid(xs, ys, have, scale)
        out[f"profile_{name}"] = dict(x=grid, values=vals, ylabel=label,
                                      xlabel="f/<f>" if xname == "force_edges" else "r",
                                      xscale=scale, yscale=scale)
    return out


def chain_ensemble_fit(curve, dgamma_typical) -> dict:
    """The <V^2> exponent fitted to the averaged forward curve (window: the last decades
    of gamma_c - gamma above 10 typical |dgamma| -- the largest of the samples' -- as for one
    run), jackknife error."""
    grid, vals = curve["x"], curve["values"]
    dg = [float(d) for d in dgamma_typical if np.isfinite(d)]
    lo, hi = fit_window(grid, max(dg) if dg else 0.0)

    def est(keep):
        m, _, n = mean_sem(vals[keep])
        m = np.where(n == keep.sum(), m, np.nan)      # only where every kept sample counts
        return fit_power_law(grid, m, lo, hi, BINS_PER_DECADE)[0]
    value, err = jackknife(est, len(vals))
    return {"V2_forward_exponent": dict(value=value, jackknife_err=err, n=len(vals),
                                        window_lo=lo, window_hi=hi)}


def jamming_rate(statuses, strains, compressing=None) -> dict:
    """Shear jams per unit strain: n_jammed / (the strain all samples ran, summed), with its
    Poisson error sqrt(n_jammed) / strain (a jam ends a sample: the strain it ran is its
    exposure).  ``compressing``: per sample, true if it jammed while it was still being
    compressed (:func:`rate_exposure`; ``strains`` are then the strains at the final phi):
    such jams are counted apart (``n_jammed_compressing``), not in the rate."""
    total = float(np.nansum(np.asarray(strains, float)))
    ramp = [bool(c) for c in compressing] if compressing is not None else [False] * len(statuses)
    n = int(sum(st == "jammed" and not c for st, c in zip(statuses, ramp)))
    rate = n / total if total > 0 else float("nan")
    return dict(value=rate, poisson_err=math.sqrt(n) / total if total > 0 else float("nan"),
                n_jammed=n, strain=total, n=len(statuses), n_jammed_compressing=int(sum(ramp)))


def rate_exposure(run) -> tuple[float, bool]:
    """(the strain a sample ran at its final packing fraction, whether it jammed before it got
    there).  A sample compressed while it flowed (a ``phi`` column) is exposed from the row
    where phi reached ``compress_to``; any other sample over its whole strain."""
    st = np.asarray(run.ts.get("strain", []), float)
    if not st.size:
        return 0.0, False
    if "phi" not in run.ts:
        return float(st[-1]), False
    phi = np.asarray(run.ts["phi"], float)
    x = strain_at_final_phi(st, phi, float(run.param("compress_to", 0.0) or phi.max()))
    if math.isnan(x):
        return 0.0, run.attrs.get("status") == "jammed"
    return x, False


def final_phi_row(phi, compress_to: float) -> int | None:
    """The first row where ``phi`` reached ``compress_to`` (None: it never got there)."""
    at = np.flatnonzero(np.asarray(phi, float) >= compress_to)
    return int(at[0]) if at.size else None


def strain_at_final_phi(strain, phi, compress_to: float) -> float:
    """The strain run from the row where ``phi`` first reached ``compress_to`` to the last
    row (the exposure of a sample compressed while it flowed); NaN if it never got there."""
    at = final_phi_row(phi, compress_to)
    if at is None or not len(strain):
        return math.nan
    return float(strain[-1] - strain[at])


def summarise(folder: str) -> dict:
    """The ensemble's statistics (the summary file's content, as dicts of arrays)."""
    files = sample_files(folder)
    index, status, seeds, runs = [], [], [], []
    for k, path in files:
        try:
            r = load_sample(path)
        except Exception as exc:       # a damaged sample file is listed, not used
            index.append(k)
            status.append(f"unreadable: {exc}"[:200])
            seeds.append(-1)
            continue
        index.append(k)
        status.append(str(r.attrs.get("status", "")))
        seeds.append(int(r.attrs.get("sample_seed", -1)))
        if status[-1] in DONE and r.ts and len(r.ts.get("step", [])):
            runs.append((k, r))
    used = np.array([k for k, _ in runs], dtype=np.int64)
    rs = [r for _, r in runs]
    model = rs[0].model if rs else ""
    scalars = {}
    for c in FINAL_COLUMNS:
        vals = np.array([float(r.ts[c][-1]) if c in r.ts and len(r.ts[c]) else np.nan for r in rs])
        if c == "step":
            scalars["steps"] = vals
        else:
            scalars[f"final_{c}"] = vals
    fits = {}
    fn = FITS.get(model)
    if fn is not None and rs:
        flat = []
        for r in rs:
            try:
                flat.append(_flatten(fn(r)))
            except Exception:          # a sample whose fit fails has none
                flat.append({})
        names = sorted({n for f in flat for n in f})
        fits = {n: np.array([f.get(n, np.nan) for f in flat]) for n in names}
    curves = {}
    if rs:
        curves.update(_leg_curves(rs))
        if model == "chain":
            curves.update(_chain_curve(rs))
        if model == "network":
            curves.update(network_curves(rs))
        curves.update(_profile_curves(rs, model))
        if model == "suspension":
            curves.update(suspension_profiles(rs))
    ens = {}
    if "V2_forward" in curves:
        ens.update(chain_ensemble_fit(curves["V2_forward"], fits.get("dgamma_typical", [])))
    if rs and any("phi" in r.ts for r in rs):        # compressed while flowing
        expo = [rate_exposure(r) for r in rs]
        scalars["rate_strain"] = np.array([e[0] for e in expo])
        scalars["jammed_compressing"] = np.array([float(e[1]) for e in expo])
    if rs:
        ens["jamming_rate"] = jamming_rate([r.attrs.get("status") for r in rs],
                                           scalars.get("rate_strain", scalars["final_strain"]),
                                           scalars.get("jammed_compressing"))
    return dict(model=model, index=np.array(index, dtype=np.int64), status=status,
                seed=np.array(seeds, dtype=np.int64), used=used, scalars=scalars, fits=fits,
                curves=curves, ensemble_fits=ens, scene=index_scene(folder))


def scene_protocol(scene_text: str):
    """What two ensembles must share to be pooled: the scene (TOML) without its seed, title,
    [ensemble] and [output] tables; None if it does not parse (then nothing pools with it)."""
    try:
        d = tomllib.loads(scene_text)
    except (tomllib.TOMLDecodeError, TypeError):
        return None
    for k in ("seed", "title", "ensemble", "output"):
        d.pop(k, None)
    return d


def index_scene(folder: str) -> str:
    """The scene text of the ensemble index ``FOLDER/ensemble.h5`` ("" if unreadable)."""
    try:
        with open_hdf5(os.path.join(folder, "ensemble.h5")) as f:
            v = f.attrs.get("scene", "")
    except (OSError, ValueError):
        return ""
    return v.decode() if isinstance(v, bytes) else str(v)


def write_summary(folder: str) -> str:
    """Compute the statistics and write ``FOLDER/summary.h5`` (whole or not at all)."""
    path = os.path.join(folder, "summary.h5")
    write_summary_file(path, summarise(folder))
    return path


def write_summary_file(path: str, s: dict) -> None:
    """Write the statistics ``s`` (:func:`summarise`'s form) to ``path``, whole or not at
    all; ``s["sources"]`` (a pooled summary's inputs) recorded if present."""
    with atomic_h5(path) as f:
        f.attrs["format"] = SUMMARY_FORMAT
        f.attrs["model"] = s["model"]
        f.attrs["n_samples"] = len(s["index"])
        f.attrs["n_used"] = len(s["used"])
        f.attrs["scene"] = s.get("scene", "")
        if s.get("sources"):
            f.attrs["pooled_from"] = "\n".join(s["sources"])
        g = f.create_group("samples")
        g["sample"] = s["index"]
        g["seed"] = s["seed"]
        g["status"] = np.array([x.encode() for x in s["status"]], dtype="S")
        g["used"] = s["used"]
        for section in ("scalars", "fits"):
            sec = f.create_group(section)
            for name, vals in s[section].items():
                m, e, n = mean_sem(vals)
                q = sec.create_group(name)
                q["values"], q["mean"], q["sem"], q["count"] = vals, m, e, n
        sec = f.create_group("curves")
        for name, c in s["curves"].items():
            m, e, n = mean_sem(c["values"])
            q = sec.create_group(name)
            q["x"], q["values"], q["mean"], q["sem"], q["count"] = c["x"], c["values"], m, e, n
            for a in ("xlabel", "ylabel", "xscale", "yscale"):
                q.attrs[a] = c[a]
        sec = f.create_group("ensemble_fits")
        for name, d in s["ensemble_fits"].items():
            q = sec.create_group(name)
            for a, v in d.items():
                q.attrs[a] = v


def read_summary(path: str) -> dict:
    """A summary file's content: attrs, samples, scalars, fits, curves, ensemble_fits."""
    with open_hdf5(path) as f:
        if f.attrs.get("format") != SUMMARY_FORMAT:
            raise ValueError(f"{path!r} is not a parflow ensemble summary")

        def grp(name):
            return {k: {d: v[()] for d, v in f[name][k].items()} | dict(f[name][k].attrs)
                    for k in f[name]} if name in f else {}
        return dict(attrs=dict(f.attrs), samples={k: v[()] for k, v in f["samples"].items()},
                    scalars=grp("scalars"), fits=grp("fits"), curves=grp("curves"),
                    ensemble_fits={k: dict(f["ensemble_fits"][k].attrs) for k in f["ensemble_fits"]})


def main(argv=None) -> int:
    """``python -m parflow.post.ensemble FOLDER...``: compute each ensemble folder's
    summary.h5 again from its sample files (e.g. after parflow's statistics changed)."""
    ap = argparse.ArgumentParser(prog="python -m parflow.post.ensemble",
                                 description="write an ensemble folder's summary.h5 again")
    ap.add_argument("folders", nargs="+", metavar="FOLDER")
    args = ap.parse_args(argv)
    for folder in args.folders:
        if not is_ensemble(folder):
            print(f"parflow.post.ensemble: {folder}: not an ensemble folder (no ensemble.h5)",
                  file=sys.stderr)
            return 2
    for folder in args.folders:
        print(write_summary(folder))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
