"""A chain ensemble against the self-consistent mode theory (post.chain_theory; docs/chain.md
"Seed averages").

    python -m parflow.plot.chain_theory FOLDER [FOLDER ...] [--png OUT.png] [--json OUT.json]
    python -m parflow.chain_split N EPS MU SEED     # one chain's <V^2> split (parflow.chain_split)

For each ensemble folder (the Fig. 2 chain, runs/ensemble_chain_*.toml): the sample files'
<V^2>, <dtheta^2> (time series of the forward leg) and l_corr (analysis instants) on a common
log grid of x = gamma_c - gamma (gamma_c = ln(N/Lx0), each sample's own), averaged (mean and
standard error over the samples that cover the grid point); the theory solved (a) for the
ensemble's expected initial spectrum and (b) for each sample's own initial angles (from
the run file's /initial state, checked against the sample's Lx0), (b)
averaged like the samples; and the exponents fitted the way post.chain.chain_fits fits a run
(log-binned least squares over each sample's window) to the data and to both theories, and
the paired difference data - theory of the same seed.
The ensemble summary has <V^2> as a curve but neither <dtheta^2> nor l_corr, so all three
curves are computed here from the sample files.
"""
from __future__ import annotations

import argparse
import glob
import os

import numpy as np

from ..io import RunFile, atomic_json
from ..post import chain_theory as ct
from ..post.ensemble import mean_sem
from ..post.fits import BINS_PER_DECADE, fit_power_law, forward_instants, forward_rows
from ..post.runs import load
from .base import new_figure, save_figure

QUANTITIES = ("V2", "dtheta2", "l_corr")
LABEL = {"V2": r"$\langle V^2\rangle$", "dtheta2": r"$\langle\Delta\theta^2\rangle$",
         "l_corr": r"$l_{corr}$"}


def _interp(xg, x, y):
    """y(x) at xg, log-log, NaN outside the sample's own range."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    ok = (x > 0) & (y > 0) & np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    if x.size < 2:
        return np.full(xg.shape, np.nan)
    o = np.argsort(x)
    x, y = x[o], y[o]
    out = np.exp(np.interp(np.log(xg), np.log(x), np.log(y)))
    return np.where((xg >= x[0]) & (xg <= x[-1]), out, np.nan)


def _mstats(vals):
    """mean, standard error and count of the finite values (post.ensemble.mean_sem)."""
    m, se, n = mean_sem(np.asarray(vals, float))
    return dict(mean=float(m), sem=float(se), n=int(n))


def initial_angles(path: str) -> np.ndarray:
    """The rods' initial angles theta_k, from the run file's /initial state (rod k joins
    nodes k and k + 1: r_k = h0 (s_j + shift - s_i))."""
    with RunFile(path) as rf:
        g = rf.initial()
    b = g["bonds"]
    r = (g["s"][b["j"]] + b["shift"] - g["s"][b["i"]]) @ np.asarray(g["h0"]).T
    return np.arctan2(r[:, 1], r[:, 0])


def sample_data(path: str) -> dict:
    """One sample: its forward leg (x, V2, dtheta2), l_corr at its instants, its window, and
    its initial mode spectrum."""
    run = load(path)
    N, eps, mu = int(run.param("N")), float(run.param("epsilon")), int(run.param("mu", 0))
    gc = float(run.model_attrs["gamma_c"])
    fw = forward_rows(run)
    x = gc - run.ts["gamma"][fw]
    theta = initial_angles(path)
    Lx0 = float(np.cos(theta).sum())
    if abs(Lx0 - float(run.model_attrs["Lx0"])) > 1e-9 * N:
        raise ValueError(f"{path}: the initial angles of /initial do not match Lx0")
    inst = [a for a in forward_instants(run) if gc - a["gamma"] > 0]
    cap = N / 2
    lc = np.array([float(a.get("l_corr", np.nan)) for a in inst])
    return dict(path=path, N=N, eps=eps, mu=mu, gamma_c=gc, x=x, V2=run.ts["V2"][fw],
                dtheta2=run.ts["dtheta2"][fw],
                lx=np.array([gc - a["gamma"] for a in inst]), l_corr=np.where(lc < cap, lc, np.nan),
                spectrum=ct.sample_spectrum(theta), seed=int(run.attrs["sample_seed"]))


def _window(folder):
    """Each sample's forward fit window from the summary (post.chain.chain_fits)."""
    from ..post.ensemble import read_summary     # noqa: E402  (layer 6, only for the windows)
    s = read_summary(os.path.join(folder, "summary.h5"))
    f = s["fits"]
    return (np.asarray(f["forward.attr.window.lo"]["values"], float),
            np.asarray(f["forward.attr.window.hi"]["values"], float), s)


