"""Ensembles (parflow.ensemble, parflow.post.ensemble): the seed rule, samples on groups of
ranks equal to the same samples run one by one (bit for bit, whatever the number of ranks and
the order), a failing sample that stops neither the others nor the job, an interrupted
ensemble restarted, and the summary's statistics against numpy on the sample files."""
import os
import shutil
import subprocess
import sys

import h5py
import numpy as np
import pytest

from parflow.ensemble import SEED_RULE, sample_seed, sample_text
from parflow.errors import InputError
from parflow.scene import load_scene
from systems import SUSPENSION_ENSEMBLE_SCENE
from hang_guard import guard

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from reference_runs import flatten  # noqa: E402  (VOLATILE entries left out)

# the tests that launch their own processes (mpirun inside) run on one rank only
serial_only = pytest.mark.serial_only

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

SCENE = """
title = "ensemble test"
seed = 5
[model]
name = "chain"
N = 60
epsilon = 0.1
mu = 0
[[protocol.leg]]
direction = "forward"
V2_above = 300.0
[[protocol.leg]]
direction = "reverse"
strain = 0.004
[observables]
analysis_quantity = "V2"
analysis_per_decade = 2
[output]
path = "unused.h5"
checkpoint_every = 10
"""

# runs parflow.shear with a failure or a stop injected into one sample (in that process)
HOOK = """
import sys
import parflow.ensemble as E
import parflow.protocol as P
from parflow.state import STOPS
mode, target, at = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
current = [None]
run_sample = E.run_sample
def wrapped(group, folder, k, *a, **kw):
    current[0] = k
    return run_sample(group, folder, k, *a, **kw)
E.run_sample = wrapped
advance = P.Clock.advance
def hooked(self, dg):
    advance(self, dg)
    if mode in ("fail", "stop") and current[0] == target and self.step == at:
        if mode == "fail":
            raise RuntimeError(f"injected failure of sample {target}")
        STOPS.handle(2)          # as if SIGTERM arrived during this step
P.Clock.advance = hooked
if mode == "jam":                # the engine's step raises Jammed (as at min_dgamma)
    import parflow.dynamics.engines as EN
    from parflow.dynamics.heun import Jammed
    step, clock_steps = EN.BondedEngine.step, [0]
    def jam_once(self, *a, **kw):
        clock_steps[0] += current[0] == target
        if current[0] == target and clock_steps[0] == at:
            raise Jammed("injected jam")
        return step(self, *a, **kw)
    EN.BondedEngine.step = jam_once
if mode == "idle-stop":          # world rank `target` takes a SIGTERM while it waits idle
    from mpi4py import MPI
    barrier, taken = E.idle_barrier, []
    def idle(comm, *a, **kw):
        if MPI.COMM_WORLD.Get_rank() == target and not taken:
            taken.append(1)
            STOPS.handle(2)
        return barrier(comm, *a, **kw)
    E.idle_barrier = idle
import parflow.shear
sys.exit(parflow.shear.main(sys.argv[4:]))
"""


def _env():
    return dict(os.environ, PYTHONPATH=ROOT)


def shear(*args, mpi=0, timeout=120, hook=None, cwd=None):
    cmd = [sys.executable, "-m", "parflow.shear"] if hook is None else \
        [sys.executable, "-c", HOOK, *map(str, hook)]
    cmd += [*map(str, args)]
    if mpi:
        cmd = [shutil.which("mpirun") or "mpirun", "-n", str(mpi)] + cmd
    return subprocess.run(cmd, capture_output=True, text=True, timeout=guard(timeout), env=_env(), cwd=cwd)


def scene(tmp_path, text=SCENE):
    p = tmp_path / "scene.toml"
    p.write_text(text)
    return p


# a restarted run's own record, and the solver's counters, which count the last session only
RESTART = {"@restarted_at_step", "@n_factorisations", "@n_reused_factor", "@n_reuse_failed",
           "@retried_after"}


