"""Output profiles: how one vehicle's command travels (issue 14).

A profile turns the bridge's per-vehicle controls c (the ``direct`` mapping's normalised wrench,
c = clip((w + w_ff) ./ max_wrench, −1, 1), FRD, order τx τy τz fx fy fz; or rotor thrusts for
``allocation``) into one MAVLink message, and back. The loopback vehicle decodes with the same
functions, and `bridge.mavlink.transport.QuantizedPlant` applies ``quantize`` (encode → the wire's
rounding → decode) so lockstep HIL and the reference stay bit-identical.

Profiles (``bridge.output``, or per vehicle in ``[[bridge.vehicle]]``):

* ``actuator_control_target`` — SET_ACTUATOR_CONTROL_TARGET (#139), controls[0:6] as float32.
  PX4 removed the message in v1.14; ArduPilot never implemented it. Kept for our loopback vehicle
  and older PX4 offboard actuator setups. Lockstep stamp: time_usec = k·h.
* ``do_set_actuator`` — COMMAND_LONG MAV_CMD_DO_SET_ACTUATOR (#187), param1–6 = controls. On
  PX4 ≥ 1.14 it drives only outputs configured as "Peripheral via Actuator Set 1–6", never the
  motors (servos, grippers). Kept for those and for the loopback vehicle. Lockstep stamp:
  ``confirmation`` = k mod 256.
* ``ardusub_manual_control`` — MANUAL_CONTROL (#69) to ArduSub in MANUAL mode. Axes, each
  round(1000·c) in ±1000: x = fx (forward), y = fy (right), r = τz (yaw right), s = τy (pitch up)
  and t = τx (roll right) with ``enabled_extensions`` bits 0 (s) and 1 (t) set; z is ArduSub's
  throttle, 0…1000 with 500 neutral and > 500 up: z = round(500 − 500·c_fz) (FRD z is down).
  Quantisation: 1e-3 of max_wrench per axis (5e-4·2 on z: 2e-3 of max fz). ArduSub: arm
  (COMPONENT_ARM_DISARM, ``bridge.arm = true``), mode MANUAL (custom mode 19), joystick gain
  JS_GAIN_DEFAULT = JS_GAIN_MAX = 1 so ±1000 reaches the full thruster range (ArduSub scales
  the axes by the pilot gain), ACRO_YAW_P at its default (MANUAL scales yaw by it), the bridge's
  HEARTBEAT at 1 Hz for the GCS fail-safe, MANUAL_CONTROL at the control rate (ArduSub's pilot
  input fail-safe FS_PILOT_INPUT fires after FS_PILOT_TIMEOUT without it). ArduSub reads s and
  t only in versions that implement the MANUAL_CONTROL extensions (check yours); its motor mix
  then maps the six normalised axes to the thrusters, so ``max_wrench`` must be the wrench the
  frame produces at ±1 per axis (from the thruster layout and thrust curve). Lockstep: MANUAL_CONTROL
  has no time field, so the loopback vehicle steps once per MANUAL_CONTROL it receives, in order
  ("lockstep by sequence"); the bridge never re-sends it (a re-send would be a second step), so
  a lost packet is a lockstep timeout (exit 4). Real ArduSub has no lockstep with a GCS.
* ``px4_attitude_thrust`` — SET_ATTITUDE_TARGET (#82) to PX4 in Offboard mode (attitude
  control): ``thrust_body`` = c[3:6] (normalised FRD force, type_mask bit THRUST_BODY_SET = 32;
  PX4's MAVLink receiver copies it into the attitude setpoint), body rates ignored, and the attitude
  setpoint that realises the torque τ = c[0:3]·max_wrench[0:3] over one control period h:
  with ω̇ = J⁻¹(τ − ω×Jω), R_d = R exp(w^), w = ω h + ½ ω̇ h² — the attitude reached after h
  at constant angular acceleration, exact to O(h³) (the neglected terms are the change of ω×Jω
  over the period and the commutator h³/12·ω×ω̇). The loopback vehicle inverts this exactly:
  w = log(Rᵀ R_d), ω̇ = 2(w − ωh)/h², τ = J ω̇ + ω×Jω, using the very state (float32 q and ω)
  the bridge used. PX4's own attitude controller does NOT realise τ: it tracks R_d with its
  P attitude / PID rate loops (MC_ATT_*, MC_*RATE_*), so on a real PX4 the torque is whatever
  its loops produce towards R_d; our law then relies on PX4's inner loop being much faster
  than the synchronisation (time-scale separation). PX4 needs Offboard mode (setpoints streamed
  at ≥ 2 Hz before and while switching, COM_OF_LOSS_T), arming, a fully actuated airframe
  whose control allocation accepts a 3-D thrust (e.g. CA_AIRFRAME with tilted rotors) — a
  standard multicopter ignores thrust_body x/y. Lockstep stamp: time_boot_ms = k·h in ms
  (h must be a whole number of milliseconds).
  pymavlink's common.xml (2.4.x) predates the ``thrust_body`` extension (float[3] after
  type_mask), so `AttitudeTargetMessage` appends it to the payload itself and
  `thrust_body_of` reads it from the packet.
"""
from __future__ import annotations

