"""Issue 13 (hardening), MAVLink part: each fault reproduced, then shown fixed.

* signed replay into a restarted vehicle (the replay window persists with the key);
* spoofed packets that are refused must not move where a link sends (bridge and vehicle);
* one future-stamped command (unknown system, or a spoofed commander) locks nobody out;
* a datagram flood: the per-pass drain is bounded and the fail-safe keeps its deadline;
* counters: bad CRC from strangers, NaN COMMAND_LONG parameters, phantom sequence gaps;
* ``--insecure``: a socket reachable from other machines needs a key.
"""
from __future__ import annotations

import json
import os
import random
import socket
import struct
import subprocess
import sys
import time

import numpy as np
import pytest

os.environ.setdefault("MAVLINK20", "1")

from bridge.mavlink.link import DRAIN_BUDGET, Counters, Peer, mavlink2  # noqa: E402
from _machine import CpuShare, skip_if_deadline_missed  # noqa: E402
from _bridge import (ROOT, VehicleProcess, VehicleThread, bound_udp,  # noqa: E402
                                 free_base_port, load)

M = mavlink2
KEY = bytes(range(7, 39))
NAN = float("nan")


def _wait(pred, timeout=15.0):
    t = time.monotonic() + timeout
    while time.monotonic() < t:
        if pred():
            return True
        time.sleep(0.01)
    return pred()


def _listen(s):
    """Our end of a udpout vehicle: ``s`` is bound to its target port (`bound_udp`, before the
    vehicle starts); returns (socket, vehicle address) once the vehicle has talked (60 s: a
    guard against a vehicle that never does, not a deadline for a slow start)."""
    s.settimeout(60.0)
    _, addr = s.recvfrom(65535)
    s.setblocking(False)
    return s, addr


def _drain(s):
    n = 0
    while True:
        try:
            s.recvfrom(65535)
            n += 1
        except (BlockingIOError, OSError):
            return n


def _sig_timestamp(pkt: bytes) -> int:
    """The 48-bit signing timestamp of a signed packet (bytes -12..-6), read independently."""
    lo, hi = struct.unpack("<IH", pkt[-12:-6])
    return lo | (hi << 32)


def _command(peer, t_us, value=0.1, target=1):
    return peer.pack(peer.mav.set_actuator_control_target_encode(t_us, 0, target, 1, [value] * 6 + [0, 0]))


# ---------------------------------------------------------------------------------------- 14
def _session(state, n):
    """n signed commands into a fresh vehicle; returns the packets as sent."""
    lis, port = bound_udp()
    with VehicleThread(count=1, base_port=port, key=KEY, signing_state=state, rate=100, aux_rate=0,
                       command_timeout=100.0) as srv:
        sock, addr = _listen(lis)
        gcs = Peer(255, 191, Counters(), key=KEY, link_id=1)
        t0 = int(time.time() * 1e6)
        pkts = [_command(gcs, t0 + i, 0.1 + 1e-4 * (i % 100)) for i in range(n)]
        for i in range(0, n, 100):
            for p in pkts[i:i + 100]:
                sock.sendto(p, addr)
            assert _wait(lambda: srv.vehicles[0].commands >= i + 100), srv.stats()
            _drain(sock)
        sock.close()
    return pkts


def _replay(state, pkts):
    lis, port = bound_udp()
    with VehicleThread(count=1, base_port=port, key=KEY, signing_state=state, rate=100, aux_rate=0,
                       command_timeout=100.0) as srv:
        sock, addr = _listen(lis)
        for i in range(0, len(pkts), 100):
            done = sum(srv.counters.rejected.values()) + srv.vehicles[0].commands
            for p in pkts[i:i + 100]:
                sock.sendto(p, addr)
            assert _wait(lambda: sum(srv.counters.rejected.values()) + srv.vehicles[0].commands >= done + 100)
            _drain(sock)
        replay = dict(srv.counters.rejected), srv.vehicles[0].commands, srv.counters.dropped
        # a new genuine session with the same key is accepted (nothing is locked out)
        gcs = Peer(255, 191, Counters(), key=KEY, link_id=1)
        sock.sendto(_command(gcs, int(time.time() * 1e6), 0.5), addr)
        assert _wait(lambda: srv.vehicles[0].commands == replay[1] + 1)
        sock.close()
    return replay


