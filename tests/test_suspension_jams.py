"""Where compressed, flowing suspensions shear-jam (parflow.post.suspension_jams): the records
read from run files of each kind of ending (a shear jam while compressing, a jam at constant
phi after compress_to, a jam that only the swelling compresses, a sample that flowed to its
end, one still running), the per-N numbers against numpy, the fit phi_inf - a N^-0.71 on
exact data, the jam table's round trip, the figure, and the command line's one-line errors."""
import json
import math
import os
import subprocess
import sys

import h5py
import numpy as np
import pytest

from parflow.post import suspension_jams as sj
from hang_guard import guard

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCENE = """
[model]
name = "suspension"
N = {N}
phi = 0.820
compress_rate = {rate}
compress_to = {to}
"""


def run_file(path, N, status, phi_ts, jam=None, rate=0.01, seed=1, to=0.8429):
    """A minimal suspension run file: the attributes, phi and gamma columns, and /jam."""
    with h5py.File(path, "w") as f:
        f.attrs.update(format="parflow-run-1", model="suspension", status=status,
                       scene=SCENE.format(N=N, rate=rate, to=to), sample_seed=seed,
                       git_commit="abc123")
        g = f.create_group("timeseries")
        g["phi"] = np.asarray(phi_ts, float)
        g["gamma"] = np.linspace(0.0, 2.0, len(phi_ts))
        if jam is not None:
            j = f.create_group("jam")
            j.attrs.update(certified=True, gamma=2.0, support=100, tau_b=-50.0,
                           strain_budget=1e-12, **jam)


def ensemble(folder, N, samples, rate=0.01, to=0.8429, seed0=0):
    os.makedirs(folder)
    with h5py.File(os.path.join(folder, "ensemble.h5"), "w"):
        pass
    for k, (status, phi_ts, jam) in enumerate(samples):
        run_file(os.path.join(folder, f"sample_{k:04d}.h5"), N, status, phi_ts, jam, rate,
                 seed=100 * N + seed0 + k, to=to)


@pytest.fixture
def folders(tmp_path):
    ensemble(tmp_path / "jams_N1024", 1024, [
        ("jammed", [0.82, 0.838], dict(phi=0.8381, tau_b_shear=-40.0)),     # shear jam
        ("jammed", [0.82, 0.8429], dict()),                                 # constant phi
        ("jammed", [0.82, 0.8395], dict(phi=0.8395, tau_b_shear=+3.0)),     # the swelling's
        ("complete", [0.82, 0.8429], None),                                 # flowed on
        ("running", [0.82, 0.83], None)])                                   # not ended
    ensemble(tmp_path / "jams_N2048", 2048, [
        ("jammed", [0.82, 0.8405], dict(phi=0.8405, tau_b_shear=-60.0)),
        ("jammed", [0.82, 0.8411], dict(phi=0.8411, tau_b_shear=-70.0))])
    ensemble(tmp_path / "jams_N4096", 4096, [
        ("jammed", [0.82, 0.8412], dict(phi=0.8412, tau_b_shear=-90.0)),
        ("jammed", [0.82, 0.8414], dict(phi=0.8414, tau_b_shear=-95.0))])
    return tmp_path


def test_records_and_per_n_numbers(folders):
    recs = sj.read_folder(str(folders / "jams_N1024"))
    assert [r["sample"] for r in recs] == [0, 1, 2, 3]             # the running one left out
    shear = [r["shear_jam"] for r in recs]
    assert shear == [True, True, False, False]
    assert recs[1]["constant_phi"] and recs[1]["phi"] == 0.8429    # its last phi
    assert recs[0]["phi"] == 0.8381 and recs[3]["phi"] == 0.8429
    res = sj.analyse([str(folders)])
    rows = {t["N"]: t for t in res["table"]}
    assert sorted(rows) == [1024, 2048, 4096]
    t = rows[1024]
    assert (t["n_samples"], t["n_shear_jams"], t["constant_phi"]) == (4, 2, 1)
    v = np.array([0.8381, 0.8429])
    assert t["phi_mean"] == pytest.approx(v.mean(), abs=1e-15)
    assert t["phi_sd"] == pytest.approx(v.std(ddof=1), rel=1e-12)
    assert t["phi_sem"] == pytest.approx(v.std(ddof=1) / math.sqrt(2), rel=1e-12)
    assert [x["sample"] for x in t["not_shear_jammed"]] == [2, 3]
    f = res["fits"][0.01]
    assert f["n_sizes"] == 3 and np.isfinite(f["phi_inf"]) and f["phi_inf_err"] > 0


