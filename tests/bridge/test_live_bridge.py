"""The bridge's live views (bridge/live.py): the swarm's merged view built from the agents' feed
datagrams (checked before use, refused by reason), seen by a real WebSocket client; the agent's
feed (`FeedTee`); the loopback vehicles' view."""
import json
import math
import socket
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("foxglove")
websocket = pytest.importorskip("websocket")

from bridge import live as BL  # noqa: E402
from controller.kernels import metrics, network_U  # noqa: E402
from controller import LawParameters  # noqa: E402
from cosim.controllers import make_controller  # noqa: E402
from cosim.plants import FmuPlant  # noqa: E402
from cosim.scenario import load_scenario  # noqa: E402

from test_live import SUBPROTOCOLS  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
HIL = ROOT / "scenarios" / "hil_6uav.toml"


@pytest.fixture(scope="module")
def sc():
    return load_scenario(HIL)


@pytest.fixture(scope="module")
def state(sc):
    """The network after 30 steps of hil_6uav: S, u, θ after the jump stage, μ_U, jumped."""
    p = FmuPlant.from_scenario(sc)
    law = make_controller("hybrid", sc)
    try:
        for _ in range(30):
            S = p.read().copy()
            u, _ = law.step_state(S, sc.step)
            p.apply(u)
            p.advance(sc.step)
        S = p.read().copy()
        u, _ = law.step_state(S, sc.step)
        return S, u.copy(), law.theta_jump.copy(), law.mu.copy(), law.jumped.copy()
    finally:
        p.close()


def _owned(sc, i):
    return [k + 1 for k, (a, _) in enumerate(sc.graph.edge_list) if a == i]


def _datagram(sc, state, i, t_ns=120_000_000, jumps=()):
    S, u, th, mu, jumped = state
    edges = [(k, th[k - 1], mu[k - 1], jumped[k - 1]) for k in _owned(sc, i)]
    return BL.encode_feed(i, t_ns, S[i - 1], u[i - 1], edges, list(jumps))


def test_feed_datagram_round_trip(sc, state):
    d = _datagram(sc, state, 2, jumps=[(2, 0.0, 0.0, 0.94, 0.3)])
    agent, t_ns, row, edges, jumps = BL.decode_feed(d)
    assert (agent, t_ns) == (2, 120_000_000)
    assert np.array_equal(row[:18], state[0][1]) and np.array_equal(row[18:], state[1][1])
    assert [e[0] for e in edges] == _owned(sc, 2) and jumps == [(2, 0.0, 0.0, 0.94, 0.3)]


def test_bad_feed_datagrams_are_refused_by_reason(sc, state):
    view = BL.SwarmLive(sc, "127.0.0.1", 0)
    try:
        good = _datagram(sc, state, 2)
        local = ("127.0.0.1", 40000)
        cases = [
            (good, ("10.1.2.3", 40000), "address"),
            (good[:20], local, "short"),
            (b"XXXX" + good[4:], local, "magic"),
            (good[:4] + bytes([9]) + good[5:], local, "version"),
            (good + b"\0", local, "length"),
            (BL.encode_feed(7, 0, state[0][0], state[1][0], [], []), local, "agent"),
            # agent 3 does not own edge 1 (1 → 2)
            (BL.encode_feed(3, 0, state[0][2], state[1][2], [(1, 0.1, 0.2, 0)], []), local,
             "not_owner"),
            (BL.encode_feed(1, 0, np.full(18, np.nan), state[1][0], [], []), local,
             "non_finite"),
        ]
        S_before = view.S.copy()
        for data, addr, why in cases:
            assert view.accept(data, addr) is False, why
        assert view.rejected == {w: 1 for _, _, w in cases}
        assert np.array_equal(view.S, S_before) and view.received == 0
        assert view.accept(good, local) and view.received == 1
        assert np.array_equal(view.S[1], state[0][1])
    finally:
        view.close()


def _client_frames(url, want, deadline=60):
    ws = websocket.create_connection(url, subprotocols=SUBPROTOCOLS, timeout=deadline)
    chans, subs, got = {}, {}, []
    t0 = time.monotonic()
    try:
        while time.monotonic() - t0 < deadline:
            try:
                m = ws.recv()
            except (websocket.WebSocketConnectionClosedException, ConnectionError):
                break   # the server closed (or reset) the connection at the end of the run
            if isinstance(m, str):
                o = json.loads(m) if m else {}
                if o.get("op") == "advertise":
                    new = []
                    for c in o["channels"]:
                        chans[c["id"]] = c
                        subs[len(subs) + 1] = c["id"]
                        new.append({"id": len(subs), "channelId": c["id"]})
                    ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
                    if len(subs) == len(new):   # the first advertisement
                        yield "subscribed"
                continue
            if m[0] == 1:
                sid = int.from_bytes(m[1:5], "little")
                t = int.from_bytes(m[5:13], "little")
                got.append((chans[subs[sid]]["topic"], t, json.loads(m[13:])))
                if want(got):
                    break
    finally:
        ws.close()
    yield got


