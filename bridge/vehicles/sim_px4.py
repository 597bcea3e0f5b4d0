"""`se3sync vehicle --sim-protocol px4`: the plant as PX4's simulator (the role Gazebo's
mavlink_interface plugin plays for PX4 SITL's `simulator_mavlink` module).

Read against PX4's own sources (PX4 cannot be built here): ``src/modules/simulation/
simulator_mavlink/SimulatorMavlink.cpp`` (PX4 connects over TCP; its lockstep clock is HIL_SENSOR
``time_usec`` of sensor id 0; it answers with HIL_ACTUATOR_CONTROLS = pwm_out_sim's outputs,
``mode`` bit 128 when armed), ``src/modules/simulation/pwm_out_sim/PWMSim.cpp`` (a non-reversible
motor's output is (pwm − PWM_MAIN_MINn)/(PWM_MAIN_MAXn − PWM_MAIN_MINn) ∈ [0, 1], others
[−1, 1]), the ``px4-rc.simulator`` start script (waits for the first HIL_SENSOR before starting the
other modules) and Gazebo's ``mavlink_interface.cpp`` (streams sensors until the first
HIL_ACTUATOR_CONTROLS, then lockstep with a 1 s poll timeout after which it steps anyway).

Transport: TCP; vehicle i listens on ``port + i − 1`` (default 4560: PX4 SITL instance n connects
to 4560 + n). Per connection:

* **start-up** (PX4 needs sensors to flow before its modules produce any actuator output): step k's
  messages are sent paced by the wall clock, one step per h seconds, the body stepping with zero
  controls (it stands on the ground, or is held), until the first HIL_ACTUATOR_CONTROLS arrives;
* **lockstep** from then on: one exchange per step of h seconds,

    simulator -> PX4   HIL_GPS (every ``gps_period``, default 0.1 s), HIL_STATE_QUATERNION (ground
                       truth), then HIL_SENSOR (time_usec = (k+1)·h: PX4 takes 0 as "no time"),
                       HEARTBEAT (1 Hz)
    PX4 -> simulator   HIL_ACTUATOR_CONTROLS: controls[0:6] -> the scenario's mapping (allocation:
                       PX4's motor outputs 0..1 are the rotor thrusts; see --write-params)

  and only then does the body advance by h. If no HIL_ACTUATOR_CONTROLS comes within
  ``lockstep_timeout`` (1 s of wall time, as Gazebo) the body steps anyway with the last controls,
  counted (``lockstep_timeouts``) and said once per stall.

Frames and units (common.xml): HIL_SENSOR acc = specific force in FRD (m/s², on the ground −g on
z), gyro FRD (rad/s), mag FRD (gauss), abs_pressure (hPa), pressure_alt (m), temperature (°C),
fields_updated = 0x1BFF (accelerometer, gyro, magnetometer, barometer; not the differential
pressure bit: there is no airspeed sensor), id 0. HIL_GPS time_usec in UTC (µs since 1970: the
server's start, whole seconds, plus simulated time), lat/lon (degE7), alt (mm, MSL), eph/epv = 100
(1.0 m), vel/vn/ve/vd (cm/s, NED), cog (cdeg, 65535 below 1 cm/s), fix 3-D, 10 satellites.
HIL_STATE_QUATERNION quaternion w-first (FRD -> NED), body rates (rad/s), lat/lon/alt as HIL_GPS,
vx/vy/vz (cm/s NED), accelerations in mG (FRD). Every integer field is clamped to its type (a body
far away or fast gives a saturated field, never an encoding error; counted, see below). Noise:
`bridge.vehicles.sim_body.Noise` (white, on HIL_SENSOR only; GPS and ground truth exact).

Clients are untrusted: sends are non-blocking into a bounded buffer per connection (a client that
does not read is dropped once ``send_buffer`` bytes are waiting: ``slow_clients``); a connection
that sends no HIL_ACTUATOR_CONTROLS for ``idle_timeout`` seconds is dropped (``idle_drops``);
malformed bytes are counted (``malformed``) and skipped; other messages are counted and ignored;
a diverging body is reset (``diverged``). No client can stop another vehicle, nor take more than
its share of the server:

* a HIL_ACTUATOR_CONTROLS advances the body only if it answers the HIL_SENSOR actually sent (its
  ``time_usec`` is that step's stamp: PX4 stamps it with ``hrt_absolute_time()``, its lockstep
  clock, set from that HIL_SENSOR); others (stale, repeated or guessed stamps) are counted
  (``stale_controls``, said once per connection) and change nothing — the first one of a
  connection, which ends the start-up streaming, excepted;
* each round of the server's loop takes at most one step per vehicle, reads at most
  ``RECV_SIZE`` bytes and handles at most ``MSGS_PER_ROUND`` messages per connection; the rest
  waits, and a connection with more than ``BACKLOG_MAX`` bytes waiting is not read until they are
  handled (``backlog_pauses``: TCP then holds the client back);
* an integer field out of its type's range is clamped (``clamped_fields``, per vehicle; said once
  per vehicle).

The protocol has no authentication: whoever can connect to the port drives the vehicle.
"""
from __future__ import annotations

