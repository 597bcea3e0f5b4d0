"""The compiled receive path of the inter-agent link (bridge/swarm/sample_wire.py) against the
reference path (`AgentLink(compiled=False)`): the same datagrams, sent to a link of each kind,
leave the same held samples (every bit), the same counters and refusals, and the same sequence
bookkeeping — over honest traffic and over every kind of irregular datagram the reference path
refuses or treats specially. Plus the decoder against pymavlink's own decoding."""
import math
import socket

import numpy as np
import pytest

from bridge.mavlink.link import Counters, Peer, mavlink2
from bridge.swarm.agent_link import AgentLink, encode_sample
from bridge.swarm.sample_wire import SCAN_STATE, SCAN_WIDTH, scan_sample
from controller import layout
from test_agent_link import HIL, H_US, drain_raw, endpoint, parse_scenario, random_row, scenario
from bridge.mavlink.link import free_base_port

pytestmark = pytest.mark.timeout(120)


def _pair(receiver, world="ned", key=None):
    """(compiled link, reference link, senders) for agent ``receiver``: one scenario (ports)
    each, and per neighbour j a socket at j's endpoint in each scenario."""
    out = []
    for compiled in (True, False):
        sc = scenario(world)
        link = AgentLink.from_scenario(sc, receiver, compiled=compiled, key=key)
        link.set_step(0)
        socks = {}
        for j in link.neighbours:
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.bind(endpoint(sc, j))
            socks[j] = s
        out.append((sc, link, socks))
    return out


def _send_both(pair, receiver, j, data):
    for sc, _, socks in pair:
        socks[j].sendto(data, endpoint(sc, receiver))


def _poll_both(pair, expected):
    import time

    for _, link, _ in pair:
        end = time.monotonic() + 5.0
        while link.counters.datagrams < expected and time.monotonic() < end:
            link.poll()
    assert [p[1].counters.datagrams for p in pair] == [expected, expected]


def _state(link):
    held = {}
    hv = link.held_values
    for q, j in enumerate(link.neighbours):
        h = link.neighbour(j)
        assert link.held_step(j) == (None if h is None else h.step)
        if hv is not None and h is not None:   # the drain's arrays hold the same sample
            nt = len(link.owned_by[j])
            assert hv[q, SCAN_STATE:SCAN_STATE + 18].tobytes() == h.S.tobytes()
            assert hv[q, 13:13 + nt].tolist() == [h.theta[k] for k in link.owned_by[j]]
        held[j] = None if h is None else (h.step, h.S.tobytes(), h.xi.tobytes(),
                                          sorted(h.theta.items()))
    st = link.stats()
    st.pop("kernel_drops", None)
    for v in st["links"].values():
        v.pop("kernel_drops", None)
    sig = link.peer.mav.signing
    return (held, st, link.peer.sequences(), link.peer.last_signed,
            (dict(sig.stream_timestamps), sig.timestamp) if link.peer.key is not None else None)