def test_fit_recovers_exact_finite_size_law():
    Ns = np.array([1024, 2048, 4096, 8192])
    m = 0.843 - 0.5 * Ns ** -sj.X_FSS
    f = sj.fit_fss(Ns, m, np.full(4, 1e-4))
    assert f["phi_inf"] == pytest.approx(0.843, abs=1e-12)
    assert f["a"] == pytest.approx(0.5, rel=1e-9)
    assert f["chi2_dof"] < 1e-12
    # the error from the covariance: a noisier size widens it
    f2 = sj.fit_fss(Ns, m, np.array([1e-4, 1e-4, 1e-4, 1e-3]))
    assert f2["phi_inf_err"] > f["phi_inf_err"]
    assert math.isnan(sj.fit_fss(Ns[:2], m[:2], np.full(2, 1e-4))["phi_inf"])
    # the exponent free: found on the grid from exact data at another exponent
    Ns5 = np.array([1024, 2048, 4096, 8192, 16384])
    m5 = 0.8425 - 2.0 * Ns5 ** -0.9
    g = sj.fit_fss_free(Ns5, m5, np.full(5, 1e-4))
    assert g["x"] == pytest.approx(0.9, abs=1e-9) and g["chi2"] < 1e-12
    assert g["a"] == pytest.approx(2.0, rel=1e-8)
    assert g["phi_inf"] == pytest.approx(0.8425, abs=1e-10)
    assert g["phi_inf_range"][0] <= 0.8425 <= g["phi_inf_range"][1]
    assert g["x_range"][0] <= 0.9 <= g["x_range"][1]
    assert not math.isnan(sj.fit_fss_free(Ns, m, np.full(4, 1e-4))["phi_inf"])
    assert math.isnan(sj.fit_fss_free(Ns[:3], m[:3], np.full(3, 1e-4))["phi_inf"])


def test_table_round_trip_and_figure(folders, tmp_path):
    out = str(tmp_path / "jams.json")
    sj.export([str(folders)], out)
    a = sj.analyse([str(folders)])
    b = sj.analyse([out])
    assert json.dumps(sj._jsonable(a["table"])) == json.dumps(sj._jsonable(b["table"]))
    # a table and the folders it came from: every sample once
    c = sj.analyse([out, str(folders)])
    assert [t["n_samples"] for t in c["table"]] == [t["n_samples"] for t in a["table"]]
    with open(tmp_path / "other.json", "w") as fh:
        json.dump(dict(kind="something else", version=1), fh)
    with pytest.raises(ValueError, match="not a suspension jam table"):
        sj.load_table(str(tmp_path / "other.json"))
    from parflow.plot.suspension_jams import phi_sj_figure
    fig = phi_sj_figure(a)
    assert len(fig.axes) == 1 and len(fig.axes[0].lines) > 3


@pytest.mark.serial_only
def test_command_line(folders, tmp_path):
    def cli(*args):
        return subprocess.run([sys.executable, "-m", "parflow.post.suspension_jams", *args],
                              capture_output=True, text=True, cwd=ROOT, timeout=guard(120))
    res = cli(str(folders), "--json", str(tmp_path / "r.json"))
    assert res.returncode == 0, res.stderr
    assert "phi_inf" in res.stdout and json.load(open(tmp_path / "r.json"))["table"]
    for args, what in (([str(tmp_path / "nothing")], "no such file"),
                       ([str(tmp_path / "empty")], "no suspension sample found")):
        os.makedirs(tmp_path / "empty", exist_ok=True)
        res = cli(*args)
        assert res.returncode == 2 and what in res.stderr
        assert len(res.stderr.strip().splitlines()) == 1


