"""Test-side stand-ins for the flight stacks' simulator clients, written from the published
protocols (MAVLink common.xml HIL_* messages and PX4's SimulatorMavlink.cpp behaviour; ArduPilot's
libraries/SITL/examples/JSON/readme.md), and an autopilot stand-in that flies a multirotor through
either of them: arm after a spool-up, climb to 2 m, hold, land, detect the touchdown, disarm.

The autopilot mixes with the stacks' own published motor tables (angles and yaw factors from
ArduPilot's AP_MotorsMatrix.cpp, the same as PX4's hex_x.toml / quad X), not with se3sync's
allocation code: if se3sync's frame presets disagreed with the stacks', it would not fly."""
from __future__ import annotations

import json
import math
import os
import select
import socket
import struct
import sys
import threading

import numpy as np

os.environ.setdefault("MAVLINK20", "1")

from bridge.mavlink.link import mavlink2 as M  # noqa: E402

G = 9.80665
ARMED = M.MAV_MODE_FLAG_SAFETY_ARMED | M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
# (angle° from the nose towards the right, yaw factor: +1 CCW, −1 CW), motor 1..n
# ArduPilot libraries/AP_Motors/AP_MotorsMatrix.cpp (setup_quad_matrix X, setup_hexa_matrix PLUS/X)
STACK_FRAMES = {
    "quad-x": ((45, 1), (-135, 1), (-45, -1), (135, -1)),
    "hexa-plus": ((0, -1), (180, 1), (-120, -1), (60, 1), (-60, 1), (120, -1)),
    "hexa-x": ((90, -1), (-90, 1), (-30, -1), (150, 1), (30, 1), (-150, -1)),
}


def rot(q) -> np.ndarray:
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def stack_mixer(frame: str, arm: float, max_thrust: float, torque_coeff: float) -> np.ndarray:
    """(n, 4): motor thrust fractions from (τx, τy, τz, T) for the stack's published frame: a rotor
    at angle φ, arm L, gives roll −L sin φ, pitch L cos φ per N of thrust, yaw ±torque_coeff."""
    rows = []
    for ang, yf in STACK_FRAMES[frame]:
        a = math.radians(ang)
        rows.append([-arm * math.sin(a), arm * math.cos(a), yf * torque_coeff, 1.0])
    B = max_thrust * np.array(rows).T          # (4, n): [τx; τy; τz; T] = B c
    return np.linalg.pinv(B)


