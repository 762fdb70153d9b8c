"""Network ensembles across dz (parflow.post.network_across_ensembles): the across-dz power
law and its error against a direct numpy computation (weighted least squares), the bootstrap
over networks against the propagated error, the per-dz means and standard errors against
numpy on the sample files of a tiny network ensemble, and the pairing of a spectrum
ensemble with the shear ensemble of the same networks."""
import math
import os
import subprocess
import sys

import h5py
import numpy as np
import pytest

from parflow.post import network_across_ensembles as nae
from parflow.post.network import fit_omega_star

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

SCENE = """
title = "network ensemble test"
seed = 3
[model]
name = "network"
N = 128
z = 3.8
phi = 0.88
correlation = false
spectrum = "{spectrum}"
response_rods = 2
[ensemble]
samples = 3
[[protocol.leg]]
direction = "forward"
sigma_above = 1e6
[[protocol.leg]]
direction = "reverse"
sigma_above = 1e7
sigma_below = 10
strain = 1.0
[observables]
omega_min_every = 2
analysis_quantity = "sigma"
analysis_per_decade = 1
[output]
path = "unused.h5"
"""


def synthetic(p=-0.5, A=0.03, noise=0.2, n=8, dz=(0.05, 0.1, 0.2, 0.3, 0.4), seed=1):
    rng = np.random.default_rng(seed)
    return np.array(dz), [A * d ** p * np.exp(noise * rng.standard_normal(n)) for d in dz]


def test_fit_across_against_numpy_wls():
    dz, vals = synthetic()
    f = nae.fit_across(dz, vals, n_boot=0, predicted=-0.5)
    m = np.array([v.mean() for v in vals])
    s = np.array([v.std(ddof=1) / math.sqrt(v.size) for v in vals])
    # numpy: polyfit of log m on log dz with weights 1 / sigma_log = m / s
    (p, c), cov = np.polyfit(np.log(dz), np.log(m), 1, w=m / s, cov="unscaled")
    chi2 = float(np.sum(((np.log(m) - (p * np.log(dz) + c)) * m / s) ** 2))
    err = math.sqrt(cov[0, 0] * max(1.0, chi2 / (dz.size - 2)))
    assert f["exponent"] == pytest.approx(p, rel=1e-10)
    assert f["prefactor"] == pytest.approx(math.exp(c), rel=1e-10)
    assert f["chi2"] == pytest.approx(chi2, rel=1e-8)
    assert f["err"] == pytest.approx(err, rel=1e-8)
    assert f["deviation"] == pytest.approx((p + 0.5) / err, rel=1e-8)
    assert f["n_dz"] == 5 and f["dof"] == 3


def test_fit_across_recovers_exponents_and_bootstrap_matches_propagated_error():
    """Over 40 synthetic ensembles: the fitted exponent scatters around the true one by about
    the propagated error, and the bootstrap over networks gives about the same error (it
    is smaller by ~sqrt((n-1)/n) for n samples a point, and noisier)."""
    devs, ratio = [], []
    for seed in range(40):
        dz, vals = synthetic(p=1.0, noise=0.3, seed=seed)
        f = nae.fit_across(dz, vals, n_boot=300, seed=seed, predicted=1.0)
        # the WLS error without the chi2 inflation, for the ratio
        m = np.array([v.mean() for v in vals])
        s = np.array([v.std(ddof=1) / math.sqrt(v.size) for v in vals])
        _, cov = np.polyfit(np.log(dz), np.log(m), 1, w=m / s, cov="unscaled")
        devs.append((f["exponent"] - 1.0) / math.sqrt(cov[0, 0]))
        ratio.append(f["boot_err"] / math.sqrt(cov[0, 0]))
    devs = np.array(devs)
    assert abs(devs.mean()) < 0.6                       # unbiased within its noise
    assert 0.6 < devs.std() < 1.6                        # the error describes the scatter
    assert 0.75 < np.median(ratio) < 1.1                 # bootstrap ~ propagated error


def test_fit_across_leaves_out_points_without_error():
    dz, vals = synthetic()
    vals[2] = vals[2][:1]                 # one sample: no standard error
    vals[3] = np.r_[vals[3], np.nan]      # NaN ignored
    f = nae.fit_across(dz, vals, n_boot=50)
    g = nae.fit_across(np.delete(dz, 2), [v for k, v in enumerate(vals) if k != 2], n_boot=0)
    assert f["n_dz"] == 4
    assert f["exponent"] == pytest.approx(g["exponent"], rel=1e-12)
    assert nae.fit_across([0.1], [vals[0]])["n_dz"] == 1
    assert math.isnan(nae.fit_across([0.1], [vals[0]])["exponent"])


def test_mean_l_c_window():
    inst = [dict(sigma=5.0, l_c=9.0), dict(sigma=10.0, l_c=2.0), dict(sigma=500.0, l_c=4.0),
            dict(sigma=800.0, l_c=np.nan), dict(sigma=2e3, l_c=7.0)]
    assert nae.mean_l_c(dict(instants=inst)) == pytest.approx(3.0)
    assert math.isnan(nae.mean_l_c(None))


