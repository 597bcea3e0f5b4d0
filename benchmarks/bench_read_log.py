"""Reading a large log back: `read_log` on the JSON and the CDR log of one run; not a test.

    python benchmarks/bench_read_log.py [--agents 1000] [--seconds 1] [--repeat 3] [--reference]

Writes both logs of an N-agent random tree (bench_fastloop's `random_tree_text`, h = 1 ms, log
at 100 Hz) with `se3sync run`, then times `read_log` on each, whole and with the topics `plot`
reads (best of --repeat, interleaved). --reference also times mcap-ros2-support's decoder
(`cdr.decode_reference`) on the CDR log, once.
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
from bench_fastloop import random_tree_text  # noqa: E402
import _markdown  # noqa: E402

PLOT_TOPICS = {"/tf", "/edges", "/agents", "/lyapunov", "/jumps"}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--agents", type=int, default=1000)
    ap.add_argument("--seconds", type=float, default=1.0)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--reference", action="store_true")
    _markdown.add_option(ap)
    args = ap.parse_args()
    with _markdown.Report(args.markdown):
        return bench(args)


def bench(args) -> int:
    from cosim.log import cdr
    from cosim.log import reader as mcaplog

    with tempfile.TemporaryDirectory() as d:
        toml = Path(d) / "tree.toml"
        toml.write_text(random_tree_text(args.agents, duration=args.seconds))
        logs = {}
        for enc in ("json", "cdr"):
            logs[enc] = Path(d) / f"{enc}.mcap"
            subprocess.run([sys.executable, "-m", "cosim.cli", "run", str(toml), "--log",
                            str(logs[enc]), "--log-encoding", enc, "--force"],
                           check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        best = {}
        for _ in range(args.repeat):
            for enc, path in logs.items():
                for what, topics in (("whole", None), ("plot topics", PLOT_TOPICS)):
                    t = time.perf_counter()
                    mcaplog.read_log(path, topics=topics)
                    el = time.perf_counter() - t
                    best[enc, what] = min(best.get((enc, what), el), el)
        for what in ("whole", "plot topics"):
            print(f"read_log, {args.agents} agents, {args.seconds:g} s, {what:11s}: JSON "
                  f"{best['json', what]:.2f} s ({logs['json'].stat().st_size / 1e6:.0f} MB), "
                  f"CDR {best['cdr', what]:.2f} s ({logs['cdr'].stat().st_size / 1e6:.0f} MB); "
                  f"CDR/JSON {best['cdr', what] / best['json', what]:.2f}")
        if args.reference:
            decode = cdr.decode
            cdr.decode = cdr.decode_reference
            try:
                t = time.perf_counter()
                mcaplog.read_log(logs["cdr"])
                el = time.perf_counter() - t
            finally:
                cdr.decode = decode
            print(f"  with mcap-ros2-support's decoder: CDR whole {el:.2f} s "
                  f"({el / best['cdr', 'whole']:.1f}× the generated decoders)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
