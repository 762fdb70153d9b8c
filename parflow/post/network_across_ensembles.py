"""Network ensembles across dz (docs/networks.md "Ensembles across dz"): C(dz), C2(dz),
omega*(dz) and l_c(dz), each as the mean over the networks (samples) of an ensemble with
its standard error, and the exponents of their power laws in dz with errors propagated from
the per-dz errors.

Per sample (one network, one run file of an ensemble folder, ``parflow.ensemble``):

* ``C``       C of the reversed branch, -dsigma/dgamma = sigma^2 / C, fitted over sigma in
              ``post.network.REVERSE_SIGMA`` (:func:`post.network.fit_reverse_branch`);
  ``a``       the exponent of -dsigma/dgamma ~ sigma^a over the same window (pred. 2);
  ``C_hi``    the same C fitted over sigma in :data:`HIGH_SIGMA`, nearer jamming (at
              N = 40 000 the reversed branch follows sigma^2 with two different C above and
              below a bump at sigma ~ 3e3-1e4: docs/networks.md Fig. 8); ``a_hi`` its exponent;
* ``C2``      the median of omega_min sqrt(sigma) over sigma >= ``post.network.C2_SIGMA_MIN``;
* ``l_c``     the mean of the point response's fitted l_c over the analysis instants with
              :data:`LC_SIGMA` [0] <= sigma <= [1] (both branches; as docs/networks.md Fig. 5);
* ``omega_star`` the gap of D(omega) (:func:`post.network.omega_star_fits`), from the
              sample's own spectra or, when the ensemble has none, from the sample with the
              same index *and the same seed* of a companion ensemble of the same networks
              (``runs/ensemble_network_gap_*.toml``: one dense spectrum at gamma = 0);
              ``omega_star_30``, ``omega_star_70``: the same with the fraction 0.3 and 0.7
              instead of 1/2 (``fit_omega_star``'s definition; the spread of the exponent
              between them is the definition's systematic error: docs/networks.md);
* ``gamma_j`` the strain at the end of the first forward leg (sigma = 1e6: near jamming;
              no prediction: docs/networks.md measured gamma_j ~ 0.45 dz on 3 networks).

Per dz (one ensemble; :func:`per_dz`): for each quantity the mean over the samples where it
is finite, the standard error s / sqrt(n) (ddof = 1) and n.  A sample's value is one fit on
one network; the mean's jackknife error (leave one network out) is exactly this standard
error, so the fit errors inside a sample (far smaller than the scatter between networks:
docs/networks.md) are not added.

Also per dz, from the ensemble-averaged reversed branch (``summary.h5``'s curve
``dsigma_dgamma_reverse``: |dsigma/dgamma| of each network on a common sigma grid):
``C_curve``, the C of the mean curve, exp(mean over the grid points in ``REVERSE_SIGMA`` of
log(sigma^2 / <|dsigma/dgamma|>)) (the sigma^2 law with its slope fixed at 2), with its
jackknife error over the networks (:func:`curve_C`).  It weights the networks by their
|dsigma/dgamma| (~1/C), the mean of the C's by C: the two differ when C scatters.

Across dz (:func:`fit_across`): y = A dz^p by weighted least squares of log(mean) on log dz,
the weight of a point 1 / sigma_log^2 with sigma_log = sem / mean (``post.fits.
fit_power_law_err``: the error of p from the covariance, times sqrt(chi2/dof) when that
exceeds 1), and, as a check that does not assume Gaussian errors, a bootstrap over the
networks: the samples of each dz redrawn with replacement :data:`N_BOOT` times (fixed seed),
the means recomputed and refitted with the same weights; its error is the standard
deviation of the refitted p.  Predictions: C ~ dz^-1/2, C2 ~ dz^1/2, omega* ~ dz,
l_c ~ dz^-1/2 (:data:`PREDICTED`).

Sample tables (:func:`export_samples`, :func:`load_samples`; docs/ensembles.md "Sample
tables"): the per-sample numbers of one ensemble (:data:`ROW_KEYS`: everything above uses)
and its reversed-branch curve (the grid and each network's |dsigma/dgamma| on it, from which
``C_curve`` is recomputed) as one small JSON file (kind :data:`SAMPLES_KIND`, with the git
commit, version and creation time of each sample's run file and the scene of sample 0), so
that ensembles run at different times, on machines whose run files are gone, enter one
analysis; every network ensemble writes its own as ``FOLDER/samples.json`` at its end.  An
analysis reads run folders and tables alike (:func:`read_sources`).  Main ensembles of the
same (N, dz) are pooled into one entry when they are the same scene but for its seed and
share no sample seed (:func:`combine`: more networks of a dz, run at another time), and
refused otherwise; their ``C_curve`` is that of the concatenated curves when their grids are
the same, else of the curves interpolated onto one grid (:func:`curve_C` of
:func:`pooled_curve`).  Companion
spectrum ensembles pair with the pooled samples by index and seed, as tables or folders.

``python -m parflow.post.network_across_ensembles PATH... [--json OUT] [--export DIR]``
prints the table and the exponents; a PATH is an ensemble folder, a sample table, or a
folder searched one level down for both (``out/network_ensembles`` holds ``z3.8/``,
``gap_z3.8/``, ...; a ``.json`` there without a ``kind``, such as the ``--json`` result, is
passed over); ``--export DIR`` writes the sample table of every ensemble folder read into DIR
(``dz0.2000_N4096.json``, ``gap_dz0.2000_N4096.json`` for a companion: :func:`table_names`).
Figures: ``python -m parflow.plot.network_ensembles``.
"""
from __future__ import annotations

