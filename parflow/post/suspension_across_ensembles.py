"""Suspension ensembles across phi (docs/suspensions.md "Ensembles across phi"): the numbers
of Figs. 6-7 as the mean over the samples of one ensemble per phi with its standard error,
and their laws across phi with errors from a bootstrap over the samples.

Per sample (one run file of an ensemble folder, ``parflow.ensemble``; only samples whose
status is complete, jammed or budget; the statistics window is the scene's, as in
``post.suspension.suspension_fits``):

* ``sigma``, ``pressure``, ``mu`` (= the strain-weighted sigma/p), ``z2``, ``z_all``: window
  averages; ``dz`` = 4 - z2 and ``dz_all`` = 4 - z_all (docs/suspensions.md: z2 removes
  particles with fewer than 2 force-bearing contacts; the d + 1 rule of jammed packings
  removes nearly every particle of a flowing state at phi <= 0.825);
* ``l_c`` (point response) and ``corr_length`` (C(r) crossing 1/e): medians over the
  window's analysis instants;
* ``dgs``: delta_gamma * sigma of the frozen contact network, the mean over the instants
  (constant if delta_gamma ~ 1/sigma);
* ``C2``: the median over the instants of omega_min(frozen) * sqrt(sigma(frozen)) (constant in
  sigma if omega_min ~ 1/sqrt(sigma); the networks' C2, predicted ~ dz^(1/2));
* ``omega_exp``, ``dgamma_exp``: the sample's own power-law exponents of omega_min and
  delta_gamma against sigma over its instants (predicted -1/2 and -1; one sample spans a
  narrow range of sigma, hence a large scatter: at phi = 0.835 one sample gives -12);
* ``C_relax``: the median C of the frozen network's relaxation, dsigma/dgamma = -sigma^2/C;
* ``strain``: the strain the sample ran (the exposure of the jamming rate).

Per phi (:func:`per_phi`): for each quantity the mean over the samples where it is finite,
the standard error s / sqrt(n) (ddof = 1) and n; the jamming rate per unit strain with its
Poisson error (``post.ensemble.jamming_rate``); ``omega_exp_pooled`` and
``dgamma_exp_pooled``, the exponents of omega_min(sigma) and delta_gamma(sigma) fitted over
the instants of all samples pooled, with a jackknife error over the samples
(:func:`pooled_exponent`).

Across phi (:func:`across`), every fit with a bootstrap over the samples: the samples of each
phi are redrawn with replacement :data:`N_BOOT` times (fixed seed), *the same draw for every
quantity* (so x and y of a fit such as sigma(dz) stay paired: the error of dz enters), the
means recomputed and refitted with the weights of the full data held fixed.

* power laws y = A x^p (:func:`fit_power`): weighted least squares of log(mean y) on
  log(mean x), weight (mean y / sem y)^2 (``post.fits.fit_power_law_err``: its ``err`` is the
  covariance error, times sqrt(chi2/dof) when that exceeds 1); ``boot_err`` the bootstrap's
  standard deviation of p.  sigma and p against dz (predicted -2.7), l_c against p (0.18)
  and dz (-1/2), corr_length against dz, C2 against dz (1/2), dgs against sigma (0);
* divergences y = A (phi_c - phi)^(-beta) (:func:`fit_divergence`): with phi_c free, the
  phi_c of least weighted chi2 on a grid (:data:`PHI_C_GRID` points between max(phi) + 1e-4
  and 0.9), beta by WLS there; with phi_c fixed at :data:`PHI_J` (0.843, the jamming point of
  the mixture, ``packing.mixture.PHI_J_2D``), beta by WLS.  For sigma and for p: mu = sigma/p drifts with phi
  (0.27 -> 0.14 over 0.810-0.835), so the two betas differ.

Sample tables (:func:`export_samples`, :func:`load_samples`): the per-sample numbers of one
ensemble (everything above uses, the instants' points included) as one small JSON file
(kind :data:`SAMPLES_KIND`, with the git commit, version and creation time of each sample's
run file and the scene of sample 0), so that ensembles run at different times, on machines
whose run files are gone, enter one analysis: docs/data/suspension_ensembles/ holds those of
the ensembles docs/suspensions.md quotes.  An analysis reads run folders and tables alike;
sources of the same (N, phi) are pooled into one ensemble when they are the same scene but
for its seed and share no sample seed (:func:`pool`: more samples of a phi, run at another
time), and refused otherwise.

``python -m parflow.post.suspension_across_ensembles PATH... [--json OUT] [--export DIR]``
prints the table and the fits; a PATH is an ensemble folder, a sample table, or a folder
searched one level down for both; ``--export DIR`` writes the sample table of every ensemble
folder read into DIR (``phi0.8100_N4096.json``).  Figures:
``python -m parflow.plot.suspension_ensembles``.
"""
from __future__ import annotations

