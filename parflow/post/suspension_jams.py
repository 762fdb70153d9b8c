"""Where a flowing suspension shear-jams, across N (docs/suspensions.md "A flowing start at
phi = 0.840"): the finite-size shear-jamming point phi_SJ(N) of the compress-while-flowing
protocol (``model.compress_rate``: the discs swell while they are sheared, until a compressed
self-stress is *proved*, status ``jammed``, the certificate in the run file's ``/jam``).

Per sample (:func:`jam_record`, one run file of an ensemble folder): its status; for a jam,
the phi where it jammed (``/jam`` attrs ``phi``; a sample that reached ``compress_to`` and
jammed later, at constant phi, has no ``/jam/phi``: its last phi, flagged ``constant_phi``),
gamma, the certificate's support, tau.b and the shear's share of it (``tau_b_shear`` < 0: the
flow, not the swelling, compresses the self-stress: a *shear* jam), the strain budget; for a
sample that did not jam, the phi it reached.

Per N (:func:`analyse`, samples grouped by N and compression rate): the phi of the shear
jams -- mean, standard deviation, standard error (ddof = 1), count -- and the samples that
did not shear-jam.  A sample whose start (rate, N, sample seed) another ensemble compressed
further (a larger ``compress_to``) is left out and counted (``superseded``): capped at its
``compress_to``, it is a truncation of that sample, not an independent one.  Across N, for
one rate: the finite-size form of the jamming point of packings (O'Hern et al. 2003:
phi*(N) - phi_J ~ N^(-1/(d nu)) with 1/(d nu) = 0.71 in 2D and 3D)

    phi_SJ(N) = phi_inf - a N^(-X_FSS),  X_FSS = 0.71 fixed,

by weighted least squares (weights 1/sem^2; ``chi2_dof``; the error of phi_inf from the
covariance, times sqrt(chi2/dof) when that exceeds 1), and phi_inf against PHI_J = 0.843, the
jamming point of the mixture (does phi_SJ(N) tend to phi_J?); with four sizes or more also
with the exponent free (:func:`fit_fss_free`: a grid over it, and the range of phi_inf over
the exponents whose chi2 is within 1 of the least).  Three or four N with a few samples
each: a rough test, and it says so (the errors).

Jam tables (:func:`export`): every sample record of the paths read as one small JSON file
(kind :data:`JAMS_KIND`), so that ensembles whose run files are gone enter the analysis:
docs/data/suspension_jams.json holds those docs/suspensions.md quotes.

Jams at constant phi (:func:`constant_phi_rates`): per (N, phi), the certified jams per unit
strain of the samples that ran there -- compressed to it while flowing, or started there --
each exposed for the strain it ran at that phi (``strain_at_phi``), with the exact Poisson
interval and the chance that a sample flows 3 strain there without a jam (the paper's 300 %).
Single run files enter as well (the flowing seeds of runs/, e.g.
runs/suspension_phi0.840_flowing_seed*.toml).

Stress excursions at constant phi (:func:`excursion_peaks`): the near-jams that came back.
An excursion starts at a row with sigma >= EXCURSION_ON and ends where sigma has stayed below
EXCURSION_OFF for EXCURSION_QUIET strain (the hysteresis counts a stretch that hovers about
EXCURSION_ON once, and the quiet strain passes over the single low rows that follow a cut
step near a jam: docs/suspensions.md, "sigma of single steps near a jam depends on the step
size"); its peak is the largest sigma within.  Per (N, phi), pooled like the jams: the
excursions whose peak reaches each of EXCURSION_LEVELS, per unit strain.  A certified jam
ends a sample inside its last excursion (counted, still open).  They are not independent
events (a sample that wanders near a jammed configuration makes many in a row), so no
Poisson interval is given for them.

``python -m parflow.post.suspension_jams PATH... [--json OUT] [--export FILE]`` prints the
tables and the fit; a PATH is an ensemble folder, a jam table, a suspension run file, or a
folder searched one level down for them.  Figure: ``python -m parflow.plot.suspension_jams PATH...``.
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import tomllib

import numpy as np

from ..io import RunFile, atomic_json
from .ensemble import (final_phi_row, find_sources, mean_sem, read_table, sample_files,
                       strain_at_final_phi)
from .network_across_ensembles import _jsonable, missing_path, print_and_save

JAMS_KIND = "parflow suspension jams"
JAMS_VERSION = 1
PHI_J = 0.843                  # phi_J of the mixture (= post.suspension_across_ensembles.PHI_J)
X_FSS = 0.71                   # 1/(d nu) of the jamming point's finite-size shift
ENDED = ("jammed", "complete", "budget", "interrupted")   # the statuses read
FLOWING = ("complete", "budget", "interrupted")   # ended still flowing: phi a lower bound
RECORD_KEYS = ("source", "sample", "seed", "N", "compress_rate", "compress_to", "status",
               "shear_jam", "phi", "constant_phi", "gamma", "support", "tau_b", "tau_b_shear",
               "strain_budget", "git_commit")
# keys a table may lack (written before they existed): read as NaN -- except strain_at_phi of
# a sample that was not compressed, which is then its last gamma (every suspension scene
# such a table came from ran one forward leg)
OPTIONAL_KEYS = ("strain_at_phi", "excursion_peaks", "branched_from")
RATE_CI = 0.95                 # the coverage of the jam rate's interval (exact Poisson)
# a stress excursion: sigma rises to >= EXCURSION_ON, and it is over when sigma has stayed
# below EXCURSION_OFF for EXCURSION_QUIET strain (flowing at phi = 0.840, N = 4096: sigma's
# median ~200, 5-95 % ~70-830; a step ~1e-4 strain, so the quiet strain is ~10 calm steps)
EXCURSION_ON = 1e3
EXCURSION_OFF = 1e2
EXCURSION_QUIET = 1e-3
EXCURSION_LEVELS = (1e3, 1e4, 1e5, 1e6, 1e7)   # the peaks counted: excursions reaching each
FLOW_STRAIN = 3.0              # the strain the paper ran before its statistics (300 %)


def excursion_peaks(sigma, strain=None, on: float = EXCURSION_ON, off: float = EXCURSION_OFF,
                    quiet: float = EXCURSION_QUIET) -> np.ndarray:
    """The peak of each stress excursion of the time series ``sigma`` (module docstring), in
    order: a stretch from a row with sigma >= ``on`` to the first row of a run of rows below
    ``off`` whose steps add up to ``quiet`` strain or more (``strain``: the cumulative strain
    of the rows; without it, or with quiet = 0, any row below ``off`` ends it), or to the end
    of the series (an excursion still open)."""
    sig = np.asarray(sigma, float)
    if sig.size == 0:
        return np.zeros(0)
    idx = np.arange(sig.size)
    below = sig < off
    ends = below
    if strain is not None and quiet > 0:
        ds = np.diff(np.asarray(strain, float), prepend=float(strain[0]))   # each row's step
        first = below & ~np.r_[False, below[:-1]]
        run = np.cumsum(first) * below                  # 1, 2, ... per run of low rows; 0 else
        long_run = np.bincount(run, weights=np.where(below, np.abs(ds), 0.0)) >= quiet
        long_run[0] = False
        ends = first & long_run[run]
    # inside an excursion: the last row at or above `on` is later than the last end
    last_on = np.maximum.accumulate(np.where(sig >= on, idx, -1))
    last_off = np.maximum.accumulate(np.where(ends, idx, -1))
    inside = last_on > last_off
    if not inside.any():
        return np.zeros(0)
    start = inside & ~np.r_[False, inside[:-1]]
    vals = sig[inside]
    return np.fmax.reduceat(vals, np.flatnonzero(start[inside]))     # fmax: a NaN row is passed over


def jam_record(path: str, source: str = "", sample: int = -1) -> dict:
    """The jam (or its absence) of one suspension run file (see the module docstring)."""
    with RunFile(path) as rf:
        attrs = rf.attrs
        if rf.model != "suspension":
            raise ValueError(f"{path}: a {rf.model or 'unknown'} run, not a suspension")
        try:
            scene = tomllib.loads(rf.scene_text)
        except tomllib.TOMLDecodeError:
            scene = {}
        model = scene.get("model", {})
        ts = rf.timeseries()
        g = rf.h5.get("jam")
        jam = {k: v.item() if isinstance(v, np.generic) else v for k, v in g.attrs.items()} \
            if g is not None else {}
    nan = math.nan
    phi_ts = ts.get("phi")
    phi_last = float(phi_ts[-1]) if phi_ts is not None and len(phi_ts) \
        else float(model.get("phi", nan))
    status = str(attrs.get("status", ""))
    jammed = status == "jammed" and bool(jam.get("certified", False))
    has_phi = "phi" in jam
    tbs = float(jam.get("tau_b_shear", jam.get("tau_b", nan))) if jammed else nan
    rate, to = float(model.get("compress_rate", 0.0)), float(model.get("compress_to", nan))
    strain = ts.get("strain", ts.get("gamma", []))
    if rate > 0:            # exposed from where phi reached compress_to (no phi column: unknown)
        at_phi = strain_at_final_phi(strain, phi_ts, to) if phi_ts is not None else nan
        first = final_phi_row(phi_ts, to) if phi_ts is not None else None
    else:
        at_phi = float(strain[-1]) if len(strain) else nan
        first = 0
    sig = ts.get("sigma")
    # the excursions over the same rows as the exposure (None: no sigma column, or never there)
    peaks = (excursion_peaks(sig[first:], np.asarray(strain, float)[first:]).tolist()
             if sig is not None and first is not None and len(strain) == len(sig) else None)
    return dict(source=source, sample=int(sample), seed=int(attrs.get("sample_seed", -1)),
                N=int(model.get("N", 0)), compress_rate=rate, compress_to=to, status=status,
                shear_jam=bool(jammed and tbs < 0),
                phi=float(jam["phi"]) if jammed and has_phi else phi_last,
                constant_phi=bool(jammed and not has_phi),
                gamma=float(jam.get("gamma", nan)) if jammed else
                (float(ts["gamma"][-1]) if len(ts.get("gamma", [])) else nan),
                support=int(jam.get("support", 0)) if jammed else 0,
                tau_b=float(jam.get("tau_b", nan)) if jammed else nan, tau_b_shear=tbs,
                strain_budget=float(jam.get("strain_budget", nan)) if jammed else nan,
                git_commit=str(attrs.get("git_commit", "")), strain_at_phi=at_phi,
                excursion_peaks=peaks, branched_from=_branch_source(attrs))


def _branch_source(attrs) -> str:
    """The source name (file name without .h5) of the run a branch was copied from
    (``branched_from``: "PATH at step N"), or "" for a run that is not a branch."""
    b = str(attrs.get("branched_from", ""))
    return os.path.splitext(os.path.basename(b.rsplit(" at step ", 1)[0]))[0] if b else ""


def read_folder(folder: str) -> list[dict]:
    """The records of the sample files of an ensemble folder whose run has ended or was
    stopped (``interrupted``: the phi it flowed to is a lower bound of where it would have
    jammed); a sample still running, or one whose file does not load, is left out."""
    src = os.path.basename(os.path.normpath(folder))
    out = []
    for k, path in sample_files(folder):
        try:
            rec = jam_record(path, src, k)
        except Exception:             # a damaged or foreign file: not a sample of this analysis
            continue
        if rec["status"] in ENDED:
            out.append(rec)
    return out


def load_table(path: str) -> list[dict]:
    """The records of a jam table written by :func:`export`; ValueError naming the file if it
    is not one."""
    doc = read_table(path, JAMS_KIND, JAMS_VERSION, "suspension jam table")
    out = []
    for r in doc.get("samples", []):
        missing = [k for k in RECORD_KEYS if k not in r]
        if missing:
            raise ValueError(f"{path}: a record lacks {', '.join(missing)}")
        rec = {k: (math.nan if r.get(k) is None else r[k]) for k in RECORD_KEYS + OPTIONAL_KEYS}
        if "strain_at_phi" not in r and not rec["compress_rate"] > 0:
            rec["strain_at_phi"] = rec["gamma"]
        out.append(rec)
    return out


def read_runs(paths) -> list[dict]:
    """The records of single suspension run files (``*.h5``: e.g. the flowing seeds of
    runs/) among ``paths`` and in the folders among them (one level down), of runs that have
    ended or were stopped (source: the file's name; sample -1: not one of an ensemble).  A
    file named as a path must be a readable suspension run (ValueError naming it otherwise);
    one found in a folder that is not is passed over."""
    named = {p for p in paths if p.endswith(".h5") and os.path.isfile(p)}
    _, files = find_sources(paths, ".h5")
    out = []
    for path in files:
        try:
            rec = jam_record(path, os.path.splitext(os.path.basename(path))[0], -1)
        except Exception as e:
            if path in named:
                raise ValueError(f"{path}: not a readable suspension run file ({e})") from None
            continue
        if rec["status"] in ENDED:
            out.append(rec)
    return out


def read_sources(paths) -> list[dict]:
    """Every record of the ensemble folders, jam tables and single run files among ``paths``
    (see :func:`find_sources`, :func:`read_runs`); a sample found twice (the same source and
    index) counts once, as read from its run file rather than from a table; a single run
    that another one read was branched from (``--restart FILE --output NEW``: NEW holds
    FILE's rows up to the branch and goes on) is left out for the branch."""
    folders, tables = find_sources(paths, ".json")
    recs, seen = [], set()
    for r in [r for f in folders for r in read_folder(f)] + read_runs(paths) + \
             [r for t in tables for r in load_table(t)]:
        key = (r["source"], r["sample"])
        if key not in seen:
            seen.add(key)
            recs.append(r)
    parents = {r["branched_from"] for r in recs if r["sample"] < 0
               and isinstance(r.get("branched_from"), str) and r["branched_from"]}
    return [r for r in recs if not (r["sample"] < 0 and r["source"] in parents)]


def export(paths, out: str) -> str:
    """Write every record read from ``paths`` as one jam table at ``out`` (JSON, written to a
    twin and renamed; NaN as null)."""
    recs = read_sources(paths)
    if not recs:
        raise ValueError("no suspension ensemble sample found to export")
    atomic_json(out, _jsonable(dict(kind=JAMS_KIND, version=JAMS_VERSION, samples=recs)),
                indent=1, allow_nan=False)
    return out


def fit_fss(Ns, mean, sem, x: float = X_FSS) -> dict:
    """phi_SJ(N) = phi_inf - a N^-x by weighted least squares (weights 1/sem^2); NaN fields
    with fewer than 3 sizes (no degree of freedom left)."""
    Ns, m, e = (np.asarray(v, float) for v in (Ns, mean, sem))
    ok = np.isfinite(m) & np.isfinite(e) & (e > 0)
    out = dict(x=x, n_sizes=int(ok.sum()), phi_inf=math.nan, phi_inf_err=math.nan,
               a=math.nan, chi2_dof=math.nan, phi_j=PHI_J, sigmas_below_phi_j=math.nan)
    if ok.sum() < 3:
        return out
    t, w = Ns[ok] ** -x, 1.0 / e[ok] ** 2
    A = np.column_stack([np.ones_like(t), -t])
    cov = np.linalg.inv(A.T @ (A * w[:, None]))
    coef = cov @ (A.T @ (w * m[ok]))
    chi2 = float(np.sum(w * (m[ok] - A @ coef) ** 2))
    dof = int(ok.sum()) - 2
    err = math.sqrt(cov[0, 0]) * max(1.0, math.sqrt(chi2 / dof))
    out.update(phi_inf=float(coef[0]), a=float(coef[1]), phi_inf_err=err,
               chi2_dof=chi2 / dof, sigmas_below_phi_j=(PHI_J - float(coef[0])) / err)
    return out


X_GRID = np.round(np.arange(0.20, 2.0001, 0.005), 3)   # exponents tried by fit_fss_free


def fit_fss_free(Ns, mean, sem) -> dict:
    """phi_SJ(N) = phi_inf - a N^-x with x free too: :func:`fit_fss` at every x of
    :data:`X_GRID`, the x of least chi2 kept; ``phi_inf_range``: the phi_inf of the x whose
    chi2 is within 1 of the least (a profile interval).  NaN fields with fewer than 4 sizes
    (three parameters)."""
    fits = [fit_fss(Ns, mean, sem, float(x)) for x in X_GRID]
    out = dict(x=math.nan, phi_inf=math.nan, a=math.nan, phi_inf_range=[math.nan, math.nan],
               x_range=[math.nan, math.nan], chi2=math.nan, n_sizes=fits[0]["n_sizes"])
    if fits[0]["n_sizes"] < 4:
        return out
    chi2 = np.array([f["chi2_dof"] * (f["n_sizes"] - 2) for f in fits])
    k = int(np.argmin(chi2))
    near = chi2 <= chi2[k] + 1.0
    phis = np.array([f["phi_inf"] for f in fits])[near]
    out.update(x=float(X_GRID[k]), phi_inf=fits[k]["phi_inf"], a=fits[k]["a"],
               chi2=float(chi2[k]),
               phi_inf_range=[float(phis.min()), float(phis.max())],
               x_range=[float(X_GRID[near].min()), float(X_GRID[near].max())])
    return out


def _superseded(recs: list) -> set:
    """Indices of records whose start (the same rate, N and sample seed) was also compressed
    further in another ensemble (a larger ``compress_to``): the run that stopped compressing
    earlier is a truncation of the same sample, not an independent one, and its phi is
    capped by its ``compress_to``.  Of records with the same start and ``compress_to``,
    none is superseded (they are repeats: read_sources keeps each source's own)."""
    def start(r):
        return r["compress_rate"], r["N"], r["seed"]

    def to(r):
        return r["compress_to"] if math.isfinite(r["compress_to"]) else -math.inf

    best: dict = {}
    for r in recs:
        best[start(r)] = max(best.get(start(r), -math.inf), to(r))
    return {k for k, r in enumerate(recs) if r["seed"] >= 0 and to(r) < best[start(r)]}


def poisson_interval(n: int, level: float = RATE_CI) -> tuple[float, float]:
    """The exact (Garwood) central interval of a Poisson mean from ``n`` events:
    chi2_{(1-level)/2}(2n) / 2 and chi2_{(1+level)/2}(2n + 2) / 2 (the lower end 0 at n = 0)."""
    from scipy.stats import chi2   # scipy.stats takes ~0.4 s to import: only where a rate is computed
    a = 1.0 - level
    lo = 0.0 if n == 0 else float(chi2.ppf(a / 2, 2 * n)) / 2
    return lo, float(chi2.ppf(1 - a / 2, 2 * n + 2)) / 2


def constant_phi_rates(recs: list) -> list[dict]:
    """Genuine jams per unit strain at constant packing fraction, per (N, phi): the samples
    that got to their final phi (compressed to ``compress_to`` while flowing, or started
    there) pooled, each exposed for the strain it ran there (``strain_at_phi``; a jam ends
    a sample), the certified jams at that phi counted (a jam while the discs still swelled
    is not one of them; nor is a sample that never reached its compress_to).  Per row: the
    count, the strain, the rate with its exact Poisson interval (:data:`RATE_CI`), and the
    probability exp(-rate FLOW_STRAIN) that a sample flows FLOW_STRAIN there without a jam
    (the rate's interval mapped alike).  A sample recorded ``jammed`` without a certificate
    (written before certificates existed) cannot be placed: counted in ``uncertified``, out
    of the pool."""
    groups: dict = {}
    for r in recs:
        x = r.get("strain_at_phi", math.nan)
        if not (isinstance(x, (int, float)) and math.isfinite(x)):
            continue
        phi = r["compress_to"] if r["compress_rate"] > 0 else r["phi"]
        if not math.isfinite(phi):
            continue
        groups.setdefault((r["N"], round(float(phi), 4)), []).append(r)
    rows = []
    for (N, phi), rs in sorted(groups.items()):
        bad = [r for r in rs if r["status"] == "jammed" and not r["shear_jam"]
               and not math.isfinite(r["tau_b"])]
        rs = [r for r in rs if not any(r is b for b in bad)]
        n = sum(1 for r in rs if r["shear_jam"] and r["constant_phi"])
        strain = float(sum(r["strain_at_phi"] for r in rs))
        lo, hi = poisson_interval(n)
        rate = n / strain if strain > 0 else math.nan
        ci = [lo / strain, hi / strain] if strain > 0 else [math.nan, math.nan]
        rows.append(dict(N=N, phi=phi, n_samples=len(rs), n_jams=n, strain=strain, rate=rate,
                         rate_ci=ci, p_flow=math.exp(-FLOW_STRAIN * rate) if strain > 0
                         else math.nan,
                         p_flow_ci=[math.exp(-FLOW_STRAIN * ci[1]), math.exp(-FLOW_STRAIN * ci[0])],
                         uncertified=len(bad), sources=sorted({r["source"] for r in rs}),
                         excursions=_excursions(rs)))
    return rows


def _excursions(rs: list) -> dict:
    """The stress excursions of the samples ``rs`` pooled (those with a peak list: a table
    written before excursions were recorded has none): the strain they ran, and per level of
    EXCURSION_LEVELS the excursions whose peak reached it, their count and per unit strain;
    and the certified jams of the same samples (excursions that did not come back)."""
    known = [r for r in rs if isinstance(r.get("excursion_peaks"), list)]
    strain = float(sum(r["strain_at_phi"] for r in known))
    jams = sum(1 for r in known if r["shear_jam"] and r["constant_phi"])
    peaks = np.array([p for r in known for p in r["excursion_peaks"]], float)
    counts = [int(np.count_nonzero(peaks >= lv)) for lv in EXCURSION_LEVELS]
    return dict(n_samples=len(known), strain=strain, levels=list(EXCURSION_LEVELS),
                counts=counts, per_strain=[c / strain if strain > 0 else math.nan
                                           for c in counts],
                jams=jams, jams_per_strain=jams / strain if strain > 0 else math.nan,
                on=EXCURSION_ON, off=EXCURSION_OFF, quiet=EXCURSION_QUIET)


def analyse(paths) -> dict:
    """Per (compression rate, N): the phi of the shear jams and the samples that did not
    shear-jam; per rate, the fit across N (:func:`fit_fss`).  ``table``: one row per group.
    ``rates``: the jams per unit strain at constant phi (:func:`constant_phi_rates`), over
    every sample read, compressed or not."""
    every = read_sources(paths)
    recs = [r for r in every if r["compress_rate"] > 0]
    superseded = _superseded(recs)
    groups, dropped, kept = {}, {}, []
    for k, r in enumerate(recs):
        g = (r["compress_rate"], r["N"])
        if k in superseded:
            dropped[g] = dropped.get(g, 0) + 1
        else:
            groups.setdefault(g, []).append(r)
            kept.append(r)
    table = []
    for (rate, N), rs in sorted(groups.items()):
        phis = np.array([r["phi"] for r in rs if r["shear_jam"]], float)
        m, e, n = mean_sem(phis)
        table.append(dict(compress_rate=rate, N=N, n_samples=len(rs), n_shear_jams=int(n),
                          phi_mean=float(m), phi_sd=float(np.std(phis, ddof=1)) if n > 1
                          else math.nan, phi_sem=float(e), phi_values=phis.tolist(),
                          constant_phi=sum(1 for r in rs if r["constant_phi"]),
                          not_shear_jammed=[dict(sample=r["sample"], source=r["source"],
                                                 status=r["status"], phi=r["phi"]) for r in rs
                                            if not r["shear_jam"]],
                          sources=sorted({r["source"] for r in rs}),
                          superseded=dropped.get((rate, N), 0)))
    fits, free = {}, {}
    for rate in sorted({t["compress_rate"] for t in table}):
        rows = [t for t in table if t["compress_rate"] == rate]
        args = ([t["N"] for t in rows], [t["phi_mean"] for t in rows],
                [t["phi_sem"] for t in rows])
        fits[rate], free[rate] = fit_fss(*args), fit_fss_free(*args)
    return dict(table=table, fits=fits, fits_free=free, n_superseded=len(superseded),
                records=kept, rates=constant_phi_rates(every))


def format_rates(rates: list) -> list[str]:
    pc = f"{100 * RATE_CI:g} %"
    out = [f"jams at constant phi:     N     phi  samples  jams  strain  per unit strain ({pc})"
           f"      P(no jam in {FLOW_STRAIN:g} strain)"]
    for t in rates:
        out.append(f"{'':21s}{t['N']:>6d}  {t['phi']:.4f} {t['n_samples']:>8d} {t['n_jams']:>5d} "
                   f"{t['strain']:>7.2f}  {t['rate']:.3f} ({t['rate_ci'][0]:.3f}-"
                   f"{t['rate_ci'][1]:.3f})      {t['p_flow']:.2f} ({t['p_flow_ci'][0]:.2f}-"
                   f"{t['p_flow_ci'][1]:.2f})"
                   + (f"  [{t['uncertified']} jammed without a certificate left out]"
                      if t["uncertified"] else ""))
        e = t.get("excursions")
        if e and e["n_samples"] and e["strain"] > 0:
            out.append(f"{'':27s}stress excursions (sigma >= {e['on']:g} until below "
                       f"{e['off']:g} for {e['quiet']:g} strain) of {e['n_samples']} "
                       f"samples in {e['strain']:.2f} strain, "
                       f"per unit strain reaching "
                       + ", ".join(f"{lv:.0e}: {x:.3g}" for lv, x in
                                   zip(e["levels"], e["per_strain"])))
    return out


def format_table(res: dict) -> list[str]:
    if not res["table"]:
        return format_rates(res.get("rates", []))
    return _format_sj(res) + format_rates(res.get("rates", []))


def _format_sj(res: dict) -> list[str]:
    out = ["compress_rate     N  samples  shear jams  phi_SJ mean +- sem (sd)        not shear-jammed"]
    for t in res["table"]:
        nj = ", ".join(f"{x['sample'] if x['sample'] >= 0 else x['source']}: {x['status']} "
                       f"at {x['phi']:.4f}"
                       + (" (still flowing)" if x["status"] in FLOWING else "")
                       for x in t["not_shear_jammed"]) or "-"
        mean = (f"{t['phi_mean']:.4f} +- {t['phi_sem']:.4f} ({t['phi_sd']:.4f})"
                if t["n_shear_jams"] else f"{'-':<24s}")
        out.append(f"{t['compress_rate']:>13g} {t['N']:>6d} {t['n_samples']:>8d} "
                   f"{t['n_shear_jams']:>11d}  {mean}        {nj}")
    sup = res.get("n_superseded", 0)
    if sup:
        out.append(f"({sup} sample(s) left out: the same start compressed further, to a larger "
                   f"compress_to, in another ensemble)")
    for rate, f in res["fits"].items():
        if math.isnan(f["phi_inf"]):
            out.append(f"rate {rate:g}: {f['n_sizes']} sizes with an error: no fit across N "
                       f"(3 needed)")
        else:
            out.append(f"rate {rate:g}: phi_SJ(N) = phi_inf - a N^-{f['x']:g} over "
                       f"{f['n_sizes']} sizes: phi_inf = {f['phi_inf']:.4f} +- "
                       f"{f['phi_inf_err']:.4f}, a = {f['a']:.3g}, chi2/dof = "
                       f"{f['chi2_dof']:.2f}; phi_J = {PHI_J} is "
                       f"{f['sigmas_below_phi_j']:+.1f} errors above phi_inf")
        g = res.get("fits_free", {}).get(rate)
        if g is not None and not math.isnan(g["phi_inf"]):
            out.append(f"rate {rate:g}, exponent free: x = {g['x']:.3f} "
                       f"({g['x_range'][0]:.3f}-{g['x_range'][1]:.3f}), phi_inf = "
                       f"{g['phi_inf']:.4f} ({g['phi_inf_range'][0]:.4f}-"
                       f"{g['phi_inf_range'][1]:.4f}: chi2 within 1 of its least, "
                       f"{g['chi2']:.2f})")
    return out


def main(argv=None) -> int:
    prog = "python -m parflow.post.suspension_jams"
    ap = argparse.ArgumentParser(prog=prog, description="Where flowing suspensions "
                                 "compressed while sheared shear-jam, across N (phi_SJ(N))")
    ap.add_argument("paths", nargs="+", metavar="PATH",
                    help="ensemble folders, jam tables (JSON), suspension run files (.h5), "
                    "or folders holding them")
    ap.add_argument("--json", metavar="OUT", help="write the result as JSON")
    ap.add_argument("--export", metavar="FILE", help="write every sample record read as one "
                    "jam table (JSON) to FILE")
    args = ap.parse_args(argv)
    name = "suspension_jams"
    if missing_path(args.paths, name):
        return 2
    try:
        res = analyse(args.paths)
    except ValueError as e:
        print(f"{name}: {e}", file=sys.stderr)
        return 2
    if not res["table"] and not res["rates"]:
        print(f"{name}: no suspension sample found that was compressed or ran at constant "
              f"phi (a PATH is an ensemble folder, a jam table, a run file, or a folder "
              f"holding them)", file=sys.stderr)
        return 2
    print_and_save(res, format_table, args.json)
    if args.export:
        print(f"{name}: wrote {export(args.paths, args.export)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