import argparse
import math
import os
import sys

import numpy as np

from ..io import atomic_json
from .ensemble import (check_poolable, finished_samples, find_sources, jackknife, mean_sem,
                       nan_floats, network_curves, read_table)
from .fits import fit_power_law_err, forward_rows
from .network import (REVERSE_SIGMA, fit_omega_star, network_dz, network_fits,
                      network_reverse_fit, network_z)
from .pool import pool_curves

HIGH_SIGMA = (1e4, 1e5)           # C_hi: the reversed-branch fit nearer jamming (N = 40 000:
#                                   the law holds there and below 1e3, not across: networks.md)
LC_SIGMA = (10.0, 1e3)            # l_c: mean over the analysis instants in this sigma window
N_BOOT = 1000                     # bootstrap resamples of the networks of each dz
BOOT_SEED = 0
OMEGA_FRACTIONS = (0.3, 0.7)      # omega* also with these fractions (the definition's spread)
OMEGA_KEYS = ("omega_star",) + tuple(f"omega_star_{round(100 * f)}" for f in OMEGA_FRACTIONS)
QUANTITIES = ("C", "a", "C_hi", "a_hi", "C2") + OMEGA_KEYS + ("l_c", "gamma_j")
PREDICTED = {"C": -0.5, "C_hi": -0.5, "C_curve": -0.5, "C2": 0.5, "l_c": -0.5} | {
    k: 1.0 for k in OMEGA_KEYS}
SAMPLES_KIND = "parflow network ensemble samples"
SAMPLES_VERSION = 1
ROW_KEYS = ("sample", "seed", "status", "steps", "N", "z", "dz", "has_spectrum") + QUANTITIES
NO_CURVE = dict(mean=float("nan"), sem=float("nan"), n=0)


# ---------------------------------------------------------------------------------------
# one sample
# ---------------------------------------------------------------------------------------
def mean_l_c(response: dict | None, window: tuple = LC_SIGMA) -> float:
    """The mean of the fitted l_c over the instants of ``post.network.response_fits`` with
    window[0] <= sigma <= window[1] and a finite l_c (NaN if none)."""
    if not response:
        return float("nan")
    v = [x["l_c"] for x in response["instants"]
         if window[0] <= x["sigma"] <= window[1] and np.isfinite(x["l_c"])]
    return float(np.mean(v)) if v else float("nan")


