"""Untrusted network input: MAVLink 2 signing (unsigned, wrong-key, replayed and tampered
commands are rejected and counted) and 10,000 random/truncated datagrams (no crash, every one
counted)."""
from __future__ import annotations

import os
import random
import socket
import struct
import time

import numpy as np
import pytest

os.environ.setdefault("MAVLINK20", "1")

from bridge.mavlink.link import Counters, Peer, mavlink2  # noqa: E402
from _bridge import VehicleThread, bound_udp, free_base_port, load  # noqa: E402

KEY = bytes(range(100, 132))
WRONG = bytes(32)


def _wait(pred, timeout=10.0):
    t = time.monotonic() + timeout
    while time.monotonic() < t:
        if pred():
            return True
        time.sleep(0.01)
    return pred()


def _listen(s):
    """``s``: bound to the vehicle's target port (`bound_udp`) before the vehicle started
    (60 s: a guard against a vehicle that never talks, not a deadline for a slow start)."""
    s.settimeout(60.0)
    _, addr = s.recvfrom(65535)  # the vehicle talks first (udpout to our port)
    return s, addr


def _command(peer, t_us, value=0.1):
    return peer.pack(peer.mav.set_actuator_control_target_encode(t_us, 0, 1, 1, [value] * 6 + [0, 0]))


def _fix_crc(pkt: bytearray) -> bytearray:
    from pymavlink.generator.mavcrc import x25crc

    plen = pkt[1]
    msgid = pkt[7] | (pkt[8] << 8) | (pkt[9] << 16)
    crc = x25crc(bytes(pkt[1:10 + plen]))
    crc.accumulate(struct.pack("B", mavlink2.mavlink_map[msgid].crc_extra))
    pkt[10 + plen:12 + plen] = struct.pack("<H", crc.crc)
    return pkt


@pytest.mark.realtime
def test_signing_rejects_unsigned_wrong_key_replayed_tampered(tmp_path):
    key_file = tmp_path / "key.hex"
    key_file.write_text(KEY.hex() + "\n")
    from bridge.mavlink.config import read_key_file

    lis, port = bound_udp()
    with VehicleThread(count=1, base_port=port, key=read_key_file(key_file), rate=100, aux_rate=0,
                       command_timeout=10.0) as srv:
        sock, addr = _listen(lis)
        good = Peer(255, 191, Counters(), key=KEY, link_id=1)   # link id = the vehicle's system id
        t = int(time.time() * 1e6)
        legit = _command(good, t)
        sock.sendto(legit, addr)
        assert _wait(lambda: srv.vehicles[0].commands == 1)
        sock.sendto(_command(Peer(255, 191, Counters()), t + 10), addr)                 # unsigned
        sock.sendto(_command(Peer(255, 191, Counters(), key=WRONG, link_id=1), t + 20), addr)  # wrong key
        sock.sendto(legit, addr)                                                       # replayed
        tampered = bytearray(_command(good, t + 30))
        tampered[14] ^= 0x40                                                           # a control value
        sock.sendto(bytes(_fix_crc(tampered)), addr)                                   # CRC valid, signature not
        assert _wait(lambda: sum(srv.counters.rejected.values()) >= 4)
        time.sleep(0.05)
        assert dict(srv.counters.rejected) == {"unsigned": 1, "bad_signature": 2, "replay": 1}
        assert srv.counters.malformed == 0
        # the stream is not locked out by the forgeries: the next genuine command is accepted
        sock.sendto(_command(good, t + 40, value=0.2), addr)
        assert _wait(lambda: srv.vehicles[0].commands == 2)
        assert np.allclose(srv.vehicles[0].controls, np.float32(0.2))
        # the vehicle signs what it sends
        sock.settimeout(2.0)
        data, _ = sock.recvfrom(65535)
        assert data[2] & 0x01
        sock.close()


