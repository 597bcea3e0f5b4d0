"""The plant as a flight stack's simulator (issue 14): PX4's simulator MAVLink interface and
ArduPilot's JSON physics interface, each driven for 1,000 lockstep steps by a client written here
from the published definitions (MAVLink common.xml HIL_* messages; ArduPilot's
libraries/SITL/examples/JSON/readme.md). No SITL runs here: what is checked is the protocol
(order, stamps, rates, sizes, duplicates) and the physics and frames of every field against
computations in this file."""
from __future__ import annotations

import json
import math
import os
import select
import socket
import struct
import threading

import numpy as np
import pytest

os.environ.setdefault("MAVLINK20", "1")

from _bridge import load  # noqa: E402


H = 0.004
MASS = 2.4
J = np.diag([0.043, 0.041, 0.082])
MW = np.array([50.0, 50.0, 50.0, 20.0, 20.0, 20.0])
G = np.array([0.0, 0.0, 9.81])          # NED: down
# our documented Earth model, written out independently of bridge.vehicles.sim_body
LAT0, LON0, ALT0, RE = 47.397742, 8.545594, 488.0, 6378137.0
INC, DEC, BG = math.radians(63.5), math.radians(3.0), 0.48
B_NED = BG * np.array([math.cos(INC) * math.cos(DEC), math.cos(INC) * math.sin(DEC), math.sin(INC)])


def _rot(q):
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


class _Thread:
    def __init__(self, srv):
        self.srv = srv
        self.t = threading.Thread(target=srv.run, daemon=True)

    def __enter__(self):
        self.t.start()
        self.srv.ready.wait(5)
        return self.srv

    def __exit__(self, *exc):
        self.srv.stop()
        self.t.join(5)
        self.srv.close()


def _gravity_scenario(extra=()):
    return load(["plant.gravity=[0.0, 0.0, 9.81]", *extra])


