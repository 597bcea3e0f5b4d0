"""A port shared by a catch-all and its peers' connected sockets (`bridge.mavlink.link.UdpSocket`
with ``reuse_port`` / ``connect_to``: the bridge's udpin endpoints, the inter-agent link).

Between a peer socket's bind and its connect the kernel may hand it anyone's datagram. Its
compiled readers take every datagram on it to be the peer's, so one such datagram once made the
bridge refuse a clean run ("vehicle 4 is claimed by two processes": vehicle 4's first ODOMETRY
was read from vehicle 1's socket, so vehicle 1's address became vehicle 4's source). Here that
instant is held open (`_Window`) while other senders send, and what every reader makes of each
datagram is compared with its true sender."""
from __future__ import annotations

import math
import socket
import time
import types

import numpy as np
import pytest

from bridge.mavlink import link
from bridge.mavlink.link import Counters, Peer, UdpSocket, mavlink2

pytestmark = pytest.mark.skipif(not hasattr(socket, "SO_REUSEPORT"), reason="no SO_REUSEPORT")

STRANGERS = 32


class _Window:
    """While active, the first connect of a socket bound with SO_REUSEPORT (a peer socket being
    made) first has ``send()`` called: its datagrams then arrive between that socket's bind and
    its connect (and ``after()``, if given, just after the connect). With ``forced`` the port's group hands them all to it meanwhile (its member
    ``forced``: the race's worst case, made certain); otherwise the kernel decides as it would."""

    def __init__(self, monkeypatch, send, forced: int | None = None, after=None):
        self.send, self.forced, self.used = send, forced, False
        outer = self

        class WindowSocket(socket.socket):
            def connect(self, addr):
                if not outer.used and self.getsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT):
                    outer.used = True
                    if outer.forced is not None:
                        assert link.steer_unclaimed(self, outer.forced)
                    outer.send(self.getsockname()[1])
                    if outer.forced is not None:
                        assert link.steer_unclaimed(self, 0)     # as UdpSocket left it
                    super().connect(addr)
                    if after is not None:
                        after(self.getsockname()[1])    # …and ``after()``'s just after it
                    return
                super().connect(addr)

        mod = types.SimpleNamespace(**{k: getattr(socket, k) for k in dir(socket)
                                       if not k.startswith("__")})
        mod.socket = WindowSocket
        monkeypatch.setattr(link, "socket", mod)


def _udp():
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    return s


def _read_until(sock: UdpSocket, n: int, guard: float = 10.0) -> list:
    """recv_all until n datagrams came (loopback delivers at once; the guard stops a hang)."""
    out = []
    t_end = time.monotonic() + guard
    while len(out) < n and time.monotonic() < t_end:
        out += sock.recv_all()
    return out


def _steering_available() -> bool:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        s.bind(("127.0.0.1", 0))
        return link.steer_unclaimed(s)
    finally:
        s.close()