class Autopilot:
    """A multirotor autopilot stand-in on the ground-truth state (NED/FRD): position PD with gravity
    feed-forward, geometric attitude control (Lee et al. 2010) and the stack's mixer; a mission of
    disarmed → spool-up (armed, motors at `spin_arm`) → climb to `height` → hold → land at
    `descent` m/s → touchdown detected (the land detector: commanded thrust below 80 % of the
    weight and |v| < 0.1 m/s for 0.5 s; the ground holds the vehicle then) → disarmed."""

    def __init__(self, frame, mass, J, *, arm=0.25, max_thrust=15.0, torque_coeff=0.016, height=2.0,
                 hold=3.0, descent=0.5, spin_arm=0.1, spool=2.0):
        self.mix = stack_mixer(frame, arm, max_thrust, torque_coeff)
        self.n = len(STACK_FRAMES[frame])
        self.m, self.J = mass, np.asarray(J, float)
        self.height, self.hold_s, self.descent, self.spin_arm, self.spool_s = height, hold, descent, spin_arm, spool
        self.phase, self.t_phase = "disarmed", 0.0
        self.z_ref = 0.0
        self.low_since = None
        self.touchdown_detected = None   # time the land detector fired
        self.log = []           # (t, phase, p, v, thrust demand / weight)

    @property
    def armed(self) -> bool:
        return self.phase not in ("disarmed", "done")

    def _to(self, phase, t):
        self.phase, self.t_phase = phase, t

    def update(self, t, h, p, v, R, w, z0) -> np.ndarray:
        """Motor outputs 0..1 for the next step; z0 the home (ground) altitude in NED."""
        dt = t - self.t_phase
        if self.phase == "disarmed":
            if dt >= 0.5:
                self._to("spool", t)
            return np.zeros(self.n)
        if self.phase == "spool":
            if dt >= self.spool_s:
                self._to("climb", t)
                self.z_ref = z0
            return np.full(self.n, self.spin_arm)
        if self.phase == "done":
            return np.zeros(self.n)
        v_ref = 0.0
        if self.phase == "climb":                          # NED: up is −z; at most 1 m/s, easing in
            target = z0 - self.height
            v_ref = float(np.clip(1.5 * (target - self.z_ref), -1.0, 1.0))
            self.z_ref += v_ref * h
            if abs(p[2] - target) < 0.02 and abs(v[2]) < 0.05:
                self._to("hold", t)
        elif self.phase == "hold":
            if dt >= self.hold_s:
                self._to("land", t)
        elif self.phase == "land":
            self.z_ref += self.descent * h
            v_ref = self.descent
        # position loop (NED): a = kp e + kd e' ; the thrust vector F = m (a − g)
        e = np.array([0.0, 0.0, self.z_ref]) - p
        e[:2] = -p[:2]
        a = 4.0 * e + 4.0 * (np.array([0.0, 0.0, v_ref]) - v)
        F = self.m * (a - np.array([0.0, 0.0, G]))
        b3 = -F / np.linalg.norm(F)                     # body z (down) points along −F
        b1c = np.array([1.0, 0.0, 0.0])
        b2 = np.cross(b3, b1c)
        b2 /= np.linalg.norm(b2)
        Rd = np.column_stack([np.cross(b2, b3), b2, b3])
        T = float(-F @ R[:, 2])                          # thrust along the body's −z
        eR = 0.5 * np.array([(Rd.T @ R - R.T @ Rd)[2, 1], (Rd.T @ R - R.T @ Rd)[0, 2], (Rd.T @ R - R.T @ Rd)[1, 0]])
        tau = self.J @ (-100.0 * eR - 20.0 * w) + np.cross(w, self.J @ w)
        c = self.mix @ np.array([tau[0], tau[1], tau[2], max(T, 0.0)])
        if self.phase == "land":                         # the land detector
            low = T < 0.8 * self.m * G and np.linalg.norm(v) < 0.1
            self.low_since = (self.low_since if self.low_since is not None else t) if low else None
            if self.low_since is not None and t - self.low_since >= 0.5:
                self._to("done", t)
                self.touchdown_detected = t
                return np.zeros(self.n)
        self.log.append((t, self.phase, p.copy(), v.copy(), T / (self.m * G)))
        return np.clip(c, 0.0, 1.0)


# ------------------------------------------------------------------ PX4
class Px4Client:
    """What PX4 SITL does on its simulator link (SimulatorMavlink.cpp): connect over TCP, take the
    simulator's HIL_SENSOR stream as its clock, send no HIL_ACTUATOR_CONTROLS until that clock has
    advanced ``start_after`` seconds (PX4's modules start only then), then answer each step with
    HIL_ACTUATOR_CONTROLS stamped with its clock (mode bit 128 when armed)."""

    def __init__(self, port: int, host: str = "127.0.0.1", timeout: float = 30.0, rcvbuf: int | None = None):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        if rcvbuf:                           # before connect: the window the server sees
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        self.sock.settimeout(5)
        self.sock.connect((host, port))
        self.mav = M.MAVLink(None, srcSystem=1, srcComponent=1)
        self.pending: list = []
        self.timeout = timeout
        self.clock_us = 0
        self.messages: list = []          # everything received, in order

    def close(self):
        self.sock.close()

    def _fill(self, timeout):
        r, _, _ = select.select([self.sock], [], [], timeout)
        if not r:
            return False
        data = self.sock.recv(65536)
        if not data:
            raise ConnectionError("simulator closed the connection")
        self.pending.extend(self.mav.parse_buffer(data) or [])
        return True

    def step(self) -> list:
        """The messages up to and including the next HIL_SENSOR (the last of a step)."""
        got = []
        while True:
            while self.pending:
                m = self.pending.pop(0)
                got.append(m)
                self.messages.append(m)
                if m.get_type() == "HIL_SENSOR":
                    self.clock_us = m.time_usec
                    return got
            if not self._fill(self.timeout):
                raise TimeoutError("no HIL_SENSOR from the simulator")

    def drain(self, quiet: float = 0.3) -> list:
        """Everything that arrives until the link has been quiet for ``quiet`` s."""
        got = []
        while self._fill(quiet):
            pass
        while self.pending:
            m = self.pending.pop(0)
            got.append(m)
            self.messages.append(m)
            if m.get_type() == "HIL_SENSOR":
                self.clock_us = m.time_usec
        return got

    def start(self, start_after: float = 0.02) -> list:
        """Start-up: wait for the clock to advance, answer once, let the stream stop; returns every
        message received. Afterwards the simulator waits for the answer to the newest step."""
        got = []
        while self.clock_us < start_after * 1e6:
            got += self.step()
        self.send([0.0] * 16, armed=False)
        got += self.drain()
        return got

    def send(self, controls, armed: bool) -> None:
        c = list(controls) + [0.0] * (16 - len(controls))
        self.sock.sendall(self.mav.hil_actuator_controls_encode(self.clock_us, c, ARMED if armed else
                                                                M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 1)
                          .pack(self.mav))
        self.mav.seq = (self.mav.seq + 1) & 0xFF