@pytest.mark.realtime
def test_signed_replay_into_restarted_vehicle_is_rejected(tmp_path):
    n = 6000
    state = tmp_path / "key.signing.json"
    pkts = _session(state, n)
    # what was persisted at exit: the stream's last timestamp, read from the packets themselves
    saved = json.loads(state.read_text())
    assert [1, 255, 191, _sig_timestamp(pkts[-1])] in saved["streams"]
    rejected, commands, dropped = _replay(state, pkts)
    assert commands == 0 and rejected == {"replay": n} and dropped == 0

    # the fault as reported: without the persisted state the same replay drives the vehicle
    rejected, commands, _ = _replay(None, pkts[:500])
    assert commands == 500 and rejected == {}


def test_own_timestamp_never_reused_after_a_crash(tmp_path):
    """Packets signed after the last periodic write (then a crash: no close) must not have their
    timestamps reused after a restart: the restored own timestamp jumps by the margin."""
    from bridge.mavlink.signing_state import SigningState, wall_timestamp

    path = tmp_path / "s.json"
    st = SigningState(path, period=0.0)
    tx = Peer(255, 191, Counters(), key=KEY, signing_state=st)
    st.tick(time.monotonic())                     # a periodic write ...
    before = [_command(tx, i) for i in range(50_000)]   # ... then 50,000 packets, then a crash
    st2 = SigningState(path)
    tx2 = Peer(255, 191, Counters(), key=KEY, signing_state=st2)
    first = _sig_timestamp(_command(tx2, 1))
    assert first > max(_sig_timestamp(p) for p in before)
    assert first >= wall_timestamp() - 100_000    # and it follows the wall clock (within 1 s)


def test_corrupt_signing_state_is_one_line_error(tmp_path):
    import pytest

    from bridge.mavlink.signing_state import SigningState
    from controller.errors import Se3SyncError

    p = tmp_path / "s.json"
    p.write_text('{"timestamp": "soon", "streams": []}')
    with pytest.raises(Se3SyncError, match=r"signing state .*s\.json: corrupt"):
        SigningState(p)


# ---------------------------------------------------------------------------------------- 16
def _hil_with_spoofer(tmp_path, overrides, key, spoof, steps=200, per_step=15):
    """A lockstep HIL run of the 6-vehicle scenario while a spoofer sends `spoof(sysid)` packets
    to the bridge's ports; returns (bridge stats, server, packets the spoofer received)."""
    from bridge.mavlink.plant import MavlinkPlant
    from cosim.master import make_controller

    port = free_base_port(6)
    sc = load([f"bridge.base_port={port}", *overrides])
    spoofer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    spoofer.bind(("127.0.0.1", 0))
    spoofer.setblocking(False)
    got = 0
    with VehicleThread(scenario=sc, lockstep=True, key=key, aux_rate=0) as srv:
        p = MavlinkPlant(sc, lockstep=True, key=key, connect_timeout=15, on_event=lambda s: None).connect()
        try:
            c = make_controller("hybrid", sc)
            for k in range(steps):
                for j in range(per_step):
                    v = (k * per_step + j) % 6
                    spoofer.sendto(spoof(v + 1), ("127.0.0.1", port + v))
                u, _ = c.step_state(p.read(), sc.step)
                p.apply(u)
                p.advance(sc.step)
                got += _drain(spoofer)
            time.sleep(0.05)
            p.poll(0.0)
            got += _drain(spoofer)
            st = p.stats()
        finally:
            p.close()
            spoofer.close()
        steps_done = [v.k for v in srv.vehicles]
        vst = srv.stats()
    return st, vst, steps_done, got


@pytest.mark.realtime
def test_spoofed_unsigned_heartbeats_divert_no_signed_command(tmp_path):
    rng = random.Random(5)
    fakes = {}

    def spoof(sysid):
        tx = fakes.setdefault(sysid, Peer(sysid, 1, Counters()))
        tx.mav.seq = rng.randrange(256)           # foreign sequence numbers: phantom gaps if counted
        return tx.pack(tx.mav.heartbeat_encode(M.MAV_TYPE_HEXAROTOR, M.MAV_AUTOPILOT_GENERIC, 0, 0, 4))

    st, vst, steps, got = _hil_with_spoofer(tmp_path, ["bridge.allow_unsigned_heartbeat=true"], KEY, spoof)
    assert got == 0                               # no command went to the spoofing address
    assert steps == [200] * 6                     # every vehicle got every command
    # 3,000 foreign sequence numbers would make ~190,000 phantom "drops"; loopback loses ~nothing
    assert st["dropped"] < 50, st
    # they come from another address than the vehicle's while the vehicle is alive: a second
    # source claiming it, refused before use (issue 29)
    assert set(st["rejected_by_reason"]) == {"other_source"} and vst["rejected"] == 0, st
    assert 0 < st["rejected"] <= 3000


