"""The loopback vehicle's command protocol, the state fallback, shared-port routing and a clean
SIGTERM."""
from __future__ import annotations

import os
import socket
import time

import numpy as np
import pytest

os.environ.setdefault("MAVLINK20", "1")

from bridge.mavlink.link import Counters, Peer, mavlink2 as M, split_datagram  # noqa: E402
from _bridge import (HIL, VehicleProcess, VehicleThread, bound_udp,  # noqa: E402
                                 free_base_port, load)


def _collect(sock, peer, seconds):
    out = []
    t = time.monotonic() + seconds
    sock.settimeout(0.05)
    while time.monotonic() < t:
        try:
            data, _ = sock.recvfrom(65535)
        except socket.timeout:
            continue
        pkts, err = split_datagram(data)
        for p in pkts:
            m = peer.accept(p)
            if m is not None:
                out.append(m)
    return out


@pytest.mark.realtime
def test_commands_acks_and_streams():
    sock, port = bound_udp()
    with VehicleThread(count=1, base_port=port, rate=100, aux_rate=10, require_arm=True) as srv:
        sock.settimeout(60)   # its first datagram: a guard, not a deadline
        _, addr = sock.recvfrom(65535)
        gcs = Peer(255, 191, Counters())
        cl = lambda cmd, *p: gcs.pack(gcs.mav.command_long_encode(1, 1, cmd, 0, *p))  # noqa: E731
        sock.sendto(cl(M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_ODOMETRY, -1, 0, 0, 0, 0, 0), addr)
        sock.sendto(cl(M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_ATTITUDE_QUATERNION, 20000, 0, 0, 0, 0, 0), addr)
        sock.sendto(cl(M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_ODOMETRY, 0, 0, 0, 0, 0, 0), addr)
        sock.sendto(cl(M.MAV_CMD_COMPONENT_ARM_DISARM, 1, 0, 0, 0, 0, 0, 0), addr)
        sock.sendto(cl(M.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 0), addr)
        _collect(sock, Peer(255, 191, Counters()), 0.3)          # let the old stream drain
        msgs = _collect(sock, Peer(255, 191, Counters()), 1.0)
        assert srv.vehicles[0].armed
        types = [m.get_type() for m in msgs]
        assert types.count("ODOMETRY") == 0                        # disabled
        assert types.count("ATTITUDE_QUATERNION") >= 30             # 50 Hz
        assert types.count("LOCAL_POSITION_NED") >= 5 and types.count("HEARTBEAT") >= 1
        sock.close()


def _collect_acks(msgs):
    return [m for m in msgs if m.get_type() == "COMMAND_ACK"]


@pytest.mark.realtime
def test_acks_are_sent():
    sock, port = bound_udp()
    with VehicleThread(count=1, base_port=port, rate=50, aux_rate=0):
        sock.settimeout(60)   # its first datagram: a guard, not a deadline
        _, addr = sock.recvfrom(65535)
        gcs = Peer(255, 191, Counters())
        for cmd, p1 in ((M.MAV_CMD_COMPONENT_ARM_DISARM, 1), (M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_ODOMETRY),
                        (M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_HEARTBEAT), (M.MAV_CMD_NAV_TAKEOFF, 0)):
            sock.sendto(gcs.pack(gcs.mav.command_long_encode(1, 1, cmd, 0, p1, 500000, 0, 0, 0, 0, 0)), addr)
        acks = {m.command: m.result for m in _collect_acks(_collect(sock, Peer(255, 191, Counters()), 0.5))}
        assert acks == {M.MAV_CMD_COMPONENT_ARM_DISARM: M.MAV_RESULT_ACCEPTED,
                        M.MAV_CMD_REQUEST_MESSAGE: M.MAV_RESULT_ACCEPTED,
                        M.MAV_CMD_SET_MESSAGE_INTERVAL: M.MAV_RESULT_ACCEPTED,
                        M.MAV_CMD_NAV_TAKEOFF: M.MAV_RESULT_UNSUPPORTED}
        sock.close()


def test_fallback_state_from_attitude_and_local_position():
    """A vehicle that sends no ODOMETRY: the bridge builds the state from ATTITUDE_QUATERNION +
    LOCAL_POSITION_NED (velocity rotated from NED into the body)."""
    from bridge.mavlink.state import StateTracker
    from controller import se3

    tx = Peer(1, 1, Counters())
    rx = Peer(255, 191, Counters())
    R = se3.R_a(0.7, np.array([0.0, 0.6, 0.8]))
    q = se3.rot_to_quat(R)
    v_body = np.array([1.0, -2.0, 0.5])
    v_ned = R @ v_body
    tr = StateTracker(Counters(), check_stale=False)
    a = rx.accept(tx.pack(tx.mav.attitude_quaternion_encode(1000, *q, 0.1, 0.2, 0.3)))
    p = rx.accept(tx.pack(tx.mav.local_position_ned_encode(1000, 1, 2, 3, *v_ned)))
    assert not tr.on_attitude_quaternion(a, 0.0) and tr.on_local_position_ned(p, 0.0)
    assert tr.source == "fallback"
    assert np.allclose(tr.wire[0:3], [1, 2, 3]) and np.allclose(tr.wire[7:10], [0.1, 0.2, 0.3], atol=1e-7)
    assert np.allclose(tr.wire[10:13], v_body, atol=1e-5)


