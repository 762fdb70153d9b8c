"""Figures from parflow run files (PNG by default).

    python -m parflow.plot FILE [FILE ...] [--out/--outdir DIR] [--format png] [--only NAME]

writes every figure that each FILE supports into DIR (default: ``<FILE stem>_plots`` next to
FILE; with several files ``DIR/<FILE stem>/``), and with several files the figures across
runs (e.g. Figs. 3-5 across z) into DIR (default: ``across_runs_plots`` next to the first
file).  Prints the paths written on stdout, and on stderr which figures were skipped and
why, plus the fitted numbers.  Exit status: 0 success, 1 a figure failed, 2 a FILE is
missing or not a parflow run file (or DIR cannot be written).  Figures are chosen by the
run's model and by what it contains; a figure whose data are absent is skipped with the
reason, never an error.

Fits: power laws by least squares in log-log after log-binning (:data:`BINS_PER_DECADE` bins a
decade, so that the crowded points near a divergence do not dominate), over the last
:data:`FIT_DECADES` decades of gamma_c - gamma above :data:`DGAMMA_GUARD` times the typical
|dgamma| near the end of the branch.  Networks: the reversed branch by
``network.fit_reverse_branch`` over sigma in :data:`REVERSE_SIGMA`; C2 = median of
omega_min sqrt(sigma) over sigma >= :data:`C2_SIGMA_MIN`; the gap omega* of D(omega) by
:func:`fit_omega_star`; power laws across runs with error bars by :func:`fit_power_law_err`.

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

Network figures (paper Figs. 3, 4, 5, 8; docs/networks.md):

* ``fig3a_sigma``       sigma against gamma, forward to jamming then reversed.
* ``fig3b_reverse``     -dsigma/dgamma against sigma on the reversed branch, log-log, slope-2
                        reference, fitted exponent and C; the local C_k against sigma.
* ``fig4_omega_min``    omega_min against sigma (fitted slopes, reference -1/2) and
                        omega_min sqrt(sigma) with C2.
* ``fig5_dos``          D(omega) at the analysis instants coloured by sigma, omega* marked;
                        F(omega)/(D_p omega), the quantity that defines omega*.
* ``fig8_correlation``  C(r) of V_na at the analysis instants coloured by sigma (lin, log).
* ``fig8_response``     point-response |V|(r) with the stored two-exponential fits, the
                        collapse V(r) sqrt(sigma) against r / sqrt(sigma), l_c and l_r
                        against sigma.

Across several network runs (one colour per run):

* ``fig3a_sigma_z``     sigma(gamma) for every run.
* ``fig3b_reverse_z``   -dsigma/dgamma against sigma, divided by dz^(1/2), and C(dz) fitted.
* ``fig4_omega_min_z``  omega_min(sigma), omega_min sqrt(sigma/dz), and C2(dz) fitted.
* ``fig5_dos_z``        D(omega) of every run with, inset, omega*(dz) fitted; D against
                        omega/dz.

Python API: :func:`plot_file` (paths written), :func:`make_plots` (paths, skipped figures
and fits), :func:`make_across_plots`, :func:`load_run`, :func:`chain_fits`,
:func:`network_fits`, :func:`across_fits`, :func:`fit_omega_star`, :func:`fit_power_law`,
:func:`fit_power_law_err`, :func:`fit_divergence_point`, :func:`fit_window`,
:func:`typical_dgamma`, :func:`log_bin`, :func:`main`.

Only numpy, h5py and matplotlib (Agg canvas, no pyplot) are used, plus scipy through
``parflow.models.network`` for the reversed-branch fit: plotting needs neither MPI nor PETSc.
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import tomllib
from dataclasses import dataclass, field

import h5py
import matplotlib
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
    if run.model == "network":
        nn = run.model_attrs.get("n_nodes")
        if nn is not None and bits[-1].startswith("N="):
            bits[-1] += f" ({int(nn)} nodes)"
        bits.append(f"z={network_z(run):.4g} (δz={network_dz(run):.3g})")
        bits.append(f"seed {_seed(run)}")
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


# ---------------------------------------------------------------------------------------
# Network fits (paper Figs. 3, 4, 5, 8; DESIGN §6; docs/networks.md)
# ---------------------------------------------------------------------------------------
REVERSE_SIGMA = (1e3, 1e5)        # sigma window of the reversed-branch fit (docs/networks.md)
C2_SIGMA_MIN = 1e3                # C2 = median of omega_min sqrt(sigma) over sigma >= this
OMEGA_STAR_FRACTION = 0.5         # omega* from the integrated D(omega): see fit_omega_star
OMEGA_STAR_PLATEAU = (0.2, 0.4)   # omega window where D(omega) is the plateau level D_p
OMEGA_STAR_BOOT = 200             # bootstrap resamples of the modes (error of omega*)
DOS_PER_DECADE = 16               # log bins of D(omega) in the figures
CORR_MIN_COUNT = 50               # C(r) bins with fewer pairs are not drawn (as crossing_length)
RESOLVED_FRACTION = 0.5           # l_r counts as measured if below this fraction of r_max


def fit_power_law_err(x, y, yerr=None) -> dict:
    """Least squares of log y = log A + p log x over the positive finite points, weighted by
    (y / yerr)^2 when ``yerr`` is given.

    Returns dict(exponent, err, prefactor, chi2, dof, n).  ``err`` is one standard deviation
    from the covariance of the fit; with error bars it is multiplied by sqrt(chi2/dof) when
    that exceeds 1 (the points scatter more than their error bars say), without them it is
    the usual residual-based error.  NaN with fewer than 2 points (err: fewer than 3 without
    error bars)."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    e = np.full(x.shape, np.nan) if yerr is None else np.asarray(yerr, float)
    ok = np.isfinite(x) & np.isfinite(y) & (x > 0) & (y > 0)
    if yerr is not None:
        ok &= np.isfinite(e) & (e > 0)
    out = dict(exponent=np.nan, err=np.nan, prefactor=np.nan, chi2=np.nan, dof=0,
               n=int(ok.sum()))
    if ok.sum() < 2 or np.ptp(np.log(x[ok])) == 0:
        return out
    X, Y = np.log(x[ok]), np.log(y[ok])
    w = (y[ok] / e[ok]) ** 2 if yerr is not None else np.ones(X.size)
    A = np.column_stack([np.ones_like(X), X])
    M = A.T @ (w[:, None] * A)
    cov = np.linalg.inv(M)
    c0, p = cov @ (A.T @ (w * Y))
    res = Y - (c0 + p * X)
    chi2 = float(np.sum(w * res ** 2))
    dof = X.size - 2
    if yerr is None:
        err = math.sqrt(chi2 / dof * cov[1, 1]) if dof > 0 else float("nan")
    else:
        err = math.sqrt(cov[1, 1] * max(1.0, chi2 / dof if dof > 0 else 1.0))
    out.update(exponent=float(p), err=float(err), prefactor=float(np.exp(c0)), chi2=chi2,
               dof=int(dof))
    return out


def _omega_star_once(w: np.ndarray, nc: int, fraction: float, plateau) -> tuple:
    """omega* of one sorted spectrum (see fit_omega_star): (omega*, D_p, omega_c)."""
    a, b = plateau
    n_pl = np.searchsorted(w, b, "left") - np.searchsorted(w, a, "left")
    Dp = n_pl / (nc * (b - a))
    if not Dp > 0:
        return float("nan"), float(Dp), float("nan")
    j = np.arange(w.size)                       # modes below w[j] (ties do not matter)
    line = fraction * Dp * w
    # the crossing must be reached before the top of the plateau window
    if np.searchsorted(w, b, "left") / nc < fraction * Dp * b:
        return float("nan"), float(Dp), float("nan")
    below = np.nonzero((j / nc < line) & (w < b))[0]
    if below.size == 0:
        return float("nan"), float(Dp), float("nan")
    wc = float(w[below[-1]])
    return (1.0 - fraction) * wc, float(Dp), wc


