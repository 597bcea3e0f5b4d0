"""The compiled state decoder of the vehicle link (bridge/mavlink/state_wire.py) against the
reference path (`MavlinkPlant.compiled_state = False`): the same datagrams from a vehicle, sent
to a plant of each kind, leave the same tracked state (every bit), the same counters and
refusals and the same sequence bookkeeping, over honest ODOMETRY and every kind of irregular
datagram the reference path refuses or treats specially. Plus the decoder against pymavlink.
The way back too: the compiled command (`state_wire.pack_command`, `MavlinkPlant.compiled_command`)
against pymavlink's bytes and against the plant's reference path, signed and not."""
from __future__ import annotations

import math
import select
import socket
import time

import numpy as np
import pytest

from bridge.mavlink.link import Counters, Peer, mavlink2
from bridge.mavlink.state_wire import (COMMAND_BYTES, ODOMETRY_SIZE, pack_command, recv_state,
                                       scan_odometry)
from _bridge import free_base_port, load
from _net import wait_queued
from bridge.mavlink.sequence import seq_last, seq_step

M = mavlink2
NAN21 = [math.nan] + [0.0] * 20
H_US = 4000

pytestmark = pytest.mark.timeout(120)


def _odometry(peer, t_us, rng, *, q=None, frame=M.MAV_FRAME_LOCAL_NED,
              child=M.MAV_FRAME_BODY_FRD, nan=False):
    q = rng.normal(size=4) if q is None else np.asarray(q, float)
    q = (q / np.linalg.norm(q)).tolist()
    p = rng.normal(size=3) * 5
    if nan:
        p[int(rng.integers(3))] = math.nan
    v, w = rng.normal(size=3), rng.normal(size=3)
    return bytes(peer.pack(peer.mav.odometry_encode(int(t_us), frame, child, *p.tolist(), q,
                                                    *v.tolist(), *w.tolist(), NAN21, NAN21, 0, 1,
                                                    100)))


class _Vehicle:
    """Vehicle 1's datagrams: honest ones (a step apart) and every irregular kind."""

    def __init__(self, rng, key=None):
        self.rng = rng
        self.key = key
        self.peer = Peer(1, 1, Counters(), key=key)
        self.t0 = int(time.time() * 1e6)
        self.last = None

    def honest(self, n):
        self.last = _odometry(self.peer, self.t0 + n * H_US, self.rng)
        return self.last

    def irregular(self, n):
        rng, t = self.rng, self.t0 + n * H_US
        kind = int(rng.integers(15))
        if kind == 0:                                  # the same datagram again
            return self.last or self.honest(n)
        if kind == 1:                                  # an older state
            return _odometry(self.peer, t - int(rng.integers(1, 4)) * H_US, rng)
        if kind == 2:                                  # far back (a reboot, if in a run)
            return _odometry(self.peer, t - 20_000_000, rng)
        if kind == 3:                                  # far in the future
            return _odometry(self.peer, t + 5_000_000, rng)
        if kind == 4:                                  # NaN
            return _odometry(self.peer, t, rng, nan=True)
        if kind == 5:                                  # |q| − 1 just inside / outside 1e-3
            q = rng.normal(size=4)
            q *= (1.0 + float(rng.choice([0.999e-3, 1.001e-3, 1e-3, 2e-3, -1.001e-3]))) \
                / np.linalg.norm(q)
            m = self.peer.mav.odometry_encode(t, M.MAV_FRAME_LOCAL_NED, M.MAV_FRAME_BODY_FRD,
                                              1, 2, 3, q.tolist(), 0, 0, 0, 0, 0, 0, NAN21,
                                              NAN21, 0, 1, 100)
            return bytes(self.peer.pack(m))
        if kind == 6:                                  # the FRD world (taken as it is)
            return _odometry(self.peer, t, rng, frame=M.MAV_FRAME_LOCAL_FRD)
        if kind == 7:                                  # velocity in the world frame (rotated)
            return _odometry(self.peer, t, rng, child=M.MAV_FRAME_LOCAL_NED)
        if kind == 8:                                  # a frame it does not handle
            return _odometry(self.peer, t, rng, frame=M.MAV_FRAME_BODY_FRD)
        if kind == 9:                                  # a bit flipped
            d = bytearray(_odometry(self.peer, t, rng))
            d[int(rng.integers(1, len(d)))] ^= 1 << int(rng.integers(8))
            return bytes(d)
        if kind == 10:                                 # truncated, or with junk after it
            d = _odometry(self.peer, t, rng)
            return d[:int(rng.integers(1, len(d)))] if rng.random() < 0.5 else d + b"\xfd"
        if kind == 11:                                 # two states in one datagram
            return _odometry(self.peer, t, rng) + _odometry(self.peer, t + 1, rng)
        if kind == 12:                                 # another system, or another component
            other = Peer(int(rng.choice([2, 99])) if rng.random() < 0.5 else 1, 2, Counters())
            return _odometry(other, t, rng)
        if kind == 13:                                 # signed with another key, or not at all
            signer = Peer(1, 1, Counters(), key=bytes(32) if self.key is None or
                          rng.random() < 0.5 else None)
            return _odometry(signer, t, rng)
        return bytes(self.peer.pack(self.peer.mav.heartbeat_encode(2, 0, 0, 0, 4)))


