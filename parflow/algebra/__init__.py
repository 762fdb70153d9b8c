"""The distributed algebra: the only package that imports petsc4py and slepc4py (besides
``cli.init_petsc``, which initialises PETSc with the command line's options first).

* :mod:`.operators` -- S and N as PETSc Mats for a fixed pair list (locked CSR pattern)
* :mod:`.solvers`   -- the force solve N tau = -b (presets, Cholesky, checks), options
* :mod:`.spectrum`  -- the low spectrum of N with SLEPc (omega_min on the force factor)
"""