def sample_values(fits: dict) -> dict:
    """The per-sample numbers (:data:`QUANTITIES`) from ``post.network.network_fits`` (and
    its ``reverse_hi``: ``network_reverse_fit`` over :data:`HIGH_SIGMA`, see
    :func:`read_ensemble`)."""
    rv, om, ost = fits.get("reverse", {}), fits.get("omega_min", {}), fits.get("omega_star", {})
    hi = fits.get("reverse_hi", {})
    return dict(C=float(rv.get("C", np.nan)), a=float(rv.get("slope", np.nan)),
                C_hi=float(hi.get("C", np.nan)), a_hi=float(hi.get("slope", np.nan)), gamma_j=float(fits.get("gamma_j", np.nan)),
                C2=float(om.get("C2", np.nan)), omega_star=float(ost.get("omega_star", np.nan)),
                l_c=mean_l_c(fits.get("response")))


def curve_C(curve: dict | None, window: tuple = REVERSE_SIGMA) -> dict:
    """C of the ensemble-averaged reversed branch, ``curve`` = dict(x = the sigma grid,
    values = |dsigma/dgamma| of each network on it, NaN outside its range): over the grid
    points in ``window`` where every (kept) network counts, C = exp(mean(log(x^2 / m))),
    m the mean over the networks; jackknife error over the networks (leave one out, refit).
    Returns dict(mean, sem, n) (NaN when no grid point qualifies)."""
    nan = dict(mean=float("nan"), sem=float("nan"), n=0)
    if curve is None:
        return nan
    x, vals = np.asarray(curve["x"], float), np.atleast_2d(np.asarray(curve["values"], float))
    w = (x >= window[0]) & (x <= window[1])
    n = vals.shape[0]

    def est(keep):
        v = vals[keep][:, w]
        ok = np.all(np.isfinite(v) & (v > 0), axis=0)
        if not ok.any():
            return float("nan")
        m = v[:, ok].mean(axis=0)
        return float(np.exp(np.mean(2.0 * np.log(x[w][ok]) - np.log(m))))
    if n == 0 or not w.any():
        return nan
    value, err = jackknife(est, n)
    return dict(mean=value, sem=err, n=int(n))


def read_ensemble(folder: str) -> dict:
    """The samples of one ensemble folder that finished (complete, jammed, budget): their
    index, seed, status, steps and :func:`sample_values`, and N, z, dz of the ensemble;
    ``curve``, their reversed branches on a common grid (``post.ensemble.network_curves``'s
    ``dsigma_dgamma_reverse``: dict(x, values), one row of values per sample; None without a
    reversed leg) and ``C_curve`` (:func:`curve_C` of it); ``provenance``: each sample's git
    commit, parflow version and creation time, and sample 0's scene."""
    rows, runs, prov = [], [], dict(samples=[], scene="")
    for r, row in finished_samples(folder, "network"):
        fits = network_fits(r)
        fw = forward_rows(r)
        fits["gamma_j"] = float(r.ts["gamma"][fw][-1]) if fw is not None else float("nan")
        hi = network_reverse_fit(r, HIGH_SIGMA)
        if hi is not None:
            fits["reverse_hi"] = hi
        v = sample_values(fits)
        for f, key in zip(OMEGA_FRACTIONS, OMEGA_KEYS[1:]):
            w = [fit_omega_star(a["omega"], fraction=f, n_boot=0)["omega_star"]
                 for a in r.analysis if "omega" in a]
            v[key] = float(np.nanmean(w)) if np.isfinite(w).any() else float("nan")
        runs.append(r)
        rows.append(row | dict(N=int(r.param("N")), z=network_z(r), dz=network_dz(r),
                               has_spectrum=any("omega" in a for a in r.analysis), **v))
        prov["samples"].append(dict(sample=row["sample"], **{
            k: str(r.attrs.get(k, "")) for k in ("git_commit", "parflow_version", "created")}))
        if not prov["scene"]:
            prov["scene"] = str(r.attrs.get("scene", ""))
    c = network_curves(runs).get("dsigma_dgamma_reverse") if runs else None
    curve = None if c is None else dict(x=np.asarray(c["x"], float),
                                        values=np.atleast_2d(np.asarray(c["values"], float)))
    return dict(folder=folder, samples=rows, curve=curve, C_curve=curve_C(curve),
                provenance=prov)


