"""Network ensembles across dz (parflow.post.network_across_ensembles): the across-dz power
law and its error against a direct numpy computation (weighted least squares), the bootstrap
over networks against the propagated error, the per-dz means and standard errors against
numpy on the sample files of a tiny network ensemble, the pairing of a spectrum
ensemble with the shear ensemble of the same networks, and the sample tables (the same
analysis as the run files, pooling, refusals)."""
import json
import math
import os
import shutil
import subprocess
import sys

import h5py
import numpy as np
import pytest

from parflow.post import network_across_ensembles as nae
from parflow.post.ensemble import GRID_POINTS, on_grid
from parflow.post.network import fit_omega_star
from hang_guard import guard

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
                         capture_output=True, text=True, timeout=guard(120),
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
    # the averaged branch is the summary's for a folder, and is drawn from tables too
    from parflow.post.ensemble import read_summary
    t = res["table"][0]
    c = read_summary(os.path.join(t["folders"][0], "summary.h5"))["curves"]["dsigma_dgamma_reverse"]
    for k in ("x", "mean", "sem", "count"):
        np.testing.assert_allclose(t["reverse_curve"][k], c[k], rtol=1e-12, equal_nan=True)
    nae.export([str(tiny)], str(tmp_path / "tables"))
    again = pne.reverse_figure(nae.analyse([str(tmp_path / "tables")], n_boot=0))
    assert len(again.axes[1].lines) == len(fig.axes[1].lines) >= 1
    np.testing.assert_array_equal(again.axes[1].lines[0].get_ydata(), fig.axes[1].lines[0].get_ydata())
    shutil.rmtree(tmp_path / "tables")
    assert pne.main([str(tiny), "--out", str(tmp_path)]) == 0
    assert sorted(os.listdir(tmp_path)) == ["network_ensembles_across.png",
                                            "network_ensembles_reverse.png"]


@pytest.mark.serial_only
@pytest.mark.parametrize("z", ["3.9", "3.8", "3.7"])
def test_N40000_scenes_are_valid(z):
    from parflow.scene import load_scene   # (the scene schema: only these tests need it)
    sc = load_scene(open(os.path.join(ROOT, "runs", f"ensemble_network_N40000_z{z}.toml")).read())
    assert sc["model"]["N"] == 40000 and sc["ensemble"]["samples"] >= 3


# ---------------------------------------------------------------------------------------
# sample tables
# ---------------------------------------------------------------------------------------
def _strip_folders(x):
    if isinstance(x, dict):
        return {k: _strip_folders(v) for k, v in x.items() if k not in ("folder", "folders")}
    if isinstance(x, list):
        return [_strip_folders(v) for v in x]
    return x


def _synthetic_pair():
    """A shear ensemble (C, a reversed-branch curve) and its companion of spectra, as
    ``read_ensemble`` returns them."""
    x = np.geomspace(10, 1e6, 40)
    vals = x ** 2 / np.array([0.03, 0.05, 0.04])[:, None]
    vals[1, x > 2e5] = np.nan
    scene = 'seed = 3\n[model]\nname = "network"\nN = 64\n'
    shear = dict(folder="runs/z3.8", samples=[_row(0, 11, C=0.03), _row(1, 12, C=0.05),
                                              _row(2, 13, C=0.04, status="jammed")],
                 curve=dict(x=x, values=vals), C_curve=nae.curve_C(dict(x=x, values=vals)),
                 provenance=dict(scene=scene, samples=[]))
    gap = dict(folder="runs/gap_z3.8",
               samples=[_row(0, 11, has_spectrum=True, omega_star=0.04, omega_star_70=0.05),
                        _row(1, 99, has_spectrum=True, omega_star=0.5),
                        _row(2, 13, has_spectrum=True, omega_star=0.06)],
               curve=None, C_curve=nae.curve_C(None), provenance=dict(scene="", samples=[]))
    return shear, gap


def test_tables_of_a_shear_and_a_companion_ensemble_combine_as_the_ensembles(comm, mpi_tmp_path):
    """export_samples / load_samples give back every number combine and per_dz use, the
    companion's omega* pairing and C_curve included (written on rank 0, as at the end of an
    ensemble, read on every rank)."""
    shear, gap = _synthetic_pair()
    paths = [str(mpi_tmp_path / f"{n}.json") for n in nae.table_names([shear, gap])]
    assert [os.path.basename(p) for p in paths] == ["dz0.2000_N64.json", "gap_dz0.2000_N64.json"]
    if comm.rank == 0:
        for e, p in zip((shear, gap), paths):
            nae.export_samples(e, p)
    comm.Barrier()
    doc = json.loads(open(paths[0]).read())
    assert doc["kind"] == nae.SAMPLES_KIND and doc["version"] == 1 and doc["source"] == "z3.8"
    assert doc["samples"][0]["omega_star"] is None                   # NaN as null
    assert doc["reverse_curve"]["values"][1][-1] is None
    loaded = [nae.load_samples(p) for p in paths]
    assert loaded[1]["curve"] is None and loaded[0]["samples"][2]["status"] == "jammed"
    assert loaded[0]["C_curve"] == shear["C_curve"]
    direct = [nae.per_dz(e) for e in nae.combine([shear, gap])]
    again = [nae.per_dz(e) for e in nae.combine(loaded)]
    assert again[0]["folders"] == paths
    assert _strip_folders(nae._jsonable(again)) == _strip_folders(nae._jsonable(direct))
    assert again[0]["omega_star"]["n"] == 2 and again[0]["omega_star_70"]["values"][0] == 0.05
    # a table of spectra and the folder-like shear ensemble pair as well
    mixed = nae.combine([shear, loaded[1]])
    assert [s["omega_star"] for s in mixed[0]["samples"]][::2] == [0.04, 0.06]


