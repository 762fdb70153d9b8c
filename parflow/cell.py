"""Moved to :mod:`parflow.geometry` (kept only while other modules are being updated)."""
from .geometry import cell_at, pair_geometry, pair_vectors, velocity_gradient  # noqa: F401
