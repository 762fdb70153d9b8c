"""Reading run files: open with clear errors (missing, not HDF5, truncated, not a run file)
and RunFile, the one reader of the format."""
from __future__ import annotations

import os
import re

import h5py
import numpy as np

from ..state import InputError, State

FORMAT = "parflow-run-1"
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


def _text(v):
    return v.decode(errors="replace") if isinstance(v, bytes) else v


def _scalar(v):
    v = _text(v)
    return v.item() if isinstance(v, np.generic) else v


class RunFile:
    """The one reader of a run file (layout above), opened read-only with the checks of
    :func:`read_run` (InputError: missing, not HDF5, damaged, not a parflow run file).

    ``with RunFile(path) as run:`` then ``run.attrs``, ``run.model``, ``run.scene_text``,
    ``run.settings``, ``run.model_attrs``, ``run.timeseries()``, ``run.analyses()``,
    ``run.snapshot_steps()``, ``run.snapshot(step)``, ``run.initial()``,
    ``run.initial_state()``, ``run.has_checkpoint``, ``run.checkpoint()``; ``run.h5`` is the
    open h5py file for what has no method yet."""

    def __init__(self, path: str):
        self.path = path
        self.h5 = read_run(path)

    def close(self) -> None:
        self.h5.close()

    def __enter__(self) -> "RunFile":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- attributes ----------------------------------------------------------------------
    @property
    def attrs(self) -> dict:
        return {k: _scalar(v) for k, v in self.h5.attrs.items()}

    @property
    def model(self) -> str:
        return str(_text(self.h5.attrs.get("model", "")))

    @property
    def scene_text(self) -> str:
        return str(_text(self.h5.attrs.get("scene", "")))

    @property
    def settings(self) -> list[str]:
        """The ``--set`` settings the run was given (and later restarts re-apply)."""
        return [s for s in str(_text(self.h5.attrs.get("scene_settings", ""))).split("\n") if s]

    @property
    def model_attrs(self) -> dict:
        g = self.h5.get("model")
        return {k: _scalar(v) for k, v in g.attrs.items()} if isinstance(g, h5py.Group) else {}

    # -- data ----------------------------------------------------------------------------
    def timeseries(self) -> dict:
        """Every 1-D time-series column, cut to their common length."""
        ts = {}
        g = self.h5.get("timeseries")
        if isinstance(g, h5py.Group):
            ts = {k: d[()] for k, d in g.items() if isinstance(d, h5py.Dataset) and d.ndim == 1}
        n = min((len(v) for v in ts.values()), default=0)
        return {k: v[:n] for k, v in ts.items()}

    def analyses(self) -> list[dict]:
        """The analysis instants in step order: their attributes and arrays in one dict."""
        out = []
        g = self.h5.get("analysis")
        for key in sorted(g) if isinstance(g, h5py.Group) else ():
            a_g = g[key]
            if not isinstance(a_g, h5py.Group):
                continue
            a = {k: _scalar(v) for k, v in a_g.attrs.items()}
            a.setdefault("step", int(key) if key.isdigit() else -1)
            a.update({k: d[()] for k, d in a_g.items() if isinstance(d, h5py.Dataset)})
            out.append(a)
        return out

    def snapshot_steps(self) -> list[int]:
        g = self.h5.get("snapshots")
        return sorted(int(k) for k in g if k.isdigit()) if isinstance(g, h5py.Group) else []

    def snapshot(self, step: int) -> dict:
        """The snapshot at ``step``: its arrays and attributes (KeyError if there is none)."""
        g = self.h5[f"snapshots/{step:08d}"]
        out = {k: _scalar(v) for k, v in g.attrs.items()}
        out.update(load_group(g))
        return out

    def initial(self) -> dict:
        return load_group(self.h5["initial"])

    def initial_state(self, gamma: float = 0.0, s=None):
        """The run's State (/initial: cell, bonds, radii), with positions ``s`` (default: the
        initial ones) at strain ``gamma``, and /model attributes as its meta."""
        g = self.initial()
        if s is not None:
            g["s"] = s
        return State.from_groups(g, gamma, self.model_attrs)

    @property
    def has_checkpoint(self) -> bool:
        return isinstance(self.h5.get("checkpoint"), h5py.Group)

    def checkpoint(self) -> dict:
        """The checkpoint's attributes and arrays in one dict."""
        g = self.h5["checkpoint"]
        ck = dict(g.attrs)
        ck.update(load_group(g))
        return ck
