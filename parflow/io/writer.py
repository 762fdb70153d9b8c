"""Writing run files: the RunWriter (a flush costs what it appends; docs/output.md "Faults"), the
one whole-or-nothing HDF5 writer (atomic_h5), and write failures raised on every rank."""
from __future__ import annotations

import errno
import io
import json
import os
import re
import shutil
import time
from dataclasses import dataclass

import h5py
import numpy as np

from ..schema import POSITIVE
from ..schema import key as _key
from .reader import FORMAT


@dataclass
class OutputOptions:
    """The scene's [output] table (``schema``)."""
    path: str = _key("out/run.h5", lambda v: len(v) > 0, "a non-empty path", "the run file")
    flush_seconds: float = _key(30.0, *POSITIVE, "seconds between flushes (and at every checkpoint)")
    checkpoint_every: int = _key(500, *POSITIVE, "steps between checkpoints")
    checkpoint_minutes: float = _key(5.0, *POSITIVE, "minutes between checkpoints")
    progress_seconds: float = _key(2.0, *POSITIVE, "seconds between progress lines")


class WriteError(RuntimeError):
    """The run file could not be written (full disk, quota, I/O error).  The run loop raises
    it on every rank at once (rank 0's failure is broadcast), so that ``cli.run_main``
    reports it in one line and exits 1 without an MPI abort."""


_FULL = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)


def write_failure(path: str, exc: BaseException) -> str:
    """One line saying why writing ``path`` failed; a full disk is named as such."""
    folder = os.path.dirname(os.path.abspath(path))
    text = str(exc)
    code = getattr(exc, "errno", None)
    if not code:    # HDF5's own errors: "... errno = 28, error message = 'No space left ...'"
        m = re.search(r"errno = (\d+)", text)
        code = int(m.group(1)) if m else None
    if code in _FULL:
        try:
            free = f"{shutil.disk_usage(folder).free / 1e6:.1f} MB free"
        except OSError:
            free = "free space unknown"
        why = {errno.ENOSPC: "no space left on the device", errno.EDQUOT: "disk quota exceeded",
               errno.EFBIG: "file too large"}[code] + f" ({folder}: {free})"
    elif code:
        why = os.strerror(code)
    else:
        why = (text.splitlines() or [type(exc).__name__])[0][:200]
    return f"cannot write the run file {path!r}: {why}"


def collective_write(comm, writer, action) -> None:
    """``action(writer)`` on the writing rank (``writer`` is None elsewhere); a write failure
    there (OSError: full disk, quota, I/O error) is raised as the same WriteError on every
    rank, which costs one broadcast on several ranks."""
    err = None
    if writer is not None:
        try:
            action(writer)
        except OSError as exc:
            err = write_failure(writer.path, exc)
            if writer.n_rows:
                err += f"; the file keeps the run up to step {writer.n_rows - 1} (its last flush)"
    if comm.getSize() > 1:
        err = comm.tompi4py().bcast(err, root=0)
    if err is not None:
        raise WriteError(err)


CHUNK_ROWS = 4096        # rows per chunk of a time-series column


