"""HDF5 output: one file per run, written by rank 0 (layout: docs/output.md).

The file named FILE is always a complete, closed HDF5 file: a flush appends what is pending
to a twin of it, ``FILE.tmp``, and renames the twin over FILE (atomic on POSIX); the old FILE
then becomes the next twin (``RunWriter``; guarantees and measurements: docs/output.md
"Faults").  A run killed at any moment therefore leaves FILE as of its last flush.

Layout:
    /            attrs: format, parflow_version, scene (TOML text), petsc_options, versions,
                        n_ranks, git_commit, created, status, message
    /initial     s, h0, E, bonds/{i, j, shift, l0}: the initial state
    /model       attrs: model constants (e.g. gamma_c of a chain)
    /timeseries  one resizable 1-D dataset per quantity, one row per accepted step
    /analysis/NNNNNNNN   arrays and attrs (step, gamma, scalars) at chosen instants
    /snapshots/NNNNNNNN  s, V_na, tau at chosen steps
    /checkpoint  the state needed by --restart (replaced at each checkpoint)

The package: :mod:`.reader` (``RunFile``, the one reader; ``read_run``, ``open_hdf5``,
``load_group``), :mod:`.writer` (``RunWriter``, ``atomic_h5``, the one whole-or-nothing writer,
``atomic_json`` its JSON twin, ``collective_write``, ``OutputOptions`` = the scene's [output]),
:mod:`.paths`
(``check_output_path``).
"""
from .paths import check_output_path
from .reader import FORMAT, HDF5_SIGNATURE, RunFile, load_group, open_hdf5, read_run
from .writer import (CHUNK_ROWS, OutputOptions, RunWriter, WriteError, atomic_h5, atomic_json,
                     collective_write, h5_attr, write_failure)

__all__ = ["CHUNK_ROWS", "FORMAT", "HDF5_SIGNATURE", "OutputOptions", "RunFile", "RunWriter",
           "WriteError", "atomic_h5", "atomic_json", "check_output_path", "collective_write", "h5_attr",
           "load_group", "open_hdf5", "read_run", "write_failure"]
