"""Start-up time of the command line: `se3sync --help`, `se3sync check` on the paper scenario and
`se3sync run` of its first 0.01 s (analysis, 100 compiled steps, the log), optionally against another revision in the same run (interleaved, so load affects both alike).

    python benchmarks/bench_startup.py [--against REV] [--repeat K]

Reports the median wall time of K runs of each command (numba's on-disk cache warm: one untimed
run first) and, with --against, the ratio new/old.
"""
from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from _revisions import trees as revision_trees  # noqa: E402
import _markdown  # noqa: E402
COMMANDS = {"--help": ["--help"], "check paper": ["check", "scenarios/paper_6uav.toml"],
            "run paper": ["run", "scenarios/paper_6uav.toml", "--duration", "0.01",
                          "--log", "{tmp}/run.mcap"]}


def once(tree: Path, args) -> float:
    t = time.perf_counter()
    subprocess.run([sys.executable, "-m", "cosim.cli", *args], cwd=tree, check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--against", metavar="REV", help="also time this revision (git worktree)")
    ap.add_argument("--repeat", type=int, default=7)
    _markdown.add_option(ap)
    args = ap.parse_args()
    rows = []
    with _markdown.Report(args.markdown) as rep, revision_trees(args.against) as trees, \
            tempfile.TemporaryDirectory() as tmp:
        for name, cmd in COMMANDS.items():
            cmd = [c.format(tmp=tmp) for c in cmd]
            times = {k: [] for k in trees}
            for tree in trees.values():
                once(tree, cmd)  # warm the numba cache and the file system
            for _ in range(args.repeat):
                for k, tree in trees.items():
                    times[k].append(once(tree, cmd))
            med = {k: statistics.median(v) for k, v in times.items()}
            line = ", ".join(f"{k} {v * 1e3:.0f} ms" for k, v in med.items())
            if args.against:
                line += f"; ratio {med['this tree'] / med[args.against]:.2f}"
            print(f"se3sync {name:12s} median of {args.repeat}: {line}")
            rows.append([f"`se3sync {' '.join(COMMANDS[name])}`".replace("{tmp}/", "")]
                        + [f"{v * 1e3:.0f}" for v in med.values()]
                        + ([f"{med['this tree'] / med[args.against]:.2f}"] if args.against else []))
        rep.table(["command"] + [f"{k} (ms)" for k in trees]
                  + (["ratio"] if args.against else []), rows,
                  caption=f"median wall time of {args.repeat} fresh processes each, numba's "
                          f"on-disk cache warm")
    return 0


if __name__ == "__main__":
    sys.exit(main())
