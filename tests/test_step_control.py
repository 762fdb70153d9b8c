"""Step-size control of the Heun integrator (integrator.controller) and scene settings given
on the command line (--set), also on a restart: validation, persistence in the run file, and
a restart that continues the very same run."""
import h5py
import numpy as np
import pytest
from petsc4py import PETSc

from parflow.dynamics.heun import Heun, StepControl
from parflow.run import Run, setup_logging
from parflow.scene import apply_settings, load_scene
from parflow.state import InputError

NET = """
seed = 3
[model]
name = "network"
N = 256
z = 3.8
[[protocol.leg]]
direction = "forward"
sigma_above = 3e4
[[protocol.leg]]
direction = "reverse"
sigma_below = 30
strain = 0.05
[integrator]
controller = "{controller}"
[output]
path = "{path}"
"""


def test_growth_factor():
    i = Heun(None, StepControl(tol=0.2))
    assert i.growth(0.1, 0) == pytest.approx(1.8) and i.growth(0.0, 0) == 2.0
    assert i.growth(10.0, 0) == 0.2 and i.growth(0.1, 2) == pytest.approx(1.8)
    pi = Heun(None, StepControl(tol=0.2, controller="PI"))
    assert pi.growth(0.1, 0) == pytest.approx(1.8)            # no history yet: as "I"
    pi.err_prev = 0.1
    # the error grew since the last step: PI grows less than I would
    assert pi.growth(0.17, 0) == pytest.approx((0.18 / 0.17) ** 0.7 * (0.1 / 0.17) ** 0.4)
    assert pi.growth(0.17, 0) < 0.18 / 0.17
    assert pi.growth(0.05, 1) == 1.0                           # no growth after a rejection
    with pytest.raises(InputError, match="integrator.controller"):
        StepControl(controller="PID").validate()


def run(text, path, **kw):
    setup_logging(PETSc.COMM_WORLD, quiet=True)
    scene = load_scene(text)
    scene["output"]["path"] = path
    return Run(scene, PETSc.COMM_WORLD, path, quiet=True, **kw).execute()


def test_pi_controller_run_and_restart(mpi_tmp_path, comm):
    """PI control: rods rigid, the reversed branch relaxes, fewer rejected steps than I control
    on the way to sigma = 3e4; a restart continues it exactly (err_prev is checkpointed)."""
    paths = {c: str(mpi_tmp_path / f"{c}.h5") for c in ("I", "PI", "part")}
    for c in ("I", "PI"):
        assert run(NET.format(controller=c, path=paths[c]), paths[c]) == "complete"
    part = NET.format(controller="PI", path=paths["part"])
    assert run(part, paths["part"], max_steps=70) == "budget"
    assert run(part, paths["part"], restart=True, max_steps=10**6) == "complete"
    comm.Barrier()
    with h5py.File(paths["I"]) as a, h5py.File(paths["PI"]) as b, h5py.File(paths["part"]) as c:
        assert np.max(b["timeseries/length_error"][()]) < 1e-10
        assert b["timeseries/sigma"][-1] <= 30 and np.max(b["timeseries/sigma"][()]) >= 3e4
        # the same physics to the step's tolerance: where sigma first passes 1e3, 1e4
        for level in (1e3, 1e4):
            ga = a["timeseries/gamma"][np.argmax(a["timeseries/sigma"][()] >= level)]
            gb = b["timeseries/gamma"][np.argmax(b["timeseries/sigma"][()] >= level)]
            assert gb == pytest.approx(ga, rel=2e-3)
        assert b["timeseries/rejected"][()].sum() <= 0.1 * b["timeseries/step"][-1]
        for q in ("gamma", "sigma", "dgamma"):
            np.testing.assert_array_equal(b["timeseries"][q][:], c["timeseries"][q][:])
    comm.Barrier()


def test_set_validates():
    scene = load_scene(NET.format(controller="I", path="x.h5"))
    s = apply_settings(scene, ["integrator.controller=PI", "integrator.tol=0.1", "solver.reuse_factor=on"])
    assert s["integrator"]["controller"] == "PI" and s["integrator"]["tol"] == 0.1
    assert s["solver"]["reuse_factor"] == "on" and scene["integrator"]["controller"] == "I"
    assert s["settings"] == ["integrator.controller=PI", "integrator.tol=0.1", "solver.reuse_factor=on"]
    for bad, msg in [("integrator.controller", "SECTION.KEY=VALUE"),
                     ("controller=PI", "SECTION.KEY=VALUE"),
                     ("integrator.tol=2", "out of range"),
                     ("integrator.tol=fast", "must be of type float"),
                     ("integrator.tolerance=0.1", "unknown key integrator"),
                     ("integrater.tol=0.1", "unknown key --set section"),
                     ("integrator.preset=fast", "set the preset's keys"),
                     ("integrator.min_dgamma=1", "min_dgamma must be smaller")]:
        with pytest.raises(InputError, match=msg):
            apply_settings(scene, [bad])
    for bad in ("model.z=3.9", "seed.x=1", "observables.omega_min_every=5", "output.path=y.h5"):
        with pytest.raises(InputError):
            apply_settings(scene, [bad], restart=True)
    assert apply_settings(scene, ["output.checkpoint_minutes=1"], restart=True)["output"]["checkpoint_minutes"] == 1.0