def compare(folder: str, per_decade: int = 12) -> dict:
    """The data and both theories on a common grid, and the exponents (see module doc)."""
    paths = sorted(glob.glob(os.path.join(folder, "sample_*.h5")))
    samples = [sample_data(p) for p in paths]
    if not samples:
        raise ValueError(f"{folder}: no sample files")
    N, eps, mu = samples[0]["N"], samples[0]["eps"], samples[0]["mu"]
    lo_w, hi_w, summary = _window(folder)
    used = list(np.asarray(summary["samples"]["used"]).astype(int))
    xmin = min(float(np.min(s["x"][s["x"] > 0])) for s in samples)
    xmax = max(float(np.max(s["x"])) for s in samples)
    xg = np.geomspace(xmin, xmax, int(np.ceil(per_decade * np.log10(xmax / xmin))) + 1)
    mean_sol = ct.solve(ct.mean_spectrum(N, eps, mu))
    sols = [ct.solve(s["spectrum"]) for s in samples]
    data, theo_s = {}, {}
    for q in QUANTITIES:
        if q == "l_corr":
            rows = [_interp(xg, s["lx"], s["l_corr"]) for s in samples]
        else:
            rows = [_interp(xg, s["x"], s[q]) for s in samples]
        data[q] = mean_sem(rows)
        theo_s[q] = mean_sem([ct.on_grid(sol, xg, q) for sol in sols])
    theo_m = {q: ct.on_grid(mean_sol, xg, q) for q in QUANTITIES}
    # exponents: each sample's data and both theories over that sample's window
    ex = {q: dict(data=[], theory_mean=[], theory_sample=[]) for q in QUANTITIES}
    for k, (s, sol) in enumerate(zip(samples, sols)):
        idx = int(os.path.basename(s["path"])[7:11])
        j = used.index(idx) if idx in used else None
        if j is None:
            continue
        lo, hi = lo_w[j], hi_w[j]
        for q in QUANTITIES:
            xd, yd = (s["lx"], s["l_corr"]) if q == "l_corr" else (s["x"], s[q])
            pd = None if q == "l_corr" else BINS_PER_DECADE
            ex[q]["data"].append(fit_power_law(xd, yd, lo, hi, pd)[0])
            xt = np.geomspace(lo, hi, 200)
            ex[q]["theory_mean"].append(fit_power_law(xt, ct.on_grid(mean_sol, xt, q))[0])
            ex[q]["theory_sample"].append(fit_power_law(xt, ct.on_grid(sol, xt, q))[0])
    for q, d in ex.items():     # paired: data minus the theory for the same seed
        d["data_minus_theory_sample"] = list(np.subtract(d["data"], d["theory_sample"]))
    exps = {q: {k: _mstats(v) for k, v in d.items()} for q, d in ex.items()}
    return dict(folder=folder, N=N, eps=eps, mu=mu, n_samples=len(samples), x=xg, data=data,
                theory_mean=theo_m, theory_sample=theo_s, exponents=exps,
                window=(float(np.nanmedian(lo_w)), float(np.nanmedian(hi_w))),
                asymptotic=ct.asymptotic(mu, eps), summary=summary)


