"""Suspension ensembles across phi (parflow.post.suspension_across_ensembles): the divergence
fit sigma = A (phi_c - phi)^-beta against a brute-force numpy scan and polyfit, its recovery
of phi_c and beta from synthetic ensembles, the pairing of the bootstrap (x and y of a fit
redrawn together), and the per-phi numbers against numpy on the sample files of two tiny
suspension ensembles."""
import json
import math
import os
import subprocess
import sys

import h5py
import numpy as np
import pytest

from parflow.post import suspension_across_ensembles as sae
from systems import SUSPENSION_ENSEMBLE_SCENE
from hang_guard import guard

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

SCENE = SUSPENSION_ENSEMBLE_SCENE.replace("{ensemble}", "[ensemble]\nsamples = 3")


def table_of(phi, values: dict, N=4096) -> list[dict]:
    """per_phi-like rows from per-sample values {q: [array per phi]}."""
    rows = []
    for i, ph in enumerate(phi):
        t = dict(phi=float(ph), N=N, n_samples=None, n_flowing=None)
        for q, vals in values.items():
            v = np.asarray(vals[i], float)
            t[q] = dict(mean=float(v.mean()), sem=float(v.std(ddof=1) / math.sqrt(v.size)),
                        n=int(v.size), values=v.tolist())
            t["n_samples"] = t["n_flowing"] = int(v.size)
        rows.append(t)
    return rows


def synthetic(phi_c=0.843, beta=2.0, A=0.05, noise=0.05, n=4, seed=1,
              phi=(0.810, 0.815, 0.820, 0.825, 0.830, 0.835)):
    rng = np.random.default_rng(seed)
    phi = np.array(phi)
    return phi, [A * (phi_c - p) ** -beta * np.exp(noise * rng.standard_normal(n)) for p in phi]


def test_divergence_against_brute_force_scan():
    phi, vals = synthetic()
    t = table_of(phi, dict(sigma=vals))
    f = sae.fit_divergence(t, "sigma")
    m = np.array([v.mean() for v in vals])
    s = np.array([v.std(ddof=1) / math.sqrt(v.size) for v in vals])
    best = None
    for pc in np.linspace(phi.max() + 1e-4, sae.PHI_C_MAX, sae.PHI_C_GRID):
        X = np.log(pc - phi)
        a, b = np.polyfit(X, np.log(m), 1, w=m / s)
        chi2 = float(np.sum(((np.log(m) - (a * X + b)) * m / s) ** 2))
        if best is None or chi2 < best[0]:
            best = (chi2, pc, -a, math.exp(b))
    assert f["phi_c"] == best[1]
    assert f["beta"] == pytest.approx(best[2], rel=1e-9)
    assert f["prefactor"] == pytest.approx(best[3], rel=1e-9)
    assert f["chi2"] == pytest.approx(best[0], rel=1e-6, abs=1e-12)
    assert f["dof"] == 3 and f["n_phi"] == 6 and not f["fixed"]
    # phi_c fixed: plain weighted polyfit in log(phi_c - phi)
    g = sae.fit_divergence(t, "sigma", phi_c=0.843)
    a, b = np.polyfit(np.log(0.843 - phi), np.log(m), 1, w=m / s)
    assert g["beta"] == pytest.approx(-a, rel=1e-10) and g["phi_c"] == 0.843 and g["fixed"]
    assert g["prefactor"] == pytest.approx(math.exp(b), rel=1e-10) and g["dof"] == 4
    # fewer points than parameters + 1: NaN
    assert math.isnan(sae.fit_divergence(t[:3], "sigma")["beta"])


def test_divergence_recovers_phi_c_and_beta_with_its_bootstrap_error():
    """Over 30 synthetic ensembles (4 samples per phi, 5 % noise): phi_c and beta scatter
    around the truth by about the bootstrap error."""
    dev_pc, dev_b = [], []
    for seed in range(30):
        phi, vals = synthetic(seed=seed)
        t = table_of(phi, dict(sigma=vals))
        f = sae.fit_divergence(t, "sigma", draws=sae.boot_draws(t, 300, seed))
        assert f["phi_c_boot_err"] > 0 and f["beta_boot_err"] > 0
        dev_pc.append((f["phi_c"] - 0.843) / f["phi_c_boot_err"])
        dev_b.append((f["beta"] - 2.0) / f["beta_boot_err"])
    for d in (np.array(dev_pc), np.array(dev_b)):
        assert abs(np.median(d)) < 0.7
        assert np.percentile(np.abs(d), 80) < 3.0      # the error bar is of the right size