class _Neighbour:
    """Neighbour j's MAVLink sender, and the datagrams it (or someone claiming it) may send."""

    def __init__(self, link, j, rng, key=None):
        self.j = j
        self.owned = link.owned_by[j]
        self.key = key
        self.peer = Peer(j, 191, Counters(), key=key)
        self.rng = rng
        self.sent = []

    def msgs(self, s, S=None, theta=None, h_us=H_US):
        S = random_row(self.rng) if S is None else S
        theta = list(self.rng.normal(size=len(self.owned))) if theta is None else theta
        return [bytes(self.peer.pack(m)) for m in
                encode_sample(self.peer.mav, s, h_us, S, theta)]

    def honest(self, s):
        d = b"".join(self.msgs(s))
        self.sent.append(d)
        return d

    def irregular(self, s):
        """One of the datagrams the reference path refuses or handles specially."""
        rng = self.rng
        kind = int(rng.integers(19 if self.key is not None else 16))
        if kind == 16:                                 # a replay of an earlier datagram
            return self.sent[int(rng.integers(len(self.sent)))] if self.sent else b"\xfd"
        if kind == 17:                                 # signed with another key, or not at all
            other = Peer(self.j, 191, Counters(), key=bytes(32) if rng.random() < 0.5 else None)
            return b"".join(bytes(other.pack(m)) for m in
                            encode_sample(other.mav, s, H_US, random_row(rng), [0.1] * len(self.owned)))
        if kind == 18 and self.owned:                  # a fresh pose with a replayed θ
            old = self.sent[-1] if self.sent else self.honest(s)
            return self.msgs(s)[0] + old[len(self.msgs(s)[0]):]
        if kind == 0:                                  # θ first, then the pose
            return b"".join(self.msgs(s)[::-1])
        if kind == 1:                                  # pose and θ in separate datagrams
            return self.msgs(s)[0]
        if kind == 2:                                  # a bit flipped (checksum)
            d = bytearray(self.honest(s))
            d[int(rng.integers(10, len(d)))] ^= 1 << int(rng.integers(8))
            return bytes(d)
        if kind == 3:                                  # NaN in the pose
            S = random_row(rng)
            S[layout.P.start] = math.nan
            return b"".join(self.msgs(s, S))
        if kind == 4:                                  # |q| − 1 just inside / outside 1e-3
            q = rng.normal(size=4)
            q *= (1.0 + float(rng.choice([0.999e-3, 1.001e-3, 1e-3, 2e-3, -1.001e-3]))) \
                / np.linalg.norm(q)
            m = self.peer.mav.odometry_encode(
                s * H_US, mavlink2.MAV_FRAME_LOCAL_NED, mavlink2.MAV_FRAME_BODY_FRD, 1, 2, 3,
                q.tolist(), 0, 0, 0, 0, 0, 0, [math.nan] + [0.0] * 20,
                [math.nan] + [0.0] * 20, 0, 0, 100)
            return bytes(self.peer.pack(m)) + b"".join(self.msgs(s)[1:])
        if kind == 5:                                  # from the future
            return self.honest(s + 10_000)
        if kind == 6:                                  # not a whole step
            return b"".join(self.msgs(s, h_us=H_US + 1))
        if kind == 7:                                  # an old one
            return self.honest(max(0, s - int(rng.integers(1, 5))))
        if kind == 8:                                  # far back (a restart, if in a run)
            return self.honest(max(0, s - 5000))
        if kind == 9:                                  # truncated
            d = self.honest(s)
            return d[:int(rng.integers(1, len(d)))]
        if kind == 10:                                 # claims another system
            other = Peer(self.j % 6 + 1, 191, Counters())
            return b"".join(bytes(other.pack(m)) for m in
                            encode_sample(other.mav, s, H_US, random_row(rng), [0.1] * len(self.owned)))
        if kind == 11 and self.owned:                  # a wrong θ name or array id
            m = self.peer.mav.debug_float_array_encode(s * H_US, b"thetaX" if rng.random() < 0.5
                                                       else b"theta", self.j + 1,
                                                       [0.5] * 58)
            return self.msgs(s)[0] + bytes(self.peer.pack(m))
        if kind == 12:                                 # θ NaN
            th = [math.nan] * len(self.owned)
            return b"".join(self.msgs(s, theta=th))
        if kind == 13:                                 # the same sample again
            return self.honest(s)
        if kind == 14:                                 # a pose with another frame id
            m = self.peer.mav.odometry_encode(
                s * H_US, mavlink2.MAV_FRAME_LOCAL_FRD, mavlink2.MAV_FRAME_BODY_FRD, 0, 0, 0,
                [1, 0, 0, 0], 0, 0, 0, 0, 0, 0, [math.nan] + [0.0] * 20,
                [math.nan] + [0.0] * 20, 0, 0, 100)
            return bytes(self.peer.pack(m)) + b"".join(self.msgs(s)[1:])
        return self.honest(s) + b"\xfd"               # trailing junk


KEY = bytes(range(32))