def test_stopped_samples_are_lower_bounds(folders):
    """Samples stopped still flowing (status interrupted) enter as the phi they reached:
    listed apart, out of the means and the fit; a size with no jam yet is a row without a
    mean; the figure draws them as lower bounds."""
    ensemble(folders / "jams_N8192", 8192, [
        ("interrupted", [0.82, 0.8416], None),
        ("interrupted", [0.82, 0.8415], None),
        ("running", [0.82, 0.8410], None)])
    res = sj.analyse([str(folders)])
    rows = {t["N"]: t for t in res["table"]}
    t = rows[8192]
    assert (t["n_samples"], t["n_shear_jams"]) == (2, 0) and math.isnan(t["phi_mean"])
    assert [(x["status"], x["phi"]) for x in t["not_shear_jammed"]] == \
        [("interrupted", 0.8416), ("interrupted", 0.8415)]
    before = sj.analyse([str(folders / f"jams_N{n}") for n in (1024, 2048, 4096)])
    assert res["fits"][0.01] == before["fits"][0.01]            # the fit has no N = 8192
    lines = sj.format_table(res)
    row = [ln for ln in lines if ln.split()[:2] == ["0.01", "8192"]]
    assert len(row) == 1 and "interrupted at 0.8416 (still flowing)" in row[0] and "nan" not in row[0]
    from parflow.plot.suspension_jams import phi_sj_figure
    ax = phi_sj_figure(res).axes[0]
    up = [ln for ln in ax.lines if ln.get_marker() == "^"]
    assert len(up) == 1 and sorted(up[0].get_ydata()) == [0.8415, 0.8416, 0.8429]  # + N = 1024 complete
    assert up[0].get_label() == "still flowing at 0.01 per unit strain (a lower bound), 3"


def test_a_start_compressed_further_supersedes_its_capped_run(folders):
    """The same start (rate, N, sample seed) run with a smaller compress_to is a truncation
    of the sample compressed further: left out of the means, the fit and the figure, and
    counted; a capped run of another start stays in."""
    before = sj.analyse([str(folders)])
    ensemble(folders / "jams_N2048_capped", 2048, [
        ("jammed", [0.82, 0.840], dict()),                  # seed of jams_N2048 sample 0
        ("jammed", [0.82, 0.8398], dict(phi=0.8398, tau_b_shear=-30.0))], to=0.840)
    ensemble(folders / "jams_N2048_other", 2048, [
        ("jammed", [0.82, 0.840], dict())], to=0.840, seed0=7)   # another start: kept
    res = sj.analyse([str(folders)])
    rows = {(t["compress_rate"], t["N"]): t for t in res["table"]}
    t = rows[(0.01, 2048)]
    assert t["superseded"] == 2 and t["n_samples"] == 3
    assert sorted(t["phi_values"]) == [0.8400, 0.8405, 0.8411]
    assert rows[(0.01, 1024)]["superseded"] == 0
    assert rows[(0.01, 4096)]["phi_values"] == [0.8412, 0.8414]
    assert len(res["records"]) == len(before["records"]) + 1
    assert any("2 sample(s) left out" in ln for ln in sj.format_table(res))


def test_rate_figure_with_a_second_rate(folders):
    """With one rate there is no figure against the rate; with a second one it draws one
    mean per (N, rate), joined across the rates of each N, at the groups' means."""
    from parflow.plot.suspension_jams import _figures, phi_sj_rate_figure
    assert [name for name, _ in _figures(sj.analyse([str(folders)]))] == \
        ["suspension_jams_phiSJ"]
    ensemble(folders / "jams_N1024_fast", 1024, [
        ("jammed", [0.82, 0.8401], dict(phi=0.8401, tau_b_shear=-40.0)),
        ("jammed", [0.82, 0.8409], dict(phi=0.8409, tau_b_shear=-41.0))], rate=0.04)
    res = sj.analyse([str(folders)])
    assert [name for name, _ in _figures(res)] == \
        ["suspension_jams_phiSJ", "suspension_jams_rate"]
    ax = phi_sj_rate_figure(res).axes[0]
    means = [ln for ln in ax.lines if ln.get_marker() == "s"]
    assert len(means) == 3                                  # N = 1024, 2048, 4096
    n1024 = [ln for ln in means if len(ln.get_xdata()) == 2]
    assert len(n1024) == 1
    y = n1024[0].get_ydata()
    rows = {(t["compress_rate"], t["N"]): t["phi_mean"] for t in res["table"]}
    assert y[0] == pytest.approx(0.5 * (0.8381 + 0.8429)) == rows[(0.01, 1024)]
    assert y[1] == pytest.approx(0.8405) == rows[(0.04, 1024)]
    x = n1024[0].get_xdata()
    assert x[1] / x[0] == pytest.approx(4.0)


