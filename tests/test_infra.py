"""Smoke tests of the toolchain parflow relies on: petsc4py/slepc4py from Debian,
MPI, and the direct solvers named in DESIGN.md §4 (MUMPS in parallel, CHOLMOD serially).
They also exercise tests/conftest.py (PETSc initialised without pytest's arguments,
``comm`` fixture, ``serial_only`` marker)."""

import sys

import numpy as np
import pytest
from petsc4py import PETSc
from slepc4py import SLEPc
from hang_guard import guard


def _laplacian_1d(n, comm):
    """SPD tridiagonal [-1 2 -1] matrix, AIJ, distributed over ``comm``."""
    A = PETSc.Mat().createAIJ([n, n], nnz=3, comm=comm)
    rstart, rend = A.getOwnershipRange()
    for i in range(rstart, rend):
        A.setValue(i, i, 2.0)
        if i > 0:
            A.setValue(i, i - 1, -1.0)
        if i < n - 1:
            A.setValue(i, i + 1, -1.0)
    A.assemble()
    return A


def _direct_solve(A, pc_type, solver_type):
    """Solve A x = A·1 with KSPPREONLY + a direct factorisation; return max |x - 1|."""
    ksp = PETSc.KSP().create(comm=A.getComm())
    ksp.setOperators(A)
    ksp.setType(PETSc.KSP.Type.PREONLY)
    pc = ksp.getPC()
    pc.setType(pc_type)
    pc.setFactorSolverType(solver_type)
    x_exact, b = A.createVecs()
    x_exact.set(1.0)
    A.mult(x_exact, b)
    x = x_exact.duplicate()
    ksp.solve(b, x)
    assert pc.getFactorSolverType() == solver_type
    assert ksp.getConvergedReason() > 0
    x.axpy(-1.0, x_exact)
    err = x.norm(PETSc.NormType.INFINITY)
    for obj in (ksp, x, x_exact, b):
        obj.destroy()
    return err


def test_petsc_is_initialised_without_pytest_args(comm):
    # conftest passes sys.argv[:1] to PETSc: none of pytest's own options (e.g. the
    # "-p no:cacheprovider" of make test-mpi) may show up in the PETSc options database.
    assert PETSc.Sys.isInitialized()
    opts = PETSc.Options().getAll()
    leaked = [a for a in sys.argv[1:]
              if a.startswith("-") and a.lstrip("-").split("=")[0] in opts]
    assert not leaked, (leaked, opts)
    assert PETSc.COMM_WORLD.getSize() == comm.Get_size()
    assert PETSc.COMM_WORLD.getRank() == comm.Get_rank()


def test_numpy_is_debian_1x():
    assert np.__version__.startswith("1."), np.__version__


def test_2x2_matrix_on_comm_world(comm):
    A = PETSc.Mat().createAIJ([2, 2], comm=PETSc.COMM_WORLD)
    A.setUp()
    rstart, rend = A.getOwnershipRange()
    for i in range(rstart, rend):
        A.setValues([i], [0, 1], [[2.0, 1.0] if i == 0 else [1.0, 3.0]])
    A.assemble()
    assert A.getSize() == (2, 2)
    assert comm.allreduce(rend - rstart) == 2
    y = A.createVecLeft()
    x = A.createVecRight()
    x.set(1.0)
    A.mult(x, y)
    # Gather the result on every rank and compare with the dense product.
    scatter, y_all = PETSc.Scatter.toAll(y)
    scatter.scatter(y, y_all)
    np.testing.assert_allclose(y_all.getArray(), [3.0, 4.0])
    assert A.norm(PETSc.NormType.FROBENIUS) == pytest.approx(np.sqrt(4 + 1 + 1 + 9))
    A.destroy()


def test_mumps_cholesky_and_lu(comm):
    A = _laplacian_1d(20, PETSc.COMM_WORLD)
    A.setOption(PETSc.Mat.Option.SPD, True)
    assert _direct_solve(A, PETSc.PC.Type.CHOLESKY, PETSc.Mat.SolverType.MUMPS) < 1e-10
    assert _direct_solve(A, PETSc.PC.Type.LU, PETSc.Mat.SolverType.MUMPS) < 1e-10
    A.destroy()


