"""A suspension run's averages in windows of equal strain (parflow.post.suspension_windows):
the windows start where phi reached its final value, each step weighs by its strain, a
linear drift is found and a flat series shows none, runs are averaged over, and the command
line fails in one line on bad input."""
import json
import math
import subprocess
import sys

import h5py
import numpy as np
import pytest

from parflow.post import suspension_windows as sw
from hang_guard import guard

SCENE = """
[model]
name = "{model}"
N = 64
phi = 0.820
compress_rate = 0.02
compress_to = 0.840
"""


def run_file(path, sigma, dgamma, phi, model="suspension", status="complete"):
    """A suspension run file with the columns the windows read: sigma, pressure = 10 sigma
    (mu = 0.1), z2, phi, and the step's strain."""
    sigma, dgamma = np.asarray(sigma, float), np.asarray(dgamma, float)
    strain = np.cumsum(dgamma)
    with h5py.File(path, "w") as f:
        f.attrs.update(format="parflow-run-1", model=model, status=status,
                       scene=SCENE.format(model=model), sample_seed=1)
        g = f.create_group("timeseries")
        g["step"] = np.arange(1, sigma.size + 1)
        g["direction"] = np.ones(sigma.size, np.int64)
        g["strain"] = strain
        g["gamma"] = strain
        g["dgamma"] = dgamma
        g["sigma"] = sigma
        g["pressure"] = 10.0 * sigma
        g["mu"] = np.full(sigma.size, 0.1)
        g["z2"] = np.full(sigma.size, 3.95)
        g["phi"] = np.asarray(phi, float)
    return str(path)


def series(n=4000, length=4.0, seed=0, slope=0.0):
    """Steps of uneven size over ``length`` strain, phi compressed 0.82 -> 0.84 over the first
    strain; sigma = 200 + slope * strain + noise."""
    rng = np.random.default_rng(seed)
    dg = rng.uniform(0.5, 1.5, n)
    dg *= length / dg.sum()
    strain = np.cumsum(dg)
    phi = np.minimum(0.82 + 0.02 * strain, 0.84)
    phi[strain >= 1.0] = 0.84
    sigma = 200.0 + slope * strain + rng.normal(0.0, 20.0, n)
    return sigma, dg, phi, strain


def test_windows_start_at_the_final_phi_and_weigh_steps_by_strain(tmp_path):
    sigma, dg, phi, strain = series()
    path = run_file(tmp_path / "r.h5", sigma, dg, phi)
    res = sw.run_windows(path, width=1.0)
    first = strain[np.flatnonzero(phi >= 0.84)[0]]
    assert res["whole"]["lo"] == pytest.approx(first)
    assert len(res["windows"]) == 3                       # ~3 strain at 0.840, 1 wide each
    for w in res["windows"]:
        m = (strain > w["lo"]) & (strain <= w["hi"])
        assert w["steps"] == m.sum()
        assert w["sigma"][0] == pytest.approx(np.sum(dg[m] * sigma[m]) / np.sum(dg[m]), rel=1e-12)
        assert w["pressure"][0] == pytest.approx(10.0 * w["sigma"][0], rel=1e-12)
        assert w["mu"][0] == pytest.approx(0.1)
        assert 0.0 < w["sigma"][1] < 5.0                  # 20 / sqrt(~1000 steps) ~ 0.6
    # a short last piece joins the window before
    res = sw.run_windows(path, width=1.2)
    assert [round(w["hi"] - w["lo"], 6) for w in res["windows"]][-1] > 1.2


