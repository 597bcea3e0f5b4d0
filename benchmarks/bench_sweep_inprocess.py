"""Sweep throughput in one process (`se3sync sweep --workers 0`), optionally against another
revision in the same run (interleaved, so load affects both alike).

    python benchmarks/bench_sweep_inprocess.py [--against REV] [--samples K] [--repeat R]

Reports runs per minute on scenarios/sweep_small.toml (the adversarial samples plus K random ones,
hybrid and gradient), best of R, start-up excluded (a 1-sample sweep is timed and subtracted).
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


def sweep(tree: Path, samples: int, out: Path) -> float:
    out.unlink(missing_ok=True)
    t = time.perf_counter()
    subprocess.run([sys.executable, "-m", "cosim.cli", "sweep", "scenarios/sweep_small.toml",
                    "--samples", str(samples), "--workers", "0", "--out", str(out)], cwd=tree,
                   check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--against", metavar="REV")
    ap.add_argument("--samples", type=int, default=300)
    ap.add_argument("--repeat", type=int, default=2)
    _markdown.add_option(ap)
    args = ap.parse_args()
    with _markdown.Report(args.markdown):
        return bench(args)


def bench(args) -> int:
    runs = 2 * (12 + args.samples)  # sweep_small: 3M + 3 = 12 adversarial samples, 2 laws
    with tempfile.TemporaryDirectory() as tmp, revision_trees(args.against) as trees:
        best = {}
        for tree in trees.values():   # a fresh worktree compiles its numba cache: not timed
            sweep(tree, 1, Path(tmp) / "w.csv")
        for _ in range(args.repeat):
            for k, tree in trees.items():
                base = sweep(tree, 1, Path(tmp) / "b.csv")
                full = sweep(tree, args.samples, Path(tmp) / "f.csv")
                rate = (runs - 26) / max(full - base, 1e-9) * 60
                best[k] = max(best.get(k, 0.0), rate)
        line = ", ".join(f"{k} {v:,.0f} runs/min" for k, v in best.items())
        if args.against:
            line += f"; ratio {best['this tree'] / best[args.against]:.2f}"
        print(f"sweep_small in one process, {runs} runs: {line}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