def fit_omega_star(omega, fraction: float = OMEGA_STAR_FRACTION,
                   plateau: tuple = OMEGA_STAR_PLATEAU, n_boot: int = OMEGA_STAR_BOOT,
                   seed: int = 0) -> dict:
    """The gap omega* of the spectrum {omega_k} of N (all Nc of them: the ``omega`` dataset).

    Definition.  D_p is the plateau level of D(omega) (normalised to 1 over the Nc modes):
    the fraction of modes in the window ``plateau`` divided by its width.  F(omega) is the
    fraction of modes below omega (the integrated D).  omega_c is the largest omega at which
    the integrated D is still below ``fraction`` times the integral of the plateau,
    F(omega) < fraction * D_p * omega, and

        omega* = (1 - fraction) * omega_c.

    Why this one: for a sharp gap (D = 0 below omega_g, D_p above) F = D_p (omega - omega_g)
    and omega* = omega_g exactly, for any fraction; for any D(omega) = D_p g(omega/omega_g)
    omega* is proportional to omega_g, so the exponent of omega* against dz does not depend
    on the choice (a fixed fraction of *all* modes, or D = D_p/2 on fixed-width bins, would
    add a dz-independent offset or resolution).  It counts modes instead of binning them
    (about fraction * D_p * omega_c * Nc modes lie below omega_c: ~50 at dz = 0.1, Nc ~ 8000),
    and a few modes inside the gap (the soft mode near jamming) move it by a few % only.
    The plateau window must lie above the gap and below the rise of D(omega) towards its
    maximum (omega ~ 2): (0.2, 0.4) for the 2D networks here, which puts the crossing
    below 0.4, i.e. omega* < 0.2 (NaN otherwise).

    Error: standard deviation over ``n_boot`` bootstrap resamples of the modes (fixed seed:
    reproducible).  It treats the modes as independent draws, which overstates the noise
    of a spectrum (eigenvalues repel): an upper bound.

    Returns dict(omega_star, err, D_plateau, omega_c, fraction, plateau, n_modes)."""
    w = np.asarray(omega, float)
    w = np.sort(w[np.isfinite(w)])
    nc = w.size
    out = dict(omega_star=np.nan, err=np.nan, D_plateau=np.nan, omega_c=np.nan,
               fraction=float(fraction), plateau=tuple(plateau), n_modes=int(nc))
    if nc < 10 or not 0 < fraction < 1:
        return out
    ws, Dp, wc = _omega_star_once(w, nc, fraction, plateau)
    out.update(omega_star=ws, D_plateau=Dp, omega_c=wc)
    if np.isfinite(ws) and n_boot > 1:
        rng = np.random.default_rng(seed)
        boot = np.array([_omega_star_once(np.sort(w[rng.integers(0, nc, nc)]), nc, fraction,
                                          plateau)[0] for _ in range(n_boot)])
        boot = boot[np.isfinite(boot)]
        if boot.size > 1:
            out["err"] = float(np.std(boot, ddof=1))
    return out


def network_dz(run: Run) -> float:
    """dz = 2d - z (model attribute, else from the scene's z)."""
    dz = run.model_attrs.get("dz")
    if dz is not None and np.isfinite(dz):
        return float(dz)
    z = run.model_attrs.get("z", run.param("z"))
    d = int(run.param("d", 2) or 2)
    return 2.0 * d - float(z) if z is not None else float("nan")


def network_z(run: Run) -> float:
    z = run.model_attrs.get("z", run.param("z"))
    return float(z) if z is not None else float("nan")


def _seed(run: Run):
    return run.scene.get("seed", run.model_attrs.get("network_seed"))


def _run_label(run: Run) -> str:
    return f"z={network_z(run):.3g} (δz={network_dz(run):.3g}), seed {_seed(run)}"


def network_reverse_fit(run: Run, window: tuple = REVERSE_SIGMA) -> dict | None:
    """dsigma/dgamma on the first reversed branch (network.reverse_branch) and the fit of
    network.fit_reverse_branch over ``window`` of sigma; None without a reversed branch."""
    rv = reverse_rows(run)
    if rv is None or "sigma" not in run.ts or "strain" not in run.ts:
        return None
    from .models.network import fit_reverse_branch, reverse_branch
    rows, _ = rv
    strain, sigma = run.ts["strain"][rows], run.ts["sigma"][rows]
    if strain.size < 3:
        return None
    out = fit_reverse_branch(strain, sigma, *window)
    out["window"] = tuple(window)
    out["branch"] = reverse_branch(strain, sigma)
    return out


def omega_min_fit(run: Run, sigma_min: float = C2_SIGMA_MIN) -> dict | None:
    """omega_min ~ sigma^x on each branch and C2 = omega_min sqrt(sigma) (median and
    16-84 %) over the records with sigma >= sigma_min; None without omega_min."""
    ts = run.ts
    if "omega_min" not in ts or "sigma" not in ts:
        return None
    w, s = np.asarray(ts["omega_min"], float), np.asarray(ts["sigma"], float)
    d = ts["direction"] if "direction" in ts else np.ones(w.size, int)
    ok = np.isfinite(w) & np.isfinite(s) & (w > 0) & (s > 0)
    if not ok.any():
        return None
    out = dict(sigma_min=sigma_min)
    for sgn, name in ((1, "forward"), (-1, "reverse")):
        m = ok & (d == sgn) & (s >= sigma_min)
        out[name] = fit_power_law(s[m], w[m]) + (int(m.sum()),)
    m = ok & (s >= sigma_min)
    c2 = w[m] * np.sqrt(s[m])
    if c2.size:
        out.update(C2=float(np.median(c2)), C2_p16=float(np.percentile(c2, 16)),
                   C2_p84=float(np.percentile(c2, 84)), n=int(c2.size))
    else:
        out.update(C2=np.nan, C2_p16=np.nan, C2_p84=np.nan, n=0)
    return out


def spectrum_instants(run: Run) -> list[dict]:
    """Analysis instants holding the full spectrum (``omega``) or a binned D(omega)."""
    return [a for a in run.analysis if "omega" in a or ("dos" in a and "dos_edges" in a)]


def omega_star_fits(run: Run) -> dict | None:
    """fit_omega_star at every instant with the full spectrum, and the run's value: the mean
    over the instants, with error sqrt(mean(err^2) + std^2) (the instants share the network,
    so their errors are not divided by sqrt(n); the spread with strain is added)."""
    inst = [a for a in run.analysis if "omega" in a]
    if not inst:
        return None
    per = []
    for a in inst:
        f = fit_omega_star(a["omega"])
        f.update(sigma=float(a.get("sigma", np.nan)), gamma=float(a.get("gamma", np.nan)),
                 direction=int(a.get("direction", 1)), step=int(a.get("step", -1)))
        per.append(f)
    v = np.array([p["omega_star"] for p in per])
    e = np.array([p["err"] for p in per])
    ok = np.isfinite(v)
    out = dict(instants=per, omega_star=np.nan, err=np.nan, n=int(ok.sum()))
    if ok.any():
        spread = float(np.std(v[ok], ddof=1)) if ok.sum() > 1 else 0.0
        e2 = float(np.nanmean(e[ok] ** 2)) if np.isfinite(e[ok]).any() else 0.0
        out.update(omega_star=float(np.mean(v[ok])), err=math.sqrt(e2 + spread ** 2),
                   spread=spread)
    return out


def response_instants(run: Run) -> list[dict]:
    return [a for a in run.analysis if "resp_V" in a and "resp_r" in a]


def response_fits(run: Run) -> dict | None:
    """Per analysis instant: the stored two-exponential fit of the V profile (l_c, l_r, A,
    B), whether l_r is resolved (finite and below RESOLVED_FRACTION of the largest r of the
    profile: the tail decays by at least e^2 within it), and the
    collapse variables l_r/sqrt(sigma) and B sqrt(sigma) (constant if V(r) sqrt(sigma) is a
    function of r/sqrt(sigma) in the tail); the exponent of l_r against sigma over the
    resolved instants."""
    inst = response_instants(run)
    if not inst:
        return None
    rows = []
    for a in inst:
        r = np.asarray(a["resp_r"], float)
        rmax = float(r[-1] + (r[1] - r[0]) / 2) if r.size > 1 else float("nan")
        s = float(a.get("sigma", np.nan))
        lc, lr = float(a.get("resp_l_c", np.nan)), float(a.get("resp_l_r", np.nan))
        B = float(a.get("resp_B", np.nan))
        res = bool(np.isfinite(lr) and lr < RESOLVED_FRACTION * rmax)
        rows.append(dict(sigma=s, direction=int(a.get("direction", 1)), l_c=lc, l_r=lr,
                         A=float(a.get("resp_A", np.nan)), B=B, rmax=rmax, resolved=res,
                         lr_over_sqrt_sigma=lr / math.sqrt(s) if res and s > 0 else np.nan,
                         B_sqrt_sigma=B * math.sqrt(s) if res and s > 0 else np.nan,
                         VV=float(a.get("VV", np.nan))))
    res = [x for x in rows if x["resolved"]]
    fit = fit_power_law_err([x["sigma"] for x in res], [x["l_r"] for x in res])
    return dict(instants=rows, l_r_vs_sigma=fit)