def figure(results: list):
    """One column per ensemble, one row per quantity: the sample mean with a band of one
    standard error, the theory for the expected spectrum (dashed), the mean of the per-sample
    theories (dotted, band), the asymptotic law (thin grey)."""
    fig = new_figure(4.6 * len(results) + 0.4, 3.0 * len(QUANTITIES) + 0.6)
    axes = fig.subplots(len(QUANTITIES), len(results), squeeze=False, sharex="col")
    for j, r in enumerate(results):
        x = r["x"]
        for i, q in enumerate(QUANTITIES):
            ax = axes[i, j]
            m, s, n = r["data"][q]
            ok = n >= max(2, 0.75 * r["n_samples"])
            ax.fill_between(x[ok], np.maximum(m - s, m * 1e-3)[ok], (m + s)[ok], color="C0",
                            alpha=0.3, lw=0)
            ax.loglog(x[ok], m[ok], "-", color="C0", lw=1.6,
                      label=f"parflow, mean of {r['n_samples']} seeds ± s.e.")
            ax.loglog(x, r["theory_mean"][q], "--", color="C3", lw=1.2,
                      label="theory, expected spectrum")
            tm, ts_, tn = r["theory_sample"][q]
            okt = tn >= max(2, 0.75 * r["n_samples"])
            ax.loglog(x[okt], tm[okt], ":", color="k", lw=1.2,
                      label="theory per seed, averaged")
            asy = r["asymptotic"]
            if q in ("V2", "dtheta2"):
                ax.loglog(x, asy[q](x), "-", color="0.6", lw=0.8,
                          label=f"asymptote, exponent {asy['exponents'][q]:+.3g}")
            e = r["exponents"][q]["data"]
            ax.axvspan(*r["window"], color="0.93", zorder=0)
            ax.set_ylabel(LABEL[q])
            ax.set_title(f"N = {r['N']}, ε = {r['eps']:g}, μ = {r['mu']}: fitted "
                         f"{e['mean']:+.3f} ± {e['sem']:.3f}", fontsize=9)
            ax.grid(True, which="major", alpha=0.3)
            if i == 0:
                ax.legend(fontsize=7, loc="best")
        axes[-1, j].set_xlabel(r"$\gamma_c - \gamma$")
    return fig


def _jsonable(r):
    keep = {k: r[k] for k in ("folder", "N", "eps", "mu", "n_samples", "window", "exponents")}
    x = r["x"]
    for at in (1e-5, 1e-4, 1e-3):
        if x[0] <= at <= x[-1]:
            k = int(np.argmin(np.abs(np.log(x / at))))
            keep[f"at_{at:g}"] = {q: dict(x=float(x[k]), data=float(r["data"][q][0][k]),
                                          sem=float(r["data"][q][1][k]),
                                          n=int(r["data"][q][2][k]),
                                          theory_mean=float(r["theory_mean"][q][k]),
                                          theory_sample=float(r["theory_sample"][q][0][k]))
                                  for q in QUANTITIES}
    f = r["summary"]["fits"]
    keep["summary_fits"] = {k: dict(mean=float(v["mean"]), sem=float(v["sem"]),
                                    count=int(v["count"]))
                            for k, v in f.items() if "exponent" in k or k.startswith("gamma")}
    keep["ensemble_fits"] = {k: {a: (float(b) if np.isscalar(b) else str(b)) for a, b in v.items()}
                             for k, v in r["summary"]["ensemble_fits"].items()}
    return keep


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m parflow.plot.chain_theory", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("folders", nargs="*")
    p.add_argument("--png", default=None)
    p.add_argument("--json", default=None)
    a = p.parse_args(argv)
    results = [compare(f) for f in a.folders]
    if a.png:
        fig = figure(results)
        save_figure(fig, a.png, dpi=72)
    out = [_jsonable(r) for r in results]
    if a.json:
        atomic_json(a.json, out, indent=1)
    for r in out:
        print(r["folder"], f"N={r['N']} mu={r['mu']} samples={r['n_samples']}")
        for q, d in r["exponents"].items():
            print("  exponent", q, {k: f"{v['mean']:+.3f}±{v['sem']:.3f} (n={v['n']})"
                                    for k, v in d.items()})


if __name__ == "__main__":
    main()