@pytest.mark.realtime
def test_spoofed_nan_odometry_diverts_no_command(tmp_path):
    fakes = {}

    def spoof(sysid):
        tx = fakes.setdefault(sysid, Peer(sysid, 1, Counters()))
        return tx.pack(tx.mav.odometry_encode(0, M.MAV_FRAME_LOCAL_NED, M.MAV_FRAME_BODY_FRD, NAN, 0, 0,
                                              [1, 0, 0, 0], 0, 0, 0, 0, 0, 0, [NAN] + [0] * 20,
                                              [NAN] + [0] * 20, 0, 0, 100))

    st, vst, steps, got = _hil_with_spoofer(tmp_path, [], None, spoof)
    assert got == 0
    assert steps == [200] * 6
    # from another address than the vehicle's: refused as a second source before decoding
    assert st["rejected_by_reason"].get("other_source", 0) > 0
    assert set(st["rejected_by_reason"]) == {"other_source"}
    assert st["dropped"] < 50, st


@pytest.mark.realtime
def test_vehicle_address_does_not_follow_refused_packets():
    """udpin vehicle: a refused command from another address must not redirect its replies."""
    with VehicleThread(count=1, endpoints=["udpin:127.0.0.1:0"], rate=200, aux_rate=0,
                       command_timeout=100.0) as srv:
        port = srv.vehicles[0].sock.local[1]   # the vehicle's port, chosen by the OS
        gcs = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        gcs.bind(("127.0.0.1", 0))
        evil = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        evil.bind(("127.0.0.1", 0))
        tx = Peer(255, 191, Counters())
        gcs.sendto(_command(tx, int(time.time() * 1e6)), ("127.0.0.1", port))
        assert _wait(lambda: srv.vehicles[0].commands == 1)
        bad = Peer(255, 191, Counters())                                   # spoofs the commander
        for i in range(50):
            evil.sendto(_command(bad, int(time.time() * 1e6), value=NAN), ("127.0.0.1", port))  # bad_command
            evil.sendto(_command(Peer(9, 1, Counters()), int(time.time() * 1e6)), ("127.0.0.1", port))
        assert _wait(lambda: sum(srv.counters.rejected.values()) == 100)
        assert dict(srv.counters.rejected) == {"bad_command": 50, "not_commander": 50}
        assert srv.vehicles[0].gcs_addr == gcs.getsockname()
        evil.setblocking(False)
        time.sleep(0.1)
        assert _drain(evil) == 0
        gcs.close()
        evil.close()


# ---------------------------------------------------------------------------------------- 17
def _future_stamped(attacker):
    lis, port = bound_udp()
    with VehicleThread(count=1, base_port=port, rate=200, aux_rate=0, command_timeout=100.0) as srv:
        sock, addr = _listen(lis)
        gcs = Peer(255, 191, Counters())
        t0 = int(time.time() * 1e6)
        n = 200
        for i in range(n):
            if i == 50:
                sock.sendto(_command(attacker, t0 + i * 5000 + 9_000_000, value=0.9), addr)
            sock.sendto(_command(gcs, t0 + i * 5000), addr)
            time.sleep(0.005)
        assert _wait(lambda: srv.vehicles[0].commands + sum(srv.counters.rejected.values()) >= n + 1)
        time.sleep(0.05)
        sock.close()
        return srv.vehicles[0].commands, dict(srv.counters.rejected), srv.vehicles[0].controls.copy()


@pytest.mark.realtime
def test_future_stamped_command_from_unknown_system_rejects_no_genuine_command():
    commands, rejected, controls = _future_stamped(Peer(200, 1, Counters()))
    assert commands == 200 and rejected == {"not_commander": 1}
    assert np.allclose(controls, np.float32(0.1))


@pytest.mark.realtime
def test_future_stamped_command_from_spoofed_commander_rejects_no_genuine_command():
    commands, rejected, _ = _future_stamped(Peer(255, 191, Counters()))
    assert commands == 200 and rejected == {"future": 1}


