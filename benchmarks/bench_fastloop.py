"""Benchmark of the compiled block loop (cosim/fastloop.py); not a test.

    python benchmarks/bench_fastloop.py [--seconds 20] [--big 1000] [--big-seconds 1]
                                        [--repeat 3] [--skip-fmpy] [--skip-big] [--startup-only]

All numbers come from one process; compare them as ratios.
  paper    paper scenario, h = 0.1 ms, MCAP log at 100 Hz: compiled loop with and without the
           log, the Python reference loop with the log (best of --repeat each), and
           fmpy.simulate_fmu stepping the same FMU open loop at the same step (output every
           step, no controller);
  records  cost of one log record (/tf, /edges, /agents, /lyapunov) through `record` (the
           reference encoder) and `record_fast` (templates), at N = 6 and N = --big;
  big      --big-agent random tree, h = 1 ms, log at 100 Hz, --big-seconds simulated: compiled
           loop with the JSON log, with the CDR log (--log-encoding cdr) and without a log (the
           logging share of the step time), best of --repeat;
  startup  fresh processes (median of 7, after one that warms the caches): from the parent's
           spawn to the end of the first 100 compiled steps of the paper scenario, numba's
           code loaded from its on-disk cache, and the three phases inside the process.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
import _markdown  # noqa: E402
PAPER = ROOT / "scenarios" / "paper_6uav.toml"
HIL = ROOT / "scenarios" / "hil_6uav.toml"


def random_tree_text(n, seed=1, step=1e-3, duration=1.0):
    """hil_6uav's weighting and gains (designed for h = 4 ms, so the loop is stable at h = 1 ms)
    with n agents on a random tree (random orientations), random initial poses, log at 100 Hz."""
    rng = np.random.default_rng(seed)
    edges = []
    for i in range(1, n):
        e = [int(rng.integers(0, i)) + 1, i + 1]
        edges.append(e if rng.random() < 0.5 else e[::-1])
    text = HIL.read_text()
    text = text[:text.index("[bridge]")]
    text = text.replace("count = 6\n", f"count = {n}\n")
    text = text.replace("edges = [[1, 2], [2, 3], [3, 4], [2, 5], [5, 6]]", f"edges = {edges}")
    text = text.replace('generator = "paper"\naxis = [0.2997, 0.8380, 0.4560]',
                        f'generator = "random"\nseed = {seed}\nposition_box = 1.0')
    text = text.replace("duration = 20.0", f"duration = {duration}")
    text = text.replace("log_rate = 50.0", "log_rate = 100.0")
    return text.replace("step = 0.004", f"step = {step}")


def run(sc, compiled=True, log=None, encoding="json"):
    from cosim.master import Master
    from cosim.log.writer import McapLogger
    from cosim.plants import FmuPlant

    plant = FmuPlant.from_scenario(sc)
    if log:   # a new path, as a run usually writes: replacing the last run's files costs more
        for p in (Path(log), Path(log).with_suffix(".layout.json")):
            p.unlink(missing_ok=True)
    logger = McapLogger(log, sc, encoding=encoding) if log else None
    try:
        m = Master(sc, plant, "hybrid", logger)
        m.use_compiled = compiled
        t0, c0 = time.perf_counter(), time.process_time()
        s = m.run(sc.n_steps())
        if logger is not None:
            logger.close()  # part of the cost: the writer thread has drained by now
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    finally:
        plant.close()
    s["cpu_s"] = cpu  # CPU of all threads: unlike the wall time, not inflated by other load
    return wall, s


def record_cost(sc, n_rec, fast, use_orjson=True, encoding="json"):
    """Seconds per record of McapLogger.record / record_fast (random finite values, no jump);
    use_orjson=False: record_fast with float-repr templates (the bytes of `record`);
    encoding "cdr": the CDR log's record (one record at a time: the loop hands over blocks)."""
    from cosim.log.writer import McapLogger

    N, M = sc.graph.n, sc.graph.M
    rng = np.random.default_rng(0)
    S = rng.standard_normal((n_rec, N, 18))
    u = rng.standard_normal((n_rec, N, 6))
    e = rng.standard_normal((n_rec, 5, M))
    q = rng.standard_normal((n_rec, N, 4))
    no = np.zeros(M, np.bool_)
    with tempfile.TemporaryDirectory() as d:
        lg = McapLogger(os.path.join(d, "r.mcap"), sc, encoding=encoding)
        lg.orjson = use_orjson
        rec = lg.record_fast if fast else lg.record
        t0 = time.perf_counter()
        for r in range(n_rec):
            rec(10_000_000 * r, S[r], u[r], e[r, 0], e[r, 1], no, e[r, 2], e[r, 3], e[r, 4], q[r],
                0.5, 0.25)
        lg.close()
        return (time.perf_counter() - t0) / n_rec


