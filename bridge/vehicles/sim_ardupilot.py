"""`se3sync vehicle --sim-protocol ardupilot`: the plant as the physics backend of ArduPilot's
JSON SITL interface (libraries/SITL/examples/JSON/readme.md; run ArduPilot SITL with
``--model JSON:127.0.0.1``).

Transport: UDP; vehicle i listens on ``port + 10·(i − 1)`` (default 9002; SITL instance I uses
9002 + 10·I) and replies to whatever address the servo packet came from.

In (binary, little endian): ``uint16 magic = 18458, uint16 frame_rate, uint32 frame_count,
uint16 pwm[16]`` (40 bytes), or magic 29569 with pwm[32] (72 bytes, SERVO_32_ENABLE = 1).
Each new frame advances the body by 1/frame_rate s; a repeated frame_count re-sends the last
reply without stepping (SITL re-sends after 10 s of silence); a smaller frame_count means SITL
restarted: the vehicle is reset to its initial state; a gap counts lost frames and steps once.
PWM -> controls: unidirectional rotors (allocation, not reversible) c = (pwm − 1000)/1000 ∈ [0, 1]
(ArduPilot's motor range); otherwise c = (pwm − 1500)/500 ∈ [−1, 1]; channels 1–6 are used.

Out (text, one JSON object preceded and terminated by "\\n"): ``timestamp`` (s, physics time),
``imu.gyro`` (rad/s, FRD), ``imu.accel_body`` (m/s², FRD specific force), ``position`` (m, NED),
``velocity`` (m/s, NED), ``quaternion`` (w, x, y, z: FRD -> NED). The IMU has the same white noise
as the PX4 interface (`bridge.vehicles.sim_body.Noise`). With ``[plant] ground = true`` the body stands on
the ground plane and lifts off when the thrust exceeds its weight; without, until a motor PWM
exceeds 1000 µs (allocation) — ArduPilot spins armed motors at MOT_SPIN_ARM — it is held at its
initial pose (`sim_body`). Malformed packets (size, magic, frame_rate 0) are counted and dropped
without a reply. A body that diverges (`sim_body.Diverged`) is put back at its initial state,
counted per vehicle (``diverged``) and reported; the other vehicles go on.

Fair share: each round of the server's loop reads at most ``BURST`` packets per vehicle and stops
at the first that takes a step, so a client that floods its port (UDP: what the server does not
read the kernel drops) gets one step per round, as every other vehicle's SITL does.

The protocol has no authentication: whoever can send UDP to the port drives the vehicle (keep it
on loopback or a trusted network).
"""
from __future__ import annotations

import json
import select
import socket
import struct
import sys
import threading
import time

import numpy as np

from controller import layout

from bridge.mavlink.airframes import MAX_ROTORS, rotor_count
from bridge.mavlink.config import default_config
from bridge.mavlink.mapping import ALLOCATION
from .sim_body import Diverged, Noise, bodies_from_scenario

MAGIC16, MAGIC32 = 18458, 29569
PKT16, PKT32 = struct.Struct("<HHI16H"), struct.Struct("<HHI32H")
DEFAULT_PORT = 9002
BURST = 4            # packets read per vehicle and round of the loop (at most one of them steps)


def parse_servo_packet(data: bytes):
    """-> (frame_rate, frame_count, pwm tuple) or None if the packet is not a valid servo packet."""
    if len(data) == PKT16.size:
        magic, rate, count, *pwm = PKT16.unpack(data)
        ok = magic == MAGIC16
    elif len(data) == PKT32.size:
        magic, rate, count, *pwm = PKT32.unpack(data)
        ok = magic == MAGIC32
    else:
        return None
    if not ok or rate == 0:
        return None
    return rate, count, tuple(pwm)


def pwm_to_controls(pwm, unidirectional: bool) -> np.ndarray:
    p = np.asarray(pwm[:6], dtype=np.float64)
    if unidirectional:
        return np.clip((p - 1000.0) / 1000.0, 0.0, 1.0)
    return np.clip((p - 1500.0) / 500.0, -1.0, 1.0)


class _JsonLink:
    def __init__(self, body, host, port, unidirectional, motors):
        self.body = body
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((host, port))
        self.sock.setblocking(False)
        self.port = self.sock.getsockname()[1]
        self.unidirectional = unidirectional
        self.motors = motors            # PWM channels that drive rotors (1..motors)
        self.last_count = None
        self.last_reply = None
        self.diverged = 0
        self.steps = 0


