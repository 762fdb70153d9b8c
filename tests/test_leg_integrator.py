"""A leg's own integrator keys ([[protocol.leg]] integrator = {...}, over the scene's
[integrator]): validation, that a leg runs exactly the integrator it names (the same legs
written the other way round give the same run, bit for bit), and restart = uninterrupted
inside a leg that changes the integrator; and a leg's perturb (a seeded displacement of
the nodes at its start).
"""
import h5py
import numpy as np
import pytest

from parflow.dynamics.ros2 import REJECTION_CAUSES as CAUSES
from parflow.scene import load_scene
from parflow.state import InputError
from systems import run_scene

SCENE = """
seed = 1
[model]
name = "chain"
N = 400
epsilon = 0.1
[[protocol.leg]]
direction = "forward"
V2_above = 1e6
{leg0}
[[protocol.leg]]
direction = "reverse"
V2_below = 1e3
strain = 0.05
{leg1}
[integrator]
{scene}
[output]
path = "{path}"
checkpoint_every = 100
"""
# a suspension scene's one leg, open for one more leg key
SUSPENSION = """
seed = 1
[model]
name = "suspension"
N = 64
phi = 0.8
[[protocol.leg]]
direction = "forward"
strain = 0.01
"""
RKC = 'method = "rkc", tol = 0.001'
HEUN = 'method = "heun", tol = 0.01'


def _scene(path, scene, leg0="", leg1=""):
    return load_scene(SCENE.format(path=path, scene=scene.replace(", ", "\n"),
                                   leg0=f"integrator = {{ {leg0} }}" if leg0 else "",
                                   leg1=f"integrator = {{ {leg1} }}" if leg1 else ""))


def _series(path):
    with h5py.File(path, "r") as f:
        ts = f["timeseries"]
        return {k: ts[k][:] for k in ("gamma", "V2", "err", "leg", "rejected")}


def test_leg_integrator_is_validated():
    ok = _scene("x.h5", RKC, leg1=HEUN)
    assert ok["protocol"]["leg"][1]["integrator"] == {"method": "heun", "tol": 0.01}
    assert "integrator" not in ok["protocol"]["leg"][0]
    assert ok["integrator"]["method"] == "rkc"                  # the scene's table is untouched
    for leg1, match in [('method = "euler"', r"protocol.leg\[1\].integrator.method"),
                        ("tol = -1.0", r"protocol.leg\[1\].integrator.tol"),
                        ("toll = 0.1", r"protocol.leg\[1\].integrator.*toll"),
                        ('preset = "fast"', r"protocol.leg\[1\].integrator.preset"),
                        ("min_dgamma = 1.0", r"protocol.leg\[1\].*min_dgamma")]:
        with pytest.raises(InputError, match=match):
            _scene("x.h5", RKC, leg1=leg1)
    with pytest.raises(InputError, match=r"protocol.leg\[1\].integrator must be"):
        load_scene(SCENE.format(path="x.h5", scene="", leg0="", leg1="integrator = 3"))
    susp = SUSPENSION + 'integrator = { method = "heun" }\n'
    with pytest.raises(InputError, match=r"protocol.leg\[0\].integrator: the suspension model has no integrator"):
        load_scene(susp)


def test_each_leg_runs_the_integrator_it_names(mpi_tmp_path, comm):
    """RKC forward then Heun reversed, written as scene RKC + leg Heun and as scene Heun + leg
    RKC: the same run bit for bit; its forward leg is the all-RKC run's, its reversed leg not."""
    a, b, c = (str(mpi_tmp_path / f"{x}.h5") for x in "abc")
    assert run_scene(_scene(a, RKC, leg1=HEUN)) == "complete"
    assert run_scene(_scene(b, HEUN, leg0=RKC)) == "complete"
    assert run_scene(_scene(c, RKC)) == "complete"
    comm.barrier()
    A, B, C = _series(a), _series(b), _series(c)
    for k in A:
        np.testing.assert_array_equal(A[k], B[k])
    fw = A["leg"] == 0
    n = int(fw.sum())
    np.testing.assert_array_equal(A["gamma"][:n], C["gamma"][:n])
    assert np.all(C["leg"][:n] == 0)
    rv = A["leg"] == 1
    assert rv.sum() > 5
    # Heun (tol 0.01) takes more, shorter steps on the reversed leg than RKC (tol 0.001)
    assert rv.sum() != (C["leg"] == 1).sum() or not np.array_equal(A["gamma"][rv], C["gamma"][C["leg"] == 1])