# ---------------------------------------------------------------------------------------
# sample tables
# ---------------------------------------------------------------------------------------
def export_samples(ens: dict, path: str) -> None:
    """Write the sample table of ``ens`` (:func:`read_ensemble`) to ``path``: kind
    :data:`SAMPLES_KIND`, version :data:`SAMPLES_VERSION`, the folder's base name
    (``source``), ``provenance``, one row per sample (:data:`ROW_KEYS`) and
    ``reverse_curve`` (dict(x, values): the grid and one row per sample, in the order of the
    rows; null without a reversed leg).  JSON, written to a twin and renamed (never
    half-written); NaN as null."""
    curve = ens.get("curve")
    if curve is not None:
        curve = dict(x=np.asarray(curve["x"], float).tolist(),
                     values=np.atleast_2d(np.asarray(curve["values"], float)).tolist())
    doc = dict(kind=SAMPLES_KIND, version=SAMPLES_VERSION,
               source=os.path.basename(os.path.normpath(ens["folder"])),
               provenance=ens.get("provenance", {}),
               samples=[{k: x[k] for k in ROW_KEYS} for x in ens["samples"]],
               reverse_curve=curve)
    atomic_json(path, _jsonable(doc), indent=1, allow_nan=False)


def load_samples(path: str) -> dict:
    """An ensemble (as :func:`read_ensemble`, ``C_curve`` recomputed from the table's curve)
    from a sample table written by :func:`export_samples`; ValueError naming the file if it
    is not one."""
    doc = read_table(path, SAMPLES_KIND, SAMPLES_VERSION, "network sample table")
    rows = []
    try:
        for r in doc["samples"]:
            missing = [k for k in ROW_KEYS if k not in r]
            if missing:
                raise ValueError(f"sample {r.get('sample')} lacks {', '.join(missing)}")
            row = {k: int(r[k]) for k in ("sample", "seed", "steps", "N")}
            row.update(status=str(r["status"]), has_spectrum=bool(r["has_spectrum"]))
            row.update({k: math.nan if r[k] is None else float(r[k])
                        for k in ("z", "dz") + QUANTITIES})
            rows.append(row)
        c = doc["reverse_curve"]
        curve = None
        if c is not None:
            x = nan_floats(c["x"])
            values = np.array([nan_floats(v) for v in c["values"]], float).reshape(-1, x.size)
            if values.shape[0] != len(rows):
                raise ValueError(f"its reverse_curve has {values.shape[0]} rows for "
                                 f"{len(rows)} samples")
            curve = dict(x=x, values=values)
    except (KeyError, TypeError, ValueError, AttributeError) as e:
        raise ValueError(f"{path}: not a valid network sample table ({type(e).__name__}: "
                         f"{e})") from None
    return dict(folder=path, samples=rows, curve=curve, C_curve=curve_C(curve),
                provenance=doc.get("provenance", {}))


def read_sources(paths) -> list[dict]:
    """The ensembles under ``paths``: each ensemble folder read (:func:`read_ensemble`) and
    each sample table loaded (:func:`load_samples`; ``post.ensemble.find_sources``, which
    passes over an analysis's ``--json`` result found in a searched folder)."""
    folders, tables = find_sources(paths, ".json")
    return [read_ensemble(f) for f in folders] + [load_samples(t) for t in tables]


