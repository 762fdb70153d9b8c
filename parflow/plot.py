"""Figures from a parflow run file (PNG by default).

    python -m parflow.plot FILE [--out DIR] [--format png]

writes every figure that FILE supports into DIR (default: ``<FILE stem>_plots`` next to
FILE), prints the paths written on stdout, and on stderr which figures were skipped and why,
plus the fitted exponents.  Exit status: 0 success, 1 a figure failed, 2 FILE is missing or
not a parflow run file (or DIR cannot be written).

Fits: power laws by least squares in log-log after log-binning (:data:`BINS_PER_DECADE` bins a
decade, so that the crowded points near a divergence do not dominate), over the last
:data:`FIT_DECADES` decades of gamma_c - gamma above :data:`DGAMMA_GUARD` times the typical
|dgamma| near the end of the branch.

Figures (DESIGN §6, paper Fig. 2 for the chain):

* ``chain_forward``     <V^2>, <dtheta^2>, <thetadot^2> against gamma_c - gamma, log-log, for
                        gamma_c = ln(N / Lx0) (model attribute) and for gamma_c fitted where
                        <V^2>^(-(1+mu)/(3+mu)) extrapolates to zero; fitted and theory slopes.
* ``chain_reverse``     reverse branch: <V^2> against gamma_turn - gamma and against
                        gamma~_c - gamma (gamma~_c: where 1/<V^2> extrapolates to zero), log-log,
                        slope -1, with the forward branch against gamma_turn - gamma (the two
                        branches do not coincide); 1/<V^2> near the turn on linear axes.
* ``chain_correlation`` C(n) at the forward analysis instants coloured by <V^2>; C against
                        n / l_corr.
* ``chain_lengths``     l_corr, l_r and <dtheta^2>^(-1/2) against gamma_c - gamma, log-log.
* ``chain_response``    |tau_n| / |tau_0| of the point response, semilog-y.
* ``stress_strain``     sigma and <V^2> against the accumulated strain, legs coloured.
* ``step_diagnostics``  dgamma, err, rejected, sigma_mismatch, length_error, residual, ...
                        against the step number.
* ``omega_min``         omega_min against sigma, log-log, reference slope -1/2.

Python API: :func:`plot_file` (paths written), :func:`make_plots` (paths, skipped figures
and fits), :func:`load_run`, :func:`chain_fits`, :func:`fit_power_law`,
:func:`fit_divergence_point`, :func:`fit_window`, :func:`typical_dgamma`, :func:`log_bin`,
:func:`main`.

Only numpy, h5py and matplotlib (Agg canvas, no pyplot) are used: plotting needs neither MPI
nor PETSc.
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import tomllib
from dataclasses import dataclass, field

import h5py
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.cm import ScalarMappable
from matplotlib.colors import LogNorm, Normalize
from matplotlib.figure import Figure

FORMAT = "parflow-run-1"          # == parflow.io.FORMAT (not imported: keep this module light)
FIT_DECADES = 2.0                 # power-law fits use the last 2 decades of gamma_c - gamma
DGAMMA_GUARD = 10.0               # ... and only points with gamma_c - gamma > 10 typical |dgamma|
DIVERGENCE_DECADES = 2.0          # gamma_c fit: the top 2 decades of <V^2> on the branch
BINS_PER_DECADE = 8               # log-binning before power-law fits (even weight per decade)


class RunFileError(Exception):
    """FILE is missing or is not a parflow run file (reported as one line, exit status 2)."""


class Skip(Exception):
    """A figure whose data are absent: skipped, with the reason."""


# ---------------------------------------------------------------------------------------
# Reading
# ---------------------------------------------------------------------------------------
@dataclass
class Run:
    """The parts of a run file that the figures use, read into memory."""
    path: str
    attrs: dict
    model: str
    model_attrs: dict
    scene: dict
    ts: dict                                        # name -> 1-D array
    analysis: list = field(default_factory=list)    # dicts: attrs + arrays + "direction"

    def param(self, name, default=None):
        """A [model] parameter of the scene (e.g. mu, N)."""
        return self.scene.get("model", {}).get(name, default)


def _text(v):
    return v.decode() if isinstance(v, bytes) else v


def _scalar(v):
    v = _text(v)
    if isinstance(v, np.generic):
        return v.item()
    return v


def load_run(path: str) -> Run:
    """Read a parflow run file.  Raises :class:`RunFileError` with a one-line message."""
    if not os.path.exists(path):
        raise RunFileError(f"{path}: no such file")
    if os.path.isdir(path):
        raise RunFileError(f"{path}: is a directory, not a parflow run file")
    try:
        f = h5py.File(path, "r")
    except OSError:
        raise RunFileError(f"{path}: not a parflow run file (not an HDF5 file)") from None
    with f:
        if _text(f.attrs.get("format")) != FORMAT:
            raise RunFileError(f"{path}: not a parflow run file (format attribute is not "
                               f"{FORMAT!r})")
        attrs = {k: _scalar(v) for k, v in f.attrs.items()}
        try:
            scene = tomllib.loads(str(attrs.get("scene", "")))
        except tomllib.TOMLDecodeError:
            scene = {}
        model = str(attrs.get("model") or scene.get("model", {}).get("name", ""))
        model_attrs = {k: _scalar(v) for k, v in f["model"].attrs.items()} if "model" in f else {}
        ts = {}
        if "timeseries" in f:
            for k, d in f["timeseries"].items():
                if isinstance(d, h5py.Dataset) and d.ndim == 1:
                    ts[k] = d[()]
        n = min((len(v) for v in ts.values()), default=0)
        ts = {k: v[:n] for k, v in ts.items()}
        analysis = []
        if "analysis" in f:
            for key in sorted(f["analysis"]):
                g = f["analysis"][key]
                if not isinstance(g, h5py.Group):
                    continue
                a = {k: _scalar(v) for k, v in g.attrs.items()}
                a.setdefault("step", int(key) if key.isdigit() else -1)
                for k, d in g.items():
                    if isinstance(d, h5py.Dataset):
                        a[k] = d[()]
                analysis.append(a)
    run = Run(path, attrs, model, model_attrs, scene, ts, analysis)
    _tag_analysis(run)
    return run


def _tag_analysis(run: Run) -> None:
    """Give each analysis instant the direction and leg of its timeseries row."""
    ts = run.ts
    if "step" not in ts or not len(ts["step"]):
        return
    steps = ts["step"]
    for a in run.analysis:
        rows = np.nonzero(steps == a["step"])[0]
        if rows.size:
            r = rows[-1]
            a.setdefault("direction", int(ts["direction"][r]) if "direction" in ts else 1)
            a.setdefault("leg", int(ts["leg"][r]) if "leg" in ts else 0)
            a["row"] = int(r)


# ---------------------------------------------------------------------------------------
# Fitting
# ---------------------------------------------------------------------------------------
def log_bin(x, y, per_decade: int = BINS_PER_DECADE):
    """Geometric means of x and y in logarithmic bins of x (positive finite points only).
    Gives each decade of x the same weight in a least-squares fit, however the points are
    spaced (adaptive steps crowd the points near a divergence)."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    ok = np.isfinite(x) & np.isfinite(y) & (x > 0) & (y > 0)
    lx, ly = np.log10(x[ok]), np.log10(y[ok])
    if lx.size == 0:
        return np.array([]), np.array([])
    k = np.floor(lx * per_decade).astype(np.int64)
    keys, inv = np.unique(k, return_inverse=True)
    cnt = np.bincount(inv)
    bx = np.bincount(inv, lx) / cnt
    by = np.bincount(inv, ly) / cnt
    return 10.0 ** bx, 10.0 ** by


