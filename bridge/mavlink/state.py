"""Vehicle state in: ODOMETRY (primary) or ATTITUDE_QUATERNION + LOCAL_POSITION_NED (fallback),
validated and kept as "wire" rows (see `bridge.mavlink.transport`), in NED/FRD.

A message is rejected and counted when it is
* ``nan``: any field not finite;
* ``non_unit_quaternion``: | ‖q‖ − 1 | > 1e-3 (MAVLink carries float32, so ~1e-7 is normal);
* ``out_of_order``: its time_usec is not newer than the last accepted one (an exact repeat is
  counted as ``duplicate`` instead); a vehicle that rebooted stamps more than 10 s back and keeps
  going from there: `REBOOT_STATES` such states in a row, each newer than the one before, are its
  reboot (the last one is accepted, ``reboots``), one packet never is;
* ``future``: real time, stamped more than `FUTURE_US` (1 s, as the vehicle's own bound on
  commands) ahead of the vehicle's clock as estimated from the offset (accepted, one forged
  packet would hold the ordering window, and the stale reference, for as long as it claimed);
  lockstep, stamped after the step being waited for (``max_time_usec``);
* ``stale``: it arrived more than ``stale_after`` seconds later than the best-case delay seen on
  this link in the last 1–2 s (the vehicle's clock and ours differ by an unknown offset,
  estimated as the minimum of arrival − time_usec over a window of `OFFSET_WINDOW_S` to 2×, so
  that clock drift and one bad estimate expire); not checked in lockstep, where time_usec is
  simulated time;
* ``bad_frame``: an ODOMETRY frame_id/child_frame_id we do not handle.
"""
from __future__ import annotations

import math

import numpy as np

from controller.se3 import quat_to_rot_row

from .link import mavlink2
from .transport import WIRE

FRAME_LOCAL_NED = mavlink2.MAV_FRAME_LOCAL_NED
FRAME_LOCAL_FRD = mavlink2.MAV_FRAME_LOCAL_FRD
FRAME_BODY_FRD = mavlink2.MAV_FRAME_BODY_FRD
FRAME_BODY_NED = getattr(mavlink2, "MAV_FRAME_BODY_NED", 8)
QUAT_TOL = 1e-3
REBOOT_JUMP_US = 10_000_000
REBOOT_STATES = 3
FUTURE_US = 1_000_000
OFFSET_WINDOW_S = 1.0
# `StateTracker.clock`'s slots: the offset (the last whole window's minimum of arrival − vehicle
# time, lowered by any smaller one since), this window's minimum, and when this window began
# (time.monotonic())
C_OFFSET, C_MIN, C_START = range(3)
CLOCK_SLOTS = 3

ID_ODOMETRY = mavlink2.MAVLINK_MSG_ID_ODOMETRY
ID_ATTITUDE_QUATERNION = mavlink2.MAVLINK_MSG_ID_ATTITUDE_QUATERNION
ID_LOCAL_POSITION_NED = mavlink2.MAVLINK_MSG_ID_LOCAL_POSITION_NED


def _rot_T_apply(q, v):
    """Rᵀ v for the unit quaternion q (w, x, y, z), fixed operation order."""
    R = quat_to_rot_row(*q)
    return [R[i] * v[0] + R[3 + i] * v[1] + R[6 + i] * v[2] for i in range(3)]


