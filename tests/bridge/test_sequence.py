"""`dropped`: what never came, from the senders' sequence numbers (bridge/mavlink/sequence.py).

The expectation is computed here from the stream itself: of the packets a sender numbered
between the first and the newest that came, those that never came at all. Packets that come
late, twice, or are refused for being old (read after a stall, a sample resent) came.
"""
import socket
import time

import numpy as np
import pytest

from bridge.mavlink.link import Counters, Peer
from bridge.mavlink.sequence import SEQ_WINDOW, seq_last, seq_step
from bridge.swarm.agent_link import AgentLink

from test_agent_link import closing, random_row, scenario  # noqa: F401


def _stream(rng, n, lose=0.02, reorder=0.1, twice=0.05):
    """A sender's packet indices 0..n−1 as they come: runs of losses (under 100), indices
    moved up to 8 places later, some twice. Returns (the order they come in, the set that
    came)."""
    keep = []
    i = 0
    while i < n:
        if rng.random() < lose:
            i += int(rng.integers(1, 100))
        keep.append(i)
        i += 1
    key = np.array(keep, float)
    moved = rng.random(len(keep)) < reorder
    key[moved] += rng.uniform(0.5, 8.0, int(moved.sum()))
    order = [keep[k] for k in np.argsort(key, kind="stable")]
    out = []
    for x in order:
        out.append(x)
        if rng.random() < twice:
            out.append(x)
    return out, set(keep)


def _lost(came: set) -> int:
    lo, hi = min(came), max(came)
    return sum(1 for i in range(lo, hi + 1) if i not in came)


@pytest.mark.parametrize("seed", range(6))
def test_losses_are_the_numbers_that_never_came(seed):
    rng = np.random.default_rng(seed)
    arrivals, came = _stream(rng, 4000)
    state, dropped = -1, 0
    for i in arrivals:
        state, lost = seq_step(state, i & 0xFF)
        dropped += lost
    assert seq_last(state) == max(came) & 0xFF
    assert dropped == _lost(came) > 0


def test_late_and_twice_cost_nothing():
    """In order: gaps only. The same stream with a number late, or twice: the same count."""
    def count(seqs):
        st, d = -1, 0
        for s in seqs:
            st, lost = seq_step(st, s)
            d += lost
        return d

    base = list(range(250, 256)) + list(range(0, 40))          # across the wrap
    assert count(base) == 0
    assert count([s for s in base if s not in (3, 4, 9)]) == 3
    late = [s for s in base if s != 5]
    late.insert(late.index(20), 5)                              # 5 comes after 19
    assert count(late) == 0
    assert count(base[:10] + [base[9]] * 3 + base[10:]) == 0    # 0..3 again
    # 45 places late, past the window: not recognised, its gap stays counted, and it costs
    # nothing more (the numbers after it are not counted lost again)
    far = [s for s in range(101) if s != 50]
    far.insert(far.index(95), 50)
    assert count(far) == 1
    assert count(list(range(100)) + list(range(100 - SEQ_WINDOW - 10, 100)) + [100]) == 0


def test_the_compiled_rule_is_the_links():
    """The readers that count in compiled code (`state_wire.take_states`,
    `sample_wire.drain_samples`) inline `state_wire._seq_step`: the same states and counts
    as the plain rule for every sequence number from random states."""
    from bridge.mavlink.state_wire import _seq_step

    rng = np.random.default_rng(7)
    states = [-1] + [int(s) | (int(m) << 8) for s, m in
                     zip(rng.integers(0, 256, 300), rng.integers(0, 1 << SEQ_WINDOW, 300))]
    for st in states:
        for seq in range(256):
            assert tuple(int(x) for x in _seq_step(np.int64(st), np.int64(seq))) == \
                seq_step(st, seq), (st, seq)


