"""Intermediate force solves by PCG on the loaded factor ([integrator] stage_rtol > 0,
dynamics.bonded): Heun's predictor, RKC's stages and power iteration, and the projection's
Newton steps.  The run must follow the one with a factorisation per solve to the accuracy
asked for, keep the rods rigid and the sigma identity (the step's last force is always a
fresh factorisation), factorise less, and restart bit-identically."""
import h5py
import numpy as np
import pytest

from parflow.scene import load_scene
from systems import run_scene

SCENE = """
seed = 7
[model]
name = "network"
N = 256
z = 3.8
[[protocol.leg]]
direction = "forward"
sigma_above = 3e4
[[protocol.leg]]
direction = "reverse"
sigma_below = 100
strain = 0.5
[integrator]
method = "{method}"
stage_rtol = {rtol}
[output]
path = "{path}"
checkpoint_every = 20
"""


def _run(path, method, rtol, **kw):
    scene = load_scene(SCENE.format(method=method, rtol=rtol, path=path))
    assert run_scene(scene, **kw) in ("complete", "budget")
    with h5py.File(path, "r") as f:
        ts = f["timeseries"]
        return {k: ts[k][:] for k in ("gamma", "sigma", "sigma_tb", "length_error", "direction",
                                       "strain")}, dict(f.attrs)


@pytest.mark.parametrize("method", ["heun", "rkc"])
def test_stage_solves_follow_the_factorised_run(mpi_tmp_path, comm, method):
    exact, ae = _run(str(mpi_tmp_path / f"{method}_exact.h5"), method, 0.0)
    pcg, ap = _run(str(mpi_tmp_path / f"{method}_pcg.h5"), method, 1e-10)
    assert ae["n_stage_pcg"] == 0 and ap["n_stage_pcg"] > 0
    assert ap["n_factorisations"] < 0.8 * ae["n_factorisations"]
    # the same trajectory: sigma at equal strain (forward and reversed) to far below the
    # integration error (tol = 0.05: ~1e-3)
    for run in (exact, pcg):
        assert np.max(run["length_error"]) <= 1e-11                  # rods rigid
        np.testing.assert_allclose(run["sigma_tb"], run["sigma"], rtol=1e-9)
    assert exact["strain"].size == pcg["strain"].size                 # the same steps were taken
    np.testing.assert_allclose(pcg["strain"], exact["strain"], rtol=1e-7)
    np.testing.assert_allclose(pcg["sigma"], exact["sigma"], rtol=1e-5)
    comm.barrier()


def test_a_loose_stage_tolerance_is_felt(mpi_tmp_path, comm):
    """The comparison above can fail: at stage_rtol = 9e-4 the runs part by > 1e-4 (3.9e-3 measured)."""
    exact, _ = _run(str(mpi_tmp_path / "exact.h5"), "heun", 0.0)
    loose, _ = _run(str(mpi_tmp_path / "loose.h5"), "heun", 9e-4)
    n = min(exact["sigma"].size, loose["sigma"].size)
    assert np.max(np.abs(loose["sigma"][:n] / exact["sigma"][:n] - 1)) > 1e-4
    comm.barrier()


@pytest.mark.parametrize("method", ["heun", "rkc"])
def test_stage_solves_restart_is_the_uninterrupted_run(mpi_tmp_path, comm, method):
    whole, _ = _run(str(mpi_tmp_path / "whole.h5"), method, 1e-10)
    path = str(mpi_tmp_path / "part.h5")
    _run(path, method, 1e-10, max_steps=30)
    comm.barrier()
    assert run_scene(load_scene(SCENE.format(method=method, rtol=1e-10, path=path)),
                     restart=True) == "complete"
    comm.barrier()
    with h5py.File(path, "r") as f:
        g, s = f["timeseries/gamma"][:], f["timeseries/sigma"][:]
    np.testing.assert_array_equal(g, whole["gamma"])
    np.testing.assert_array_equal(s, whole["sigma"])