class StateTracker:
    """The latest valid state of one vehicle."""

    def __init__(self, counters, stale_after: float = 0.1, check_stale: bool = True,
                 fallback: bool = True):
        self.c = counters
        self.fallback = fallback      # use ATTITUDE_QUATERNION + LOCAL_POSITION_NED if no ODOMETRY
        self.stale_after = float(stale_after)
        self.check_stale = check_stale
        self.wire = np.zeros(WIRE)
        self.have = False
        # the time checks' state, kept in arrays that compiled code reads and moves too
        # (`state_wire.take_states`); None is NaN in ``clock`` and ``stamped`` False for the stamp
        self.clock = np.full(CLOCK_SLOTS, np.nan)   # offset, the window's minimum, its start
        self.stamp = np.zeros(1, np.uint64)         # time_usec (the wire's uint64)
        self.stamped = False
        self.t_arrival = None         # our wall time (time.monotonic()) of the latest accepted state
        self.n_states = 0
        self.n_odometry = 0
        self.source = None            # "odometry" | "fallback"
        self._att = None              # (time_boot_ms, q(4), rates(3))
        self._pos = None              # (time_boot_ms, p(3), v_ned(3))
        self.duplicates = 0
        self.reboots = 0
        self.max_time_usec = None     # lockstep: the stamp of the step being waited for
        self._back = None             # (newest far-back stamp, run length): a reboot's evidence

    @property
    def time_usec(self) -> int | None:
        """Vehicle time of the latest accepted state (µs), None before any."""
        return int(self.stamp[0]) if self.stamped else None

    @time_usec.setter
    def time_usec(self, t) -> None:
        self.stamped = t is not None
        self.stamp[0] = 0 if t is None else t

    def _slot(self, i: int) -> float | None:
        v = float(self.clock[i])
        return None if v != v else v

    def _set(self, i: int, v) -> None:
        self.clock[i] = np.nan if v is None else v

    @property
    def offset(self) -> float | None:
        """min(arrival − vehicle time) over the last whole window, µs (None: unknown)."""
        return self._slot(C_OFFSET)

    @offset.setter
    def offset(self, v) -> None:
        self._set(C_OFFSET, v)

    def reset_clock(self):
        self.time_usec = None
        self.clock[:] = np.nan

    def _roll(self, t_wall: float) -> None:
        start = self._slot(C_START)
        if start is None or t_wall - start >= OFFSET_WINDOW_S:
            last = self._slot(C_MIN) if start is not None and t_wall - start < 2 * OFFSET_WINDOW_S \
                else None
            self._set(C_MIN, None)
            self._set(C_START, t_wall)
            self.offset = last

    def _time_ok(self, t_us: int, t_wall: float) -> bool:
        if self.max_time_usec is not None and t_us > self.max_time_usec:
            self.c.reject("future")
            return False
        if self.check_stale:
            self._roll(t_wall)
            d = t_wall * 1e6 - t_us
            if self.offset is not None and d < self.offset - FUTURE_US:
                self.c.reject("future")
                return False
        if self.time_usec is not None:
            if t_us == self.time_usec:
                self.duplicates += 1
                return False
            if t_us < self.time_usec:
                if self.time_usec - t_us <= REBOOT_JUMP_US:
                    self.c.reject("out_of_order")
                    return False
                back = self._back
                run = 1 if back is None or t_us <= back[0] else back[1] + 1
                self._back = (t_us, run)
                if run < REBOOT_STATES:
                    self.c.reject("out_of_order")
                    return False
                self.reboots += 1
                self.reset_clock()
                if self.check_stale:
                    self._roll(t_wall)
        self._back = None
        if self.check_stale:
            off = self.offset
            if off is None or d < off:
                self.offset = d
            elif d - off > self.stale_after * 1e6:
                self.c.reject("stale")
                return False
            w = self._slot(C_MIN)
            if w is None or d < w:
                self._set(C_MIN, d)
        return True

    def _accept(self, vals, t_us, t_wall, source) -> bool:
        if not all(math.isfinite(v) for v in vals):
            self.c.reject("nan")
            return False
        q = vals[3:7]
        if abs(math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]) - 1.0) > QUAT_TOL:
            self.c.reject("non_unit_quaternion")
            return False
        return self._store(vals, t_us, t_wall, source)

    def _store(self, vals, t_us, t_wall, source) -> bool:
        """A state whose values passed the checks: taken if its time does."""
        if not self._time_ok(t_us, t_wall):
            return False
        self.wire[:] = vals
        self.time_usec = t_us
        self.t_arrival = t_wall
        self.have = True
        self.n_states += 1
        self.source = source
        return True

    def took(self, n: int, t_wall: float) -> None:
        """``n`` ODOMETRY states, each newer than the one before, were taken at ``t_wall`` by
        compiled code that made this tracker's checks and moved its arrays (``wire``, ``clock``,
        ``stamp``: `state_wire.take_states`): the rest of what `on_odometry_row` records."""
        self.n_states += n
        self.n_odometry += n
        self.t_arrival = t_wall
        self.have = True
        self.source = "odometry"
        self._back = None

    def on_odometry(self, m, t_wall: float) -> bool:
        vals = [m.x, m.y, m.z, *m.q, m.rollspeed, m.pitchspeed, m.yawspeed, m.vx, m.vy, m.vz]
        if m.frame_id not in (FRAME_LOCAL_NED, FRAME_LOCAL_FRD) or \
                m.child_frame_id not in (FRAME_BODY_FRD, FRAME_LOCAL_NED, FRAME_BODY_NED):
            self.c.reject("bad_frame")
            return False
        if m.child_frame_id != FRAME_BODY_FRD:
            # velocity given in the world (NED) frame: rotate into the body frame
            if not all(math.isfinite(v) for v in vals):
                self.c.reject("nan")
                return False
            q = vals[3:7]
            n2 = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]
            if n2 > 0:
                vals[10:13] = _rot_T_apply(q, vals[10:13])
        return self._odometry(vals, int(m.time_usec), t_wall, self._accept)

    def on_odometry_row(self, row, t_us: int, t_wall: float) -> bool:
        """`on_odometry` of a state whose frames (child MAV_FRAME_BODY_FRD) and values compiled
        code has checked as `on_odometry` checks them (`bridge.mavlink.state_wire`): row, its
        wire row; the time checks and the rest are the same."""
        return self._odometry(row, int(t_us), t_wall, self._store)

    def _odometry(self, vals, t_us: int, t_wall: float, accept) -> bool:
        if not self.n_odometry and self.source == "fallback":
            # the first ODOMETRY after states from the fallback: its time_usec is another clock
            # than their time_boot_ms (often the Unix epoch), so it starts the clock estimate
            # afresh; checked against theirs it was refused as `future` for good, and the vehicle
            # stayed on the fallback's rate
            self.reset_clock()
        ok = accept(vals, t_us, t_wall, "odometry")
        if ok and not self.n_odometry:
            self.time_usec = t_us
        self.n_odometry += ok
        return ok

    def on_attitude_quaternion(self, m, t_wall: float) -> bool:
        if not self.fallback or self.n_odometry:
            return False  # the vehicle sends ODOMETRY: the fallback is not used (other time base)
        self._att = (m.time_boot_ms, [m.q1, m.q2, m.q3, m.q4], [m.rollspeed, m.pitchspeed, m.yawspeed])
        return self._combine(t_wall)

    def on_local_position_ned(self, m, t_wall: float) -> bool:
        if not self.fallback or self.n_odometry:
            return False  # the vehicle sends ODOMETRY: the fallback is not used (other time base)
        self._pos = (m.time_boot_ms, [m.x, m.y, m.z], [m.vx, m.vy, m.vz])
        return self._combine(t_wall)

    def _combine(self, t_wall: float) -> bool:
        if self._att is None or self._pos is None:
            return False
        ta, q, w = self._att
        tp, p, v = self._pos
        t_ms = max(ta, tp)
        if abs(ta - tp) > self.stale_after * 1000:
            return False  # wait for a matching pair
        vals = [*p, *q, *w, *v]
        if not all(math.isfinite(x) for x in vals):
            self.c.reject("nan")
            return False
        vals[10:13] = _rot_T_apply(q, v) if (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]) > 0 else v
        self._att = self._pos = None
        return self._accept(vals, int(t_ms) * 1000, t_wall, "fallback")
