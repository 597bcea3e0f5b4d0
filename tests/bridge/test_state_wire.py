"""The compiled state decoder of the vehicle link (bridge/mavlink/state_wire.py) against the
reference path (`MavlinkPlant.compiled_state = False`): the same datagrams from a vehicle, sent
to a plant of each kind, leave the same tracked state (every bit), the same counters and
refusals and the same sequence bookkeeping, over honest ODOMETRY and every kind of irregular
datagram the reference path refuses or treats specially. Plus the decoder against pymavlink."""
from __future__ import annotations

import math
import socket
import time

import numpy as np
import pytest

from bridge.mavlink.link import Counters, Peer, mavlink2
from bridge.mavlink.state_wire import ODOMETRY_SIZE, scan_odometry
from _bridge import free_base_port, load

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
    scratch, out, meta = np.zeros(ODOMETRY_SIZE, np.uint8), np.zeros(13), np.zeros(5, np.int64)
    for trial in range(200):
        t = int(rng.integers(0, 1 << 62))
        data = _odometry(peer, t, rng, frame=frame)
        assert scan_odometry(np.frombuffer(data, np.uint8), len(data), 0, scratch, out, meta) == 1
        m = dec.decode(bytearray(data))
        want = [m.x, m.y, m.z, *m.q, m.rollspeed, m.pitchspeed, m.yawspeed, m.vx, m.vy, m.vz]
        assert out.tolist() == want
        assert meta.tolist() == [m.get_seq(), 7, 1, m.time_usec, frame]


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