import math
import os
import sys

import numpy as np

from .ensemble import (check_poolable, find_sources, finished_samples, jackknife, jamming_rate,
                       rate_exposure,
                       mean_sem, nan_floats, read_table)
from ..io import atomic_json
from .fits import fit_power_law_err
from .network_across_ensembles import _jsonable, run_cli
from .suspension import suspension_fits

PHI_J = 0.843                     # phi_J of the mixture, = packing.mixture.PHI_J_2D (post does
#                                   not import the model side; tested equal): the fixed phi_c
PHI_C_MAX = 0.9                   # the free phi_c is searched in (max phi + 1e-4, PHI_C_MAX)
PHI_C_GRID = 4000
N_BOOT = 1000
BOOT_SEED = 0
QUANTITIES = ("sigma", "pressure", "mu", "z2", "z_all", "dz", "dz_all", "l_c", "corr_length",
              "dgs", "C2", "omega_exp", "dgamma_exp", "C_relax", "collisions_per_strain",
              "strain")
# (name, y, x, predicted exponent): the power laws across phi
POWER_LAWS = (("sigma_dz", "sigma", "dz", -2.7), ("pressure_dz", "pressure", "dz", -2.7),
              ("sigma_dz_all", "sigma", "dz_all", -2.7), ("lc_p", "l_c", "pressure", 0.18),
              ("lc_dz", "l_c", "dz", -0.5), ("corr_dz", "corr_length", "dz", -0.5),
              ("C2_dz", "C2", "dz", 0.5), ("dgs_sigma", "dgs", "sigma", 0.0))
DIVERGENCES = ("sigma", "pressure")
SAMPLES_KIND = "parflow suspension ensemble samples"
SAMPLES_VERSION = 1
ROW_KEYS = ("sample", "seed", "status", "steps", "phi", "N") + QUANTITIES


# ---------------------------------------------------------------------------------------
# one sample, one ensemble
# ---------------------------------------------------------------------------------------
def sample_values(run) -> dict:
    """The per-sample numbers (:data:`QUANTITIES`) of one suspension run."""
    f = suspension_fits(run)
    nan = float("nan")

    def first(key):
        v = f.get(key)
        return float(v[0]) if isinstance(v, tuple) else nan
    out = {q: first(q) for q in ("sigma", "pressure", "mu", "z2", "z_all")}
    out["dz"], out["dz_all"] = 4.0 - out["z2"], 4.0 - out["z_all"]
    out["l_c"], out["corr_length"] = first("resp_l_c"), first("corr_length")
    sig, dg = (np.asarray(a, float) for a in f.get("delta_gamma_points", ([], [])))
    v = sig * dg
    v = v[np.isfinite(v)]
    out["dgs"] = float(v.mean()) if v.size else nan
    sig, om = (np.asarray(a, float) for a in f.get("omega_min_points", ([], [])))
    c2 = om * np.sqrt(np.where(sig > 0, sig, np.nan))
    c2 = c2[np.isfinite(c2)]
    out["C2"] = float(np.median(c2)) if c2.size else nan
    out["points"] = dict(omega=(sig, om), dgamma=tuple(np.asarray(a, float) for a in
                                                      f.get("delta_gamma_points", ([], []))))
    out["omega_exp"] = float(f.get("omega_min", {}).get("exponent", nan))
    out["dgamma_exp"] = float(f.get("delta_gamma", {}).get("exponent", nan))
    out["C_relax"] = float(f.get("relax_frozen", {}).get("C_median", nan))
    out["collisions_per_strain"] = float(f.get("collisions_per_strain", nan))
    st = run.ts.get("strain")
    out["strain"] = float(st[-1]) if st is not None and len(st) else nan
    # the strain at the final phi and whether it jammed before (compressed while flowing)
    out["rate_strain"], out["jammed_compressing"] = rate_exposure(run)
    out["phi"] = float(f.get("phi", nan))
    out["N"] = int(f.get("N", 0))
    return out