def test_curve_C_and_its_jackknife_against_numpy():
    rng = np.random.default_rng(4)
    x = np.geomspace(10, 1e6, 60)
    C = np.array([0.02, 0.03, 0.05, 0.04, 0.025])
    vals = x ** 2 / C[:, None] * np.exp(0.05 * rng.standard_normal((5, x.size)))
    vals[1, x > 3e5] = np.nan                 # a network that does not cover the top
    vals[2, 3] = np.nan                       # nor one point below the window
    got = nae.curve_C(dict(x=x, values=vals))
    w = (x >= 1e3) & (x <= 1e5)

    def c_of(rows):
        return np.exp(np.mean(2 * np.log(x[w]) - np.log(rows[:, w].mean(axis=0))))
    loo = np.array([c_of(np.delete(vals, i, axis=0)) for i in range(5)])
    assert got["mean"] == pytest.approx(c_of(vals), rel=1e-12)
    assert got["sem"] == pytest.approx(math.sqrt(4 / 5 * np.sum((loo - loo.mean()) ** 2)),
                                       rel=1e-10)
    assert got["n"] == 5
    # the C of the mean curve is the harmonic mean of the C's (slope exactly 2, no noise)
    exact = nae.curve_C(dict(x=x, values=x ** 2 / C[:, None]))
    assert exact["mean"] == pytest.approx(1 / np.mean(1 / C), rel=1e-12)
    assert math.isnan(nae.curve_C(None)["mean"])


def test_fit_means_is_fit_across_without_bootstrap():
    dz, vals = synthetic()
    f = nae.fit_across(dz, vals, n_boot=0, predicted=-0.5)
    g = nae.fit_means(dz, [v.mean() for v in vals],
                      [v.std(ddof=1) / math.sqrt(v.size) for v in vals], -0.5)
    assert g["exponent"] == f["exponent"] and g["err"] == f["err"]


def _row(k, seed, **v):
    base = dict(sample=k, seed=seed, status="complete", steps=1, N=64, z=3.8, dz=0.2,
                has_spectrum=False) | {q: np.nan for q in nae.QUANTITIES}
    return base | v


def test_combine_pairs_spectra_by_sample_and_seed():
    shear = dict(folder="z3.8", samples=[_row(0, 11, C=0.03), _row(1, 12, C=0.05),
                                         _row(2, 13, C=0.04)])
    gap = dict(folder="gap_z3.8", samples=[_row(0, 11, has_spectrum=True, omega_star=0.04,
                                                omega_star_30=0.03),
                                           _row(1, 99, has_spectrum=True, omega_star=0.5),
                                           _row(2, 13, has_spectrum=True, omega_star=0.06)])
    other = dict(folder="z3.6", samples=[_row(0, 21, dz=0.4, C=0.02)])
    out = nae.combine([gap, shear, other])
    assert [(e["dz"], e["folders"]) for e in out] == [(0.2, ["z3.8", "gap_z3.8"]),
                                                      (0.4, ["z3.6"])]
    ws = [s["omega_star"] for s in out[0]["samples"]]
    assert ws[0] == 0.04 and math.isnan(ws[1]) and ws[2] == 0.06    # seed 99 is another network
    assert out[0]["samples"][0]["omega_star_30"] == 0.03
    t = nae.per_dz(out[0])
    assert t["omega_star"]["n"] == 2 and t["omega_star"]["mean"] == pytest.approx(0.05)
    assert t["omega_star"]["sem"] == pytest.approx(np.std([0.04, 0.06], ddof=1) / math.sqrt(2))
    assert t["C"]["mean"] == pytest.approx(0.04) and t["C"]["n"] == 3


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """Three N = 128 networks forward to sigma = 1e6 and back, with the dense spectrum."""
    d = tmp_path_factory.mktemp("tiny")
    (d / "scene.toml").write_text(SCENE.format(spectrum="dense"))
    res = subprocess.run([sys.executable, "-m", "parflow.shear", str(d / "scene.toml"),
                          "--output", str(d / "z3.8"), "--quiet", "--no-plots"],
                         capture_output=True, text=True, timeout=120,
                         env=dict(os.environ, PYTHONPATH=ROOT))
    assert res.returncode == 0, res.stderr
    return d


