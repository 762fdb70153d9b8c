"""HDF5 output: one file per run, written by rank 0 (layout: docs/output.md).

The file on disk is always a complete, closed HDF5 file: every flush copies it to
``FILE.tmp``, appends what is pending, and renames the copy over ``FILE`` (atomic on POSIX).
A run killed at any moment therefore leaves the file as of its last flush.

Layout:
    /            attrs: format, parflow_version, scene (TOML text), petsc_options, versions,
                        n_ranks, git_commit, created, status, message
    /initial     s, h0, E, bonds/{i, j, shift, l0}: the initial state
    /model       attrs: model constants (e.g. gamma_c of a chain)
    /timeseries  one resizable 1-D dataset per quantity, one row per accepted step
    /analysis/NNNNNNNN   arrays and attrs (step, gamma, scalars) at chosen instants
    /snapshots/NNNNNNNN  s, V_na, tau at chosen steps
    /checkpoint  the state needed by --restart (replaced at each checkpoint)
"""
from __future__ import annotations

import os
import shutil
import time

import h5py
import numpy as np

from .state import InputError

FORMAT = "parflow-run-1"


def check_output_path(path: str, overwrite: bool) -> None:
    """Fail early (before any work) if the output cannot be written."""
    if os.path.isdir(path):
        raise InputError(f"output path {path!r} is a directory: give a file name")
    if os.path.exists(path) and not overwrite:
        raise InputError(f"output file {path!r} exists: pass --overwrite to replace it, or "
                         f"--output to choose another file")
    folder = os.path.dirname(os.path.abspath(path))
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create the output folder {folder!r}: {exc.strerror}") from None
    if not os.access(folder, os.W_OK):
        raise InputError(f"output folder {folder!r} is not writable")


class RunWriter:
    """Buffers rows and groups; ``flush()`` publishes them atomically."""

    def __init__(self, path: str, flush_seconds: float = 30.0):
        self.path = path
        self.tmp = path + ".tmp"
        self.flush_seconds = flush_seconds
        self._rows: dict[str, list] = {}
        self._groups: list[tuple[str, dict, dict]] = []
        self._attrs: dict = {}
        self._checkpoint = None
        self._truncate_to: int | None = None
        self._last_flush = time.monotonic()
        self.n_rows = 0          # rows in the file after the last flush

    # -- creation / reopening ---------------------------------------------------------
    def create(self, attrs: dict, groups: dict[str, tuple[dict, dict]]) -> None:
        with h5py.File(self.tmp, "w") as f:
            f.attrs["format"] = FORMAT
            for k, v in attrs.items():
                f.attrs[k] = _attr(v)
            for name, (arrays, gattrs) in groups.items():
                _write_group(f, name, arrays, gattrs)
            f.create_group("timeseries")
        os.replace(self.tmp, self.path)
        self.n_rows = 0

    def reopen(self, n_rows: int, last_step: int) -> None:
        """Continue a run: drop rows after ``n_rows`` and groups after ``last_step``."""
        self._truncate_to = n_rows
        self._drop_after = last_step
        self.n_rows = n_rows
        self.flush(force=True)

    # -- buffering ----------------------------------------------------------------------
    def append(self, row: dict) -> None:
        for k, v in row.items():
            self._rows.setdefault(k, []).append(v)

    def add_group(self, name: str, arrays: dict, attrs: dict) -> None:
        self._groups.append((name, arrays, attrs))

    def set_attrs(self, **attrs) -> None:
        self._attrs.update(attrs)

    def set_checkpoint(self, arrays: dict, attrs: dict) -> None:
        self._checkpoint = (arrays, attrs)

    def due(self) -> bool:
        return time.monotonic() - self._last_flush >= self.flush_seconds

    # -- publishing ---------------------------------------------------------------------
    def flush(self, force: bool = False) -> None:
        pending = self._rows or self._groups or self._attrs or self._checkpoint is not None \
            or self._truncate_to is not None
        if not pending and not force:
            return
        shutil.copyfile(self.path, self.tmp)
        try:
            with h5py.File(self.tmp, "a") as f:
                ts = f.require_group("timeseries")
                if self._truncate_to is not None:
                    for name in ts:
                        ts[name].resize((self._truncate_to,))
                    for gname in ("analysis", "snapshots"):
                        if gname in f:
                            for key in list(f[gname]):
                                if int(f[gname][key].attrs.get("step", 0)) > self._drop_after:
                                    del f[gname][key]
                    self._truncate_to = None
                n_new = len(next(iter(self._rows.values()))) if self._rows else 0
                for name, values in self._rows.items():
                    arr = np.asarray(values)
                    if name not in ts:
                        fill = np.full(self.n_rows, np.nan) if arr.dtype.kind == "f" \
                            else np.zeros(self.n_rows, dtype=arr.dtype)
                        ts.create_dataset(name, data=fill, maxshape=(None,), chunks=(4096,))
                    d = ts[name]
                    d.resize((self.n_rows + n_new,))
                    d[self.n_rows:] = arr
                for name in ts:                   # quantities absent from this batch
                    if ts[name].shape[0] < self.n_rows + n_new:
                        old = ts[name].shape[0]
                        ts[name].resize((self.n_rows + n_new,))
                        if ts[name].dtype.kind == "f":
                            ts[name][old:] = np.nan
                for name, arrays, attrs in self._groups:
                    _write_group(f, name, arrays, attrs)
                if self._checkpoint is not None:
                    if "checkpoint" in f:
                        del f["checkpoint"]
                    _write_group(f, "checkpoint", *self._checkpoint)
                for k, v in self._attrs.items():
                    f.attrs[k] = _attr(v)
            os.replace(self.tmp, self.path)
        except BaseException:
            if os.path.exists(self.tmp):
                os.remove(self.tmp)
            raise
        self.n_rows += n_new
        self._rows.clear()
        self._groups.clear()
        self._attrs.clear()
        self._checkpoint = None
        self._last_flush = time.monotonic()