def read_ensemble(folder: str) -> dict:
    """The finished suspension samples of one ensemble folder: index, seed, status, steps and
    :func:`sample_values`; and every sample's status (for the jamming rate).  ``provenance``:
    each sample's git commit, parflow version and creation time, and sample 0's scene."""
    rows, prov = [], dict(samples=[], scene="")
    for r, row in finished_samples(folder, "suspension"):
        rows.append(row | sample_values(r))
        prov["samples"].append(dict(sample=row["sample"], **{
            k: str(r.attrs.get(k, "")) for k in ("git_commit", "parflow_version", "created")}))
        if not prov["scene"]:
            prov["scene"] = str(r.attrs.get("scene", ""))
    return dict(folder=folder, samples=rows, provenance=prov)


def export_samples(ens: dict, path: str) -> None:
    """Write the sample table of ``ens`` (:func:`read_ensemble`) to ``path`` (JSON; written to
    a twin and renamed: never half-written; NaN as null)."""
    rows = []
    for x in ens["samples"]:
        r = {k: x[k] for k in ROW_KEYS}
        r["points"] = {k: [np.asarray(a, float).tolist() for a in v]
                       for k, v in x["points"].items()}
        rows.append(r)
    doc = dict(kind=SAMPLES_KIND, version=SAMPLES_VERSION,
               source=os.path.basename(os.path.normpath(ens["folder"])),
               provenance=ens.get("provenance", {}), samples=rows)
    atomic_json(path, _jsonable(doc), indent=1, allow_nan=False)


def load_samples(path: str) -> dict:
    """An ensemble (as :func:`read_ensemble`) from a sample table written by
    :func:`export_samples`; ValueError naming the file if it is not one."""
    doc = read_table(path, SAMPLES_KIND, SAMPLES_VERSION, "suspension sample table")
    rows = []
    for r in doc.get("samples", []):
        missing = [k for k in ROW_KEYS + ("points",) if k not in r]
        if missing:
            raise ValueError(f"{path}: sample {r.get('sample')} lacks {', '.join(missing)}")
        row = {k: r[k] for k in ("sample", "seed", "status", "steps", "N")}
        row.update({k: math.nan if r[k] is None else float(r[k])
                    for k in ("phi",) + QUANTITIES})
        row["points"] = {k: tuple(nan_floats(a) for a in v) for k, v in r["points"].items()}
        rows.append(row)
    return dict(folder=path, samples=rows, provenance=doc.get("provenance", {}))


