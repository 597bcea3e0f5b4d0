"""Output files that appear whole or not at all.

Every output but the streamed MCAP log is written to a temporary file beside its target and
renamed onto it, so a failed or interrupted command never leaves half a file behind.
"""
from __future__ import annotations

import json
import os
import tempfile
from contextlib import contextmanager
from pathlib import Path

from controller.errors import Se3SyncError


def _umask() -> int:
    m = os.umask(0o022)
    os.umask(m)
    return m


def check_output(option: str, path, suffixes=None) -> Path:
    """Refuses, before any work starts, an output path that cannot be written: a directory, a
    missing parent, a place where no file can be created (tried for real: permission bits say
    nothing to root or on read-only file systems), or a suffix outside ``suffixes``. Raises
    Se3SyncError naming the option and the path; returns the Path."""
    p = Path(path)
    if suffixes is not None and p.suffix.lower() not in suffixes:
        raise Se3SyncError(f"{option}: {str(path)!r} must end in {' or '.join(suffixes)}")
    if p.is_dir():
        raise Se3SyncError(f"{option}: {str(path)!r} is a directory")
    _writable_in(option, path, p.parent if str(p.parent) else Path("."))
    return p


def _writable_in(option: str, path, d: Path) -> None:
    """d exists and a file can be created in it (tried for real)."""
    if not d.is_dir():
        raise Se3SyncError(f"{option}: {str(path)!r}: directory {str(d)!r} does not exist")
    try:
        fd, tmp = tempfile.mkstemp(prefix=".se3sync.", suffix=".check", dir=d)
    except OSError as exc:
        raise Se3SyncError(f"{option}: {str(path)!r}: cannot write in {str(d)!r}: "
                           f"{exc.strerror or exc}") from None
    os.close(fd)
    os.unlink(tmp)


def check_output_dir(option: str, path) -> Path:
    """Refuses, before any work starts, a directory option that cannot hold outputs: a file, a
    missing parent (the directory itself is created when missing, its parent never), or a
    place where no file can be created. Raises Se3SyncError naming the option and the path."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise Se3SyncError(f"{option}: {str(path)!r} exists and is not a directory")
    _writable_in(option, path, p if p.is_dir() else (p.parent if str(p.parent) else Path(".")))
    return p


@contextmanager
def atomic_path(path):
    """Yield a temporary path beside `path`; on success it replaces `path`, else it is removed."""
    path = Path(path)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part",
                                   dir=path.parent if str(path.parent) else ".")
    except OSError as exc:
        raise Se3SyncError(f"{path}: cannot write: {exc.strerror or exc}") from None
    os.close(fd)
    try:
        yield tmp
        # mkstemp creates 0600; an output file gets the permissions any new file would.
        os.chmod(tmp, 0o666 & ~_umask())
        try:
            os.replace(tmp, path)
        except OSError as exc:  # e.g. the target became a directory meanwhile
            raise Se3SyncError(f"{path}: cannot write: {exc.strerror or exc}") from None
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def write_json_atomic(path, obj) -> None:
    """Writes JSON to a temporary file in the same directory, then renames it into place."""
    with atomic_path(path) as tmp:
        try:
            with open(tmp, "w", encoding="utf-8") as f:
                json.dump(obj, f, indent=1, allow_nan=True)
                f.write("\n")
        except OSError as exc:  # a full disk names the file the user asked for
            raise Se3SyncError(f"{path}: cannot write: {exc.strerror or exc}") from None