def table_names(ens: list[dict]) -> list[str]:
    """The file names (without ``.json``) of the sample tables of ``ens`` (ensembles with a
    finished sample) in one export: ``dz0.2000_N4096`` (dz to 4 decimals, N), with ``gap_``
    in front for a companion ensemble of spectra only (no finite C:
    ``runs/ensemble_network_gap_*.toml``); when two would get the same name (parts of one dz
    run with other seeds), each of them has its folder's base name added
    (``dz0.2000_N4096_z3.8_seed4``), and a number (``_2``, ...) if that still collides."""
    names = []
    for e in ens:
        s0 = e["samples"][0]
        gap = not any(np.isfinite(s["C"]) for s in e["samples"])
        names.append(f"{'gap_' if gap else ''}dz{s0['dz']:.4f}_N{int(s0['N'])}")
    names = [f"{n}_{os.path.basename(os.path.normpath(e['folder']))}" if names.count(n) > 1
             else n for n, e in zip(names, ens)]
    seen: dict = {}
    for i, n in enumerate(names):
        seen[n] = seen.get(n, 0) + 1
        if seen[n] > 1:
            names[i] = f"{n}_{seen[n]}"
    return names


def export(paths, out_dir: str) -> list[str]:
    """Write the sample table of every ensemble folder under ``paths`` with a finished
    sample into ``out_dir``, named by :func:`table_names`; the files written."""
    ens = [e for e in (read_ensemble(f) for f in find_sources(paths)[0]) if e["samples"]]
    os.makedirs(out_dir, exist_ok=True)
    written = []
    for e, n in zip(ens, table_names(ens)):
        path = os.path.join(out_dir, f"{n}.json")
        export_samples(e, path)
        written.append(path)
    return written


# ---------------------------------------------------------------------------------------
# per dz
# ---------------------------------------------------------------------------------------
def pooled_curve(group: list[dict]) -> dict | None:
    """The reversed-branch curve (x, values: one row per network) of the main ensembles
    ``group`` pooled: their ``curve`` rows together when every one has its curve on the same
    grid, else each network's curve interpolated in log-log onto one geometric grid over
    their joint range of sigma (``post.pool.pool_curves``, as pooled summaries do: each
    ensemble's grid spans its own networks' range, so separately run ensembles almost never
    share one); None when one has no curve."""
    curves = [e.get("curve") for e in group]
    if not curves or any(c is None for c in curves):
        return None
    if len(curves) == 1:
        return curves[0]
    rows = [np.atleast_2d(np.asarray(c["values"], float)) for c in curves]
    pooled = pool_curves([dict(x=np.asarray(c["x"], float), values=v, xscale="log",
                               yscale="log") for c, v in zip(curves, rows)],
                         [v.shape[0] for v in rows])
    return None if pooled is None else dict(x=pooled["x"], values=pooled["values"])


def curve_stats(curve: dict | None) -> dict | None:
    """Mean, standard error and count of |dsigma/dgamma| over the networks at each point of a
    (pooled) reversed-branch curve (``post.ensemble.mean_sem``: finite values only), for the
    figure; None without a curve."""
    if curve is None:
        return None
    m, e, n = mean_sem(np.atleast_2d(np.asarray(curve["values"], float)))
    return dict(x=np.asarray(curve["x"], float).tolist(), mean=m.tolist(), sem=e.tolist(),
                count=np.asarray(n, int).tolist())


