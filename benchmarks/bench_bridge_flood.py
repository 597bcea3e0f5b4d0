"""Fail-safe delay of a loopback vehicle under a datagram flood (issue 13, item 18).

One vehicle process (250 Hz, control period h = 4 ms, command timeout 2 h) gets commands at
~250 Hz for 0.25 s, then none for 0.15 s, six times, while this process floods its socket with
half well-formed HEARTBEATs from a stranger and half truncated frames. Reports the offered flood
rate and the fail-safe delays (time from the last command to the fail-safe) in control periods.

    .venv/bin/python benchmarks/bench_bridge_flood.py               # this tree
    .venv/bin/python benchmarks/bench_bridge_flood.py --root DIR    # the vehicle from another tree
"""
from __future__ import annotations

import argparse
import json
import os
import random
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("MAVLINK20", "1")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bridge.mavlink.link import Counters, Peer, free_base_port  # noqa: E402
sys.path.insert(0, str(ROOT / "benchmarks"))
import _markdown  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--root", default=str(ROOT), help="source tree the vehicle runs from")
    ap.add_argument("--cycles", type=int, default=6)
    _markdown.add_option(ap)
    a = ap.parse_args()
    with _markdown.Report(a.markdown):
        return bench(a)


def bench(a) -> int:
    h = 0.004
    port = free_base_port(1)
    stats = Path(tempfile.mkdtemp()) / "stats.json"
    proc = subprocess.Popen([sys.executable, "-m", "cosim.cli", "vehicle", "--count", "1", "--base-port", str(port),
                             "--rate", "250", "--step", str(h), "--aux-rate", "0", "--stats", str(stats)],
                            cwd=a.root, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", port))
    s.settimeout(30)
    _, addr = s.recvfrom(65535)
    s.setblocking(False)
    rng = random.Random(3)
    stranger = Peer(77, 1, Counters())
    hb = stranger.pack(stranger.mav.heartbeat_encode(0, 0, 0, 0, 4))
    junk = [bytes([0xFD]) + rng.randbytes(rng.randrange(1, 40)) for _ in range(64)]
    flood = [hb if i % 2 else junk[i // 2 % 64] for i in range(128)]
    gcs = Peer(255, 191, Counters())

    def drain():
        while True:
            try:
                s.recvfrom(65535)
            except OSError:
                return

    sent = 0
    t0 = time.monotonic()
    for _ in range(a.cycles):
        t_end = time.monotonic() + 0.25
        while time.monotonic() < t_end:
            s.sendto(gcs.pack(gcs.mav.set_actuator_control_target_encode(
                int(time.time() * 1e6), 0, 1, 1, [0.1] * 6 + [0, 0])), addr)
            t_next = time.monotonic() + h
            while time.monotonic() < t_next:
                for d in flood:
                    s.sendto(d, addr)
                sent += len(flood)
            drain()
        t_end = time.monotonic() + 0.15
        while time.monotonic() < t_end:
            for d in flood:
                s.sendto(d, addr)
            sent += len(flood)
            drain()
    rate = sent / (time.monotonic() - t0)
    proc.terminate()
    proc.wait(10)
    st = json.loads(stats.read_text())
    d = np.sort(np.array(st["failsafe_delays"]) / h)
    print(f"root {a.root}: flood {rate:.0f} datagrams/s offered, {st['datagrams']} read; "
          f"{len(d)} fail-safes, delay in periods p50 {np.percentile(d, 50):.2f}, p90 {np.percentile(d, 90):.2f}, "
          f"max {d.max():.2f}; drain_max {st.get('drain_max', 'n/a')}, drain_capped {st.get('drain_capped', 'n/a')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