# ------------------------------------------------------------------------------------------ PX4
@pytest.mark.realtime
def test_px4_simulator_lockstep_1000_steps():
    """A client that starts as PX4 does (lets the HIL_SENSOR stream advance its clock before it sends
    any HIL_ACTUATOR_CONTROLS: Px4Client.start) reaches lockstep; then 1,000 exchanges."""
    from bridge.vehicles.sim_px4 import Px4SimServer
    from sim_clients import Px4Client

    sc = _gravity_scenario()
    srv = Px4SimServer(sc, port=0, step=H, noise=True, seed=7, lockstep_timeout=60.0)
    n, n_held = 1000, 200
    c_free = np.array([1e-4, -2e-4, 1e-4, 0.1, -0.05, -0.3])     # τ = c·MW (N·m), f = c·MW (N)
    f_body = c_free[3:] * MW[3:]
    with _Thread(srv):
        cl = Px4Client(srv.links[0].port)
        quiet_checks = 0
        try:
            start = cl.start(start_after=0.02)          # streamed steps, then one answer
            k0 = sum(m.get_type() == "HIL_SENSOR" for m in start)
            for k in range(n):
                if k in (5, 300, 700):   # lockstep: nothing of the next step before our reply
                    cl.drain(0.1)
                    assert cl.clock_us == (k0 + k) * 4000
                    quiet_checks += 1
                armed = k >= n_held
                cl.send(list(c_free) if armed else [0.0] * 6, armed)
                cl.step()
        finally:
            cl.close()
    msgs = cl.messages
    sensors = [m for m in msgs if m.get_type() == "HIL_SENSOR"]
    states = [m for m in msgs if m.get_type() == "HIL_STATE_QUATERNION"]
    gps = [m for m in msgs if m.get_type() == "HIL_GPS"]
    st = srv.stats()
    total = k0 + n
    assert k0 >= 6 and st["streamed_steps"] == k0 - 2 and quiet_checks == 3       # ≥ 0.02 s of 4 ms steps, + 1
    assert st["steps"] == total - 1 and st["malformed"] == 0 and st["ignored"] == 0
    assert st["lockstep_timeouts"] == 0
    # rates: one HIL_SENSOR and one HIL_STATE_QUATERNION per step, stamps (k+1)·h (never 0); HIL_GPS at 10 Hz
    assert [m.time_usec for m in sensors] == [(k + 1) * 4000 for k in range(total)]
    assert [m.time_usec for m in states] == [(k + 1) * 4000 for k in range(total)]
    assert [m.time_usec - srv.epoch_us for m in gps] == [(k + 1) * 4000 for k in range(0, total, 25)]
    assert srv.epoch_us > 1_600_000_000 * 10 ** 6                # HIL_GPS time_usec is UTC, not near 1970
    assert all(m.fields_updated == 0x1BFF and m.id == 0 for m in sensors)   # no differential pressure
    assert all(m.fix_type == 3 and m.satellites_visible >= 6 for m in gps)
    F = k0 + n_held                                  # the first state after the first armed reply

    q = np.array([m.attitude_quaternion for m in states], dtype=float)
    assert np.allclose(np.linalg.norm(q, axis=1), 1, atol=1e-6)
    Rs = np.array([_rot(x) for x in q])
    # frame: held on the ground at the scenario's initial pose (NED world, FRD body, w-first, body->NED)
    assert np.allclose(Rs[0], sc.S0[0, 3:12].reshape(3, 3), atol=1e-6)
    acc = np.array([[m.xacc, m.yacc, m.zacc] for m in sensors])
    gyro = np.array([[m.xgyro, m.ygyro, m.zgyro] for m in sensors])
    mag = np.array([[m.xmag, m.ymag, m.zmag] for m in sensors])
    rates = np.array([[m.rollspeed, m.pitchspeed, m.yawspeed] for m in states])
    sig_a, sig_g = 4e-3 / math.sqrt(H), 3.4e-4 / math.sqrt(H)
    held, free = slice(0, F), slice(F, total)
    # accelerometer = specific force: −Rᵀg on the ground (z ≈ −9.81 when level), f/m in flight
    e_held = acc[held] - np.array([-(R.T @ G) for R in Rs[held]])
    e_free = acc[free] - f_body / MASS
    for e, sig in ((e_held, sig_a), (e_free, sig_a), (gyro - rates, sig_g)):
        assert np.all(np.abs(e.mean(axis=0)) < 5 * sig / math.sqrt(len(e))), e.mean(axis=0)
        assert np.all(np.abs(e.std(axis=0) / sig - 1) < 0.2), (e.std(axis=0), sig)   # the documented noise
    e_mag = mag - np.array([R.T @ B_NED for R in Rs])
    assert np.all(np.abs(e_mag.mean(axis=0)) < 5 * 5e-3 / math.sqrt(len(e_mag)))
    assert np.all(np.abs(e_mag.std(axis=0) / 5e-3 - 1) < 0.2)
    # rigid-body physics in the frames: ω̇ = J⁻¹(τ − ω×Jω) (body), v̇ = R f/m + g (NED)
    tau = c_free[:3] * MW[:3]
    om = rates[F:]
    wd_pred = np.array([np.linalg.solve(J, tau - np.cross(w, J @ w)) for w in om[:-1]])
    wd_meas = np.diff(om, axis=0) / H
    assert np.abs(wd_meas - wd_pred).max() < 2e-3 * np.abs(wd_pred).max() + 1e-4
    v = np.array([[m.vx, m.vy, m.vz] for m in states], dtype=float) / 100     # cm/s -> m/s
    a_ned = np.array([R @ (f_body / MASS) + G for R in Rs])
    v_pred = np.concatenate([[0.0], np.cumsum(0.5 * (a_ned[F:-1, 2] + a_ned[F + 1:, 2]) * H)])
    assert np.all(np.abs(v[F:, 2] - v[F, 2] - v_pred) <= 0.03)    # down is +z, cm quantisation
    assert v[-1, 2] > 1.0                                                            # it does fall (NED)
    # GPS agrees with the ground truth; positions and altitude in the documented geodetic frame
    by_t = {m.time_usec: m for m in states}
    for g in gps:
        s = by_t[g.time_usec - srv.epoch_us]
        assert (g.lat, g.lon, g.alt) == (s.lat, s.lon, s.alt) and (g.vn, g.ve, g.vd) == (s.vx, s.vy, s.vz)
    p0 = sc.S0[0, 0:3]
    lat0 = LAT0 + math.degrees(p0[0] / RE)
    lon0 = LON0 + math.degrees(p0[1] / (RE * math.cos(math.radians(LAT0))))
    assert abs(states[0].lat - lat0 * 1e7) <= 1 and abs(states[0].lon - lon0 * 1e7) <= 1
    assert abs(states[0].alt - (ALT0 - p0[2]) * 1000) <= 1
    alt = np.array([m.alt for m in states]) / 1000.0
    dz = -(alt[-1] - alt[F])
    assert abs(dz - np.sum(0.5 * (v[F:-1, 2] + v[F + 1:, 2]) * H)) < 0.02
    # barometer: ISA pressure at the altitude, σ = 0.01 hPa; pressure_alt = the altitude
    p_isa = 1013.25 * (1 - 2.25577e-5 * alt) ** 5.25588
    e_p = np.array([m.abs_pressure for m in sensors]) - p_isa
    assert abs(e_p.mean()) < 5 * 0.01 / math.sqrt(len(e_p)) + 1e-4 and abs(e_p.std() / 0.01 - 1) < 0.2
    assert np.allclose([m.pressure_alt for m in sensors], alt, atol=2e-3)