def per_phi(ens: dict) -> dict:
    """Mean, standard error and count of each quantity over an ensemble's samples, its phi
    and N, and the jamming rate.  Jammed samples enter the rate only: their window (if any)
    ends at the jam."""
    s = ens["samples"]
    flowing = [x for x in s if x["status"] != "jammed"]
    out = dict(folder=ens["folder"], phi=s[0]["phi"], N=s[0]["N"], n_samples=len(s),
               n_flowing=len(flowing))
    for q in QUANTITIES:
        v = np.array([x[q] for x in flowing], float)
        m, e, n = mean_sem(v)
        out[q] = dict(mean=float(m), sem=float(e), n=int(n), values=v.tolist())
    out["jamming_rate"] = jamming_rate([x["status"] for x in s],
                                       [x.get("rate_strain", x["strain"]) for x in s],
                                       [x.get("jammed_compressing", False) for x in s])
    for key in ("omega", "dgamma"):
        out[f"{key}_exp_pooled"] = pooled_exponent([x["points"][key] for x in flowing])
    return out


def pooled_exponent(points: list) -> dict:
    """The power-law exponent of y against sigma over the analysis instants of all samples
    pooled (``points``: (sigma, y) per sample; one sample spans too narrow a range of sigma
    for a fit of its own), with its jackknife error over the samples (leave one out)."""
    n = len(points)

    def est(keep):
        xs = [np.asarray(p[0], float) for p, k in zip(points, keep) if k]
        ys = [np.asarray(p[1], float) for p, k in zip(points, keep) if k]
        if not xs:
            return math.nan
        return fit_power_law_err(np.concatenate(xs), np.concatenate(ys))["exponent"]
    if n == 0:
        return dict(mean=math.nan, sem=math.nan, n=0)
    value, err = jackknife(est, n)
    return dict(mean=float(value), sem=float(err), n=int(n))


# ---------------------------------------------------------------------------------------
# across phi
# ---------------------------------------------------------------------------------------
def boot_draws(table: list[dict], n_boot: int = N_BOOT, seed: int = BOOT_SEED) -> list:
    """One index array (n_boot, n) per row of ``table`` (n its flowing samples), drawn once
    and used for every quantity (paired resampling)."""
    rng = np.random.default_rng(seed)
    return [rng.integers(0, max(t["n_flowing"], 1), (n_boot, max(t["n_flowing"], 1)))
            for t in table]


def _boot_means(table: list[dict], q: str, draws: list) -> np.ndarray:
    """(n_boot, len(table)): the mean of quantity q over each bootstrap draw of each row
    (NaN where a drawn value is not finite)."""
    cols = []
    for t, idx in zip(table, draws):
        v = np.asarray(t[q]["values"], float)
        cols.append(v[idx].mean(axis=1) if v.size else np.full(idx.shape[0], np.nan))
    return np.column_stack(cols)


def _wls(X, Y, w):
    """Slope and intercept of Y on X with weights w, along the last axis; X (..., n),
    Y (..., n), w (n,).  Also chi2."""
    W = w.sum()
    xm = (X * w).sum(-1, keepdims=True) / W
    ym = (Y * w).sum(-1, keepdims=True) / W
    sxx = (w * (X - xm) ** 2).sum(-1)
    sxy = (w * (X - xm) * (Y - ym)).sum(-1)
    syy = (w * (Y - ym) ** 2).sum(-1)
    slope = sxy / sxx
    return slope, ym[..., 0] - slope * xm[..., 0], syy - sxy ** 2 / sxx


def _summary(p: np.ndarray) -> dict:
    p = p[np.isfinite(p)]
    if p.size < 2:
        return dict(boot_err=math.nan, boot_p16=math.nan, boot_p84=math.nan, boot_n=int(p.size))
    return dict(boot_err=float(np.std(p, ddof=1)), boot_p16=float(np.percentile(p, 16)),
                boot_p84=float(np.percentile(p, 84)), boot_n=int(p.size))