def _state(plant):
    v = plant.vehicles[0]
    tr = v.tracker
    sig = v.peer.mav.signing
    return (plant.wire.tobytes(), tr.wire.tobytes(), tr.time_usec, tr.n_states, tr.n_odometry,
            tr.have, tr.duplicates, tr.reboots, tr.source, plant.counters.as_dict(),
            v.peer.sequences(), v.src is None, v.connected, sum(plant.lat_hist),
            (dict(sig.stream_timestamps), sig.timestamp) if plant.key is not None else None)


KEY = bytes(range(5, 37))


@pytest.mark.parametrize("key", [None, KEY])
def test_compiled_state_path_equals_the_reference(key):
    from bridge.mavlink.plant import MavlinkPlant

    rng = np.random.default_rng(3)
    plants, tx = [], []
    try:
        for compiled in (True, False):
            port = free_base_port(6)
            sc = load([f"bridge.base_port={port}", "bridge.stale_after=1000"])
            p = MavlinkPlant(sc, connect_timeout=1, on_event=lambda s: None, key=key)
            p.compiled_state = compiled
            plants.append(p)
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.bind(("127.0.0.1", 0))
            tx.append((s, ("127.0.0.1", port)))
        veh = _Vehicle(rng, key)
        sent = 0
        for n in range(400):
            # one datagram, or a few before the next poll (read in one batch)
            for _ in range(1 if rng.random() < 0.6 else int(rng.integers(2, 5))):
                data = veh.honest(n) if rng.random() < 0.5 else veh.irregular(n)
                for s, addr in tx:
                    s.sendto(data, addr)
                sent += 1
            for p in plants:
                end = time.monotonic() + 5.0
                while p.counters.datagrams < sent and time.monotonic() < end:
                    p.poll(0.01)
            assert _state(plants[0]) == _state(plants[1]), n
        comp, ref = plants
        assert comp.scanned_states > 150 and ref.scanned_states == 0
        assert comp.read_compiled > 150 and ref.read_compiled == 0
        # without a key the states were taken whole in compiled code (`take_states`), but for
        # the first and the ones the reference path decided
        assert (comp.taken_states > 100) if key is None else comp.taken_states == 0
        assert ref.taken_states == 0
        st = ref.counters.as_dict()
        assert st["malformed"] > 0 and {"out_of_order", "future", "nan", "non_unit_quaternion",
                                        "bad_frame", "wrong_system"} <= set(st["rejected_by_reason"])
        assert ref.vehicles[0].tracker.duplicates > 0 or key is not None
        if key is not None:
            assert {"replay", "unsigned", "bad_signature"} <= set(st["rejected_by_reason"])
    finally:
        for p in plants:
            p.close()
        for s, _ in tx:
            s.close()


@pytest.mark.parametrize("frame", [M.MAV_FRAME_LOCAL_NED, M.MAV_FRAME_LOCAL_FRD])
def test_decoder_reads_what_pymavlink_reads(frame):
    """Random states: the decoder's row is pymavlink's decoded fields (float32 widened)."""
    rng = np.random.default_rng(frame)
    peer = Peer(7, 1, Counters())
    dec = mavlink2.MAVLink(None)
    scratch, out, meta = np.zeros(ODOMETRY_SIZE, np.uint8), np.zeros(13), np.zeros(6, np.int64)
    for trial in range(200):
        t = int(rng.integers(0, 1 << 62))
        data = _odometry(peer, t, rng, frame=frame)
        assert scan_odometry(np.frombuffer(data, np.uint8), len(data), 0, scratch, out, meta) == 1
        m = dec.decode(bytearray(data))
        want = [m.x, m.y, m.z, *m.q, m.rollspeed, m.pitchspeed, m.yawspeed, m.vx, m.vy, m.vz]
        assert out.tolist() == want
        assert meta[:5].tolist() == [m.get_seq(), 7, 1, m.time_usec, frame]