def content(path, restarted=False) -> dict:
    """Every dataset and attribute of a sample file but the machine's (wall times, ...)."""
    with h5py.File(path) as f:
        return {k: v for k, v in flatten(f).items() if not (restarted and k in RESTART)}


def assert_same(a, b, restarted=False):
    ca, cb = content(a, restarted), content(b, restarted)
    assert ca.keys() == cb.keys(), set(ca) ^ set(cb)
    for k in ca:
        assert np.array_equal(ca[k], cb[k]) or (isinstance(ca[k], np.ndarray) and
                                                np.array_equal(ca[k], cb[k], equal_nan=True)), k


@pytest.fixture(scope="module")
def serial(tmp_path_factory):
    """The reference: 5 samples, one after the other, on one rank."""
    d = tmp_path_factory.mktemp("serial")
    res = shear(scene(d), "--samples", 5, "--output", d / "ens", "--quiet", "--no-plots")
    assert res.returncode == 0, res.stderr
    return d / "ens"


def sample(folder, k):
    return os.path.join(folder, f"sample_{k:04d}.h5")


# ---------------------------------------------------------------------------------------
def test_seed_rule():
    """seed_k depends on (seed, k) only: numpy's SeedSequence(seed).spawn(K)[k], 63 bits."""
    seeds = [sample_seed(5, k) for k in range(200)]
    assert len(set(seeds)) == 200 and all(0 <= s < 2**63 for s in seeds)
    spawned = np.random.SeedSequence(5).spawn(200)
    assert seeds == [int(s.generate_state(1, np.uint64)[0] >> np.uint64(1)) for s in spawned]
    assert sample_seed(5, 7) == seeds[7] and sample_seed(6, 7) != seeds[7]
    assert "SeedSequence" in SEED_RULE
    # the sample's scene text: the same scene but for its seed
    text = sample_text(SCENE, seeds[3])
    a, b = load_scene(SCENE), load_scene(text)
    assert b["seed"] == seeds[3]
    assert {**a, "seed": 0, "text": ""} == {**b, "seed": 0, "text": ""}
    no_seed = SCENE.replace("seed = 5\n", "")
    assert load_scene(sample_text(no_seed, 11))["seed"] == 11
    with pytest.raises(InputError, match="cannot set each sample's seed"):
        sample_text(SCENE.replace("seed = 5", "\"seed\" = 5"), 1)   # a quoted key


@serial_only
def test_serial_samples_record_index_and_seed(serial):
    with h5py.File(os.path.join(serial, "ensemble.h5")) as f:
        assert list(f["status"].asstr()[()]) == ["complete"] * 5
        assert list(f["seed"][()]) == [sample_seed(5, k) for k in range(5)]
        assert f.attrs["samples"] == 5 and f.attrs["seed"] == 5
    for k in range(5):
        with h5py.File(sample(serial, k)) as f:
            assert f.attrs["sample"] == k and f.attrs["sample_seed"] == sample_seed(5, k)
            assert f.attrs["status"] == "complete"
    # different seeds, different samples
    with h5py.File(sample(serial, 0)) as f0, h5py.File(sample(serial, 1)) as f1:
        assert not np.array_equal(f0["initial/s"][()], f1["initial/s"][()])


@serial_only
def test_two_samples_on_two_ranks_equal_serial(serial, tmp_path):
    res = shear(scene(tmp_path), "--samples", 2, "--output", tmp_path / "ens", "--quiet",
                "--no-plots", mpi=2)
    assert res.returncode == 0, res.stderr
    for k in range(2):
        assert_same(sample(tmp_path / "ens", k), sample(serial, k))