def fit_power_law(x, y, xmin: float | None = None, xmax: float | None = None,
                  per_decade: int | None = None) -> tuple[float, float]:
    """Least-squares fit of y = prefactor * x**exponent in log-log, over the positive finite
    points with xmin <= x <= xmax.  With ``per_decade`` the points are first log-binned
    (:func:`log_bin`).  Returns (exponent, prefactor); (nan, nan) with fewer than 3 points
    or less than 0.1 decade of x."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    ok = np.isfinite(x) & np.isfinite(y) & (x > 0) & (y > 0)
    if xmin is not None:
        ok &= x >= xmin
    if xmax is not None:
        ok &= x <= xmax
    x, y = x[ok], y[ok]
    if per_decade:
        x, y = log_bin(x, y, per_decade)
    if x.size < 3 or np.log10(x.max() / x.min()) < 0.1:
        return float("nan"), float("nan")
    slope, icept = np.polyfit(np.log(x), np.log(y), 1)
    return float(slope), float(np.exp(icept))


def fit_divergence_point(gamma, y, exponent: float, decades: float = DIVERGENCE_DECADES,
                         skip: float = 0.0) -> float:
    """Where y ~ |gamma_c - gamma|**exponent (exponent < 0) diverges: y**(1/exponent) is then
    linear in gamma and vanishes at gamma_c.  Fitted over the points whose y lies between
    10**-(skip + decades) and 10**-skip times the largest y.  Returns nan if it cannot be
    fitted."""
    gamma, y = np.asarray(gamma, float), np.asarray(y, float)
    ok = np.isfinite(gamma) & np.isfinite(y) & (y > 0)
    if ok.sum() < 3 or not exponent < 0:
        return float("nan")
    g, y = gamma[ok], y[ok]
    top = y.max()
    sel = (y >= top * 10.0 ** (-(skip + decades))) & (y <= top * 10.0 ** (-skip))
    if sel.sum() < 3 or np.ptp(g[sel]) == 0:
        return float("nan")
    a, b = np.polyfit(g[sel], y[sel] ** (1.0 / exponent), 1)
    return float(-b / a) if a != 0 else float("nan")


def fit_window(x, dgamma_typical: float = 0.0, decades: float = FIT_DECADES):
    """(xmin, xmax): the last ``decades`` decades of x > 0 above DGAMMA_GUARD * dgamma
    (fewer if the data span fewer)."""
    x = np.asarray(x, float)
    ok = np.isfinite(x) & (x > 0) & (x >= DGAMMA_GUARD * dgamma_typical)
    if not ok.any():
        return float("nan"), float("nan")
    lo = float(x[ok].min())
    return lo, min(lo * 10.0 ** decades, float(x[ok].max()))


# ---------------------------------------------------------------------------------------
# Branches and the chain's numbers
# ---------------------------------------------------------------------------------------
def segments(direction) -> list[tuple[int, int, int]]:
    """Contiguous runs of equal direction: (start, stop, direction), rows [start, stop)."""
    d = np.asarray(direction)
    if d.size == 0:
        return []
    cut = np.nonzero(np.diff(d) != 0)[0] + 1
    starts = np.r_[0, cut]
    stops = np.r_[cut, d.size]
    return [(int(a), int(b), int(d[a])) for a, b in zip(starts, stops)]


def forward_rows(run: Run) -> slice | None:
    """The first forward branch (first contiguous rows with direction +1)."""
    for a, b, d in segments(run.ts.get("direction", np.ones(len(run.ts.get("step", [])), int))):
        if d > 0:
            return slice(a, b)
    return None


def reverse_rows(run: Run) -> tuple[slice, float] | None:
    """The first reverse branch (direction -1) and the turning strain gamma_turn (the last
    gamma before it; its own first gamma if the run starts in reverse)."""
    if "direction" not in run.ts:
        return None
    for a, b, d in segments(run.ts["direction"]):
        if d < 0:
            g = run.ts["gamma"]
            return slice(a, b), float(g[a - 1] if a > 0 else g[a])
    return None


def typical_dgamma(dg, tail: float = 0.1) -> float:
    """Median |dgamma| over the last ``tail`` fraction (at least 5) of the steps of a branch:
    the step size where the branch approaches its divergence."""
    dg = np.abs(np.asarray(dg, float))
    dg = dg[np.isfinite(dg) & (dg > 0)]
    if not dg.size:
        return 0.0
    k = max(5, int(math.ceil(tail * dg.size)))
    return float(np.median(dg[-k:]))


def chain_theory(mu: float) -> dict:
    """Exponents of DESIGN §6 (x = gamma_c - gamma on the forward branch)."""
    p = (3.0 + mu) / (1.0 + mu)
    return dict(V2=-p, dtheta2=p, thetadot2=-1.0, l_corr=-1.0 / (1.0 + mu), l_r=-p / 2,
                reverse_V2=-1.0)


def chain_fits(run: Run) -> dict:
    """The chain's fitted numbers: gamma_c (attribute and fitted), forward exponents for each
    gamma_c, reverse exponent, exponents of l_corr, l_r and <dtheta^2>^(-1/2).  Keys absent
    when their data are."""
    mu = float(run.param("mu", 0) or 0)
    th = chain_theory(mu)
    out: dict = dict(mu=mu, theory=th)
    fw = forward_rows(run)
    if fw is None or "V2" not in run.ts or "gamma" not in run.ts:
        return out
    ts = run.ts
    g, V2 = ts["gamma"][fw], ts["V2"][fw]
    dg = typical_dgamma(ts["dgamma"][fw]) if "dgamma" in ts else 0.0
    out["dgamma_typical"] = dg
    out["gamma_end"] = float(g[-1])
    gcs = {}
    if np.isfinite(run.model_attrs.get("gamma_c", np.nan)):
        gcs["attr"] = float(run.model_attrs["gamma_c"])
    gfit = fit_divergence_point(g, V2, th["V2"])
    if np.isfinite(gfit):
        gcs["fit"] = gfit
    out["gamma_c"] = gcs
    out["forward"] = {}
    for which, gc in gcs.items():
        x = gc - g
        lo, hi = fit_window(x, dg)
        res = dict(window=(lo, hi))
        for q in ("V2", "dtheta2", "thetadot2"):
            if q in ts:
                res[q] = fit_power_law(x, ts[q][fw], lo, hi, BINS_PER_DECADE)
        out["forward"][which] = res
    gc = primary_gamma_c(gcs)
    if gc is not None:
        inst = [a for a in forward_instants(run) if gc - a["gamma"] > 0]
        if inst:
            x = np.array([gc - a["gamma"] for a in inst])
            lo, hi = fit_window(x, dg)
            cap = length_cap(run)
            lengths = {}
            for q in ("l_corr", "l_r", "dtheta2^-1/2"):
                if q == "dtheta2^-1/2":
                    y = np.array([float(a.get("dtheta2", np.nan)) for a in inst]) ** -0.5
                else:
                    y = np.array([float(a.get(q, np.nan)) for a in inst])
                    y = np.where(y < cap, y, np.nan)      # measured beyond N/2: finite size
                lengths[q] = fit_power_law(x, y, lo, hi)
            out["lengths"] = lengths
            out["lengths_window"] = (lo, hi)
    rv = reverse_rows(run)
    if rv is not None:
        rows, gturn = rv
        gr, Vr = ts["gamma"][rows], ts["V2"][rows]
        out["gamma_turn"] = gturn
        rev = dict()
        # against gamma_turn - gamma (> 0: gamma decreases), past the plateau that follows the turn
        xr = gturn - gr
        lo, hi = reverse_window(xr, Vr)
        rev["turn"] = dict(window=(lo, hi), V2=fit_power_law(xr, Vr, lo, hi, BINS_PER_DECADE))
        # gamma~_c: where 1/V2, linear in gamma once past the plateau (one to two decades below
        # the value at the turn), extrapolates to zero
        gct = fit_divergence_point(gr, Vr, chain_theory(mu)["reverse_V2"], decades=1.0, skip=1.0)
        rev["gamma_c_tilde"] = gct
        if np.isfinite(gct):
            xt = gct - gr
            lo, hi = reverse_window(xt, Vr)
            rev["tilde"] = dict(window=(lo, hi), V2=fit_power_law(xt, Vr, lo, hi, BINS_PER_DECADE))
        out["reverse"] = rev
    return out


def length_cap(run: Run) -> float:
    """N/2: longer lengths are finite-size artefacts and stay out of the fits."""
    N = run.param("N")
    if N is None:
        Cs = [len(a["C_n"]) for a in run.analysis if "C_n" in a]
        N = 2 * (Cs[0] - 1) if Cs else None
    return float(N) / 2 if N else float("inf")


def primary_gamma_c(gcs: dict) -> float | None:
    """gamma_c used by the figures with a single x axis: the exact ln(N a0 / Lx(0)) (the
    chain is straight, hence jammed, exactly there), else the fitted one.  The fitted value
    is a diagnostic of how far the run is from the asymptotic regime, not a better gamma_c."""
    return gcs.get("attr", gcs.get("fit"))


def reverse_window(x, V2):
    """Fit window on the reverse branch: from where <V^2> has dropped by a factor 10 below its
    value at the turn (past the initial plateau) to the end of the branch."""
    x, V2 = np.asarray(x, float), np.asarray(V2, float)
    ok = np.isfinite(V2) & (x > 0)
    if ok.sum() < 3:
        return float("nan"), float("nan")
    v_turn = V2[np.isfinite(V2)][0]
    past = ok & (V2 <= v_turn / 10.0)
    lo = float(x[past].min()) if past.any() else float(x[ok].min())
    return lo, float(x[ok].max())


def forward_instants(run: Run) -> list[dict]:
    fw = forward_rows(run)
    if fw is None:
        return []
    return [a for a in run.analysis if "row" in a and fw.start <= a["row"] < fw.stop
            and np.isfinite(a.get("gamma", np.nan))]


# ---------------------------------------------------------------------------------------
# Figure helpers
# ---------------------------------------------------------------------------------------
def _figure(w, h) -> Figure:
    fig = Figure(figsize=(w, h), dpi=110, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _fmt_exp(p: float) -> str:
    return "n/a" if not np.isfinite(p) else f"{p:+.3f}"


def _reference(ax, x0, y0, slope, span, label, **kw):
    """A dashed power law y = y0 (x/x0)^slope over [x0/span, x0*span]."""
    if not (np.isfinite(x0) and np.isfinite(y0) and x0 > 0 and y0 > 0):
        return
    xs = np.geomspace(x0 / span, x0 * span, 20)
    kw.setdefault("color", "k")
    ax.plot(xs, y0 * (xs / x0) ** slope, "--", lw=1.2, label=label, **kw)


def _fit_line(ax, fit, lo, hi, label, color):
    p, A = fit
    if np.isfinite(p) and np.isfinite(lo) and np.isfinite(hi):
        xs = np.geomspace(lo, hi, 20)
        ax.plot(xs, A * xs ** p, "-", color=color, lw=2.5, alpha=0.45, label=label)


def _anchor(fit, lo, hi):
    """A point on the fitted line in the middle of the window (to hang reference slopes)."""
    p, A = fit
    if not (np.isfinite(p) and np.isfinite(lo) and np.isfinite(hi)):
        return float("nan"), float("nan")
    xm = math.sqrt(lo * hi)
    return xm, A * xm ** p


def _positive(x, y):
    x, y = np.asarray(x, float), np.asarray(y, float)
    ok = np.isfinite(x) & np.isfinite(y) & (x > 0) & (y > 0)
    return x[ok], y[ok]


_QLABEL = {"V2": r"$\langle V^2\rangle$", "dtheta2": r"$\langle\Delta\theta^2\rangle$",
           "thetadot2": r"$\langle\dot\theta^2\rangle$"}


def _title(run: Run, what: str) -> str:
    name = os.path.basename(run.path)
    bits = [f"{run.model}"]
    if run.param("N") is not None:
        bits.append(f"N={run.param('N')}")
    if run.model == "chain":
        bits.append(f"μ={run.param('mu', 0)}")
    return f"{what} — {name} ({', '.join(bits)})"


# ---------------------------------------------------------------------------------------
# Chain figures
# ---------------------------------------------------------------------------------------
def fig_chain_forward(run: Run, fits: dict) -> Figure:
    """(a) <V^2>, <dtheta^2>, <thetadot^2> against gamma_c - gamma, one column per gamma_c."""
    fw = forward_rows(run)
    if fw is None or "V2" not in run.ts:
        raise Skip("no forward branch (direction == +1) with V2")
    gcs = fits.get("gamma_c", {})
    if not gcs:
        raise Skip("neither the gamma_c attribute nor a fitted gamma_c is available")
    qs = [q for q in ("V2", "dtheta2", "thetadot2") if q in run.ts]
    th = fits["theory"]
    cols = [c for c in ("attr", "fit") if c in gcs]
    fig = _figure(5.6 * len(cols) + 0.4, 3.3 * len(qs) + 0.6)
    axes = fig.subplots(len(qs), len(cols), squeeze=False, sharex="col")
    g = run.ts["gamma"][fw]
    colors = {"V2": "C0", "dtheta2": "C1", "thetadot2": "C2"}
    for j, which in enumerate(cols):
        gc = gcs[which]
        res = fits["forward"][which]
        lo, hi = res["window"]
        x = gc - g
        for i, q in enumerate(qs):
            ax = axes[i, j]
            xx, yy = _positive(x, run.ts[q][fw])
            ax.loglog(xx, yy, ".", ms=2.5, color=colors[q], label="data")
            fit = res.get(q, (np.nan, np.nan))
            _fit_line(ax, fit, lo, hi, f"fit: slope {_fmt_exp(fit[0])}", colors[q])
            x0, y0 = _anchor(fit, lo, hi)
            if not np.isfinite(x0) and xx.size:            # no fit: hang it on the data
                x0, y0 = xx[len(xx) // 2], yy[len(yy) // 2]
            span = math.sqrt(hi / lo) if np.isfinite(lo) and hi > lo else 10.0
            _reference(ax, x0, y0 * 2.5, th[q], max(span, 3.0), f"theory: slope {th[q]:+.3g}")
            if np.isfinite(lo):
                ax.axvspan(lo, hi, color="0.9", zorder=0)
            ax.set_ylabel(_QLABEL[q])
            ax.grid(True, which="major", alpha=0.3)
            ax.legend(fontsize=8, loc="best")
        axes[-1, j].set_xlabel(r"$\gamma_c - \gamma$" + ("  (γ_c = ln N/Lx0)" if which == "attr"
                                                           else "  (γ_c fitted)"))
        head = (r"$\gamma_c = \ln(N/L_{x0})$ = " if which == "attr" else
                r"$\gamma_c$ fitted ($\langle V^2\rangle^{-(1+\mu)/(3+\mu)}\to 0$) = ")
        axes[0, j].set_title(head + f"{gc:.6g}", fontsize=10)
    gline = "; ".join(f"γ_c({'attr' if k == 'attr' else 'fit'}) = {v:.6g}" for k, v in gcs.items())
    fig.suptitle(_title(run, "forward branch") + f"\n{gline}; run ends at γ = "
                 f"{fits['gamma_end']:.6g}; grey: fit window", fontsize=10)
    return fig


def fig_chain_reverse(run: Run, fits: dict) -> Figure:
    """(b) the reverse branch against gamma_turn - gamma and gamma~_c - gamma, with the
    forward branch against gamma_turn - gamma; 1/<V^2> on linear axes near the turn."""
    rv = reverse_rows(run)
    if rv is None or "V2" not in run.ts:
        raise Skip("no reverse branch (direction == -1)")
    rows, gturn = rv
    if rows.stop - rows.start < 3:
        raise Skip("reverse branch has fewer than 3 rows")
    ts = run.ts
    gr, Vr = ts["gamma"][rows], ts["V2"][rows]
    res = fits["reverse"]
    gct = res.get("gamma_c_tilde", np.nan)
    fig = _figure(13, 5.0)
    ax, ax2 = fig.subplots(1, 2)
    fw = forward_rows(run)
    if fw is not None:
        xf, yf = _positive(gturn - ts["gamma"][fw], ts["V2"][fw])
        ax.loglog(xf, yf, ".", ms=2, color="C0", alpha=0.7,
                  label=r"forward, against $\gamma_{turn}-\gamma$")
    xr, yr = _positive(gturn - gr, Vr)
    ax.loglog(xr, yr, ".", ms=3, color="C3", label=r"reverse, against $\gamma_{turn}-\gamma$")
    fit_t = res["turn"]["V2"]
    _fit_line(ax, fit_t, *res["turn"]["window"], f"fit: slope {_fmt_exp(fit_t[0])}", "C3")
    fit = fit_t
    lo, hi = res["turn"]["window"]
    if "tilde" in res:
        xt, yt = _positive(gct - gr, Vr)
        ax.loglog(xt, yt, "+", ms=3, color="C4", alpha=0.8,
                  label=r"reverse, against $\tilde\gamma_c-\gamma$")
        fit = res["tilde"]["V2"]
        lo, hi = res["tilde"]["window"]
        _fit_line(ax, fit, lo, hi, f"fit: slope {_fmt_exp(fit[0])}", "C4")
    x0, y0 = _anchor(fit, lo, hi)
    span = math.sqrt(hi / lo) if np.isfinite(lo) and hi > lo else 10.0
    _reference(ax, x0, y0 * 4, -1.0, span, "theory: slope -1")
    ax.set_xlabel(r"$\gamma_{turn} - \gamma$  or  $\tilde\gamma_c - \gamma$")
    ax.set_ylabel(_QLABEL["V2"])
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8, loc="lower left")
    ax.set_title("log-log; fits from where ⟨V²⟩ has dropped 10× below its turning value",
                 fontsize=9)
    # 1/V2 on linear axes near the turn: straight if <V^2> ~ 1/(gamma~_c - gamma)
    near = Vr >= Vr[0] / 300
    ax2.plot(gturn - gr[near], 1 / Vr[near], ".", ms=4, color="C3", label="reverse")
    if np.isfinite(gct):
        sel = (Vr <= Vr[0] / 10) & (Vr >= Vr[0] / 100)
        if sel.any():
            a = np.polyfit(gr[sel], 1 / Vr[sel], 1)[0]
            xs = np.linspace(gturn - gct, np.max(gturn - gr[near]), 50)
            ax2.plot(xs, a * (gturn - xs - gct), "k-", lw=1, alpha=0.6,
                     label="linear fit (⟨V²⟩ 10–100× below the turn)")
        ax2.axvline(gturn - gct, color="k", ls=":", lw=1,
                    label=r"$\gamma_{turn}-\tilde\gamma_c$" + f" = {gturn - gct:.3g}")
    ax2.set_xlabel(r"$\gamma_{turn} - \gamma$")
    ax2.set_ylabel(r"$1/\langle V^2\rangle$")
    ax2.ticklabel_format(style="sci", scilimits=(-3, 3))
    ax2.grid(True, alpha=0.3)
    ax2.legend(fontsize=8, loc="upper left")
    ax2.set_title(r"$1/\langle V^2\rangle$ near the turn (linear axes)", fontsize=10)
    line = (f"γ_turn = {gturn:.9g}; reverse exponent {_fmt_exp(fit_t[0])} against γ_turn − γ")
    if "tilde" in res:
        line += f", {_fmt_exp(res['tilde']['V2'][0])} against γ̃_c − γ (γ̃_c − γ_turn = " \
                f"{gct - gturn:.3g})"
    fig.suptitle(_title(run, "reverse branch") + f"\n{line}; theory −1", fontsize=10)
    return fig


def _instant_colors(inst, key="V2", cmap="viridis"):
    v = np.array([float(a.get(key, np.nan)) for a in inst])
    ok = np.isfinite(v) & (v > 0)
    if ok.sum() >= 2 and v[ok].max() > v[ok].min():
        norm = LogNorm(v[ok].min(), v[ok].max())
    else:
        norm = Normalize(0, 1)
    sm = ScalarMappable(norm=norm, cmap=cmap)
    cols = [sm.to_rgba(x) if np.isfinite(x) and x > 0 else (0.5, 0.5, 0.5, 1) for x in v]
    return cols, sm


def fig_chain_correlation(run: Run, fits: dict) -> Figure:
    """(c) C(n) at forward instants, coloured by <V^2>, and C against n / l_corr."""
    inst = [a for a in forward_instants(run) if "C_n" in a]
    if not inst:
        raise Skip("no forward analysis groups with C_n")
    cols, sm = _instant_colors(inst)
    fig = _figure(12.5, 4.6)
    ax, ax2 = fig.subplots(1, 2)
    for a, c in zip(inst, cols):
        C = np.asarray(a["C_n"], float)
        n = np.arange(C.size)
        ax.plot(n[1:], C[1:], "-", color=c, lw=1.2)
        lc = float(a.get("l_corr", np.nan))
        if np.isfinite(lc) and lc > 0:
            ax2.plot(n[1:] / lc, C[1:], "-", color=c, lw=1.2)
    for a_ in (ax, ax2):
        a_.set_xscale("log")
        a_.axhline(0, color="k", lw=0.6)
        a_.axhline(np.exp(-1), color="0.5", lw=0.6, ls=":")
        a_.grid(True, alpha=0.3)
        a_.set_ylabel("C(n)")
    u = np.geomspace(1e-2, 3, 100)
    ax2.plot(u, np.exp(-u ** 2), "k--", lw=1, label=r"guide: $e^{-(n/l_{corr})^2}$")
    ax2.legend(fontsize=8, loc="lower left")
    ax.set_xlabel("n (rods along the chain)")
    ax2.set_xlabel(r"$n / l_{corr}$")
    ax.set_title("velocity correlation, forward instants (dotted: 1/e)", fontsize=10)
    ax2.set_title(r"collapse: $l_{corr}$ = first n with C(n) < 1/e", fontsize=10)
    fig.colorbar(sm, ax=[ax, ax2], label=_QLABEL["V2"])
    fig.suptitle(_title(run, "velocity correlation C(n)"), fontsize=10)
    return fig


def fig_chain_lengths(run: Run, fits: dict) -> Figure:
    """(d) l_corr, l_r and <dtheta^2>^(-1/2) against gamma_c - gamma (forward), log-log."""
    gc = primary_gamma_c(fits.get("gamma_c", {}))
    inst = [a for a in forward_instants(run) if "l_corr" in a or "l_r" in a]
    if not inst:
        raise Skip("no forward analysis groups with l_corr / l_r")
    if gc is None:
        raise Skip("no gamma_c (attribute or fit)")
    th = fits["theory"]
    L = fits.get("lengths", {})
    cap = length_cap(run)
    wlo, whi = fits.get("lengths_window", (0.0, np.inf))
    x = np.array([gc - a["gamma"] for a in inst])
    fig = _figure(7.5, 5.6)
    ax = fig.subplots()
    spec = [("l_corr", r"$l_{corr}$", "C0", "o", th["l_corr"]),
            ("l_r", r"$l_r$ (exponential fit of $\tau_n$)", "C3", "s", th["l_r"])]
    for key, lab, c, mk, p_th in spec:
        y = np.array([float(a.get(key, np.nan)) for a in inst])
        xx, yy = _positive(x, y)
        if not xx.size:
            continue
        fit = L.get(key, (np.nan, np.nan))
        ax.loglog(xx, yy, mk, color=c, ms=6, label=f"{lab}: fit slope {_fmt_exp(fit[0])}")
        inside = (yy < cap) & (xx >= wlo) & (xx <= whi)
        if inside.any():
            _fit_line(ax, fit, xx[inside].min(), xx[inside].max(), None, c)
        i = len(xx) // 2
        _reference(ax, xx[i], yy[i] * 1.8, p_th, 10, f"theory slope {p_th:+.3g}", color=c)
    fw = forward_rows(run)
    if "dtheta2" in run.ts and fw is not None:
        xx, yy = _positive(gc - run.ts["gamma"][fw], run.ts["dtheta2"][fw] ** -0.5)
        ax.loglog(xx, yy, "-", color="C1", lw=1, alpha=0.7,
                  label=r"$\langle\Delta\theta^2\rangle^{-1/2}$ (timeseries)")
    y = np.array([float(a.get("dtheta2", np.nan)) for a in inst]) ** -0.5
    xx, yy = _positive(x, y)
    if xx.size:
        fit = L.get("dtheta2^-1/2", (np.nan, np.nan))
        ax.loglog(xx, yy, "^", color="C1", ms=6, mfc="none",
                  label=r"$\langle\Delta\theta^2\rangle^{-1/2}$ at the instants: fit slope "
                        + _fmt_exp(fit[0]))
    if np.isfinite(cap):
        ax.axhline(cap, color="0.4", ls=":", lw=1, label="N/2 (finite size: above it, not fitted)")
    ax.set_xlabel(r"$\gamma_c - \gamma$" + f"  (γ_c = {gc:.6g}, "
                  + ("fitted" if "fit" in fits.get("gamma_c", {}) else "ln N/Lx0") + ")")
    ax.set_ylabel("length (rods)")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.suptitle(_title(run, "length scales, forward branch"), fontsize=10)
    return fig


def fig_chain_response(run: Run, fits: dict) -> Figure:
    """(e) |tau_n| / |tau_0| of the point response, semilog-y, forward (and reverse)."""
    inst = [a for a in run.analysis if "tau_response" in a]
    if not inst:
        raise Skip("no analysis groups with tau_response")
    groups = [("forward instants", [a for a in inst if a.get("direction", 1) > 0], "viridis"),
              ("reverse instants", [a for a in inst if a.get("direction", 1) < 0], "plasma")]
    groups = [gr for gr in groups if gr[1]]
    fig = _figure(6.2 * len(groups) + 0.5, 4.8)
    axes = fig.subplots(1, len(groups), squeeze=False)[0]
    for ax, (what, sel, cmap) in zip(axes, groups):
        cols, sm = _instant_colors(sel, cmap=cmap)
        for a, c in zip(sel, cols):
            t = np.abs(np.asarray(a["tau_response"], float))
            if t.size == 0 or not t[0] > 0:
                continue
            p = t / t[0]
            n = np.arange(p.size)
            ok = p > 0
            ax.semilogy(n[ok], p[ok], "-", color=c, lw=1.2)
        ax.set_ylim(max(ax.get_ylim()[0], 1e-16), 2.0)
        ax.set_xlabel("n (distance from the elongated rod)")
        ax.set_ylabel(r"$|\tau_n| / |\tau_0|$")
        ax.grid(True, alpha=0.3)
        ax.set_title(what, fontsize=10)
        fig.colorbar(sm, ax=ax, label=_QLABEL["V2"])
    fig.suptitle(_title(run, "point response profiles"), fontsize=10)
    return fig


# ---------------------------------------------------------------------------------------
# Generic figures
# ---------------------------------------------------------------------------------------
def _leg_label(run: Run, k: int) -> str:
    ts = run.ts
    d = ts["direction"][ts["leg"] == k] if "direction" in ts else []
    word = "" if len(d) == 0 else (" forward" if d[-1] > 0 else " reverse")
    return f"leg {k}{word}"


def _by_leg(run: Run):
    """(leg index, row mask) for each leg present (one group if there is no leg column)."""
    ts = run.ts
    n = len(ts.get("step", next(iter(ts.values()), [])))
    if "leg" not in ts:
        return [(0, np.ones(n, bool))]
    return [(int(k), ts["leg"] == k) for k in np.unique(ts["leg"])]


def fig_stress_strain(run: Run, fits: dict) -> Figure:
    """(g1) sigma and <V^2> against the accumulated strain, legs coloured, log-y."""
    ts = run.ts
    qs = [q for q in ("sigma", "V2") if q in ts and np.any(ts[q] > 0)]
    if "strain" not in ts or not qs:
        raise Skip("no strain with sigma or V2 in /timeseries")
    fig = _figure(8.5, 2.9 * len(qs) + 0.6)
    axes = fig.subplots(len(qs), 1, squeeze=False, sharex=True)[:, 0]
    labels = {"sigma": r"$\sigma$", "V2": _QLABEL["V2"]}
    for ax, q in zip(axes, qs):
        for k, m in _by_leg(run):
            x, y = ts["strain"][m], ts[q][m]
            ok = np.isfinite(y) & (y > 0)
            ax.semilogy(x[ok], y[ok], ".-", ms=2, lw=0.8, color=f"C{k % 10}",
                        label=_leg_label(run, k) if "leg" in ts else None)
        ax.set_ylabel(labels[q])
        ax.grid(True, alpha=0.3)
        if "leg" in ts:
            ax.legend(fontsize=8)
    axes[-1].set_xlabel(r"accumulated strain $\sum|d\gamma|$")
    fig.suptitle(_title(run, "stress against strain") + f"\nstatus: {run.attrs.get('status', '?')}",
                 fontsize=10)
    return fig


_DIAG = [("dgamma", r"$|d\gamma|$", True), ("err", "err (step error estimate)", True),
         ("rejected", "rejected steps", False), ("sigma_mismatch", "σ mismatch", True),
         ("length_error", "length error", True), ("residual", "residual", True),
         ("backward_error", "backward error", True), ("proj_iter", "projection iterations", False),
         ("refinements", "refinements", False)]


def fig_step_diagnostics(run: Run, fits: dict) -> Figure:
    """(g2) step diagnostics against the step number (log-y where positive)."""
    ts = run.ts
    present = [d for d in _DIAG if d[0] in ts]
    if "step" not in ts or not present or len(ts["step"]) < 2:
        raise Skip("no step diagnostics in /timeseries")
    ncol = 3
    nrow = math.ceil(len(present) / ncol)
    fig = _figure(13, 2.8 * nrow + 0.6)
    axes = fig.subplots(nrow, ncol, squeeze=False, sharex=True).ravel()
    for ax, (q, lab, logy) in zip(axes, present):
        y = np.asarray(ts[q], float)
        if q == "dgamma":
            y = np.abs(y)
        pos = np.isfinite(y) & (y > 0)
        use_log = logy and pos.any()
        for k, m in _by_leg(run):
            mm = m & (pos if use_log else np.isfinite(y))
            ax.plot(ts["step"][mm], y[mm], ".", ms=2, color=f"C{k % 10}",
                    label=_leg_label(run, k) if "leg" in ts else None)
        if use_log:
            ax.set_yscale("log")
        ax.set_title(lab + ("" if use_log or not logy else " (no positive values)"), fontsize=9)
        ax.grid(True, alpha=0.3)
    for ax in axes[len(present):]:
        ax.set_visible(False)
    for ax in axes[max(0, len(present) - ncol):len(present)]:
        ax.set_xlabel("step")
        ax.xaxis.set_tick_params(labelbottom=True)
    if "leg" in ts:
        axes[0].legend(fontsize=7, markerscale=3)
    fig.suptitle(_title(run, "step diagnostics"), fontsize=10)
    return fig


def fig_omega_min(run: Run, fits: dict) -> Figure:
    """(g3) omega_min against sigma (log-log), reference slope -1/2."""
    ts = run.ts
    if "omega_min" not in ts or "sigma" not in ts:
        raise Skip("no omega_min in /timeseries")
    w, s = np.asarray(ts["omega_min"], float), np.asarray(ts["sigma"], float)
    ok = np.isfinite(w) & np.isfinite(s) & (w > 0) & (s > 0)
    if not ok.any():
        raise Skip("omega_min was not computed (all NaN)")
    fig = _figure(7, 5.2)
    ax = fig.subplots()
    d = ts["direction"] if "direction" in ts else np.ones(len(w), int)
    for sgn, lab, c in ((1, "forward", "C0"), (-1, "reverse", "C3")):
        m = ok & (d == sgn)
        if m.any():
            fit = fit_power_law(s[m], w[m])
            ax.loglog(s[m], w[m], "o", ms=4, color=c,
                      label=f"{lab}: fit slope {_fmt_exp(fit[0])}" if np.isfinite(fit[0]) else lab)
    sx, wx = s[ok], w[ok]
    x0 = math.sqrt(sx.min() * sx.max())
    _reference(ax, x0, float(np.exp(np.mean(np.log(wx)))) * 1.5, -0.5,
               max(3.0, math.sqrt(sx.max() / sx.min())), "reference slope -1/2")
    ax.set_xlabel(r"$\sigma$")
    ax.set_ylabel(r"$\omega_{min}$")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.suptitle(_title(run, "lowest frequency against stress"), fontsize=10)
    return fig


# name, models (None: any), function
FIGURES = [
    ("chain_forward", {"chain"}, fig_chain_forward),
    ("chain_reverse", {"chain"}, fig_chain_reverse),
    ("chain_correlation", {"chain"}, fig_chain_correlation),
    ("chain_lengths", {"chain"}, fig_chain_lengths),
    ("chain_response", {"chain"}, fig_chain_response),
    ("stress_strain", None, fig_stress_strain),
    ("step_diagnostics", None, fig_step_diagnostics),
    ("omega_min", None, fig_omega_min),
]


# ---------------------------------------------------------------------------------------
# Driver
# ---------------------------------------------------------------------------------------
@dataclass
class PlotResult:
    written: list            # paths
    skipped: list            # (figure name, reason)
    failed: list             # (figure name, "ExceptionType: message")
    fits: dict               # chain_fits() for a chain, else {}


def default_outdir(path: str) -> str:
    stem = os.path.splitext(os.path.basename(path))[0]
    return os.path.join(os.path.dirname(os.path.abspath(path)), stem + "_plots")


def make_plots(path: str, outdir: str | None = None, fmt: str = "png",
               only: list[str] | None = None) -> PlotResult:
    """Draw every figure the run file supports.  Raises :class:`RunFileError`."""
    run = load_run(path)
    outdir = outdir or default_outdir(path)
    fits = chain_fits(run) if run.model == "chain" else {}
    res = PlotResult([], [], [], fits)
    if not run.ts or not len(next(iter(run.ts.values()))):
        for name, _, _ in FIGURES:
            if not only or name in only:
                res.skipped.append((name, "no rows in /timeseries"))
        return res
    for name, models, func in FIGURES:
        if only and name not in only:
            continue
        if models is not None and run.model not in models:
            res.skipped.append((name, f"model is {run.model!r}, not {'/'.join(sorted(models))}"))
            continue
        try:
            fig = func(run, fits)
        except Skip as exc:
            res.skipped.append((name, str(exc)))
            continue
        except Exception as exc:  # a bad figure must not cost the others
            res.failed.append((name, f"{type(exc).__name__}: {exc}"))
            continue
        os.makedirs(outdir, exist_ok=True)
        out = os.path.join(outdir, f"{name}.{fmt}")
        fig.savefig(out, format=fmt)
        res.written.append(out)
    return res


def plot_file(path: str, outdir: str | None = None, fmt: str = "png",
              only: list[str] | None = None) -> list[str]:
    """Draw every figure the run file supports (or those named in ``only``); returns the
    paths written.  Raises :class:`RunFileError`."""
    return make_plots(path, outdir, fmt, only).written


def format_fits(fits: dict) -> list[str]:
    """Human-readable lines summarising :func:`chain_fits`."""
    if not fits:
        return []
    th = fits["theory"]
    lines = []
    for which, gc in fits.get("gamma_c", {}).items():
        r = fits["forward"][which]
        lo, hi = r["window"]
        ex = ", ".join(f"{q} {_fmt_exp(r[q][0])} (theory {th[q]:+.3g})"
                       for q in ("V2", "dtheta2", "thetadot2") if q in r)
        lines.append(f"forward, gamma_c {which} = {gc:.8g}: {ex}; window gamma_c-gamma in "
                     f"[{lo:.3g}, {hi:.3g}]")
    if "lengths" in fits:
        L = fits["lengths"]
        lines.append("lengths: " + ", ".join(
            f"{k} {_fmt_exp(v[0])}" for k, v in L.items())
            + f" (theory l_corr {th['l_corr']:+.3g}, l_r {th['l_r']:+.3g})")
    if "reverse" in fits:
        r = fits["reverse"]
        t = r["turn"]
        line = (f"reverse, gamma_turn = {fits['gamma_turn']:.10g}: V2 {_fmt_exp(t['V2'][0])} "
                f"(theory -1) against gamma_turn-gamma in [{t['window'][0]:.3g}, "
                f"{t['window'][1]:.3g}]")
        if "tilde" in r:
            w = r["tilde"]["window"]
            line += (f"; {_fmt_exp(r['tilde']['V2'][0])} against gamma~_c-gamma in [{w[0]:.3g}, "
                     f"{w[1]:.3g}], gamma~_c - gamma_turn = "
                     f"{r['gamma_c_tilde'] - fits['gamma_turn']:.3g}")
        lines.append(line)
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m parflow.plot",
        description="Draw the figures a parflow run file supports.")
    ap.add_argument("file", help="parflow run file (HDF5)")
    ap.add_argument("--out", metavar="DIR", default=None,
                    help="output folder (default: <FILE stem>_plots next to FILE)")
    ap.add_argument("--format", default="png", choices=("png", "pdf", "svg"),
                    help="image format (default png)")
    ap.add_argument("--only", metavar="NAME", action="append",
                    choices=[n for n, _, _ in FIGURES], help="draw only this figure (repeatable)")
    args = ap.parse_args(argv)
    try:
        res = make_plots(args.file, args.out, args.format, args.only)
    except RunFileError as exc:
        print(f"parflow.plot: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:                      # the output folder cannot be written
        where = exc.filename or args.out or default_outdir(args.file)
        print(f"parflow.plot: error: cannot write {where}: {exc.strerror or exc}",
              file=sys.stderr)
        return 2
    for p in res.written:
        print(p)
    for name, why in res.skipped:
        print(f"parflow.plot: skipped {name}: {why}", file=sys.stderr)
    for name, why in res.failed:
        print(f"parflow.plot: FAILED {name}: {why}", file=sys.stderr)
    for line in format_fits(res.fits):
        print(f"parflow.plot: {line}", file=sys.stderr)
    return 1 if res.failed else 0


if __name__ == "__main__":
    sys.exit(main())
