"""Output paths, checked before any work."""
from __future__ import annotations

import errno
import os

from ..state import InputError


def check_output_path(path: str, overwrite: bool, flag: str = "--output") -> None:
    """Fail early (before any work) if the output cannot be written: the name, an existing
    file without ``overwrite``, and the folder (created if missing, like ``mkdir -p``; a
    probe file, as long a name as the temporary files the writers use, is created and
    removed in it, so that a folder where files cannot be created -- /proc, a read-only
    mount -- is refused now rather than at the first write)."""
    if not isinstance(path, str) or not path.strip():
        raise InputError(f"the output path is empty: give a file name ({flag})")
    if "\x00" in path:
        raise InputError(f"output path {path!r} contains a NUL character")
    if path.endswith(("/", os.sep, "/.", "/..")) or os.path.basename(path) in (".", ".."):
        raise InputError(f"output path {path!r} names a folder, not a file: give a file name "
                         f"(e.g. {os.path.join(path, 'run.h5')!r})")
    if os.path.isdir(path):
        raise InputError(f"output path {path!r} is a directory: give a file name")
    if os.path.lexists(path):
        if not overwrite:
            raise InputError(f"output file {path!r} exists: pass --overwrite to replace it, or "
                             f"{flag} to choose another file")
        if os.path.exists(path) and not os.path.isfile(path):
            raise InputError(f"output path {path!r} exists and is not a regular file: "
                             f"it is not replaced")
    folder = os.path.dirname(os.path.abspath(path))
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create the output folder {folder!r}: "
                         f"{exc.strerror or exc}") from None
    if not os.path.isdir(folder):
        raise InputError(f"cannot create the output folder {folder!r}: not a directory")
    probe = os.path.join(folder, f".{os.path.basename(path)}.probe")
    try:
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        fd = None          # a probe left by a killed check: the folder takes files
    except OSError as exc:
        if exc.errno == errno.ENAMETOOLONG:
            raise InputError(f"output file name {os.path.basename(path)[:40]!r}... is too long "
                             f"({len(os.path.basename(path))} characters): give a shorter "
                             f"name") from None
        raise InputError(f"cannot create files in the output folder {folder!r}: "
                         f"{exc.strerror or exc}") from None
    if fd is not None:
        os.close(fd)
    try:
        os.remove(probe)
    except OSError:
        pass