@pytest.mark.realtime
def test_px4_simulator_survives_garbage_and_reconnects():
    from bridge.vehicles.sim_px4 import Px4SimServer
    from sim_clients import Px4Client

    srv = Px4SimServer(load(), port=0, step=H, noise=False, lockstep_timeout=60.0)
    with _Thread(srv):
        for attempt in range(2):
            cl = Px4Client(srv.links[0].port)
            try:
                cl.start()
                t0 = cl.clock_us
                cl.sock.sendall(b"\xfd\x09garbage-not-mavlink" * 20)   # counted, skipped
                cl.send([0.0] * 16, armed=False)
                cl.step()
                assert cl.clock_us == t0 + 4000
            finally:
                cl.close()
    assert srv.stats()["malformed"] > 0 and srv.stats()["connections"] == 2


# ------------------------------------------------------------------------------------ ArduPilot
def _servo(count, pwm, rate=400, channels=16, magic=None):
    magic = magic or (18458 if channels == 16 else 29569)
    pwm = list(pwm) + [1500] * (channels - len(pwm))
    return struct.pack(f"<HHI{channels}H", magic, rate, count, *pwm)


def _json_reply(sock, timeout=5.0):
    r, _, _ = select.select([sock], [], [], timeout)
    assert r, "no JSON reply"
    data = sock.recv(65536)
    text = data.decode()
    assert text.startswith("\n") and text.endswith("\n") and text.count("\n") == 2   # the documented framing
    return data, json.loads(text)


@pytest.mark.realtime
def test_ardupilot_json_lockstep_1000_frames():
    from bridge.vehicles.sim_ardupilot import ArduPilotJsonServer

    sc = _gravity_scenario()
    srv = ArduPilotJsonServer(sc, port=0, noise=True, seed=3)
    rate, n = 400, 1000
    h = 1.0 / rate
    c = np.array([2e-3, -2e-3, 2e-3, 0.1, -0.05, -0.3])     # 1 µs of PWM is 2e-3 of the range
    pwm = [int(round(1500 + 500 * x)) for x in c]          # direct mapping: bidirectional, 1500 neutral
    c_q = (np.array(pwm) - 1500) / 500.0
    with _Thread(srv):
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind(("127.0.0.1", 0))
        addr = ("127.0.0.1", srv.links[0].port)
        frames = []
        try:
            for k in range(1, n + 1):
                sock.sendto(_servo(k, pwm, rate, channels=32 if k % 100 == 0 else 16), addr)
                raw, d = _json_reply(sock)
                frames.append(d)
                if k == 500:   # a duplicate frame: the same reply, no step
                    sock.sendto(_servo(k, pwm, rate), addr)
                    raw2, _ = _json_reply(sock)
                    assert raw2 == raw
                if k == 600:   # malformed packets: no reply
                    for bad in (b"\x00" * 10, _servo(k + 1, pwm, rate, magic=1234), _servo(k + 1, pwm, 0)):
                        sock.sendto(bad, addr)
                    r, _, _ = select.select([sock], [], [], 0.2)
                    assert not r
            # SITL restarted: frame_count goes back, the body starts again from its initial state
            sock.sendto(_servo(1, [1500] * 6, rate), addr)
            _, d_reset = _json_reply(sock)
        finally:
            sock.close()
    st = srv.stats()
    assert st["steps"] == n + 1 and st["duplicates"] == 1 and st["malformed"] == 3 and st["resets"] == 1
    for key in ("timestamp", "imu", "position", "velocity", "quaternion"):
        assert all(key in d for d in frames)
    t = np.array([d["timestamp"] for d in frames])
    assert np.allclose(t, np.arange(1, n + 1) * h, rtol=0, atol=1e-9)
    q = np.array([d["quaternion"] for d in frames])
    assert np.allclose(np.linalg.norm(q, axis=1), 1, atol=1e-9)
    Rs = np.array([_rot(x) for x in q])
    p = np.array([d["position"] for d in frames])
    v = np.array([d["velocity"] for d in frames])
    acc = np.array([d["imu"]["accel_body"] for d in frames])
    gyro = np.array([d["imu"]["gyro"] for d in frames])
    f = c_q[3:] * MW[3:]
    sig_a, sig_g = 4e-3 / math.sqrt(h), 3.4e-4 / math.sqrt(h)
    e = acc - f / MASS
    assert np.all(np.abs(e.mean(axis=0)) < 5 * sig_a / math.sqrt(n)) and np.all(np.abs(e.std(axis=0) / sig_a - 1) < 0.2)
    # NED velocity: v̇ = R f/m + g (gravity along +z, down), exact float64 numbers in the JSON
    a_pred = np.array([R @ (f / MASS) + G for R in Rs])
    a_meas = np.diff(v, axis=0) / h
    assert np.abs(a_meas - 0.5 * (a_pred[:-1] + a_pred[1:])).max() < 1e-3
    assert np.abs(np.diff(p, axis=0) - 0.5 * (v[:-1] + v[1:]) * h).max() < 1e-6
    # gyro (FRD body rates): the rotation between consecutive quaternions is ≈ ω h
    dq = [np.linalg.norm(np.array(_rot(q[k]).T @ _rot(q[k + 1]) - np.eye(3))) / math.sqrt(2) for k in range(n - 1)]
    om_norm = np.linalg.norm(gyro[1:], axis=1)
    assert abs(np.mean(dq) / h - np.mean(om_norm)) < 0.02 * np.mean(om_norm) + 5 * sig_g / math.sqrt(n)
    # after the reset: one step from the initial pose (it had fallen ~30 m before)
    assert np.abs(np.array(d_reset["position"]) - sc.S0[0, 0:3]).max() < 1e-3 < np.abs(p[-1] - sc.S0[0, 0:3]).max()