def network_fits(run: Run) -> dict:
    """Every network number the figures show (keys absent when their data are)."""
    out: dict = dict(model="network", z=network_z(run), dz=network_dz(run), seed=_seed(run),
                     N=run.param("N"), path=run.path)
    rv = network_reverse_fit(run)
    if rv is not None:
        out["reverse"] = rv
    om = omega_min_fit(run)
    if om is not None:
        out["omega_min"] = om
    ost = omega_star_fits(run)
    if ost is not None:
        out["omega_star"] = ost
    rf = response_fits(run)
    if rf is not None:
        out["response"] = rf
    return out


def across_fits(fits: list[dict]) -> dict:
    """Power laws across runs (one value per run): C(dz) of the reversed branch (pred.
    exponent -1/2), C2(dz) (pred. 1/2), omega*(dz) (pred. 1), by fit_power_law_err.

    C and C2 are fitted unweighted (their error is the scatter between networks: the fit
    error of C and the 16-84 % range of C2 are far smaller than the seed-to-seed scatter, so
    as weights they would let a few runs decide); omega* is weighted by its error (bootstrap
    over the modes and spread over the run's spectra: see omega_star_fits)."""
    def collect(get):
        dz, y, e = [], [], []
        for f in fits:
            v = get(f)
            if v is not None and np.isfinite(v[0]):
                dz.append(f["dz"]), y.append(v[0]), e.append(v[1])
        return np.array(dz), np.array(y), np.array(e, float)

    out = {}
    spec = dict(
        C=(lambda f: (f["reverse"]["C"], f["reverse"]["C_err"]) if "reverse" in f else None,
           -0.5, False),
        C2=(lambda f: (f["omega_min"]["C2"], (f["omega_min"]["C2_p84"]
                                              - f["omega_min"]["C2_p16"]) / 2)
            if "omega_min" in f else None, 0.5, False),
        omega_star=(lambda f: (f["omega_star"]["omega_star"], f["omega_star"]["err"])
                    if "omega_star" in f else None, 1.0, True))
    for key, (get, pred, weighted) in spec.items():
        dz, y, e = collect(get)
        if np.unique(dz).size < 2:
            continue
        e = np.where(np.isfinite(e) & (e > 0), e, np.nan)
        use = weighted and np.isfinite(e).all()
        fit = fit_power_law_err(dz, y, e if use else None)
        out[key] = dict(dz=dz, value=y, err=e, fit=fit, predicted=pred, weighted=bool(use))
    return out


def format_network_fits(f: dict) -> list[str]:
    lines = []
    head = f"z = {f['z']:.4g} (dz = {f['dz']:.3g}), seed {f['seed']}"
    if "reverse" in f:
        r = f["reverse"]
        lines.append(f"{head}: reversed branch, -dsigma/dgamma ~ sigma^a over sigma in "
                     f"[{r['window'][0]:g}, {r['window'][1]:g}] ({r['n']} records): a = "
                     f"{r['slope']:.3f} +- {r['slope_err']:.3f} (pred. 2), C = {r['C']:.4g} "
                     f"+- {r['C_err']:.2g} (local C_k median {r['C_median']:.4g})")
    if "omega_min" in f:
        o = f["omega_min"]
        lines.append(f"{head}: omega_min ~ sigma^x for sigma >= {o['sigma_min']:g}: forward "
                     f"{_fmt_exp(o['forward'][0])} ({o['forward'][2]}), reverse "
                     f"{_fmt_exp(o['reverse'][0])} ({o['reverse'][2]}) (pred. -1/2); C2 = "
                     f"omega_min sqrt(sigma) = {o['C2']:.4g} ({o['C2_p16']:.4g}-"
                     f"{o['C2_p84']:.4g})")
    if "omega_star" in f:
        o = f["omega_star"]
        each = ", ".join(f"{p['omega_star']:.4f} (sigma {p['sigma']:.3g})"
                         for p in o["instants"])
        lines.append(f"{head}: omega* = {o['omega_star']:.4f} +- {o['err']:.4f} (instants: "
                     f"{each})")
    if "response" in f:
        r = f["response"]
        res = [x for x in r["instants"] if x["resolved"]]
        if res:
            lines.append(f"{head}: point response, l_r ~ sigma^{r['l_r_vs_sigma']['exponent']:.3f}"
                         f" +- {r['l_r_vs_sigma']['err']:.3f} over {len(res)} instants with "
                         f"l_r < {RESOLVED_FRACTION:g} r_max (pred. 0.5); l_r/sqrt(sigma) = "
                         + ", ".join(f"{x['lr_over_sqrt_sigma']:.2f}" for x in res)
                         + "; B sqrt(sigma) = "
                         + ", ".join(f"{x['B_sqrt_sigma']:.3g}" for x in res))
    return lines


def format_across_fits(a: dict) -> list[str]:
    names = dict(C="C of the reversed branch", C2="C2 = omega_min sqrt(sigma)",
                 omega_star="omega*")
    lines = []
    for k, v in a.items():
        f = v["fit"]
        how = (f"weighted, chi2/dof = {f['chi2'] / f['dof']:.2g}" if v["weighted"] and f["dof"]
               else "weighted" if v["weighted"] else "unweighted")
        lines.append(f"across runs: {names[k]} ~ dz^b, b = {f['exponent']:.3f} +- "
                     f"{f['err']:.3f} (pred. {v['predicted']:+g}; {f['n']} runs, {how})")
    return lines


# ---------------------------------------------------------------------------------------
# Network figures
# ---------------------------------------------------------------------------------------
_SIGMA = r"$\sigma$ [$\eta_0\dot\gamma$]"
_OMEGA = r"$\omega$ (dimensionless: $\sqrt{\lambda(\mathcal{N})}$)"


def _need_network(run: Run):
    if run.model != "network":
        raise Skip(f"model is {run.model!r}, not network")


def _sigma_colors(inst, cmap="viridis"):
    return _instant_colors(inst, key="sigma", cmap=cmap)


def _branch_style(a) -> str:
    return "-" if a.get("direction", 1) > 0 else "--"


def _branch_note() -> str:
    return "solid: forward, dashed: reversed"


def fig3a_sigma(run: Run, fits: dict) -> Figure:
    """Fig. 3a: sigma against gamma, forward to jamming then reversed, log-y."""
    _need_network(run)
    ts = run.ts
    if "sigma" not in ts or "gamma" not in ts:
        raise Skip("no sigma / gamma in /timeseries")
    fig = _figure(7.5, 5.2)
    ax = fig.subplots()
    _draw_sigma_gamma(ax, run, "C0", "C3", labels=True)
    ax.set_xlabel(r"$\gamma$ (strain coordinate)")
    ax.set_ylabel(_SIGMA)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.suptitle(_title(run, "Fig. 3a: stress against strain"), fontsize=10)
    return fig


def _draw_sigma_gamma(ax, run, cf, cr, labels=False, label=""):
    ts = run.ts
    d = ts["direction"] if "direction" in ts else np.ones(len(ts["sigma"]), int)
    for a, b, sgn in segments(d):
        g, s = ts["gamma"][a:b], ts["sigma"][a:b]
        if a > 0:                                    # join the branches at the turn
            g, s = np.r_[ts["gamma"][a - 1], g], np.r_[ts["sigma"][a - 1], s]
        ok = np.isfinite(s) & (s > 0)
        lab = (("forward" if sgn > 0 else "reversed") if labels else
               (label if sgn > 0 else None))
        ax.semilogy(g[ok], s[ok], "-" if sgn > 0 else "--", color=cf if sgn > 0 else cr,
                    lw=1.2, label=lab)


