"""The numbers the docs quote, computed from run files (no drawing).

* :mod:`.fits`        log-binning, power laws, divergence points, fit windows, branches
* :mod:`.chain`       chain_theory, chain_fits, reversal_departure (paper Fig. 2)
* :mod:`.network`     reverse_branch, fit_reverse_branch, fit_omega_star, network_fits,
                      across_fits (paper Figs. 3, 4, 5, 8)
* :mod:`.suspension`  suspension_fits, pooled_fits, fit_phi_c, across_suspension (Figs. 6-7)
* :mod:`.report`      format_fits and the format_* lines printed by ``python -m parflow.plot``

A layer rule, checked by tests/test_plot.py: this package imports numpy (and the standard
library) and nothing of parflow outside it but ``parflow.io``; in particular neither the
models, the engines nor PETSc/SLEPc.  A run is what ``parflow.plot.load_run`` returns (see
:mod:`.fits`).
"""
