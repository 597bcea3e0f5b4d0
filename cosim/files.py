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


def _umask() -> int:
    m = os.umask(0o022)
    os.umask(m)
    return m


@contextmanager
def atomic_path(path):
    """Yield a temporary path beside `path`; on success it replaces `path`, else it is removed."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part",
                               dir=path.parent if str(path.parent) else ".")
    os.close(fd)
    try:
        yield tmp
        # mkstemp creates 0600; an output file gets the permissions any new file would.
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def write_json_atomic(path, obj) -> None:
    """Writes JSON to a temporary file in the same directory, then renames it into place."""
    with atomic_path(path) as tmp, open(tmp, "w", encoding="utf-8") as f:
        json.dump(obj, f, indent=1, allow_nan=True)
        f.write("\n")