@pytest.mark.parametrize("receiver,world,key", [(2, "ned", None), (3, "enu", None),
                                                (1, "ned", None), (2, "enu", KEY),
                                                (3, "ned", KEY)])
def test_compiled_receive_path_equals_the_reference(receiver, world, key):
    rng = np.random.default_rng(receiver)
    pair = _pair(receiver, world, key)
    try:
        ref = pair[1][1]
        nbs = [_Neighbour(ref, j, np.random.default_rng(10 * receiver + j), key)
               for j in ref.neighbours]
        sent = 0
        for n in range(300):
            for _, link, _ in pair:
                link.set_step(n)
            for nb in nbs:
                r = rng.random()
                if r < 0.1:
                    continue                          # lost
                data = nb.honest(n) if r < 0.6 else nb.irregular(n)
                _send_both(pair, receiver, nb.j, data)
                sent += 1
            _poll_both(pair, sent)
            assert _state(pair[0][1]) == _state(pair[1][1]), n
        comp, ref = pair[0][1], pair[1][1]
        # both paths were taken, and every kind of refusal was met
        assert comp.scanned > 100 and ref.scanned == 0
        # the neighbours' sockets were read by the compiled drain (libc's recv; NED: the state
        # row it decodes is the scenario's)
        assert (comp.drained > 100) if world == "ned" else comp.drained == 0
        st = ref.stats()
        assert st["malformed"] > 0 and {"out_of_order", "future", "bad_stamp", "nan",
                                        "non_unit_quaternion", "not_neighbour",
                                        "duplicate"} <= set(st["rejected_by_reason"])
        if key is not None:
            assert {"replay", "unsigned", "bad_signature"} <= set(st["rejected_by_reason"])
    finally:
        for _, link, socks in pair:
            link.close()
            for s in socks.values():
                s.close()


def test_restart_runs_and_held_samples_agree():
    """A neighbour that restarts (stamps far back, RESTART_SAMPLES in a row): the compiled path
    hands those to the reference path, and what is held afterwards is the same."""
    pair = _pair(2)
    try:
        ref = pair[1][1]
        nb = _Neighbour(ref, 1, np.random.default_rng(7))
        sent = 0
        steps = list(range(3000, 3010)) + list(range(5, 20))
        for k, s in enumerate(steps):
            for _, link, _ in pair:
                link.set_step(3010 + k)
            _send_both(pair, 2, 1, nb.honest(s))
            sent += 1
            _poll_both(pair, sent)
            assert _state(pair[0][1]) == _state(pair[1][1]), s
        assert ref.stats()["links"]["1"]["restarts"] == 1
        assert pair[0][1].scanned > 10
    finally:
        for _, link, socks in pair:
            link.close()
            for s in socks.values():
                s.close()


@pytest.mark.parametrize("n_theta", [0, 1, 2, 58])
def test_decoder_reads_what_pymavlink_reads(n_theta):
    """Random samples: the decoder's values are pymavlink's decoded fields (float32 widened)."""
    rng = np.random.default_rng(n_theta)
    peer = Peer(4, 191, Counters())
    dec = mavlink2.MAVLink(None)
    scratch = np.zeros(256, np.uint8)
    out = np.zeros(SCAN_WIDTH)
    seqs = np.zeros(4, np.int64)
    for _ in range(200):
        s = int(rng.integers(0, 1 << 40))
        theta = list(rng.normal(size=n_theta) * 10.0 ** rng.integers(-30, 30))
        S = random_row(rng)
        S[layout.XI] *= 10.0 ** rng.integers(-30, 30)
        bufs = [bytes(peer.pack(m)) for m in encode_sample(peer.mav, s, H_US, S, theta)]
        data = b"".join(bufs)
        got = scan_sample(np.frombuffer(data, np.uint8), len(data), 0, 4, n_theta, H_US, 1 << 60,
                          scratch, out, seqs)
        assert got == s
        msgs = [dec.decode(bytearray(b)) for b in bufs]
        o = msgs[0]
        want = [o.x, o.y, o.z, *o.q, o.rollspeed, o.pitchspeed, o.yawspeed, o.vx, o.vy, o.vz]
        assert out[:13].tolist() == want
        if n_theta:
            assert out[13:13 + n_theta].tolist() == list(msgs[1].data[:n_theta])
        assert seqs[:len(bufs)].tolist() == [m.get_seq() for m in msgs]
        # the receiver's limit: one step short refuses it
        assert scan_sample(np.frombuffer(data, np.uint8), len(data), 0, 4, n_theta, H_US, s - 1,
                           scratch, out, seqs) == -1
        # an unsigned packet where signed ones are due is not a sample
        assert scan_sample(np.frombuffer(data, np.uint8), len(data), 1, 4, n_theta, H_US, 1 << 60,
                           scratch, out, seqs) == -1



