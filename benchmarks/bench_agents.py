"""The per-vehicle agent processes (`se3sync swarm`) in real time: CPU per agent process, the age
of the neighbour data used, losses, and the loop's outcome.

    python benchmarks/bench_agents.py [--duration S] [--cases 6x250,32x100]

Cases: NxRATE = N agents (hil_6uav's gains; for N ≠ 6 a chain 1-2-…-N with the same bodies and
the "paper" start) at RATE Hz, each with its own loopback vehicle (one `se3sync vehicle` process
serves them all), no logs. Per case one swarm run; reported: the CPU of each agent process while
it stepped (share of one core, median and max over the agents), its late steps, the inter-agent
data age p50/p99 (steps) and the losses over every directed link, the final errors, each agent
process's peak resident memory and its start-up (seconds from its start to its compiled kernels
loaded, ``warm_s``; the vehicle's first state comes after that, once the vehicle process is up).
Numbers from one machine at one time: compare them with each other, not across machines; with
other work on the machine the CPU figures include what sharing the cores costs (caches).
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
from pathlib import Path

import _markdown

ROOT = Path(__file__).resolve().parents[1]
HIL = ROOT / "scenarios" / "hil_6uav.toml"


def scenario_for(n: int, rate: float, tmp: Path) -> tuple[Path, list]:
    from bridge.mavlink.link import free_base_port

    sets = [f"simulation.step={1.0 / rate!r}", f"bridge.base_port={free_base_port(n)}"]
    nb = free_base_port(n)
    sets.append(f"network.base_port={nb}")
    if n == 6:
        return HIL, sets
    chain = ", ".join(f"[{i}, {i + 1}]" for i in range(1, n))
    return HIL, sets + [f"agents.count={n}", f"graph.edges=[{chain}]"]


def run_case(n: int, rate: float, duration: float) -> dict:
    from bridge.swarm.launcher import run_swarm

    with tempfile.TemporaryDirectory() as d:
        path, sets = scenario_for(n, rate, Path(d))
        merged, rc = run_swarm(path, sets, vehicles="loopback", duration=duration,
                               workdir=Path(d) / "work", on_event=lambda s: None)
    cpu = [a["cpu_fraction"] for a in merged["agents"] if a.get("cpu_fraction") is not None]
    late = [a["late_steps"] for a in merged["agents"] if a.get("late_steps") is not None]
    links = merged["links"]
    p50 = [ln["age_p50_steps"] for ln in links if ln["age_p50_steps"] is not None]
    p99 = [ln["age_p99_steps"] for ln in links if ln["age_p99_steps"] is not None]
    rss = [a["max_rss_mb"] for a in merged["agents"] if a.get("max_rss_mb") is not None]
    warm = [a["startup"]["warm_s"] for a in merged["agents"]
            if (a.get("startup") or {}).get("warm_s") is not None]
    return {"agents": n, "rate_hz": rate, "exit": rc, "steps": merged["steps"],
            "cpu_median": statistics.median(cpu) if cpu else None, "cpu_max": max(cpu, default=None),
            "late_steps_median": statistics.median(late) if late else None,
            "age_p50_steps_max": max(p50, default=None), "age_p99_steps_median":
                statistics.median(p99) if p99 else None, "age_p99_steps_max": max(p99, default=None),
            "rss_mb_median": statistics.median(rss) if rss else None, "rss_mb_max": max(rss, default=None),
            "warm_s_median": statistics.median(warm) if warm else None,
            "warm_s_max": max(warm, default=None),
            "sent": merged["link_total"]["sent"], "lost": merged["link_total"]["lost"],
            "final": merged["final"], "missing": merged["agents_missing"]}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--cases", default="6x250,32x100")
    _markdown.add_option(ap)
    a = ap.parse_args(argv)
    with _markdown.Report(a.markdown) as rep:
        rows = bench(a)
        rep.table(["case", "CPU per agent process (share of a core)", "late steps (median)",
                   "data age p50 / p99 (steps)", "lost", "peak RSS per agent (MB)",
                   "start-up to kernels loaded (s)", "final rot_err", "exit"], rows,
                  caption=f"one swarm run per case, {a.duration:g} s, loopback vehicles, no logs")


def _g(x) -> str:
    return "n/a" if x is None else f"{x:.3g}"


def bench(a) -> list:
    rows = []
    for case in a.cases.split(","):
        n, rate = case.split("x")
        r = run_case(int(n), float(rate), a.duration)
        f = r["final"] or {}
        print(f"{r['agents']:3d} agents at {r['rate_hz']:g} Hz, {r['steps']} steps: CPU per agent "
              f"median {r['cpu_median']:.3f} / max {r['cpu_max']:.3f} of a core; late steps median "
              f"{r['late_steps_median']}; data age p50 ≤ {r['age_p50_steps_max']}, p99 median "
              f"{r['age_p99_steps_median']} / max {r['age_p99_steps_max']} steps; lost {r['lost']} "
              f"of {r['sent']}; peak RSS median {_g(r['rss_mb_median'])} / max "
              f"{_g(r['rss_mb_max'])} MB; start-up (kernels loaded) median "
              f"{_g(r['warm_s_median'])} / max {_g(r['warm_s_max'])} s; final rot_err "
              f"{f.get('rot_err', float('nan')):.3g} (exit {r['exit']})")
        print(json.dumps(r), file=sys.stderr)
        rows.append((f"{r['agents']} agents at {r['rate_hz']:g} Hz, {r['steps']} steps",
                     f"median {r['cpu_median']:.3f}, max {r['cpu_max']:.3f}",
                     f"{r['late_steps_median']} of {r['steps']}",
                     f"≤ {r['age_p50_steps_max']} / median {r['age_p99_steps_median']}, "
                     f"max {r['age_p99_steps_max']}",
                     f"{r['lost']} of {r['sent']}",
                     f"median {_g(r['rss_mb_median'])}, max {_g(r['rss_mb_max'])}",
                     f"median {_g(r['warm_s_median'])}, max {_g(r['warm_s_max'])}",
                     f"{f.get('rot_err', float('nan')):.3g}",
                     r["exit"]))
    return rows


if __name__ == "__main__":
    main()