def _write_group(f, name, arrays: dict, attrs: dict):
    g = f.require_group(name)
    for k, v in arrays.items():
        if isinstance(v, dict):
            _write_group(g, k, v, {})
        else:
            if k in g:
                del g[k]
            g.create_dataset(k, data=np.asarray(v))
    for k, v in attrs.items():
        g.attrs[k] = _attr(v)


def _attr(v):
    return v.replace("\x00", "") if isinstance(v, str) else v


HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


def _hdf5_signature(path: str, size: int) -> bool:
    """Whether the HDF5 superblock signature is where the format puts it: at byte 0, or
    after a user block of 512, 1024, 2048, ... bytes."""
    with open(path, "rb") as fh:
        offset = 0
        while offset + len(HDF5_SIGNATURE) <= size:
            fh.seek(offset)
            if fh.read(len(HDF5_SIGNATURE)) == HDF5_SIGNATURE:
                return True
            offset = 512 if offset == 0 else 2 * offset
    return False


def open_hdf5(path: str) -> h5py.File:
    """Open an HDF5 file read-only, with a clear error if it is missing, unreadable, not
    HDF5 at all, or an HDF5 file that is cut short or damaged (a copy that did not finish,
    a full disk)."""
    import re
    if os.path.isdir(path):
        raise InputError(f"{path!r} is a directory, not an HDF5 file")
    if not os.path.isfile(path):
        raise InputError(f"{path!r} does not exist")
    try:
        size = os.path.getsize(path)
        signed = _hdf5_signature(path, size)
    except OSError as exc:
        raise InputError(f"cannot read {path!r}: {exc.strerror or exc}") from None
    if not signed:
        raise InputError(f"{path!r} is not an HDF5 file ({size} bytes, no HDF5 signature)")
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        text = str(exc)
        m = re.search(r"stored_eof\s*=\s*(\d+)", text)
        whole = f" of its {int(m.group(1))}" if m else ""
        why = "truncated" if "truncated" in text else "damaged or truncated"
        raise InputError(f"{path!r} is a {why} HDF5 file ({size} bytes{whole}): it cannot be "
                         f"read; restore it from a copy") from None


def read_run(path: str) -> h5py.File:
    """Open a parflow run file read-only, with a clear error if it is not one."""
    f = open_hdf5(path)
    fmt = f.attrs.get("format")
    if isinstance(fmt, bytes):
        fmt = fmt.decode(errors="replace")
    if fmt != FORMAT:
        f.close()
        why = "format attribute missing" if fmt is None else f"format {fmt!r}, not {FORMAT!r}"
        raise InputError(f"{path!r} is not a parflow run file ({why})")
    return f


def load_group(g) -> dict:
    out = {}
    for k, v in g.items():
        out[k] = load_group(v) if isinstance(v, h5py.Group) else v[()]
    return out