import select
import socket
import sys
import threading
import time

import numpy as np

from controller import layout
from controller.errors import Se3SyncError

from bridge.mavlink.link import mavlink2
from .sim_body import (G0, B_NED, Diverged, Noise, bodies_from_scenario, isa_pressure_hpa, isa_temperature_c,
                       ned_to_geodetic)

M = mavlink2
DEFAULT_PORT = 4560
# HIL_SENSOR fields_updated (PX4 SimulatorMavlink.hpp SensorSource): accel 0b111, gyro 0b111000,
# mag 0b111000000, baro 0b1101000000000; the differential pressure bit 0b10000000000 is left out
FIELDS_SENSORS = 0x1BFF
LOCKSTEP_TIMEOUT = 1.0           # s of wall time without HIL_ACTUATOR_CONTROLS before stepping anyway
IDLE_TIMEOUT = 30.0              # s of wall time without HIL_ACTUATOR_CONTROLS before dropping a client
SEND_BUFFER = 256 * 1024         # bytes waiting for a client before it is dropped (≈ 1,000 steps)
KERNEL_SNDBUF = 64 * 1024        # the connection's kernel send buffer
# fair share: per connection and round of the loop, at most one step, one read of RECV_SIZE bytes
# and MSGS_PER_ROUND messages (PX4 sends one HIL_ACTUATOR_CONTROLS of 93 bytes per step, and a
# HEARTBEAT a second); above BACKLOG_MAX unhandled bytes the connection is not read at all
RECV_SIZE = 4096
MSGS_PER_ROUND = 8
BACKLOG_MAX = 16 * 1024
I16, I32 = (-32768, 32767), (-2 ** 31, 2 ** 31 - 1)


def _int(x: float, lo: int, hi: int, clamped: list | None = None, name: str = "") -> int:
    """An integer field: rounded and clamped to its type, never an encoding error (a clamped or
    non-finite value appends ``name`` to ``clamped``)."""
    if not np.isfinite(x):
        if clamped is not None:
            clamped.append(name)
        return 0
    r = round(x)
    if lo <= r <= hi:
        return int(r)
    if clamped is not None:
        clamped.append(name)
    return int(min(hi, max(lo, r)))


class _Px4Link:
    """One PX4 instance: listening socket, connection, parser, the body, the lockstep state."""

    def __init__(self, body, host: str, port: int, sysid: int):
        self.body = body
        self.lsock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.lsock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.lsock.bind((host, port))
        self.lsock.listen(4)
        self.lsock.setblocking(False)
        self.port = self.lsock.getsockname()[1]
        self.sysid = sysid
        self.conn = None
        self.mav = M.MAVLink(None, srcSystem=sysid, srcComponent=M.MAV_COMP_ID_AUTOPILOT1)
        self.mav.robust_parsing = True
        self.out = bytearray()      # bytes waiting for the client
        self.k = 0                  # steps taken in this connection
        self.lockstep = False       # False: start-up streaming (wall clock), True: lockstep
        self.waiting = False        # lockstep: step k's HIL_SENSOR sent, HIL_ACTUATOR_CONTROLS awaited
        self.t_sent = 0.0           # wall time step k's sensors were sent
        self.next_stream = 0.0      # start-up: wall time of the next streamed step
        self.last_actuator = 0.0    # wall time of the last HIL_ACTUATOR_CONTROLS (or the accept)
        self.controls = np.zeros(16)
        self.stalled = False        # a lockstep timeout was said (once per stall)
        self.next_hb = 0.0
        self.sent_us = 0            # time_usec of the HIL_SENSOR sent last (the step an answer must name)
        self.more = False           # messages may be waiting in the parser (handle them next round)
        self.paused = False         # not read: more than BACKLOG_MAX bytes wait to be handled
        self.said_stale = False     # stale HIL_ACTUATOR_CONTROLS said (once per connection)
        self.said_clamped = False   # clamped fields said (once per vehicle)
        self.counts = {"steps": 0, "streamed_steps": 0, "lockstep_timeouts": 0, "stale_controls": 0,
                       "clamped_fields": 0, "backlog_pauses": 0, "diverged": 0}


