"""The floor under an agent's step on this machine: what a process pays per step for its
datagrams and one compiled call alone, flat out and paced at a rate.

    python benchmarks/bench_wake_floor.py [--rates 0,250,100] [--steps N]

Per step: four datagrams (300 bytes) sent to four sockets of its own and read back, one
compiled kernel call (`controller.kernels.rot_to_quat_rows` on one row), four more sends to a
sink and the sink drained: roughly the system calls of agent 2 of hil_6uav (its vehicle's state
and three neighbours' samples in, three samples and a command out) with no Python of the agent
around them. Rate 0 is flat out; any other rate sleeps until each step's deadline, as an agent
does. Reported: the thread's CPU per step (`time.thread_time`) and as a share of a core at that
rate. Compare it with `bench_agent_step.py` (flat out and ``--paced``): the gap is the agent's
own Python; the rise from flat out to paced is what waking up costs here.
"""
from __future__ import annotations

import argparse
import socket
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from controller import kernels  # noqa: E402


def floor(rate: float, steps: int) -> float:
    """µs of thread CPU per step at ``rate`` Hz (0: flat out)."""
    socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(6)]
    try:
        rx, tx, sink = socks[:4], socks[4], socks[5]
        for s in socks:
            s.bind(("127.0.0.1", 0))
            s.setblocking(False)
        addrs = [s.getsockname() for s in rx]
        out = sink.getsockname()
        data = b"x" * 300
        R = np.eye(3).reshape(1, 9).copy()
        q = np.empty((1, 4))
        kernels.rot_to_quat_rows(R, q)
        h = 1.0 / rate if rate else 0.0
        t0 = time.monotonic() + 0.05
        c0 = time.thread_time()
        for k in range(steps):
            if h:
                wait = t0 + k * h - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
            for a in addrs:
                tx.sendto(data, a)
            for s in rx:
                try:
                    s.recvfrom(2048)
                except BlockingIOError:
                    pass
            kernels.rot_to_quat_rows(R, q)
            for _ in range(4):
                tx.sendto(data, out)
            while True:
                try:
                    sink.recvfrom(2048)
                except BlockingIOError:
                    break
        return (time.thread_time() - c0) / steps * 1e6
    finally:
        for s in socks:
            s.close()


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rates", default="0,250,100",
                    help="comma-separated rates in Hz; 0 = flat out (default 0,250,100)")
    ap.add_argument("--steps", type=int, default=1000)
    a = ap.parse_args(argv)
    try:
        rates = [float(x) for x in a.rates.split(",")]
    except ValueError:
        ap.error(f"--rates: must be comma-separated numbers, got {a.rates!r}")
    if any(r < 0 or r > 10000 for r in rates):
        ap.error(f"--rates: each must be 0 (flat out) or a rate in Hz up to 10000, got {a.rates}")
    if a.steps < 1:
        ap.error(f"--steps: must be ≥ 1, got {a.steps}")
    for r in rates:
        us = floor(r, a.steps)
        what = "flat out" if not r else f"paced at {r:g} Hz"
        share = f" = {us * r * 1e-6:.4f} of a core" if r else ""
        print(f"{what}: {us:.1f} µs of thread CPU per step{share}")


if __name__ == "__main__":
    main()