def test_mumps_via_options_database(comm):
    A = _laplacian_1d(12, PETSc.COMM_WORLD)
    ksp = PETSc.KSP().create(comm=PETSc.COMM_WORLD)
    ksp.setOptionsPrefix("infra_")
    opts = PETSc.Options()
    opts["infra_ksp_type"] = "preonly"
    opts["infra_pc_type"] = "cholesky"
    opts["infra_pc_factor_mat_solver_type"] = "mumps"
    try:
        ksp.setOperators(A)
        ksp.setFromOptions()
        x, b = A.createVecs()
        b.set(1.0)
        ksp.solve(b, x)
        assert ksp.getPC().getFactorSolverType() == "mumps"
        r = b.duplicate()
        A.mult(x, r)
        r.axpy(-1.0, b)
        assert r.norm() < 1e-10
    finally:
        for k in ("ksp_type", "pc_type", "pc_factor_mat_solver_type"):
            opts.delValue("infra_" + k)
        ksp.destroy()
        A.destroy()


@pytest.mark.serial_only
def test_cholmod_cholesky():
    A = _laplacian_1d(20, PETSc.COMM_SELF)
    A.setOption(PETSc.Mat.Option.SPD, True)
    assert _direct_solve(A, PETSc.PC.Type.CHOLESKY, PETSc.Mat.SolverType.CHOLMOD) < 1e-10
    A.destroy()


def test_slepc_smallest_eigenvalue(comm):
    n = 30
    A = _laplacian_1d(n, PETSc.COMM_WORLD)
    eps = SLEPc.EPS().create(comm=PETSc.COMM_WORLD)
    eps.setOperators(A)
    eps.setProblemType(SLEPc.EPS.ProblemType.HEP)
    eps.setWhichEigenpairs(SLEPc.EPS.Which.SMALLEST_REAL)
    eps.setTolerances(1e-10, 1000)
    eps.solve()
    assert eps.getConverged() >= 1
    lam = eps.getEigenvalue(0).real
    assert lam == pytest.approx(2 - 2 * np.cos(np.pi / (n + 1)), rel=1e-8)
    eps.destroy()
    A.destroy()


@pytest.mark.serial_only
def test_serial_only_marker_skips_under_mpi(comm):
    assert comm.Get_size() == 1


def test_mpi_tmp_path_is_shared(comm, mpi_tmp_path):
    paths = comm.allgather(str(mpi_tmp_path))
    assert len(set(paths)) == 1
    assert mpi_tmp_path.is_dir()


def test_h5py_parallel_write(comm, mpi_tmp_path):
    # Debian's h5py loads its MPI build only under mpirun (or with H5PY_ALWAYS_USE_MPI=1).
    import h5py

    path = mpi_tmp_path / "infra.h5"
    if comm.Get_size() > 1:
        assert h5py.get_config().mpi
        with h5py.File(path, "w", driver="mpio", comm=comm) as f:
            dset = f.create_dataset("rank", (comm.Get_size(),), dtype="i8")
            dset[comm.Get_rank()] = comm.Get_rank()
    else:
        with h5py.File(path, "w") as f:
            f.create_dataset("rank", data=[0])
    comm.Barrier()
    with h5py.File(path, "r") as f:
        np.testing.assert_array_equal(f["rank"][...], np.arange(comm.Get_size()))


def test_hang_guards_scale_with_the_test_timeout(monkeypatch):
    """PARFLOW_TEST_TIMEOUT above its default gives the subprocess hang guards the same
    factor; at or below it (and 0, no watchdog) they stay as written."""
    for value, expected in (("600", 120.0), ("1800", 360.0), ("300", 120.0), ("0", 120.0)):
        monkeypatch.setenv("PARFLOW_TEST_TIMEOUT", value)
        assert guard(120) == expected
    monkeypatch.delenv("PARFLOW_TEST_TIMEOUT")
    assert guard(30) == 30.0