def test_bootstrap_pairs_x_and_y():
    """y = 3 x for every sample: the mean of y is 3 times the mean of x in every bootstrap
    draw, so a paired bootstrap gives the exponent 1 exactly (an unpaired one would not)."""
    rng = np.random.default_rng(2)
    x = [np.exp(rng.normal(np.log(d), 0.1, 5)) for d in (0.1, 0.2, 0.3, 0.4)]
    y = [3.0 * v for v in x]
    t = table_of([0.80, 0.81, 0.82, 0.83], dict(dz=x, sigma=y))
    f = sae.fit_power(t, "sigma", "dz", predicted=1.0, draws=sae.boot_draws(t, 200, 0))
    assert f["exponent"] == pytest.approx(1.0, abs=1e-12)
    assert f["boot_err"] < 1e-10 and f["boot_n"] == 200
    # the same fit with x redrawn independently of y scatters
    d2 = sae.boot_draws(t, 200, 1)
    bx, by = sae._boot_means(t, "dz", d2), sae._boot_means(t, "sigma", sae.boot_draws(t, 200, 0))
    p = np.polyfit(np.log(bx[0]), np.log(by[0]), 1)[0]
    assert abs(p - 1.0) > 1e-3


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """Two N = 64 suspension ensembles (phi = 0.78, 0.80), 3 samples each, 0.2 strain."""
    d = tmp_path_factory.mktemp("tiny_susp")
    for phi in ("0.78", "0.80"):
        (d / f"scene{phi}.toml").write_text(SCENE.format(phi=phi))
        res = subprocess.run([sys.executable, "-m", "parflow.shear", str(d / f"scene{phi}.toml"),
                              "--output", str(d / f"phi{phi}"), "--quiet", "--no-plots"],
                             capture_output=True, text=True, timeout=guard(300),
                             env=dict(os.environ, PYTHONPATH=ROOT))
        assert res.returncode == 0, res.stderr
    return d


def _direct(path, from_strain=0.1):
    """sigma (strain-weighted over the window rows), dz = 4 - z2, delta_gamma*sigma and C2
    from the raw sample file with numpy alone."""
    with h5py.File(path) as f:
        ts = f["timeseries"]
        st, s, dg, z2, step = (np.asarray(ts[k][()], float)
                               for k in ("strain", "sigma", "dgamma", "z2", "step"))
        inst = [dict(g.attrs) | {n: g[n][()] for n in g} for g in f["analysis"].values()]
    m = (st >= from_strain) & (step > 0)
    sigma = float(np.sum(s[m] * dg[m]) / np.sum(dg[m]))
    z2m = float(np.sum(z2[m] * dg[m]) / np.sum(dg[m]))
    inst = [a for a in inst if a["strain"] >= from_strain - 1e-12]
    dgs = np.mean([a["delta_gamma"] * a["frozen_sigma"] for a in inst])
    c2 = np.median([a["frozen_omega_min"] * math.sqrt(a["frozen_sigma"]) for a in inst])
    return sigma, 4.0 - z2m, dgs, c2


def _instant_points(path, from_strain=0.1):
    with h5py.File(path) as f:
        inst = [dict(g.attrs) | {n: g[n][()] for n in g} for g in f["analysis"].values()]
    inst = [a for a in inst if a["strain"] >= from_strain - 1e-12]
    return (np.array([a["frozen_sigma"] for a in inst]),
            np.array([a["frozen_omega_min"] for a in inst]))