def _sent(compiled, world, key, steps, row, theta_of, receiver=2):
    """What agent ``receiver``'s link (compiled or reference) sends its first neighbour over
    ``steps`` publishes: pose and θ, pose only (every 5th), θ only (every 7th)."""
    sc = scenario(world)
    link = AgentLink.from_scenario(sc, receiver, compiled=compiled, key=key)
    if key is not None:
        link.peer.mav.signing.timestamp = 12345      # the two links' own clocks: one start
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(endpoint(sc, link.neighbours[0]))
    s.settimeout(5.0)
    got = []
    try:
        for n in range(steps):
            pose, th = n % 7 != 0, n % 5 != 0
            if link.publish(n, row(n) if pose else None,
                            {k: theta_of(n, k) for k in link.owned} if th else None):
                got.append(s.recv(65535))
        return got, link.peer.mav.seq, (link.peer.mav.signing.timestamp if key else None)
    finally:
        link.close()
        s.close()


@pytest.mark.parametrize("world,key,receiver", [("ned", None, 2), ("enu", None, 3),
                                                ("ned", KEY, 2), ("enu", KEY, 1)])
def test_compiled_send_path_sends_the_reference_bytes(world, key, receiver):
    """`sample_wire.pack_sample` (what a compiled link sends) against `encode_sample` and
    `Peer.pack` (the reference link's, pymavlink's bytes: test_mavlink_codec.py): every datagram
    the same bytes, over random states (half turns among them: every branch of the quaternion),
    θ of every magnitude, pose-only and θ-only samples, sequence numbers wrapping past 255 and,
    signed, the signing timestamps."""
    rows = {}

    def row(n):
        if n not in rows:
            rng = np.random.default_rng(n)
            S = random_row(rng)
            if n % 11 == 0:
                S[layout.R] = np.diag([1.0, -1.0, -1.0] if n % 2 else [-1.0, -1.0, 1.0]).ravel()
            S[layout.XI] *= 10.0 ** rng.integers(-30, 30)
            rows[n] = S
        return rows[n]

    def theta_of(n, k):
        return float(np.random.default_rng(1000 * n + k).normal() * 10.0 ** (n % 60 - 30))

    new = _sent(True, world, key, 300, row, theta_of, receiver)
    ref = _sent(False, world, key, 300, row, theta_of, receiver)
    assert len(new[0]) == len(ref[0]) > 250
    assert new == ref


