"""parflow.plot and parflow.post on a small synthetic run file written directly with h5py
(no solver, no MPI: under mpirun every rank runs these in its own tmp_path)."""

import ast
import os
import subprocess
import sys

import h5py
import numpy as np
import pytest

from parflow import plot
from parflow.plot import base as plot_base
from parflow.plot import chain as plot_chain
from parflow.plot import common as plot_common
from parflow.post import chain as post_chain
from parflow.post import fits as post_fits
from parflow.post import network as post_network
from parflow.post import report as post_report
from parflow.post import suspension as post_suspension
from hang_guard import guard

PNG = b"\x89PNG\r\n\x1a\n"
ALL = ["chain_forward", "chain_reverse", "chain_correlation", "chain_lengths",
       "chain_response", "stress_strain", "step_diagnostics", "omega_min"]

GC = 5e-3          # true jamming strain of the synthetic forward branch
N = 64


def _synthetic(path, *, analysis=True, reverse=True, omega=True, model="chain",
               gamma_c_attr=GC, noise=0.0, seed=0, mu=0, p=3.0):
    """A chain-like run: forward V2 = A x^-p, dtheta2 = B x^3, thetadot2 = C/x with
    x = GC - gamma (4 decades), then reverse V2 = a / (gamma_turn + x0 - gamma)."""
    rng = np.random.default_rng(seed)
    x = np.geomspace(GC, GC * 1e-4, 160)
    g_f = GC - x
    V2_f = 1e-5 * x ** -p
    dth_f = 1e3 * x ** 3.0
    thd_f = 2.0 / x
    g_turn = g_f[-1]
    V2_turn = V2_f[-1]
    a = 1.0
    x0 = a / V2_turn
    if reverse:
        xr = np.geomspace(x0 / 10, 1e-2, 80)
        g_r = g_turn - xr
        V2_r = a / (xr + x0)
        dth_r = 1e-3 * xr
        thd_r = 1.0 / (xr + x0)
    else:
        g_r = V2_r = dth_r = thd_r = np.array([])
    gamma = np.r_[g_f, g_r]
    V2 = np.r_[V2_f, V2_r] * (1 + noise * rng.standard_normal(gamma.size))
    n = gamma.size
    nf = g_f.size
    direction = np.r_[np.ones(nf, int), -np.ones(n - nf, int)]
    dgamma = np.r_[0.0, np.diff(gamma)]
    sigma = V2 * N / (N * N)
    ts = dict(step=np.arange(n), gamma=gamma, strain=np.cumsum(np.abs(dgamma)),
              leg=(direction < 0).astype(int), direction=direction, dgamma=dgamma,
              err=np.full(n, 0.03), rejected=(np.arange(n) % 17 == 3).astype(int),
              sigma=sigma, sigma_tb=sigma, sigma_mismatch=1e-14 * V2, pressure=-sigma / 2,
              V2=V2, length_error=np.full(n, 1e-13), proj_iter=np.ones(n, int),
              residual=1e-16 * V2, backward_error=np.full(n, 4e-17),
              refinements=np.zeros(n, int), wall=np.linspace(0, 1, n),
              omega_min=np.where(np.arange(n) % 10 == 0, 0.3 / np.sqrt(sigma), np.nan)
              if omega else np.full(n, np.nan),
              dtheta2=np.r_[dth_f, dth_r], thetadot2=np.r_[thd_f, thd_r])
    with h5py.File(path, "w") as f:
        f.attrs["format"] = "parflow-run-1"
        f.attrs["model"] = model
        f.attrs["scene"] = (f'title = "synthetic"\n[model]\nname = "{model}"\nN = {N}\nmu = {mu}\n'
                            '[[protocol.leg]]\ndirection = "forward"\n')
        f.attrs["status"] = "complete"
        f.attrs["n_ranks"] = 1
        f.create_dataset("initial/s", data=np.zeros((N, 2)))
        f.create_dataset("checkpoint/s", data=np.zeros((N, 2)))
        m = f.create_group("model")
        m.attrs.update(dict(gamma_c=gamma_c_attr, Lx0=N * np.exp(-gamma_c_attr),
                            eps2_over_2=GC, dtheta2_0=dth_f[0]))
        t = f.create_group("timeseries")
        for k, v in ts.items():
            t.create_dataset(k, data=v, maxshape=(None,))
        if analysis:
            k = np.arange(N // 2 + 1)
            rows = list(range(0, nf, 30)) + [nf - 1] + ([nf + 20, n - 1] if reverse else [])
            for r in rows:
                l_corr = 0.5 + 2e-3 / (GC - gamma[r]) if r < nf else 0.5
                l_r = ts["dtheta2"][r] ** -0.5
                grp = f.create_group(f"analysis/{r:08d}")
                grp.create_dataset("C_n", data=np.exp(-(k / l_corr) ** 2)
                                   * np.cos(np.pi * k * (r >= nf)))
                grp.create_dataset("tau_response", data=np.exp(-k / l_r))
                grp.attrs.update(dict(step=r, gamma=gamma[r], V2=V2[r], sigma=sigma[r],
                                      dtheta2=ts["dtheta2"][r], thetadot2=ts["thetadot2"][r],
                                      l_corr=l_corr, l_r=l_r))
    return dict(g_turn=g_turn, x0=x0)


def _is_png(p):
    with open(p, "rb") as fh:
        head = fh.read(8)
    return head == PNG and os.path.getsize(p) > 2000


def test_plot_file_writes_every_figure(tmp_path):
    src = tmp_path / "run.h5"
    _synthetic(src)
    out = tmp_path / "figs"
    paths = plot.plot_file(str(src), str(out))
    assert [os.path.basename(p) for p in paths] == [f"{n}.png" for n in ALL]
    for p in paths:
        assert os.path.dirname(p) == str(out)
        assert _is_png(p), p


def test_fit_power_law_recovers_exponent():
    rng = np.random.default_rng(1)
    x = np.geomspace(1e-6, 1e-2, 400)
    y = 3e-4 * x ** -3.0 * np.exp(0.1 * rng.standard_normal(x.size))
    p, A = post_fits.fit_power_law(x, y)
    assert abs(p + 3) < 0.05
    assert abs(np.log(A / 3e-4)) < 0.5
    # binned, and restricted to a window
    p2, _ = post_fits.fit_power_law(x, y, xmin=1e-5, xmax=1e-3, per_decade=8)
    assert abs(p2 + 3) < 0.05
    assert np.isnan(post_fits.fit_power_law([1, 2], [1, 2])[0])      # too few points


def test_chain_fits_on_synthetic_run(tmp_path):
    src = tmp_path / "run.h5"
    truth = _synthetic(src, noise=0.02)
    fits = post_chain.chain_fits(plot.load_run(str(src)))
    assert fits["gamma_c"]["attr"] == pytest.approx(GC)
    assert fits["gamma_c"]["fit"] == pytest.approx(GC, rel=1e-3)
    fw = fits["forward"]["fit"]
    assert abs(fw["V2"][0] + 3) < 0.05
    assert abs(fw["dtheta2"][0] - 3) < 0.05
    assert abs(fw["thetadot2"][0] + 1) < 0.05
    assert fits["gamma_turn"] == pytest.approx(truth["g_turn"], abs=1e-15)
    rev = fits["reverse"]
    assert rev["gamma_c_tilde"] == pytest.approx(truth["g_turn"] + truth["x0"], rel=1e-9,
                                                 abs=truth["x0"] * 0.05)
    assert abs(rev["tilde"]["V2"][0] + 1) < 0.05
    assert abs(fits["lengths"]["dtheta2^-1/2"][0] + 1.5) < 0.05
    assert post_report.format_fits(fits)                        # the CLI's summary lines


def test_a_fitted_gamma_c_the_run_went_past_is_dropped(tmp_path):
    """gamma_c fitted by linearising with the mean-field exponent (-5/3 for mu = 2) lands
    before the end of a forward branch that diverges faster (here x^-4, as the mu = 2 chains
    at N = 1e5 do): the run went past it, so it is no divergence point and not reported (a
    sample's fit on such a gamma_c once gave an exponent of -0.002 on a 2e-8 window)."""
    src = tmp_path / "run.h5"
    _synthetic(src, mu=2, p=4.0, reverse=False)
    run = plot.load_run(str(src))
    g = run.ts["gamma"][run.ts["direction"] > 0]
    assert post_fits.fit_divergence_point(g, run.ts["V2"][run.ts["direction"] > 0], -5 / 3) < g.max()
    fits = post_chain.chain_fits(run)
    assert "fit" not in fits["gamma_c"] and list(fits["forward"]) == ["attr"]
    assert abs(fits["forward"]["attr"]["V2"][0] + 4) < 0.05


def test_main_default_outdir_and_skips(tmp_path, capsys):
    """A model with no figures of its own, without omega_min: only the generic figures,
    into FILE-stem_plots."""
    src = tmp_path / "susp.h5"
    _synthetic(src, model="suspension", analysis=False, omega=False)
    assert plot.main([str(src)]) == 0
    out, err = capsys.readouterr()
    folder = tmp_path / "susp_plots"
    written = out.split()
    assert written == [str(folder / f"{n}.png") for n in ("stress_strain", "step_diagnostics")]
    assert all(_is_png(p) for p in written)
    for name in ALL:
        if name.startswith("chain_"):
            assert f"skipped {name}: model is 'suspension', not chain" in err
    assert "skipped fig5_dos: model is 'suspension', not network" in err
    assert "skipped omega_min: omega_min was not computed" in err


def test_chain_figures_skip_without_their_data(tmp_path):
    src = tmp_path / "bare.h5"
    _synthetic(src, analysis=False, reverse=False, omega=False)
    run = plot.load_run(str(src))
    fits = post_chain.chain_fits(run)
    assert "reverse" not in fits and "lengths" not in fits
    for func in (plot_chain.fig_chain_reverse, plot_chain.fig_chain_correlation,
                 plot_chain.fig_chain_lengths, plot_chain.fig_chain_response,
                 plot_common.fig_omega_min):
        with pytest.raises(plot.Skip):
            func(run, fits)
    res = plot.make_plots(str(src), str(tmp_path / "o"), only=["chain_lengths", "omega_min"])
    assert res.written == [] and not res.failed
    assert [n for n, _ in res.skipped] == ["chain_lengths", "omega_min"]
    assert "analysis" in res.skipped[0][1]


def _one_line_error(capsys, argv):
    rc = plot.main(argv)
    out, err = capsys.readouterr()
    assert rc == 2
    assert out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    return lines[0]


def test_not_a_parflow_file(tmp_path, capsys):
    src = tmp_path / "other.h5"
    with h5py.File(src, "w") as f:
        f.create_dataset("x", data=np.arange(3))
        f.attrs["format"] = "something-else"
    msg = _one_line_error(capsys, [str(src), "--out", str(tmp_path / "o")])
    assert "not a parflow run file" in msg
    assert not (tmp_path / "o").exists()
    txt = tmp_path / "notes.h5"
    txt.write_text("hello\n")
    assert "not a parflow run file" in _one_line_error(capsys, [str(txt)])


def test_missing_file(tmp_path, capsys):
    msg = _one_line_error(capsys, [str(tmp_path / "nope.h5")])
    assert "nope.h5" in msg and "no such file" in msg
    with pytest.raises(plot.RunFileError):
        plot.plot_file(str(tmp_path / "nope.h5"))


def test_module_entry_point_without_petsc(tmp_path):
    """``python -m parflow.plot`` exits 2 on a missing file, and never imports PETSc/MPI
    (nor pyplot)."""
    code = (
        "import runpy, sys\n"
        f"sys.argv = ['parflow.plot', {str(tmp_path / 'nope.h5')!r}]\n"
        "try:\n"
        "    runpy.run_module('parflow.plot', run_name='__main__', alter_sys=True)\n"
        "    code = 0\n"
        "except SystemExit as exc:\n"
        "    code = exc.code\n"
        "bad = [m for m in ('petsc4py', 'slepc4py', 'mpi4py', 'matplotlib.pyplot')\n"
        "       if m in sys.modules]\n"
        "print('exit', code, 'imported', bad)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=guard(120))
    assert r.stdout.strip() == "exit 2 imported []", r.stdout + r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "no such file" in r.stderr


# ---------------------------------------------------------------------------------------
# Networks (paper Figs. 3, 4, 5, 8)
# ---------------------------------------------------------------------------------------
NET_FIGS = ["fig3a_sigma", "fig3b_reverse", "fig4_omega_min", "fig5_dos", "fig8_correlation",
            "fig8_response"]
ACROSS = ["fig3a_sigma_z", "fig3b_reverse_z", "fig4_omega_min_z", "fig5_dos_z"]
SIGMA_TURN = 1e6


def _gap_spectrum(omega_star, nc=3000, Dp=0.4, rng=None):
    """Nc frequencies with D = Dp above a sharp gap omega_star, 0 below: evenly spaced
    quantiles (rng None) or random draws."""
    u = (np.arange(nc) + 0.5) / nc if rng is None else np.sort(rng.random(nc))
    return omega_star + u / Dp


def _network_synthetic(path, *, z=3.8, C=0.035, C2=0.13, omega_star=0.04, lr_k=2.5, B0=0.2,
                       analysis=True, spectrum="dense", omega=True, reverse=True, seed=1):
    """A network-like run: forward sigma 5 -> 1e6, then the exact reversed law
    1/sigma = 1/sigma_turn + x/C (x: strain since the reversal) down to sigma = 10;
    omega_min = C2/sqrt(sigma) every other row; analysis instants with a sharp-gap spectrum
    (omega*), C(r), and a point response A e^(-r/l_c) + B e^(-r/l_r) with l_r = lr_k
    sqrt(sigma), B = B0/sqrt(sigma) (V sqrt(sigma) collapses exactly in the tail)."""
    dz = 4.0 - z
    nf = 120
    s_f = np.geomspace(5.0, SIGMA_TURN, nf)
    g_f = np.linspace(0.0, 0.08, nf)
    if reverse:
        x_end = C * (1 / 10.0 - 1 / SIGMA_TURN)
        x = np.r_[np.geomspace(1e-9, x_end, 150)]
        s_r = 1.0 / (1.0 / SIGMA_TURN + x / C)
        g_r = g_f[-1] - x
    else:
        x = s_r = g_r = np.array([])
    gamma, sigma = np.r_[g_f, g_r], np.r_[s_f, s_r]
    n = gamma.size
    direction = np.r_[np.ones(nf, int), -np.ones(n - nf, int)]
    strain = np.r_[g_f, g_f[-1] + x]
    dgamma = np.r_[0.0, np.diff(gamma)]
    wmin = np.where(np.arange(n) % 2 == 0, C2 / np.sqrt(sigma), np.nan) if omega \
        else np.full(n, np.nan)
    ts = dict(step=np.arange(n), gamma=gamma, strain=strain, leg=(direction < 0).astype(int),
              direction=direction, dgamma=dgamma, err=np.full(n, 0.03),
              rejected=np.zeros(n, int), sigma=sigma, sigma_tb=sigma,
              sigma_mismatch=1e-14 * sigma, pressure=sigma / 3, V2=sigma, omega_min=wmin,
              length_error=np.full(n, 1e-13), z=np.full(n, z))
    with h5py.File(path, "w") as f:
        f.attrs["format"] = "parflow-run-1"
        f.attrs["model"] = "network"
        f.attrs["scene"] = (f'seed = {seed}\n[model]\nname = "network"\nN = 256\nz = {z}\n'
                            f'spectrum = "{spectrum}"\n')
        f.attrs["status"] = "complete"
        m = f.create_group("model")
        m.attrs.update(dict(z=z, dz=dz, n_nodes=250, network_seed=seed))
        t = f.create_group("timeseries")
        for k, v in ts.items():
            t.create_dataset(k, data=v, maxshape=(None,))
        if analysis:
            r = (np.arange(80) + 0.5) * 0.5
            for row in sorted({0, 40, 80, nf - 1, min(nf + 60, n - 1), n - 1}):
                sg = sigma[row]
                lc, lr, A, B = 2.0, lr_k * np.sqrt(sg), 0.5, B0 / np.sqrt(sg)
                grp = f.create_group(f"analysis/{row:08d}")
                grp.create_dataset("resp_r", data=r)
                grp.create_dataset("resp_V", data=A * np.exp(-r / lc) + B * np.exp(-r / lr))
                grp.create_dataset("resp_counts_V", data=np.full(r.size, 30.0))
                grp.create_dataset("corr_r", data=r)
                grp.create_dataset("corr_C", data=np.exp(-r / lc) + 0.05 * np.exp(-r / lr))
                grp.create_dataset("corr_counts", data=np.full(r.size, 1e3))
                if spectrum == "dense":
                    grp.create_dataset("omega", data=_gap_spectrum(omega_star))
                elif spectrum == "low":
                    grp.create_dataset("omega_low", data=np.geomspace(1e-3, 1e-2, 10))
                grp.attrs.update(dict(step=row, gamma=gamma[row], sigma=sg, resp_l_c=lc,
                                      resp_l_r=lr, resp_A=A, resp_B=B, VV=1.0))
    return dict(dz=dz)


def test_network_figures_and_fits_on_synthetic_run(tmp_path):
    src = tmp_path / "net.h5"
    _network_synthetic(src, C=0.035, C2=0.13, omega_star=0.04)
    res = plot.make_plots(str(src), str(tmp_path / "o"))
    assert not res.failed, res.failed
    names = [os.path.splitext(os.path.basename(p))[0] for p in res.written]
    assert names == ["stress_strain", "step_diagnostics", "omega_min"] + NET_FIGS
    assert all(_is_png(p) for p in res.written)
    f = res.fits
    # Fig. 3b: the exact law 1/sigma = 1/sigma_turn + x/C gives slope 2 and C
    rv = f["reverse"]
    assert rv["n"] > 10
    assert rv["slope"] == pytest.approx(2.0, abs=1e-6)
    assert rv["C"] == pytest.approx(0.035, rel=1e-6)
    # Fig. 4: omega_min = C2 / sqrt(sigma)
    om = f["omega_min"]
    assert om["forward"][0] == pytest.approx(-0.5, abs=1e-9)
    assert om["reverse"][0] == pytest.approx(-0.5, abs=1e-9)
    assert om["C2"] == pytest.approx(0.13, rel=1e-9)
    # Fig. 5: the sharp gap, to within the spacing of the modes (1/(Nc D_p))
    ost = f["omega_star"]
    assert len(ost["instants"]) == 6
    assert ost["omega_star"] == pytest.approx(0.04, abs=2 / (3000 * 0.4))
    # Fig. 8: l_r = 2.5 sqrt(sigma), B sqrt(sigma) = 0.2 on the resolved instants
    resp = f["response"]
    res_inst = [x for x in resp["instants"] if x["resolved"]]
    assert 2 <= len(res_inst) < 6              # l_r beyond r_max / 2 at large sigma
    assert resp["l_r_vs_sigma"]["exponent"] == pytest.approx(0.5, abs=1e-9)
    assert all(x["lr_over_sqrt_sigma"] == pytest.approx(2.5) for x in res_inst)
    assert all(x["B_sqrt_sigma"] == pytest.approx(0.2) for x in res_inst)
    assert post_report.format_fits(f)


def test_fit_omega_star_sharp_and_scaled_gaps():
    """Exact for a sharp gap (any fraction); proportional to the gap for a smooth edge."""
    for ws in (0.01, 0.05, 0.12):
        w = _gap_spectrum(ws, nc=4000)
        for frac in (0.3, 0.5, 0.7):
            r = post_network.fit_omega_star(w, fraction=frac, n_boot=0)
            assert r["omega_star"] == pytest.approx(ws, abs=1.5 / (4000 * 0.4)), (ws, frac)
            assert r["D_plateau"] == pytest.approx(0.4, rel=0.01)
    # smooth edge D = Dp * min(1, (omega/wg)^2) below a flat plateau: omega* is proportional
    # to wg (inverse CDF sampling, evenly spaced quantiles)
    def smooth(wg, nc=20000, Dp=0.4):
        u = (np.arange(nc) + 0.5) / nc          # F(w) = Dp w^3 / (3 wg^2) below wg
        Fg = Dp * wg / 3
        return np.where(u < Fg, (3 * u * wg ** 2 / Dp) ** (1 / 3), wg + (u - Fg) / Dp)
    a = post_network.fit_omega_star(smooth(0.02), n_boot=0)["omega_star"]
    b = post_network.fit_omega_star(smooth(0.06), n_boot=0)["omega_star"]
    assert b / a == pytest.approx(3.0, rel=0.01)
    assert 0.02 * 2 / 3 * 0.9 < a < 0.02     # the "missing modes" of the edge: (2/3) wg
    # no plateau above the gap (gap too wide for the window): NaN, not a wrong number
    assert np.isnan(post_network.fit_omega_star(_gap_spectrum(0.5), n_boot=0)["omega_star"])
    assert np.isnan(post_network.fit_omega_star([0.1, 0.2])["omega_star"])


def test_fit_omega_star_exponent_on_random_spectra():
    """omega* = 0.15 (dz/0.4)^b on random spectra (Nc = 10^4 uniform draws above the gap) at five
    dz: the fit recovers b within its error, for b = 1 and b = 1.5, and the bootstrap error
    is of the right size."""
    rng = np.random.default_rng(3)
    dz = np.array([0.05, 0.1, 0.2, 0.3, 0.4])
    for b in (1.0, 1.5):
        vals, errs = [], []
        for d in dz:
            r = post_network.fit_omega_star(_gap_spectrum(0.15 * (d / 0.4) ** b, nc=10_000, rng=rng),
                                    n_boot=100, seed=1)
            vals.append(r["omega_star"])
            errs.append(r["err"])
        vals, errs = np.array(vals), np.array(errs)
        assert np.all(errs > 0) and np.all(errs < 0.5 * vals)
        assert np.all(np.abs(vals - 0.15 * (dz / 0.4) ** b) < 4 * errs)
        fit = post_fits.fit_power_law_err(dz, vals, errs)
        assert fit["n"] == 5 and fit["dof"] == 3
        assert 0 < fit["err"] < 0.1
        assert abs(fit["exponent"] - b) < 3 * fit["err"]


def test_fit_power_law_err():
    x = np.array([0.1, 0.2, 0.3, 0.4])
    y = 2.0 * x ** -0.5
    f = post_fits.fit_power_law_err(x, y, 0.01 * y)
    assert f["exponent"] == pytest.approx(-0.5, abs=1e-12)
    assert f["prefactor"] == pytest.approx(2.0)
    assert f["err"] > 0 and f["chi2"] == pytest.approx(0, abs=1e-12)
    # scatter larger than the error bars: the error grows with sqrt(chi2/dof)
    y2 = y * np.array([1.1, 0.9, 1.1, 0.9])
    small = post_fits.fit_power_law_err(x, y2, 0.001 * y2)
    large = post_fits.fit_power_law_err(x, y2, 0.1 * y2)
    assert small["err"] == pytest.approx(large["err"], rel=1e-6)   # Birge-scaled below
    assert np.isnan(post_fits.fit_power_law_err([1.0], [1.0])["exponent"])
    assert np.isnan(post_fits.fit_power_law_err([1.0, 2.0], [1.0, 2.0])["err"])   # no dof


def test_across_runs_figures_and_exponents(tmp_path, capsys):
    """Three runs at dz = 0.1, 0.2, 0.4 with C = 0.016 dz^-1/2, C2 = 0.3 dz^1/2,
    omega* = 0.2 dz: the across-run figures, and the fitted exponents."""
    paths = []
    for z in (3.6, 3.8, 3.9):
        dz = 4.0 - z
        p = tmp_path / f"net_z{z}.h5"
        _network_synthetic(p, z=z, C=0.016 * dz ** -0.5, C2=0.3 * dz ** 0.5,
                           omega_star=0.2 * dz)
        paths.append(str(p))
    out = tmp_path / "figs"
    only = [a for n in ACROSS + ["fig3a_sigma"] for a in ("--only", n)]
    assert plot.main(paths + ["--outdir", str(out)] + only) == 0
    o, err = capsys.readouterr()
    written = o.split()
    for name in ACROSS:
        assert str(out / f"{name}.png") in written
    for p in paths:                                   # each file's own figures in out/<stem>/
        stem = os.path.splitext(os.path.basename(p))[0]
        assert str(out / stem / "fig3a_sigma.png") in written
    assert all(_is_png(p) for p in written)
    assert "across runs: omega* ~ dz^b" in err
    runs = [plot.load_run(p) for p in paths]
    ac = post_network.across_fits([post_network.network_fits(r) for r in runs])
    assert ac["C"]["fit"]["exponent"] == pytest.approx(-0.5, abs=1e-6)
    assert ac["C2"]["fit"]["exponent"] == pytest.approx(0.5, abs=1e-6)
    assert ac["omega_star"]["fit"]["exponent"] == pytest.approx(1.0, abs=0.02)
    # one run only: the across-run figures are skipped with the reason
    res = plot.make_across_plots(paths[:1], str(tmp_path / "one"))
    assert res.written == [] and not res.failed
    assert all("needs 2 or more network runs" in why for name, why in res.skipped
               if name in {s.name for s in plot.ACROSS_FIGURES if s.models == {"network"}})


def test_network_run_without_analyses_skips_figures(tmp_path, capsys):
    """No analysis groups and no omega_min: Figs. 4, 5, 8 are skipped with a message, the
    others drawn; a 'low' spectrum says why there is no D(omega)."""
    src = tmp_path / "bare.h5"
    _network_synthetic(src, analysis=False, omega=False)
    only = [a for n in NET_FIGS for a in ("--only", n)]
    assert plot.main([str(src), "--out", str(tmp_path / "o")] + only) == 0
    out, err = capsys.readouterr()
    names = [os.path.splitext(os.path.basename(p))[0] for p in out.split()]
    assert names == ["fig3a_sigma", "fig3b_reverse"]
    assert "skipped fig4_omega_min: omega_min was not computed" in err
    assert "skipped fig5_dos: no analysis groups with a spectrum" in err
    assert "skipped fig8_correlation: no analysis groups with corr_C" in err
    assert "skipped fig8_response: no analysis groups with the point response" in err
    low = tmp_path / "low.h5"
    _network_synthetic(low, spectrum="low", reverse=False, omega=False)
    res = plot.make_plots(str(low), str(tmp_path / "o2"), only=NET_FIGS)
    assert not res.failed
    why = dict(res.skipped)
    assert "model.spectrum = 'low'" in why["fig5_dos"]
    assert "no reversed branch" in why["fig3b_reverse"]
    # across runs with neither spectra nor omega_min: those figures skip, the rest draw
    res = plot.make_across_plots([str(src), str(low)], str(tmp_path / "o3"))
    assert not res.failed
    assert [os.path.basename(p) for p in res.written] == ["fig3a_sigma_z.png",
                                                           "fig3b_reverse_z.png"]
    net_skipped = {n for n, _ in res.skipped if n in ACROSS}
    assert net_skipped == {"fig4_omega_min_z", "fig5_dos_z"}


def test_several_files_one_missing(tmp_path, capsys):
    src = tmp_path / "net.h5"
    _network_synthetic(src, analysis=False)
    msg = _one_line_error(capsys, [str(src), str(tmp_path / "nope.h5"), "--outdir",
                                   str(tmp_path / "o")])
    assert "nope.h5" in msg and "no such file" in msg
    assert not (tmp_path / "o").exists()


def test_tiny_network_run_draws_the_network_figures(mpi_tmp_path, comm, tmp_path):
    """A real run through the driver (N = 128, forward to sigma = 1e4 and back, dense
    spectrum, C(r), point response, omega_min): every network figure is drawn, none fails.
    Under MPI the ranks run it together, then each draws into its own folder."""
    from petsc4py import PETSc

    from parflow.run import Run, setup_logging
    from parflow.scene import load_scene
    path = str(mpi_tmp_path / "tiny_net.h5")
    scene = load_scene(f"""
seed = 7
[model]
name = "network"
N = 128
z = 3.8
spectrum = "dense"
[[protocol.leg]]
direction = "forward"
sigma_above = 1e4
[[protocol.leg]]
direction = "reverse"
sigma_below = 20
strain = 0.05
[observables]
omega_min_every = 2
analysis_quantity = "sigma"
analysis_per_decade = 1
[output]
path = "{path}"
""")
    setup_logging(PETSc.COMM_WORLD, quiet=True)
    assert Run(scene, PETSc.COMM_WORLD, path, quiet=True).execute() == "complete"
    comm.Barrier()
    res = plot.make_plots(path, str(tmp_path / "figs"), only=NET_FIGS)
    assert not res.failed, res.failed
    names = [os.path.splitext(os.path.basename(p))[0] for p in res.written]
    assert names == NET_FIGS
    assert all(_is_png(p) for p in res.written)
    f = res.fits
    assert f["omega_min"]["n"] > 0 and np.isfinite(f["omega_min"]["C2"])
    assert len(f["omega_star"]["instants"]) >= 4
    assert f["reverse"]["branch"]["sigma"].size > 3
    comm.Barrier()


def test_suspension_compressed_while_flowing_plots_phi(mpi_tmp_path, comm, tmp_path):
    """A suspension compressed while it flows (N = 64, 0.78 -> 0.79): the stress-strain figure
    draws phi beside sigma, the fig6a title says phi -> compress_to, the fits take the
    window's phi."""
    from parflow.scene import load_scene
    from systems import run_scene
    path = str(mpi_tmp_path / "compressing.h5")
    scene = load_scene(f"""
seed = 3
[model]
name = "suspension"
N = 64
phi = 0.78
compress_rate = 0.5
compress_to = 0.79
[[protocol.leg]]
direction = "forward"
strain = 0.04
[output]
path = "{path}"
""")
    assert run_scene(scene) == "complete"
    comm.Barrier()
    res = plot.make_plots(path, str(tmp_path / "figs"), only=["stress_strain", "fig6a_sigma"])
    assert not res.failed, res.failed
    assert len(res.written) == 2 and all(_is_png(p) for p in res.written)
    fig = plot_common.fig_stress_strain(plot_base.load_run(path), {})
    assert any(ax.get_ylabel().startswith("φ") for ax in fig.axes)
    assert res.fits["phi"] == pytest.approx(0.79, abs=1e-12)      # the last half: at 0.79
    assert res.fits["phi_range"] == (pytest.approx(0.79, abs=1e-12), pytest.approx(0.79, abs=1e-12))
    comm.Barrier()


# ---------------------------------------------------------------------------------------
# Layers and the registry
# ---------------------------------------------------------------------------------------
PARFLOW = os.path.dirname(os.path.dirname(os.path.abspath(plot.__file__)))   # parflow/
# what post/ and plot/ must never import (the solver side of parflow, PETSc, SLEPc)
FORBIDDEN = ("parflow.models", "parflow.engines", "parflow.system", "parflow.algebra.solvers",
             "parflow.spectrum", "parflow.dynamics", "parflow.algebra", "petsc4py", "slepc4py")


def _imports(path: str, package: str) -> set:
    """Every module imported anywhere in the file (relative imports resolved; ``from . import
    x`` counts as module ``package.x``)."""
    out = set()
    for node in ast.walk(ast.parse(open(path).read(), path)):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                mod = f"{base}.{node.module}" if node.module else base
            else:
                mod = node.module
            out.add(mod)
            if not node.module:
                out.update(f"{mod}.{a.name}" for a in node.names)
    return out


def _package_imports(name: str) -> dict:
    folder = os.path.join(PARFLOW, name)
    files = sorted(f for f in os.listdir(folder) if f.endswith(".py"))
    assert files, folder
    return {f: _imports(os.path.join(folder, f), f"parflow.{name}") for f in files}


@pytest.mark.parametrize("package", ["post", "plot"])
def test_post_and_plot_never_import_the_solver_side(package):
    for f, mods in _package_imports(package).items():
        bad = sorted(m for m in mods if m.startswith(FORBIDDEN))
        assert not bad, f"parflow/{package}/{f} imports {bad}"


def test_post_imports_only_io_and_itself():
    """post sits on parflow.io and numpy: no other parflow module, no matplotlib, no plot."""
    for f, mods in _package_imports("post").items():
        ours = {m for m in mods if m == "parflow" or m.startswith("parflow.")}
        assert all(m == "parflow.io" or m.startswith("parflow.post") for m in ours), (f, ours)
        assert not any(m.startswith(("matplotlib", "h5py")) for m in mods), (f, mods)


def test_plot_imports_io_post_and_itself():
    """plot imports parflow.io, parflow.post and itself, nothing else of parflow."""
    for f, mods in _package_imports("plot").items():
        ours = {m for m in mods if m == "parflow" or m.startswith("parflow.")}
        allowed = {"parflow.io", "parflow.errors"}
        assert all(m in allowed or m.startswith(("parflow.post", "parflow.plot"))
                   for m in ours), (f, ours)


def test_registry_order_and_models():
    """The figures, in the order they are drawn, each registered beside its definition with
    the models it applies to; every model named has its fits registered."""
    susp = ["fig6a_sigma", "fig6b_relaxation", "fig6c_delta_gamma", "fig6d_omega_min",
            "fig6f_forces", "fig7a_correlation"]
    assert [s.name for s in plot.FIGURES] == ALL + NET_FIGS + susp
    assert [s.name for s in plot.ACROSS_FIGURES] == ACROSS + [
        "fig6b_relaxation_phi", "fig6c_delta_gamma_phi", "fig6d_omega_min_phi",
        "fig6e_sigma_dz", "fig7b_lengths"]
    assert {s.name for s in plot.FIGURES if s.models is None} == {
        "stress_strain", "step_diagnostics", "omega_min"}
    for s in plot.FIGURES + plot.ACROSS_FIGURES:
        assert s.models is None or s.models <= set(plot.MODELS), s
        assert s.draw.__module__.startswith("parflow.plot."), s
    assert all(len(s.models) == 1 for s in plot.ACROSS_FIGURES)
    with pytest.raises(ValueError, match="registered twice"):
        plot_base.figure("stress_strain")(lambda run, fits: None)
    with pytest.raises(ValueError, match="exactly one model"):
        plot_base.figure("x_across", across=True)
    assert len(plot.FIGURES) == len(ALL + NET_FIGS + susp)      # nothing was added


def test_model_tables(tmp_path):
    """Fits, titles and summary lines are looked up by the model: a model without an entry
    gets no fits, the generic title and no lines."""
    src = tmp_path / "other.h5"
    _synthetic(src, model="other", analysis=False)
    run = plot.load_run(str(src))
    assert plot.model_fits(run) == {}
    assert plot_base.title(run, "x") == "x — other.h5 (other, N=64)"
    assert post_report.format_fits({"model": "other", "a": 1}) == []
    assert post_report.format_fits({"model": "other", "runs": [], "across": {}}) == []
    res = plot.make_plots(str(src), str(tmp_path / "o"))
    assert [os.path.basename(p) for p in res.written] == ["stress_strain.png",
                                                          "step_diagnostics.png",
                                                          "omega_min.png"]
    chain = plot.load_run(str(_synthetic_path(tmp_path)))
    assert plot_base.title(chain, "x") == "x — chain.h5 (chain, N=64, μ=0)"
    assert plot.model_fits(chain)["model"] == "chain"


def _synthetic_path(tmp_path):
    p = tmp_path / "chain.h5"
    _synthetic(p)
    return p


def test_documented_api_is_re_exported():
    """parflow.plot keeps the fits it documents (their home is parflow.post)."""
    assert plot.fit_omega_star is post_network.fit_omega_star
    assert plot.network_fits is post_network.network_fits
    assert plot.across_fits is post_network.across_fits
    assert plot.chain_fits is post_chain.chain_fits
    assert plot.format_fits is post_report.format_fits
    for name in ("fit_power_law", "fit_power_law_err", "fit_divergence_point", "fit_window",
                 "typical_dgamma", "log_bin"):
        assert getattr(plot, name) is getattr(post_fits, name)


def test_suspension_relaxation_is_passed_in(tmp_path):
    """post.suspension.suspension_fits applies a collision-free relaxation fit (its own
    post.suspension.relaxation unless another is given, None for none)."""
    src = tmp_path / "susp.h5"
    _synthetic(src, model="suspension", analysis=False, omega=False, reverse=False)
    with h5py.File(src, "a") as f:
        n = f["timeseries/step"].shape[0]
        f.create_dataset("timeseries/n_coll", data=np.zeros(n, int))
    run = plot.load_run(str(src))
    seen = []

    def fake(gamma, dgamma, sigma, n_coll):
        seen.append(len(gamma))
        return dict(pairs=7, slope=2.0)
    assert post_suspension.suspension_fits(run, fake)["relaxation"] == dict(pairs=7, slope=2.0)
    assert seen and seen[0] == int(post_suspension.window_rows(run).sum())
    assert "relaxation" not in post_suspension.suspension_fits(run, None)
    rel = plot.model_fits(run)["relaxation"]
    assert rel["pairs"] == seen[0] - 1          # every step collision-free


def test_save_figure_writes_whole_or_nothing(tmp_path):
    """plot.base.save_figure: a figure is written under its name only when complete; a save
    that fails half-way leaves neither the file nor its twin, and an earlier file stays."""
    from parflow.plot.base import new_figure, save_figure
    fig = new_figure(2, 2)
    fig.add_subplot().plot([0, 1], [1, 0])
    path = str(tmp_path / "f.png")
    assert save_figure(fig, path) == path
    good = open(path, "rb").read()
    assert good[:8] == b"\x89PNG\r\n\x1a\n"

    def broken(target, **kw):
        with open(target, "wb") as fh:
            fh.write(b"\x89PNG half")
        raise OSError("disk full")

    fig.savefig = broken
    with pytest.raises(OSError, match="disk full"):
        save_figure(fig, path)
    assert open(path, "rb").read() == good
    assert os.listdir(tmp_path) == ["f.png"]