def test_state_rows_are_wire_to_state_bits():
    """The compiled rows (`MavlinkPlant.read` in a NED world) against `wire_to_state`, bit for
    bit, on float32 wire rows with quaternions off unit length by up to the tolerance."""
    from bridge.mavlink.state_wire import wire_to_state_ned
    from bridge.mavlink.transport import wire_to_state

    rng = np.random.default_rng(11)
    for n in (1, 2, 7):
        for _ in range(100):
            wire = rng.normal(size=(n, 13)) * 10.0 ** rng.integers(-3, 4)
            q = rng.normal(size=(n, 4))
            wire[:, 3:7] = q / np.linalg.norm(q, axis=1)[:, None] * (1 + rng.uniform(-1e-3, 1e-3, (n, 1)))
            wire = wire.astype(np.float32).astype(np.float64)
            S = np.empty((n, 18))
            wire_to_state_ned(wire, S)
            assert S.tobytes() == wire_to_state(wire, "ned").tobytes()


def test_recv_state_reads_what_the_socket_holds():
    """The compiled read of a connected socket: every datagram whole, in order, its length in
    meta[5]; the common case scanned (`scan_odometry`'s row), the rest handed on; the empty
    socket (0) and an ICMP error the socket reported (−2, and the next read goes on)."""
    rng = np.random.default_rng(43)
    veh = _Vehicle(rng)
    a, b = (socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(2))
    try:
        for s in (a, b):
            s.bind(("127.0.0.1", 0))
        a.connect(b.getsockname())
        b.connect(a.getsockname())
        b.setblocking(False)
        buf, scratch = np.zeros(1 << 16, np.uint8), np.zeros(ODOMETRY_SIZE, np.uint8)
        out, meta = np.zeros(13), np.zeros(6, np.int64)
        out2, meta2 = np.zeros(13), np.zeros(6, np.int64)
        sent = [veh.honest(n) if n % 2 else veh.irregular(n) for n in range(60)] + [b""]
        for d in sent:
            a.send(d)
        wait_queued(b, [len(d) for d in sent])
        for d in sent:
            r = recv_state(b.fileno(), buf, 0, scratch, out, meta)
            want = scan_odometry(np.frombuffer(d, np.uint8), len(d), 0, scratch, out2, meta2)
            assert r == (1 if want else 2) and meta[5] == len(d) and bytes(buf[:len(d)]) == d
            if want:
                assert out.tobytes() == out2.tobytes() and (meta[:5] == meta2[:5]).all()
        assert recv_state(b.fileno(), buf, 0, scratch, out, meta) == 0
        # a datagram to a port nobody holds: the ICMP error comes back on b's next read
        dead = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        dead.bind(("127.0.0.1", 0))
        gone = dead.getsockname()
        dead.close()
        b.connect(gone)
        b.send(b"x")
        select.select([b], [], [], 10.0)    # the error makes it readable
        assert recv_state(b.fileno(), buf, 0, scratch, out, meta) == -2
        assert recv_state(b.fileno(), buf, 0, scratch, out, meta) == 0
        assert recv_state(-1, buf, 0, scratch, out, meta) == -1      # EBADF: stop
    finally:
        a.close()
        b.close()


def _tracker_state(tr, peer):
    return (tr.clock.tobytes(), tr.stamp.tobytes(), tr.stamped, tr.wire.tobytes(), tr.n_states,
            tr.n_odometry, tr.have, tr.source, tr.duplicates, tr.reboots, tr._back, tr.t_arrival,
            peer.counters.as_dict(), peer.sequences(), peer.last_signed)