@pytest.mark.serial_only
def test_restart_with_set_is_recorded_and_kept(tmp_path):
    from test_cli import shear
    out = tmp_path / "r.h5"
    scene = tmp_path / "s.toml"
    scene.write_text(NET.format(controller="I", path=out))
    res = shear(scene, "--quiet", "--no-plots", "--max-steps", "30", "--set", f"output.path={out}")
    assert res.returncode == 0, res.stderr
    res = shear("--restart", out, "--quiet", "--no-plots", "--max-steps", "60",
                "--set", "integrator.controller=PI")
    assert res.returncode == 0, res.stderr
    with h5py.File(out) as f:
        assert f.attrs["scene_settings"] == f"output.path={out}\nintegrator.controller=PI"
        assert f.attrs["restarted_at_step"] == 30 and "restart_git_commit" in f.attrs
    res = shear("--restart", out, "--quiet", "--no-plots", "--max-steps", "90")
    assert res.returncode == 0, res.stderr
    with h5py.File(out) as f:
        assert f.attrs["scene_settings"] == f"output.path={out}\nintegrator.controller=PI"   # kept
        assert f["timeseries/step"][-1] == 90
    res = shear("--restart", out, "--set", "model.z=3.9")
    assert res.returncode != 0 and "continues the same simulation" in res.stderr


@pytest.mark.serial_only
def test_branch_a_run_into_a_new_file(tmp_path):
    """--restart FILE --output NEW: a copy continues in NEW, here reversed at once by a lower
    stop stress for the forward leg; FILE is left untouched; a plain restart cannot change
    the protocol."""
    from test_cli import shear
    out, new = tmp_path / "r.h5", tmp_path / "b.h5"
    scene = tmp_path / "s.toml"
    scene.write_text(NET.format(controller="I", path=out))
    assert shear(scene, "--quiet", "--no-plots", "--max-steps", "40").returncode == 0
    with h5py.File(out) as f:
        sigma_now = float(f["timeseries/sigma"][-1])
        rows, ck = f["timeseries/step"].shape[0], int(f["checkpoint"].attrs["step"])
    res = shear("--restart", out, "--quiet", "--no-plots", "--set", "protocol.leg.0.sigma_above=1")
    assert res.returncode == 2 and "branch the run into a new file" in res.stderr
    res = shear("--restart", out, "--output", new, "--no-plots", "--max-steps", "100000",
                "--set", f"protocol.leg.0.sigma_above={0.5 * sigma_now}")
    assert res.returncode == 0, res.stderr
    assert f"at its checkpoint (step {ck})" in res.stderr
    with h5py.File(out) as f:                      # the original: as it was
        assert f["timeseries/step"].shape[0] == rows and f.attrs["status"] == "budget"
    with h5py.File(new) as f:
        assert f.attrs["branched_from"].endswith(f"at step {ck}")
        assert f.attrs["status"] == "complete"
        d = f["timeseries/direction"][()]
        assert np.all(d[:rows] > 0) and np.all(d[rows:] < 0)        # reversed right away
        assert f["timeseries/sigma"][-1] <= 30
        assert f.attrs["scene_settings"] == f"protocol.leg.0.sigma_above={0.5 * sigma_now}"
    res = shear("--restart", out, "--output", new, "--no-plots")
    assert res.returncode == 2 and "exists" in res.stderr
    res = shear("--restart", out, "--output", out, "--no-plots")
    assert res.returncode == 2 and "names the file being restarted" in res.stderr
    res = shear("--restart", out, "--output", tmp_path / "c.h5", "--set", "protocol.leg.5.strain=1")
    assert res.returncode == 2 and "K in 0..1" in res.stderr and not (tmp_path / "c.h5").exists()


@pytest.mark.serial_only
def test_branch_of_a_complete_run_reopens_its_last_leg(tmp_path):
    """A complete run branched with a longer last leg shears on from its end to the new leg
    strain, the rows before the branch point as they were; branched with its protocol
    unchanged it is complete at once, with no step added."""
    from test_cli import GOOD, shear
    out, longer, same = tmp_path / "r.h5", tmp_path / "longer.h5", tmp_path / "same.h5"
    scene = tmp_path / "s.toml"
    scene.write_text(GOOD.replace("V2_above = 100.0", "strain = 0.002"))
    assert shear(scene, "--quiet", "--no-plots", "--output", out).returncode == 0
    with h5py.File(out) as f:
        assert f.attrs["status"] == "complete"
        rows = f["timeseries/step"].shape[0]
        strain0 = f["timeseries/strain"][()]
        assert strain0[-1] == pytest.approx(0.002, rel=1e-12)
    res = shear("--restart", out, "--output", longer, "--no-plots",
                "--set", "protocol.leg.0.strain=0.003")   # it jams at ~0.0047
    assert res.returncode == 0, res.stderr
    assert "its last leg reopened" in res.stderr
    with h5py.File(longer) as f:
        assert f.attrs["status"] == "complete"
        strain = f["timeseries/strain"][()]
        assert strain.shape[0] > rows and np.array_equal(strain[:rows], strain0)
        assert strain[-1] == pytest.approx(0.003, rel=1e-12)
        assert np.all(f["timeseries/leg"][()] == 0)
        assert int(f["checkpoint"].attrs["leg"]) == 1
    res = shear("--restart", out, "--output", same, "--no-plots", "--quiet")
    assert res.returncode == 0, res.stderr
    with h5py.File(same) as f:
        assert f.attrs["status"] == "complete" and f["timeseries/step"].shape[0] == rows