def px4_controls_blob(mav, stamps, controls=(0.5,) * 16) -> bytes:
    """HIL_ACTUATOR_CONTROLS (armed) stamped with each of ``stamps``, back to back."""
    return b"".join(mav.hil_actuator_controls_encode(t, list(controls), ARMED, 1).pack(mav) for t in stamps)


def px4_flood(port: int, mode: str, host: str = "127.0.0.1", h_us: int = 4000, burst: int = 2000) -> None:
    """A PX4 client gone wrong, for the tests (run as ``python tests/sim_clients.py px4-flood PORT
    MODE``): starts as PX4 does (Px4Client.start), then reads everything the server sends (in a
    thread) and sends HIL_ACTUATOR_CONTROLS as fast as the server takes them, until the connection
    closes. ``mode`` "stale": stamped 0 (they answer no step); "guess": blocks of ``burst`` stamped
    with the newest HIL_SENSOR's time_usec and the next ``burst`` − 1 steps' (each a valid answer
    once the server gets that far)."""
    cl = Px4Client(port, host)
    cl.start()
    cl.sock.settimeout(None)
    clock = [cl.clock_us]

    def reader():
        mav = M.MAVLink(None)
        mav.robust_parsing = True
        while True:
            try:
                data = cl.sock.recv(65536)
            except OSError:
                return
            if not data:
                return
            if mode == "guess":
                for m in mav.parse_buffer(data) or []:
                    if m.get_type() == "HIL_SENSOR":
                        clock[0] = m.time_usec

    threading.Thread(target=reader, daemon=True).start()
    stale = px4_controls_blob(cl.mav, [0] * burst)
    while True:
        blob = stale if mode == "stale" else px4_controls_blob(cl.mav, [clock[0] + h_us * j for j in range(burst)])
        try:
            cl.sock.sendall(blob)
        except OSError:
            return


def ardupilot_flood(port: int, host: str = "127.0.0.1", rate: int = 400) -> None:
    """An ArduPilot JSON client gone wrong (``python tests/sim_clients.py ardupilot-flood PORT``):
    servo packets with a new frame_count each, as fast as it can send them, never waiting for a
    reply (the replies are read and thrown away); until killed."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind((host, 0))
    sock.setblocking(False)
    count = 0
    while True:
        for _ in range(64):
            count += 1
            try:
                sock.sendto(servo_packet(count, [1000] * 6, rate), (host, port))
            except (BlockingIOError, InterruptedError):
                select.select([], [sock], [], 0.01)
            except OSError:
                pass
        try:
            while True:
                sock.recv(65536)
        except OSError:
            pass


def px4_truth(msgs) -> dict:
    """The newest ground truth in a step's messages (HIL_STATE_QUATERNION, HIL_SENSOR)."""
    st = [m for m in msgs if m.get_type() == "HIL_STATE_QUATERNION"][-1]
    sen = [m for m in msgs if m.get_type() == "HIL_SENSOR"][-1]
    return dict(t=sen.time_usec * 1e-6, alt=st.alt * 1e-3, q=np.array(st.attitude_quaternion, float),
                v=np.array([st.vx, st.vy, st.vz], float) / 100, w=np.array([st.rollspeed, st.pitchspeed, st.yawspeed]),
                lat=st.lat, lon=st.lon, acc=np.array([sen.xacc, sen.yacc, sen.zacc]))