# ---------------------------------------------------------------------------------------- 18
@pytest.mark.realtime
def test_flood_keeps_failsafe_deadline(tmp_path):
    """~10^5 datagrams/s at one vehicle while commands come and stop 6 times: the drain per pass
    is bounded (drain_max <= DRAIN_BUDGET, passes capped), every fail-safe is detected at the first
    tick due after the 2-period command timeout, and the median wall-clock delay stays within 10
    periods (the rest is the tick's lateness: scheduling noise on a shared machine)."""
    lis, port = bound_udp()
    h = 0.004
    rng = random.Random(3)
    stranger = Peer(77, 1, Counters())
    hb = _command(stranger, 1)                  # well formed, actuation from a stranger: not_commander
    junk = [bytes([0xFD]) + rng.randbytes(rng.randrange(1, 40)) for _ in range(64)]  # truncated frames
    flood = [hb if i % 2 else junk[i // 2 % 64] for i in range(128)]
    sent = 0
    with CpuShare() as cpu, VehicleProcess(["--count", "1", "--base-port", port, "--rate", 250,
                                            "--step", h, "--aux-rate", 0], tmp_path) as vp:
        vp.wait_ready()
        sock, addr = _listen(lis)
        gcs = Peer(255, 191, Counters())
        t_start = time.monotonic()
        for cycle in range(6):
            t_end = time.monotonic() + 0.25
            while time.monotonic() < t_end:                 # commands at ~250 Hz inside the flood
                sock.sendto(_command(gcs, int(time.time() * 1e6)), addr)
                t_next = time.monotonic() + h
                while time.monotonic() < t_next:
                    for d in flood:
                        sock.sendto(d, addr)
                    sent += len(flood)
                _drain(sock)
            t_end = time.monotonic() + 0.15                 # commands stop: flood only
            while time.monotonic() < t_end:
                for d in flood:
                    sock.sendto(d, addr)
                sent += len(flood)
                _drain(sock)
        rate = sent / (time.monotonic() - t_start)
        sock.close()
        st = vp.stop()
    delays = np.array(st["failsafe_delays"]) / h
    print(f"\nflood {rate:.0f} datagrams/s offered; fail-safe delays in periods: "
          f"{np.round(np.sort(delays), 2).tolist()}; drain_max {st['drain_max']}, "
          f"drain_capped {st['drain_capped']}, deadline cuts {st['drain_deadline_hits']}, "
          f"datagrams read {st['datagrams']}")
    assert st["failsafe"] >= 6 and len(delays) == st["failsafe"]
    # counted from the time the detecting tick was due, the design bound (timeout 2 h + one tick)
    # holds exactly; the wall-clock delay adds that tick's lateness, which the drain budget keeps
    # small under the flood (25 periods at the median before it): the median guards that, the
    # benchmark (benchmarks/bench_bridge_flood.py) measures it
    assert max(st["failsafe_tick_delays"]) <= 3 * h + 1e-6, st["failsafe_tick_delays"]
    assert st["drain_max"] <= DRAIN_BUDGET and st["drain_capped"] > 0
    # every datagram read is accounted once: a command, or refused as malformed / not_commander
    rj = st["rejected_by_reason"]
    assert st["datagrams"] == st["commands"] + st["malformed"] + rj.get("not_commander", 0) \
        + rj.get("out_of_order", 0), st
    # the wall-clock delay needs the vehicle's ticks on time (tests/_machine.py)
    skip_if_deadline_missed(cpu, {"the vehicle": (st["late_ticks"], st["ticks"])},
                            "fail-safe under a flood")
    assert np.median(delays) <= 10.0, delays


# ---------------------------------------------------------------------------------------- 19
def _corrupt_crc(pkt: bytes) -> bytes:
    b = bytearray(pkt)
    b[-1] ^= 0xFF
    return bytes(b)


@pytest.mark.realtime
def test_bad_crc_from_unknown_system_is_malformed_at_the_bridge():
    from bridge.mavlink.plant import MavlinkPlant

    port = free_base_port(6)
    sc = load([f"bridge.base_port={port}"])
    p = MavlinkPlant(sc, connect_timeout=1, on_event=lambda s: None)
    try:
        tx = Peer(99, 1, Counters())
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        hb = tx.pack(tx.mav.heartbeat_encode(0, 0, 0, 0, 4))
        s.sendto(_corrupt_crc(hb), ("127.0.0.1", port))
        s.sendto(tx.pack(tx.mav.heartbeat_encode(0, 0, 0, 0, 4)), ("127.0.0.1", port))
        assert _wait(lambda: (p.poll(0.05), p.counters.datagrams)[1] == 2, 5)
        assert p.counters.malformed == 1 and dict(p.counters.rejected) == {"wrong_system": 1}
        s.close()
    finally:
        p.close()


@pytest.mark.realtime
def test_vehicle_counters_bad_crc_and_nan_command_long():
    lis, port = bound_udp()
    with VehicleThread(count=1, base_port=port, rate=200, aux_rate=0, command_timeout=100.0) as srv:
        sock, addr = _listen(lis)
        stranger, gcs = Peer(99, 1, Counters()), Peer(255, 191, Counters())
        sock.sendto(_corrupt_crc(stranger.pack(stranger.mav.heartbeat_encode(0, 0, 0, 0, 4))), addr)
        sock.sendto(gcs.pack(gcs.mav.command_long_encode(1, 1, M.MAV_CMD_DO_SET_ACTUATOR, 0,
                                                         0.1, 0.1, 0.1, 0.1, 0.1, 0.1, NAN)), addr)
        assert _wait(lambda: srv.counters.datagrams == 2, 5)
        assert srv.counters.malformed == 1
        assert dict(srv.counters.rejected) == {"bad_command": 1}
        assert srv.vehicles[0].commands == 0
        sock.close()


# ---------------------------------------------------------------------------------------- 15
def _cli(*args, timeout=60):
    return subprocess.run([sys.executable, "-m", "cosim.cli", *map(str, args)], cwd=str(ROOT),
                          capture_output=True, text=True, timeout=timeout)


def test_insecure_needed_for_non_loopback_without_key(tmp_path):
    # the vehicles bind a port the OS chooses (0); connect refuses before it binds anything
    r = _cli("vehicle", "--endpoint", "udpin:0.0.0.0:0", "--duration", "0.2")
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "--insecure" in r.stderr, r.stderr
    r = _cli("vehicle", "--endpoint", "udpin:0.0.0.0:0", "--duration", "0.2", "--insecure")
    assert r.returncode == 0, r.stderr
    key = tmp_path / "k.hex"
    key.write_text(KEY.hex())
    r = _cli("vehicle", "--endpoint", "udpin:0.0.0.0:0", "--duration", "0.2", "--key", key)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "k.hex.vehicle.signing.json").exists()   # the signing state is kept with the key
    port = free_base_port(6)
    eps = [a for i in range(6) for a in ("--vehicle", f"udpin:0.0.0.0:{port + i}")]
    r = _cli("connect", ROOT / "scenarios" / "hil_6uav.toml", *eps)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "--insecure" in r.stderr, r.stderr


@pytest.mark.realtime
def test_bridge_keeps_signing_state_beside_the_key(tmp_path):
    """The bridge side: state written at close beside the key file (or at bridge.signing_state),
    and a restarted bridge signs above the stored own timestamp by the margin."""
    from bridge.mavlink.plant import MavlinkPlant
    from bridge.mavlink.signing_state import wall_timestamp

    key = tmp_path / "k.hex"
    key.write_text(KEY.hex())
    port = free_base_port(6)
    sc = load([f"bridge.base_port={port}"])
    w0 = wall_timestamp()
    p = MavlinkPlant(sc, key=key, on_event=lambda s: None)
    p.close()
    saved = json.loads((tmp_path / "k.hex.bridge.signing.json").read_text())
    assert saved["timestamp"] >= w0
    elsewhere = tmp_path / "state" / "bridge.json"
    elsewhere.parent.mkdir()
    sc = load([f"bridge.base_port={port}", f"bridge.signing_state=\"{elsewhere}\""])
    p = MavlinkPlant(sc, key=key, on_event=lambda s: None)
    try:
        assert p.signing.path == str(elsewhere) and not elsewhere.exists()
        p.signing.timestamp = saved["timestamp"] + 10**9     # as if it had signed far ahead
    finally:
        p.close()
    assert elsewhere.exists()
    p = MavlinkPlant(sc, key=key, on_event=lambda s: None)
    try:
        assert min(v.peer.mav.signing.timestamp for v in p.vehicles) >= saved["timestamp"] + 10**9 + p.signing.margin_units
    finally:
        p.close()