@serial_only
def test_every_group_logs_its_sample(tmp_path):
    """Two samples on two ranks, not quiet: each sample's lines come from its own group's
    leader, marked with the sample's index (before, only world rank 0's sample was heard);
    the ensemble's own lines once."""
    res = shear(scene(tmp_path), "--samples", 2, "--output", tmp_path / "ens", "--no-plots", mpi=2)
    assert res.returncode == 0, res.stderr
    lines = res.stderr.splitlines()
    for k in range(2):
        own = [ln for ln in lines if ln.startswith(f"[parflow] sample {k}: ")]
        assert sum(" steps, " in ln and "wrote" in ln for ln in own) == 1, res.stderr
        assert any("chain:" in ln for ln in own), res.stderr
    assert sum(ln.startswith("[parflow] ensemble: 2 samples (2 to run)") for ln in lines) == 1, res.stderr
    assert not any("sample" not in ln and " steps, " in ln for ln in lines), res.stderr


def test_sample_lines_marked_and_the_job_line_not():
    """While a sample runs, its lines are marked "sample k:"; the job's progress line, which
    world rank 0's thread logs meanwhile (with ensemble_line), is not."""
    import logging
    from parflow.ensemble import _SampleFormatter
    fmt = _SampleFormatter(3)
    rec = logging.LogRecord("parflow", logging.INFO, __file__, 1, "step %d", (7,), None)
    assert fmt.format(rec) == "[parflow] sample 3: step 7"
    job = logging.LogRecord("parflow", logging.INFO, __file__, 1, "%s", ("ensemble: 1/2",), None)
    job.ensemble_line = True
    assert fmt.format(job) == "[parflow] ensemble: 1/2"


@serial_only
def test_groups_of_two_ranks(serial, tmp_path):
    """ranks_per_sample = 2 on 2 ranks: one group, each sample on both ranks; the same samples
    as on one rank to solver round-off (the chain's replicated solve: bit for bit here)."""
    res = shear(scene(tmp_path), "--samples", 2, "--ranks-per-sample", 2, "--output",
                tmp_path / "ens", "--quiet", "--no-plots", mpi=2)
    assert res.returncode == 0, res.stderr
    for k in range(2):
        with h5py.File(sample(tmp_path / "ens", k)) as a, h5py.File(sample(serial, k)) as b:
            assert a.attrs["n_ranks"] == 2 and a.attrs["sample_seed"] == b.attrs["sample_seed"]
            for q in ("gamma", "sigma", "V2"):
                np.testing.assert_allclose(a["timeseries"][q][()], b["timeseries"][q][()],
                                           rtol=1e-10, atol=0)


@serial_only
def test_queue_five_samples_on_three_groups(serial, tmp_path):
    """K = 5 on 3 ranks: a queue; every sample is the serial one, whoever ran it."""
    res = shear(scene(tmp_path), "--samples", 5, "--output", tmp_path / "ens", "--quiet",
                "--no-plots", mpi=3, timeout=180)
    assert res.returncode == 0, res.stderr
    for k in range(5):
        assert_same(sample(tmp_path / "ens", k), sample(serial, k))
    assert not os.path.exists(tmp_path / "ens" / ".claims")