# ------------------------------------------------------------------ ArduPilot
def servo_packet(count, pwm, rate=400, channels=16, magic=None) -> bytes:
    magic = magic or (18458 if channels == 16 else 29569)
    pwm = list(pwm) + [1000] * (channels - len(pwm))
    return struct.pack(f"<HHI{channels}H", magic, rate, count, *pwm)


class ArduPilotClient:
    """ArduPilot SITL's side of the JSON interface: one servo packet per frame (frame_count + 1),
    then wait for the JSON reply before the next (lockstep)."""

    def __init__(self, port: int, host: str = "127.0.0.1", rate: int = 400, timeout: float = 30.0):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((host, 0))
        self.addr = (host, port)
        self.rate, self.count, self.timeout = rate, 0, timeout

    def close(self):
        self.sock.close()

    def frame(self, pwm) -> dict:
        self.count += 1
        self.sock.sendto(servo_packet(self.count, pwm, self.rate), self.addr)
        r, _, _ = select.select([self.sock], [], [], self.timeout)
        if not r:
            raise TimeoutError("no JSON reply")
        return json.loads(self.sock.recv(65536).decode())


def fly(client_kind: str, port: int, frame: str, mass: float, J, *, h: float, after: float = 1.0) -> dict:
    """The scripted flight through a simulator server, then ``after`` s more on the ground; returns
    the recorded truth (t, down = height below home (NED z), vz, phase, accelerometer) and when
    the autopilot detected the touchdown. Lockstep all the way: nothing depends on wall-clock timing."""
    ap = Autopilot(frame, mass, J)
    rec = {"t": [], "down": [], "vz": [], "phase": [], "acc": []}
    done_at = None
    if client_kind == "px4":
        cl = Px4Client(port)
        state = lambda msgs: px4_truth(msgs)   # noqa: E731
        msgs = cl.start()
    else:
        cl = ArduPilotClient(port, rate=int(round(1 / h)))
        msgs = cl.frame([1000] * 6)
    try:
        home = None
        while done_at is None or len(rec["t"]) - done_at < int(round(after / h)):
            if client_kind == "px4":
                tr = state(msgs)
                if home is None:
                    home = (tr["lat"], tr["lon"], tr["alt"])
                north = math.radians((tr["lat"] - home[0]) * 1e-7) * 6378137.0
                east = math.radians((tr["lon"] - home[1]) * 1e-7) * 6378137.0 * math.cos(math.radians(home[0] * 1e-7))
                t, p, v, R, w, acc = tr["t"], np.array([north, east, home[2] - tr["alt"]]), tr["v"], rot(tr["q"]), \
                    tr["w"], tr["acc"]
            else:
                d = msgs
                if home is None:
                    home = np.array(d["position"], float)
                t, p, v = d["timestamp"], np.array(d["position"], float) - home, np.array(d["velocity"], float)
                R, w, acc = rot(d["quaternion"]), np.array(d["imu"]["gyro"], float), d["imu"]["accel_body"]
            c = ap.update(t, h, p, v, R, w, 0.0)
            rec["t"].append(t)
            rec["down"].append(p[2])
            rec["vz"].append(v[2])
            rec["phase"].append(ap.phase)
            rec["acc"].append(np.asarray(acc, float))
            if ap.phase == "done" and done_at is None:
                done_at = len(rec["t"])
            if client_kind == "px4":
                cl.send(c, ap.armed)
                msgs = cl.step()
            else:
                msgs = cl.frame([int(round(1000 + 1000 * x)) for x in c] if ap.armed else [1000] * len(c))
            if len(rec["t"]) > 30000:
                raise AssertionError(f"the flight did not finish (phase {ap.phase})")
    finally:
        cl.close()
    out = {k: (np.array(v) if k != "phase" else v) for k, v in rec.items()}
    out["touchdown_detected"] = ap.touchdown_detected
    out["autopilot"] = ap
    return out


if __name__ == "__main__":
    if sys.argv[1:2] == ["px4-flood"]:
        px4_flood(int(sys.argv[2]), sys.argv[3])
    elif sys.argv[1:2] == ["ardupilot-flood"]:
        ardupilot_flood(int(sys.argv[2]))
    else:
        sys.exit("usage: sim_clients.py px4-flood PORT stale|guess | ardupilot-flood PORT")