def combine(ensembles: list[dict]) -> list[dict]:
    """One entry per (N, dz): the samples of the main ensembles (those with a finite C, i.e.
    a reversed branch), pooled when there are several: they must be the same scene but for
    its seed and share no sample seed (``post.ensemble.check_poolable``; ValueError naming
    the two otherwise) -- more networks of a dz, run at another time with another ``seed``,
    from run folders or sample tables.  omega* is filled in from a companion ensemble (same
    N, dz) whose sample of the same index has the same seed (the same network).  Ensembles
    made only of spectra (the companions) give an entry of their own only if no other
    ensemble has their (N, dz) (then the first of them).  ``C_curve``: :func:`curve_C` of
    :func:`pooled_curve` (the curves on one grid)."""
    groups: dict = {}
    for e in ensembles:
        if not e["samples"]:
            continue
        s0 = e["samples"][0]
        key = (s0["N"], round(s0["dz"], 6))
        groups.setdefault(key, []).append(e)
    out = []
    for (N, dz), es in sorted(groups.items()):
        main = [e for e in es if any(np.isfinite(s["C"]) for s in e["samples"])]
        spec = [e for e in es if any(s["has_spectrum"] for s in e["samples"])]
        if main:
            check_poolable([(e["folder"], e.get("provenance", {}).get("scene", ""),
                             [s["seed"] for s in e["samples"]]) for e in main])
        base = main or es[:1]
        samples = [dict(s) for e in base for s in e["samples"]]
        sources = [e["folder"] for e in base]
        for e in spec:
            if any(e is b for b in base):
                continue
            by = {s["sample"]: s for s in e["samples"]}
            used = False
            for s in samples:
                o = by.get(s["sample"])
                if o is not None and o["seed"] == s["seed"] and not np.isfinite(s["omega_star"]):
                    for key in OMEGA_KEYS:
                        s[key] = o[key]
                    used = True
            if used:
                sources.append(e["folder"])
        curve = pooled_curve(base)
        out.append(dict(N=N, dz=dz, z=base[0]["samples"][0]["z"], folders=sources,
                        samples=samples, C_curve=curve_C(curve), curve=curve))
    return out


def per_dz(entry: dict) -> dict:
    """Mean, standard error and count of each quantity over the entry's samples."""
    out = dict(N=entry["N"], dz=entry["dz"], z=entry["z"], n_samples=len(entry["samples"]),
               folders=entry["folders"])
    for q in QUANTITIES:
        v = np.array([s[q] for s in entry["samples"]], float)
        m, e, n = mean_sem(v)
        out[q] = dict(mean=float(m), sem=float(e), n=int(n), values=v.tolist())
    out["C_curve"] = dict(entry.get("C_curve", NO_CURVE))
    out["reverse_curve"] = curve_stats(entry.get("curve"))
    return out


# ---------------------------------------------------------------------------------------
# across dz
# ---------------------------------------------------------------------------------------
def fit_means(dz, mean, sem, predicted: float = float("nan")) -> dict:
    """y = A dz^p from per-dz values ``mean`` with errors ``sem`` (weighted least squares
    as in :func:`fit_across`, no bootstrap: boot_* NaN)."""
    dz, mean, sem = (np.asarray(a, float) for a in (dz, mean, sem))
    use = np.isfinite(mean) & np.isfinite(sem) & (sem > 0) & (mean > 0) & (dz > 0)
    out = dict(exponent=np.nan, err=np.nan, boot_err=np.nan, boot_p16=np.nan, boot_p84=np.nan,
               prefactor=np.nan, chi2=np.nan, dof=0, n_dz=int(use.sum()),
               predicted=float(predicted), deviation=np.nan, dz=dz.tolist(),
               mean=mean.tolist(), sem=sem.tolist())
    if use.sum() < 2:
        return out
    f = fit_power_law_err(dz[use], mean[use], sem[use])
    out.update(exponent=f["exponent"], err=f["err"], prefactor=f["prefactor"], chi2=f["chi2"],
               dof=f["dof"])
    if np.isfinite(predicted) and f["err"] > 0:
        out["deviation"] = (f["exponent"] - predicted) / f["err"]
    return out


