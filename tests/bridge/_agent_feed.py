"""A deterministic feed for one agent process (`bridge.swarm.agent.AgentNode`), for tests that
run the same agent two ways (e.g. ``compiled=True`` / ``False``) and compare what it did.

Derived from `benchmarks/bench_agent_step.py`'s ``once``: agent i of a scenario (hil_6uav by
default) in real-time mode with its timeline in the past (no step waits), or in lockstep, driven
by `cosim.master.Master`; its vehicle and its neighbours are sockets of this process. Before each
step n the vehicle sends its ODOMETRY (real time: stamped with the clock, strictly increasing;
lockstep: n·h) and each neighbour j its sample of step n (`encode_sample`), unless
``withhold(n, j)`` says to leave it out (holds, fail-safes, rejoins). Every datagram the node
sends to the vehicle and to each neighbour is captured, as are the controller's outputs of every
step, the master's summary (wall-clock and link-timing fields dropped) and the node's age-rule
counters.

The inputs move (`trajectory`): each agent's pose turns and drifts from its S0 row at its own
rates, ξ varies, the neighbours' θ change, so the relative poses sweep through the jump sets.
The feed checks that every datagram it sent was taken as sent (`FeedDisturbed` otherwise: a
machine stalled long enough for the vehicle's state to be refused as stale); a caller compares
two runs only when both were undisturbed.
"""
from __future__ import annotations

import math
import socket
import time
from pathlib import Path

import numpy as np

from bridge.mavlink.link import Counters, Peer, free_base_port
from bridge.mavlink.link import mavlink2 as M
from bridge.swarm.agent import AgentNode, _warm_up
from bridge.swarm.agent_link import encode_sample
from controller import layout
from controller.se3 import R_a, rot_to_quat
from cosim.master import Master
from cosim.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[2]
HIL = ROOT / "scenarios" / "hil_6uav.toml"
# the age rule in 2-step units at h = 4 ms: fresh up to 2 steps old, hold 2 more, then fail-safe
AGE_RULE = ("network.max_age=0.008", "network.hold=0.008")
WALL_FIELDS = ("wall_time_s", "realtime_factor", "us_per_step", "link")


class FeedDisturbed(RuntimeError):
    """The node did not take the feed as sent (a stall made a state stale): not comparable."""


def default_withhold(neighbours):
    """Neighbour q (0-based) loses its samples in four windows, offset by 37 q steps: 3 steps
    (a hold), 7 steps (hold, then fail-safe), 1 step (still fresh) and 10 steps (fail-safe
    again); it rejoins after each."""
    windows = {j: [(s + 37 * q, e + 37 * q) for s, e in ((30, 32), (70, 76), (120, 120),
                                                          (180, 189))]
               for q, j in enumerate(neighbours)}

    def withhold(n, j):
        return any(s <= n <= e for s, e in windows[j])
    return withhold


def trajectory(S0_row, agent: int, n: int, h: float) -> np.ndarray:
    """Agent ``agent``'s state row at step n: its S0 pose turned about an axis of its own at a
    rate of its own, its position drifting, ξ varying (deterministic, smooth)."""
    a = float(agent)
    t = n * h
    axis = np.array([math.sin(1.3 * a), math.cos(0.7 * a), 0.5 + 0.1 * a])
    axis /= np.linalg.norm(axis)
    rate = 8.0 * (-1) ** agent + a
    R0 = np.asarray(S0_row[layout.R], float).reshape(3, 3)
    R = R0 @ R_a(rate * t, axis)
    row = np.array(S0_row, float)
    row[layout.P] = row[layout.P] + 0.3 * np.array([math.sin(0.9 * t + a), math.cos(1.1 * t),
                                                    math.sin(0.5 * a * t)])
    row[layout.R] = R.ravel()
    row[layout.OMEGA] = rate * axis + 0.1 * np.array([math.sin(3 * t), math.cos(2 * t + a), 0.0])
    row[layout.V] = 0.2 * np.array([math.cos(t + a), math.sin(1.7 * t), math.cos(0.3 * a * t)])
    return row


def neighbour_theta(k: int, n: int, theta0: float) -> float:
    """θ_k as its owner publishes it at step n."""
    return theta0 + 0.8 * math.sin(0.05 * n + k)


def _drain(sock, out: list, n: int) -> None:
    while True:
        try:
            out.append((n, sock.recv(65536)))
        except BlockingIOError:
            return


def frames(datagram: bytes) -> list:
    """The MAVLink 2 frames of a datagram as (msgid, sequence, payload) (unsigned)."""
    out = []
    i = 0
    while i < len(datagram):
        if datagram[i] != 0xFD:
            raise ValueError(f"not a MAVLink 2 frame at byte {i}")
        ln, incompat, seq = datagram[i + 1], datagram[i + 2], datagram[i + 4]
        msgid = datagram[i + 7] | (datagram[i + 8] << 8) | (datagram[i + 9] << 16)
        out.append((msgid, seq, datagram[i + 10:i + 10 + ln]))
        i += 12 + ln + (13 if incompat & 1 else 0)
    return out


