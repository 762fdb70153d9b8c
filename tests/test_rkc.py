"""The stabilised explicit integrator (dynamics.rkc, [integrator] method = "rkc"): its
Chebyshev coefficients, and runs of a chain near jamming against a tight Heun reference --
rod lengths, the sigma identity, accuracy, far fewer steps, restart = uninterrupted."""
import h5py
import numpy as np
import pytest

from parflow.dynamics.rkc import rkc_coefficients, stages_for
from parflow.scene import load_scene
from systems import run_scene


def _R(s, z):
    """The stability polynomial of RKC2 with s stages at z = h lambda (the recursion)."""
    mut1, mu, nu, mut, gt = rkc_coefficients(s)
    y2, y1, c2, c1 = 1.0, 1.0 + mut1 * z, 0.0, mut1
    for j in range(2, s + 1):
        m, n, mt, g = mu[j - 2], nu[j - 2], mut[j - 2], gt[j - 2]
        y2, y1 = y1, (1 - m - n) + m * y1 + n * y2 + mt * z * y1 + g * z
        c2, c1 = c1, m * c1 + n * c2 + mt + g
    return y1, c1


@pytest.mark.parametrize("s", [2, 3, 5, 10, 40])
def test_rkc_coefficients(s):
    assert _R(s, 0.0)[1] == pytest.approx(1.0, abs=1e-12)            # the last stage is at t + h
    for z in (-1e-2, -2e-2):                                          # second order: error ~ z^3
        assert abs(_R(s, z)[0] - np.exp(z)) < 0.25 * abs(z) ** 3
    zs = -np.linspace(0.0, 0.65 * (s * s - 1), 400)                   # stable on [-0.65 (s^2-1), 0]
    assert max(abs(_R(s, z)[0]) for z in zs) <= 1.0 + 1e-9
    assert stages_for(0.65 * (s * s - 1) / 1.2 / 1.01, 1.0) >= s


SCENE = """
seed = 1
[model]
name = "chain"
N = 1000
epsilon = 0.1
[[protocol.leg]]
direction = "forward"
V2_above = 1e7
[integrator]
method = "{method}"
tol = {tol}
[output]
path = "{path}"
checkpoint_every = 15
"""


def _run(path, method, tol, **kw):
    assert run_scene(load_scene(SCENE.format(method=method, tol=tol, path=path)), **kw) in ("complete", "budget")
    with h5py.File(path, "r") as f:
        ts = f["timeseries"]
        return {k: ts[k][:] for k in ("gamma", "V2", "sigma", "sigma_tb", "length_error", "rejected",
                                       "step", "s_dummy") if k in ts}, dict(f.attrs)


@pytest.mark.serial_only          # three runs; 1 rank = 2 ranks: the restart test below
def test_rkc_is_as_accurate_with_far_fewer_steps(mpi_tmp_path, comm):
    ref, _ = _run(str(mpi_tmp_path / "ref.h5"), "heun", 0.005)   # error ~ tol^2: 1 % of heun 0.05
    heun, _ = _run(str(mpi_tmp_path / "heun.h5"), "heun", 0.05)
    rkc, _ = _run(str(mpi_tmp_path / "rkc.h5"), "rkc", 0.001)

    def error(run):
        ok = (run["gamma"] > ref["gamma"][1]) & (run["gamma"] < ref["gamma"][-2])
        return np.max(np.abs(np.log(run["V2"][ok] / np.exp(np.interp(run["gamma"][ok], ref["gamma"],
                                                                        np.log(ref["V2"]))))))
    print(f"max |d ln V2|: heun {error(heun):.2e}, rkc {error(rkc):.2e}; steps (with rejected): "
          f"heun {heun['step'][-1] + heun['rejected'].sum()}, rkc {rkc['step'][-1] + rkc['rejected'].sum()}")
    assert error(rkc) <= error(heun)                           # at least as accurate ...
    steps = lambda r: r["step"][-1] + r["rejected"].sum()      # noqa: E731
    assert steps(rkc) * 3 < steps(heun)                        # ... in far fewer steps (measured 4.3x at N = 1000)
    assert rkc["rejected"].sum() <= 0.1 * rkc["step"][-1]
    assert np.max(rkc["length_error"]) <= 1e-11                # rods rigid
    np.testing.assert_allclose(rkc["sigma_tb"], rkc["sigma"], rtol=1e-9)
    comm.barrier()


def test_rkc_restart_is_the_uninterrupted_run(mpi_tmp_path, comm):
    whole, _ = _run(str(mpi_tmp_path / "whole.h5"), "rkc", 0.001)
    path = str(mpi_tmp_path / "part.h5")
    _run(path, "rkc", 0.001, max_steps=40)
    comm.barrier()
    scene = load_scene(SCENE.format(method="rkc", tol=0.001, path=path))
    assert run_scene(scene, restart=True) == "complete"
    comm.barrier()
    with h5py.File(path, "r") as f:
        g, v = f["timeseries/gamma"][:], f["timeseries/V2"][:]
    np.testing.assert_array_equal(g, whole["gamma"])
    np.testing.assert_array_equal(v, whole["V2"])


def test_max_stages_bounds_the_stage_count():
    from parflow.state import InputError
    assert stages_for(1.0, 1e12, 2) == 2 and stages_for(1.0, 1e12) == 200
    scene = SCENE.format(method="rkc", tol=0.01, path="x.h5").replace("tol = 0.01", "tol = 0.01\nmax_stages = 5")
    assert load_scene(scene)["integrator"]["max_stages"] == 5
    with pytest.raises(InputError, match="max_stages"):
        load_scene(scene.replace("max_stages = 5", "max_stages = 1"))


@pytest.mark.serial_only          # five runs of a 1000-rod chain, ~5 s
def test_rkc_error_and_step_count_follow_its_order(mpi_tmp_path):
    """Against a tight reference (RKC2 at tol 1e-5, its error ~100x below the runs'): the
    error of <V^2> falls like tol (the controller holds the local error per unit of
    displacement at tol), and the steps grow like tol^(-1/2) -- a second-order method (first
    order would need tol^-1).  Measured: exponents 1.08 and 0.48 over tol = 8e-3 ... 1e-3."""
    ref, _ = _run(str(mpi_tmp_path / "ref.h5"), "rkc", 1e-5)
    tols = np.array([0.008, 0.004, 0.002, 0.001])
    errs, steps = [], []
    for tol in tols:
        r, _ = _run(str(mpi_tmp_path / f"rkc_{tol}.h5"), "rkc", tol)
        ok = (r["gamma"] > ref["gamma"][1]) & (r["gamma"] < ref["gamma"][-2])
        errs.append(np.max(np.abs(np.log(r["V2"][ok]) - np.interp(r["gamma"][ok], ref["gamma"],
                                                                    np.log(ref["V2"])))))
        steps.append(r["step"][-1] + r["rejected"].sum())
    p_err = np.polyfit(np.log(tols), np.log(errs), 1)[0]
    p_steps = -np.polyfit(np.log(tols), np.log(steps), 1)[0]
    print(f"errors {np.array(errs)}, steps {steps}: error ~ tol^{p_err:.2f}, steps ~ tol^-{p_steps:.2f}")
    assert 0.8 <= p_err <= 1.3
    assert 0.35 <= p_steps <= 0.65
    assert errs[-1] < 1e-3
