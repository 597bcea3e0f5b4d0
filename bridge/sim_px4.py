"""`se3sync vehicle --sim-protocol px4`: the plant as PX4's simulator (the role Gazebo's
mavlink_interface plugin plays for PX4 SITL's `simulator_mavlink` module).

Transport: TCP; vehicle i listens on ``port + i − 1`` (default 4560: PX4 SITL instance n connects
to 4560 + n). Lockstep, one exchange per simulation step of h seconds:

  simulator -> PX4   HIL_GPS (every ``gps_period``, default 0.1 s), HIL_STATE_QUATERNION (ground
                     truth, every step), then HIL_SENSOR (every step, time_usec = k·h), all stamped
                     k·h; HEARTBEAT (1 Hz)
  PX4 -> simulator   HIL_ACTUATOR_CONTROLS: controls[0:6] -> the scenario's mapping (allocation:
                     rotor thrusts 0..1 = PX4's motor outputs; direct: the normalised wrench)

and only then does the body advance by h. PX4 runs its clock from HIL_SENSOR's time_usec.

Frames and units (common.xml): HIL_SENSOR acc = specific force in FRD (m/s², at rest −g on z),
gyro FRD (rad/s), mag FRD (gauss), abs_pressure (hPa), pressure_alt (m), temperature (°C),
fields_updated = 0x1FFF (all 13). HIL_GPS lat/lon (degE7), alt (mm, MSL), eph/epv = 100 (DOP 1.0),
vel/vn/ve/vd (cm/s, NED), cog (cdeg), fix 3-D, 10 satellites. HIL_STATE_QUATERNION quaternion
w-first (FRD -> NED), body rates (rad/s), lat/lon/alt as HIL_GPS, vx/vy/vz (cm/s NED), accelerations
in mG (FRD). Noise: `bridge.sim_body.Noise` (white, on HIL_SENSOR only; GPS and ground truth exact).
Until PX4 arms (MAV_MODE_FLAG_SAFETY_ARMED in HIL_ACTUATOR_CONTROLS.mode), the body is held on
"the ground" (`sim_body`).

Malformed bytes on the stream are counted (``malformed``) and skipped; other messages from PX4
(HEARTBEAT, …) are counted and ignored.
"""
from __future__ import annotations

import select
import socket
import threading
import time

import numpy as np

from controller.errors import Se3SyncError
from controller import layout

from .link import mavlink2
from .sim_body import G0, B_NED, Noise, bodies_from_scenario, isa_pressure_hpa, isa_temperature_c, ned_to_geodetic

M = mavlink2
DEFAULT_PORT = 4560
FIELDS_ALL = 0x1FFF


def _i16(x: float) -> int:
    """An int16 field (cm/s, mG): rounded and clamped, never an encoding error."""
    return int(min(32767, max(-32768, round(x)))) if np.isfinite(x) else 0


class _Px4Link:
    """One PX4 instance: listening socket, connection, parser, the body, the lockstep state."""

    def __init__(self, body, host: str, port: int, sysid: int):
        self.body = body
        self.lsock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.lsock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.lsock.bind((host, port))
        self.lsock.listen(1)
        self.lsock.setblocking(False)
        self.port = self.lsock.getsockname()[1]
        self.conn = None
        self.mav = M.MAVLink(None, srcSystem=sysid, srcComponent=M.MAV_COMP_ID_AUTOPILOT1)
        self.mav.robust_parsing = True
        self.k = 0
        self.waiting = False       # HIL_SENSOR of step k sent, HIL_ACTUATOR_CONTROLS awaited
        self.next_hb = 0.0