def fig3b_reverse(run: Run, fits: dict) -> Figure:
    """Fig. 3b: -dsigma/dgamma against sigma on the reversed branch, log-log, with the fit
    (exponent a and C of -dsigma/dgamma = sigma^2/C) and the local C_k."""
    _need_network(run)
    r = fits.get("reverse")
    if r is None:
        raise Skip("no reversed branch (direction == -1) with sigma and strain")
    br = r["branch"]
    ok = (br["dsdg"] < 0) & (br["sigma"] > 0)
    if ok.sum() < 3:
        raise Skip("reversed branch has fewer than 3 decreasing records")
    lo, hi = r["window"]
    fig = _figure(12.5, 5.0)
    ax, ax2 = fig.subplots(1, 2)
    s, y = br["sigma"][ok], -br["dsdg"][ok]
    ax.loglog(s, y, ".", ms=4, color="C3", label="finite differences of the time series")
    ax.axvspan(lo, hi, color="0.92", zorder=0, label=f"fit window σ ∈ [{lo:g}, {hi:g}]")
    if np.isfinite(r["C"]):
        xs = np.geomspace(max(lo, s.min()), min(hi, s.max()), 20)
        ax.loglog(xs, xs ** 2 / r["C"], "-", color="C3", lw=2.5, alpha=0.5,
                  label=f"σ²/C, C = {r['C']:.4g} ± {r['C_err']:.2g}")
    if np.isfinite(r["slope"]):
        m = (s >= lo) & (s <= hi)
        k = float(np.median(np.log(y[m]) - r["slope"] * np.log(s[m]))) if m.any() else np.nan
        xs = np.geomspace(s.min(), s.max(), 20)
        ax.loglog(xs, np.exp(k) * xs ** r["slope"] * 3, ":", color="k", lw=1,
                  label=f"fit slope a = {r['slope']:.3f} ± {r['slope_err']:.3f} (×3)")
    xm = math.sqrt(s.min() * s.max())
    _reference(ax, xm, float(np.exp(np.median(np.log(y / s ** 2)))) * xm ** 2 / 3, 2.0,
               math.sqrt(s.max() / s.min()), "reference slope 2 (÷3)")
    ax.set_xlabel(_SIGMA)
    ax.set_ylabel(r"$-d\sigma/d\tilde\gamma$  ($\tilde\gamma$: strain since the reversal)")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    ax.set_title("reversed branch: paper −dσ/dγ = σ²/C(δz)", fontsize=10)
    Ck = br["C"][ok]
    pos = Ck > 0
    ax2.semilogx(s[pos], Ck[pos], ".", ms=4, color="C3",
                 label=r"local $C_k = \Delta x/\Delta(1/\sigma)$")
    if np.isfinite(r["C"]):
        ax2.axhline(r["C"], color="k", lw=1, label=f"fit C = {r['C']:.4g}")
    ax2.axvspan(lo, hi, color="0.92", zorder=0)
    if pos.any():
        top = np.percentile(Ck[pos], 95)
        ax2.set_ylim(0, 2 * top)
    ax2.set_xlabel(_SIGMA)
    ax2.set_ylabel(r"$C = \sigma^2 / (-d\sigma/d\tilde\gamma)$")
    ax2.grid(True, alpha=0.3)
    ax2.legend(fontsize=8)
    ax2.set_title("constant where the σ² law holds", fontsize=10)
    fig.suptitle(_title(run, "Fig. 3b: reversed branch"), fontsize=10)
    return fig


def fig4_omega_min(run: Run, fits: dict) -> Figure:
    """Fig. 4: omega_min against sigma (fits over sigma >= C2_SIGMA_MIN, slope -1/2) and
    omega_min sqrt(sigma) against sigma (C2)."""
    _need_network(run)
    o = fits.get("omega_min")
    if o is None:
        raise Skip("omega_min was not computed (observables.omega_min_every = 0)")
    ts = run.ts
    w, s = np.asarray(ts["omega_min"], float), np.asarray(ts["sigma"], float)
    d = ts["direction"] if "direction" in ts else np.ones(w.size, int)
    ok = np.isfinite(w) & np.isfinite(s) & (w > 0) & (s > 0)
    fig = _figure(12.5, 5.0)
    ax, ax2 = fig.subplots(1, 2)
    for sgn, name, c, mk in ((1, "forward", "C0", "o"), (-1, "reverse", "C3", "s")):
        m = ok & (d == sgn)
        if not m.any():
            continue
        p = o[name]
        ax.loglog(s[m], w[m], mk, ms=3, color=c, mfc="none",
                  label=f"{name}: slope {_fmt_exp(p[0])} (σ ≥ {o['sigma_min']:g}, {p[2]} pts)")
        ax2.semilogx(s[m], w[m] * np.sqrt(s[m]), mk, ms=3, color=c, mfc="none", label=name)
    sx = s[ok]
    if np.isfinite(o["C2"]):
        xs = np.geomspace(sx.min(), sx.max(), 20)
        ax.loglog(xs, o["C2"] / np.sqrt(xs), "k--", lw=1,
                  label=r"$C_2/\sqrt{\sigma}$ (slope −1/2)")
        ax2.axhline(o["C2"], color="k", lw=1,
                    label=f"C₂ = {o['C2']:.4g} (median, σ ≥ {o['sigma_min']:g}; "
                          f"16–84 %: {o['C2_p16']:.4g}–{o['C2_p84']:.4g})")
    ax.axvline(o["sigma_min"], color="0.6", ls=":", lw=1)
    ax2.axvline(o["sigma_min"], color="0.6", ls=":", lw=1)
    ax.set_xlabel(_SIGMA)
    ax.set_ylabel(r"$\omega_{min}$ (dimensionless)")
    ax2.set_xlabel(_SIGMA)
    ax2.set_ylabel(r"$\omega_{min}\sqrt{\sigma}$")
    for a_ in (ax, ax2):
        a_.grid(True, alpha=0.3)
        a_.legend(fontsize=8)
    ax.set_title("paper: ω_min ≈ C₂(δz)/√σ", fontsize=10)
    ax2.set_title("C₂ = ω_min √σ (dotted: σ from which C₂ is taken)", fontsize=10)
    fig.suptitle(_title(run, "Fig. 4: lowest frequency of N against stress"), fontsize=10)
    return fig


def _dos_curve(a: dict):
    """(omega bin centres, D) for an instant: from the full spectrum on fixed log bins
    (DOS_PER_DECADE per decade, so that instants compare), else the stored binned D."""
    if "omega" in a:
        w = np.asarray(a["omega"], float)
        w = w[np.isfinite(w)]
        pos = w[w > 0]
        if pos.size < 2:
            return np.array([]), np.array([])
        k0 = math.floor(math.log10(pos.min()) * DOS_PER_DECADE)
        k1 = math.ceil(math.log10(pos.max()) * DOS_PER_DECADE)
        edges = 10.0 ** (np.arange(k0, k1 + 1) / DOS_PER_DECADE)
        h, _ = np.histogram(w, edges)
        D = h / (w.size * np.diff(edges))
    else:
        edges, D = np.asarray(a["dos_edges"], float), np.asarray(a["dos"], float)
    x = np.sqrt(edges[1:] * edges[:-1])
    return x, np.where(D > 0, D, np.nan)       # empty bins break the line


