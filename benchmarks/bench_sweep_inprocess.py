"""Sweep throughput in one process (`se3sync sweep --workers 0`), optionally against another
revision in the same run (interleaved, so load affects both alike).

    python benchmarks/bench_sweep_inprocess.py [--against REV] [--samples K] [--repeat R]

Reports runs per minute on scenarios/sweep_small.toml (the adversarial samples plus K random ones,
with every law the tree registers, or the hybrid law only with --hybrid-only: the same runs on
both sides when the two revisions register different laws), best of R, start-up excluded (a
1-sample sweep is timed and subtracted). Runs are counted in the output file.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from _revisions import trees as revision_trees  # noqa: E402
import _markdown  # noqa: E402


def sweep(tree: Path, samples: int, out: Path, hybrid_only: bool = False) -> tuple:
    """(seconds, runs) of one sweep; runs counted in the CSV it wrote."""
    out.unlink(missing_ok=True)
    t = time.perf_counter()
    subprocess.run([sys.executable, "-m", "cosim.cli", "sweep", "scenarios/sweep_small.toml",
                    "--samples", str(samples), "--workers", "0", "--out", str(out)]
                   + (["--no-baseline"] if hybrid_only else []), cwd=tree,
                   check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wall = time.perf_counter() - t
    with open(out) as f:
        return wall, sum(1 for _ in f) - 1


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--against", metavar="REV")
    ap.add_argument("--samples", type=int, default=300)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--hybrid-only", action="store_true", help="sweep the hybrid law only")
    _markdown.add_option(ap)
    args = ap.parse_args()
    with _markdown.Report(args.markdown):
        return bench(args)


def bench(args) -> int:
    ho = args.hybrid_only
    with tempfile.TemporaryDirectory() as tmp, revision_trees(args.against) as trees:
        best, runs = {}, {}
        for tree in trees.values():   # a fresh worktree compiles its numba cache: not timed
            sweep(tree, 1, Path(tmp) / "w.csv", ho)
        for _ in range(args.repeat):
            for k, tree in trees.items():
                base, n0 = sweep(tree, 1, Path(tmp) / "b.csv", ho)
                full, n1 = sweep(tree, args.samples, Path(tmp) / "f.csv", ho)
                runs[k] = n1
                rate = (n1 - n0) / max(full - base, 1e-9) * 60
                best[k] = max(best.get(k, 0.0), rate)
        line = ", ".join(f"{k} {v:,.0f} runs/min ({runs[k]} runs)" for k, v in best.items())
        if args.against:
            line += f"; ratio {best['this tree'] / best[args.against]:.2f}"
        print(f"sweep_small in one process{' (hybrid only)' if ho else ''}: {line}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