@serial_only
def test_failing_sample_does_not_stop_the_others(serial, tmp_path):
    """Sample 1 raises mid-run (an exception no solver check expected): it is recorded as
    failed, the other samples run to the end (equal to the serial ones), the job exits 1
    with one line naming the sample; no hang."""
    folder = tmp_path / "ens"
    res = shear(scene(tmp_path), "--samples", 4, "--output", folder, "--quiet", "--no-plots",
                mpi=2, hook=("fail", 1, 10), timeout=120)
    assert res.returncode == 1, res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.startswith("parflow.shear: ensemble:")]
    assert len(lines) == 1 and "1 of 4 samples failed (sample 1: RuntimeError: injected" in lines[0], res.stderr
    assert "Traceback" not in res.stderr
    with h5py.File(folder / "ensemble.h5") as f:
        st = list(f["status"].asstr()[()])
        assert st == ["complete", "failed", "complete", "complete"], st
        assert "injected failure" in f["message"].asstr()[1]
    with h5py.File(sample(folder, 1)) as f:
        assert f.attrs["status"] == "failed"
    for k in (0, 2, 3):
        assert_same(sample(folder, k), sample(serial, k))
    with h5py.File(folder / "summary.h5") as f:
        assert list(f["samples/used"][()]) == [0, 2, 3]
    # a restart skips the failed sample as well as the finished ones
    res = shear("--restart", folder, "--quiet", "--no-plots")
    assert res.returncode == 1 and "1 of 4 samples failed" in res.stderr
    with h5py.File(sample(folder, 1)) as f:
        assert f.attrs["status"] == "failed"
    # --retry runs it again; it failed before its first checkpoint (step 10, between the
    # step and its row: no checkpoint was written then), so it starts afresh
    mtime0 = os.path.getmtime(sample(folder, 0))
    res = shear("--restart", folder, "--retry", "--quiet", "--no-plots")
    assert res.returncode == 0, res.stderr
    assert os.path.getmtime(sample(folder, 0)) == mtime0
    assert_same(sample(folder, 1), sample(serial, 1))
    with h5py.File(folder / "ensemble.h5") as f:
        assert list(f["status"].asstr()[()]) == ["complete"] * 4


@serial_only
def test_retry_continues_a_failed_sample_from_its_checkpoint(serial, tmp_path):
    """Sample 1 fails at step 15, between the step and its row: the file keeps the checkpoint
    of step 10 (not one of the half-done step 15).  --restart FOLDER --retry continues it
    from there: the uninterrupted sample 1, bit for bit; the file says what it was retried
    after."""
    folder = tmp_path / "ens"
    res = shear(scene(tmp_path), "--samples", 2, "--output", folder, "--quiet", "--no-plots",
                hook=("fail", 1, 15))
    assert res.returncode == 1, res.stderr
    with h5py.File(sample(folder, 1)) as f:
        assert f.attrs["status"] == "failed" and f["checkpoint"].attrs["step"] == 10
    res = shear("--restart", folder, "--retry", "--quiet", "--no-plots")
    assert res.returncode == 0, res.stderr
    assert "starts afresh" not in res.stderr
    with h5py.File(sample(folder, 1)) as f:
        assert f.attrs["status"] == "complete" and f.attrs["restarted_at_step"] == 10
        assert str(f.attrs["retried_after"]).startswith("failed: RuntimeError: injected failure")
    for k in (0, 1):
        assert_same(sample(folder, k), sample(serial, k), restarted=k == 1)


@serial_only
@pytest.mark.parametrize("mpi", [0, 2])
def test_interrupted_ensemble_restarts(serial, tmp_path, mpi):
    """A stop (SIGTERM) in sample 1 at step 15: the job exits 143 with a checkpoint in
    sample 1; --restart FOLDER skips the finished samples, continues sample 1 and starts
    the rest; every sample is then bit-identical to the uninterrupted serial run."""
    folder = tmp_path / "ens"
    res = shear(scene(tmp_path), "--samples", 4, "--output", folder, "--quiet", "--no-plots",
                mpi=mpi, hook=("stop", 1, 15))
    assert res.returncode == 143, res.stderr
    with h5py.File(sample(folder, 1)) as f:
        assert f.attrs["status"] == "interrupted" and "checkpoint" in f
        assert f["checkpoint"].attrs["step"] == 15
    with h5py.File(sample(folder, 0)) as f:
        assert f.attrs["status"] == "complete"
    mtime0 = os.path.getmtime(sample(folder, 0))
    res = shear("--restart", folder, "--quiet", "--no-plots", mpi=mpi)
    assert res.returncode == 0, res.stderr
    assert os.path.getmtime(sample(folder, 0)) == mtime0          # skipped, not rerun
    with h5py.File(sample(folder, 1)) as f:
        assert f.attrs["restarted_at_step"] == 15
    for k in range(4):
        assert_same(sample(folder, k), sample(serial, k), restarted=k == 1)
    with h5py.File(folder / "ensemble.h5") as f:
        assert list(f["status"].asstr()[()]) == ["complete"] * 4