def single_run(path, status, phi_ts, strain_ts, jam=None, rate=0.02, to=0.840, seed=5,
               sigma=None):
    """A single flowing run's file (as runs/suspension_phi0.840_flowing_seed*.toml write
    them): phi and strain columns (and sigma, if given), /jam for a certified jam."""
    with h5py.File(path, "w") as f:
        f.attrs.update(format="parflow-run-1", model="suspension", status=status,
                       scene=SCENE.format(N=4096, rate=rate, to=to), sample_seed=seed,
                       git_commit="abc123")
        g = f.create_group("timeseries")
        g["phi"] = np.asarray(phi_ts, float)
        g["gamma"] = g["strain"] = np.asarray(strain_ts, float)
        if sigma is not None:
            g["sigma"] = np.asarray(sigma, float)
        if jam is not None:
            j = f.create_group("jam")
            j.attrs.update(certified=True, gamma=strain_ts[-1], support=7800, tau_b=-100.0,
                           strain_budget=3e-12, **jam)


def test_poisson_interval_is_garwoods():
    """The exact central 95 % interval of a Poisson mean (Garwood 1936; the tabulated values
    for 0, 1 and 5 events)."""
    for n, (lo, hi) in ((0, (0.0, 3.689)), (1, (0.0253, 5.572)), (5, (1.623, 11.668))):
        a, b = sj.poisson_interval(n)
        assert a == pytest.approx(lo, abs=6e-4) and b == pytest.approx(hi, abs=6e-4)


def test_jam_rate_at_constant_phi(tmp_path):
    """Single flowing runs pooled at their final phi: each exposed from the row where phi
    reached compress_to, a jam there counted, a jam while the discs swelled and a run that
    never got there left out; the command line reads the files themselves."""
    ramp = [0.820, 0.830, 0.840, 0.840, 0.840]
    single_run(tmp_path / "seed5.h5", "interrupted", ramp, [0.0, 0.5, 1.0, 2.0, 2.92])
    single_run(tmp_path / "seed6.h5", "jammed", ramp, [0.0, 0.5, 1.0, 1.6, 2.145], jam={})
    single_run(tmp_path / "seed7.h5", "jammed", [0.82, 0.83, 0.8395], [0.0, 0.5, 0.975],
               jam=dict(phi=0.8395, tau_b_shear=-80.0), seed=7)      # jammed while swelling
    single_run(tmp_path / "seed8.h5", "interrupted", [0.82, 0.83], [0.0, 0.5], seed=8)
    single_run(tmp_path / "seed9.h5", "running", ramp, [0.0, 0.5, 1.0, 1.1, 1.2], seed=9)
    recs = sj.read_sources([str(tmp_path)])
    by = {r["source"]: r for r in recs}
    assert sorted(by) == ["seed5", "seed6", "seed7", "seed8"]        # the running one left out
    assert by["seed5"]["strain_at_phi"] == pytest.approx(1.92)
    assert by["seed6"]["strain_at_phi"] == pytest.approx(1.145)
    assert by["seed6"]["constant_phi"] and by["seed6"]["shear_jam"]
    assert math.isnan(by["seed7"]["strain_at_phi"]) and math.isnan(by["seed8"]["strain_at_phi"])
    (row,) = sj.constant_phi_rates(recs)
    assert (row["N"], row["phi"], row["n_samples"], row["n_jams"]) == (4096, 0.84, 2, 1)
    assert row["strain"] == pytest.approx(3.065)
    assert row["rate"] == pytest.approx(1 / 3.065)
    lo, hi = sj.poisson_interval(1)
    assert row["rate_ci"] == pytest.approx([lo / 3.065, hi / 3.065])
    assert row["p_flow"] == pytest.approx(math.exp(-3.0 / 3.065))
    # the same samples from a table written before strain_at_phi existed: a compressed
    # sample's exposure is then unknown (out of the pool), an uncompressed one's its gamma
    old = [dict(r) for r in recs]
    for r in old:
        del r["strain_at_phi"]
    rest = dict(old[0], source="rest", compress_rate=0.0, compress_to=None, gamma=0.25,
                phi=0.84, status="complete", shear_jam=False, constant_phi=False)
    os.makedirs(tmp_path / "tables")
    path = tmp_path / "tables" / "old.json"
    with open(path, "w") as fh:
        json.dump(sj._jsonable(dict(kind=sj.JAMS_KIND, version=sj.JAMS_VERSION,
                                    samples=old + [rest])), fh)
    (row,) = sj.constant_phi_rates(sj.load_table(str(path)))
    assert (row["n_samples"], row["n_jams"], row["strain"]) == (1, 0, 0.25)
    # the files' records win over the table's (the same source and sample)
    (row,) = sj.constant_phi_rates(sj.read_sources([str(tmp_path), str(path)]))
    assert (row["n_samples"], row["n_jams"]) == (3, 1)
    assert row["strain"] == pytest.approx(3.315)
    # an uncertified "jammed" (before certificates) cannot be placed: counted apart
    single_run(tmp_path / "seed10.h5", "jammed", ramp, [0.0, 0.5, 1.0, 1.2, 1.3], seed=10)
    (row,) = sj.constant_phi_rates(sj.read_sources([str(tmp_path)]))
    assert row["uncertified"] == 1 and row["n_samples"] == 2