def _direct(path):
    """C (sigma in 1e3..1e5), C_hi (1e4..1e5), C2 from the raw time series with numpy alone
    (docs/networks.md definitions)."""
    with h5py.File(path) as f:
        ts = f["timeseries"]
        d, s, x, w, g = (np.asarray(ts[k][()], float) for k in ("direction", "sigma", "strain",
                                                                 "omega_min", "gamma"))
    rev = np.nonzero(d < 0)[0]
    rev = rev[: np.argmax(np.diff(rev) > 1) + 1] if np.any(np.diff(rev) > 1) else rev
    xs, ss = x[rev] - x[rev[0]], s[rev]
    C = [1.0 / np.polyfit(xs[m], 1.0 / ss[m], 1)[0]
         for m in ((ss >= 1e3) & (ss <= 1e5), (ss >= 1e4) & (ss <= 1e5))]
    ok = np.isfinite(w) & (w > 0) & (s >= 1e3)
    C2 = float(np.median(w[ok] * np.sqrt(s[ok])))
    return C[0], C[1], C2, g[np.argmax(d < 0) - 1]      # gamma_j: the last forward row


@pytest.mark.serial_only
def test_per_dz_against_numpy_on_sample_files(tiny):
    res = nae.analyse([str(tiny)], n_boot=0)
    assert len(res["table"]) == 1
    t = res["table"][0]
    assert t["n_samples"] == 3 and t["N"] == 128
    files = sorted(os.path.join(tiny, "z3.8", f) for f in os.listdir(tiny / "z3.8")
                   if f.startswith("sample_") and f.endswith(".h5"))
    direct = np.array([_direct(p) for p in files])
    for j, q in enumerate(("C", "C_hi", "C2", "gamma_j")):
        v = direct[:, j]
        assert t[q]["values"] == pytest.approx(v.tolist(), rel=1e-9)
        assert t[q]["mean"] == pytest.approx(v.mean(), rel=1e-9)
        assert t[q]["sem"] == pytest.approx(v.std(ddof=1) / math.sqrt(3), rel=1e-9)
    assert t["omega_star"]["n"] == 3 and 0 < t["omega_star"]["mean"] < 0.2
    with h5py.File(files[0]) as f:        # omega* with another fraction, from the spectrum
        w = [g["omega"][()] for g in f["analysis"].values() if "omega" in g]
    assert t["omega_star_70"]["values"][0] == pytest.approx(
        np.mean([fit_omega_star(x, fraction=0.7, n_boot=0)["omega_star"] for x in w]), rel=1e-12)
    assert np.isfinite(t["l_c"]["mean"]) and t["l_c"]["mean"] > 0
    assert all(np.isfinite(t["a"]["values"]))
    assert t["C_curve"]["n"] == 3 and np.isfinite(t["C_curve"]["sem"])
    # the C of the mean curve lies between the smallest and the largest C of the networks
    assert min(t["C"]["values"]) / 2 < t["C_curve"]["mean"] < 2 * max(t["C"]["values"])
    lines = nae.format_table(res)
    assert lines[2].startswith("| 128 | 3.8 | 0.2")


NETWORK_KEYS = ("N", "phi", "pressure", "z", "d", "network_file")


@pytest.mark.serial_only
@pytest.mark.parametrize("z", ["3.95", "3.9", "3.8", "3.7", "3.6"])
def test_gap_scenes_build_the_networks_of_the_shear_scenes(z):
    """The omega* ensembles are paired with the shear ensembles sample by sample: both
    scenes must be valid and build the same networks (same seed and network keys)."""
    from parflow.scene import load_scene   # (the scene schema: only this test needs it)
    a, b = (load_scene(open(os.path.join(ROOT, "runs", f"ensemble_network_{k}z{z}.toml")).read())
            for k in ("", "gap_"))
    assert a["seed"] == b["seed"]
    assert [a["model"].get(k) for k in NETWORK_KEYS] == [b["model"].get(k) for k in NETWORK_KEYS]
    assert a["ensemble"]["samples"] >= 8 and b["ensemble"]["samples"] >= 8
    assert a["model"]["spectrum"] == "none" and b["model"]["spectrum"] == "dense"


@pytest.mark.serial_only
def test_figures_draw_the_ensemble_means(tiny, tmp_path):
    from parflow.plot import network_ensembles as pne   # (matplotlib: only this test)
    res = nae.analyse([str(tiny)], n_boot=0)
    fig = pne.across_figure(res)
    ax = fig.axes[0]                                     # the C panel
    ys = np.concatenate([ln.get_ydata() for ln in ax.lines])
    assert np.any(np.isclose(ys, res["table"][0]["C"]["mean"], rtol=1e-12))
    fig = pne.reverse_figure(res)
    assert len(fig.axes) == 3 and fig.axes[0].lines
    assert pne.main([str(tiny), "--out", str(tmp_path)]) == 0
    assert sorted(os.listdir(tmp_path)) == ["network_ensembles_across.png",
                                            "network_ensembles_reverse.png"]


@pytest.mark.serial_only
@pytest.mark.parametrize("z", ["3.9", "3.8", "3.7"])
def test_N40000_scenes_are_valid(z):
    from parflow.scene import load_scene   # (the scene schema: only these tests need it)
    sc = load_scene(open(os.path.join(ROOT, "runs", f"ensemble_network_N40000_z{z}.toml")).read())
    assert sc["model"]["N"] == 40000 and sc["ensemble"]["samples"] >= 3