@serial_only
def test_retry_continues_a_jammed_sample(serial, tmp_path):
    """Sample 1 stops "jammed" at its 15th step (injected; the run writes its checkpoint
    there): a restart skips it, --retry continues it to the uninterrupted sample 1."""
    folder = tmp_path / "ens"
    res = shear(scene(tmp_path), "--samples", 2, "--output", folder, "--quiet", "--no-plots",
                hook=("jam", 1, 15))
    assert res.returncode == 0, res.stderr                 # jammed is a finished sample
    with h5py.File(sample(folder, 1)) as f:
        assert f.attrs["status"] == "jammed" and f["checkpoint"].attrs["step"] == 14
    mtime = os.path.getmtime(sample(folder, 1))
    assert shear("--restart", folder, "--quiet", "--no-plots").returncode == 0
    assert os.path.getmtime(sample(folder, 1)) == mtime    # skipped without --retry
    res = shear("--restart", folder, "--retry", "--quiet", "--no-plots")
    assert res.returncode == 0, res.stderr
    with h5py.File(sample(folder, 1)) as f:
        assert f.attrs["status"] == "complete" and f.attrs["restarted_at_step"] == 14
        assert str(f.attrs["retried_after"]) == "jammed: injected jam"
    # the jammed run's analysis at its stop stays in the file: the rest is the serial run's
    a, b = content(sample(folder, 1), True), content(sample(serial, 1), True)
    extra = sorted(set(a) - set(b))
    assert all(k.startswith("analysis/00000014") for k in extra), extra
    for k in b:
        assert np.array_equal(a[k], b[k]) or np.array_equal(a[k], b[k], equal_nan=True), k


@serial_only
def test_a_signal_on_an_idle_rank_waits_for_the_running_group(serial, tmp_path):
    """One sample on two ranks: rank 1's group has none and waits; a SIGTERM there is held
    until rank 0's group has finished its sample (which it does, unharmed: equal to the
    serial sample 0); then the job stops with exit 143 and one line -- no MPI_Abort."""
    folder = tmp_path / "ens"
    res = shear(scene(tmp_path), "--samples", 1, "--output", folder, "--quiet", "--no-plots",
                mpi=2, hook=("idle-stop", 1, 1))
    assert res.returncode == 143, res.stderr
    assert "MPI_ABORT" not in res.stderr and res.stderr.count("parflow.shear: terminated") == 1, res.stderr
    assert_same(sample(folder, 0), sample(serial, 0))