def test_merged_view_of_the_agents_feeds(sc, state):
    """Six agents' datagrams (each its own row and owned edges, one with a jump) make one
    frame whose /edges errors and V̄ are those of the whole network, computed independently."""
    view = BL.SwarmLive(sc, "127.0.0.1", 0, rate=1e9)   # every datagram its own frame
    try:
        gen = _client_frames(view.server.url,
                             lambda got: any(g[0] == "/lyapunov" and g[1] == 120_000_000
                                             for g in got) and any(g[0] == "/jumps" for g in got))
        assert next(gen) == "subscribed"
        t0 = time.monotonic()
        while not view.server.sink.watched() and time.monotonic() - t0 < 30:
            time.sleep(0.01)
        host, port = view.feed.split(":")
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        for i in range(1, 7):
            jumps = [(2, 0.004, 0.1, 0.9, 0.5)] if i == 2 else []
            s.sendto(_datagram(sc, state, i, t_ns=(100_000_000 if i < 6 else 120_000_000),
                               jumps=jumps), (host, int(port)))
            time.sleep(0.01)   # in order, each its own frame at most
        s.close()
        got = next(gen)
    finally:
        view.close()
    S, u, th, mu, jumped = state
    edges = [g for g in got if g[0] == "/edges" and g[1] == 120_000_000][-1][2]["edges"]
    # independent: the kernels on the full state
    P = LawParameters.of(sc.weighting, sc.design, sc.gains).P
    M = sc.graph.M
    U, rot, pos, quat = np.zeros(M), np.zeros(M), np.zeros(M), np.zeros((6, 4))
    network_U(S, th, np.ascontiguousarray(sc.graph.edges), P, U)
    V, _ = metrics(S, np.ascontiguousarray(sc.graph.edges), U, float(sc.gains.k_X),
                   np.ascontiguousarray(sc.masses, float), np.ascontiguousarray(sc.inertias,
                                                                                float),
                   rot, pos, quat)
    assert [e["rot_err"] for e in edges] == rot.tolist()
    assert [e["theta"] for e in edges] == th.tolist()
    lyap = [g for g in got if g[0] == "/lyapunov" and g[1] == 120_000_000][-1][2]
    assert math.isclose(lyap["V"], V, rel_tol=0, abs_tol=0)
    (jmp,) = [g[2] for g in got if g[0] == "/jumps"]
    assert (jmp["edge"], jmp["theta_after"]) == (2, 0.9)


def test_feed_tee_sends_own_row_and_owned_edges(sc, state):
    """FeedTee, as an agent's master drives it: its datagram carries the agent's own row of
    the neighbourhood and the edges it owns, with the swarm's edge numbers."""
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(10)

    class Node:   # agent 2 of hil_6uav: neighbours 1, 3, 5; edges 1, 2, 4 (2 and 4 owned)
        i = 2
        agents = (1, 2, 3, 5)
        edge_ids = (1, 2, 4)
        owned = (2, 4)

    tee = BL.feed_logger(None, ("127.0.0.1", rx.getsockname()[1], 30.0), Node())
    S, u, th, mu, jumped = state
    rows = [0, 1, 2, 4]
    loc = [0, 1, 3]
    tee.jump(0, 0.0, 2, 0.0, 0.94, 0.3)   # local edge 2 = swarm edge 2
    tee.record(40_000_000, S[rows], u[rows], th[loc], mu[loc], jumped[loc], None, None, None,
               None, 0.0, 0.0)
    data, _ = rx.recvfrom(65536)
    tee.close()
    rx.close()
    agent, t_ns, row, edges, jumps = BL.decode_feed(data)
    assert (agent, t_ns) == (2, 40_000_000)
    assert np.array_equal(row[:18], S[1]) and np.array_equal(row[18:], u[1])
    assert [(e[0], e[1]) for e in edges] == [(2, th[1]), (4, th[3])]
    assert jumps == [(2, 0.0, 0.0, 0.94, 0.3)]