def fit_across(dz, values: list, n_boot: int = N_BOOT, seed: int = BOOT_SEED,
               predicted: float = float("nan")) -> dict:
    """y = A dz^p across dz: ``values[i]`` the per-sample values at dz[i] (NaN ignored).

    Weighted least squares of log(mean_i) on log(dz_i), weights (mean_i / sem_i)^2
    (``fit_power_law_err``), and a bootstrap over the samples of each dz with those weights
    held fixed.  Returns dict(exponent, err (WLS), boot_err, boot_p16, boot_p84, prefactor,
    chi2, dof, n_dz, predicted, deviation = (p - predicted) / err).  Points with fewer than
    two finite samples are left out (no error bar)."""
    dz = np.asarray(dz, float)
    vals = [np.asarray(v, float)[np.isfinite(np.asarray(v, float))] for v in values]
    mean = np.array([v.mean() if v.size else np.nan for v in vals])
    sem = np.array([v.std(ddof=1) / math.sqrt(v.size) if v.size > 1 else np.nan for v in vals])
    use = np.isfinite(mean) & np.isfinite(sem) & (sem > 0) & (mean > 0) & (dz > 0)
    out = fit_means(dz, mean, sem, predicted)
    if use.sum() < 2:
        return out
    if n_boot > 1:
        X = np.log(dz[use])
        w = (mean[use] / sem[use]) ** 2
        A = np.column_stack([np.ones_like(X), X])
        solve = np.linalg.solve(A.T @ (w[:, None] * A), (A * w[:, None]).T)   # 2 x n_dz
        rng = np.random.default_rng(seed)
        means = np.empty((n_boot, int(use.sum())))
        for j, v in enumerate(v for v, u in zip(vals, use) if u):
            means[:, j] = v[rng.integers(0, v.size, (n_boot, v.size))].mean(axis=1)
        ok = np.all(means > 0, axis=1)
        p = (np.log(means[ok]) @ solve.T)[:, 1]
        if p.size > 1:
            out.update(boot_err=float(np.std(p, ddof=1)), boot_p16=float(np.percentile(p, 16)),
                       boot_p84=float(np.percentile(p, 84)))
    return out


def across(table: list[dict], n_boot: int = N_BOOT) -> dict:
    """For each N: :func:`fit_across` of each quantity of :data:`PREDICTED` (and of ``a``,
    the reversed-branch exponent, against dz: pred. 0, i.e. a = 2 at every dz)."""
    out = {}
    for N in sorted({t["N"] for t in table}):
        rows = sorted((t for t in table if t["N"] == N), key=lambda t: t["dz"])
        res = {}
        for q in QUANTITIES:
            pred = PREDICTED.get(q, 0.0 if q in ("a", "a_hi") else float("nan"))
            res[q] = fit_across([t["dz"] for t in rows], [t[q]["values"] for t in rows],
                                n_boot=n_boot, predicted=pred)
        res["C_curve"] = fit_means([t["dz"] for t in rows], [t["C_curve"]["mean"] for t in rows],
                                   [t["C_curve"]["sem"] for t in rows], PREDICTED["C_curve"])
        out[int(N)] = res
    return out


def analyse(paths, n_boot: int = N_BOOT) -> dict:
    """The ensembles under ``paths`` (folders and sample tables: :func:`read_sources`): the
    per-(N, dz) table (:func:`combine`, :func:`per_dz`) and the fits across dz."""
    table = [per_dz(e) for e in combine(read_sources(paths))]
    return dict(table=table, across=across(table, n_boot), lc_sigma=list(LC_SIGMA))


# ---------------------------------------------------------------------------------------
# report
# ---------------------------------------------------------------------------------------
def _pm(d: dict, digits: int = 4) -> str:
    if not np.isfinite(d["mean"]):
        return "—"
    e = f" ± {d['sem']:.2g}" if np.isfinite(d["sem"]) else ""
    return f"{d['mean']:.{digits}g}{e} ({d['n']})"