class ArduPilotJsonServer:
    """Serves each scenario vehicle as one ArduPilot JSON physics backend (lockstep by frame)."""

    def __init__(self, scenario, *, host: str = "127.0.0.1", port: int = DEFAULT_PORT, noise: bool = True,
                 seed: int = 0, on_event=None):

        cfg = scenario.bridge or default_config(scenario.n_agents)
        self.scenario = scenario
        self.noise_on, self.seed = noise, seed
        self.noise = None
        self.counters = {"received": 0, "sent": 0, "malformed": 0, "duplicates": 0, "lost_frames": 0,
                         "resets": 0, "steps": 0, "diverged": 0, "rounds": 0}
        self.on_event = on_event or (lambda text: print(f"se3sync vehicle: {text}", file=sys.stderr, flush=True))
        self._stop = threading.Event()
        self.ready = threading.Event()
        self.links: list[_JsonLink] = []
        n = scenario.n_agents
        self._bodies = bodies_from_scenario(scenario, "apsim")
        try:
            for i in range(n):
                spec = cfg.mappings[i]
                alloc = spec.kind == ALLOCATION
                uni = alloc and not spec.allocation.reversible
                motors = rotor_count(spec.allocation) if alloc else MAX_ROTORS
                self.links.append(_JsonLink(self._bodies[i], host, port + 10 * i if port else 0, uni, motors))
        except OSError:
            self.close()
            raise

    # ------------------------------------------------------------------ one packet
    def reply(self, ln: _JsonLink, h: float) -> bytes:
        b = ln.body
        if self.noise is None or abs(self.noise.h - h) > 1e-12:
            self.noise = Noise(h, self.noise_on, self.seed)
        nz = self.noise
        d = {"timestamp": b.t,
             "imu": {"gyro": [float(x) for x in nz.add(b.omega, nz.gyro)],
                     "accel_body": [float(x) for x in nz.add(b.specific_force(), nz.accel)]},
             "position": [float(x) for x in b.S[layout.P]],
             "velocity": [float(x) for x in b.v_ned],
             "quaternion": [float(x) for x in b.q]}
        return ("\n" + json.dumps(d, separators=(",", ":")) + "\n").encode()

    def handle(self, ln: _JsonLink, data: bytes, addr) -> bool:
        """One packet; True if it advanced the body."""
        pkt = parse_servo_packet(data)
        if pkt is None:
            self.counters["malformed"] += 1
            return False
        stepped = False
        self.counters["received"] += 1
        rate, count, pwm = pkt
        h = 1.0 / rate
        if ln.last_count is not None and count == ln.last_count:
            self.counters["duplicates"] += 1
        else:
            if ln.last_count is not None and count < ln.last_count:
                self.counters["resets"] += 1      # SITL restarted: start again from the initial state
                ln.body.reset(clock=True)
            elif ln.last_count is not None and count > ln.last_count + 1:
                self.counters["lost_frames"] += count - ln.last_count - 1
            c = pwm_to_controls(pwm, ln.unidirectional)
            c[ln.motors:] = 0.0
            if ln.body.held and (not ln.unidirectional or np.any(np.asarray(pwm[:ln.motors]) > 1000)):
                ln.body.release()
            try:
                ln.body.step(c, h)
            except Diverged as exc:
                self._diverged(ln, exc)
            self.counters["steps"] += 1
            ln.steps += 1
            stepped = True
            ln.last_count = count
            ln.last_reply = self.reply(ln, h)
        try:
            ln.sock.sendto(ln.last_reply, addr)
            self.counters["sent"] += 1
        except OSError:
            pass
        return stepped

    def _diverged(self, ln: _JsonLink, exc) -> None:
        """The body left any physical range: back to its initial state; counted and said."""
        ln.diverged += 1
        self.counters["diverged"] += 1
        ln.body.reset()
        i = self.links.index(ln) + 1
        self.on_event(f"vehicle {i} diverged ({exc}); reset to its initial state ({ln.diverged} so far)")

    # ------------------------------------------------------------------ loop
    def stop(self) -> None:
        self._stop.set()

    def run(self, duration: float | None = None) -> dict:
        end = None if duration is None else time.monotonic() + duration
        by_fd = {ln.sock.fileno(): ln for ln in self.links}
        self.ready.set()
        try:
            while not self._stop.is_set():
                if end is not None and time.monotonic() >= end:
                    break
                r, _, _ = select.select(list(by_fd), [], [], 0.05)
                self.counters["rounds"] += 1
                for fd in r:
                    ln = by_fd[fd]
                    for _ in range(BURST):      # the rest waits for the next round (or is dropped by the kernel)
                        try:
                            data, addr = ln.sock.recvfrom(2048)
                        except (BlockingIOError, InterruptedError):
                            break
                        except OSError:
                            self.counters["malformed"] += 1
                            break
                        if self.handle(ln, data, addr):
                            break
        except KeyboardInterrupt:
            pass
        return self.stats()

    def stats(self) -> dict:
        return dict(self.counters, ports=[ln.port for ln in self.links],
                    diverged_vehicles=[ln.diverged for ln in self.links],
                    vehicles=[{"steps": ln.steps, "diverged": ln.diverged} for ln in self.links])

    def close(self) -> None:
        for ln in self.links:
            ln.sock.close()
        for b in getattr(self, "_bodies", []):
            b.close()