@pytest.mark.parametrize("case", ["steered", "kernel's choice, unsteered", "forced onto it"])
def test_what_reaches_a_peer_socket_before_its_connect_keeps_its_true_sender(monkeypatch, case):
    """32 strangers send one datagram each while the peer socket is bound but not connected.
    Steered (as `UdpSocket` sets the catch-all up): all reach the catch-all. Unsteered (an
    older kernel) or forced: some or all reach the peer socket, and `recv_all` gives them
    first, each with its sender's address. Then the peer's datagrams reach the peer socket
    only, and the strangers' the catch-all."""
    if case == "steered" and not _steering_available():
        pytest.skip("this kernel has no SO_ATTACH_REUSEPORT_CBPF")
    if case == "kernel's choice, unsteered":
        monkeypatch.setattr(link, "steer_unclaimed", lambda s, member=0: False)
    strangers = [_udp() for _ in range(STRANGERS)]
    peer = _udp()
    catch = None
    s = None
    try:
        catch = UdpSocket("udpin:127.0.0.1:0", reuse_port=True)
        port = catch.local[1]
        sent = {(b"from %d" % x.getsockname()[1], x.getsockname()) for x in strangers}

        def send(to_port):
            for x in strangers:
                x.sendto(b"from %d" % x.getsockname()[1], ("127.0.0.1", to_port))

        w = _Window(monkeypatch, send, forced=1 if case == "forced onto it" else None)
        s = UdpSocket(f"udpin:127.0.0.1:{port}", reuse_port=True, connect_to=peer.getsockname())
        monkeypatch.undo()
        assert w.used
        early = s.recv_all()
        rest = _read_until(catch, STRANGERS - len(early))
        assert {(d, tuple(a)) for d, a in early + rest} == sent and len(early + rest) == STRANGERS
        if case == "steered":
            assert early == []
        else:
            # forced: all of them (loopback delivers within the sender's call; one the kernel
            # deferred would reach the catch-all after the connect). Unsteered: each lands on
            # either socket (a hash of its address), and none on the peer's would happen one
            # time in 2**32
            assert early
        peer.sendto(b"peer", ("127.0.0.1", port))
        strangers[0].sendto(b"stranger", ("127.0.0.1", port))
        assert _read_until(s, 1) == [(b"peer", peer.getsockname())]
        assert _read_until(catch, 1) == [(b"stranger", strangers[0].getsockname())]
    finally:
        for x in (*strangers, peer):
            x.close()
        for x in (catch, s):
            if x is not None:
                x.close()


@pytest.mark.parametrize("stamped", [True, False], ids=["arrival times", "none"])
def test_merge_backlog_keeps_a_senders_order_across_the_two_sockets(monkeypatch, stamped):
    """One sender's datagrams around a peer socket's connect: a0 waits on the catch-all, a1 and
    a2 reach the peer socket before its connect (forced there), a3 the catch-all after it.
    `merge_backlog` gives them back on the catch-all as they arrived, a0…a3; without the
    kernel's arrival times (documented fallback) the catch-all's come first: a0, a3, a1, a2."""
    if not stamped:
        monkeypatch.setattr(link, "_SO_TIMESTAMPNS", None)
    x, peer = _udp(), _udp()
    catch = s = None
    try:
        catch = UdpSocket("udpin:127.0.0.1:0", reuse_port=True)
        port = catch.local[1]
        assert catch.stamped is stamped
        x.sendto(b"a0", ("127.0.0.1", port))

        def window(to_port):
            for d in (b"a1", b"a2"):
                x.sendto(d, ("127.0.0.1", to_port))

        w = _Window(monkeypatch, window, forced=1,
                    after=lambda to_port: x.sendto(b"a3", ("127.0.0.1", to_port)))
        s = UdpSocket(f"udpin:127.0.0.1:{port}", reuse_port=True, connect_to=peer.getsockname())
        assert w.used and [d for d, _ in s.backlog] == [b"a1", b"a2"]
        catch.merge_backlog(s)
        assert s.backlog == [] and s.recv_all() == []
        got = catch.recv_all()
        assert all(a == x.getsockname() for _, a in got)
        want = [b"a0", b"a1", b"a2", b"a3"] if stamped else [b"a0", b"a3", b"a1", b"a2"]
        assert [d for d, _ in got] == want
    finally:
        for y in (x, peer):
            y.close()
        for y in (catch, s):
            if y is not None:
                y.close()


def _odometry(peer: Peer) -> bytes:
    t = int(time.time() * 1e6)
    return bytes(peer.pack(peer.mav.odometry_encode(
        t, mavlink2.MAV_FRAME_LOCAL_NED, mavlink2.MAV_FRAME_BODY_FRD, 0, 0, 0, [1, 0, 0, 0],
        0, 0, 0, 0, 0, 0, [math.nan] + [0.0] * 20, [math.nan] + [0.0] * 20, 0, 0, 100)))