STARTUP = r"""
import sys, time
t0 = time.perf_counter()
sys.path.insert(0, {root!r})
from cosim.scenario import load_scenario
from cosim.master import Master
from cosim.plants import FmuPlant
sc = load_scenario({paper!r}, ["simulation.duration=0.01"])
p = FmuPlant.from_scenario(sc)
t1 = time.perf_counter()
m = Master(sc, p, "hybrid")
t2 = time.perf_counter()
m.run(100)
t3 = time.perf_counter()
wall = time.time()
p.close()
print(t1 - t0, t2 - t1, t3 - t2, repr(wall))
"""


def startup():
    code, rows = STARTUP.format(root=str(ROOT), paper=str(PAPER)), []
    for k in range(8):     # the first run writes any missing .pyc and warms the file cache
        t = time.time()
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                             check=True).stdout.split()
        if k:
            rows.append([float(out[3]) - t] + [float(x) for x in out[:3]])
    med = np.median(np.array(rows), axis=0)
    low = min(r[0] for r in rows)
    print(f"start-up (fresh process, numba cache on disk; median of {len(rows)}): spawn to the "
          f"end of the first 100 compiled steps {med[0]:.3f} s (min {low:.3f}); "
          f"inside: imports + FMU {med[1]:.3f} s, Master() {med[2]:.3f} s, first 100 compiled "
          f"steps (loads run_block) {med[3]:.3f} s")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--big", type=int, default=1000, help="agents of the random tree")
    ap.add_argument("--skip-fmpy", action="store_true")
    ap.add_argument("--skip-big", action="store_true")
    ap.add_argument("--startup-only", action="store_true", help="only the start-up line")
    ap.add_argument("--big-seconds", type=float, default=1.0,
                    help="simulated seconds of the big run (trails fill up after 5 s)")
    ap.add_argument("--repeat", type=int, default=3,
                    help="paper and big runs: best of this many, interleaved")
    _markdown.add_option(ap)
    args = ap.parse_args()
    with _markdown.Report(args.markdown):
        bench(args)