@pytest.mark.realtime
def test_ardupilot_json_holds_until_motors_spin():
    """Unidirectional rotors (allocation): PWM ≤ 1000 µs = stopped, the body rests on the ground
    and reads −Rᵀg; above, it moves."""
    from bridge.vehicles.sim_ardupilot import ArduPilotJsonServer

    sc = _gravity_scenario(["bridge.mapping=\"allocation\"", "bridge.allocation={max_thrust = 60.0}"])
    srv = ArduPilotJsonServer(sc, port=0, noise=False)
    with _Thread(srv):
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind(("127.0.0.1", 0))
        addr = ("127.0.0.1", srv.links[0].port)
        try:
            out = []
            for k in range(1, 41):
                sock.sendto(_servo(k, [1000] * 6 if k <= 20 else [1100] * 6, 400), addr)
                out.append(_json_reply(sock)[1])
        finally:
            sock.close()
    R0 = sc.S0[0, 3:12].reshape(3, 3)
    for d in out[:20]:
        assert np.allclose(d["imu"]["accel_body"], -(R0.T @ G), atol=1e-12)
        assert np.allclose(d["position"], sc.S0[0, 0:3]) and np.allclose(d["velocity"], 0)
    assert not np.allclose(out[-1]["velocity"], 0)


def test_sim_cli_errors_are_one_line_exit_2():
    import subprocess
    import sys

    from _bridge import HIL, ROOT

    busy = socket.socket()
    busy.bind(("127.0.0.1", 0))
    busy.listen(1)
    port = busy.getsockname()[1]
    try:
        alloc = ["--set", 'bridge.mapping="allocation"']
        for args, key in ((["--sim-protocol", "px4"], "--sim-protocol"),
                          (["--sim-protocol", "px4", "--scenario", HIL, *alloc, "--sim-port", str(port)], "--sim-port"),
                          (["--sim-protocol", "px4", "--scenario", HIL, *alloc, "--sim-step", "0"], "--sim-step"),
                          (["--sim-protocol", "px4", "--scenario", HIL], "bridge.mapping"),   # direct: refused
                          (["--sim-protocol", "ardupilot", "--scenario", HIL, "--count", "1"], "--count"),
                          (["--sim-protocol", "ardupilot", "--scenario", HIL, "--write-params", "x.parm"],
                           "--write-params")):    # gravity-free: no hover throttle
            r = subprocess.run([sys.executable, "-m", "cosim.cli", "vehicle", *args], capture_output=True, text=True,
                               timeout=120, cwd=str(ROOT))
            lines = r.stderr.strip().splitlines()
            assert r.returncode == 2 and len(lines) == 1 and key in lines[0], (r.returncode, r.stderr)
    finally:
        busy.close()
