"""Cost of McapLogger.record at N = 6 with and without the Foxglove /scene and /trail channels.

Run: .venv/bin/python benchmarks/bench_see_log.py [--markdown FILE.md]   (prints µs per record
and the ratio)
"""
import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

import _markdown
from cosim.log.writer import McapLogger
from cosim.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[1]


def per_record(scene_rate, n=4000, log_rate=100.0):
    sc = load_scenario(ROOT / "scenarios" / "paper_6uav.toml")
    rng = np.random.default_rng(0)
    S = rng.standard_normal((6, 18))
    u = rng.standard_normal((6, 6))
    q = rng.standard_normal((6, 4))
    M = 5
    th, mu, rot, pos, U = (rng.standard_normal(M) for _ in range(5))
    jumped = np.zeros(M, bool)
    with tempfile.TemporaryDirectory() as d:
        lg = McapLogger(Path(d) / "b.mcap", sc, scene_rate=scene_rate, layout_path=None)
        dt = round(1e9 / log_rate)
        t0 = time.perf_counter()
        for k in range(n):
            lg.record(k * dt, S, u, th, mu, jumped, rot, pos, U, q, 1.0, 0.5)
        el = time.perf_counter() - t0
        lg.close()
    return el / n * 1e6


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    _markdown.add_option(ap)
    with _markdown.Report(ap.parse_args().markdown):
        base = per_record(0)
        with_scene = per_record(20.0)
        print(f"record() at N=6, log_rate 100 Hz: {base:.1f} µs without /scene+/trail, "
              f"{with_scene:.1f} µs with them at 20 Hz (ratio {with_scene / base:.2f}, "
              f"extra {with_scene - base:.1f} µs per record)")