def fig5_dos(run: Run, fits: dict) -> Figure:
    """Fig. 5: D(omega) at the analysis instants (coloured by sigma) with omega* marked, and
    the quantity that defines omega*: F(omega) / (D_p omega) (fit_omega_star)."""
    _need_network(run)
    inst = spectrum_instants(run)
    if not inst:
        if any("omega_low" in a for a in run.analysis):
            raise Skip("only the lowest frequencies were computed (model.spectrum = 'low'): "
                       "no D(omega)")
        raise Skip("no analysis groups with a spectrum (model.spectrum = 'none')")
    cols, sm = _sigma_colors(inst)
    ost = {p["step"]: p for p in fits.get("omega_star", {}).get("instants", [])}
    fig = _figure(12.5, 5.0)
    ax, ax2 = fig.subplots(1, 2)
    for a, c in zip(inst, cols):
        x, D = _dos_curve(a)
        ax.loglog(x, D, _branch_style(a), color=c, lw=1.2, marker=".", ms=3)
        p = ost.get(int(a.get("step", -1)))
        if p is not None and np.isfinite(p["omega_star"]):
            ax.axvline(p["omega_star"], color=c, ls=_branch_style(a), lw=0.8, alpha=0.8)
    ost_all = fits.get("omega_star")
    if ost_all is not None and np.isfinite(ost_all["omega_star"]):
        ax.plot([], [], "k-", lw=0.8, label=f"ω* (vertical lines): {ost_all['omega_star']:.4f} ± "
                                             f"{ost_all['err']:.4f} (mean of instants)")
        Dp = np.nanmean([p["D_plateau"] for p in ost.values()])
        ax.axhline(Dp, color="0.5", ls=":", lw=1,
                   label=f"plateau D_p = {Dp:.3f} (ω ∈ {OMEGA_STAR_PLATEAU})")
    ax.set_xlabel(_OMEGA)
    ax.set_ylabel(r"$D(\omega)$ (normalised to 1)")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    ax.set_title(f"density of states at the analysis instants ({_branch_note()})", fontsize=10)
    fig.colorbar(sm, ax=ax, label=_SIGMA)
    drawn = False
    for a, c in zip(inst, cols):
        p = ost.get(int(a.get("step", -1)))
        if p is None or not np.isfinite(p["D_plateau"]):
            continue
        w = np.sort(np.asarray(a["omega"], float))
        F = np.arange(w.size) / w.size
        m = (w > 0) & (w < OMEGA_STAR_PLATEAU[1])
        ax2.plot(w[m], F[m] / (p["D_plateau"] * w[m]), _branch_style(a), color=c, lw=1.2,
                 label=f"σ = {p['sigma']:.3g}: ω* = {p['omega_star']:.4f} ± {p['err']:.4f}")
        ax2.plot(p["omega_c"], OMEGA_STAR_FRACTION, "o", color=c, ms=5)
        drawn = True
    if drawn:
        ax2.axhline(OMEGA_STAR_FRACTION, color="k", lw=0.8, ls=":")
        ax2.set_ylim(0, 1.3)
        ax2.set_xscale("log")
        wcs = [p["omega_c"] for p in ost.values() if np.isfinite(p["omega_c"])]
        if wcs:
            ax2.set_xlim(0.1 * min(wcs), OMEGA_STAR_PLATEAU[1])
        ax2.legend(fontsize=8, loc="upper left")
    else:
        ax2.text(0.5, 0.5, "no full spectrum (omega): ω* not measured", ha="center",
                 transform=ax2.transAxes)
    ax2.set_xlabel(_OMEGA)
    ax2.set_ylabel(r"$F(\omega) / (D_p\,\omega)$")
    ax2.grid(True, alpha=0.3)
    ax2.set_title(f"ω* = (1 − {OMEGA_STAR_FRACTION:g}) ω_c, ω_c (dots): last crossing of "
                  f"{OMEGA_STAR_FRACTION:g}", fontsize=10)
    fig.suptitle(_title(run, "Fig. 5: density of states of N and its gap ω*"), fontsize=10)
    return fig


def _good_corr(a):
    r, C = np.asarray(a["corr_r"], float), np.asarray(a["corr_C"], float)
    ok = np.isfinite(C)
    if "corr_counts" in a:
        ok &= np.asarray(a["corr_counts"]) >= CORR_MIN_COUNT
    return r[ok], C[ok]


def fig8_correlation(run: Run, fits: dict) -> Figure:
    """Fig. 8: C(r) of V_na at the analysis instants, coloured by sigma; linear and log-y."""
    _need_network(run)
    inst = [a for a in run.analysis if "corr_C" in a and "corr_r" in a]
    if not inst:
        raise Skip("no analysis groups with corr_C (model.correlation = false)")
    cols, sm = _sigma_colors(inst)
    fig = _figure(12.5, 5.0)
    ax, ax2 = fig.subplots(1, 2)
    for a, c in zip(inst, cols):
        r, C = _good_corr(a)
        ax.semilogx(r, C, _branch_style(a), color=c, lw=1.2)
        ax2.semilogy(r, np.where(C > 0, C, np.nan), _branch_style(a), color=c, lw=1.0)
    ax.axhline(0, color="k", lw=0.6)
    ax.axhline(np.exp(-1), color="0.5", lw=0.6, ls=":")
    ax.set_xlabel(r"$r$ [$a_0$]")
    ax.set_ylabel(r"$C(r) = \langle V_i\cdot V_j\rangle / \langle V^2\rangle$")
    ax.set_title(f"velocity correlation of V_na ({_branch_note()}; dotted: 1/e)", fontsize=10)
    ax2.set_xlabel(r"$r$ [$a_0$]")
    ax2.set_ylabel(r"$C(r)$ (positive values, log)")
    ax2.set_title("log-y: initial decay on l_c, weak tail on l_r", fontsize=10)
    ax2.set_ylim(1e-3, 1.5)
    for a_ in (ax, ax2):
        a_.grid(True, alpha=0.3)
    fig.colorbar(sm, ax=[ax, ax2], label=_SIGMA)
    fig.suptitle(_title(run, f"Fig. 8: velocity correlations (bins with ≥ {CORR_MIN_COUNT} "
                             "pairs)"), fontsize=10)
    return fig


def fig8_response(run: Run, fits: dict) -> Figure:
    """Point response: |V|(r) coloured by sigma with the two-exponential fits, the collapse
    V(r) sqrt(sigma) against r / sqrt(sigma), and l_c, l_r against sigma."""
    _need_network(run)
    inst = response_instants(run)
    if not inst:
        raise Skip("no analysis groups with the point response (resp_V)")
    rf = fits["response"]["instants"]
    cols, sm = _sigma_colors(inst)
    fig = _figure(16, 5.0)
    ax, ax2, ax3 = fig.subplots(1, 3)
    for a, c, x in zip(inst, cols, rf):
        r, V = np.asarray(a["resp_r"], float), np.asarray(a["resp_V"], float)
        ok = np.isfinite(V) & (V > 0)
        if "resp_counts_V" in a:
            ok &= np.asarray(a["resp_counts_V"]) > 0
        st = _branch_style(a)
        ax.semilogy(r[ok], V[ok], st, color=c, lw=1.2)
        if np.isfinite(x["A"]) and np.isfinite(x["l_c"]) and x["l_c"] > 0:
            tail = x["B"] * np.exp(-r[ok] / x["l_r"]) if np.isfinite(x["l_r"]) and \
                np.isfinite(x["B"]) else x["B"] if np.isfinite(x["B"]) else 0.0
            ax.semilogy(r[ok], x["A"] * np.exp(-r[ok] / x["l_c"]) + tail, ":", color=c, lw=0.9)
        s = x["sigma"]
        if s > 0:
            ax2.semilogy(r[ok] / math.sqrt(s), V[ok] * math.sqrt(s), st, color=c,
                         lw=1.5 if x["resolved"] else 0.6, alpha=1.0 if x["resolved"] else 0.35)
    ax.set_xlabel(r"$r$ [$a_0$] (distance from the extended rod)")
    ax.set_ylabel(r"$\langle|V|\rangle(r)$ (per unit extension rate of the rod)")
    ax.set_title(f"point response ({_branch_note()}; dotted: "
                 r"$Ae^{-r/l_c}+Be^{-r/l_r}$)", fontsize=10)
    ax2.set_xlabel(r"$r/\sqrt{\sigma}$")
    ax2.set_ylabel(r"$\langle|V|\rangle\sqrt{\sigma}$")
    res = [x for x in rf if x["resolved"]]
    txt = (f"instants with l_r < {RESOLVED_FRACTION:g} r_max (bold): l_r/√σ = "
           + ", ".join(f"{x['lr_over_sqrt_sigma']:.2f}" for x in res) + "; B√σ = "
           + ", ".join(f"{x['B_sqrt_sigma']:.2g}" for x in res)) if res else \
        f"no instant with l_r below {RESOLVED_FRACTION:g} r_max"
    ax2.set_title("collapse (paper): V√σ against r/√σ", fontsize=10)
    if res:                         # where the resolved curves overlap, and a bit beyond
        xr = 1.5 * min(x["rmax"] / math.sqrt(x["sigma"]) for x in res)
        lows = []
        for a, x in zip(inst, rf):
            if x["resolved"]:
                r, V = np.asarray(a["resp_r"], float), np.asarray(a["resp_V"], float)
                m = (r / math.sqrt(x["sigma"]) <= xr) & np.isfinite(V) & (V > 0)
                if m.any():
                    lows.append(float(np.min(V[m])) * math.sqrt(x["sigma"]))
        ax2.set_xlim(0, xr)
        if lows:
            ax2.set_ylim(bottom=0.5 * min(lows))
    ax2.text(0.02, 0.02, txt, transform=ax2.transAxes, fontsize=7, va="bottom", wrap=True)
    sg = np.array([x["sigma"] for x in rf])
    for key, mk, c, lab in (("l_c", "o", "C0", r"$l_c$"), ("l_r", "s", "C3", r"$l_r$")):
        v = np.array([x[key] for x in rf])
        fin = np.isfinite(v) & (v > 0) & (sg > 0)
        for sgn, mfc in ((1, c), (-1, "none")):
            m = fin & (np.array([x["direction"] for x in rf]) == sgn)
            if m.any():
                ax3.loglog(sg[m], v[m], mk, color=c, mfc=mfc, ms=6,
                           label=f"{lab} ({'forward' if sgn > 0 else 'reversed'})")
    lrf = fits["response"]["l_r_vs_sigma"]
    if np.isfinite(lrf["exponent"]):
        xs = np.geomspace(min(x["sigma"] for x in res), max(x["sigma"] for x in res), 20)
        ax3.loglog(xs, lrf["prefactor"] * xs ** lrf["exponent"], "-", color="C3", lw=2.5,
                   alpha=0.45, label=f"fit l_r ~ σ^{lrf['exponent']:.2f} ± {lrf['err']:.2g}")
    if sg[sg > 0].size:
        xm = math.sqrt(sg[sg > 0].min() * sg[sg > 0].max())
        y0 = np.nanmedian([x["lr_over_sqrt_sigma"] for x in res]) if res else 2.5
        _reference(ax3, xm, y0 * math.sqrt(xm), 0.5, math.sqrt(sg[sg > 0].max() / sg[sg > 0].min()),
                   "reference √σ")
    rmax = np.nanmin([x["rmax"] for x in rf])
    if np.isfinite(rmax):
        ax3.axhline(rmax, color="0.4", ls=":", lw=1, label=f"r_max = {rmax:.3g} (profile end)")
    ax3.set_ylim(top=3 * rmax if np.isfinite(rmax) else None)
    ax3.set_xlabel(_SIGMA)
    ax3.set_ylabel(r"length [$a_0$]")
    ax3.grid(True, alpha=0.3)
    ax3.legend(fontsize=7, loc="best")
    ax3.set_title("fitted lengths (paper: l_c ∝ δz^−1/2, l_r ∝ √σ)", fontsize=10)
    for a_ in (ax, ax2):
        a_.grid(True, alpha=0.3)
    fig.colorbar(sm, ax=[ax, ax2], label=_SIGMA)
    fig.suptitle(_title(run, "point response and its collapse"), fontsize=10)
    return fig