def test_vehicle_view_shows_the_vehicles_state(sc, state):
    """VehicleLive after a tick: the vehicles' poses on /tf, the geometry of every edge, and θ,
    U, V̄ (the controller's, unknown to the vehicles) as null."""
    S, u, *_ = state

    class V:
        def __init__(self, i):
            self.S, self.wrench, self.k = S[i], u[i], 25

    class Srv:
        vehicles = [V(i) for i in range(6)]

    view = BL.VehicleLive(sc, "127.0.0.1", 0, rate=1e9, step=0.004)
    try:
        gen = _client_frames(view.server.url, lambda got: any(g[0] == "/lyapunov" for g in got))
        assert next(gen) == "subscribed"
        t0 = time.monotonic()
        while not view.server.sink.watched() and time.monotonic() - t0 < 30:
            time.sleep(0.01)
        view(Srv())
        got = next(gen)
    finally:
        view.close()
    tf = [g for g in got if g[0] == "/tf"][0]
    assert tf[1] == 100_000_000   # k · step
    for x, row in zip(tf[2]["transforms"], S):
        assert [x["translation"][c] for c in "xyz"] == row[:3].tolist()
    edges = [g for g in got if g[0] == "/edges"][0][2]["edges"]
    assert all(e["theta"] is None and e["U"] is None for e in edges)
    assert all(e["rot_err"] >= 0 for e in edges)
    assert [g for g in got if g[0] == "/lyapunov"][0][2]["V"] is None


@pytest.mark.realtime
@pytest.mark.timeout(300)
def test_connect_live_view_over_mavlink(tmp_path, monkeypatch):
    """`connect --live` (run_hil with live): six lockstep loopback vehicles over real UDP; a
    WebSocket client subscribed before the first step receives the log's /tf and /edges
    messages, byte for byte."""
    import os
    import threading

    os.environ.setdefault("MAVLINK20", "1")
    from bridge.mavlink.hil import run_hil
    from bridge.mavlink.plant import MavlinkPlant
    from cosim.log import live as L
    from _bridge import VehicleThread, free_base_port, load
    from test_live import _messages_with_bytes

    urls, servers = [], []

    def announce(self, command):   # hold the run until a client watches (no race with it)
        servers.append(self)
        urls.append(self.url)
        t0 = time.monotonic()
        while not self.sink.watched() and time.monotonic() - t0 < 60:
            time.sleep(0.01)

    monkeypatch.setattr(L.LiveServer, "announce", announce)
    sc = load([f"bridge.base_port={free_base_port(6)}", "simulation.duration=1.0"])
    log = tmp_path / "hil.mcap"
    out = {}
    with VehicleThread(scenario=sc, lockstep=True, aux_rate=0):
        p = MavlinkPlant(sc, lockstep=True, connect_timeout=30, on_event=lambda s: None)
        try:
            p.connect()

            def go():
                out["summary"] = run_hil(sc, p, log_path=log, live=("127.0.0.1", 0, 200.0))

            t = threading.Thread(target=go)
            t.start()
            t0 = time.monotonic()
            while not urls and time.monotonic() - t0 < 60:
                time.sleep(0.01)
            gen = _client_frames(urls[0], lambda got: False, deadline=120)
            assert next(gen) == "subscribed"
            got = next(gen)   # until the run ends and the server closes
            t.join(120)
        finally:
            p.close()
    assert out["summary"]["steps"] == 250
    logged = _messages_with_bytes(log)
    rec = [g for g in got if g[0] in ("/tf", "/edges")]
    assert rec
    for topic, t_ns, msg in rec:
        assert json.loads(logged[(topic, t_ns)]) == msg


def test_one_forged_time_stamp_does_not_freeze_the_swarm_view(sc, state):
    """Audit of issue 29, 7: one feed datagram stamped far ahead set the view's time, so no later
    (genuine) datagram was newer and the view published nothing more. A stamp is now taken only
    within a window of the view's current time (``future`` otherwise)."""
    view = BL.SwarmLive(sc, "127.0.0.1", 0)
    local = ("127.0.0.1", 40000)
    try:
        assert view.accept(_datagram(sc, state, 1, t_ns=10**18), local) is False
        assert view.accept(_datagram(sc, state, 1, t_ns=120_000_000), local)
        assert view.accept(_datagram(sc, state, 2, t_ns=120_000_000 + 3600 * 10**9), local) is False
        assert view.rejected == {"future": 2}
        assert view.accept(_datagram(sc, state, 2, t_ns=160_000_000), local)
        assert view.t_ns == 160_000_000 and view.received == 2
    finally:
        view.close()
