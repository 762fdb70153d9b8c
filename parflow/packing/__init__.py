"""Jammed soft-sphere packings and the binary mixture they are made of (no PETSc, no MPI).

Used by the network build (``models.network_build``), the suspension's initial states
(``models.suspension``) and ``prepare compress``.

* ``mixture``: the one source of the mixture's constants (SMALL_DIAMETER, RADIUS_RATIO,
  PHI_J by dimension), ``binary_radii``, volumes, box sides and input checks;
* ``fire``: FIRE minimisation, ``make_packing`` (with pressure targeting), ``Packing``,
  ``remove_rattlers``;
* ``pairs``: the pair-list interface ``PairList``, the numpy kernel ``NumpyPairs`` and
  ``pair_list(kernel=...)``, which picks a kernel;
* ``pairs_numba``: the compiled kernel ``NumbaPairs`` (optional numba, imported at first
  use).

The submodules are not imported here, so that ``mixture`` stays a numpy-only import.
"""