def test_take_states_equals_the_trackers_checks():
    """`take_states` (a real-time vehicle's states taken whole in compiled code) against the
    reference path (`Peer.accepted`, `StateTracker.on_odometry_row`, `Peer.commit`) on the same
    datagrams at the same wall times: after every batch the same clock, stamp, wire row and
    counts, bit for bit. The datagrams stream at 250 Hz with late arrivals (stale), repeats,
    older states, states far in the future, reboots (runs far back), lost sequence numbers,
    pauses that roll the offset's window once or twice, and datagrams of other kinds."""
    from bridge.mavlink.state import StateTracker
    from bridge.mavlink.state_wire import (T_DROPPED, T_TAKEN, TAKE_FULL, TAKE_OTHER,
                                           TAKE_SCANNED, TAKE_SLOTS, TAKE_STOP, take_states)

    rng = np.random.default_rng(59)
    veh = _Vehicle(rng)
    a, b = (socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(2))
    sides = []
    for _ in range(2):
        c = Counters()
        sides.append((StateTracker(c, stale_after=0.05), Peer(255, 190, c)))
    (tr_c, peer_c), (tr_r, peer_r) = sides
    seqs = peer_c.sequence_array([(1, 1)])
    buf, scratch = np.zeros(1 << 16, np.uint8), np.zeros(ODOMETRY_SIZE, np.uint8)
    out, meta, tot = np.zeros(13), np.zeros(6, np.int64), np.zeros(TAKE_SLOTS, np.int64)
    ends = dict.fromkeys(("taken", "scanned", "other", "full"), 0)

    def reference(tr, peer, data, now):
        if not scan_odometry(np.frombuffer(data, np.uint8), len(data), 0, scratch, out, meta):
            return              # not a state the row path takes: both sides' glue skips it
        seq, sysid, compid, t_us, _, _ = meta.tolist()
        m0 = peer.counters.mark()
        if peer.accepted(data, seq, sysid, compid):
            tr.on_odometry_row(out, t_us, now)
            if peer.counters.arrived_since(m0):     # taken, or refused as old: it came
                peer.commit()

    try:
        for s in (a, b):
            s.bind(("127.0.0.1", 0))
        a.connect(b.getsockname())
        b.connect(a.getsockname())
        b.setblocking(False)
        t_v, now = veh.t0, 5000.0       # the vehicle's clock (µs) and ours (s)
        for n in range(1500):
            t_v += H_US
            now += H_US * 1e-6 + float(rng.uniform(0, 3e-4))
            kind = int(rng.integers(40))
            if kind == 0:                            # a pause: one window rolls, or two
                gap = float(rng.choice([1.2, 2.5]))
                t_v += int(gap * 1e6)
                now += gap
            batch = [_odometry(veh.peer, t_v, rng)]
            t = now
            if kind == 1:                            # late: stale against the offset
                t += float(rng.uniform(0.06, 0.3))
            elif kind == 2:
                batch.append(batch[0])               # the same datagram again
            elif kind == 3:                          # an older state
                batch.append(_odometry(veh.peer, t_v - 2 * H_US, rng))
            elif kind == 4:                          # in the future, beyond the bound
                ahead = int(rng.choice([1_500_000, 5_000_000]))
                batch.insert(0, _odometry(veh.peer, t_v + ahead, rng))
            elif kind == 5:                          # a reboot: states far back, newer each
                t_v -= 20_000_000
                batch = [_odometry(veh.peer, t_v + k * H_US, rng) for k in range(4)]
                t_v += 3 * H_US
            elif kind == 6:                          # lost sequence numbers
                veh.peer.mav.seq = (veh.peer.mav.seq + int(rng.integers(1, 5))) & 0xFF
            elif kind == 7:                          # another kind of datagram
                batch.append(veh.irregular(n))
            for d in batch:
                a.send(d)
            time.sleep(0.0005)
            # compiled, with the plant's glue (`MavlinkPlant._take_states`)
            tot[:] = 0
            while True:
                compid = 1 if tr_c.n_odometry and tr_c.stamped else -1
                r = take_states(b.fileno(), buf, scratch, out, meta, 1, compid, 3, t,
                                tr_c.stale_after * 1e6, tr_c.clock, tr_c.stamp, seqs, tr_c.wire,
                                tot)
                if tot[T_TAKEN]:
                    ends["taken"] += int(tot[T_TAKEN])
                    peer_c.took_counted(int(tot[T_TAKEN]), int(tot[T_DROPPED]))
                    tr_c.took(int(tot[T_TAKEN]), t)
                    tot[T_TAKEN] = tot[T_DROPPED] = 0
                if r == TAKE_STOP:
                    break
                if r == TAKE_FULL:
                    ends["full"] += 1
                    tot[:] = 0
                    continue
                ends["scanned" if r == TAKE_SCANNED else "other"] += 1
                assert r in (TAKE_SCANNED, TAKE_OTHER)
                reference(tr_c, peer_c, bytes(buf[:meta[5]]), t)
            for d in batch:
                reference(tr_r, peer_r, d, t)
            assert _tracker_state(tr_c, peer_c) == _tracker_state(tr_r, peer_r), n
        rej = peer_r.counters.as_dict()["rejected_by_reason"]
        assert {"stale", "future", "out_of_order"} <= set(rej), rej
        assert tr_r.reboots >= 3 and tr_r.duplicates > 10 and peer_r.counters.dropped > 10
        assert ends["taken"] > 1000 and min(ends.values()) > 0, ends
    finally:
        a.close()
        b.close()