def test_a_peer_counts_a_late_packet_once_and_a_refused_one_not_at_all():
    """`Peer`: a number committed late fills its gap; a packet the application refuses for
    anything but age (`Counters.arrived_since`) is not committed, and leaves a gap."""
    c = Counters()
    peer = Peer(255, 190, c)
    src = Peer(1, 1, Counters())

    def packet(seq):
        src.mav.seq = seq
        return bytes(src.pack(src.mav.heartbeat_encode(2, 0, 0, 0, 4)))

    for seq, reason in [(0, None), (1, None), (3, None), (2, "out_of_order"), (4, "nan"),
                        (5, None)]:
        d = packet(seq)
        assert peer.accepted(d, seq, 1, 1)
        m0 = c.mark()
        if reason is not None:
            c.reject(reason)
        if c.arrived_since(m0):
            peer.commit()
    assert c.dropped == 1 and peer.sequences() == {(1, 1): 5}   # 4: refused, never counted


def _plant_and_vehicle(compiled):
    """A one-vehicle bridge (stale after 50 ms) and a socket that sends it vehicle 1's states,
    stamped t0 + 4 ms·n: (plant, send(n, t0), read_all())."""
    from bridge.mavlink.plant import MavlinkPlant
    from _bridge import free_base_port, load
    from test_state_wire import _odometry

    port = free_base_port(6)
    sc = load([f"bridge.base_port={port}", "bridge.stale_after=0.05"])
    p = MavlinkPlant(sc, connect_timeout=1, on_event=lambda s: None)
    p.compiled_state = compiled
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx.bind(("127.0.0.1", 0))
    rng = np.random.default_rng(1)
    veh = Peer(1, 1, Counters())
    sent = [0]

    def send(n, t0):
        tx.sendto(_odometry(veh, t0 + 4000 * n, rng), ("127.0.0.1", port))
        sent[0] += 1

    def read_all():
        end = time.monotonic() + 5.0
        while p.counters.datagrams < sent[0] and time.monotonic() < end:
            p.poll(0.01)
    return p, tx, send, read_all


@pytest.mark.parametrize("compiled", [True, False])
def test_states_read_after_a_stall_are_stale_not_lost(compiled):
    """The bridge stops reading for 0.3 s while a vehicle streams at 250 Hz: what waited is
    refused as stale, and none of it is reported lost (it was: ``dropped`` = ``stale``)."""
    # a bridge of its own first takes a few states: the readers compiled (seconds on a cold
    # cache, a stall of its own in the middle of the stream below)
    p, tx, send, read_all = _plant_and_vehicle(compiled)
    try:
        t0 = int(time.time() * 1e6)
        for n in range(3):
            send(n, t0)
            read_all()
        assert p.counters.datagrams == 3
    finally:
        p.close()
        tx.close()
    p, tx, send, read_all = _plant_and_vehicle(compiled)
    try:
        t0 = int(time.time() * 1e6)
        start = time.monotonic()
        for n in range(200):       # 0.8 s at 250 Hz, the bridge stalled in the middle
            while time.monotonic() < start + 0.004 * n:
                time.sleep(0.0005)
            send(n, t0)
            if not 80 <= n < 155:
                read_all()
        read_all()
        st = p.counters.as_dict()
        stale = st["rejected_by_reason"].get("stale", 0)
        assert p.counters.datagrams == 200
        assert stale > 10, st
        assert st["dropped"] == 0 and p.vehicles[0].peer.sequences() == {(1, 1): 199}, st
    finally:
        p.close()
        tx.close()


def test_a_resent_sample_is_a_duplicate_not_a_loss(closing):
    """A neighbour's sample sent twice (lockstep resends): refused as a duplicate, and the
    next sample's numbers show no gap."""
    sc = scenario()
    tx = AgentLink.from_scenario(sc, 2)
    rx = AgentLink.from_scenario(sc, 1)
    closing.extend([tx, rx])
    rng = np.random.default_rng(2)
    rows = [random_row(rng) for _ in range(3)]
    for n, again in [(0, 0), (1, 2), (2, 0)]:
        for _ in range(1 + again):
            tx.publish(n, rows[n], {2: 0.1 * n, 4: -0.1 * n})
    end = time.monotonic() + 5.0
    while rx.stats()["datagrams"] < 5 and time.monotonic() < end:
        rx.poll()
        time.sleep(0.001)
    st = rx.stats()
    assert st["datagrams"] == 5 and rx.neighbour(2).step == 2
    assert st["rejected_by_reason"] == {"duplicate": 4}, st     # two packets each, twice
    assert st["dropped"] == 0, st
