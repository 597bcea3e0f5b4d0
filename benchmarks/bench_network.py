"""Cost of one step of the law over [network] links (cosim.network.NetworkController) against the
plain network step (HybridController), at N = 6 (the paper's graph), with moving states.

    python benchmarks/bench_network.py [STEPS]

Cases: delay 0 (the delayed code path, bit-identical to the network step), delay 20 ms with
10 ms jitter and 10 % loss at h = 4 ms, and the same at h = 1e-4 s (a 301-step ring). Times are
medians of 5 repeats in one process: compare the ratios, not the absolute numbers.
"""
from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np

import _markdown
from cosim.controllers import make_controller
from cosim.network import networked
from cosim.scenario import parse_scenario

ROOT = Path(__file__).resolve().parents[1]
TEXT = (ROOT / "scenarios" / "hil_6uav.toml").read_text()


def per_step(ctrl, states, h):
    t0 = time.perf_counter()
    step = ctrl.step_state
    for S in states:
        step(S, h)
    return (time.perf_counter() - t0) / len(states)


def main(steps: int = 100_000, rep=None) -> None:
    rows = []
    rng = np.random.default_rng(0)
    base = parse_scenario(TEXT, path="hil.toml")
    S = np.ascontiguousarray(base.S0)
    states = []
    for _ in range(64):  # a few distinct states, reused cyclically
        X = S.copy()
        X[:, :3] += 0.01 * rng.standard_normal((6, 3))
        X[:, 12:] += 0.01 * rng.standard_normal((6, 6))
        states.append(X)
    states = [states[n % 64] for n in range(steps)]
    cases = [("delay 0", "delay = 0.0", 0.004),
             ("20 ms + 10 ms jitter + 10 % loss, h = 4 ms",
              "delay = 0.02\njitter = 0.01\nloss = 0.1\nseed = 1", 0.004),
             ("20 ms + 10 ms jitter + 10 % loss, h = 0.1 ms",
              "delay = 0.02\njitter = 0.01\nloss = 0.1\nseed = 1", 1e-4)]
    for label, net, h in cases:
        sc = parse_scenario(TEXT + "\n[network]\n" + net + "\n", path="net.toml")
        plain = make_controller("hybrid", sc)
        delayed = networked(sc, make_controller("hybrid", sc))
        per_step(plain, states[:1000], h)      # compile / warm up
        per_step(delayed, states[:1000], h)
        tp, td = [], []
        for _ in range(5):
            plain.reset(sc.theta0)
            delayed.reset(sc.theta0)
            tp.append(per_step(plain, states, h))
            td.append(per_step(delayed, states, h))
        p, d = statistics.median(tp), statistics.median(td)
        print(f"{label:45s} plain {p * 1e6:6.2f} µs/step, networked {d * 1e6:6.2f} µs/step, "
              f"ratio {d / p:5.2f}")
        rows.append((f"one law step, {label}", f"{p * 1e6:.2f}", f"{d * 1e6:.2f}", f"{d / p:.2f}"))

    # a whole run (plant FMU + master + log-free summary): the paper's scenario, h = 1e-4 s
    from cosim.run import run_scenario

    paper = (ROOT / "scenarios" / "paper_6uav.toml").read_text()
    plain_sc = parse_scenario(paper, path="paper.toml", duration=2.0)
    net_sc = parse_scenario(paper + "\n[network]\ndelay = 0.0\n", path="p.toml", duration=2.0)
    run_scenario(plain_sc, duration=0.1)  # warm-up: FMU load, compiled metrics
    run_scenario(net_sc, duration=0.1)
    a = run_scenario(plain_sc)
    b = run_scenario(net_sc)
    print(f"paper scenario, 20000 steps: plain {a['us_per_step']:.2f} µs/step, networked "
          f"{b['us_per_step']:.2f} µs/step, ratio {b['us_per_step'] / a['us_per_step']:.2f}; "
          f"summaries identical: {a['final'] == b['final'] and a['samples'] == b['samples']}")
    rows.append(("whole run, paper scenario with `[network] delay = 0`, 20000 steps",
                 f"{a['us_per_step']:.2f}", f"{b['us_per_step']:.2f}",
                 f"{b['us_per_step'] / a['us_per_step']:.2f}"))
    if rep is not None:
        rep.table(["case (N = 6)", "plain (µs/step)", "networked (µs/step)", "ratio"], rows)
        rep.note(f"Law steps: medians of 5 repeats of {steps} steps in one process. The whole "
                 f"runs' summaries are identical: "
                 f"{a['final'] == b['final'] and a['samples'] == b['samples']}.")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("steps", nargs="?", type=int, default=100_000, help="steps per repeat (100000)")
    _markdown.add_option(ap)
    args = ap.parse_args()
    with _markdown.Report(args.markdown) as report:
        main(args.steps, report)
