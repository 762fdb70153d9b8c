"""Pooled ensemble summaries (parflow.post.pool): two small chain ensembles of one scene with
different seeds pooled into one summary -- samples, per-sample fits and curves against numpy
on the inputs, the ensemble fit recomputed (and equal to the input's own for one input), the
refusals (the same sample twice, another scene), and the figures drawn from the pool."""
import math
import os
import shutil

import h5py
import numpy as np
import pytest

from parflow.post import pool as P
from parflow.post.ensemble import GRID_POINTS, read_summary
from test_ensemble import SCENE, shear

pytestmark = pytest.mark.serial_only          # runs parflow.shear in subprocesses


@pytest.fixture(scope="module")
def two(tmp_path_factory):
    """The chain ensemble scene of tests/test_ensemble.py with seeds 5 and 6, 2 samples each."""
    d = tmp_path_factory.mktemp("pool")
    out = []
    for seed in (5, 6):
        scene = d / f"scene{seed}.toml"
        scene.write_text(SCENE.replace("seed = 5", f"seed = {seed}"))
        folder = d / f"seed{seed}"
        res = shear(scene, "--samples", 2, "--output", folder, "--quiet", "--no-plots")
        assert res.returncode == 0, res.stderr
        out.append(str(folder))
    return out


def test_pooled_summary_against_its_inputs(two, tmp_path):
    a, b = (read_summary(os.path.join(f, "summary.h5")) for f in two)
    assert P.main([*two, "--out", str(tmp_path / "pooled")]) == 0
    s = read_summary(str(tmp_path / "pooled" / "summary.h5"))
    assert list(s["samples"]["seed"]) == list(a["samples"]["seed"]) + list(b["samples"]["seed"])
    assert list(s["samples"]["used"]) == [0, 1, 2, 3]
    assert s["attrs"]["pooled_from"].split("\n") == [os.path.join(f, "summary.h5") for f in two]
    # per-sample fits: concatenated; mean and error over the four
    name = next(n for n in a["fits"] if np.all(np.isfinite(a["fits"][n]["values"])) and
                np.all(np.isfinite(b["fits"][n]["values"])) and "V2" in n)
    v = np.concatenate([a["fits"][name]["values"], b["fits"][name]["values"]])
    q = s["fits"][name]
    assert np.array_equal(q["values"], v)
    assert q["mean"] == pytest.approx(v.mean(), rel=1e-12)
    assert q["sem"] == pytest.approx(v.std(ddof=1) / math.sqrt(4), rel=1e-10)
    # the forward <V^2> curve: each input's rows, log-log interpolated onto the pooled grid
    c = s["curves"]["V2_forward"]
    lo = min(a["curves"]["V2_forward"]["x"].min(), b["curves"]["V2_forward"]["x"].min())
    hi = max(a["curves"]["V2_forward"]["x"].max(), b["curves"]["V2_forward"]["x"].max())
    assert np.allclose(c["x"], np.geomspace(lo, hi, GRID_POINTS), rtol=1e-14)
    rows = []
    for src in (a, b):
        x, vals = src["curves"]["V2_forward"]["x"], src["curves"]["V2_forward"]["values"]
        for row in vals:
            ok = np.isfinite(row) & (row > 0)
            g = np.log(c["x"])
            inside = (g >= np.log(x[ok][0])) & (g <= np.log(x[ok][-1]))
            r = np.full(g.size, np.nan)
            r[inside] = np.exp(np.interp(g[inside], np.log(x[ok]), np.log(row[ok])))
            rows.append(r)
    np.testing.assert_allclose(c["values"], np.array(rows), rtol=1e-12)
    e = s["ensemble_fits"]["V2_forward_exponent"]
    assert e["n"] == 4 and np.isfinite(e["value"]) and np.isfinite(e["jackknife_err"])
    assert s["ensemble_fits"]["jamming_rate"]["n"] == 4
    # the figures of an ensemble folder, drawn from the pool
    from parflow.plot import main as plot_main     # (matplotlib: only this test needs it)
    assert plot_main([str(tmp_path / "pooled"), "--out", str(tmp_path / "plots")]) == 0
    assert any(n.endswith(".png") for n in os.listdir(tmp_path / "plots"))


def test_one_input_keeps_its_own_ensemble_fit(two):
    s = P.pool_summaries([two[0]])
    a = read_summary(os.path.join(two[0], "summary.h5"))
    for name, c in a["curves"].items():          # one grid: the rows as they are
        assert np.array_equal(s["curves"][name]["x"], c["x"]), name
        assert np.array_equal(s["curves"][name]["values"], c["values"], equal_nan=True), name
    mine, theirs = s["ensemble_fits"]["V2_forward_exponent"], a["ensemble_fits"]["V2_forward_exponent"]
    assert mine["value"] == pytest.approx(theirs["value"], rel=1e-10)
    assert mine["jackknife_err"] == pytest.approx(theirs["jackknife_err"], rel=1e-8)


def test_refused_inputs_fail_with_one_line(two, tmp_path, capsys):
    assert P.main([two[0], two[0], "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "the same sample (seed" in err[0]
    other = tmp_path / "other"
    shutil.copytree(two[1], other)
    with h5py.File(other / "summary.h5", "r+") as f:
        f.attrs["scene"] = str(f.attrs["scene"]).replace("mu = 0", "mu = 2")
    assert P.main([two[0], str(other), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not the same scene" in err[0]
    assert P.main([str(tmp_path / "nothing"), "--out", str(tmp_path / "x")]) == 2
    assert P.main([two[0], two[1], "--out", two[0]]) == 2
    assert not os.path.exists(tmp_path / "x")
