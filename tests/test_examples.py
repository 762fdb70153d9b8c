"""The worked examples of docs/architecture.md, run: how to add a model, a per-step
observable and an integrator.  Each is the code the page shows, driven through the real
driver (``parflow.run.Run``), serially and on 2 ranks."""
import types

import h5py
import numpy as np
import pytest

from parflow.dynamics import heun
from parflow.geometry import velocity_gradient
from parflow.models import MODELS, register_model, unregister_model
from parflow.models import chain
from parflow.scene import load_scene
from parflow.state import Bonds, State
from systems import run_scene


# --------------------------------------------------------------------------- a model
# "ring": the rigid chain of the paper, but in simple shear instead of planar extension
# (a network whose nodes have degree 2).  A model is a module (here: a namespace) keeping
# models/base.py's contract.

def ring_build(params, seed):
    """N rods of unit length along x with random angles (chain.initial_angles), closed by
    the periodic image of node 0, in a square box that simple shear tilts."""
    N, eps = params["N"], params["epsilon"]
    theta = chain.initial_angles(N, eps, 0, np.random.default_rng(seed))
    t = np.column_stack([np.cos(theta), np.sin(theta)])
    r = np.vstack([np.zeros(2), np.cumsum(t, axis=0)[:-1]])
    Lx = float(t[:, 0].sum())
    h0 = np.diag([Lx, Lx])
    shift = np.zeros((N, 2), dtype=np.int64)
    shift[-1, 0] = 1
    bonds = Bonds(np.arange(N), (np.arange(N) + 1) % N, shift, np.ones(N))
    return State(r @ np.linalg.inv(h0).T, h0, velocity_gradient("shear", 2), 0.0, bonds,
                 meta=dict(model="ring"))


def mean_tension(state, F) -> dict:
    """The new per-step observable: <tau> over the rods (tau > 0 is compression)."""
    return dict(tau_mean=float(np.mean(F.tau)))


ring = types.SimpleNamespace(
    NAME="ring", ENGINE="bonded", FLOW="shear", FACTOR_REUSE=False, omega_min=None,
    PARAMS={"N": (int, 64, lambda v: v >= 3, "number of rods (>= 3)"),
            "epsilon": (float, 0.1, lambda v: 0 < v < 1, "rms initial angle (0 < eps < 1)")},
    build=ring_build,
    observables=lambda state, F: {**mean_tension(state, F), "z": 2.0},
    analyses=lambda at: dict(arrays=dict(tau=at.F.tau), scalars=dict(tau_max=float(at.F.tau.max()))),
)


# --------------------------------------------------------------------------- an integrator
class Euler(heun.Heun):
    """Explicit Euler with the step control of [integrator]: the Heun predictor, accepted
    when the change of V_na over the step is within tol, then projected on the rod lengths
    like every bonded step.  (First order: an example, not a preset.)"""

    def step(self, s, gamma, F0, direction, dg, dg_cap=None):
        dg = self.bound(F0, dg)
        if dg_cap is not None:
            dg = min(dg, dg_cap)
        s1 = s + direction * dg * F0.ds
        g1 = gamma + direction * dg
        s1, proj_iter, length_error, F1 = self.finish(s1, g1)
        err = heun.vnorm(F1.V_na - F0.V_na) / max(heun.vnorm(F0.V_na), heun.vnorm(F1.V_na), 1e-300)
        return heun.StepResult(s1, g1, F1, direction * dg, dg * self.growth(err, 0), err, 0,
                               proj_iter, length_error)


@pytest.fixture
def registered():
    register_model(ring)
    heun.INTEGRATORS["euler"] = Euler
    try:
        yield
    finally:
        unregister_model("ring")
        heun.INTEGRATORS.pop("euler")
    assert "ring" not in MODELS


SCENE = """
seed = 4
[model]
name = "ring"
N = 48
[[protocol.leg]]
direction = "forward"
strain = 0.004
[[protocol.leg]]
direction = "reverse"
strain = 0.002
[integrator]
method = "{method}"
[observables]
analysis_every = 20
[output]
path = "{path}"
"""


@pytest.mark.parametrize("method", ["heun", "euler"])
def test_worked_examples_run_through_the_driver(registered, mpi_tmp_path, comm, method):
    path = str(mpi_tmp_path / f"ring_{method}.h5")
    assert run_scene(load_scene(SCENE.format(method=method, path=path))) == "complete"
    comm.barrier()
    with h5py.File(path, "r") as f:
        ts = f["timeseries"]
        assert f.attrs["model"] == "ring" and f.attrs["engine"] == "bonded"
        assert "tau_mean" in ts and np.all(np.isfinite(ts["tau_mean"][:]))   # the observable
        assert np.max(ts["length_error"][:]) <= 1e-11                      # rods stay rigid
        np.testing.assert_allclose(ts["sigma_tb"][:], ts["sigma"][:], rtol=1e-8)
        assert ts["gamma"][-1] == pytest.approx(0.004 - 0.002, abs=1e-12)
        assert len(f["analysis"]) >= 2                                      # the model's analyses
        a = f["analysis"][sorted(f["analysis"])[-1]]
        assert a.attrs["tau_max"] == pytest.approx(float(np.max(a["tau"][()])))
    comm.barrier()


def test_an_unregistered_integrator_is_refused():
    from parflow.state import InputError
    with pytest.raises(InputError, match="integrator.method"):
        load_scene(SCENE.replace('name = "ring"', 'name = "chain"').format(method="rk4", path="x.h5"))