def test_table_names_tell_apart_companions_and_parts():
    shear, gap = _synthetic_pair()
    part = dict(shear, folder="runs/z3.8_seed4")
    assert nae.table_names([shear, gap, part]) == [
        "dz0.2000_N64_z3.8", "gap_dz0.2000_N64", "dz0.2000_N64_z3.8_seed4"]
    assert nae.table_names([shear, dict(shear, folder="other/z3.8")]) == [
        "dz0.2000_N64_z3.8", "dz0.2000_N64_z3.8_2"]


def test_pooled_curve_C_on_one_grid():
    def pooled_curve_C(group):
        return nae.curve_C(nae.pooled_curve(group))

    shear, _ = _synthetic_pair()
    other = dict(shear, curve=dict(x=shear["curve"]["x"], values=shear["curve"]["values"][:2]))
    got = pooled_curve_C([shear, other])
    both = np.vstack([shear["curve"]["values"], shear["curve"]["values"][:2]])
    assert got == nae.curve_C(dict(x=shear["curve"]["x"], values=both)) and got["n"] == 5
    # another grid: every network's curve interpolated in log-log onto one geometric grid
    x = np.asarray(shear["curve"]["x"], float)
    moved = dict(shear, curve=dict(x=x * 1.001, values=shear["curve"]["values"]))
    got = pooled_curve_C([shear, moved])
    grid = np.geomspace(x.min(), 1.001 * x.max(), GRID_POINTS)
    rows = [on_grid(xx, v, grid, log=True) for xx in (x, 1.001 * x)
            for v in np.atleast_2d(shear["curve"]["values"])]
    assert got == nae.curve_C(dict(x=grid, values=np.array(rows)))
    assert got["n"] == 2 * np.atleast_2d(shear["curve"]["values"]).shape[0]
    assert math.isfinite(got["mean"]) and got["mean"] == pytest.approx(
        nae.curve_C(shear["curve"])["mean"], rel=0.01)
    assert math.isnan(pooled_curve_C([shear, dict(shear, curve=None)])["mean"])


def _one_line(capsys):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