def _peaks_by_loop(sig, on, off, steps=None, quiet=0.0):
    """Stress excursions the plain way: a state machine over the rows (``steps``: each row's
    strain; an excursion ends once the rows below ``off`` in a row add up to ``quiet``)."""
    out, inside, low = [], False, 0.0
    for k, x in enumerate(sig):
        if x < off:
            low += steps[k] if steps is not None else math.inf
            if inside and low >= quiet:
                inside = False
            continue
        low = 0.0
        if not inside and x >= on:
            inside = True
            out.append(x)
        elif inside:
            out[-1] = max(out[-1], x)
    return out


def test_excursion_peaks():
    """An excursion runs from sigma >= on to the first row below off (hovering between the two
    is one excursion), the last one may be open; the vectorised peaks equal a plain state
    machine's on random series."""
    e = sj.excursion_peaks
    assert e([10, 2e3, 500, 3e3, 50, 5e4, 1e5, 20, 1e3]).tolist() == [3e3, 1e5, 1e3]
    assert e([]).size == 0 and e([5, 99, 999]).size == 0 and e([2e3]).tolist() == [2e3]
    assert e([1e3, 99.9, 1e3, 100.0, 7e3], on=1e3, off=1e2).tolist() == [1e3, 7e3]
    # with the strain: a dip of little strain (after a cut step) does not end an excursion,
    # low rows that add up to the quiet strain do
    sig = [2e3, 5.0, 4e4, 50, 60, 2e3]
    strain = np.cumsum([1e-4, 1e-6, 1e-5, 6e-4, 6e-4, 1e-4])
    assert e(sig, strain, quiet=1e-3).tolist() == [4e4, 2e3]
    assert e(sig, strain, quiet=2e-3).tolist() == [4e4]
    assert e(sig).tolist() == e(sig, strain, quiet=0.0).tolist() == [2e3, 4e4, 2e3]
    rng = np.random.default_rng(3)
    for _ in range(20):
        n = int(rng.integers(1, 400))
        sig, steps = 10 ** rng.uniform(0, 5, n), 10 ** rng.uniform(-6, -3, n)
        assert e(sig, on=1e3, off=1e2).tolist() == _peaks_by_loop(sig, 1e3, 1e2)
        assert e(sig, np.cumsum(steps), quiet=1e-3).tolist() == \
            _peaks_by_loop(sig, 1e3, 1e2, np.r_[0.0, steps[1:]], 1e-3)


