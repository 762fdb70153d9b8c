"""The force at the end of a step solved with a reused factor (solver.reuse_factor): PCG on
N(s) preconditioned by the factor of a nearby N, against a fresh factorisation; the fallback
when the PCG does not converge; the Mat brought back to the current N before analyses;
through the driver: the same run as with fresh factorisations (to round-off), and a restart
that continues from the very numbers of the uninterrupted run.

Under ``mpirun -n 2`` both ranks run every test (the algebra is replicated or distributed as
the default resolves it); the assertions hold on both."""
import h5py
import numpy as np
import pytest
from petsc4py import PETSc

from parflow.dynamics import bonded as sy
from parflow.dynamics.heun import Heun, StepControl
from parflow.models import network as nw
from parflow.run import Run, setup_logging
from parflow.scene import load_scene
from parflow.state import InputError
from parflow.dynamics.bonded import BondedSystem, resolve_reuse


@pytest.fixture(scope="module")
def state():
    return nw.build(dict(N=256, z=3.8, phi=0.88), seed=3)


def strained_to(state, sigma_target=3e3):
    """A configuration near jamming (sigma >= sigma_target), and the step that led to it."""
    sysm = BondedSystem(PETSc.COMM_WORLD, state)
    integ = Heun(sysm, StepControl())
    s, g = state.s.copy(), 0.0
    F = sysm.evaluate(s, g)
    dg = 1e-4
    while F.sigma < sigma_target:
        R = integ.step(s, g, F, +1, dg)
        s, g, F, dg = R.s, R.gamma, R.F, R.next_dgamma
    sysm.destroy()
    return s, g, dg, F


def test_pcg_with_a_nearby_factor_is_the_direct_solve(state):
    s, g, dg, F = strained_to(state)
    sysm = BondedSystem(PETSc.COMM_WORLD, state, reuse_factor=True)
    # the factor of the predictor point of a step, then the force at the corrector point
    F1 = sysm.evaluate(s + dg * F.ds, g + dg)
    s_new = s + 0.5 * dg * (F.ds + F1.ds)
    s_new, _, _ = sysm.project(s_new, g + dg, tol=1e-12)
    before = sysm.n_factor
    Fr = sysm.evaluate(s_new, g + dg, reuse=True)
    assert sysm.n_factor == before                 # no factorisation
    assert sysm.n_reused == 1 and sysm.n_reuse_failed == 0
    assert sysm.ops.values_stale
    assert 1 <= Fr.info.refinements <= sy.REUSE_MAX_IT
    assert Fr.info.backward_error <= sy.REUSE_BERR
    ref = BondedSystem(PETSc.COMM_WORLD, state)
    Fd = ref.evaluate(s_new, g + dg)
    cond_eps = 1e-16 * Fd.sigma * 1e3              # round-off grows like cond(N) ~ sigma
    np.testing.assert_allclose(Fr.tau, Fd.tau, rtol=0, atol=max(1e-9, cond_eps) * np.abs(Fd.tau).max())
    np.testing.assert_allclose(Fr.V_na, Fd.V_na, rtol=0, atol=max(1e-9, cond_eps) * np.abs(Fd.V_na).max())
    assert Fr.sigma == pytest.approx(Fd.sigma, rel=1e-8)
    # V_na = S^T tau used the unit vectors of s_new (not the loaded ones)
    np.testing.assert_allclose(sysm.ST(Fr.tau), Fr.V_na, rtol=0, atol=1e-12 * np.abs(Fr.V_na).max())
    # sync() writes N(s_new) into the Mat: a solve after it is the direct one
    sysm.sync()
    assert not sysm.ops.values_stale and sysm.n_factor == before + 1
    x = sysm.solve_N(-Fd.b)
    np.testing.assert_allclose(x, Fd.tau, rtol=0, atol=max(1e-9, cond_eps) * np.abs(Fd.tau).max())
    sysm.destroy(), ref.destroy()


