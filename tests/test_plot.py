"""parflow.plot on a small synthetic run file written directly with h5py (no solver, no MPI:
under mpirun every rank runs these in its own tmp_path)."""

import os
import subprocess
import sys

import h5py
import numpy as np
import pytest

from parflow import plot

PNG = b"\x89PNG\r\n\x1a\n"
ALL = ["chain_forward", "chain_reverse", "chain_correlation", "chain_lengths",
       "chain_response", "stress_strain", "step_diagnostics", "omega_min"]

GC = 5e-3          # true jamming strain of the synthetic forward branch
N = 64


def _synthetic(path, *, analysis=True, reverse=True, omega=True, model="chain",
               gamma_c_attr=GC, noise=0.0, seed=0):
    """A chain-like run: forward V2 = A x^-3, dtheta2 = B x^3, thetadot2 = C/x with
    x = GC - gamma (4 decades), then reverse V2 = a / (gamma_turn + x0 - gamma)."""
    rng = np.random.default_rng(seed)
    x = np.geomspace(GC, GC * 1e-4, 160)
    g_f = GC - x
    V2_f = 1e-5 * x ** -3.0
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
        f.attrs["scene"] = (f'title = "synthetic"\n[model]\nname = "{model}"\nN = {N}\nmu = 0\n'
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
    p, A = plot.fit_power_law(x, y)
    assert abs(p + 3) < 0.05
    assert abs(np.log(A / 3e-4)) < 0.5
    # binned, and restricted to a window
    p2, _ = plot.fit_power_law(x, y, xmin=1e-5, xmax=1e-3, per_decade=8)
    assert abs(p2 + 3) < 0.05
    assert np.isnan(plot.fit_power_law([1, 2], [1, 2])[0])      # too few points


def test_chain_fits_on_synthetic_run(tmp_path):
    src = tmp_path / "run.h5"
    truth = _synthetic(src, noise=0.02)
    fits = plot.chain_fits(plot.load_run(str(src)))
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
    assert plot.format_fits(fits)                               # the CLI's summary lines


def test_main_default_outdir_and_skips(tmp_path, capsys):
    """A non-chain model without omega_min: only the generic figures, into FILE-stem_plots."""
    src = tmp_path / "net.h5"
    _synthetic(src, model="network", analysis=False, omega=False)
    assert plot.main([str(src)]) == 0
    out, err = capsys.readouterr()
    folder = tmp_path / "net_plots"
    written = out.split()
    assert written == [str(folder / f"{n}.png") for n in ("stress_strain", "step_diagnostics")]
    assert all(_is_png(p) for p in written)
    for name in ALL:
        if name.startswith("chain_"):
            assert f"skipped {name}: model is 'network'" in err
    assert "skipped omega_min: omega_min was not computed" in err


def test_chain_figures_skip_without_their_data(tmp_path):
    src = tmp_path / "bare.h5"
    _synthetic(src, analysis=False, reverse=False, omega=False)
    run = plot.load_run(str(src))
    fits = plot.chain_fits(run)
    assert "reverse" not in fits and "lengths" not in fits
    for func in (plot.fig_chain_reverse, plot.fig_chain_correlation, plot.fig_chain_lengths,
                 plot.fig_chain_response, plot.fig_omega_min):
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
                       timeout=120)
    assert r.stdout.strip() == "exit 2 imported []", r.stdout + r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "no such file" in r.stderr
