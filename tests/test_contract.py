"""Every registered model through the same contract: its module keeps models/base.py's
contract, and the engine it names builds, steps, observes, checkpoints and analyses it
through one interface (serially and on 2 ranks)."""
import numpy as np
import pytest
from petsc4py import PETSc

from parflow.dynamics.engines import make_engine
from parflow.models import MODELS, get_model
from parflow.models.base import check_contract
from parflow.scene import load_scene
from parflow.state import Instant, State

SMALL = {"chain": "N = 40\nepsilon = 0.1",
         "network": "N = 128\nz = 3.8\nresponse_rods = 1\ncorrelation = false",
         "suspension": "N = 64\nphi = 0.78\nresponse_rods = 1\ndelta_gamma = false"}


@pytest.mark.parametrize("name", MODELS)
def test_model_keeps_the_contract(name):
    model = get_model(name)
    check_contract(model)
    assert model.NAME == name


@pytest.mark.parametrize("name", MODELS)
def test_engine_interface(name, comm):
    assert set(SMALL) == set(MODELS), "add a small scene for the new model here"
    scene = load_scene(f'seed = 2\n[model]\nname = "{name}"\n{SMALL[name]}\n'
                       '[[protocol.leg]]\ndirection = "forward"\nmax_steps = 3\n')
    model = get_model(name)
    state = model.build(scene["model"], scene["seed"])
    assert isinstance(state, State) and state.d == 2
    eng = make_engine(PETSc.COMM_WORLD, state, scene, model)
    assert eng.kind == model.ENGINE and eng.state is state
    eng.start()
    first = eng.observe()
    assert {"sigma", "V2"} <= set(first) and first["sigma"] >= 0
    gammas = [eng.gamma]
    for direction in (1, 1, -1):
        dg = eng.step(direction, None)
        assert dg * direction > 0
        gammas.append(eng.gamma)
        assert eng.state.gamma == eng.gamma and eng.state.s is eng.s   # the engine's state is current
        obs = eng.observe()
        assert np.isfinite(obs["sigma"]) and obs["sigma"] >= 0
        row = eng.row()
        assert "dgamma" in row
    np.testing.assert_allclose(np.diff(gammas)[:2] > 0, True)
    at = eng.instant()
    assert isinstance(at, Instant) and at.state is eng.state and at.scene is scene
    res = eng.analyses()
    assert set(res) == {"arrays", "scalars"}
    w = eng.omega_min()
    assert w > 0 or np.isnan(w)
    arrays, attrs = eng.checkpoint()
    assert np.array_equal(arrays["s"], eng.s) and attrs["gamma"] == eng.gamma
    snap = eng.snapshot()
    assert snap["s"].shape == eng.s.shape and snap["V_na"].shape == eng.s.shape
    desc, opts = eng.describe()
    assert isinstance(desc, str) and isinstance(opts, dict)
    eng.destroy()
    comm.barrier()