def test_reuse_falls_back_to_a_factorisation(state, monkeypatch):
    """A factor from far away does not precondition well enough within the iterations
    allowed: N(s) is factorised and the answer is the direct one."""
    s, g, dg, F = strained_to(state, 1e2)
    sysm = BondedSystem(PETSc.COMM_WORLD, state, reuse_factor=True)
    sysm.evaluate(state.s, 0.0)                   # the factor of the unstrained network
    monkeypatch.setattr(sy, "REUSE_MAX_IT", 1)
    before = sysm.n_factor
    Fr = sysm.evaluate(s, g, reuse=True)
    assert sysm.n_reuse_failed == 1 and sysm.n_reused == 0
    assert sysm.n_factor == before + 1 and not sysm.ops.values_stale
    np.testing.assert_allclose(Fr.tau, F.tau, rtol=1e-9, atol=1e-12 * np.abs(F.tau).max())
    # reuse off (the default): never a PCG
    plain = BondedSystem(PETSc.COMM_WORLD, state)
    plain.evaluate(state.s, 0.0)
    plain.evaluate(s, g, reuse=True)
    assert plain.n_reused == plain.n_reuse_failed == 0 and plain.n_factor == 2
    sysm.destroy(), plain.destroy()


def test_resolve_reuse():
    big = sy.REUSE_AUTO_MIN_NC
    assert resolve_reuse("auto", big, "direct", True)
    assert not resolve_reuse("auto", big - 1, "direct", True)
    assert not resolve_reuse("auto", big, "accurate", True)      # exact solves asked for
    assert not resolve_reuse("auto", big, "direct", False)       # e.g. the chain
    assert resolve_reuse("on", 10, "accurate", False)
    assert not resolve_reuse("off", big, "direct", True)
    with pytest.raises(ValueError, match="reuse_factor"):
        resolve_reuse("yes", big, "direct", True)


def scene_text(path, reuse, legs=None):
    legs = legs or ('[[protocol.leg]]\ndirection = "forward"\nsigma_above = 1e4\n'
                    '[[protocol.leg]]\ndirection = "reverse"\nsigma_below = 30\nstrain = 0.05\n')
    return f"""
seed = 3
[model]
name = "network"
N = 256
z = 3.8
{legs}
[solver]
reuse_factor = "{reuse}"
[output]
path = "{path}"
"""


def test_bad_reuse_value():
    with pytest.raises(InputError, match="solver.reuse_factor"):
        load_scene(scene_text("x.h5", "sometimes"))


def run(text, path, **kw):
    setup_logging(PETSc.COMM_WORLD, quiet=True)
    scene = load_scene(text)
    scene["output"]["path"] = path
    return Run(scene, PETSc.COMM_WORLD, path, quiet=True, **kw).execute()


def test_run_with_reuse_matches_fresh_factorisations(mpi_tmp_path, comm):
    on, off = str(mpi_tmp_path / "on.h5"), str(mpi_tmp_path / "off.h5")
    assert run(scene_text(on, "on"), on) == "complete"
    assert run(scene_text(off, "off"), off) == "complete"
    comm.Barrier()
    with h5py.File(on) as a, h5py.File(off) as b:
        assert a.attrs["n_reused_factor"] > 0.9 * a["timeseries/step"][-1]
        assert b.attrs["n_reused_factor"] == 0
        assert a.attrs["n_factorisations"] < 0.7 * b.attrs["n_factorisations"]
        fwd = a["timeseries/direction"][()] > 0
        n = min(np.count_nonzero(fwd), np.count_nonzero(b["timeseries/direction"][()] > 0))
        # the same trajectory: round-off only (amplified near jamming by cond(N) ~ sigma)
        np.testing.assert_allclose(a["timeseries/sigma"][:n], b["timeseries/sigma"][:n], rtol=1e-6)
        np.testing.assert_allclose(a["timeseries/gamma"][:n], b["timeseries/gamma"][:n], rtol=1e-9)
        assert np.max(a["timeseries/length_error"][()]) < 1e-10
        assert np.max(a["timeseries/sigma_mismatch"][()]) < 1e-8
        assert a["timeseries/sigma"][-1] <= 30
    comm.Barrier()


def test_restart_with_reuse_equals_uninterrupted(mpi_tmp_path, comm):
    full, part = str(mpi_tmp_path / "full.h5"), str(mpi_tmp_path / "part.h5")
    assert run(scene_text(full, "on"), full) == "complete"
    assert run(scene_text(part, "on"), part, max_steps=60) == "budget"
    comm.Barrier()
    with h5py.File(part) as f:
        assert f["checkpoint/tau"].shape == (len(f["initial/bonds/i"]),)
    assert run(scene_text(part, "on"), part, restart=True, max_steps=10**6) == "complete"
    comm.Barrier()
    with h5py.File(full) as a, h5py.File(part) as b:
        for q in ("gamma", "sigma", "V2", "dgamma"):
            np.testing.assert_array_equal(a["timeseries"][q][:], b["timeseries"][q][:])
        np.testing.assert_array_equal(a["checkpoint/s"][:], b["checkpoint/s"][:])
    comm.Barrier()