class RunWriter:
    """Buffers rows and groups; ``flush()`` publishes them atomically, at a cost that does
    not grow with the file (docs/output.md "Faults").

    Two files: FILE, which is only ever replaced whole, by a rename, and its twin, the
    shadow ``FILE.tmp``.  A flush appends the pending batch to the shadow in place (HDF5),
    closes and fsyncs it, keeps the current FILE under ``FILE.prev`` (a hard link), renames
    the shadow over FILE, renames FILE.prev to be the next shadow and appends the same batch
    to it.  Each batch is written twice, and nothing else is: FILE is never open for
    writing, so a kill at any moment leaves it a complete, closed file, as of the last
    flush.  When there is no good shadow (the first flush, after a failed or interrupted
    write, a reader holding the old FILE open so that HDF5's file lock refuses it, a file
    system without hard links), the flush starts by copying FILE: the old scheme's cost,
    once.  ``shadow=False`` copies at every flush (the old scheme, kept for the benchmark).

    HDF5 is never left to meet a full disk (its close then fails, and the library is left in
    a state that crashes the process): before writing a batch into a file, the space it
    needs is reserved with ``posix_fallocate`` (HDF5 trims the file to its end when it
    closes it), so a full disk is a clean OSError before anything is written, and the
    shadow stays a good twin.
    """

    def __init__(self, path: str, flush_seconds: float = 30.0, shadow: bool = True):
        self.path = path
        self.tmp = path + ".tmp"        # the shadow
        self.prev = path + ".prev"      # for an instant during a flush: the replaced FILE
        self.flush_seconds = flush_seconds
        self.shadow = shadow
        self._shadow_ok = False         # self.tmp is a closed twin of FILE
        self._rows: dict[str, list] = {}
        self._groups: list[tuple[str, dict, dict]] = []
        self._attrs: dict = {}
        self._checkpoint = None
        self._truncate: tuple[int, int] | None = None
        self._columns: dict[str, int] = {}   # time-series columns in the file: item size
        self._last_flush = time.monotonic()
        self.n_rows = 0          # rows in the file after the last flush
        self.copies = 0          # whole-file copies made so far

    # -- creation / reopening ---------------------------------------------------------
    def create(self, attrs: dict, groups: dict[str, tuple[dict, dict]]) -> None:
        """A new file: built in memory, then written with plain writes (a full disk is a
        clean OSError), fsynced and renamed to FILE."""
        self.discard()
        buf = io.BytesIO()
        with h5py.File(buf, "w") as f:
            f.attrs["format"] = FORMAT
            for k, v in attrs.items():
                f.attrs[k] = h5_attr(v)
            for name, (arrays, gattrs) in groups.items():
                _write_group(f, name, arrays, gattrs)
            f.create_group("timeseries")
        try:
            with open(self.tmp, "wb") as fh:
                fh.write(buf.getbuffer())
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(self.tmp, self.path)
        except BaseException:
            _remove(self.tmp)
            raise
        _fsync_dir(self.path)
        self.n_rows = 0
        self._columns = {}

    def reopen(self, n_rows: int, last_step: int) -> None:
        """Continue a run: drop rows after ``n_rows`` and groups after ``last_step``."""
        self.discard()             # a shadow left by a killed run is not trusted
        with h5py.File(self.path, "r") as f:
            ts = f.get("timeseries", {})
            self._columns = {k: ts[k].dtype.itemsize for k in ts}
        self._truncate = (n_rows, last_step)
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

    @property
    def pending_rows(self) -> int:
        return len(next(iter(self._rows.values()))) if self._rows else 0

    def drop_data(self) -> None:
        """Forget the pending rows, groups and checkpoint (kept: attributes, truncation)."""
        self._rows.clear()
        self._groups.clear()
        self._checkpoint = None

    # -- publishing ---------------------------------------------------------------------
    def flush(self, force: bool = False, final: bool = False) -> None:
        """Publish what is pending.  ``final``: the run's last flush (no next shadow is
        prepared).  On failure FILE is as it was, the pending data stay pending, and the
        exception (OSError for a full disk) propagates."""
        pending = self._rows or self._groups or self._attrs or self._checkpoint is not None \
            or self._truncate is not None
        if not pending and not force:
            return
        batch = dict(n0=self.n_rows, n_new=self.pending_rows, truncate=self._truncate,
                     rows={k: np.asarray(v) for k, v in self._rows.items()},
                     groups=list(self._groups), checkpoint=self._checkpoint, attrs=dict(self._attrs))
        need = self.batch_bytes(batch)
        keep = self.shadow and not final
        if not self._shadow_ok:
            self._copy()
        # room for both writes of the batch, taken before either: a full disk fails here,
        # cleanly, and the shadow is still a good twin (FILE.prev holds the second share)
        if keep:
            _allocate(self.prev, need, new=True)
        try:
            _allocate(self.tmp, need)
        except BaseException:
            _remove(self.prev)
            raise
        linked = False
        self._shadow_ok = False
        try:
            with h5py.File(self.tmp, "r+") as f:
                _apply(f, batch)
            _fsync(self.tmp)
            if keep:
                linked = self._link_prev()         # (frees the second share)
            os.replace(self.tmp, self.path)        # the flush takes effect here, atomically
        except BaseException:
            _remove(self.tmp)
            _remove(self.prev)
            raise
        # FILE holds the batch: it is no longer pending
        self.n_rows = batch["n0"] + batch["n_new"]
        self._columns.update({k: v.dtype.itemsize for k, v in batch["rows"].items()})
        self._rows.clear()
        self._groups.clear()
        self._attrs.clear()
        self._checkpoint = None
        self._truncate = None
        self._last_flush = time.monotonic()
        _fsync_dir(self.path)
        if not linked:
            return
        try:                                       # the old FILE becomes the next shadow
            os.replace(self.prev, self.tmp)
            _allocate(self.tmp, need)
            with h5py.File(self.tmp, "r+") as f:   # (refused if a reader has it open)
                _apply(f, batch)
            self._shadow_ok = True
        except Exception:
            self.discard()                         # the next flush copies FILE instead
        except BaseException:
            self.discard()
            raise

    def close(self, data: bool = True, **attrs) -> str | None:
        """The run's last write: what is pending (``data=False``: only the attributes) plus
        ``attrs`` (status, message, ...); then no temporary is left.  If the data cannot be
        written (a full disk), they are dropped and the attributes written alone, the
        message and ``steps`` saying where the file ends; if even that fails, FILE stays as
        of its last flush.  Returns None when everything was written, else one line saying
        what was not."""
        self.set_attrs(**attrs)
        why = "not written"
        if data:
            try:
                self.flush(force=True, final=True)
                self.discard()
                return None
            except OSError as exc:
                why = write_failure(self.path, exc)
        last = self.n_rows - 1
        if self.pending_rows or self._groups or self._checkpoint is not None:
            self.drop_data()
            if data:
                self._attrs["message"] = f"{self._attrs.get('message', '')}; {why}: the file " \
                                         f"ends at step {last}, its last flush".lstrip("; ")
            if "steps" in self._attrs:
                self._attrs["steps"] = last
        try:
            self.flush(force=True, final=True)
            return None if not data else \
                f"{why}: the rows after step {last} were dropped; the status was written"
        except OSError as exc:
            self._attrs.clear()
            return f"{write_failure(self.path, exc)}: the status could not be written; the " \
                   f"file is as of its last flush (step {last})"
        finally:
            self.discard()

    def discard(self) -> None:
        """Remove the shadow and FILE.prev (a run's end; a failed write; a new start)."""
        self._shadow_ok = False
        _remove(self.tmp)
        _remove(self.prev)

    def _copy(self) -> None:
        self._shadow_ok = False
        try:
            shutil.copyfile(self.path, self.tmp)
        except BaseException:
            _remove(self.tmp)
            raise
        self.copies += 1
        self._shadow_ok = True

    def _link_prev(self) -> bool:
        _remove(self.prev)
        try:
            os.link(self.path, self.prev)
            return True
        except OSError:          # no hard links here: the next flush copies FILE
            return False

    def batch_bytes(self, batch: dict) -> int:
        """An upper bound of what ``_apply(batch)`` adds to a file: the new chunks of the
        time series, the arrays and attributes of groups and checkpoint, HDF5's headers and
        B-tree nodes, plus a margin."""
        n0 = batch["n0"]
        n1 = n0 + batch["n_new"]

        def chunks(a, b):
            return -(-b // CHUNK_ROWS) - (-(-a // CHUNK_ROWS))

        need = 0
        items = dict(self._columns)
        items.update({k: v.dtype.itemsize for k, v in batch["rows"].items()})
        for name, item in items.items():
            new = chunks(n0 if name in self._columns else 0, n1)
            need += new * CHUNK_ROWS * item + (4096 if new or name not in self._columns else 0)

        def tree(arrays: dict, attrs: dict) -> int:
            b = 4096 + sum(_nbytes(v) + 512 for v in attrs.values())
            for v in arrays.values():
                b += tree(v, {}) if isinstance(v, dict) else _nbytes(v) + 4096
            return b

        for _, arrays, attrs in batch["groups"]:
            need += tree(arrays, attrs)
        if batch["checkpoint"] is not None:
            need += tree(*batch["checkpoint"])
        need += sum(_nbytes(v) + 1024 for v in batch["attrs"].values())
        return int(1.25 * need) + 16384


def _allocate(path: str, need: int, new: bool = False) -> None:
    """Allocate ``need`` bytes past the end of ``path`` (``new``: a new file of that size);
    a full disk raises OSError here, leaving the file as it was (``new``: removed).  HDF5
    trims a file it has written to its end when it closes it."""
    if not hasattr(os, "posix_fallocate"):
        return
    if new:
        _remove(path)
    fd = os.open(path, os.O_RDWR | (os.O_CREAT | os.O_EXCL if new else 0), 0o644)
    size = 0
    try:
        size = os.fstat(fd).st_size
        os.posix_fallocate(fd, size, need)
    except OSError as exc:
        if new:
            _remove(path)
        else:
            os.ftruncate(fd, size)
        if exc.errno in _FULL:
            raise
        # no fallocate on this file system: write without the reservation
    finally:
        os.close(fd)


def _nbytes(v) -> int:
    if isinstance(v, str):
        return len(v.encode())
    return int(np.asarray(v).nbytes)


def _apply(f, batch: dict) -> None:
    """Write one flush's batch into the open file ``f`` (the same batch goes into both
    copies, which stay alike)."""
    ts = f.require_group("timeseries")
    if batch["truncate"] is not None:
        n_keep, last_step = batch["truncate"]
        for name in ts:
            ts[name].resize((n_keep,))
        for gname in ("analysis", "snapshots"):
            if gname in f:
                for key in list(f[gname]):
                    if int(f[gname][key].attrs.get("step", 0)) > last_step:
                        del f[gname][key]
    n0, n_new = batch["n0"], batch["n_new"]
    if batch["checkpoint"] is not None and "checkpoint" in f:
        del f["checkpoint"]            # first: the new one reuses its space
    cols = {name: ts[name] for name in ts}     # (one lookup each: h5py's are not free)
    for name, arr in batch["rows"].items():
        d = cols.get(name)
        if d is None:
            fill = np.full(n0, np.nan) if arr.dtype.kind == "f" else np.zeros(n0, dtype=arr.dtype)
            d = cols[name] = ts.create_dataset(name, data=fill, maxshape=(None,),
                                               chunks=(CHUNK_ROWS,))
        d.resize((n0 + n_new,))
        d[n0:] = arr
    for name, d in cols.items():       # quantities absent from this batch
        if name not in batch["rows"] and d.shape[0] < n0 + n_new:
            old = d.shape[0]
            d.resize((n0 + n_new,))
            if d.dtype.kind == "f":
                d[old:] = np.nan
    for name, arrays, attrs in batch["groups"]:
        _write_group(f, name, arrays, attrs)
    if batch["checkpoint"] is not None:
        _write_group(f, "checkpoint", *batch["checkpoint"])
    for k, v in batch["attrs"].items():
        f.attrs[k] = h5_attr(v)


def _remove(path: str) -> None:
    try:
        os.remove(path)
    except FileNotFoundError:
        pass


def _fsync(path: str) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_dir(path: str) -> None:
    """Make a rename in the folder of ``path`` durable (where the file system allows)."""
    try:
        fd = os.open(os.path.dirname(os.path.abspath(path)), os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


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
        g.attrs[k] = h5_attr(v)


def atomic_json(path: str, obj, **dump_kw) -> None:
    """Write ``obj`` as JSON to ``path`` whole or not at all: to ``path.tmp``, fsynced, renamed
    over ``path`` (the twin removed on any error)."""
    tmp = path + ".tmp"
    try:
        with open(tmp, "w") as fh:
            json.dump(obj, fh, **dump_kw)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        _remove(tmp)
        raise


def h5_attr(v):
    return v.replace("\x00", "") if isinstance(v, str) else v


class atomic_h5:
    """``with atomic_h5(path) as f:`` -- an HDF5 file written whole or not at all: written as
    ``path.tmp`` (a copy of ``source`` first, if given, then opened for appending), fsynced and
    renamed over ``path`` on success; removed on any error.  (A run file's repeated flushes
    use :class:`RunWriter` instead, whose cost does not grow with the file.)"""

    def __init__(self, path: str, source: str | None = None):
        self.path, self.source, self.tmp = path, source, path + ".tmp"
        self.f = None

    def __enter__(self) -> h5py.File:
        try:
            if self.source is not None:
                shutil.copyfile(self.source, self.tmp)
                self.f = h5py.File(self.tmp, "a")
            else:
                self.f = h5py.File(self.tmp, "w")
        except BaseException:
            _remove(self.tmp)
            raise
        return self.f

    def __exit__(self, typ, exc, tb) -> None:
        try:
            self.f.close()
            if typ is None:
                _fsync(self.tmp)
                os.replace(self.tmp, self.path)
                _fsync_dir(self.path)
        finally:
            _remove(self.tmp)