@serial_only
def test_summary_against_numpy(serial):
    """The summary's means, standard errors and counts, and its averaged <V^2> curve,
    recomputed from the sample files with numpy."""
    files = [h5py.File(sample(serial, k)) for k in range(5)]
    try:
        with h5py.File(os.path.join(serial, "summary.h5")) as s:
            assert s.attrs["n_used"] == 5
            for col, name in (("sigma", "final_sigma"), ("V2", "final_V2"), ("gamma", "final_gamma")):
                v = np.array([f["timeseries"][col][-1] for f in files])
                g = s["scalars"][name]
                assert np.array_equal(g["values"][()], v)
                assert np.isclose(g["mean"][()], v.mean(), rtol=1e-14)
                assert np.isclose(g["sem"][()], v.std(ddof=1) / np.sqrt(5), rtol=1e-12)
                assert g["count"][()] == 5
            c = s["curves/V2_forward"]
            x = c["x"][()]
            rows = []
            for f in files:
                ts = f["timeseries"]
                fw = ts["direction"][()] > 0
                gc = f["model"].attrs["gamma_c"]
                xx, yy = gc - ts["gamma"][()][fw], ts["V2"][()][fw]
                o = np.argsort(xx)
                lx, ly = np.log(xx[o]), np.log(yy[o])
                r = np.full(x.size, np.nan)
                inside = (np.log(x) >= lx[0]) & (np.log(x) <= lx[-1])
                r[inside] = np.exp(np.interp(np.log(x[inside]), lx, ly))
                rows.append(r)
            rows = np.array(rows)
            assert np.allclose(c["values"][()], rows, rtol=1e-12, equal_nan=True)
            n = np.isfinite(rows).sum(axis=0)
            assert np.array_equal(c["count"][()], n)
            full = n == 5
            assert np.allclose(c["mean"][()][full], rows[:, full].mean(axis=0), rtol=1e-12)
            assert np.allclose(c["sem"][()][full], rows[:, full].std(axis=0, ddof=1) / np.sqrt(5),
                               rtol=1e-10)
            # a fitted exponent per sample: its mean and error; the ensemble fit and its
            # jackknife error are finite and near the chain's forward exponent -(3 + mu)/(1 + mu)
            e = s["fits/forward.attr.V2.exponent"]
            assert e["count"][()] == 5 and np.isfinite(e["sem"][()])
            fit = dict(s["ensemble_fits/V2_forward_exponent"].attrs)
            assert np.isfinite(fit["value"]) and 0 < fit["jackknife_err"] < 1
            assert abs(fit["value"] + 3) < 1.5
            # the profile C(n) at each sample's last forward analysis instant
            C = s["curves/profile_C_n"]
            last = []
            for f in files:
                fw_steps = f["timeseries"]["step"][()][f["timeseries"]["direction"][()] > 0]
                steps = sorted(int(k) for k in f["analysis"] if int(k) <= fw_steps.max())
                last.append(f["analysis"][f"{steps[-1]:08d}"]["C_n"][()])
            last = np.array(last)
            assert C["x"].size == last.shape[1]             # same N: the grid is n itself
            assert np.allclose(C["mean"][()], last.mean(axis=0), rtol=1e-12, atol=1e-15)
            assert np.allclose(C["sem"][()], last.std(axis=0, ddof=1) / np.sqrt(5), rtol=1e-9, atol=1e-15)
            jam = dict(s["ensemble_fits/jamming_rate"].attrs)      # none jammed here
            strain = sum(f["timeseries"]["strain"][-1] for f in files)
            assert jam["n_jammed"] == 0 and jam["value"] == 0 and np.isclose(jam["strain"], strain)
    finally:
        for f in files:
            f.close()


SUSPENSION_SCENE = SUSPENSION_ENSEMBLE_SCENE.format(phi="0.80", ensemble="")


def _window_instants_h5(path, from_strain):
    """The analysis instants of a sample file at strain >= from_strain, read with h5py."""
    with h5py.File(path) as f:
        g = f["analysis"]
        out = []
        for k in sorted(g):
            a = g[k]
            if a.attrs["strain"] >= from_strain - 1e-12:
                out.append(dict(a.attrs) | {n: a[n][()] for n in a})
        return out