def fit_power(table: list[dict], y: str, x: str, predicted: float = math.nan,
              draws: list | None = None) -> dict:
    """y = A x^p across the rows of ``table`` (:func:`per_phi` entries) from their means,
    weights (mean y / sem y)^2, with the paired bootstrap of ``draws``."""
    xm = np.array([t[x]["mean"] for t in table], float)
    ym = np.array([t[y]["mean"] for t in table], float)
    ye = np.array([t[y]["sem"] for t in table], float)
    f = fit_power_law_err(xm, ym, ye)
    out = dict(exponent=f["exponent"], err=f["err"], prefactor=f["prefactor"], chi2=f["chi2"],
               dof=f["dof"], n_phi=f["n"], predicted=float(predicted), deviation=math.nan,
               x=x, y=y, boot_err=math.nan, boot_p16=math.nan, boot_p84=math.nan, boot_n=0)
    if np.isfinite(predicted) and np.isfinite(f["err"]) and f["err"] > 0:
        out["deviation"] = (f["exponent"] - predicted) / f["err"]
    use = np.isfinite(xm) & np.isfinite(ym) & np.isfinite(ye) & (xm > 0) & (ym > 0) & (ye > 0)
    if draws is not None and use.sum() >= 2:
        bx, by = _boot_means(table, x, draws)[:, use], _boot_means(table, y, draws)[:, use]
        ok = np.all((bx > 0) & (by > 0) & np.isfinite(bx) & np.isfinite(by), axis=1)
        w = (ym[use] / ye[use]) ** 2
        p, _, _ = _wls(np.log(bx[ok]), np.log(by[ok]), w)
        out.update(_summary(p))
    return out


def _divergence(phi, Y, w, phi_c=None, grid: int = PHI_C_GRID):
    """log y = log A - beta log(phi_c - phi) with weights w; Y (B, n) or (n,).  phi_c None:
    the grid value of least chi2 per row.  Returns (phi_c, beta, log A, chi2), each (B,)."""
    Y = np.atleast_2d(Y)
    if phi_c is not None:
        X = np.broadcast_to(np.log(phi_c - phi), Y.shape)
        s, c, chi2 = _wls(X, Y, w)
        return np.full(Y.shape[0], phi_c), -s, c, chi2
    pcs = np.linspace(phi.max() + 1e-4, PHI_C_MAX, grid)
    X = np.log(pcs[:, None] - phi[None, :])                         # (G, n)
    W = w.sum()
    Xc = X - (X * w).sum(1, keepdims=True) / W                      # (G, n)
    Yc = Y - (Y * w).sum(1, keepdims=True) / W                      # (B, n)
    sxx = (w * Xc ** 2).sum(1)                                      # (G,)
    sxy = (Yc * w) @ Xc.T                                           # (B, G)
    syy = (w * Yc ** 2).sum(1)                                      # (B,)
    chi2 = syy[:, None] - sxy ** 2 / sxx[None, :]
    j = np.argmin(chi2, axis=1)
    rows = np.arange(Y.shape[0])
    s = sxy[rows, j] / sxx[j]
    xm = (X[j] * w).sum(1) / W
    ym = (Y * w).sum(1) / W
    return pcs[j], -s, ym - s * xm, chi2[rows, j]


