"""The working tree and, optionally, another revision checked out beside it (a temporary git
worktree), for benchmarks that compare the two in one run."""
from __future__ import annotations

import subprocess
import tempfile
from contextlib import contextmanager
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


@contextmanager
def trees(against=None):
    """Yields {"this tree": ROOT, against: its worktree} (the second only when ``against``)."""
    with tempfile.TemporaryDirectory() as tmp:
        out = {"this tree": ROOT}
        if against:
            old = Path(tmp) / "old"
            subprocess.run(["git", "worktree", "add", "--detach", "-q", str(old), against],
                           cwd=ROOT, check=True)
            out[against] = old
        try:
            yield out
        finally:
            if against:
                subprocess.run(["git", "worktree", "remove", "--force", str(out[against])],
                               cwd=ROOT)
