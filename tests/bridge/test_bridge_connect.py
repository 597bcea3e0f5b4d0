"""`MavlinkPlant.connect` asks a vehicle that streams its state but has not sent a HEARTBEAT yet
for one (MAV_CMD_REQUEST_MESSAGE), instead of waiting up to a second for the periodic one: most
of an agent's start-up was that wait (issue 31)."""
from __future__ import annotations

import math
import socket
import threading
import time

import pytest

from _bridge import load
from bridge.mavlink.link import Counters, Peer, mavlink2, split_datagram

pytestmark = [pytest.mark.realtime, pytest.mark.timeout(120)]


class _QuietVehicles(threading.Thread):
    """Six vehicles on one socket that stream ODOMETRY every 10 ms and send a HEARTBEAT only when
    asked for one: never periodically."""

    def __init__(self, port: int):
        super().__init__(daemon=True)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.01)
        self.dest = ("127.0.0.1", port)
        self.peers = {i: Peer(i, 1, Counters()) for i in range(1, 7)}
        self.asked = []          # (system, command) of every COMMAND_LONG received
        self.stop = threading.Event()

    def run(self):
        dec = mavlink2.MAVLink(None)
        while not self.stop.is_set():
            for i, p in self.peers.items():
                self.sock.sendto(bytes(p.pack(p.mav.odometry_encode(
                    int(time.time() * 1e6), mavlink2.MAV_FRAME_LOCAL_NED,
                    mavlink2.MAV_FRAME_BODY_FRD, 0, 0, -i, [1, 0, 0, 0], 0, 0, 0, 0, 0, 0,
                    [math.nan] + [0.0] * 20, [math.nan] + [0.0] * 20, 0, 0, 100))), self.dest)
            try:
                data, _ = self.sock.recvfrom(65535)
            except OSError:
                continue
            for pkt in split_datagram(data)[0]:
                m = dec.decode(bytearray(pkt))
                if m.get_type() != "COMMAND_LONG":
                    continue
                self.asked.append((m.target_system, m.command))
                if m.command == mavlink2.MAV_CMD_REQUEST_MESSAGE and m.param1 == 0 \
                        and m.target_system in self.peers:
                    p = self.peers[m.target_system]
                    self.sock.sendto(bytes(p.pack(p.mav.heartbeat_encode(
                        mavlink2.MAV_TYPE_HEXAROTOR, mavlink2.MAV_AUTOPILOT_GENERIC, 0, 0,
                        mavlink2.MAV_STATE_ACTIVE))), self.dest)


def test_connect_asks_a_streaming_vehicle_for_its_heartbeat():
    from bridge.mavlink.config import default_config
    from bridge.mavlink.plant import MavlinkPlant

    sc = load([])
    cfg = (sc.bridge or default_config(sc.n_agents)).with_endpoints(
        ["udpin:127.0.0.1:0"] * sc.n_agents)
    p = MavlinkPlant(sc, cfg, connect_timeout=20, on_event=lambda s: None)
    veh = _QuietVehicles(p.socks[0].local[1])
    veh.start()
    try:
        p.connect()     # without asking, ConnectError ("no heartbeat") after 20 s
        assert all(v.connected for v in p.vehicles)
        asked = {s for s, c in veh.asked if c == mavlink2.MAV_CMD_REQUEST_MESSAGE}
        assert asked == set(range(1, 7))
    finally:
        veh.stop.set()
        veh.join()
        veh.sock.close()
        p.close()