def test_counts_taken_in_compiled_code_stay_one_set():
    """The peer's sequence numbers kept in an array (`Peer.sequence_array`) move with `commit`
    as compiled code moves them; a second array would split them, and is refused. What compiled
    code counted is recorded by `took_counted`, which only an unsigned link without a tlog has."""
    from controller.errors import Se3SyncError

    c = Counters()
    peer = Peer(255, 190, c)
    src = Peer(1, 1, Counters())

    def take(seq):
        src.mav.seq = seq
        d = bytes(src.pack(src.mav.heartbeat_encode(2, 0, 0, 0, 4)))
        assert peer.accepted(d, d[4], 1, 1)
        peer.commit()

    take(10)
    take(11)
    seqs = peer.sequence_array([(1, 1)])
    assert seq_last(int(seqs[0])) == 11 and peer.sequences() == {(1, 1): 11}
    seqs[0], lost = seq_step(int(seqs[0]), 14)   # compiled code took 14: 12 and 13 lost
    assert lost == 2
    peer.took_counted(1, lost)
    assert (c.received, c.dropped) == (3, 2) and peer.sequences() == {(1, 1): 14}
    take(17)                     # counted against the array's 14: 15 and 16 lost
    assert seq_last(int(seqs[0])) == 17 and (c.received, c.dropped) == (4, 4)
    take(15)                     # late, not lost after all
    assert seq_last(int(seqs[0])) == 17 and (c.received, c.dropped) == (5, 3)
    with pytest.raises(Se3SyncError, match="keeps an array already"):
        peer.sequence_array([(2, 1)])
    with pytest.raises(Se3SyncError, match="without a key"):
        Peer(255, 190, Counters(), key=KEY).took_counted(1, 0)


@pytest.mark.parametrize("signed", [False, True])
def test_pack_command_is_pymavlinks_bytes(signed):
    """Random controls, times, ids and sequence numbers (zeros at the end dropped as MAVLink 2
    drops them, NaN and ±0 kept, a value beyond float32 refused): pymavlink's bytes."""
    from bridge.mavlink import codec

    rng = np.random.default_rng(47)
    key = bytes(range(32))
    mine, theirs = mavlink2.MAVLink(None, 255, 190), mavlink2.MAVLink(None, 255, 190)
    if signed:
        for mav in (mine, theirs):
            codec.setup_signing(mav, key, link_id=3, initial_timestamp=123456)
    buf, f32 = np.zeros(COMMAND_BYTES, np.uint8), np.zeros(8, np.float32)
    for trial in range(500):
        c = (rng.uniform(-1, 1, 6) * 10.0 ** rng.integers(-40, 39)).tolist()
        if trial % 5 == 0:
            c[int(rng.integers(6))] = float(rng.choice([0.0, -0.0, np.nan, 3.4e38]))
        t = int(rng.integers(0, 1 << 63))
        g, ts, tc = (int(x) for x in rng.choice([0, 1, 7, 255], 3))
        mine.seq = theirs.seq = int(rng.integers(256))
        mine.srcSystem = theirs.srcSystem = int(rng.integers(1, 256))
        want = bytes(mavlink2.MAVLink_set_actuator_control_target_message(
            t, g, ts, tc, c + [0.0, 0.0]).pack(theirs))
        n = pack_command(buf, t, *c, g, ts, tc, mine.seq, mine.srcSystem, 190, int(signed), f32)
        if signed:
            codec.sign_frame(mine, buf, 0, n)
        assert bytes(buf[:n]) == want, trial
    assert pack_command(buf, 0, 1e39, 0.0, 0.0, 0.0, 0.0, 0.0, 0, 1, 1, 0, 1, 1, 0, f32) == -1