@pytest.mark.realtime
def test_shared_port_routing_lockstep():
    from bridge.mavlink.plant import MavlinkPlant
    from bridge.mavlink.transport import QuantizedPlant
    from cosim.master import make_controller

    port = free_base_port(1)
    sc = load([f"bridge.base_port={port}", "bridge.routing=\"shared\""])
    assert len({v.endpoint for v in sc.bridge.vehicles}) == 1
    with VehicleThread(scenario=sc, lockstep=True, aux_rate=0):
        p = MavlinkPlant(sc, lockstep=True, connect_timeout=10, on_event=lambda s: None).connect()
        q = QuantizedPlant(sc)
        c1, c2 = make_controller("hybrid", sc), make_controller("hybrid", sc)
        try:
            for _ in range(30):
                u1, _ = c1.step_state(p.read(), sc.step)
                u2, _ = c2.step_state(q.read(), sc.step)
                p.apply(u1)
                q.apply(u2)
                p.advance(sc.step)
                q.advance(sc.step)
            assert np.array_equal(p.read(), q.read())
            assert p.stats()["rejected"] == 0 and len(p.socks) == 1
        finally:
            p.close()
            q.close()


@pytest.mark.realtime
def test_sigterm_stops_cleanly(tmp_path):
    port = free_base_port(6)
    with VehicleProcess(["--scenario", HIL, "--set", f"bridge.base_port={port}"], tmp_path) as veh:
        veh.wait_ready()
        time.sleep(1.0)
        st = veh.stop()
        # SIGTERM stops it cleanly (stats written) with the documented status 143 (issue 13)
        assert veh.proc.returncode == 143, veh.stderr
    assert st["sent"] > 0 and "stopped" in veh.stderr


@pytest.mark.parametrize("key", [None, bytes(range(32))])
def test_vehicle_odometry_is_pymavlinks_bytes(key):
    """The loopback vehicle's ODOMETRY (`SimVehicle.odometry`, the struct codec) packs to the
    bytes of pymavlink's odometry_encode of the same fields, signed and unsigned, at random
    states."""
    from bridge.vehicles.loopback import NAN21, VehicleServer

    srv = VehicleServer(1, base_port=free_base_port(1), key=key, insecure=True)
    try:
        v = srv.vehicles[0]
        v.time_usec = lambda: 1_700_000_123_456_789
        rng = np.random.default_rng(7)
        mav = v.peer.mav
        for _ in range(50):
            v.wire[:] = rng.normal(scale=5.0, size=13)
            seq = mav.seq
            ts = mav.signing.timestamp if key else None
            mine = v.peer.pack(v.odometry())
            mav.seq = seq
            if key:
                mav.signing.timestamp = ts
            x = v.wire
            ref = v.peer.pack(mav.odometry_encode(
                v.time_usec(), M.MAV_FRAME_LOCAL_NED, M.MAV_FRAME_BODY_FRD, x[0], x[1], x[2],
                [x[3], x[4], x[5], x[6]], x[10], x[11], x[12], x[7], x[8], x[9], NAN21, NAN21, 0,
                M.MAV_ESTIMATOR_TYPE_NAIVE, 100))
            assert bytes(mine) == bytes(ref)
            assert (mine[2] & 1) == (key is not None)
    finally:
        srv.close()


@pytest.mark.realtime
def test_real_time_reads_once_a_tick_and_takes_every_command():
    """Real time: the sockets are read just before each physics tick, not at each datagram (a
    process blocked in select is woken by every command, and so is its sender's sendto). A
    commander sending four commands a tick: every one is taken, in about one read pass a tick
    (at most one more per 50 ms of idling), not one per command."""
    from bridge.mavlink.output import ACTUATOR_CONTROL_TARGET, profile

    sock, port = bound_udp()
    with VehicleThread(count=1, base_port=port, rate=100, aux_rate=0) as srv:
        sock.settimeout(60)   # its first datagram: a guard, not a deadline
        _, addr = sock.recvfrom(65535)
        gcs = Peer(255, 191, Counters())
        prof = profile(ACTUATOR_CONTROL_TARGET, h=0.01, max_wrench=np.ones(6))
        sent = 0
        t0 = time.monotonic()
        p0, k0 = srv.read_passes, srv.ticks
        while time.monotonic() - t0 < 1.0:
            msg = prof.message(gcs.mav, np.full(6, 0.01), target=1, k=sent + 1, lockstep=False)
            sock.sendto(gcs.pack(msg), addr)
            sent += 1
            time.sleep(0.0025)
        end = time.monotonic() + 15.0   # the last ones taken (a busy machine may lag a tick)
        while srv.vehicles[0].commands < sent and time.monotonic() < end:
            time.sleep(0.01)
        passes, ticks = srv.read_passes - p0, srv.ticks - k0
        taken = srv.vehicles[0].commands
        sock.close()
    assert taken == sent > 100
    assert passes <= ticks + 25, (passes, ticks, sent)
