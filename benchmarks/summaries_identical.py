"""Show that a change leaves `se3sync run` bit-identical: run every shipped scenario with every
registered law at two revisions and compare the summaries, wall-clock fields aside.

    python benchmarks/summaries_identical.py REV [--duration S]

REV is checked out into a temporary git worktree; the working tree is the other side. A scenario
or a law that REV does not have is listed and skipped. Exit status 0 when every summary compared
is identical, 1 otherwise.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
WALL = {"wall_time_s", "realtime_factor", "us_per_step", "log", "log_messages", "scenario_path"}


def run(tree: Path, scenario: str, law: str, out: Path, duration) -> dict:
    cmd = [sys.executable, "-m", "cosim.cli", "run", str(tree / "scenarios" / scenario),
           "--controller", law, "--summary", str(out), "--force"]
    if duration is not None:
        cmd += ["--duration", str(duration)]
    subprocess.run(cmd, cwd=tree, check=True, capture_output=True, text=True)
    d = json.loads(out.read_text())
    for k in WALL:
        d.pop(k, None)
    return d


def laws(tree: Path) -> list:
    """The laws registered in that tree's cosim/registry.py (imported from the tree itself)."""
    out = subprocess.run([sys.executable, "-c", "from cosim.registry import LAWS; print(*LAWS)"],
                         cwd=tree, check=True, capture_output=True, text=True)
    return out.stdout.split()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("rev", help="the revision to compare the working tree with (e.g. HEAD~1)")
    ap.add_argument("--duration", type=float, help="shorter runs (default: each scenario's)")
    args = ap.parse_args()
    scenarios = sorted(p.name for p in (ROOT / "scenarios").glob("*.toml"))
    same = True
    with tempfile.TemporaryDirectory() as tmp:
        old = Path(tmp) / "old"
        subprocess.run(["git", "worktree", "add", "--detach", "-q", str(old), args.rev], cwd=ROOT,
                       check=True)
        try:
            old_laws = set(laws(old))
            for sc in scenarios:
                if not (old / "scenarios" / sc).exists():
                    print(f"{sc:28s} (new at this revision, skipped)")
                    continue
                for law in laws(ROOT):
                    if law not in old_laws:
                        print(f"{sc:28s} {law:9s} (a law {args.rev} does not have, skipped)")
                        continue
                    a = run(old, sc, law, Path(tmp) / "a.json", args.duration)
                    b = run(ROOT, sc, law, Path(tmp) / "b.json", args.duration)
                    diff = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
                    same &= not diff
                    print(f"{sc:28s} {law:9s} {'identical' if not diff else 'DIFFERS: ' + ', '.join(diff)}")
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(old)], cwd=ROOT)
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