def test_a_vehicles_state_read_from_another_vehicles_socket_keeps_its_vehicle(monkeypatch):
    """The failure above, made certain: hil_6uav's six vehicles share one udpin port; vehicle 1's
    first ODOMETRY opens its socket, and while that socket is bound but not connected vehicles
    2–6 send theirs, all of which it gets. Each must be taken as its own vehicle's, from its
    own address: the vehicles' next states are all accepted, no second source is seen, and
    the plant reads each vehicle on its own socket from then on."""
    from bridge.mavlink.config import default_config
    from bridge.mavlink.plant import MavlinkPlant
    from cosim.scenario import load_scenario

    sc = load_scenario("scenarios/hil_6uav.toml")
    cfg = (sc.bridge or default_config(sc.n_agents)).with_endpoints(["udpin:127.0.0.1:0"] * 6)
    p = MavlinkPlant(sc, cfg, connect_timeout=5, on_event=lambda s: None)
    socks = [_udp() for _ in range(6)]
    peers = [Peer(i + 1, 1, Counters()) for i in range(6)]
    try:
        assert p.compiled_state      # the reader that takes every datagram to be the source's
        port = p.socks[0].local[1]

        # stamped now, as a vehicle stamps its state before it sends it (stamped in the window,
        # they would look newer than the poll that reads them: the stale rule's offset would
        # then count any later delay, a first compilation's say, against the next states)
        first = [_odometry(pe) for pe in peers]

        def send(to_port):
            for s, data in zip(socks[1:], first[1:]):
                s.sendto(data, ("127.0.0.1", to_port))

        w = _Window(monkeypatch, send, forced=1)
        socks[0].sendto(first[0], ("127.0.0.1", port))
        t_end = time.monotonic() + 10
        while p.counters.received < 6 and time.monotonic() < t_end:
            p.poll(0.01)
        monkeypatch.undo()
        assert w.used and p.counters.received == 6
        for _ in range(3):                                   # the vehicles stream on
            for s, pe in zip(socks, peers):
                s.sendto(_odometry(pe), ("127.0.0.1", port))
        t_end = time.monotonic() + 10
        while p.counters.received < 24 and time.monotonic() < t_end:
            p.poll(0.01)
        st = p.stats()
        # every packet passed the link as its own vehicle's (a second source is refused before
        # that); a machine stalled past the stale rule's 0.1 s may still make a state stale
        assert st["received"] == 24 and set(st["rejected_by_reason"]) <= {"stale"}, st
        assert st["other_sources"] == {} and st["source_sockets"] == 6
    finally:
        p.close()
        for s in socks:
            s.close()