def bench(args):
    if args.startup_only:
        startup()
        return

    from cosim.scenario import load_scenario, parse_scenario
    from plant_fmu.build import fmu_path

    sc = load_scenario(PAPER, [f"simulation.duration={args.seconds}"])
    n = sc.n_steps()
    print(f"paper: {sc.graph.n} agents, h = {sc.step:g} s, {n} steps, log {sc.log_rate:g} Hz")
    run(load_scenario(PAPER, ["simulation.duration=0.05"]))  # warm-up (FMU, numba cache)
    with tempfile.TemporaryDirectory() as d:
        # interleaved, best of --repeat (a 0.3 s run is easily disturbed on a shared machine)
        runs = {"log": [], "nolog": [], "ref": []}
        for _ in range(max(1, args.repeat)):
            runs["log"].append(run(sc, True, os.path.join(d, "a.mcap")))
            runs["nolog"].append(run(sc, True))
            runs["ref"].append(run(sc, False, os.path.join(d, "b.mcap")))
        (w_log, s), (w_nolog, s0), (w_ref, sr) = (min(runs[k], key=lambda x: x[0])
                                                  for k in ("log", "nolog", "ref"))
    us = lambda w: w / n * 1e6  # noqa: E731
    print(f"  compiled + log   {w_log:7.3f} s  {us(w_log):6.2f} µs/step wall, "
          f"{us(s['cpu_s']):6.2f} µs/step CPU ({s['n_jumps']} jumps)")
    print(f"  compiled, no log {w_nolog:7.3f} s  {us(w_nolog):6.2f} µs/step wall, "
          f"{us(s0['cpu_s']):6.2f} µs/step CPU")
    print(f"  Python loop + log{w_ref:7.3f} s  {us(w_ref):6.2f} µs/step wall, "
          f"{us(sr['cpu_s']):6.2f} µs/step CPU")
    print(f"  compiled / Python loop = {w_log / w_ref:.3f}× wall; logging share "
          f"{(w_log - w_nolog) / w_log * 100:.1f} % of the wall time, "
          f"{(s['cpu_s'] - s0['cpu_s']) / s['cpu_s'] * 100:.1f} % of the CPU time")
    if not args.skip_fmpy:
        from fmpy import simulate_fmu

        t0 = time.perf_counter()
        simulate_fmu(str(fmu_path(sc.graph.n)), stop_time=args.seconds, step_size=sc.step,
                     output_interval=sc.step, fmi_type="CoSimulation")
        w_fmpy = time.perf_counter() - t0
        print(f"  fmpy.simulate_fmu open loop {w_fmpy:7.3f} s  {us(w_fmpy):6.2f} µs/step; "
              f"compiled + log / fmpy = {w_log / w_fmpy:.3f}×")

    print("record cost (/tf, /edges, /agents, /lyapunov + /scene and trails when due; MCAP "
          "chunking + zstd included; the logger's set-up is not):")
    sizes = [(sc, 400)]
    big = None
    if not args.skip_big:
        big = parse_scenario(random_tree_text(args.big, duration=args.big_seconds),
                             name=f"tree{args.big}")
        sizes.append((big, 40))
    from cosim.log import writer as mcaplog

    for s_, k in sizes:
        slow, tpl = record_cost(s_, k, False), record_cost(s_, k, True, False)
        line = (f"  N = {s_.graph.n:5d}: record {slow * 1e6:9.1f} µs, record_fast (repr) "
                f"{tpl * 1e6:9.1f} µs ({slow / tpl:.1f}×)")
        if mcaplog._orjson is not None:
            fast = record_cost(s_, k, True, True)
            line += f", record_fast (orjson) {fast * 1e6:9.1f} µs ({slow / fast:.1f}×)"
        record_cost(s_, 2, True, encoding="cdr")   # numba's first call of the fill kernel
        c = record_cost(s_, k, True, encoding="cdr")
        line += f", CDR {c * 1e6:9.1f} µs ({slow / c:.1f}×)"
        print(line)

    if big is not None:
        nb = big.n_steps()
        run(parse_scenario(random_tree_text(args.big, duration=0.005), name="warm"))
        with tempfile.TemporaryDirectory() as d:
            # interleaved, best of --repeat: the no-log time varies by ±30 % from run to run
            # on a shared machine, and the share is a ratio of the two
            logged, plain = {"json": [], "cdr": []}, []
            for _ in range(max(1, args.repeat)):
                for enc in logged:
                    logged[enc].append(run(big, True, os.path.join(d, f"{enc}.mcap"), enc))
                plain.append(run(big, True))
            size = {enc: os.path.getsize(os.path.join(d, f"{enc}.mcap")) for enc in logged}
            wb_nolog, sb0 = min(plain, key=lambda x: x[0])
        print(f"{args.big}-agent random tree, h = {big.step:g} s, {nb} steps, log 100 Hz; no log "
              f"{wb_nolog:7.3f} s ({wb_nolog / nb * 1e6:8.1f} µs/step)")
        for enc, runs in logged.items():
            wb_log, sb = min(runs, key=lambda x: x[0])
            print(f"  compiled + {enc:4s} log {wb_log:7.3f} s ({wb_log / nb * 1e6:8.1f} µs/step, "
                  f"{size[enc] / 1e6:.1f} MB, {sb['n_jumps']} jumps); logging share "
                  f"{(wb_log - wb_nolog) / wb_log * 100:.1f} % of the wall time, "
                  f"{(sb['cpu_s'] - sb0['cpu_s']) / sb['cpu_s'] * 100:.1f} % of the CPU time")

    startup()


if __name__ == "__main__":
    main()
