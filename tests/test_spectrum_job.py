"""python -m parflow.spectrum on saved states: low / interval / dense agree with numpy on a
small network, from a run file (checkpoint, snapshot) and from a network file; bad input."""
import h5py
import numpy as np
import pytest
from petsc4py import PETSc

from parflow.models import network as nw
from parflow.models import network_build as nb
from parflow.run import Run, setup_logging
from parflow.scene import load_scene
from parflow.spectrum import load_state, main


@pytest.fixture(scope="module")
def run_file(tmp_path_factory):
    """One small network run shared by the tests of this module (a folder common to all ranks)."""
    from mpi4py import MPI
    comm = MPI.COMM_WORLD
    folder = comm.bcast(str(tmp_path_factory.mktemp("specjob")) if comm.rank == 0 else None, root=0)
    path = folder + "/net.h5"
    scene = load_scene(f"""
seed = 2
[model]
name = "network"
N = 160
z = 3.8
[[protocol.leg]]
direction = "forward"
sigma_above = 100
[observables]
snapshot_every = 5
[output]
path = "{path}"
""")
    setup_logging(PETSc.COMM_WORLD, quiet=True)
    assert Run(scene, PETSc.COMM_WORLD, path, quiet=True).execute() == "complete"
    comm.barrier()
    return path


def _reference(state):
    from parflow.geometry import pair_geometry
    bd = state.bonds
    _, _, n, _ = pair_geometry(state.s, state.h, state.E, bd.i, bd.j, bd.shift)
    return nw.dense_spectrum(n, bd, state.n)


def test_low_interval_dense_agree(run_file, mpi_tmp_path, comm):
    state, prov = load_state(run_file)
    assert prov["where"] == "checkpoint" and state.gamma > 0
    ref = _reference(state)
    outs = {}
    for method, extra in (("low", ["--k", "5"]), ("dense", []),
                          ("interval", ["--omega-max", f"{ref[7] * 1.0001:.17g}"])):
        out = str(mpi_tmp_path / f"sp_{method}.h5")
        assert main([run_file, "--method", method, "--output", out] + extra) == 0
        outs[method] = out
    comm.barrier()
    with h5py.File(outs["low"]) as a, h5py.File(outs["dense"]) as b, h5py.File(outs["interval"]) as c:
        assert a.attrs["format"] == "parflow-spectrum-1" and a.attrs["n_rods"] == len(state.bonds)
        np.testing.assert_allclose(a["omega"][:], ref[:5], rtol=1e-8)
        np.testing.assert_allclose(b["omega"][:], ref, rtol=1e-8, atol=1e-12)
        np.testing.assert_allclose(c["omega"][:], ref[:8], rtol=1e-8)
        assert a.attrs["gamma"] == pytest.approx(state.gamma)
    comm.barrier()


def test_snapshot_and_network_file(run_file, mpi_tmp_path, comm):
    st5, prov = load_state(run_file, step=5)
    assert prov["where"] == "snapshots/00000005"
    out = str(mpi_tmp_path / "sp5.h5")
    assert main([run_file, "--step", "5", "--k", "3", "--output", out]) == 0
    netfile = str(mpi_tmp_path / "netfile.h5")
    if comm.rank == 0:
        nb.save_network(netfile, nw.make(dict(N=160, z=3.8), seed=2))
    comm.barrier()
    out0 = str(mpi_tmp_path / "sp0.h5")
    assert main([netfile, "--k", "2", "--output", out0]) == 0
    comm.barrier()
    with h5py.File(out) as a, h5py.File(out0) as b:
        np.testing.assert_allclose(a["omega"][:], _reference(st5)[:3], rtol=1e-8)
        assert b.attrs["source_kind"] == "network" and b.attrs["gamma"] == 0.0
        st0, _ = load_state(netfile)
        np.testing.assert_allclose(b["omega"][:], _reference(st0)[:2], rtol=1e-8)
    comm.barrier()


@pytest.mark.parametrize("args, msg", [
    (["nofile.h5"], "does not exist"),
    (["RUN", "--step", "3"], "no snapshot at step 3"),
    (["RUN", "--k", "0"], "--k must be"),
    (["RUN", "--method", "interval"], "omega-max"),
])
def test_bad_input(args, msg, run_file, mpi_tmp_path, capsys, comm):
    out = str(mpi_tmp_path / "bad.h5")
    args = [run_file if a == "RUN" else a for a in args]
    assert main(args + ["--output", out]) == 2
    comm.barrier()
    if comm.rank == 0:
        assert msg in capsys.readouterr().err
    import os
    assert not os.path.exists(out) and not os.path.exists(out + ".tmp")
    comm.barrier()