@pytest.mark.parametrize("forced", [None, 2], ids=["kernel's choice", "forced onto it"])
def test_a_vehicles_first_states_keep_their_order_across_a_new_source_socket(monkeypatch, forced):
    """`connect` once counted a vehicle's first packets lost ("dropped 3" on a clean loopback
    run, test_bridge_attacks): with one vehicle's socket connected already, Linux hands every
    datagram nobody claims to the next vehicle's socket while it is bound but not connected,
    not to the catch-all (6.18 does so on its own; ``forced`` makes it certain elsewhere).
    Vehicle 3's first state landed there, its second on the catch-all just after the connect,
    and the catch-all was read first: the first state was then refused as older, and a gap
    counted. Now both are taken in the order they were sent, and nothing is counted lost."""
    from bridge.mavlink.config import default_config
    from bridge.mavlink.plant import MavlinkPlant
    from cosim.scenario import load_scenario

    sc = load_scenario("scenarios/hil_6uav.toml")
    cfg = (sc.bridge or default_config(sc.n_agents)).with_endpoints(["udpin:127.0.0.1:0"] * 6)
    p = MavlinkPlant(sc, cfg, connect_timeout=5, on_event=lambda s: None)
    socks = [_udp() for _ in range(3)]
    peers = [Peer(i + 1, 1, Counters()) for i in range(3)]
    try:
        port = p.socks[0].local[1]

        def poll_until(received):
            t_end = time.monotonic() + 10
            while p.counters.received < received and time.monotonic() < t_end:
                p.poll(0.01)

        socks[0].sendto(_odometry(peers[0]), ("127.0.0.1", port))
        poll_until(1)
        assert p.stats()["source_sockets"] == 1          # vehicle 1's: connected
        c1 = _odometry(peers[2])
        time.sleep(0.002)
        c2 = _odometry(peers[2])
        w = _Window(monkeypatch, lambda to: socks[2].sendto(c1, ("127.0.0.1", to)), forced,
                    after=lambda to: socks[2].sendto(c2, ("127.0.0.1", to)))
        socks[1].sendto(_odometry(peers[1]), ("127.0.0.1", port))   # opens vehicle 2's socket
        poll_until(4)
        monkeypatch.undo()
        assert w.used
        time.sleep(0.002)
        socks[2].sendto(_odometry(peers[2]), ("127.0.0.1", port))   # vehicle 3 streams on
        poll_until(5)
        st = p.stats()
        assert st["received"] == 5 and st["rejected"] == 0, st
        assert st["dropped"] == 0 and st["other_sources"] == {}, st
        assert p.vehicles[2].tracker.n_odometry == 3
        assert p.vehicles[2].peer.sequences() == {(3, 1): 2}
    finally:
        p.close()
        for s in socks:
            s.close()


def test_a_strangers_sample_read_from_a_neighbours_socket_is_refused(monkeypatch):
    """The same at the inter-agent link, where the address is what authenticates an unsigned
    neighbour: while agent 1's socket for agent 2 is bound but not connected, strangers send
    samples claiming to be agent 2, all of which it gets. Each is refused as from a wrong
    address (the compiled drain reads no addresses: taken there, one would be agent 2's), and
    agent 2's genuine sample is then taken."""
    from bridge.swarm.agent_link import AGENT_COMPONENT, AgentLink
    from controller import layout
    from cosim.scenario import parse_scenario

    base = link.free_base_port(6)
    text = open("scenarios/hil_6uav.toml").read() + f"\n[network]\nbase_port = {base}\n"
    sc = parse_scenario(text, name="al", path="al.toml")
    strangers = [_udp() for _ in range(8)]
    forger = mavlink2.MAVLink(None, srcSystem=2, srcComponent=AGENT_COMPONENT)
    S = np.zeros(layout.S_WIDTH)
    S[layout.R] = np.eye(3).ravel()
    rx = tx = None
    try:
        def send(to_port):
            for x in strangers:
                x.sendto(_sample(forger, S), ("127.0.0.1", to_port))

        w = _Window(monkeypatch, send, forced=1)
        rx = AgentLink.from_scenario(sc, 1)
        monkeypatch.undo()
        assert w.used
        tx = AgentLink.from_scenario(sc, 2)
        S2 = S.copy()
        S2[layout.P] = [1.0, 2.0, 3.0]
        tx.publish(1, S2, {2: 0.25, 4: 0.5})
        t_end = time.monotonic() + 10
        while rx.neighbour(2) is None and time.monotonic() < t_end:
            rx.poll()
        st = rx.stats()
        assert st["rejected_by_reason"].get("wrong_address") == len(strangers), st
        got = rx.neighbour(2)
        assert got is not None and got.step == 1 and np.allclose(got.S[layout.P], [1.0, 2.0, 3.0],
                                                                 atol=1e-6)
    finally:
        for x in (rx, tx, *strangers):
            if x is not None:
                x.close()


def _sample(mav, S) -> bytes:
    """A whole sample of step 1 (ODOMETRY and the θ of edges 2 and 4), as agent 2 sends it."""
    from bridge.swarm.agent_link import encode_sample

    return b"".join(bytes(m.pack(mav)) for m in encode_sample(mav, 1, 4000, S, [9.0, 9.0]))