@pytest.mark.parametrize("key", [None, KEY])
def test_compiled_command_path_equals_the_reference(key, monkeypatch):
    """The plant's commands (real time) framed and sent by compiled code, against `Peer.pack`
    and the socket's send: at the vehicle, the same datagrams byte for byte (one clock for
    both, one signing timestamp), and the same counters."""
    from bridge.mavlink import output
    from bridge.mavlink.plant import MavlinkPlant

    class _Clock:
        t = 1.8e9

        def time(self):
            return self.t

    clock = _Clock()
    monkeypatch.setattr(output, "time", clock)
    rng = np.random.default_rng(53)
    plants, tx = [], []
    try:
        for compiled in (True, False):
            port = free_base_port(6)
            sc = load([f"bridge.base_port={port}", "bridge.stale_after=1000"])
            p = MavlinkPlant(sc, connect_timeout=1, on_event=lambda s: None, key=key)
            p.compiled_command = compiled
            p.warm_up()
            plants.append(p)
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.bind(("127.0.0.1", 0))
            s.settimeout(5.0)
            tx.append((s, ("127.0.0.1", port)))
        veh = _Vehicle(rng, key)
        for n in range(3):              # the vehicle's address (and its source socket)
            data = veh.honest(n)
            for (s, addr), p in zip(tx, plants):
                s.sendto(data, addr)
                end = time.monotonic() + 5.0
                while p.counters.datagrams < n + 1 and time.monotonic() < end:
                    p.poll(0.01)
        assert all(p.vehicles[0].src is not None for p in plants)
        n_u = plants[0].n
        for k in range(80):
            u = rng.normal(size=(n_u, 6)) * 10.0 ** rng.integers(-2, 3)
            clock.t += 0.004 + rng.uniform(0, 1e-3)
            got = []
            for (s, _), p in zip(tx, plants):
                if key is not None:
                    p.vehicles[0].peer.mav.signing.timestamp = 10_000 + k
                p.apply(u.copy())
                got.append(s.recv(4096))
                p.k += 1
                p._S = None
            assert got[0] == got[1], k
            m = mavlink2.MAVLink(None)
            if key is not None:
                m.signing.secret_key = key
            msg = m.parse_char(bytearray(got[0]))
            assert msg is not None and msg.get_type() == "SET_ACTUATOR_CONTROL_TARGET"
            assert msg.time_usec == int(clock.t * 1e6)
        comp, ref = plants
        assert comp.packed_commands == 80 and ref.packed_commands == 0
        assert comp.counters.as_dict() == ref.counters.as_dict()
        assert comp.vehicles[0].peer.mav.seq == ref.vehicles[0].peer.mav.seq
    finally:
        for p in plants:
            p.close()
        for s, _ in tx:
            s.close()


@pytest.mark.parametrize("key", [None, KEY])
@pytest.mark.parametrize("world,gc", [("ned", False), ("enu", True), ("ned", True),
                                      ("enu", False)])