def test_pack_sample_frames_what_codec_frames():
    """The kernel alone against `codec.frame` over the cases a link does not reach: 0 to 58 θ,
    θ = 0 last (MAVLink 2 drops the payload's trailing zeros), any system id and sequence
    number; and a value beyond float32, which it refuses (-1) for the reference to raise."""
    from bridge.mavlink import codec
    from bridge.swarm.sample_wire import PACK_BYTES, pack_sample

    rng = np.random.default_rng(3)
    buf = np.zeros(PACK_BYTES, np.uint8)
    f32 = np.zeros(58, np.float32)
    ends = np.zeros(2, np.int64)
    for trial in range(300):
        nt = int(rng.integers(0, 59))
        sysid = int(rng.integers(1, 256))
        seq = int(rng.integers(0, 256))
        theta = rng.normal(size=max(nt, 1))
        if trial % 3 == 0 and nt:
            theta[nt - 1] = 0.0
        S = random_row(rng)
        peer = Peer(sysid, 191, Counters())
        peer.mav.seq = seq
        t = int(rng.integers(0, 1 << 50))
        want = [bytes(peer.pack(m)) for m in encode_sample(peer.mav, t // H_US, H_US, S,
                                                           list(theta[:nt]))]
        nf = pack_sample(buf, (t // H_US) * H_US, S, True, theta, nt, sysid, seq, 0, f32, ends)
        assert nf == len(want)
        assert buf[:ends[nf - 1]].tobytes() == b"".join(want)
        assert ends[0] == len(want[0])
    S = random_row(rng)
    S[layout.V.start] = 1e39
    assert pack_sample(buf, 0, S, True, np.zeros(1), 0, 1, 0, 0, f32, ends) == -1
    assert pack_sample(buf, 0, random_row(rng), True, np.array([-1e39]), 1, 1, 0, 0, f32,
                       ends) == -1
    with pytest.raises(Exception) as ref_exc:
        encode_sample(Peer(1, 191, Counters()).mav, 0, H_US, S, [])
    sc = scenario()
    link = AgentLink.from_scenario(sc, 2, compiled=True)
    try:
        with pytest.raises(type(ref_exc.value)):
            link.publish(0, S, {k: 0.0 for k in link.owned})
    finally:
        link.close()


def test_take_signed_is_accept_fields_and_commit_packet_by_packet():
    """`Peer.take_signed` against the reference (`accept_fields` then `commit`, packet after
    packet) on pairs of signed packets whose signing timestamps go forward, repeat, go back,
    come from a new stream a minute behind, or carry a wrong signature: it takes a pair exactly
    when the reference takes both packets, leaving the same windows and counts, and changes
    nothing when it does not."""
    import copy

    from bridge.swarm.agent_link import _TYPES

    rng = np.random.default_rng(11)
    taker, ref = Peer(2, 191, Counters(), key=KEY), Peer(2, 191, Counters(), key=KEY)
    sender = Peer(1, 191, Counters(), key=KEY)
    sg = sender.mav.signing
    taken = refused = 0
    T = sg.timestamp
    for i in range(400):
        T += 10
        before = copy.deepcopy((taker.mav.signing.stream_timestamps, taker.mav.signing.timestamp,
                                taker._last_seq, taker.counters.received))
        pkts = []
        for _ in range(2):
            r = rng.random()
            sg.timestamp = T + int(rng.integers(0, 3))
            if r < 0.15:
                sg.timestamp = T - int(rng.integers(1, 50))          # back in time
            elif r < 0.2:
                sg.timestamp = T - 7_000_000                         # a minute and more
            sg.link_id = int(rng.integers(2)) if rng.random() < 0.2 else 0
            p = bytearray(sender.pack(encode_sample(sender.mav, i, H_US, random_row(rng), [])[0]))
            if rng.random() < 0.05:
                p[-1] ^= 1                                           # signature broken
            pkts.append(bytes(p))
        data = b"".join(pkts)
        ends = [len(pkts[0]), len(data)]
        ok = taker.take_signed(data, ends, 1, 191)
        both = True
        for p in pkts:
            if ref.accept_fields(p, _TYPES) is None:
                both = False
                break
            ref.commit()
        if ok:
            taken += 1
            assert both
        else:
            refused += 1
            assert copy.deepcopy((taker.mav.signing.stream_timestamps, taker.mav.signing.timestamp,
                                  taker._last_seq, taker.counters.received)) == before
        # from the reference's state after each pair the two start alike again
        taker.mav.signing.stream_timestamps = dict(ref.mav.signing.stream_timestamps)
        taker.mav.signing.timestamp = ref.mav.signing.timestamp
        taker._last_seq = dict(ref._last_seq)
        if ok:
            assert taker.counters.received == ref.counters.received
        taker.counters.received = ref.counters.received
    assert taken > 100 and refused > 50


def test_age_rules_are_the_age_rule_of_each_neighbour():
    """`AgentLink.age_rules` (one compiled call over the drain's arrays) against `age_rule` per
    neighbour on a twin link fed the same samples: the same ages, verdicts and recorded age
    percentiles, the held θ copied, through no sample yet, fresh, hold, fail-safe, ages past the
    compiled histogram and a sample from the future (the receiver's step moved back)."""
    import time

    from bridge.swarm.agent_link import VERDICTS
    from bridge.swarm.sample_wire import AGE_BINS
    from controller.kernels import FRESH

    rng = np.random.default_rng(41)
    links, socks = [], []
    try:
        for _ in range(2):
            sc = parse_scenario(HIL + f"\n[network]\nbase_port = {free_base_port(6)}\n"
                                "max_age = 0.04\nhold = 0.02\n", name="ar", path="ar.toml")
            link = AgentLink.from_scenario(sc, 2, compiled=True)
            links.append(link)
            s = {}
            for j in link.neighbours:
                s[j] = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                s[j].bind(endpoint(sc, j))
            socks.append((sc, s))
        a, b = links
        assert a.held_values is not None and a.max_age_steps is not None
        nbs = [_Neighbour(a, j, np.random.default_rng(50 + j)) for j in a.neighbours]
        # received edges: (q, r, column) with r in a small rx of its own
        pairs = [(q, 13 + c) for q, j in enumerate(a.neighbours) for c in range(len(a.owned_by[j]))]
        index = [(q, r, col) for r, (q, col) in enumerate(pairs)]
        rx_index = tuple(np.array([x[i] for x in index], np.int64) for i in range(3))
        m = len(a.neighbours)
        verdict, mode, rx = np.zeros(m, np.int64), np.zeros(m, np.int64), np.zeros(len(index))
        sent = 0
        stamps = {j: None for j in a.neighbours}
        seen = set()
        n = 10
        for trial in range(80):
            n += int(rng.choice([1, 2, 5, 30, AGE_BINS]))
            for nb in nbs:
                if rng.random() < 0.5:
                    s = n - int(rng.choice([-2, 0, 1, 3, 9, 11, 13, 16, 40, AGE_BINS]))
                    if s < 0 or (stamps[nb.j] is not None and s <= stamps[nb.j]):
                        continue
                    data = nb.honest(s)
                    for link in links:
                        link.set_step(s + 1)
                    for sc, ss in socks:
                        ss[nb.j].sendto(data, endpoint(sc, 2))
                    sent += 1
                    stamps[nb.j] = s
            for link in links:
                end = time.monotonic() + 5.0
                while link.counters.datagrams < sent and time.monotonic() < end:
                    link.poll()
            if trial % 7 == 3 and any(x is not None for x in stamps.values()):
                n = max(x for x in stamps.values() if x is not None) - 50   # a step moved back
            for link in links:
                link.set_step(n)
            ages = a.age_rules(n, verdict, mode, rx, rx_index).tolist()
            for q, j in enumerate(a.neighbours):
                s, age, v = b.age_rule(j, n)
                assert (None if a.held_steps[q] < 0 else ages[q]) == age
                assert VERDICTS[verdict[q]] == v and (None if a.held_steps[q] < 0 else
                                                      int(a.held_steps[q])) == s
                assert mode[q] == (FRESH if v == "fresh" else FRESH + 1)
                seen.add(v)
                held = a.neighbour(j)
                for qq, r, col in index:
                    if qq == q and held is not None:
                        assert rx[r] == held.theta[a.owned_by[j][col - 13]]
        sa, sb = a.stats()["links"], b.stats()["links"]
        assert {j: (x["age_p50_steps"], x["age_p99_steps"]) for j, x in sa.items()} == \
            {j: (x["age_p50_steps"], x["age_p99_steps"]) for j, x in sb.items()}
        assert max(x["age_p99_steps"] for x in sa.values()) >= AGE_BINS - 1
        assert seen == set(VERDICTS)
    finally:
        for link in links:
            link.close()
        for _, s in socks:
            for x in s.values():
                x.close()