def test_drift_found_and_a_flat_series_shows_none(tmp_path):
    sigma, dg, phi, _ = series(n=8000, length=7.0, slope=10.0, seed=1)
    res = sw.run_windows(run_file(tmp_path / "ramp.h5", sigma, dg, phi), width=1.0)
    d = res["drift"]["sigma"]
    assert len(res["windows"]) == 6
    assert abs(d["slope"] - 10.0) < 4 * d["err"] and d["err"] < 2.0
    sigma, dg, phi, _ = series(n=8000, length=7.0, slope=0.0, seed=2)
    d = sw.run_windows(run_file(tmp_path / "flat.h5", sigma, dg, phi))["drift"]["sigma"]
    assert abs(d["slope"]) < 4 * d["err"]
    # fewer than three windows: no drift
    assert math.isnan(sw.drift([1.0, 2.0], [3.0, 4.0], [1.0, 1.0])[0])
    s, e = sw.drift([0.0, 1.0, 2.0], [1.0, 3.0, 5.0], [1.0, 1.0, 1.0])
    assert s == pytest.approx(2.0) and e == pytest.approx(1.0 / math.sqrt(2.0))


def test_range_and_runs_averaged(tmp_path):
    paths = []
    for k in range(3):
        sigma, dg, phi, _ = series(seed=10 + k)
        paths.append(run_file(tmp_path / f"s{k}.h5", sigma + 20.0 * k, dg, phi))
    res = sw.analyse(paths, width=1.0, from_strain=2.0, to_strain=3.5)
    for r in res["runs"]:
        assert r["whole"]["lo"] == 2.0 and r["whole"]["hi"] == 3.5
    means = [r["whole"]["sigma"][0] for r in res["runs"]]
    assert res["across"]["sigma"][0] == pytest.approx(np.mean(means))
    assert res["across"]["sigma"][1] == pytest.approx(np.std(means, ddof=1) / math.sqrt(3))
    assert any("across 3 runs" in line for line in sw.format_table(res))


@pytest.mark.serial_only
def test_command_line(tmp_path):
    sigma, dg, phi, _ = series()
    good = run_file(tmp_path / "r.h5", sigma, dg, phi)
    net = run_file(tmp_path / "n.h5", sigma, dg, phi, model="network")
    out = tmp_path / "w.json"

    def cli(*args):
        return subprocess.run([sys.executable, "-m", "parflow.post.suspension_windows", *args],
                              capture_output=True, text=True, timeout=guard(120))

    p = cli(good, "--json", str(out))
    assert p.returncode == 0, p.stderr
    assert "drift per unit strain" in p.stdout
    assert len(json.load(open(out))["runs"][0]["windows"]) == 3
    for args, says in (([str(tmp_path / "missing.h5")], "no such file"),
                       ([net], "not a suspension"),
                       ([good, "--width", "0"], "--width must be > 0"),
                       ([good, "--from-strain", "9"], "no forward steps")):
        p = cli(*args)
        assert p.returncode == 2, (args, p.stdout, p.stderr)
        assert says in p.stderr and len(p.stderr.strip().splitlines()) == 1, p.stderr


def two_runs(tmp_path):
    paths = []
    for k in range(2):
        sigma, dg, phi, _ = series(seed=20 + k)
        paths.append(run_file(tmp_path / f"f{k}.h5", sigma, dg, phi))
    return paths


def test_figure(tmp_path):
    from parflow.plot.suspension_windows import windows_figure
    res = sw.analyse(two_runs(tmp_path))
    fig = windows_figure(res)
    top, bottom = fig.axes
    assert len(top.containers) == 2 and len(bottom.containers) == 2     # one per run
    line = top.containers[0].lines[0]
    assert np.allclose(line.get_ydata(), [w["sigma"][0] for w in res["runs"][0]["windows"]])
    line = bottom.containers[1].lines[0]
    assert np.allclose(line.get_ydata(), [w["mu"][0] for w in res["runs"][1]["windows"]])


@pytest.mark.serial_only
def test_figure_command_line(tmp_path):
    paths, out = two_runs(tmp_path), tmp_path / "figs"
    p = subprocess.run([sys.executable, "-m", "parflow.plot.suspension_windows", *paths,
                        "--out", str(out)], capture_output=True, text=True, timeout=guard(120))
    assert p.returncode == 0, p.stderr
    assert (out / "suspension_windows.png").stat().st_size > 0
    p = subprocess.run([sys.executable, "-m", "parflow.plot.suspension_windows",
                        str(tmp_path / "none.h5")], capture_output=True, text=True,
                       timeout=guard(120))
    assert p.returncode == 2 and "no such file" in p.stderr