def test_unsigned_heartbeat_option():
    tx = Peer(1, 1, Counters())
    hb = tx.pack(tx.mav.heartbeat_encode(13, 0, 0, 0, 4))
    cmd = _command(tx, 1)
    strict, lax = Counters(), Counters()
    assert Peer(255, 191, strict, key=KEY).accept(hb) is None and strict.rejected["unsigned"] == 1
    p = Peer(255, 191, lax, key=KEY, allow_unsigned_heartbeat=True)
    assert p.accept(hb).get_type() == "HEARTBEAT"
    assert p.accept(cmd) is None and lax.rejected["unsigned"] == 1


@pytest.mark.realtime
def test_signed_lockstep_hil_runs():
    from bridge.mavlink.plant import MavlinkPlant
    from cosim.master import make_controller

    port = free_base_port(6)
    sc = load([f"bridge.base_port={port}"])
    with VehicleThread(scenario=sc, lockstep=True, key=KEY, aux_rate=0) as srv:
        p = MavlinkPlant(sc, lockstep=True, key=KEY, connect_timeout=10, on_event=lambda s: None).connect()
        try:
            c = make_controller("hybrid", sc)
            for _ in range(50):
                u, _ = c.step_state(p.read(), sc.step)
                p.apply(u)
                p.advance(sc.step)
            st = p.stats()
        finally:
            p.close()
        assert st["rejected"] == 0 and srv.counters.as_dict()["rejected"] == 0
        assert srv.vehicles[0].k == 50


def _fuzz_datagrams(n, rng, valid):
    out = []
    for i in range(n):
        if i % 2 == 0:
            ln = rng.randrange(0, 300)
            d = bytes(rng.getrandbits(8) for _ in range(ln))
            if i % 10 == 0 and d:
                d = b"\xfd" + d[1:]           # plausible magic, garbage after
        else:
            v = valid[rng.randrange(len(valid))]
            d = v[:rng.randrange(0, len(v))]  # truncated (possibly empty)
        out.append(d)
    return out


@pytest.mark.realtime
@pytest.mark.timeout(120)
def test_10000_random_and_truncated_datagrams(tmp_path):
    rng = random.Random(5)
    tx = Peer(255, 191, Counters())
    valid = [_command(tx, 10 + i) for i in range(20)] + \
            [tx.pack(tx.mav.command_long_encode(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0))]
    lis, port = bound_udp()
    with VehicleThread(count=1, base_port=port, rate=100, aux_rate=0) as srv:
        sock, addr = _listen(lis)
        data = _fuzz_datagrams(10_000, rng, valid)
        for i in range(0, len(data), 100):
            for d in data[i:i + 100]:
                sock.sendto(d, addr)
            time.sleep(0.004)  # stay within the socket buffer: kernel drops would not be counted
        c = srv.counters
        assert _wait(lambda: c.datagrams >= 10_000, 30), c.as_dict()
        time.sleep(0.1)
        assert c.datagrams == 10_000
        assert c.malformed + sum(c.rejected.values()) == 10_000, c.as_dict()
        assert c.received == 0 and srv.vehicles[0].commands == 0
        # still alive and serving
        sock.sendto(valid[0], addr)
        assert _wait(lambda: srv.vehicles[0].commands == 1)
        sock.close()


@pytest.mark.realtime
def test_bridge_side_survives_garbage():
    from bridge.mavlink.plant import MavlinkPlant

    port = free_base_port(6)
    sc = load([f"bridge.base_port={port}"])
    p = MavlinkPlant(sc, connect_timeout=1, on_event=lambda s: None)
    rng = random.Random(9)
    tx = Peer(1, 1, Counters())
    valid = [tx.pack(tx.mav.heartbeat_encode(13, 0, 0, 0, 4))]
    data = _fuzz_datagrams(2000, rng, valid)
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        for i in range(0, len(data), 100):
            for d in data[i:i + 100]:
                s.sendto(d, ("127.0.0.1", port))
            p.poll(0.004)
        t = time.monotonic() + 5
        while p.counters.datagrams < 2000 and time.monotonic() < t:
            p.poll(0.01)
        c = p.counters
        assert c.datagrams == 2000 and c.malformed + sum(c.rejected.values()) == 2000, c.as_dict()
    finally:
        s.close()
        p.close()