class Px4SimServer:
    """Serves each scenario vehicle as one PX4 simulator endpoint (TCP; start-up streaming, then lockstep)."""

    def __init__(self, scenario, *, host: str = "127.0.0.1", port: int = DEFAULT_PORT, step: float = 0.004,
                 gps_period: float = 0.1, noise: bool = True, seed: int = 0,
                 lockstep_timeout: float = LOCKSTEP_TIMEOUT, idle_timeout: float = IDLE_TIMEOUT,
                 send_buffer: int = SEND_BUFFER, on_event=None):
        self.h = float(step)
        self.h_us = int(round(self.h * 1e6))
        if self.h_us < 1 or abs(self.h_us - self.h * 1e6) > 1e-6:
            raise Se3SyncError(f"--sim-step: must be a whole number of microseconds > 0, got {step:g}")
        g = gps_period / self.h
        if abs(g - round(g)) > 1e-9 or round(g) < 1:
            raise Se3SyncError(f"--sim-gps-period: must be a whole number of steps of {self.h:g} s, got {gps_period:g}")
        self.gps_every = int(round(g))
        self.lockstep_timeout = float(lockstep_timeout)
        self.idle_timeout = float(idle_timeout)
        self.send_buffer = int(send_buffer)
        self.epoch_us = int(time.time()) * 1_000_000     # HIL_GPS: UTC of simulated time 0
        self.noise = Noise(self.h, noise, seed)
        self.on_event = on_event or (lambda text: print(f"se3sync vehicle: {text}", file=sys.stderr, flush=True))
        self.counters = {"sent": 0, "received": 0, "malformed": 0, "ignored": 0, "steps": 0, "connections": 0,
                         "streamed_steps": 0, "lockstep_timeouts": 0, "slow_clients": 0, "idle_drops": 0,
                         "diverged": 0, "stale_controls": 0, "clamped_fields": 0, "backlog_pauses": 0, "rounds": 0}
        self._stop = threading.Event()
        self.ready = threading.Event()
        self.links: list[_Px4Link] = []
        self._bodies = bodies_from_scenario(scenario, "px4sim")
        try:
            for i, b in enumerate(self._bodies):
                self.links.append(_Px4Link(b, host, port + i if port else 0, i + 1))
        except OSError:
            self.close()
            raise

    # ------------------------------------------------------------------ messages
    def sensor_messages(self, ln: _Px4Link) -> list:
        """The messages of step k: HIL_GPS when due, HIL_STATE_QUATERNION, HIL_SENSOR (last)."""
        b, mav, nz = ln.body, ln.mav, self.noise
        t_us = (ln.k + 1) * self.h_us
        R = b.R
        acc = nz.add(b.specific_force(), nz.accel)
        gyro = nz.add(b.omega, nz.gyro)
        mag = nz.add(R.T @ B_NED, nz.mag)
        p = b.S[layout.P]
        clamped: list = []          # names of the fields clamped in this step's messages
        lat, lon, alt = ned_to_geodetic(p, clamped)
        if not -1000.0 <= alt <= 40000.0:       # the ISA model's range
            clamped.append("abs_pressure")
        pres = float(nz.add(isa_pressure_hpa(max(-1000.0, min(alt, 40000.0))), nz.baro))
        sensor = mav.hil_sensor_encode(t_us, acc[0], acc[1], acc[2], gyro[0], gyro[1], gyro[2], mag[0], mag[1],
                                       mag[2], pres, 0.0, alt, isa_temperature_c(alt), FIELDS_SENSORS, 0)
        v = b.v_ned
        lat7 = _int(lat * 1e7, *I32, clamped, "lat")
        lon7 = _int(lon * 1e7, *I32, clamped, "lon")
        alt_mm = _int(alt * 1000, *I32, clamped, "alt")
        vcm = [_int(x * 100, *I16, clamped, name) for x, name in zip(v, ("vn", "ve", "vd"))]
        sf_mg = [_int(x / G0 * 1000, *I16, clamped, name)
                 for x, name in zip(b.specific_force(), ("xacc", "yacc", "zacc"))]
        om = b.omega
        # ground truth and GPS first, HIL_SENSOR last: PX4 advances its clock on HIL_SENSOR, so the
        # other data of the same instant is already there
        out = []
        if ln.k % self.gps_every == 0:
            gs = float(np.hypot(v[0], v[1]))
            # course in [0, 360)° as centidegrees 0..35999 (359.999° rounds to 0, not 36000)
            cog = int(round((np.degrees(np.arctan2(v[1], v[0])) % 360.0) * 100)) % 36000 if gs > 0.01 else 65535
            out.append(mav.hil_gps_encode(self.epoch_us + t_us, 3, lat7, lon7, alt_mm, 100, 100,
                                          _int(gs * 100, 0, 65534, clamped, "vel"), vcm[0], vcm[1], vcm[2], cog,
                                          10, 0, 0))
        out.append(mav.hil_state_quaternion_encode(t_us, list(b.q), om[0], om[1], om[2], lat7, lon7, alt_mm,
                                                   vcm[0], vcm[1], vcm[2], 0, 0, sf_mg[0], sf_mg[1], sf_mg[2]))
        out.append(sensor)
        if clamped:
            self._clamped(ln, clamped, t_us)
        return out

    def _clamped(self, ln: _Px4Link, names: list, t_us: int) -> None:
        """Fields out of their types' ranges: counted per vehicle, said once per vehicle."""
        self.counters["clamped_fields"] += len(names)
        ln.counts["clamped_fields"] += len(names)
        if not ln.said_clamped:
            ln.said_clamped = True
            self.on_event(f"vehicle {ln.sysid}: {', '.join(dict.fromkeys(names))} out of range of their MAVLink "
                          f"fields at t = {t_us * 1e-6:.3f} s (the body is far away or fast): clamped, counted "
                          "in clamped_fields (said once per vehicle)")

    def _send(self, ln: _Px4Link, msg) -> None:
        if ln.conn is None:
            return
        buf = msg.pack(ln.mav)
        ln.mav.seq = (ln.mav.seq + 1) & 0xFF
        ln.out += buf
        self.counters["sent"] += 1
        self._flush(ln)

    def _flush(self, ln: _Px4Link) -> None:
        """Non-blocking: what the client's socket takes now; the rest waits (bounded)."""
        while ln.out and ln.conn is not None:
            try:
                n = ln.conn.send(ln.out)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                self._drop(ln)
                return
            del ln.out[:n]
        if len(ln.out) > self.send_buffer:
            self.counters["slow_clients"] += 1
            self.on_event(f"vehicle {ln.sysid}: the client reads nothing ({len(ln.out)} bytes waiting): dropped")
            self._drop(ln)

    def _send_step(self, ln: _Px4Link, now: float) -> None:
        ln.sent_us = (ln.k + 1) * self.h_us
        for m in self.sensor_messages(ln):
            self._send(ln, m)
        ln.t_sent = now
        ln.waiting = ln.lockstep and ln.conn is not None

    def _advance(self, ln: _Px4Link, controls) -> None:
        """One step of h of the body (a diverging body is reset, counted and said)."""
        try:
            ln.body.step(controls, self.h)
        except Diverged as exc:
            self.counters["diverged"] += 1
            ln.counts["diverged"] += 1
            ln.body.reset()
            self.on_event(f"vehicle {ln.sysid} diverged ({exc}); reset to its initial state")
        ln.k += 1
        self.counters["steps"] += 1
        ln.counts["steps"] += 1

    def _on_message(self, ln: _Px4Link, m, now: float) -> None:
        if m.get_type() == "BAD_DATA":
            self.counters["malformed"] += 1
            return
        self.counters["received"] += 1
        if m.get_msgId() != M.MAVLINK_MSG_ID_HIL_ACTUATOR_CONTROLS:
            self.counters["ignored"] += 1
            return
        ln.last_actuator = now
        if not ln.lockstep:
            ln.lockstep = True                  # the first actuator controls (any stamp): lockstep from now on
            self.on_event(f"vehicle {ln.sysid}: first HIL_ACTUATOR_CONTROLS after {ln.k} streamed steps: lockstep")
        elif not ln.waiting or m.time_usec != ln.sent_us:
            self._stale(ln, m.time_usec)        # not the answer to the step sent: no step
            return
        c = np.asarray(m.controls, dtype=np.float64)
        ln.controls[:len(c)] = c[:16]
        if ln.body.held and (m.mode & M.MAV_MODE_FLAG_SAFETY_ARMED):
            ln.body.release()
        if ln.stalled:
            ln.stalled = False
            self.on_event(f"vehicle {ln.sysid}: HIL_ACTUATOR_CONTROLS again: lockstep resumed")
        self._advance(ln, ln.controls[:6])
        ln.waiting = False
        self._send_step(ln, now)

    def _stale(self, ln: _Px4Link, t_us: int) -> None:
        self.counters["stale_controls"] += 1
        ln.counts["stale_controls"] += 1
        if not ln.said_stale:
            ln.said_stale = True
            self.on_event(f"vehicle {ln.sysid}: HIL_ACTUATOR_CONTROLS stamped {t_us} µs does not answer the "
                          f"HIL_SENSOR sent ({ln.sent_us} µs): ignored, counted in stale_controls (said once per "
                          "connection)")

    def _handle(self, ln: _Px4Link, data: bytes, now: float) -> None:
        """Feed ``data`` to the link's parser and handle what is waiting there: at most MSGS_PER_ROUND
        messages and at most one step; the rest waits for the next round (``ln.more``)."""
        steps = ln.counts["steps"]
        mav = ln.mav
        ln.more = False
        for i in range(MSGS_PER_ROUND):
            try:
                m = mav.parse_char(data if i == 0 else b"")
            except Exception:  # noqa: BLE001 (network input is untrusted)
                self.counters["malformed"] += 1
                continue
            if m is None:
                break
            self._on_message(ln, m, now)
            if ln.conn is None:
                return
            if ln.counts["steps"] != steps:
                ln.more = mav.buf_len() > 0
                break
        else:
            ln.more = True
        if mav.buf_index > 4 * BACKLOG_MAX:       # pymavlink frees its buffer only once it is empty
            del mav.buf[:mav.buf_index]
            mav.buf_index = 0

    def _accept(self, ln: _Px4Link, now: float) -> None:
        try:
            conn, _ = ln.lsock.accept()
        except OSError:
            return
        conn.setblocking(False)
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        # a fixed kernel send buffer (no autotuning to megabytes): what a client leaves unread
        # piles up in ln.out, where it is bounded and counted
        conn.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, KERNEL_SNDBUF)
        ln.conn = conn
        ln.mav = M.MAVLink(None, srcSystem=ln.sysid, srcComponent=M.MAV_COMP_ID_AUTOPILOT1)
        ln.mav.robust_parsing = True
        ln.out = bytearray()
        if ln.k:                       # a new session starts from the initial state at t = 0
            ln.body.reset(clock=True)
        ln.k = 0
        ln.lockstep = ln.waiting = ln.stalled = ln.more = ln.paused = ln.said_stale = False
        ln.controls[:] = 0.0
        ln.last_actuator = now
        ln.next_stream = now + self.h
        ln.next_hb = now
        self.counters["connections"] += 1
        self._send_step(ln, now)       # PX4 waits for the first HIL_SENSOR to start its clock

    def _drop(self, ln: _Px4Link) -> None:
        if ln.conn is not None:
            try:
                ln.conn.close()
            except OSError:
                pass
        ln.conn = None
        ln.waiting = ln.more = ln.paused = False
        ln.out = bytearray()

    def _timers(self, ln: _Px4Link, now: float) -> None:
        if ln.conn is None:
            return
        if now - ln.last_actuator > self.idle_timeout:
            self.counters["idle_drops"] += 1
            self.on_event(f"vehicle {ln.sysid}: no HIL_ACTUATOR_CONTROLS for {self.idle_timeout:g} s: "
                          "connection dropped")
            self._drop(ln)
            return
        if not ln.lockstep:
            if now - ln.next_stream > 10 * self.h:      # fell far behind (suspended?): no burst
                ln.next_stream = now
            if now >= ln.next_stream:                   # one step per round, as every other step
                self._advance(ln, np.zeros(6))
                self.counters["streamed_steps"] += 1
                ln.counts["streamed_steps"] += 1
                self._send_step(ln, now)
                ln.next_stream += self.h
        elif ln.waiting and now - ln.t_sent > self.lockstep_timeout:
            self.counters["lockstep_timeouts"] += 1
            ln.counts["lockstep_timeouts"] += 1
            if not ln.stalled:
                ln.stalled = True
                self.on_event(f"vehicle {ln.sysid}: no HIL_ACTUATOR_CONTROLS for {self.lockstep_timeout:g} s at "
                              f"step {ln.k}: stepping anyway with the last controls")
            self._advance(ln, ln.controls[:6])
            ln.waiting = False
            self._send_step(ln, now)
        if ln.conn is not None and now >= ln.next_hb:
            ln.next_hb = now + 1.0
            self._send(ln, ln.mav.heartbeat_encode(M.MAV_TYPE_GENERIC, M.MAV_AUTOPILOT_INVALID, 0, 0,
                                                   M.MAV_STATE_ACTIVE))

    # ------------------------------------------------------------------ loop
    def stop(self) -> None:
        self._stop.set()

    def run(self, duration: float | None = None) -> dict:
        """Serve until stop(), Ctrl-C or ``duration`` s. Each round of the loop: one select over the
        connections (a connection with a large backlog is left out), then per connection at most
        one read, MSGS_PER_ROUND messages and one step, then the timers (streaming, lockstep
        timeout, idle drop, heartbeat)."""
        end = None if duration is None else time.monotonic() + duration
        self.ready.set()
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                if end is not None and now >= end:
                    break
                fds, rfds, wfds = {}, [], []
                timeout = 0.05
                for ln in self.links:
                    if ln.conn is None:
                        fds[ln.lsock.fileno()] = ln
                        rfds.append(ln.lsock.fileno())
                        continue
                    fd = ln.conn.fileno()
                    fds[fd] = ln
                    backlog = ln.mav.buf_len() > BACKLOG_MAX
                    if backlog and not ln.paused:
                        self.counters["backlog_pauses"] += 1
                        ln.counts["backlog_pauses"] += 1
                    ln.paused = backlog
                    if not backlog:
                        rfds.append(fd)
                    if ln.out:
                        wfds.append(fd)
                    if ln.more:
                        timeout = 0.0
                    elif not ln.lockstep:
                        timeout = min(timeout, max(0.0, ln.next_stream - now))
                    elif ln.waiting:
                        timeout = min(timeout, max(0.0, ln.t_sent + self.lockstep_timeout - now))
                r, w, _ = select.select(rfds, wfds, [], timeout)
                self.counters["rounds"] += 1
                now = time.monotonic()
                for fd in w:
                    self._flush(fds[fd])
                readable = set(r)
                for ln in self.links:
                    if ln.conn is None:
                        if ln.lsock.fileno() in readable:
                            self._accept(ln, now)
                        continue
                    if ln.conn.fileno() in readable:
                        try:
                            data = ln.conn.recv(RECV_SIZE)
                        except (BlockingIOError, InterruptedError):
                            data = None
                        except OSError:
                            data = b""
                        if data == b"":
                            self._drop(ln)
                            continue
                        self._handle(ln, data or b"", now)
                    elif ln.more:
                        self._handle(ln, b"", now)
                now = time.monotonic()
                for ln in self.links:
                    self._timers(ln, now)
        except KeyboardInterrupt:
            pass
        return self.stats()

    def stats(self) -> dict:
        """The counters (all vehicles), ``vehicles`` (the same per vehicle), ``step_index`` (each
        connection's step) and ``ports``."""
        return dict(self.counters, vehicles=[dict(ln.counts) for ln in self.links],
                    step_index=[ln.k for ln in self.links], ports=[ln.port for ln in self.links])

    def close(self) -> None:
        for ln in self.links:
            self._drop(ln)
            ln.lsock.close()
        for b in getattr(self, "_bodies", []):
            b.close()