# ---------------------------------------------------------------------------------------
# Across runs (several network runs: one colour per run)
# ---------------------------------------------------------------------------------------
def _across_title(runs: list, what: str) -> str:
    Ns = sorted({str(r.param("N")) for r in runs})
    seeds = sorted({str(_seed(r)) for r in runs})
    zs = sorted(network_z(r) for r in runs)
    return (f"{what} — network, N={'/'.join(Ns)}, seed {'/'.join(seeds)}, "
            f"z = {zs[0]:.3g}–{zs[-1]:.3g} ({len(runs)} runs)")


def _run_colors(items):
    """One colour per z (runs at the same z, e.g. several seeds, share it); ``items``: runs
    or (run, fits) pairs."""
    runs = [x[0] if isinstance(x, tuple) else x for x in items]
    zs = sorted({_z_key(r) for r in runs})
    if len(zs) <= 10:
        table = {z: f"C{k}" for k, z in enumerate(zs)}
    else:
        cmap = matplotlib.colormaps["viridis"]
        table = {z: cmap(k / (len(zs) - 1)) for k, z in enumerate(zs)}
    return [table[_z_key(r)] for r in runs]


def _z_key(run: Run) -> float:
    """The z a run was made for (the scene's target; the network's z differs by < 1/N)."""
    z = run.param("z")
    return round(float(z), 4) if z is not None else round(network_z(run), 2)


def _run_markers(items, base="."):
    """A marker per run among the runs at its z (first: ``base``, then x, +, ...)."""
    runs = [x[0] if isinstance(x, tuple) else x for x in items]
    seen: dict = {}
    out = []
    for r in runs:
        z = _z_key(r)
        k = seen.get(z, 0)
        seen[z] = k + 1
        out.append((base, "x", "+", "1", "2", "3")[k % 6])
    return out


def fig3a_sigma_z(runs: list, fits: list, across: dict) -> Figure:
    """Fig. 3a across runs: sigma(gamma) for every z."""
    runs2 = [r for r in runs if "sigma" in r.ts and "gamma" in r.ts]
    if not runs2:
        raise Skip("no run with sigma / gamma")
    fig = _figure(8, 5.5)
    ax = fig.subplots()
    for r, c in zip(runs2, _run_colors(runs2)):
        _draw_sigma_gamma(ax, r, c, c, label=_run_label(r))
    ax.set_xlabel(r"$\gamma$ (strain coordinate)")
    ax.set_ylabel(_SIGMA)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(_branch_note(), fontsize=10)
    fig.suptitle(_across_title(runs2, "Fig. 3a: stress against strain"), fontsize=10)
    return fig


def fig3b_reverse_z(runs: list, fits: list, across: dict) -> Figure:
    """Fig. 3b across runs: -dsigma/dgamma against sigma; divided by dz^(1/2) (collapse if
    C ~ dz^(-1/2)); C against dz with its fit."""
    sel = [(r, f) for r, f in zip(runs, fits) if "reverse" in f]
    if not sel:
        raise Skip("no run with a reversed branch")
    fig = _figure(17, 5.2)
    ax, ax2, ax3 = fig.subplots(1, 3)
    lo, hi = sel[0][1]["reverse"]["window"]
    allx = []
    for (r, f), c, mk in zip(sel, _run_colors(sel), _run_markers(sel)):
        br = f["reverse"]["branch"]
        ok = (br["dsdg"] < 0) & (br["sigma"] > 0)
        s, y = br["sigma"][ok], -br["dsdg"][ok]
        allx.append(s)
        fr = f["reverse"]
        lab = f"{_run_label(r)}: a = {fr['slope']:.3f}, C = {fr['C']:.4g}"
        ax.loglog(s, y, mk, ms=3, color=c, label=lab)
        ax2.loglog(s, y / math.sqrt(f["dz"]), mk, ms=3, color=c)
    allx = np.concatenate(allx)
    for a_ in (ax, ax2):
        a_.axvspan(lo, hi, color="0.92", zorder=0)
        a_.set_xlabel(_SIGMA)
        a_.grid(True, alpha=0.3)
    if allx.size:
        xm = math.sqrt(allx.min() * allx.max())
        span = math.sqrt(allx.max() / allx.min())
        Cm = np.nanmedian([f["reverse"]["C"] for _, f in sel])
        dzm = np.nanmedian([f["dz"] for _, f in sel])
        if np.isfinite(Cm):
            _reference(ax, xm, xm ** 2 / Cm / 5, 2.0, span, "reference slope 2 (÷5)")
            _reference(ax2, xm, xm ** 2 / Cm / math.sqrt(dzm) / 5, 2.0, span,
                       "reference slope 2 (÷5)")
    ax.set_ylabel(r"$-d\sigma/d\tilde\gamma$  ($\tilde\gamma$: strain since the reversal)")
    ax2.set_ylabel(r"$(-d\sigma/d\tilde\gamma)\,/\,\delta z^{1/2}$")
    ax.legend(fontsize=7 if len(sel) <= 8 else 5.5, loc="upper left")
    ax2.legend(fontsize=8, loc="upper left")
    ax.set_title(f"reversed branches (grey: fit window σ ∈ [{lo:g}, {hi:g}])", fontsize=10)
    ax2.set_title("collapse if C ∝ δz^−1/2", fontsize=10)
    _across_panel(ax3, across.get("C"), "C (fit of 1/σ = 1/σ₀ + γ̃/C)", -0.5)
    fig.suptitle(_across_title([r for r, _ in sel], "Fig. 3b: reversed branch, "
                                                    "−dσ/dγ = σ²/C(δz)"), fontsize=10)
    return fig