def vehicle_commands(captured, lockstep: bool) -> list:
    """The node's messages to its vehicle, (step, msgid, payload), without its HEARTBEATs (sent by
    the wall clock) and, in real time, with SET_ACTUATOR_CONTROL_TARGET's time_usec (Unix time,
    the payload's first 8 bytes) zeroed; the sequence numbers move with the heartbeats."""
    out = []
    for n, d in captured:
        for msgid, _, payload in frames(d):
            if msgid == M.MAVLINK_MSG_ID_HEARTBEAT:
                continue
            if msgid == M.MAVLINK_MSG_ID_SET_ACTUATOR_CONTROL_TARGET and not lockstep:
                payload = bytes(8) + payload[8:]
            out.append((n, msgid, bytes(payload)))
    return out


def run_feed(agent: int, steps: int, *, law: str = "hybrid", lockstep: bool = False,
             withhold=None, overrides=(), scenario=HIL, node_kwargs=None) -> dict:
    """Agent ``agent`` for ``steps`` steps on the feed (see the module docstring). ``withhold``:
    (n, j) -> True to leave out neighbour j's sample of step n (real time only), None for
    `default_withhold`, False to send every sample; ``overrides``: the scenario's (`AGE_RULE`
    makes the age rule's steps short); ``node_kwargs`` go to `AgentNode`. Returns {"vehicle":
    [(step, datagram)], "neighbours": {j: [(step, datagram)]}, "steps": [per-step controller
    outputs], "summary", "node" (age-rule counters, own samples and final θ), "events" (the
    node's fail-safe and rejoin events), "sent" (what was fed)}."""
    nb, bb = free_base_port(6), free_base_port(6)
    sc = load_scenario(scenario, [f"network.base_port={nb}", f"bridge.base_port={bb}",
                                  "simulation.duration=100000", *overrides])
    h = float(sc.step)
    h_us = round(h * 1e6)
    events: list = []
    node = AgentNode(sc, agent, law=law, lockstep=lockstep, on_event=events.append,
                     insecure=True, **(node_kwargs or {}))
    if withhold is False or lockstep:   # lockstep waits for every sample
        withhold = lambda n, j: False  # noqa: E731
    elif withhold is None:
        withhold = default_withhold(node.neighbours)
    socks = []
    try:
        vport = int(node.vehicle.cfg.vehicles[0].endpoint.split(":")[2])
        vs = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        vs.bind(("127.0.0.1", 0))
        socks.append(vs)
        vpeer = Peer(agent, 1, Counters())
        nsock, npeer = {}, {}
        for j in node.neighbours:
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.bind(("127.0.0.1", nb + j - 1))
            socks.append(s)
            nsock[j], npeer[j] = s, Peer(j, 191, Counters())
        mav = vpeer.mav
        nan21 = (math.nan,) + (0.0,) * 20
        last_us = [0]
        sent = {"states": 0, "samples": {j: 0 for j in node.neighbours}}

        def vehicle_packets(n):
            """The vehicle's datagrams before step n: its state of step n."""
            out = [vpeer.pack(mav.heartbeat_encode(M.MAV_TYPE_QUADROTOR, M.MAV_AUTOPILOT_GENERIC,
                                                   0, 0, M.MAV_STATE_ACTIVE))] \
                if n % 250 == 0 else []
            row = trajectory(sc.S0[agent - 1], agent, n, h)
            q = rot_to_quat(row[layout.R].reshape(3, 3)).tolist()
            if lockstep:
                t_us = n * h_us
            else:   # a vehicle's clock: the tracker refuses a repeat, and a stamp far off the wall
                t_us = last_us[0] = max(int(time.monotonic() * 1e6), last_us[0] + 1)
            out.append(vpeer.pack(mav.odometry_encode(
                t_us, M.MAV_FRAME_LOCAL_NED, M.MAV_FRAME_BODY_FRD, *row[layout.P].tolist(), q,
                *row[layout.V].tolist(), *row[layout.OMEGA].tolist(), list(nan21), list(nan21),
                0, 0, 100)))
            sent["states"] += 1
            return out

        def samples(n):
            """Each neighbour's datagram of step n (None: withheld)."""
            out = {}
            for j in node.neighbours:
                if withhold(n, j):
                    out[j] = None
                    continue
                theta = [neighbour_theta(k, n, float(sc.theta0[k - 1]))
                         for k in sc.graph.M_plus(j)]
                out[j] = b"".join(npeer[j].pack(m) for m in encode_sample(
                    npeer[j].mav, n, h_us, trajectory(sc.S0[j - 1], j, n, h), theta))
                sent["samples"][j] += 1
            return out

        vaddr, naddr = ("127.0.0.1", vport), ("127.0.0.1", nb + agent - 1)
        _warm_up(node)
        for d in vehicle_packets(0):
            vs.sendto(d, vaddr)
        for s in socks:
            s.setblocking(False)
        node.connect()
        node.n_steps = steps
        node.sample_every = 50
        if not lockstep:
            node.vehicle.pace_from(time.monotonic() - 1e6)   # every step already due: no sleep
        for j, d in samples(0).items():
            if d is not None:
                nsock[j].sendto(d, naddr)
        node.vehicle.poll(0.01)
        captured_v: list = []
        captured_n = {j: [] for j in node.neighbours}
        plant, ctl = node.plant, node.controller
        rec = []
        step = ctl.step_state

        def recorded_step(S, hh):
            u, ev = step(S, hh)
            rec.append({"S": S.copy(), "u": u.copy(), "theta": ctl.theta.copy(),
                        "theta_prev": ctl.theta_prev.copy(), "theta_jump": ctl.theta_jump.copy(),
                        "mu": ctl.mu.copy(), "jumped": ctl.jumped.copy(),
                        "events": tuple(ev), "failsafe": node.failsafe,
                        "state": dict(node._state), "used": dict(node.used)})
            return u, ev

        adv = plant.advance

        def advance(hh):
            n = node.n     # the step just done
            _drain(vs, captured_v, n)
            for j, s in nsock.items():
                _drain(s, captured_n[j], n)
            for d in vehicle_packets(n + 1):   # (lockstep: the answer to step n's command)
                vs.sendto(d, vaddr)
            for j, d in samples(n + 1).items():
                if d is not None:
                    nsock[j].sendto(d, naddr)
            adv(hh)

        ctl.step_state = recorded_step
        plant.advance = advance
        summary = Master(node.local, plant, ctl, None).run(steps)
        _drain(vs, captured_v, node.n)
        for j, s in nsock.items():
            _drain(s, captured_n[j], node.n)
        st = node.stats()
        links = st["agent_link"]["links"]
        rejected = {**st["rejected_by_reason"], **st["agent_link"]["rejected_by_reason"]}
        taken = {int(j): v["samples"] for j, v in links.items()}
        if rejected or taken != sent["samples"] or summary["steps"] != steps:
            raise FeedDisturbed(f"agent {agent}: rejected {rejected}, samples taken {taken} of "
                                f"{sent['samples']}, {summary['steps']} of {steps} steps")
        return {
            "vehicle": captured_v,
            "neighbours": captured_n,
            "steps": rec,
            "summary": {k: v for k, v in summary.items() if k not in WALL_FIELDS},
            "node": {"failsafe_steps": node.failsafe_steps,
                     "failsafe_entries": node.failsafe_entries, "hold_steps": node.hold_steps,
                     "transitions": list(node.transitions), "own_samples": node.own_samples,
                     "own_final_theta": node.theta_owned, "compiled": node.compiled,
                     "scanned": node.link.scanned, "link": _link_counts(st["agent_link"]),
                     "vehicle_compiled": (node.vehicle.read_compiled,
                                          node.vehicle.packed_commands,
                                          node.vehicle.taken_states)},
            "events": [e for e in events if e.startswith(("fail-safe", "rejoined"))],
            "sent": sent,
        }
    finally:
        node.close()
        for s in socks:
            s.close()


def _link_counts(st: dict) -> dict:
    """The inter-agent link's statistics without what the kernel says of its sockets."""
    st = {k: v for k, v in st.items() if k != "kernel_drops"}
    st["links"] = {j: {k: v for k, v in ln.items() if k != "kernel_drops"}
                   for j, ln in st["links"].items()}
    return st


def run_pair(agent: int, steps: int, kwargs_a: dict, kwargs_b: dict, attempts: int = 3,
             **kw) -> tuple:
    """`run_feed` with node kwargs ``kwargs_a``, then ``kwargs_b`` (e.g. ``{"compiled": False}``,
    the reference, and ``{"compiled": True}``), both again (up to ``attempts`` times) while
    either was disturbed by the machine."""
    for i in range(attempts):
        try:
            return (run_feed(agent, steps, **kw, node_kwargs=kwargs_a),
                    run_feed(agent, steps, **kw, node_kwargs=kwargs_b))
        except FeedDisturbed:
            if i == attempts - 1:
                raise


__all__ = ["run_feed", "run_pair", "vehicle_commands", "frames", "trajectory",
           "default_withhold", "FeedDisturbed", "AGE_RULE"]
