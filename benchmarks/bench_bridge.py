"""Benchmark of the MAVLink bridge on loopback: N vehicles × R Hz in real time.

    /work/venv/bin/python benchmarks/bench_bridge.py                 # 6 × 250 Hz and 64 × 100 Hz, 10 s each
    /work/venv/bin/python benchmarks/bench_bridge.py --case 6x250 --duration 20 --json out.json

For each case: one `se3sync vehicle` process serving N vehicles (ODOMETRY at R Hz, physics tick
1/R), and the bridge in this process (MavlinkPlant driven by cosim's Master at h = 1/R, the
hybrid controller included). Reported: CPU of each side as a fraction of one core (user + system
time over the run's wall time; the bridge from getrusage, the vehicle from /proc/<pid>/stat),
command → state latency p50/p99 (command sent → next valid state of that vehicle received),
state age p50/p99 (age of the oldest state used at a control step), packets dropped (sequence
gaps, both directions), late control steps, the vehicle process's late ticks (a physics tick more
than one tick after it was due) and resyncs (it fell 10 ticks behind and skipped them), vehicle
fail-safes, and rejected/malformed packets.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time

from bridge.mavlink.link import free_base_port
from pathlib import Path

import _markdown

os.environ.setdefault("MAVLINK20", "1")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SCENARIO = """
[agents]
count = {n}
mass = 2.4
inertia = [0.043, 0.041, 0.082]
[graph]
edges = {edges}
[weighting]
A = [[4.5518, 0.6768, 1.0328], [0.6768, 7.4998, 0.7520], [1.0328, 0.7520, 6.1484]]
b = [0.6466, 0.5116, 0.5658]
d = 5.0
[synergy]
Theta_over_pi = [0.3]
[gains]
k_X = 10.0
k_xi = 3.0
k_e = 0.3
[initial]
generator = "random"
seed = 1
position_box = 1.0
[simulation]
duration = {duration}
step = {step}
log_rate = 10.0
[bridge]
base_port = {port}
max_wrench = [50.0, 50.0, 50.0, 20.0, 20.0, 20.0]
"""


def proc_cpu(pid) -> float:
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    tck = os.sysconf("SC_CLK_TCK")
    return (int(fields[11]) + int(fields[12])) / tck  # utime + stime


def run_case(n, rate, duration, tmp):
    from bridge.mavlink.hil import run_hil
    from bridge.mavlink.plant import MavlinkPlant
    from cosim.scenario import load_scenario

    port = free_base_port(n)
    edges = [[i, i + 1] for i in range(1, n)]
    path = Path(tmp) / f"bench_{n}x{rate:g}.toml"
    path.write_text(SCENARIO.format(n=n, edges=edges, duration=duration, step=1.0 / rate, port=port))
    sc = load_scenario(path)
    stats_path = Path(tmp) / f"vehicle_{n}.json"
    veh = subprocess.Popen([sys.executable, "-m", "cosim.cli", "vehicle", "--scenario", str(path),
                            "--rate", str(rate), "--aux-rate", "0", "--stats", str(stats_path)],
                           stderr=subprocess.DEVNULL, stdout=subprocess.DEVNULL, cwd=str(ROOT))
    events = []
    # warm up the JIT-compiled controller and metrics outside the measurement
    from cosim.master import Master, make_controller
    from cosim.plants import FmuPlant

    ctrl = make_controller("hybrid", sc)
    warm = FmuPlant.from_scenario(sc)
    Master(sc, warm, ctrl).run(2)
    warm.close()
    ctrl.reset(sc.theta0)
    try:
        plant = MavlinkPlant(sc, connect_timeout=30, on_event=events.append).connect()
        try:
            r0 = resource.getrusage(resource.RUSAGE_SELF)
            v0 = proc_cpu(veh.pid)
            w0 = time.monotonic()
            summary = run_hil(sc, plant, controller=ctrl)
            w1 = time.monotonic()
            r1 = resource.getrusage(resource.RUSAGE_SELF)
            v1 = proc_cpu(veh.pid)
        finally:
            plant.close()
    finally:
        veh.terminate()
        veh.wait(10)
    vst = json.loads(stats_path.read_text()) if stats_path.exists() else {}
    wall = w1 - w0
    ln = summary["link"]
    return {
        "case": f"{n}x{rate:g}Hz", "duration_s": round(wall, 3), "steps": summary["steps"],
        "bridge_cpu_pct_of_core": round(100 * ((r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)) / wall, 1),
        "vehicle_cpu_pct_of_core": round(100 * (v1 - v0) / wall, 1),
        "latency_ms_p50": ln["latency_ms_p50"], "latency_ms_p99": ln["latency_ms_p99"],
        "state_age_ms_p50": ln["state_age_ms_p50"], "state_age_ms_p99": ln["state_age_ms_p99"],
        "dropped_vehicle_to_bridge": ln["dropped"], "dropped_bridge_to_vehicle": vst.get("dropped"),
        "bridge_sent": ln["sent"], "bridge_received": ln["received"],
        "rejected": ln["rejected"], "rejected_by_reason": ln["rejected_by_reason"], "malformed": ln["malformed"], "late_steps": ln["late_steps"],
        "vehicle_failsafes_during_run": max(0, ln["vehicle_failsafes"]),
        "vehicle_commands": vst.get("commands"),
        # the vehicle process's own deadlines: physics ticks more than one tick late, of its
        # ticks (from the first command), and times it fell 10 ticks behind and skipped them
        "vehicle_late_ticks": vst.get("late_ticks"), "vehicle_ticks": vst.get("ticks"),
        "vehicle_resyncs": vst.get("resyncs"),
    }


def _ms(x) -> str:
    return "n/a" if x is None else f"{x:.2f}"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--case", action="append", help="NxHZ, e.g. 6x250 (repeatable; default 6x250 and 64x100)")
    ap.add_argument("--duration", type=float, default=10.0, help="seconds per case (default 10)")
    ap.add_argument("--json", help="write the results here")
    _markdown.add_option(ap)
    a = ap.parse_args(argv)
    cases = a.case or ["6x250", "64x100"]
    out = []
    with _markdown.Report(a.markdown) as rep, tempfile.TemporaryDirectory() as tmp:
        for c in cases:
            n, r = c.lower().split("x")
            res = run_case(int(n), float(r), a.duration, tmp)
            out.append(res)
            print(json.dumps(res), flush=True)
        rep.table(["case", "bridge CPU", "vehicle CPU", "latency p50 / p99", "state age p50 / p99",
                   "dropped (vehicle → bridge, bridge → vehicle)", "late steps",
                   "vehicle: late ticks of ticks, resyncs", "vehicle fail-safes"],
                  [(r["case"], f"{r['bridge_cpu_pct_of_core']} % of a core",
                    f"{r['vehicle_cpu_pct_of_core']} %",
                    f"{_ms(r['latency_ms_p50'])} / {_ms(r['latency_ms_p99'])} ms",
                    f"{_ms(r['state_age_ms_p50'])} / {_ms(r['state_age_ms_p99'])} ms",
                    f"{r['dropped_vehicle_to_bridge']}, {r['dropped_bridge_to_vehicle']}",
                    r["late_steps"],
                    f"{r['vehicle_late_ticks']} of {r['vehicle_ticks']}, {r['vehicle_resyncs']}",
                    r["vehicle_failsafes_during_run"]) for r in out],
                  caption=f"{a.duration:g} s of real time per case")
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