def _across_panel(ax, a: dict | None, ylabel: str, pred: float, loglog: bool = True):
    """value(dz) with error bars, the weighted power-law fit and the predicted slope."""
    if a is None:
        ax.text(0.5, 0.5, "needs runs at 2 or more δz", ha="center", transform=ax.transAxes)
        ax.set_xlabel(r"$\delta z = 2d - z$")
        ax.set_ylabel(ylabel)
        return
    dz, y, e, f = a["dz"], a["value"], a["err"], a["fit"]
    ax.errorbar(dz, y, yerr=np.where(np.isfinite(e), e, 0), fmt="o", color="C0", ms=5,
                capsize=3, label="runs")
    if np.isfinite(f["exponent"]):
        xs = np.geomspace(dz.min() / 1.2, dz.max() * 1.2, 20)
        ax.plot(xs, f["prefactor"] * xs ** f["exponent"], "-", color="C0", lw=1.5, alpha=0.7,
                label=f"fit: δz^({f['exponent']:.2f} ± {f['err']:.2f})")
        xm = math.sqrt(dz.min() * dz.max())
        _reference(ax, xm, f["prefactor"] * xm ** f["exponent"] * 1.3, pred,
                   math.sqrt(dz.max() / dz.min()) * 1.2, f"predicted slope {pred:+g}")
    if loglog:
        ax.set_xscale("log")
        ax.set_yscale("log")
        _plain_log_ticks(ax, dz)
    ax.set_xlabel(r"$\delta z = 2d - z$")
    ax.set_ylabel(ylabel)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)


def _plain_log_ticks(ax, x, y=None):
    """Log axes labelled at the data values (x, and y if given), plain numbers, no minor
    labels."""
    from matplotlib.ticker import FixedLocator, NullFormatter, NullLocator
    for axis, v in ((ax.xaxis, x), (ax.yaxis, y)):
        if v is None:
            continue
        v = np.asarray(v, float)
        v = np.unique([float(f"{t:.2g}") for t in v[np.isfinite(v) & (v > 0)]])
        axis.set_major_locator(FixedLocator(v))
        axis.set_major_formatter(lambda t, pos: f"{t:.3g}")
        axis.set_minor_locator(NullLocator())
        axis.set_minor_formatter(NullFormatter())


def fig4_omega_min_z(runs: list, fits: list, across: dict) -> Figure:
    """Fig. 4 across runs: omega_min(sigma), omega_min sqrt(sigma / dz) (collapse if
    C2 ~ sqrt(dz)), C2 against dz."""
    sel = [(r, f) for r, f in zip(runs, fits) if "omega_min" in f]
    if not sel:
        raise Skip("no run with omega_min (observables.omega_min_every = 0)")
    fig = _figure(17, 5.2)
    ax, ax2, ax3 = fig.subplots(1, 3)
    for (r, f), c in zip(sel, _run_colors(sel)):
        ts = r.ts
        w, s = np.asarray(ts["omega_min"], float), np.asarray(ts["sigma"], float)
        d = ts["direction"] if "direction" in ts else np.ones(w.size, int)
        ok = np.isfinite(w) & np.isfinite(s) & (w > 0) & (s > 0)
        for sgn, mk in ((1, "o"), (-1, "s")):
            m = ok & (d == sgn)
            lab = f"{_run_label(r)}: C₂ = {f['omega_min']['C2']:.4g}" if sgn > 0 else None
            ax.loglog(s[m], w[m], mk, ms=2.5, color=c, mfc="none" if sgn < 0 else c, label=lab)
            ax2.semilogx(s[m], w[m] * np.sqrt(s[m] / f["dz"]), mk, ms=2.5, color=c,
                         mfc="none" if sgn < 0 else c)
    allx = np.concatenate([np.asarray(r.ts["sigma"], float) for r, _ in sel])
    allx = allx[np.isfinite(allx) & (allx > 0)]
    if allx.size:
        C2m = np.nanmedian([f["omega_min"]["C2"] for _, f in sel])
        _reference(ax, math.sqrt(allx.min() * allx.max()),
                   C2m / (allx.min() * allx.max()) ** 0.25 * 2, -0.5,
                   math.sqrt(allx.max() / allx.min()), "reference slope −1/2")
    ax.set_ylabel(r"$\omega_{min}$ (dimensionless)")
    ax2.set_ylabel(r"$\omega_{min}\sqrt{\sigma}\,/\,\sqrt{\delta z}$")
    for a_ in (ax, ax2):
        a_.set_xlabel(_SIGMA)
        a_.grid(True, alpha=0.3)
        a_.axvline(C2_SIGMA_MIN, color="0.6", ls=":", lw=1)
    ax.legend(fontsize=7)
    ax.set_title("filled: forward, open: reversed", fontsize=10)
    ax2.set_title("collapse if C₂ ∝ √δz", fontsize=10)
    _across_panel(ax3, across.get("C2"), r"$C_2$ = median $\omega_{min}\sqrt{\sigma}$ "
                                         f"(σ ≥ {C2_SIGMA_MIN:g})", 0.5)
    fig.suptitle(_across_title([r for r, _ in sel], "Fig. 4: ω_min ≈ C₂(δz)/√σ"), fontsize=10)
    return fig


def fig5_dos_z(runs: list, fits: list, across: dict) -> Figure:
    """Fig. 5 across runs: D(omega) of every run (its first spectrum) with omega* marked and,
    inset, omega* against dz with its fit; D against omega / dz (gap edges align if
    omega* ~ dz)."""
    sel = [(r, f) for r, f in zip(runs, fits) if spectrum_instants(r)]
    if not sel:
        raise Skip("no run with a spectrum (model.spectrum = 'none')")
    fig = _figure(13.5, 5.4)
    ax, ax2 = fig.subplots(1, 2)
    for (r, f), c in zip(sel, _run_colors(sel)):
        a = spectrum_instants(r)[0]
        x, D = _dos_curve(a)
        ost = f.get("omega_star")
        lab = _run_label(r) + f", σ = {float(a.get('sigma', np.nan)):.3g}"
        if ost is not None and np.isfinite(ost["omega_star"]):
            lab += f": ω* = {ost['omega_star']:.4f} ± {ost['err']:.4f}"
            ax.axvline(ost["omega_star"], color=c, lw=0.8, ls=":")
        ax.loglog(x, D, "-", color=c, lw=1.2, marker=".", ms=3, label=lab)
        ax2.loglog(x / f["dz"], D, "-", color=c, lw=1.2, marker=".", ms=3)
    ax.set_xlabel(_OMEGA)
    ax.set_ylabel(r"$D(\omega)$ (normalised to 1)")
    ax.set_ylim(3e-3, 3.0)
    ax.legend(fontsize=7, loc="upper left")
    ax.set_title("first spectrum of each run (dotted: ω*, mean over the run's spectra)",
                 fontsize=10)
    ax2.set_xlabel(r"$\omega / \delta z$")
    ax2.set_ylabel(r"$D(\omega)$")
    ax2.set_title("gap edges align if ω* ∝ δz", fontsize=10)
    for a_ in (ax, ax2):
        a_.grid(True, alpha=0.3)
    a = across.get("omega_star")
    ins = ax.inset_axes([0.45, 0.1, 0.5, 0.38])
    _across_panel(ins, a, "ω*", 1.0)
    if a is not None:
        _plain_log_ticks(ins, a["dz"], a["value"])
    ins.tick_params(labelsize=7)
    ins.xaxis.label.set_fontsize(8)
    ins.yaxis.label.set_fontsize(8)
    if ins.get_legend() is not None:
        ins.legend(fontsize=6, loc="upper left")
    fig.suptitle(_across_title([r for r, _ in sel], "Fig. 5: density of states, gap ω* ∝ δz"),
                 fontsize=10)
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
    ("fig3a_sigma", {"network"}, fig3a_sigma),
    ("fig3b_reverse", {"network"}, fig3b_reverse),
    ("fig4_omega_min", {"network"}, fig4_omega_min),
    ("fig5_dos", {"network"}, fig5_dos),
    ("fig8_correlation", {"network"}, fig8_correlation),
    ("fig8_response", {"network"}, fig8_response),
]

# across several runs of one model: name, model, function(runs, fits, across fits)
ACROSS_FIGURES = [
    ("fig3a_sigma_z", "network", fig3a_sigma_z),
    ("fig3b_reverse_z", "network", fig3b_reverse_z),
    ("fig4_omega_min_z", "network", fig4_omega_min_z),
    ("fig5_dos_z", "network", fig5_dos_z),
]


def _suspension_across(fl: list) -> dict:
    from .plot_suspension import across_suspension, pooled_fits
    out = pooled_fits(fl)
    out.update(across_suspension(fl))
    out["model"] = "suspension"
    return out


