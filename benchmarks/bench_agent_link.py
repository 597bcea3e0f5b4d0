"""Cost of the inter-agent link (bridge.swarm.agent_link) per control step, against the control period.

    python benchmarks/bench_agent_link.py [STEPS]

Agent 2 of hil_6uav (three neighbours, two owned edges) publishes STEPS samples over loopback UDP
while agents 1, 3 and 5 poll them; unsigned and signed. Reported: time per publish (encode, pack,
three sendto) and per sample taken by a receiver (drain, decode, checks, wire → row), as fractions
of the 4 ms period, medians of 3 repeats in one run: compare the ratios, not the absolute numbers.
"""
from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import _markdown
from bridge.swarm.agent_link import AgentLink
from bridge.mavlink.link import free_base_port
from cosim.scenario import parse_scenario

ROOT = Path(__file__).resolve().parents[1]
TEXT = (ROOT / "scenarios" / "hil_6uav.toml").read_text()


def once(steps: int, key) -> tuple[float, float]:
    sc = parse_scenario(TEXT + f"\n[network]\nbase_port = {free_base_port(6)}\n", path="b.toml")
    links = {i: AgentLink.from_scenario(sc, i, key=key) for i in (1, 2, 3, 5)}
    try:
        S, th = sc.S0[1], {2: 0.1, 4: 0.2}
        t_pub = t_rx = 0.0
        for n in range(steps):
            t0 = time.perf_counter()
            links[2].publish(n, S, th)
            t1 = time.perf_counter()
            for i in (1, 3, 5):
                if hasattr(links[i], "set_step"):
                    links[i].set_step(n)      # the receivers' own step (stamps ahead are refused)
                links[i].poll()
            t_rx += time.perf_counter() - t1
            t_pub += t1 - t0
        taken = sum(links[i].stats()["links"]["2"]["samples"] for i in (1, 3, 5))
        return t_pub / steps, t_rx / max(taken, 1)
    finally:
        for link in links.values():
            link.close()


def main(steps: int = 5000, rep=None) -> None:
    h = 0.004
    rows = []
    for name, key in (("unsigned", None), ("signed", bytes(range(32)))):
        runs = [once(steps, key) for _ in range(3)]
        pub = statistics.median(r[0] for r in runs)
        rx = statistics.median(r[1] for r in runs)
        print(f"{name:9s} publish to 3 neighbours: {pub / h:.4f} of h   "
              f"one sample received: {rx / h:.4f} of h   (h = 4 ms)")
        rows.append((name, f"{100 * pub / h:.2f} % ({pub * 1e6:.0f} µs)",
                     f"{100 * rx / h:.2f} % ({rx * 1e6:.0f} µs)"))
    if rep is not None:
        rep.table(["packets", "publish to 3 neighbours", "one sample received"], rows,
                  caption=f"share of a 4 ms control period; medians of 3 repeats of {steps} steps")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("steps", nargs="?", type=int, default=5000, help="samples per repeat (5000)")
    _markdown.add_option(ap)
    a = ap.parse_args()
    with _markdown.Report(a.markdown) as report:
        main(a.steps, report)