@serial_only
def test_suspension_summary_against_numpy(tmp_path):
    """A suspension ensemble's summary: per sample the window averages of sigma, p, mu = sigma/p
    and z (post.suspension.suspension_fits of each sample file), and their mean and error."""
    from parflow.post.runs import load
    from parflow.post.suspension import suspension_fits
    res = shear(scene(tmp_path, SUSPENSION_SCENE), "--samples", 3, "--output", tmp_path / "ens",
                "--quiet", "--no-plots")
    assert res.returncode == 0, res.stderr
    fits = [suspension_fits(load(sample(tmp_path / "ens", k))) for k in range(3)]
    with h5py.File(tmp_path / "ens" / "summary.h5") as s:
        for q, name in (("sigma", "sigma"), ("pressure", "pressure"), ("mu", "stress_ratio"),
                        ("z", "z")):
            v = np.array([f[q][0] for f in fits])
            assert np.all(np.isfinite(v)) and np.ptp(v) > 0, q     # samples differ
            g = s[f"fits/{name}.mean"]
            assert np.array_equal(g["values"][()], v), q
            assert np.isclose(g["mean"][()], v.mean(), rtol=1e-14)
            assert np.isclose(g["sem"][()], v.std(ddof=1) / np.sqrt(3), rtol=1e-12)
        mu = s["fits/stress_ratio.mean/values"][()]
        sig, p = s["fits/sigma.mean/values"][()], s["fits/pressure.mean/values"][()]
        assert np.all((mu > 0) & (mu < 1)) and np.allclose(mu, sig / p, rtol=0.3)
        # P(f/<f>), C(r): each sample's mean over its window's instants (C(r) on the bins all
        # instants share), then the mean over samples; delta_gamma * sigma per sample
        inst = [_window_instants_h5(sample(tmp_path / "ens", k), 0.1) for k in range(3)]
        assert all(len(i) >= 2 for i in inst)
        P = np.array([np.mean([a["force_P"] for a in i], axis=0) for i in inst])
        edges = inst[0][0]["force_edges"]
        g = s["curves/profile_force_P"]
        assert np.allclose(g["x"][()], np.sqrt(edges[:-1] * edges[1:]), rtol=1e-15)
        assert np.allclose(g["values"][()], P, rtol=1e-13, equal_nan=True)
        assert np.allclose(g["mean"][()], np.mean(P, axis=0), rtol=1e-12, equal_nan=True)
        assert np.allclose(g["sem"][()], np.std(P, axis=0, ddof=1) / np.sqrt(3), rtol=1e-10,
                           equal_nan=True)
        # each sample's P(f/<f>) is a density of f/<f>: it integrates to one over the bins
        assert np.allclose(np.sum(P * np.diff(edges), axis=1), 1.0, rtol=1e-12)
        m = min(a["corr_r"].size for i in inst for a in i)
        C = np.array([np.mean([a["corr_C"][:m] for a in i], axis=0) for i in inst])
        g = s["curves/profile_corr_C"]
        assert np.array_equal(g["x"][()], inst[0][0]["corr_r"][:m])
        assert np.allclose(g["values"][()], C, rtol=1e-13, equal_nan=True)
        dgs = np.array([np.mean([a["delta_gamma"] * a["frozen_sigma"] for a in i]) for i in inst])
        assert np.all(np.isfinite(dgs)) and np.all(dgs > 0)
        assert np.allclose(s["fits/delta_gamma_sigma.mean/values"][()], dgs, rtol=1e-13)


def test_jamming_rate_poisson():
    from parflow.post.ensemble import jamming_rate
    r = jamming_rate(["jammed", "complete", "jammed", "jammed"], [0.5, 1.0, 0.25, 0.25])
    assert r["n_jammed"] == 3 and r["value"] == 3 / 2.0 and np.isclose(r["poisson_err"], np.sqrt(3) / 2)