def fit_divergence(table: list[dict], y: str, phi_c: float | None = None,
                   draws: list | None = None) -> dict:
    """y = A (phi_c - phi)^(-beta) across the rows of ``table``; ``phi_c`` None: fitted (the
    grid of :data:`PHI_C_GRID` points up to :data:`PHI_C_MAX`; needs 4 points, 3 parameters),
    else fixed.  Weights (mean / sem)^2 in log y; bootstrap errors of phi_c and beta."""
    phi = np.array([t["phi"] for t in table], float)
    ym = np.array([t[y]["mean"] for t in table], float)
    ye = np.array([t[y]["sem"] for t in table], float)
    use = np.isfinite(phi) & np.isfinite(ym) & np.isfinite(ye) & (ym > 0) & (ye > 0)
    if phi_c is not None:
        use &= phi < phi_c
    out = dict(y=y, phi_c=math.nan, beta=math.nan, prefactor=math.nan, chi2=math.nan, dof=0,
               n_phi=int(use.sum()), fixed=phi_c is not None, phi_c_boot_err=math.nan,
               phi_c_p16=math.nan, phi_c_p84=math.nan, beta_boot_err=math.nan,
               beta_p16=math.nan, beta_p84=math.nan)
    npar = 2 if phi_c is not None else 3
    if use.sum() < npar + 1:
        return out
    w = (ym[use] / ye[use]) ** 2
    pc, beta, c, chi2 = _divergence(phi[use], np.log(ym[use]), w, phi_c)
    out.update(phi_c=float(pc[0]), beta=float(beta[0]), prefactor=float(np.exp(c[0])),
               chi2=float(chi2[0]), dof=int(use.sum() - npar))
    if draws is not None:
        by = _boot_means(table, y, draws)[:, use]
        ok = np.all(np.isfinite(by) & (by > 0), axis=1)
        pcb, bb, _, _ = _divergence(phi[use], np.log(by[ok]), w, phi_c)
        for name, arr in (("beta", bb), ("phi_c", pcb)):
            if phi_c is not None and name == "phi_c":
                continue
            s = _summary(arr)
            out.update({f"{name}_boot_err": s["boot_err"], f"{name}_p16": s["boot_p16"],
                        f"{name}_p84": s["boot_p84"]})
    return out


def across(table: list[dict], n_boot: int = N_BOOT, seed: int = BOOT_SEED) -> dict:
    """Every fit across phi (for each N): :data:`POWER_LAWS`, and the divergences of
    :data:`DIVERGENCES` with phi_c free and fixed at :data:`PHI_J`."""
    out = {}
    for N in sorted({t["N"] for t in table}):
        rows = sorted((t for t in table if t["N"] == N), key=lambda t: t["phi"])
        draws = boot_draws(rows, n_boot, seed) if n_boot > 1 else None
        res = {name: fit_power(rows, y, x, pred, draws) for name, y, x, pred in POWER_LAWS}
        for y in DIVERGENCES:
            res[f"{y}_phi_free"] = fit_divergence(rows, y, None, draws)
            res[f"{y}_phi_fixed"] = fit_divergence(rows, y, PHI_J, draws)
        out[int(N)] = res
    return out


def pool(group: list[dict]) -> dict:
    """One ensemble from several of the same (N, phi): their samples together, if they may be
    pooled (``post.ensemble.check_poolable``: the same scene but for the seed, e.g. the same
    scene run again with another ``seed`` -- docs/ensembles.md -- and no sample twice); else
    ValueError naming the two."""
    check_poolable([(e["folder"], e.get("provenance", {}).get("scene", ""),
                     [x["seed"] for x in e["samples"]]) for e in group])
    if len(group) == 1:
        return group[0]
    return dict(folder=" + ".join(e["folder"] for e in group),
                samples=[x for e in group for x in e["samples"]],
                provenance=dict(scene=group[0]["provenance"]["scene"],
                                samples=[p for e in group
                                         for p in e.get("provenance", {}).get("samples", [])]))


def read_sources(paths) -> list[dict]:
    """The ensembles under ``paths`` (:func:`find_sources`) with a finished sample, those of
    the same (N, phi) pooled (:func:`pool`)."""
    folders, tables = find_sources(paths, ".json")
    ens = [read_ensemble(f) for f in folders] + [load_samples(t) for t in tables]
    groups: dict = {}
    for e in ens:
        if e["samples"]:
            key = (int(e["samples"][0]["N"]), round(float(e["samples"][0]["phi"]), 6))
            groups.setdefault(key, []).append(e)
    return [pool(g) for g in groups.values()]


def analyse(paths, n_boot: int = N_BOOT) -> dict:
    """The suspension ensembles under ``paths``: the per-phi table and the fits across phi."""
    ens = read_sources(paths)
    table = sorted((per_phi(e) for e in ens), key=lambda t: (t["N"], t["phi"]))
    return dict(table=table, across=across(table, n_boot), phi_j=PHI_J)