def all_figures() -> list:
    """FIGURES and the suspension figures (parflow.plot_suspension imports this module, so
    its lists are joined here, when first needed)."""
    from .plot_suspension import FIGURES as SUSPENSION
    return FIGURES + SUSPENSION


def all_across_figures() -> list:
    from .plot_suspension import ACROSS_FIGURES as SUSPENSION
    return ACROSS_FIGURES + SUSPENSION


# ---------------------------------------------------------------------------------------
# Driver
# ---------------------------------------------------------------------------------------
@dataclass
class PlotResult:
    written: list            # paths
    skipped: list            # (figure name, reason)
    failed: list             # (figure name, "ExceptionType: message")
    fits: dict               # chain_fits() for a chain, network_fits() for a network


def default_outdir(path: str) -> str:
    stem = os.path.splitext(os.path.basename(path))[0]
    return os.path.join(os.path.dirname(os.path.abspath(path)), stem + "_plots")


def make_plots(path: str, outdir: str | None = None, fmt: str = "png",
               only: list[str] | None = None, run: Run | None = None) -> PlotResult:
    """Draw every figure the run file supports (``run``: the file already loaded).
    Raises :class:`RunFileError`."""
    run = run if run is not None else load_run(path)
    outdir = outdir or default_outdir(path)
    res = PlotResult([], [], [], {})
    try:
        fits = _fits(run)
    except Exception as exc:  # the figures that need no fit are still drawn
        fits = {}
        res.failed.append(("fits", f"{type(exc).__name__}: {exc}"))
    res.fits = fits
    if not run.ts or not len(next(iter(run.ts.values()))):
        for name, _, _ in all_figures():
            if not only or name in only:
                res.skipped.append((name, "no rows in /timeseries"))
        return res
    for name, models, func in all_figures():
        if only and name not in only:
            continue
        if models is not None and run.model not in models:
            res.skipped.append((name, f"model is {run.model!r}, not {'/'.join(sorted(models))}"))
            continue
        _draw(res, name, lambda: func(run, fits), outdir, fmt)
    return res


def _draw(res: PlotResult, name: str, draw, outdir: str, fmt: str) -> None:
    """Draw one figure into ``res``: written, skipped (:class:`Skip`) or failed (any other
    exception: a bad figure must not cost the others)."""
    try:
        fig = draw()
    except Skip as exc:
        res.skipped.append((name, str(exc)))
        return
    except Exception as exc:
        res.failed.append((name, f"{type(exc).__name__}: {exc}"))
        return
    res.written.append(_save(fig, outdir, name, fmt))


def _fits(run: Run) -> dict:
    if run.model == "chain":
        return chain_fits(run)
    if run.model == "network":
        return network_fits(run)
    if run.model == "suspension":
        from .plot_suspension import suspension_fits
        return suspension_fits(run)
    return {}


def _save(fig: Figure, outdir: str, name: str, fmt: str) -> str:
    os.makedirs(outdir, exist_ok=True)
    out = os.path.join(outdir, f"{name}.{fmt}")
    fig.savefig(out, format=fmt)
    return out


def default_across_outdir(paths: list[str]) -> str:
    return os.path.join(os.path.dirname(os.path.abspath(paths[0])), "across_runs_plots")


def make_across_plots(paths: list[str], outdir: str | None = None, fmt: str = "png",
                      only: list[str] | None = None, runs: list | None = None) -> PlotResult:
    """The figures that compare several runs (e.g. Fig. 3-5 across z), drawn from the runs
    of the model each figure is for.  ``fits`` of the result: dict(runs=[per-run fits],
    across=across_fits).  Raises :class:`RunFileError`."""
    runs = runs if runs is not None else [load_run(p) for p in paths]
    outdir = outdir or default_across_outdir(paths)
    res = PlotResult([], [], [], {})
    cache: dict = {}
    for name, model, func in all_across_figures():
        if only and name not in only:
            continue
        sel = [r for r in runs if r.model == model and r.ts and len(next(iter(r.ts.values())))]
        if model == "network":
            sel.sort(key=lambda r: (_z_key(r), str(_seed(r))))
        if len(sel) < 2:
            res.skipped.append((name, f"needs 2 or more {model} runs with rows in /timeseries "
                                      f"(got {len(sel)})"))
            continue
        if model not in cache:
            fl = [_fits(r) for r in sel]
            cache[model] = (fl, across_fits(fl) if model == "network" else
                            _suspension_across(fl) if model == "suspension" else {})
            res.fits = dict(runs=fl, across=cache[model][1])
        fl, ac = cache[model]
        _draw(res, name, lambda: func(sel, fl, ac), outdir, fmt)
    return res


def plot_file(path: str, outdir: str | None = None, fmt: str = "png",
              only: list[str] | None = None) -> list[str]:
    """Draw every figure the run file supports (or those named in ``only``); returns the
    paths written.  Raises :class:`RunFileError`."""
    return make_plots(path, outdir, fmt, only).written


def format_fits(fits: dict) -> list[str]:
    """Human-readable lines summarising :func:`chain_fits` or :func:`network_fits` (or the
    ``fits`` of :func:`make_across_plots`)."""
    if not fits:
        return []
    if fits.get("model") == "suspension":
        from .plot_suspension import format_suspension_fits
        return format_suspension_fits(fits)
    if fits.get("across", {}).get("model") == "suspension":
        from .plot_suspension import format_across_suspension
        return format_across_suspension(fits["across"])
    if fits.get("model") == "network":
        return format_network_fits(fits)
    if "across" in fits:
        return format_across_fits(fits["across"])
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


def _outdirs(paths: list[str], out: str | None) -> list[str | None]:
    """Where each file's own figures go: ``out`` for one file; ``out/<stem>`` for several
    (``<stem>-2``, ... if stems repeat); the default next to each file without ``out``."""
    if len(paths) == 1:
        return [out]
    if out is None:
        return [None] * len(paths)
    seen: dict = {}
    dirs = []
    for p in paths:
        stem = os.path.splitext(os.path.basename(p))[0]
        seen[stem] = seen.get(stem, 0) + 1
        dirs.append(os.path.join(out, stem if seen[stem] == 1 else f"{stem}-{seen[stem]}"))
    return dirs


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m parflow.plot",
        description="Draw the figures parflow run files support: each file's own figures, "
                    "and with several files the figures across runs (e.g. Figs. 3-5 across z).")
    ap.add_argument("files", nargs="+", metavar="FILE", help="parflow run file(s) (HDF5)")
    ap.add_argument("--out", "--outdir", dest="out", metavar="DIR", default=None,
                    help="output folder (default: <FILE stem>_plots next to FILE).  With "
                         "several files: each file's figures in DIR/<FILE stem>/, the figures "
                         "across runs in DIR (default: across_runs_plots next to the first "
                         "file)")
    ap.add_argument("--format", default="png", choices=("png", "pdf", "svg"),
                    help="image format (default png)")
    ap.add_argument("--only", metavar="NAME", action="append",
                    choices=[n for n, _, _ in all_figures()] + [n for n, _, _ in all_across_figures()],
                    help="draw only this figure (repeatable)")
    args = ap.parse_args(argv)
    try:
        runs = [load_run(p) for p in args.files]
    except RunFileError as exc:
        print(f"parflow.plot: error: {exc}", file=sys.stderr)
        return 2
    several = len(args.files) > 1
    results = []
    try:
        for path, run, od in zip(args.files, runs, _outdirs(args.files, args.out)):
            results.append((path, make_plots(path, od, args.format, args.only, run=run)))
        if several:
            results.append((None, make_across_plots(args.files, args.out, args.format,
                                                    args.only, runs=runs)))
    except OSError as exc:                      # the output folder cannot be written
        where = exc.filename or args.out or default_outdir(args.files[0])
        print(f"parflow.plot: error: cannot write {where}: {exc.strerror or exc}",
              file=sys.stderr)
        return 2
    failed = False
    for path, res in results:
        for p in res.written:
            print(p)
        where = "" if not several else (f" ({path})" if path else " (across runs)")
        for name, why in res.skipped:
            print(f"parflow.plot: skipped {name}{where}: {why}", file=sys.stderr)
        for name, why in res.failed:
            print(f"parflow.plot: FAILED {name}{where}: {why}", file=sys.stderr)
        for line in format_fits(res.fits):
            print(f"parflow.plot: {line}", file=sys.stderr)
        failed |= bool(res.failed)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