def test_jamming_rate_of_samples_compressed_while_flowing():
    """A sample compressed while it flowed is exposed from the row where phi reached
    compress_to; a jam before that is counted apart, not in the rate."""
    from types import SimpleNamespace
    from parflow.post.ensemble import jamming_rate, rate_exposure

    def run(phi, status, strain):
        return SimpleNamespace(ts=dict(strain=np.asarray(strain, float), phi=np.asarray(phi, float)),
                               attrs=dict(status=status),
                               param=lambda k, d=None: dict(compress_to=0.84).get(k, d))
    reached = run([0.82, 0.83, 0.84, 0.84, 0.84], "jammed", [0.0, 0.5, 1.0, 1.2, 1.25])
    ramp = run([0.82, 0.83, 0.835], "jammed", [0.0, 0.5, 0.75])
    flowing = run([0.82, 0.84, 0.84], "complete", [0.0, 1.0, 2.0])
    assert rate_exposure(reached) == (pytest.approx(0.25), False)
    assert rate_exposure(ramp) == (0.0, True)
    assert rate_exposure(flowing) == (pytest.approx(1.0), False)
    plain = SimpleNamespace(ts=dict(strain=np.array([0.0, 0.3])), attrs=dict(status="jammed"),
                            param=lambda k, d=None: d)
    assert rate_exposure(plain) == (pytest.approx(0.3), False)
    e = [rate_exposure(r) for r in (reached, ramp, flowing)]
    r = jamming_rate(["jammed", "jammed", "complete"], [x[0] for x in e], [x[1] for x in e])
    assert r["n_jammed"] == 1 and r["n_jammed_compressing"] == 1
    assert r["value"] == pytest.approx(1 / 1.25) and r["strain"] == pytest.approx(1.25)


@serial_only
def test_plot_folder(serial, tmp_path):
    out = tmp_path / "figs"
    res = subprocess.run([sys.executable, "-m", "parflow.plot", str(serial), "--out", str(out)],
                         capture_output=True, text=True, timeout=guard(120), env=_env())
    assert res.returncode == 0, res.stderr
    assert (out / "ensemble_V2_forward.png").stat().st_size > 10_000


@pytest.mark.parametrize("args, fragment", [
    (("--samples", 2, "--ranks-per-sample", 2), "ranks_per_sample = 2 does not divide the job's 1 ranks"),
    (("--samples", 0), "--samples must be a positive integer"),
    (("--samples", 10**9), "--samples must be a positive integer (at most 1000000)"),
    (("--set", "ensemble.samples=-1"), "ensemble.samples = -1 is out of range"),
    (("--ranks-per-sample", 2), "--ranks-per-sample is for an ensemble"),
    (("--retry",), "--retry continues an ensemble's jammed or failed samples"),
])
@serial_only
def test_bad_ensemble_arguments(tmp_path, args, fragment):
    res = shear(scene(tmp_path), "--output", tmp_path / "ens", *args)
    assert res.returncode == 2, res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.startswith("parflow.shear: error:")]
    assert len(lines) == 1 and fragment in lines[0], res.stderr
    assert not (tmp_path / "ens").exists()


@serial_only
def test_existing_folder_and_bad_restart(tmp_path, serial):
    res = shear(scene(tmp_path), "--samples", 2, "--output", serial, "--no-plots")
    assert res.returncode == 2 and "holds an ensemble already" in res.stderr
    res = shear("--restart", tmp_path, "--no-plots")
    assert res.returncode == 2 and "not an ensemble folder" in res.stderr
    # the [ensemble] table of the scene, --samples on the command line wins
    text = SCENE + "\n[ensemble]\nsamples = 3\n"
    res = shear(scene(tmp_path, text), "--samples", 2, "--output", tmp_path / "e2", "--quiet",
                "--no-plots")
    assert res.returncode == 0, res.stderr
    assert sorted(os.listdir(tmp_path / "e2")).count("sample_0001.h5") == 1
    assert not (tmp_path / "e2" / "sample_0002.h5").exists()


def test_split_world_groups():
    """In process, on 1 or 2 ranks (mpirun -n 2 pytest): the world cut into groups of r."""
    from parflow.algebra.comm import idle_barrier, max_over, split_world, world
    w = world()
    P, rank = w.getSize(), w.getRank()
    for r in sorted({1, P}):
        g, index, n = split_world(r)
        assert g.getSize() == r and n == P // r and index == rank // r
        assert g.getRank() == rank % r
        assert max_over(w, rank) == P - 1
        idle_barrier(w)
    assert max_over(w, sample_seed(5, rank)) == max(sample_seed(5, k) for k in range(P))
