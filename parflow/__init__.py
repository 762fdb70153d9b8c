"""parflow: parallel flow of dense non-Brownian suspensions and floppy rod networks
(affine solvent model), on PETSc/SLEPc."""

__version__ = "0.1.0"
