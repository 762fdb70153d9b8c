"""Recovery from a bad force solve: a Cholesky solve left far off round-off by its refinements
is refined further or refactorised (algebra.solvers, SUSPECT_BERR), and a bonded step whose
error does not shrink with the step re-evaluates the force at its start (dynamics.heun.Stall)
instead of shrinking the step until it declares a jam."""
import dataclasses

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from petsc4py import PETSc

from parflow.algebra.solvers import SUSPECT_BERR, CholeskySolver
from parflow.dynamics.bonded import BondedSystem
from parflow.dynamics.heun import Heun, Stall, StepControl
from parflow.dynamics.rkc import RKC
from parflow.models import chain


def spd(n=300, seed=0):
    """A sparse SPD matrix (a shifted ring Laplacian with random weights)."""
    rng = np.random.default_rng(seed)
    w = 0.5 + rng.random(n)
    i = np.arange(n)
    L = sp.coo_matrix((np.r_[-w, -w], (np.r_[i, (i + 1) % n], np.r_[(i + 1) % n, i])), (n, n))
    A = (L + sp.diags(np.asarray(-L.sum(axis=1)).ravel() + 1e-3)).tocsr()
    A.sort_indices()
    return A


def solver_on_own_arrays(A, prefix):
    """A CholeskySolver on a Mat built on the arrays of ``A`` (MatCreateSeqAIJWithArrays):
    writing A.data without assembling leaves PETSc's factor stale -- a factor that is wrong
    for the Mat, as the one bad solve measured on a long chain run was."""
    it = PETSc.IntType
    M = PETSc.Mat().createAIJWithArrays(A.shape, (A.indptr.astype(it), A.indices.astype(it), A.data),
                                        comm=PETSc.COMM_SELF)
    M.assemble()
    return M, CholeskySolver(M, prefix)


def solve(solver, M, b):
    rhs, x = M.createVecs()
    rhs.setArray(b)
    info = solver.solve(rhs, x, "test")
    return x.getArray().copy(), info


@pytest.mark.parametrize("change, refactorised", [(1e-3, False), (0.3, True)])
def test_a_solve_far_off_round_off_is_refined_or_refactorised(change, refactorised):
    A = spd()
    M, solver = solver_on_own_arrays(A, f"trec{int(refactorised)}_")
    b = np.random.default_rng(1).standard_normal(A.shape[0])
    x, info = solve(solver, M, b)
    assert info.backward_error < 1e-15 and solver.n_suspect == 0       # a sound factor
    d = 1 + change * np.random.default_rng(2).random(A.shape[0])     # A -> D A D, in place
    A.data *= d[np.repeat(np.arange(A.shape[0]), np.diff(A.indptr))] * d[A.indices]
    x, info = solve(solver, M, b)
    exact = spla.spsolve(A.tocsc(), b)
    # one refinement on the stale factor leaves it far off; the solve is not taken as it is
    assert solver.n_suspect == 1
    assert info.backward_error <= SUSPECT_BERR
    assert np.linalg.norm(x - exact) <= 1e-9 * np.linalg.norm(exact)
    # a small change is refined away (a few more steps); a large one needs the fresh factor
    assert info.refinements > 1 if not refactorised else info.refinements <= 1
    assert solver.n_refactorised == int(refactorised)
    solver.destroy()
    M.destroy()


def test_stall_needs_a_decade_without_progress():
    st = Stall()
    assert not st.stalled(1e-3, 0.2) and not st.stalled(3e-4, 0.2)
    assert st.stalled(9e-5, 0.19)                      # 11x smaller, error down only 5 %
    assert "did not shrink" in st.note and not st.stalled(1e-6, 0.2)   # once per step
    ok = Stall()
    for dg, err in [(1e-3, 0.2), (3e-4, 0.06), (9e-5, 0.02)]:    # err ~ dg: a stiff step
        assert not ok.stalled(dg, err)


@pytest.mark.parametrize("method", ["heun", "rkc"])
def test_a_step_from_a_bad_start_force_re_evaluates_it(method):
    """A start force 15 % off (a bad solve, or a checkpoint that kept one): every trial's error
    stays ~0.15 > tol however small the step.  The step evaluates the force again and goes on
    -- Heun to the very step the correct force gives, RKC to one as accurate."""
    st = chain.build(dict(N=120, epsilon=0.1, mu=0), seed=4)
    sysm = BondedSystem(PETSc.COMM_WORLD, st)
    c = StepControl(tol=0.05, method=method)
    cls = {"heun": Heun, "rkc": RKC}[method]
    F0 = sysm.evaluate(st.s, 0.0)
    good = cls(sysm, c).step(st.s, 0.0, F0, +1, 1e-3)
    rng = np.random.default_rng(3)
    noise = rng.standard_normal(F0.V_na.shape)
    bad = dataclasses.replace(F0, V_na=F0.V_na + 0.15 * np.linalg.norm(F0.V_na) / np.linalg.norm(noise)
                              * noise)
    before = sysm.n_refreshed
    res = cls(sysm, c).step(st.s, 0.0, bad, +1, 1e-3)
    assert sysm.n_refreshed == before + 1
    assert res.rejected >= 3 and res.err <= c.tol
    if method == "heun":
        assert res.gamma == good.gamma and np.array_equal(res.s, good.s)
    else:
        assert res.gamma > 0.25 * good.gamma
        d = np.abs(res.s - good.s).max() if res.gamma == good.gamma else 0.0
        assert d < 1e-6
    sysm.destroy()


def test_cholmod_factor_is_rebuilt_before_its_mark_overflows(monkeypatch):
    """CHOLMOD's workspace mark grows by n with each numeric factorisation and the one that
    passes 2^31 comes out wrong (measured at n = 1e5: the 21 475th); CholeskySolver rebuilds
    the factor before CHOLMOD_MARK_LIMIT rows.  With the limit lowered to 10 factorisations'
    worth, 25 refactorisations rebuild it twice, every solve still exact; another package
    (PETSc's own Cholesky) is left alone."""
    import parflow.algebra.solvers as S
    monkeypatch.setattr(S, "CHOLMOD_MARK_LIMIT", 10 * 300)
    for package, rebuilt in (("cholmod", 2), ("petsc", 0)):
        A = spd(300, seed=3)
        PETSc.Options().setValue(f"tmark_{package}_pc_factor_mat_solver_type", package)
        M, solver = solver_on_own_arrays(A, f"tmark_{package}_")
        assert solver.package == package
        b = np.random.default_rng(4).standard_normal(300)
        for k in range(25):
            A.data *= 1.01                       # in place: the Mat is told by assemble()
            M.assemble()
            x, info = solve(solver, M, b)
            assert info.backward_error < 1e-15
            assert np.linalg.norm(A @ x - b) <= 1e-12 * np.linalg.norm(b)
        assert solver.n_rebuilt == rebuilt, package
        solver.destroy()
        M.destroy()