@pytest.mark.serial_only
def test_sample_tables_give_the_analysis_of_the_run_files(tiny, tmp_path, capsys):
    tables = tmp_path / "tables"
    assert nae.main([str(tiny), "--boot", "0", "--export", str(tables)]) == 0
    direct = nae.analyse([str(tiny)], n_boot=30)
    name = f"dz{direct['table'][0]['dz']:.4f}_N128.json"
    assert os.listdir(tables) == [name]
    table = str(tables / name)
    again = nae.analyse([str(tables)], n_boot=30)
    assert again["table"][0]["folders"] == [table]
    assert _strip_folders(nae._jsonable(again)) == _strip_folders(nae._jsonable(direct))
    assert np.isfinite(again["table"][0]["C_curve"]["mean"])
    assert again["table"][0]["C_curve"] == direct["table"][0]["C_curve"]
    # the ensemble wrote its own table at its end: the same numbers
    own = json.loads((tiny / "z3.8" / "samples.json").read_text())
    exported = json.loads(open(table).read())
    assert own["samples"] == exported["samples"] and own["kind"] == nae.SAMPLES_KIND
    assert own["reverse_curve"] == exported["reverse_curve"]
    e = nae.load_samples(table)
    assert [x["sample"] for x in e["samples"]] == [0, 1, 2]
    prov = e["provenance"]
    assert len(prov["samples"]) == 3 and "[model]" in prov["scene"]
    assert all(p["created"] and p["parflow_version"] for p in prov["samples"])
    # the --json result beside the tables is passed over when the folder is searched
    assert nae.main([str(tables), "--boot", "0", "--json", str(tables / "across.json")]) == 0
    assert nae.analyse([str(tables)], n_boot=0)["table"][0]["n_samples"] == 3
    # the same ensemble as a folder and as a table: one line, exit 2
    capsys.readouterr()
    assert nae.main([str(tiny / "z3.8"), table]) == 2
    assert "the same sample (seed" in _one_line(capsys)
    # more networks of a dz (the same scene, other seeds): pooled, from two tables
    doc = json.loads(open(table).read())
    for x in doc["samples"]:
        x["seed"] += 1000
    (tmp_path / "more.json").write_text(json.dumps(doc))
    pooled = nae.analyse([table, str(tmp_path / "more.json")], n_boot=0)
    assert len(pooled["table"]) == 1
    t, one = pooled["table"][0], direct["table"][0]
    assert t["n_samples"] == 6 and t["folders"] == [table, str(tmp_path / "more.json")]
    for q in ("C", "C2", "gamma_j", "omega_star"):
        v = np.array(one[q]["values"] * 2)
        assert t[q]["n"] == 6 and t[q]["values"] == pytest.approx(v.tolist(), rel=1e-12)
        assert t[q]["mean"] == pytest.approx(v.mean(), rel=1e-12)
        assert t[q]["sem"] == pytest.approx(v.std(ddof=1) / math.sqrt(6), rel=1e-10)
    # C_curve of the pooled entry: the curves concatenated (the same grid here), with numpy
    x = np.asarray(doc["reverse_curve"]["x"], float)
    vals = np.array([[np.nan if u is None else u for u in r]
                     for r in doc["reverse_curve"]["values"] * 2], float)
    w = (x >= 1e3) & (x <= 1e5)

    def c_of(rows):
        v = rows[:, w]
        ok = np.all(np.isfinite(v) & (v > 0), axis=0)
        return np.exp(np.mean(2 * np.log(x[w][ok]) - np.log(v[:, ok].mean(axis=0))))
    loo = np.array([c_of(np.delete(vals, i, axis=0)) for i in range(6)])
    assert t["C_curve"]["n"] == 6
    assert t["C_curve"]["mean"] == pytest.approx(c_of(vals), rel=1e-12)
    assert t["C_curve"]["sem"] == pytest.approx(math.sqrt(5 / 6 * np.sum((loo - loo.mean()) ** 2)),
                                                rel=1e-10)
    # the folder and a table of other seeds pool the same way
    mixed = nae.analyse([str(tiny / "z3.8"), str(tmp_path / "more.json")], n_boot=0)
    assert _strip_folders(nae._jsonable(mixed)) == _strip_folders(nae._jsonable(pooled))
    # another grid: the curves pool on one grid (close to the same-grid value), the
    # per-network numbers as before
    doc["reverse_curve"]["x"] = [u * 1.001 for u in doc["reverse_curve"]["x"]]
    (tmp_path / "moved.json").write_text(json.dumps(doc))
    moved = nae.analyse([table, str(tmp_path / "moved.json")], n_boot=0)["table"][0]
    assert moved["C_curve"]["n"] == 6 and moved["C"]["n"] == 6
    assert moved["C_curve"]["mean"] == pytest.approx(t["C_curve"]["mean"], rel=0.02)
    # another scene at the same dz is refused
    doc["provenance"]["scene"] = doc["provenance"]["scene"].replace("strain = 1.0", "strain = 0.9")
    assert "strain = 0.9" in doc["provenance"]["scene"]
    (tmp_path / "other.json").write_text(json.dumps(doc))
    assert nae.main([table, str(tmp_path / "other.json")]) == 2
    assert "not the same scene" in _one_line(capsys)
    # a JSON that is not a table, named or inside a searched folder
    bad = tmp_path / "bad" / "bad.json"
    bad.parent.mkdir()
    bad.write_text('{"kind": "something else"}')
    for arg in (bad, bad.parent):
        assert nae.main([str(arg)]) == 2
        line = _one_line(capsys)
        assert str(bad) in line and "not a network sample table" in line
    (tmp_path / "result.json").write_text('{"table": []}')        # named: must be a table
    assert nae.main([str(tmp_path / "result.json")]) == 2
    assert "result.json: not a network sample table" in _one_line(capsys)
    (tmp_path / "broken.json").write_text(json.dumps(dict(exported, samples=[{"sample": 0}])))
    assert nae.main([str(tmp_path / "broken.json")]) == 2
    assert "broken.json" in _one_line(capsys)


@pytest.mark.serial_only
def test_end_of_ensemble_table_failure_is_one_line_and_exit_1(tiny, tmp_path, monkeypatch, capsys):
    """The end of a network ensemble (parflow.ensemble._finish) writes FOLDER/samples.json;
    when it cannot, it says so in one line and the job's status is 1 (the samples stay)."""
    from parflow import ensemble      # (the driver side: only this test needs it)
    folder = str(tmp_path / "z3.8")
    shutil.copytree(tiny / "z3.8", folder)
    os.remove(os.path.join(folder, "samples.json"))
    base = dict(scene=dict(model=dict(name="network")))
    assert ensemble._finish(folder, base, 3, 1, 0) == 0
    assert nae.load_samples(os.path.join(folder, "samples.json"))["samples"][2]["sample"] == 2
    os.remove(os.path.join(folder, "samples.json"))

    def fail(ens, path):
        raise OSError("disk full")
    monkeypatch.setattr(nae, "export_samples", fail)
    capsys.readouterr()
    assert ensemble._finish(folder, base, 3, 1, 0) == 1
    line = _one_line(capsys)
    assert "sample table not written (OSError: disk full)" in line
    assert not os.path.exists(os.path.join(folder, "samples.json"))
