"""The floor under an agent's step on this machine: what a process pays per step for its
datagrams and one compiled call alone, flat out and paced at a rate.

    python benchmarks/bench_wake_floor.py [--rates 0,250,100] [--steps N] [--hosted SCENARIO]

Per step: four datagrams (300 bytes) sent to four sockets of its own and read back, one
compiled kernel call (`controller.kernels.rot_to_quat_rows` on one row), four more sends to a
sink and the sink drained: roughly the system calls of agent 2 of hil_6uav (its vehicle's state
and three neighbours' samples in, three samples and a command out) with no Python of the agent
around them. Rate 0 is flat out; any other rate sleeps until each step's deadline, as an agent
does. Reported: the thread's CPU per step (`time.thread_time`) and as a share of a core at that
rate. Compare it with `bench_agent_step.py` (flat out and ``--paced``): the gap is the agent's
own Python; the rise from flat out to paced is what waking up costs here.

``--hosted SCENARIO`` measures instead the floor of a process hosting that scenario's agents (as
`swarm` hosts them by default): one thread wakes once per period and, for each agent in turn,
does what its datagrams cost it and nothing else — a select on its two sockets, its vehicle's
state (245 bytes, an ODOMETRY frame) and each neighbour's sample (509 bytes: ODOMETRY and θ)
read, its sample sent to each neighbour (the graph's), a command (55 bytes) sent to its vehicle.
The vehicles' states come from a child process, as the loopback vehicle's do; the samples from
the process's own sends, as hosted agents' do. Reported per agent and step: the agent's share of
a period's thread CPU, and as a share of a core. `bench_agents.py` divides an agent's figure by
it: what the agent costs beyond its packets.
"""
from __future__ import annotations

import argparse
import multiprocessing
import os
import select
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


STATE_BYTES, SAMPLE_BYTES, COMMAND_BYTES = 245, 509, 55   # hil_6uav's frames, unsigned


def _vehicles(ports, outside, w: int, t0: float, h: float, steps: int, parent: int) -> None:
    """The child, the other processes: each period just before the step, a state to each
    agent's vehicle socket (``ports``) and a sample to ``outside`` (the link port of a hosted
    agent, once per neighbour hosted elsewhere); it takes what the agents send there (its own
    port first, on the pipe ``w``)."""
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.setblocking(False)
    os.write(w, s.getsockname()[1].to_bytes(2, "little"))
    state, sample = b"s" * STATE_BYTES, b"n" * SAMPLE_BYTES
    for k in range(steps + 1):
        if os.getppid() != parent:
            return                      # never outlives the benchmark
        wait = t0 + k * h - 5e-4 - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        for p in ports:
            s.sendto(state, ("127.0.0.1", p))
        for p in outside:
            s.sendto(sample, ("127.0.0.1", p))
        while True:                     # the commands
            try:
                s.recv(2048)
            except BlockingIOError:
                break


def hosted_floor(rate: float, steps: int, neighbours: dict, hosted=None) -> float:
    """µs of thread CPU per agent and step of a process hosting the agents ``hosted`` (default:
    every agent of ``neighbours``, {agent: [its neighbours]}) at ``rate`` Hz (see the module
    docstring); a neighbour hosted elsewhere is the child's socket."""
    ids = sorted(neighbours if hosted is None else hosted)
    veh = {i: socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for i in ids}
    link = {i: socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for i in ids}
    socks = [*veh.values(), *link.values()]
    child = None
    try:
        for s in socks:
            s.bind(("127.0.0.1", 0))
            s.setblocking(False)
        h = 1.0 / rate
        t0 = time.monotonic() + 0.3
        r, w = os.pipe()
        ctx = multiprocessing.get_context("fork")
        child = ctx.Process(target=_vehicles, daemon=True,
                            args=([veh[i].getsockname()[1] for i in ids],
                                  [link[i].getsockname()[1] for i in ids
                                   for j in neighbours[i] if j not in link],
                                  w, t0, h, steps, os.getpid()))
        child.start()
        os.close(w)
        vport = int.from_bytes(os.read(r, 2), "little")
        os.close(r)
        for s in veh.values():
            s.connect(("127.0.0.1", vport))
        to = {i: [link[j].getsockname() if j in link else ("127.0.0.1", vport)
                  for j in neighbours[i]] for i in ids}
        sample, command = b"n" * SAMPLE_BYTES, b"c" * COMMAND_BYTES
        plan = [(veh[i], link[i], [veh[i].fileno(), link[i].fileno()], to[i]) for i in ids]
        c0 = None
        for k in range(steps):
            wait = t0 + k * h - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            if k == steps // 5:          # the first fifth settles the caches and the child
                c0, k0 = time.thread_time(), k
            for v, ln, fds, dst in plan:
                select.select(fds, [], [], 0.0)
                for s in (v, ln):
                    while True:
                        try:
                            s.recv(2048)
                        except BlockingIOError:
                            break
                for a in dst:
                    ln.sendto(sample, a)
                v.send(command)
        return (time.thread_time() - c0) / ((steps - k0) * len(ids)) * 1e6
    finally:
        if child is not None:
            child.terminate()
            child.join()
        for s in socks:
            s.close()


def graph_of(path) -> dict:
    """{agent: [its neighbours]} of a scenario file."""
    from cosim.scenario import load_scenario
    g = load_scenario(Path(path)).graph
    return {i: sorted(int(j) for j in g.neighbours(i)) for i in range(1, g.n + 1)}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rates", default=None,
                    help="comma-separated rates in Hz; 0 = flat out (default 0,250,100; with "
                         "--hosted, rates above 0 only, default 250,100)")
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--hosted", metavar="SCENARIO",
                    help="the floor per agent of a process hosting the scenario's agents "
                         "(the module's docstring), e.g. scenarios/hil_6uav.toml")
    a = ap.parse_args(argv)
    if a.rates is None:
        a.rates = "0,250,100" if a.hosted is None else "250,100"
    try:
        rates = [float(x) for x in a.rates.split(",")]
    except ValueError:
        ap.error(f"--rates: must be comma-separated numbers, got {a.rates!r}")
    if any(r < 0 or r > 10000 for r in rates):
        ap.error(f"--rates: each must be 0 (flat out) or a rate in Hz up to 10000, got {a.rates}")
    if a.steps < 1:
        ap.error(f"--steps: must be ≥ 1, got {a.steps}")
    nbrs = None
    if a.hosted is not None:
        if any(r == 0 for r in rates):
            ap.error(f"--rates: with --hosted each must be a rate above 0, got {a.rates}")
        if a.steps < 5:
            ap.error(f"--steps: with --hosted must be ≥ 5, got {a.steps}")
        try:
            nbrs = graph_of(a.hosted)
        except Exception as exc:  # noqa: BLE001 - one line naming the option
            ap.error(f"--hosted: {a.hosted}: {exc}")
    for r in rates:
        if nbrs is not None:
            us = hosted_floor(r, a.steps, nbrs)
            print(f"{len(nbrs)} agents hosted, paced at {r:g} Hz: {us:.1f} µs of thread CPU per "
                  f"agent and step = {us * r * 1e-6:.4f} of a core per agent")
            continue
        us = floor(r, a.steps)
        what = "flat out" if not r else f"paced at {r:g} Hz"
        share = f" = {us * r * 1e-6:.4f} of a core" if r else ""
        print(f"{what}: {us:.1f} µs of thread CPU per step{share}")

if __name__ == "__main__":
    main()