def export(paths, out_dir: str) -> list[str]:
    """Write the sample table of every ensemble folder under ``paths`` into ``out_dir``; the
    files written."""
    os.makedirs(out_dir, exist_ok=True)
    written = []
    for f in find_sources(paths)[0]:
        e = read_ensemble(f)
        if not e["samples"]:
            continue
        s0 = e["samples"][0]
        path = os.path.join(out_dir, f"phi{s0['phi']:.4f}_N{int(s0['N'])}.json")
        export_samples(e, path)
        written.append(path)
    return written


# ---------------------------------------------------------------------------------------
# report
# ---------------------------------------------------------------------------------------
TABLE_COLUMNS = ("sigma", "pressure", "mu", "z2", "dz", "l_c", "corr_length", "dgs", "C2",
                 "omega_exp_pooled", "dgamma_exp_pooled", "C_relax")


def _pm(d: dict, digits: int = 4) -> str:
    if not np.isfinite(d["mean"]):
        return "—"
    e = f" ± {d['sem']:.2g}" if np.isfinite(d["sem"]) else ""
    return f"{d['mean']:.{digits}g}{e}"


def format_table(res: dict) -> list[str]:
    """The per-phi table (markdown) and the fits, as lines."""
    lines = ["| N | phi | samples (flowing) | " + " | ".join(TABLE_COLUMNS)
             + " | jams / strain |", "|---" * (4 + len(TABLE_COLUMNS)) + "|"]
    for t in res["table"]:
        jr = t["jamming_rate"]
        lines.append(f"| {t['N']} | {t['phi']:.4g} | {t['n_samples']} ({t['n_flowing']}) | "
                     + " | ".join(_pm(t[q]) for q in TABLE_COLUMNS)
                     + f" | {jr['n_jammed']} in {jr['strain']:.3g} |")
    lines.append("")
    for N, fits in res["across"].items():
        for name, f in fits.items():
            if "beta" in f:
                if not np.isfinite(f["beta"]):
                    continue
                pc = (f"phi_c = {f['phi_c']:.4f} fixed" if f["fixed"] else
                      f"phi_c = {f['phi_c']:.4f} ± {f['phi_c_boot_err']:.4f} bootstrap "
                      f"(16-84 % {f['phi_c_p16']:.4f}..{f['phi_c_p84']:.4f})")
                lines.append(f"N = {N}: {f['y']} = A (phi_c - phi)^-beta: {pc}, beta = "
                             f"{f['beta']:.3f} ± {f['beta_boot_err']:.3f} bootstrap "
                             f"(16-84 % {f['beta_p16']:.3f}..{f['beta_p84']:.3f}), "
                             f"chi2/dof = {f['chi2']:.2f}/{f['dof']}, {f['n_phi']} phi")
                continue
            if not np.isfinite(f["exponent"]):
                continue
            pred = (f"; predicted {f['predicted']:+g}: {f['deviation']:+.1f} sigma"
                    if np.isfinite(f["predicted"]) and np.isfinite(f["deviation"]) else "")
            lines.append(f"N = {N}: {f['y']} ~ {f['x']}^({f['exponent']:.3f} ± {f['err']:.3f}"
                         f" WLS, ± {f['boot_err']:.3f} bootstrap; 16-84 % "
                         f"{f['boot_p16']:.3f}..{f['boot_p84']:.3f}) chi2/dof = "
                         f"{f['chi2']:.2f}/{f['dof']}, {f['n_phi']} phi{pred}")
    return lines


def main(argv=None) -> int:
    return run_cli(argv, "python -m parflow.post.suspension_across_ensembles",
                   "sigma, p, mu, z, l_c, delta_gamma*sigma, C2 per phi over suspension "
                   "ensembles, and their laws across phi", analyse, format_table,
                   "no suspension ensemble with a finished sample found (run one: "
                   "runs/ensemble_suspension_phi*.toml)", export=export)


if __name__ == "__main__":
    sys.exit(main())