def format_table(res: dict) -> list[str]:
    """The per-dz table (markdown) and the exponents, as lines."""
    cols = QUANTITIES + ("C_curve",)
    lines = ["| N | z | dz | samples | " + " | ".join(cols) + " |",
             "|---" * (4 + len(cols)) + "|"]
    for t in res["table"]:
        lines.append(f"| {t['N']} | {t['z']:.3g} | {t['dz']:.3g} | {t['n_samples']} | "
                     + " | ".join(_pm(t[q]) for q in cols) + " |")
    lines.append("")
    for N, fits in res["across"].items():
        for q, f in fits.items():
            if not np.isfinite(f["exponent"]):
                continue
            pred = (f"; predicted {f['predicted']:+g}: {f['deviation']:+.1f} sigma"
                    if np.isfinite(f["predicted"]) else "")
            lines.append(f"N = {N}: {q} ~ dz^({f['exponent']:.3f} ± {f['err']:.3f} WLS, "
                         f"± {f['boot_err']:.3f} bootstrap; 16-84 % {f['boot_p16']:.3f}.."
                         f"{f['boot_p84']:.3f}) chi2/dof = {f['chi2']:.2f}/{f['dof']}, "
                         f"{f['n_dz']} dz{pred}")
    return lines


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return float(x) if math.isfinite(float(x)) else None
    if isinstance(x, np.integer):
        return int(x)
    return x


def missing_path(paths, name: str) -> bool:
    """True after one line on stderr if one of ``paths`` does not exist (the command lines
    then exit 2: a mistyped path is named as such, not taken for an empty folder)."""
    for p in paths:
        if not os.path.exists(p):
            print(f"{name}: no such file or folder {p!r}", file=sys.stderr)
            return True
    return False


def print_and_save(res: dict, format_table, json_path: str | None) -> None:
    """The table of ``res`` on stdout, and ``res`` as JSON to ``json_path`` (whole or not at
    all) when given: the end of every across-ensembles command line."""
    print("\n".join(format_table(res)))
    if json_path:
        atomic_json(json_path, _jsonable(res), indent=1)


def analyse_or_report(analyse, args: tuple, name: str, empty: str) -> dict | None:
    """``analyse(*args)``, or None after one line on stderr: the ValueError of a bad input, or
    ``empty`` when it found no ensemble (the command lines then exit 2)."""
    try:
        res = analyse(*args)
    except ValueError as e:
        print(f"{name}: {e}", file=sys.stderr)
        return None
    if not res["table"]:
        print(f"{name}: {empty}", file=sys.stderr)
        return None
    return res


def run_cli(argv, prog: str, description: str, analyse, format_table, empty: str,
            export=None) -> int:
    """The command line of an across-ensembles analysis: FOLDER... [--json OUT] [--boot B]
    (and [--export DIR] when ``export(folders, DIR)`` is given: it returns the files it
    wrote); prints ``format_table(analyse(folders, boot))``; exit 2 with one line: ``empty``
    when no ensemble is found, for a negative --boot, or the ValueError of a bad input."""
    ap = argparse.ArgumentParser(prog=prog, description=description)
    ap.add_argument("folders", nargs="+", metavar="FOLDER",
                    help="ensemble folders, or folders holding them" + (
                        " (and sample tables: see --export)" if export is not None else ""))
    ap.add_argument("--json", metavar="OUT", help="write the result as JSON")
    ap.add_argument("--boot", type=int, default=N_BOOT, help=f"bootstrap resamples ({N_BOOT})")
    if export is not None:
        ap.add_argument("--export", metavar="DIR",
                        help="write each ensemble folder's sample table (JSON) into DIR")
    args = ap.parse_args(argv)
    name = prog.rsplit(".", 1)[-1]
    if args.boot < 0:
        print(f"{name}: --boot must be >= 0 (0: no bootstrap)", file=sys.stderr)
        return 2
    if missing_path(args.folders, name):
        return 2
    res = analyse_or_report(analyse, (args.folders, args.boot), name, empty)
    if res is None:
        return 2
    print_and_save(res, format_table, args.json)
    if export is not None and args.export:
        for path in export(args.folders, args.export):
            print(f"{name}: wrote {path}")
    return 0


def main(argv=None) -> int:
    return run_cli(argv, "python -m parflow.post.network_across_ensembles",
                   "C, C2, omega*, l_c per dz over network ensembles, and their power laws in dz",
                   analyse, format_table, "no network ensemble found", export=export)


if __name__ == "__main__":
    sys.exit(main())