def test_restart_inside_a_leg_with_its_own_integrator(mpi_tmp_path, comm):
    whole, part = str(mpi_tmp_path / "whole.h5"), str(mpi_tmp_path / "part.h5")
    assert run_scene(_scene(whole, HEUN, leg0=RKC)) == "complete"
    comm.barrier()
    W = _series(whole)
    n_fw = int((W["leg"] == 0).sum())
    # stop in the forward (RKC) leg, restart, and again in the reversed (Heun) leg
    for stop in (n_fw // 2, n_fw + 4):
        run_scene(_scene(part, HEUN, leg0=RKC), max_steps=stop, restart=stop != n_fw // 2)
        comm.barrier()
    assert run_scene(_scene(part, HEUN, leg0=RKC), restart=True) == "complete"
    comm.barrier()
    P = _series(part)
    for k in ("gamma", "V2", "err"):
        np.testing.assert_array_equal(P[k], W[k])


ROS2 = 'method = "ros2", tol = 0.3'


def test_ros2_rejections_survive_a_switch_to_heun(mpi_tmp_path, comm):
    """The run file's rejected_* (ros2's rejected trial steps by cause) count this sitting's
    ros2 steps, also when the last leg runs Heun: all of them after the ROS2 -> Heun run, and
    after a restart in the Heun leg none (not the earlier sitting's left standing)."""
    whole, part = str(mpi_tmp_path / "whole.h5"), str(mpi_tmp_path / "part.h5")
    assert run_scene(_scene(whole, HEUN, leg0=ROS2)) == "complete"
    comm.barrier()
    W = _series(whole)
    fw = W["leg"] == 0
    assert W["rejected"][fw].sum() > 0           # tol 0.3: ros2 rejects some forward steps
    with h5py.File(whole, "r") as f:
        got = {c: int(f.attrs[f"rejected_{c}"]) for c in CAUSES}
    assert sum(got.values()) == W["rejected"][fw].sum()
    n_fw = int(fw.sum())
    run_scene(_scene(part, HEUN, leg0=ROS2), max_steps=n_fw + 3)
    comm.barrier()
    with h5py.File(part, "r") as f:
        assert sum(int(f.attrs[f"rejected_{c}"]) for c in CAUSES) == W["rejected"][fw].sum()
    assert run_scene(_scene(part, HEUN, leg0=ROS2), restart=True) == "complete"
    comm.barrier()
    with h5py.File(part, "r") as f:
        assert all(int(f.attrs[f"rejected_{c}"]) == 0 for c in CAUSES)
    np.testing.assert_array_equal(_series(part)["gamma"], W["gamma"])


def _perturbed(path, rms):
    return load_scene(SCENE.format(path=path, scene=HEUN.replace(", ", "\n"), leg0="",
                                   leg1=f"perturb = {rms}" if rms is not None else ""))


def test_perturb_at_the_start_of_a_leg(mpi_tmp_path, comm):
    """perturb = rms displaces the nodes once, at the leg's start: the forward leg is
    untouched, the reversed one starts elsewhere with rigid rods, the same seed gives the same
    numbers, perturb = 0 is no perturbation, and a restart inside the leg continues it."""
    p = {k: str(mpi_tmp_path / f"{k}.h5") for k in ("none", "zero", "a", "b", "part")}
    for k, rms in (("none", None), ("zero", 0.0), ("a", 1e-3), ("b", 1e-3)):
        assert run_scene(_perturbed(p[k], rms)) == "complete"
    other = _perturbed(str(mpi_tmp_path / "c.h5"), 1e-3)
    other["protocol"]["leg"][1]["perturb_seed"] = 5
    assert run_scene(other) == "complete"
    comm.barrier()
    R = {k: _series(p[k]) for k in ("none", "zero", "a", "b")}
    assert not np.array_equal(_series(str(mpi_tmp_path / "c.h5"))["V2"], R["a"]["V2"])
    for k in R["none"]:
        np.testing.assert_array_equal(R["zero"][k], R["none"][k])
        np.testing.assert_array_equal(R["a"][k], R["b"][k])
    n = int((R["none"]["leg"] == 0).sum())
    np.testing.assert_array_equal(R["a"]["gamma"][:n], R["none"]["gamma"][:n])
    assert not np.array_equal(R["a"]["V2"][n:n + 5], R["none"]["V2"][n:n + 5])
    with h5py.File(p["a"], "r") as f:
        assert np.max(f["timeseries/length_error"][:]) <= 1e-11
    run_scene(_perturbed(p["part"], 1e-3), max_steps=n + 3)
    comm.barrier()
    assert run_scene(_perturbed(p["part"], 1e-3), restart=True) == "complete"
    comm.barrier()
    P = _series(p["part"])
    for k in ("gamma", "V2"):
        np.testing.assert_array_equal(P[k], R["a"][k])


def test_perturb_is_validated():
    with pytest.raises(InputError, match=r"protocol.leg\[1\].perturb"):
        _perturbed("x.h5", -1.0)
    susp = SUSPENSION + "perturb = 1e-6\n"
    with pytest.raises(InputError, match=r"protocol.leg\[0\].perturb: only for bonded"):
        load_scene(susp)