@pytest.mark.serial_only
def test_per_phi_against_numpy_on_sample_files(tiny, tmp_path):
    res = sae.analyse([str(tiny)], n_boot=50)
    assert [t["phi"] for t in res["table"]] == pytest.approx([0.78, 0.80])
    for t in res["table"]:
        assert t["n_samples"] == 3 and t["N"] == 64
        folder = t["folder"]
        files = sorted(os.path.join(folder, f) for f in os.listdir(folder)
                       if f.startswith("sample_") and f.endswith(".h5"))
        direct = np.array([_direct(p) for p in files])
        for j, q in enumerate(("sigma", "dz", "dgs", "C2")):
            v = direct[:, j]
            assert np.all(np.isfinite(v)), q
            assert t[q]["values"] == pytest.approx(v.tolist(), rel=1e-9), q
            assert t[q]["mean"] == pytest.approx(v.mean(), rel=1e-9), q
            assert t[q]["sem"] == pytest.approx(v.std(ddof=1) / math.sqrt(3), rel=1e-8), q
        # the omega_min(sigma) exponent over the instants of the three samples pooled, and its
        # jackknife over the samples
        pts = [_instant_points(p) for p in files]

        def slope(keep):
            x = np.concatenate([q[0] for q, k in zip(pts, keep) if k])
            y = np.concatenate([q[1] for q, k in zip(pts, keep) if k])
            return np.polyfit(np.log(x), np.log(y), 1)[0]
        full = slope([True] * 3)
        loo = np.array([slope([j != i for j in range(3)]) for i in range(3)])
        g = t["omega_exp_pooled"]
        assert g["mean"] == pytest.approx(full, rel=1e-9) and g["n"] == 3
        assert g["sem"] == pytest.approx(math.sqrt(2 / 3 * np.sum((loo - loo.mean()) ** 2)),
                                         rel=1e-8)
        assert t["jamming_rate"]["n_jammed"] == 0
        assert t["jamming_rate"]["strain"] == pytest.approx(0.6, rel=1e-9)
    # denser -> more stress: the two-point power laws exist and have bootstrap errors
    f = res["across"][64]["sigma_dz"]
    assert f["n_phi"] == 2 and f["exponent"] < 0 and f["boot_n"] > 0
    lines = sae.format_table(res)
    assert lines[2].startswith("| 64 | 0.78 | 3 (3) |")
    out = tmp_path / "across.json"
    assert sae.main([str(tiny), "--boot", "20", "--json", str(out)]) == 0
    assert out.stat().st_size > 0


def test_fixed_phi_c_is_the_mixtures_phi_j():
    from parflow.packing.mixture import PHI_J_2D
    assert sae.PHI_J == PHI_J_2D