import math
import struct
import time

import numpy as np

from . import codec
from .link import mavlink2

M = mavlink2

ACTUATOR_CONTROL_TARGET = "actuator_control_target"
DO_SET_ACTUATOR = "do_set_actuator"
ARDUSUB_MANUAL_CONTROL = "ardusub_manual_control"
PX4_ATTITUDE_THRUST = "px4_attitude_thrust"

THRUST_BODY_SET = 32   # ATTITUDE_TARGET_TYPEMASK_THRUST_BODY_SET (common.xml, newer than pymavlink's copy)
RATES_IGNORE = (M.ATTITUDE_TARGET_TYPEMASK_BODY_ROLL_RATE_IGNORE | M.ATTITUDE_TARGET_TYPEMASK_BODY_PITCH_RATE_IGNORE
                | M.ATTITUDE_TARGET_TYPEMASK_BODY_YAW_RATE_IGNORE)
PX4_TYPE_MASK = RATES_IGNORE | THRUST_BODY_SET
MANUAL_EXTENSIONS = 0b11     # enabled_extensions: bit 0 = s (pitch), bit 1 = t (roll)


# ---------------------------------------------------------------------------- ArduSub MANUAL_CONTROL
def _round_clip(x: float, lo: int, hi: int) -> int:
    v = math.floor(x + 0.5)
    return lo if v < lo else hi if v > hi else int(v)


def manual_control_axes(c) -> tuple:
    """Controls (6,) in [−1, 1] -> MANUAL_CONTROL (x, y, z, r, s, t)."""
    return (_round_clip(1000.0 * c[3], -1000, 1000), _round_clip(1000.0 * c[4], -1000, 1000),
            _round_clip(500.0 - 500.0 * c[5], 0, 1000), _round_clip(1000.0 * c[2], -1000, 1000),
            _round_clip(1000.0 * c[1], -1000, 1000), _round_clip(1000.0 * c[0], -1000, 1000))


def manual_control_controls(x, y, z, r, s, t, enabled_extensions=MANUAL_EXTENSIONS) -> np.ndarray:
    """MANUAL_CONTROL axes -> controls (6,); s/t count only when their enable bit is set."""
    c = np.zeros(6)
    c[3] = x / 1000.0
    c[4] = y / 1000.0
    c[5] = (500.0 - z) / 500.0
    c[2] = r / 1000.0
    c[1] = s / 1000.0 if enabled_extensions & 1 else 0.0
    c[0] = t / 1000.0 if enabled_extensions & 2 else 0.0
    return c


# ---------------------------------------------------------------------------- PX4 attitude + thrust
def _qmul(a, b):
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw)


def _qnorm(q):
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)