def test_one_vehicles_command_in_one_call_equals_the_reference(world, gc, key, monkeypatch):
    """An agent's plant (one vehicle, direct mapping): unsigned, its command is mapped, framed
    and sent by one compiled call (`state_wire.command_row`); signed, by `pack_command` and a
    signature. Against the reference (`Transport.controls_row`, `Peer.pack`, the socket's send),
    over wrenches that saturate, carry NaN, ±inf and −0.0, in either world frame, with gravity
    compensation or without: the same datagrams at the vehicle byte for byte, the same controls
    (every bit) and the same counters of the link, the transport and the mapping."""
    import dataclasses

    from bridge.mavlink import output
    from bridge.mavlink.plant import MavlinkPlant
    from cosim.scenario import restrict

    class _Clock:
        t = 1.8e9

        def time(self):
            return self.t

    clock = _Clock()
    monkeypatch.setattr(output, "time", clock)
    rng = np.random.default_rng(59)
    plants, tx = [], []
    try:
        for compiled in (True, False):
            port = free_base_port(6)
            sc = load([f"bridge.base_port={port}", "bridge.stale_after=1000",
                       f"bridge.world_frame={world}", f"bridge.gravity_compensation={str(gc).lower()}"])
            one, _ = restrict(sc, [1])
            cfg = dataclasses.replace(sc.bridge, n_agents=1, vehicles=[sc.bridge.vehicles[0]])
            p = MavlinkPlant(one, cfg, connect_timeout=1, on_event=lambda s: None, key=key)
            p.compiled_command = compiled
            p.warm_up()
            plants.append(p)
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.bind(("127.0.0.1", 0))
            s.settimeout(5.0)
            tx.append((s, ("127.0.0.1", port)))
        assert (plants[0]._fused_command() is None) == (key is not None)
        veh = _Vehicle(rng, key)
        for n in range(3):              # the vehicle's address (and its source socket)
            data = veh.honest(n)
            for (s, addr), p in zip(tx, plants):
                s.sendto(data, addr)
                end = time.monotonic() + 5.0
                while p.counters.datagrams < n + 1 and time.monotonic() < end:
                    p.poll(0.01)
        assert all(p.vehicles[0].src is not None for p in plants)
        mw = np.asarray(plants[0].transport.mapping.max_wrench[0])
        for k in range(200):
            u = rng.normal(size=(1, 6)) * mw * rng.choice([0.3, 1.0, 3.0])
            if k % 9 == 0:
                u[0, int(rng.integers(6))] = float(rng.choice([np.nan, np.inf, -np.inf, -0.0]))
            clock.t += 0.004 + rng.uniform(0, 1e-3)
            got = []
            for (s, _), p in zip(tx, plants):
                if key is not None:
                    p.vehicles[0].peer.mav.signing.timestamp = 10_000 + k
                p.apply(u.copy())
                got.append(s.recv(4096))
                p.k += 1
                p._S = None
            assert got[0] == got[1], k
            assert plants[0]._controls.tobytes() == plants[1]._controls.tobytes(), k
        comp, ref = plants
        assert comp.packed_commands == 200 and ref.packed_commands == 0
        assert comp.counters.as_dict() == ref.counters.as_dict()
        assert comp.vehicles[0].peer.mav.seq == ref.vehicles[0].peer.mav.seq
        tc, tr = comp.transport, ref.transport
        assert tc.nan_commands == tr.nan_commands > 0
        assert tc.mapping.saturations == tr.mapping.saturations > 0
        assert tc.mapping.saturated_vehicles.tolist() == tr.mapping.saturated_vehicles.tolist()
        assert tc.mapping.last_saturated.tolist() == tr.mapping.last_saturated.tolist()
    finally:
        for p in plants:
            p.close()
        for s, _ in tx:
            s.close()


@pytest.mark.parametrize("name", sorted(__import__("bridge.mavlink.output", fromlist=["x"])
                                        .PROFILE_CLASSES))
def test_every_profiles_compiled_form_is_its_message(name):
    """Every output profile: where it has a compiled form (`compiled_fields`), the frame
    `pack_command` makes of it is `Peer.pack` of its `message`, byte for byte (lockstep stamps,
    so that both read one time); where it has none, it says so (None)."""
    from bridge.mavlink import output

    rng = np.random.default_rng(59)
    prof = output.profile(name, h=0.004, J=np.diag([0.02, 0.02, 0.04]),
                          max_wrench=np.array([1.0, 1.0, 1.0, 20.0, 20.0, 20.0]), group_mlx=2)
    peer = Peer(255, 191, Counters())
    buf, f32 = np.zeros(COMMAND_BYTES, np.uint8), np.zeros(8, np.float32)
    wire = np.array([0, 0, 0, 1, 0, 0, 0, 0, 0, 0, 0, 0, 0], float)
    for k in range(50):
        c = rng.uniform(-1, 1, 6)
        f = prof.compiled_fields(c, target=3, k=k, lockstep=True)
        want = bytes(peer.pack(prof.message(peer.mav, c, target=3, k=k, lockstep=True,
                                            wire=wire)))
        if f is None:
            assert name != "actuator_control_target"
            continue
        n = pack_command(buf, *f, (peer.mav.seq - 1) & 0xFF, 255, 191, 0, f32)
        assert bytes(buf[:n]) == want, k