def test_excursions_at_constant_phi_pooled(tmp_path):
    """A run's excursions are those of its rows at the final phi (the rows of its exposure);
    per (N, phi) they are pooled over the samples that recorded them, per unit strain; a
    sample from a table written before excursions were recorded is left out of them (not of
    the jams); the text output and the figure show them."""
    from parflow.plot.suspension_jams import _figures, excursion_figure
    ramp = [0.820, 0.830, 0.840, 0.840, 0.840, 0.840]
    # 5e3 while the discs still swell: not counted
    single_run(tmp_path / "a.h5", "interrupted", ramp, [0.0, 0.5, 1.0, 1.5, 2.0, 3.0],
               sigma=[50, 5e3, 200, 2e4, 50, 3e6])
    single_run(tmp_path / "b.h5", "jammed", ramp[:5], [0.0, 0.5, 1.0, 1.5, 2.0], jam={},
               seed=6, sigma=[50, 60, 2e3, 90, 2e8])
    recs = sj.read_sources([str(tmp_path)])
    by = {r["source"]: r for r in recs}
    assert by["a"]["excursion_peaks"] == [2e4, 3e6]
    assert by["b"]["excursion_peaks"] == [2e3, 2e8]          # the jam: its open excursion
    table = sj.export([str(tmp_path)], str(tmp_path / "t.json"))    # the peaks kept in a table
    assert {r["source"]: r["excursion_peaks"] for r in sj.load_table(table)} == \
        {"a": [2e4, 3e6], "b": [2e3, 2e8]}
    os.remove(table)
    (row,) = sj.constant_phi_rates(recs)
    ex = row["excursions"]
    assert (ex["n_samples"], ex["strain"]) == (2, pytest.approx(3.0))
    assert ex["levels"] == list(sj.EXCURSION_LEVELS)
    assert ex["counts"] == [4, 3, 2, 2, 1]
    assert ex["per_strain"] == pytest.approx([4 / 3, 1.0, 2 / 3, 2 / 3, 1 / 3])
    assert (ex["jams"], ex["jams_per_strain"]) == (1, pytest.approx(1 / 3))
    # a record without peaks (an older table): out of the excursions' pool only
    old = dict(by["b"], source="old", excursion_peaks=math.nan)
    (row,) = sj.constant_phi_rates(recs + [old])
    assert row["n_samples"] == 3 and row["excursions"]["n_samples"] == 2
    assert row["n_jams"] == 2 and row["excursions"]["jams"] == 1
    text = "\n".join(sj.format_rates([row]))
    assert "stress excursions (sigma >= 1000 until below 100 for 0.001 strain) of 2 samples in 3.00 strain" in text
    res = dict(table=[], records=[], fits={}, fits_free={}, rates=[row])
    assert "suspension_excursions" in [n for n, _ in _figures(res)]
    ax = excursion_figure(res).axes[0]
    (line,) = [ln for ln in ax.lines if ln.get_marker() == "o"]
    assert np.allclose(line.get_ydata(), ex["per_strain"])
    assert [ln.get_ydata()[0] for ln in ax.lines if ln.get_linestyle() == "--"] == \
        [pytest.approx(1 / 3.0)]
    res["rates"] = [dict(row, excursions=dict(ex, n_samples=0, strain=0.0))]
    assert "suspension_excursions" not in [n for n, _ in _figures(res)]


def test_a_branch_replaces_the_run_it_was_branched_from(tmp_path):
    """A single run continued in a branch (its rows up to the branch point, then more) is
    counted once, as the branch; read from a jam table as well."""
    ramp = [0.820, 0.830, 0.840, 0.840]
    single_run(tmp_path / "seed5.h5", "complete", ramp, [0.0, 0.5, 1.0, 4.0])
    single_run(tmp_path / "seed5_on.h5", "interrupted", ramp + [0.840], [0.0, 0.5, 1.0, 4.0, 5.5])
    with h5py.File(tmp_path / "seed5_on.h5", "a") as f:
        f.attrs["branched_from"] = f"{tmp_path / 'seed5.h5'} at step 3"
    single_run(tmp_path / "seed6.h5", "complete", ramp, [0.0, 0.5, 1.0, 2.0], seed=6)
    recs = sj.read_sources([str(tmp_path)])
    assert sorted(r["source"] for r in recs) == ["seed5_on", "seed6"]
    assert {r["source"]: r["branched_from"] for r in recs} == {"seed5_on": "seed5", "seed6": ""}
    (row,) = sj.constant_phi_rates(recs)
    assert row["strain"] == pytest.approx(4.5 + 1.0)
    table = sj.export([str(tmp_path)], str(tmp_path / "t.json"))
    os.makedirs(tmp_path / "parent")
    os.replace(tmp_path / "seed5.h5", tmp_path / "parent" / "seed5.h5")
    recs = sj.read_sources([str(tmp_path / "parent"), table])
    assert sorted(r["source"] for r in recs) == ["seed5_on", "seed6"]