def test_main_without_ensembles_fails_with_one_line(tmp_path, capsys):
    assert sae.main([str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no suspension ensemble" in err[0]
    assert sae.main([str(tmp_path), "--boot", "-1"]) == 2


def test_across_ensemble_command_lines_name_a_missing_path(tmp_path, capsys):
    """A mistyped PATH is named as missing (one line, exit 2), not reported as "no ensemble
    found": the analyses and the figures across ensembles, networks and suspensions."""
    from parflow.plot import network_ensembles, suspension_ensembles, suspension_jams as psj
    from parflow.post import network_across_ensembles, suspension_jams
    gone = str(tmp_path / "no_such_ensemble")
    for mod in (sae, network_across_ensembles, suspension_jams, network_ensembles,
                suspension_ensembles, psj):
        assert mod.main([str(tmp_path), gone]) == 2, mod.__name__
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "no such file or folder" in err[0] and gone in err[0], err


@pytest.mark.serial_only
def test_ensemble_scenes_cover_the_phi_scan():
    from parflow.scene import load_scene   # (the scene schema: only this test needs it)
    for phi in ("0.810", "0.815", "0.820", "0.825", "0.830", "0.835"):
        sc = load_scene(open(os.path.join(ROOT, "runs", f"ensemble_suspension_phi{phi}.toml")).read())
        assert sc["model"]["phi"] == float(phi) and sc["ensemble"]["samples"] >= 4
        assert sc["observables"]["analysis_from_strain"] == 3.0
        assert sc["output"]["path"] == f"out/suspension_ensembles/phi{phi}.h5"


@pytest.mark.serial_only
def test_figure_draws_the_ensemble_means(tiny, tmp_path):
    from parflow.plot import suspension_ensembles as pse   # (matplotlib: only this test)
    res = sae.analyse([str(tiny)], n_boot=0)
    fig = pse.across_figure(res)
    assert len(fig.axes) == 8
    ys = np.concatenate([ln.get_ydata() for ln in fig.axes[6].lines])    # delta_gamma sigma
    for t in res["table"]:
        assert np.any(np.isclose(ys, t["dgs"]["mean"], rtol=1e-12))
    assert pse.main([str(tiny), "--out", str(tmp_path)]) == 0
    assert os.listdir(tmp_path) == ["suspension_ensembles_across_N64.png"]
    assert pse.main([str(tmp_path)]) == 2


def _strip_folders(x):
    if isinstance(x, dict):
        return {k: _strip_folders(v) for k, v in x.items() if k != "folder"}
    if isinstance(x, list):
        return [_strip_folders(v) for v in x]
    return x


@pytest.mark.serial_only
def test_sample_tables_give_the_analysis_of_the_run_files(tiny, tmp_path, capsys):
    from parflow.post.network_across_ensembles import _jsonable
    tables = tmp_path / "tables"
    assert sae.main([str(tiny), "--boot", "0", "--export", str(tables)]) == 0
    names = sorted(os.listdir(tables))
    assert names == ["phi0.7800_N64.json", "phi0.8000_N64.json"]
    direct = sae.analyse([str(tiny)], n_boot=30)
    again = sae.analyse([str(tables)], n_boot=30)
    assert _strip_folders(_jsonable(again)) == _strip_folders(_jsonable(direct))
    # the ensemble wrote its own table at its end: the same numbers
    for phi, name in zip(("0.78", "0.80"), names):
        own = json.loads((tiny / f"phi{phi}" / "samples.json").read_text())
        assert own["samples"] == json.loads((tables / name).read_text())["samples"]
    e = sae.load_samples(str(tables / names[0]))
    assert [x["sample"] for x in e["samples"]] == [0, 1, 2]
    prov = e["provenance"]
    assert len(prov["samples"]) == 3 and "[model]" in prov["scene"]
    assert all(p["created"] for p in prov["samples"])
    # the --json result written beside the tables is passed over when the folder is
    # searched (the docs write it there), and refused when named
    assert sae.main([str(tables), "--boot", "0", "--json", str(tables / "across.json")]) == 0
    assert [t["n_samples"] for t in sae.analyse([str(tables)], n_boot=0)["table"]] == [3, 3]
    capsys.readouterr()
    assert sae.main([str(tables / "across.json")]) == 2
    assert "not a suspension sample table" in capsys.readouterr().err
    # one phi from its run files, the other from its table
    mixed = sae.analyse([str(tiny / "phi0.78"), str(tables / names[1])], n_boot=0)
    assert [t["phi"] for t in mixed["table"]] == pytest.approx([0.78, 0.80])
    # the same ensemble twice, or a file that is not a table: one line, exit 2
    capsys.readouterr()
    assert sae.main([str(tiny / "phi0.78"), str(tables / names[0])]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "the same sample (seed" in err[0]
    # more samples of a phi (the same scene with other seeds) are pooled; another scene is not
    doc = json.loads((tables / names[0]).read_text())
    for x in doc["samples"]:
        x["seed"] += 1000
    (tmp_path / "more.json").write_text(json.dumps(doc))
    pooled = sae.analyse([str(tiny / "phi0.78"), str(tmp_path / "more.json")], n_boot=0)
    t = pooled["table"][0]
    assert t["n_samples"] == 6 and t["sigma"]["n"] == 6
    one = direct["table"][0]["sigma"]["values"]
    assert t["sigma"]["values"] == pytest.approx(one + one, rel=1e-12)
    doc["provenance"]["scene"] = doc["provenance"]["scene"].replace("strain = 0.2", "strain = 0.3")
    (tmp_path / "other.json").write_text(json.dumps(doc))
    assert sae.main([str(tiny / "phi0.78"), str(tmp_path / "other.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not the same scene" in err[0]
    bad = tmp_path / "bad.json"
    bad.write_text('{"kind": "something else"}')
    assert sae.main([str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not a suspension sample table" in err[0]