class Px4SimServer:
    """Serves each scenario vehicle as one PX4 simulator endpoint (lockstep over TCP)."""

    def __init__(self, scenario, *, host: str = "127.0.0.1", port: int = DEFAULT_PORT, step: float = 0.004,
                 gps_period: float = 0.1, noise: bool = True, seed: int = 0):
        self.h = float(step)
        self.h_us = int(round(self.h * 1e6))
        g = gps_period / self.h
        if abs(g - round(g)) > 1e-9 or round(g) < 1:
            raise Se3SyncError(f"--sim-gps-period: must be a whole number of steps of {self.h:g} s, got {gps_period:g}")
        self.gps_every = int(round(g))
        self.noise = Noise(self.h, noise, seed)
        self.counters = {"sent": 0, "received": 0, "malformed": 0, "ignored": 0, "steps": 0, "connections": 0}
        self._stop = threading.Event()
        self.ready = threading.Event()
        self.links: list[_Px4Link] = []
        bodies = bodies_from_scenario(scenario, "px4sim")
        try:
            for i, b in enumerate(bodies):
                self.links.append(_Px4Link(b, host, port + i if port else 0, i + 1))
        except OSError:
            for b in bodies[len(self.links):]:
                b.close()
            self.close()
            raise

    # ------------------------------------------------------------------ messages
    def _send(self, ln: _Px4Link, msg) -> None:
        buf = msg.pack(ln.mav)
        ln.mav.seq = (ln.mav.seq + 1) & 0xFF
        try:
            ln.conn.sendall(buf)
            self.counters["sent"] += 1
        except OSError:
            self._drop(ln)

    def sensor_messages(self, ln: _Px4Link) -> list:
        """The messages of step k: HIL_GPS when due, HIL_STATE_QUATERNION, HIL_SENSOR (last)."""
        b, mav, nz = ln.body, ln.mav, self.noise
        t_us = ln.k * self.h_us
        R = b.R
        acc = nz.add(b.specific_force(), nz.accel)
        gyro = nz.add(b.omega, nz.gyro)
        mag = nz.add(R.T @ B_NED, nz.mag)
        p = b.S[layout.P]
        lat, lon, alt = ned_to_geodetic(p)
        pres = float(nz.add(isa_pressure_hpa(alt), nz.baro))
        sensor = mav.hil_sensor_encode(t_us, acc[0], acc[1], acc[2], gyro[0], gyro[1], gyro[2], mag[0], mag[1],
                                       mag[2], pres, 0.0, alt, isa_temperature_c(alt), FIELDS_ALL, 0)
        v = b.v_ned
        lat7, lon7, alt_mm = int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1000))
        vcm = [_i16(x * 100) for x in v]
        sf_mg = [_i16(x / G0 * 1000) for x in b.specific_force()]
        om = b.omega
        # ground truth and GPS first, HIL_SENSOR last: PX4 advances its clock on HIL_SENSOR, so the
        # other data of the same instant is already there
        out = []
        if ln.k % self.gps_every == 0:
            gs = float(np.hypot(v[0], v[1]))
            cog = int(round((np.degrees(np.arctan2(v[1], v[0])) % 360.0) * 100)) % 36000 if gs > 0.01 else 65535
            out.append(mav.hil_gps_encode(t_us, 3, lat7, lon7, alt_mm, 100, 100, int(round(gs * 100)),
                                          vcm[0], vcm[1], vcm[2], cog, 10, 0, 0))
        out.append(mav.hil_state_quaternion_encode(t_us, list(b.q), om[0], om[1], om[2], lat7, lon7, alt_mm,
                                                   vcm[0], vcm[1], vcm[2], 0, 0, sf_mg[0], sf_mg[1], sf_mg[2]))
        out.append(sensor)
        return out

    def _send_step(self, ln: _Px4Link) -> None:
        for m in self.sensor_messages(ln):
            self._send(ln, m)
            if ln.conn is None:
                return
        ln.waiting = True

    def _on_message(self, ln: _Px4Link, m) -> None:
        if m.get_type() == "BAD_DATA":
            self.counters["malformed"] += 1
            return
        self.counters["received"] += 1
        if m.get_msgId() != M.MAVLINK_MSG_ID_HIL_ACTUATOR_CONTROLS or not ln.waiting:
            self.counters["ignored"] += 1
            return
        c = np.asarray(m.controls[:6], dtype=np.float64)
        if ln.body.held and (m.mode & M.MAV_MODE_FLAG_SAFETY_ARMED):
            ln.body.release()
        ln.body.step(c, self.h)
        ln.k += 1
        self.counters["steps"] += 1
        ln.waiting = False
        self._send_step(ln)

    def _drop(self, ln: _Px4Link) -> None:
        if ln.conn is not None:
            try:
                ln.conn.close()
            except OSError:
                pass
        ln.conn = None
        ln.waiting = False

    # ------------------------------------------------------------------ loop
    def stop(self) -> None:
        self._stop.set()

    def run(self, duration: float | None = None) -> dict:
        end = None if duration is None else time.monotonic() + duration
        self.ready.set()
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                if end is not None and now >= end:
                    break
                fds = {}
                for ln in self.links:
                    fds[(ln.conn or ln.lsock).fileno()] = ln
                r, _, _ = select.select(list(fds), [], [], 0.05)
                for fd in r:
                    ln = fds[fd]
                    if ln.conn is None:
                        try:
                            conn, _ = ln.lsock.accept()
                        except OSError:
                            continue
                        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                        ln.conn = conn
                        ln.mav = M.MAVLink(None, srcSystem=ln.mav.srcSystem, srcComponent=ln.mav.srcComponent)
                        ln.mav.robust_parsing = True
                        self.counters["connections"] += 1
                        self._send_step(ln)   # PX4 waits for the first HIL_SENSOR to start its clock
                        continue
                    try:
                        data = ln.conn.recv(65536)
                    except OSError:
                        data = b""
                    if not data:
                        self._drop(ln)
                        continue
                    try:
                        msgs = ln.mav.parse_buffer(data) or []
                    except Exception:  # noqa: BLE001 (network input is untrusted)
                        self.counters["malformed"] += 1
                        continue
                    for m in msgs:
                        self._on_message(ln, m)
                now = time.monotonic()
                for ln in self.links:
                    if ln.conn is not None and now >= ln.next_hb:
                        ln.next_hb = now + 1.0
                        self._send(ln, ln.mav.heartbeat_encode(M.MAV_TYPE_GENERIC, M.MAV_AUTOPILOT_INVALID, 0, 0,
                                                               M.MAV_STATE_ACTIVE))
        except KeyboardInterrupt:
            pass
        return self.stats()

    def stats(self) -> dict:
        return dict(self.counters, step_index=[ln.k for ln in self.links], ports=[ln.port for ln in self.links])

    def close(self) -> None:
        for ln in self.links:
            self._drop(ln)
            ln.lsock.close()
            ln.body.close()