def test_jam_rate_figure():
    """Jams per unit strain against N at one phi: a size with jams is a point with its
    Poisson interval, a size with none its upper bound (a triangle pointing down); a phi
    with one size only has no figure."""
    from parflow.plot.suspension_jams import _figures, jam_rate_figure

    def row(N, phi, n, strain):
        lo, hi = sj.poisson_interval(n)
        return dict(N=N, phi=phi, n_samples=3, n_jams=n, strain=strain, rate=n / strain,
                    rate_ci=[lo / strain, hi / strain])
    res = dict(table=[], records=[], fits={}, fits_free={},
               rates=[row(1024, 0.84, 7, 0.54), row(2048, 0.84, 3, 1.5), row(4096, 0.84, 0, 5.0),
                      row(4096, 0.835, 1, 2.0)])
    ax = jam_rate_figure(res).axes[0]
    points = [ln for ln in ax.lines if ln.get_marker() == "o"]
    down = [ln for ln in ax.lines if ln.get_marker() == "v"]
    assert len(points) == 1 and list(points[0].get_xdata()) == [1024, 2048]
    assert np.allclose(points[0].get_ydata(), [7 / 0.54, 3 / 1.5])
    assert len(down) == 1 and list(down[0].get_xdata()) == [4096]
    assert down[0].get_ydata()[0] == pytest.approx(sj.poisson_interval(0)[1] / 5.0)
    assert len(ax.texts) == 3 and ax.texts[2].get_text() == "0 in 5"
    assert "suspension_jams_per_strain" in [n for n, _ in _figures(res)]
    res["rates"] = res["rates"][-1:]
    assert "suspension_jams_per_strain" not in [n for n, _ in _figures(res)]


@pytest.mark.serial_only
def test_command_line_on_run_files(tmp_path):
    ramp = [0.820, 0.830, 0.840, 0.840]
    single_run(tmp_path / "a.h5", "interrupted", ramp, [0.0, 0.5, 1.0, 2.5])
    single_run(tmp_path / "b.h5", "jammed", ramp, [0.0, 0.5, 1.0, 1.5], jam={}, seed=6)
    res = subprocess.run([sys.executable, "-m", "parflow.post.suspension_jams",
                          str(tmp_path / "a.h5"), str(tmp_path / "b.h5")],
                         capture_output=True, text=True, cwd=ROOT, timeout=guard(120))
    assert res.returncode == 0, res.stderr
    lines = res.stdout.splitlines()
    k = [i for i, ln in enumerate(lines) if ln.startswith("jams at constant phi")]
    assert len(k) == 1 and lines[k[0] + 1].split()[:5] == ["4096", "0.8400", "2", "1", "2.00"]
    assert "a: interrupted at 0.8400 (still flowing)" in res.stdout
    with open(tmp_path / "c.h5", "w") as fh:
        fh.write("not hdf5")
    res = subprocess.run([sys.executable, "-m", "parflow.post.suspension_jams",
                          str(tmp_path / "c.h5")],
                         capture_output=True, text=True, cwd=ROOT, timeout=guard(120))
    assert res.returncode == 2 and "not a readable suspension run file" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1


def test_exposure_starts_where_phi_reached_compress_to():
    """The exposure at the final phi and the excursions are counted from the first row where
    phi reached compress_to (post.ensemble.final_phi_row); a run that never got there has
    neither."""
    from parflow.post.ensemble import final_phi_row, strain_at_final_phi
    phi = [0.82, 0.83, 0.84, 0.84, 0.84]
    strain = [0.0, 0.5, 1.0, 1.7, 2.5]
    assert final_phi_row(phi, 0.84) == 2
    assert strain_at_final_phi(strain, phi, 0.84) == pytest.approx(1.5)
    assert final_phi_row(phi, 0.845) is None
    assert math.isnan(strain_at_final_phi(strain, phi, 0.845))
    assert math.isnan(strain_at_final_phi([], phi, 0.84))