def _qexp(w):
    """Unit quaternion of the rotation vector w (exp of w^)."""
    a = math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    if a < 1e-8:
        s = 0.5 - a * a / 48.0
        return _qnorm((1.0 - a * a / 8.0, s * w[0], s * w[1], s * w[2]))
    s = math.sin(0.5 * a) / a
    return (math.cos(0.5 * a), s * w[0], s * w[1], s * w[2])


def _qlog(q):
    """Rotation vector of a unit quaternion (shortest: |w| ≤ π)."""
    if q[0] < 0.0:
        q = (-q[0], -q[1], -q[2], -q[3])
    v = math.sqrt(q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if v < 1e-12:
        return (2.0 * q[1], 2.0 * q[2], 2.0 * q[3])
    k = 2.0 * math.atan2(v, q[0]) / v
    return (k * q[1], k * q[2], k * q[3])


def _mv(J, v):
    return (J[0][0] * v[0] + J[0][1] * v[1] + J[0][2] * v[2], J[1][0] * v[0] + J[1][1] * v[1] + J[1][2] * v[2],
            J[2][0] * v[0] + J[2][1] * v[1] + J[2][2] * v[2])


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


class AttitudeThrust:
    """The ``px4_attitude_thrust`` encoding for one vehicle: inertia J (FRD, kg·m²), control period
    h (s), torque limits (N·m). Plain float arithmetic in a fixed order, so the bridge, the loopback
    vehicle and the reference compute identical numbers."""

    def __init__(self, J, h: float, max_torque):
        J = np.asarray(J, dtype=np.float64).reshape(3, 3)
        self.J = tuple(tuple(float(x) for x in row) for row in J)
        self.Jinv = tuple(tuple(float(x) for x in row) for row in np.linalg.inv(J))
        self.h = float(h)
        self.max_torque = tuple(float(x) for x in max_torque)

    def attitude_setpoint(self, tau, q, omega) -> tuple:
        """R_d = R exp(w^), w = ω h + ½ ω̇ h², ω̇ = J⁻¹(τ − ω×Jω); q = R's quaternion (w-first)."""
        h = self.h
        om = (float(omega[0]), float(omega[1]), float(omega[2]))
        gyro = _cross(om, _mv(self.J, om))
        wd = _mv(self.Jinv, (tau[0] - gyro[0], tau[1] - gyro[1], tau[2] - gyro[2]))
        w = tuple(om[i] * h + 0.5 * wd[i] * h * h for i in range(3))
        return _qmul(_qnorm((float(q[0]), float(q[1]), float(q[2]), float(q[3]))), _qexp(w))

    def torque(self, q_d, q, omega) -> tuple:
        """The inverse: the torque whose constant-acceleration motion over h reaches q_d."""
        h = self.h
        qn = _qnorm((float(q[0]), float(q[1]), float(q[2]), float(q[3])))
        qd = _qnorm((float(q_d[0]), float(q_d[1]), float(q_d[2]), float(q_d[3])))
        w = _qlog(_qmul((qn[0], -qn[1], -qn[2], -qn[3]), qd))
        om = (float(omega[0]), float(omega[1]), float(omega[2]))
        wd = tuple(2.0 * (w[i] - om[i] * h) / (h * h) for i in range(3))
        Jw = _mv(self.J, wd)
        gyro = _cross(om, _mv(self.J, om))
        return (Jw[0] + gyro[0], Jw[1] + gyro[1], Jw[2] + gyro[2])

    def encode(self, c, wire) -> tuple:
        """Controls (6,) and the wire state (13,) the bridge used -> (q_d, thrust_body), float64."""
        mt = self.max_torque
        tau = (c[0] * mt[0], c[1] * mt[1], c[2] * mt[2])
        return self.attitude_setpoint(tau, wire[3:7], wire[7:10]), (float(c[3]), float(c[4]), float(c[5]))

    def decode(self, q_d, thrust_body, wire) -> np.ndarray:
        """(q_d, thrust_body) as received and the vehicle's wire state -> controls (6,) in [−1, 1]."""
        tau = self.torque(q_d, wire[3:7], wire[7:10])
        mt = self.max_torque
        c = np.empty(6)
        for i in range(3):
            c[i] = min(1.0, max(-1.0, tau[i] / mt[i]))
            c[3 + i] = min(1.0, max(-1.0, float(thrust_body[i])))
        return c


class AttitudeTargetMessage(M.MAVLink_set_attitude_target_message):
    """SET_ATTITUDE_TARGET with the ``thrust_body`` extension (float[3] after type_mask), which
    pymavlink's bundled common.xml lacks; the CRC extra is unchanged by extensions."""

    def __init__(self, time_boot_ms, target_system, target_component, type_mask, q, thrust_body, thrust=0.0):
        super().__init__(time_boot_ms, target_system, target_component, type_mask, q, 0.0, 0.0, 0.0, thrust)
        self.thrust_body = [float(x) for x in thrust_body]

    def pack(self, mav, force_mavlink1=False):
        base = self.unpacker.pack(self.time_boot_ms, self.q[0], self.q[1], self.q[2], self.q[3],
                                  self.body_roll_rate, self.body_pitch_rate, self.body_yaw_rate, self.thrust,
                                  self.target_system, self.target_component, self.type_mask)
        return self._pack(mav, self.crc_extra, base + struct.pack("<3f", *self.thrust_body),
                          force_mavlink1=force_mavlink1)


def thrust_body_of(m) -> tuple:
    """``thrust_body`` of a received SET_ATTITUDE_TARGET (MAVLink 2: zeros truncated at the end)."""
    buf = bytes(m.get_msgbuf())
    n = buf[1]
    payload = buf[10:10 + n] + bytes(max(0, 51 - n))
    return struct.unpack_from("<3f", payload, 39)


# ---------------------------------------------------------------------------- one vehicle's profile
def f32(x: float) -> float:
    return float(np.float32(x))


class OutputProfile:
    """One output profile: how one vehicle's controls c (6,) travel as one MAVLink message, and
    back. A profile is a subclass in the `PROFILE_CLASSES` table, which the bridge
    (`MavlinkPlant`, `QuantizedPlant`) and the loopback vehicle share: adding a message is one
    class here, nothing elsewhere (pymavlink's "messages are data").

    Class attributes: ``name`` (the scenario's ``bridge.output``), ``msg_id`` and ``command``
    (the MAVLink message, and the MAV_CMD for a COMMAND_LONG profile), ``carries_wrench`` (the
    flight stack allocates: c is the normalised wrench), ``resend_ok`` (False when a repeat
    cannot be told from the next command: lockstep by sequence)."""

    name: str = ""
    msg_id: int = -1
    command: int | None = None
    carries_wrench = False
    resend_ok = True

    def __init__(self, *, h: float, J=None, max_wrench=None, group_mlx: int = 0,
                 actuator_index_offset: int = 0):
        self.h = float(h)
        self.h_us = int(round(self.h * 1e6))
        self.h_ms = int(round(self.h * 1e3))
        self.group_mlx = group_mlx
        self.actuator_index_offset = actuator_index_offset

    @classmethod
    def key(cls) -> tuple:
        """What a received message is matched on: (message id, command or None)."""
        return (cls.msg_id, cls.command)

    @staticmethod
    def target(m) -> int:
        """The system id a received message of this profile is addressed to."""
        return m.target_system

    def lockstep_error(self) -> str | None:
        """Why this profile cannot stamp lockstep steps of h exactly, or None."""
        return None

    def stamp(self, k: int) -> int:
        """The lockstep stamp of step k carried by the message (0: none, lockstep by sequence)."""
        return 0

    def stamps(self, m, k: int) -> tuple | None:
        """Lockstep: (m is step k's command, m repeats an earlier step's), or None when the
        message carries no stamp (one step per command, in order)."""
        return None

    def time_us(self, m) -> int | None:
        """Real time: the message's Unix time stamp (µs) that orders commands, or None."""
        return None

    def message(self, mav, c, *, target: int, k: int, lockstep: bool, wire=None):
        """The MAVLink message for controls c (6,) at step k (wire: the state the bridge used), as
        a `bridge.mavlink.codec.Outgoing` (``pack(mav)`` frames it as pymavlink would; ``mav``
        is kept for profiles that need pymavlink)."""
        raise NotImplementedError

    def compiled_fields(self, c, *, target, k, lockstep) -> tuple | None:
        """What `message` sends, as the fields of SET_ACTUATOR_CONTROL_TARGET that compiled code
        frames (`bridge.mavlink.state_wire.pack_command`: time_usec, controls c[0:6], group_mlx,
        target system, target component), or None when this profile sends another message."""
        return None

    def decode(self, m, wire=None) -> np.ndarray | None:
        """A received message of this profile -> controls (6,), NaN entries meaning "no change";
        None when its contents are not a valid command of this profile."""
        raise NotImplementedError

    def quantize(self, c, wire=None) -> np.ndarray:
        """What the vehicle decodes from controls c (6,): encode, the wire's rounding, decode."""
        return np.array([f32(x) for x in c])


class ActuatorControlTarget(OutputProfile):
    name = ACTUATOR_CONTROL_TARGET
    msg_id = M.MAVLINK_MSG_ID_SET_ACTUATOR_CONTROL_TARGET

    def stamp(self, k: int) -> int:
        return k * self.h_us

    def stamps(self, m, k: int) -> tuple:
        s = self.stamp(k)
        return m.time_usec == s, m.time_usec < s

    def time_us(self, m) -> int:
        return m.time_usec

    def message(self, mav, c, *, target, k, lockstep, wire=None):
        t_us = k * self.h_us if lockstep else int(time.time() * 1e6)
        return codec.SET_ACTUATOR_CONTROL_TARGET.encoded(
            t_us, c[0], c[1], c[2], c[3], c[4], c[5], 0.0, 0.0, self.group_mlx, target, 1)

    def compiled_fields(self, c, *, target, k, lockstep):
        t_us = k * self.h_us if lockstep else int(time.time() * 1e6)
        return (t_us, c[0], c[1], c[2], c[3], c[4], c[5], self.group_mlx, target, 1)

    def decode(self, m, wire=None):
        if m.group_mlx != self.group_mlx:
            return None
        return np.asarray(m.controls[:6], dtype=np.float64)


class DoSetActuator(OutputProfile):
    name = DO_SET_ACTUATOR
    msg_id = M.MAVLINK_MSG_ID_COMMAND_LONG
    command = M.MAV_CMD_DO_SET_ACTUATOR

    def stamp(self, k: int) -> int:
        return k & 0xFF

    def stamps(self, m, k: int) -> tuple:
        return m.confirmation == self.stamp(k), m.confirmation == self.stamp(k - 1)

    def message(self, mav, c, *, target, k, lockstep, wire=None):
        return codec.COMMAND_LONG.encoded(c[0], c[1], c[2], c[3], c[4], c[5],
                                          float(self.actuator_index_offset),
                                          M.MAV_CMD_DO_SET_ACTUATOR, target, 1,
                                          k & 0xFF if lockstep else 0)

    def decode(self, m, wire=None):
        if int(m.param7) != self.actuator_index_offset:
            return None
        return np.array([m.param1, m.param2, m.param3, m.param4, m.param5, m.param6])


class ArduSubManualControl(OutputProfile):
    name = ARDUSUB_MANUAL_CONTROL
    msg_id = M.MAVLINK_MSG_ID_MANUAL_CONTROL
    carries_wrench = True
    resend_ok = False          # no time field: a re-send would be a second step

    @staticmethod
    def target(m) -> int:
        return m.target

    def message(self, mav, c, *, target, k, lockstep, wire=None):
        x, y, z, r, s, t = manual_control_axes(c)
        return codec.MANUAL_CONTROL.encoded(x, y, z, r, 0, target, 0, MANUAL_EXTENSIONS, s, t,
                                            0, 0, 0, 0, 0, 0)

    def decode(self, m, wire=None):
        if not (0 <= m.z <= 1000 and all(-1000 <= v <= 1000 for v in (m.x, m.y, m.r, m.s, m.t))):
            return None
        return manual_control_controls(m.x, m.y, m.z, m.r, m.s, m.t, m.enabled_extensions)

    def quantize(self, c, wire=None):
        return manual_control_controls(*manual_control_axes(c))


class Px4AttitudeThrust(OutputProfile):
    name = PX4_ATTITUDE_THRUST
    msg_id = M.MAVLINK_MSG_ID_SET_ATTITUDE_TARGET
    carries_wrench = True

    def __init__(self, *, h, J=None, max_wrench=None, **kw):
        super().__init__(h=h, **kw)
        self.att = AttitudeThrust(J if J is not None else np.eye(3), h, max_wrench[0:3])

    def lockstep_error(self):
        if abs(round(self.h * 1e3) - self.h * 1e3) > 1e-9:
            return (f"simulation.step: output \"px4_attitude_thrust\" in lockstep stamps steps with "
                    f"time_boot_ms, so the step must be a whole number of milliseconds, got {self.h:g}")
        return None

    def stamp(self, k: int) -> int:
        return (k * self.h_ms) & 0xFFFFFFFF

    def stamps(self, m, k: int) -> tuple:
        return m.time_boot_ms == self.stamp(k), m.time_boot_ms == self.stamp(k - 1)

    def message(self, mav, c, *, target, k, lockstep, wire=None):
        q_d, tb = self.att.encode(c, wire)
        tb_ms = (k * self.h_ms) & 0xFFFFFFFF if lockstep else \
            int(time.monotonic() * 1000) & 0xFFFFFFFF
        return codec.SET_ATTITUDE_TARGET.encoded(tb_ms, q_d[0], q_d[1], q_d[2], q_d[3], 0.0, 0.0,
                                                 0.0, 0.0, target, 1, PX4_TYPE_MASK, tb[0], tb[1],
                                                 tb[2])

    def decode(self, m, wire=None):
        q = m.q
        tb = thrust_body_of(m)
        vals = list(q) + list(tb)
        if not all(math.isfinite(v) for v in vals) or not (m.type_mask & THRUST_BODY_SET) \
                or abs(math.sqrt(sum(v * v for v in q)) - 1.0) > 1e-3:
            return None
        return self.att.decode(q, tb, wire)

    def quantize(self, c, wire=None):
        q_d, tb = self.att.encode(c, wire)
        return self.att.decode([f32(x) for x in q_d], [f32(x) for x in tb], wire)


# The table: profile name -> class. The loopback vehicle dispatches received commands on
# `PROFILE_BY_KEY`, and what only the commander may send includes every profile's message.
PROFILE_CLASSES = {cls.name: cls for cls in (ActuatorControlTarget, DoSetActuator, ArduSubManualControl,
                                             Px4AttitudeThrust)}
PROFILE_BY_KEY = {cls.key(): cls for cls in PROFILE_CLASSES.values()}


def profile(name: str, **kw) -> OutputProfile:
    """The profile ``name`` for one vehicle (keyword arguments: `OutputProfile`'s)."""
    if name not in PROFILE_CLASSES:
        raise ValueError(f"unknown output profile {name!r}")
    return PROFILE_CLASSES[name](**kw)
PROFILES = tuple(PROFILE_CLASSES)
# profiles whose flight stack does its own allocation: they carry the normalised wrench
WRENCH_PROFILES = tuple(n for n, cls in PROFILE_CLASSES.items() if cls.carries_wrench)
