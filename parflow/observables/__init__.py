"""Observables: functions of arrays (numpy/scipy), no PETSc, no models.

* :mod:`.response`    -- point response of a rod, two-exponential fits (l_c, l_r)
* :mod:`.correlation` -- velocity correlation C(r), exact and by FFT; crossing lengths
"""
