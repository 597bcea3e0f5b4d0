"""The loopback test vehicle: N simulated multirotors speaking MAVLink 2 over UDP.

Each vehicle is a single-body plant FMU (``FleetFMU(1)``) in NED/FRD. It inverts the configured
mapping (controls -> wrench), streams HEARTBEAT, ODOMETRY (default 250 Hz), ATTITUDE_QUATERNION
and LOCAL_POSITION_NED, answers SET_MESSAGE_INTERVAL, REQUEST_MESSAGE and
COMPONENT_ARM_DISARM with COMMAND_ACK, and fails safe (zero wrench; under gravity the hover
wrench −m Rᵀ g) when commands time out, saying so in a STATUSTEXT and a counter.

Who may do what (as autopilots do): any ground station may configure telemetry (HEARTBEAT,
SET_MESSAGE_INTERVAL, GET_MESSAGE_INTERVAL, REQUEST_MESSAGE, REQUEST_AUTOPILOT_CAPABILITIES →
AUTOPILOT_VERSION, PARAM_REQUEST_LIST / PARAM_REQUEST_READ → PARAM_VALUE), whatever its system
id; actuation (SET_ACTUATOR_CONTROL_TARGET, MANUAL_CONTROL, SET_ATTITUDE_TARGET, DO_SET_ACTUATOR,
arming, mode changes, parameter writes) only from the commander, or signed with the key when
there is one; anything else of it is refused as ``not_commander`` (a COMMAND_LONG with a DENIED
COMMAND_ACK). Replies go to the sender; the streams keep going where the commander is.

Stream rates are kept per requester: the commander's SET_MESSAGE_INTERVAL sets its own streams
(to the commander); a ground station's sets streams to its own address only (at most
`MAX_GROUND_STATIONS` per vehicle, each dropped after `GROUND_STATION_TIMEOUT` s without a packet
from it), so a ground station can configure only what it receives, never lower or disable what
the commander receives. Where a ground station shares the commander's address, its request can
only raise a rate there once the commander has been heard (before, it configures the link).

Real time: the wall clock advances the physics in ticks of 1/rate. ``lockstep``: a vehicle
advances exactly one control period per command whose time stamp (time_usec of
SET_ACTUATOR_CONTROL_TARGET; ``confirmation`` mod 256 for COMMAND_LONG) is its current step, and
answers with ODOMETRY at once; a repeated command re-sends the last ODOMETRY (so a bridge can
retry over a lossy link).
"""
from __future__ import annotations

import gc
import math
import select
import signal
import sys
import threading
import time

import numpy as np

from controller import layout
from controller.errors import Se3SyncError
from cosim import signals
from cosim.files import write_json_atomic
from cosim.scenario import load_scenario
from plant_fmu.fast import FleetFMU

from bridge.live import VehicleLive
from bridge.mavlink.link import (DRAIN_BUDGET, IFLAG_SIGNED, SIG_LEN, Counters, Peer, TLog, UdpSocket,
                   crc_ok, mavlink2, parse_endpoint, receive_datagrams, require_key_or_insecure)
from bridge.mavlink import codec
from bridge.mavlink.signing_state import open_signing_state
from bridge.mavlink.mapping import FleetMapping, MappingSpec
from bridge.mavlink.config import VEHICLE_TICK_LEAD, default_config, read_key_file
from bridge.mavlink.output import ACTUATOR_CONTROL_TARGET, DO_SET_ACTUATOR, PROFILE_BY_KEY, profile
from bridge.mavlink.transport import profiles_for, state_to_wire, vehicle_setup

M = mavlink2
ID_HEARTBEAT = M.MAVLINK_MSG_ID_HEARTBEAT
ID_ODOMETRY = M.MAVLINK_MSG_ID_ODOMETRY
ID_ATTQ = M.MAVLINK_MSG_ID_ATTITUDE_QUATERNION
ID_LPOS = M.MAVLINK_MSG_ID_LOCAL_POSITION_NED
STREAMABLE = (ID_HEARTBEAT, ID_ODOMETRY, ID_ATTQ, ID_LPOS)
NAN21 = [float("nan")] + [0.0] * 20
# ODOMETRY after the body rates: both covariances unknown, the frames, reset counter, estimator
# and quality (`SimVehicle.odometry`)
_ODOMETRY_TAIL = (*NAN21, *NAN21, M.MAV_FRAME_LOCAL_NED, M.MAV_FRAME_BODY_FRD, 0,
                  M.MAV_ESTIMATOR_TYPE_NAIVE, 100)
MAX_AHEAD_US = 1_000_000        # a command may be stamped at most 1 s ahead of the vehicle's clock
# --start-file: the physics ticks fall this share of a tick before each step of the swarm
TICK_LEAD = VEHICLE_TICK_LEAD
# real time: the sockets are read just before each tick (or every 50 ms when idle) instead of at
# each datagram's arrival: a process blocked in select is woken by every command that arrives (64
# a tick for 64 vehicles); asleep on a timer it is not, and a command is applied at the next tick
# however early it is read. While a socket is flooded (a pass read its whole budget) it is read
# as datagrams come, as before, so that the flood does not fill the kernel's buffer and crowd out
# the commander's commands.


def locked_tick(origin: float, now: float, tick: float, lead: float) -> float:
    """The first time >= ``now`` of the grid ``origin - lead + m·tick`` (m an integer): the
    ticks of a vehicle locked to a swarm whose step 0 is due at ``origin``."""
    first = origin - lead
    return first + math.ceil((now - first) / tick) * tick


def start_file_origin(path):
    """A callable giving the swarm's step 0 as time.monotonic() once ``path`` holds its Unix
    time (`swarm` writes it when every agent is ready), else None."""
    from pathlib import Path

    p = Path(path)

    def origin():
        try:
            start = float(p.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return None
        if not math.isfinite(start):
            return None
        return time.monotonic() + (start - time.time())
    return origin
DEFAULT_COMMANDER = (255, 191)  # the bridge's default source_system, source_component
ID_AUTOPILOT_VERSION = M.MAVLINK_MSG_ID_AUTOPILOT_VERSION
# what only the commander (or a signed sender) may send: the messages that move the vehicle or
# change its configuration, and the commands among those we implement that do
# (every output profile's message or command among them: `output.PROFILE_BY_KEY`)
ACTUATION_MSGS = frozenset((*(mid for mid, cmd in PROFILE_BY_KEY if cmd is None),
                            M.MAVLINK_MSG_ID_SET_POSITION_TARGET_LOCAL_NED,
                            M.MAVLINK_MSG_ID_SET_POSITION_TARGET_GLOBAL_INT,
                            M.MAVLINK_MSG_ID_SET_MODE, M.MAVLINK_MSG_ID_PARAM_SET,
                            M.MAVLINK_MSG_ID_RC_CHANNELS_OVERRIDE))
# the output profiles' per-step messages, decoded by `bridge.mavlink.codec` (`Peer.accept_fields`)
_FAST_COMMANDS = {m.id: {m.id: m} for m in (codec.SET_ACTUATOR_CONTROL_TARGET,
                                            codec.SET_ATTITUDE_TARGET, codec.MANUAL_CONTROL)}
ACTUATION_COMMANDS = frozenset((*(cmd for _, cmd in PROFILE_BY_KEY if cmd is not None),
                                M.MAV_CMD_COMPONENT_ARM_DISARM,
                                M.MAV_CMD_DO_SET_MODE, M.MAV_CMD_DO_SET_SERVO,
                                M.MAV_CMD_DO_MOTOR_TEST, M.MAV_CMD_DO_FLIGHTTERMINATION))
MAX_GROUND_STATIONS = 4         # per vehicle: ground stations with streams of their own
GROUND_STATION_TIMEOUT = 5.0    # s without a packet from one: its streams stop (heartbeats: 1 Hz)
PARAM_LIST_PERIOD = 1.0         # a ground station's PARAM_REQUEST_LIST: answered once per this
PARAM_LISTS_PER_S = 4           # long per address, and at most this many per second in all (each
#                                 answer is six PARAM_VALUE to an address that may be forged)
CAPABILITIES = (M.MAV_PROTOCOL_CAPABILITY_MAVLINK2 | M.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
                | M.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET)


class GroundStreams:
    """A ground station's own streams: {msgid: period (s) or None}, when each is due next, and
    when the last packet from it came."""

    __slots__ = ("interval", "due", "seen")

    def __init__(self, now: float):
        self.interval: dict = {}
        self.due: dict = {}
        self.seen = now


class SimVehicle:
    """One vehicle: FMU, socket, MAVLink peer, command state."""

    def __init__(self, server, index: int, system_id: int, endpoint: str, mapping_spec: MappingSpec,
                 mass: float, J, S0_ned, g_ned, h_internal: float, terms=None):
        self.server = server
        self.index = index
        self.sysid = system_id
        self.link_id = system_id & 0xFF   # the commander's signing link id for this vehicle
        self.sock = UdpSocket(endpoint)
        self.peer = Peer(system_id, 1, server.counters, key=server.key,
                         allow_unsigned_heartbeat=server.allow_unsigned_heartbeat,
                         link_id=index & 0xFF, tlog=server.tlog, signing_state=server.signing)
        self.mapping = FleetMapping([mapping_spec])
        self.mass = float(mass)
        self.g = np.asarray(g_ned, float)
        self.fmu = FleetFMU(1, instance_name=f"vehicle{system_id}")
        S0 = np.asarray(S0_ned, float).reshape(1, layout.S_WIDTH)
        self.fmu.set_initial_state(S0, mass=[mass], J=np.asarray(J, float).reshape(1, 3, 3),
                                   gravity=self.g, h_internal=h_internal, **(terms or {}))
        self.fmu.initialize(0.0)
        self.k = 0
        self.controls = np.zeros(6)
        self.wrench = np.zeros(6)
        self.last_cmd = None            # monotonic time of the latest accepted command
        self.last_cmd_us = None         # its time_usec (real time: older commands are dropped)
        self.failsafe = True            # no commands yet
        self.failsafe_count = 0
        self.commands = 0
        self.armed = not server.require_arm
        self.gcs_addr = None
        self.gcs_seen = None
        self.last_odom = None
        now = time.monotonic()
        # the commander's streams (to where the commander is: `destination`); changed only by
        # the commander's own SET_MESSAGE_INTERVAL
        self.interval = {ID_HEARTBEAT: 1.0, ID_ODOMETRY: server.odom_period,
                         ID_ATTQ: server.aux_period, ID_LPOS: server.aux_period}
        self.due = {k: now for k in self.interval}
        self.commander_heard = False    # a commander packet was accepted in full
        # each ground station's own streams, by its address: {addr: GroundStreams}
        self.ground: dict = {}
        self.param_lists: dict = {}     # a ground station's address -> when its list was answered
        self.wire = np.zeros(13)
        self.S = np.zeros(layout.S_WIDTH)
        # the output profiles this vehicle decodes, by (message id, command): the two that carry
        # raw controls always, and the scenario's own (`VehicleServer.__init__`)
        self.profiles = {}
        for name in (ACTUATOR_CONTROL_TARGET, DO_SET_ACTUATOR):
            prof = profile(name, h=server.h, group_mlx=server.group_mlx,
                           actuator_index_offset=server.actuator_index_offset)
            self.profiles[prof.key()] = prof
        self._reply = None              # the sender of the packet being handled (its replies)
        self._from_commander = False    # ... and whether it is the commander
        self._refresh()

    # ------------------------------------------------------------------ state
    def _refresh(self):
        S = self.fmu.get_state()
        q = self.fmu.get_quat()
        self.S[:] = S[0]
        self.wire[:] = state_to_wire(S, q)[0]

    def hover_wrench(self) -> np.ndarray:
        w = np.zeros(6)
        if self.g.any():
            R = self.S[layout.R]
            for i in range(3):
                w[3 + i] = -self.mass * (R[i] * self.g[0] + R[3 + i] * self.g[1] + R[6 + i] * self.g[2])
        return w

    def step(self, h: float) -> None:
        w = self.hover_wrench() if (self.failsafe or not self.armed) else self.wrench
        self.fmu.set_input(w.reshape(1, 6))
        self.fmu.do_step(self.k * h, h)
        self.k += 1
        self._refresh()

    # ------------------------------------------------------------------ out
    def send(self, msg, addr=None) -> None:
        """To ``addr`` (a reply), else where the commander is (udpin) or the udpout target."""
        addr = addr or self.gcs_addr
        if addr is None and self.sock.remote is None:
            return  # udpin and nobody has talked to us yet
        try:
            buf = self.peer.pack(msg)
        except Exception:  # noqa: BLE001 (e.g. a diverged state does not fit a float32)
            self.server.encode_errors += 1
            return
        if self.sock.send(buf, addr):
            self.server.counters.sent += 1
        else:
            self.server.counters.send_errors += 1

    def time_usec(self) -> int:
        if self.server.lockstep:
            return self.k * self.server.h_us
        return int(time.time() * 1e6)

    def odometry(self):
        """This vehicle's ODOMETRY now, as a `bridge.mavlink.codec` message: pymavlink's bytes
        (tests/bridge/test_bridge_vehicle.py compares them) without its objects, which were a
        third of the process's work with 64 vehicles at 100 Hz."""
        x = self.wire.tolist()
        return codec.ODOMETRY.encoded(self.time_usec(), x[0], x[1], x[2], x[3], x[4], x[5], x[6],
                                      x[10], x[11], x[12], x[7], x[8], x[9], *_ODOMETRY_TAIL)

    def send_odometry(self):
        self.send(self.odometry())

    def send_message(self, msgid: int, addr=None) -> bool:
        mav = self.peer.mav
        x = self.wire
        tb = int((time.monotonic() - self.server.t_boot) * 1000) & 0xFFFFFFFF
        if msgid == ID_AUTOPILOT_VERSION:
            self.send(self.autopilot_version(), addr)
        elif msgid == ID_ODOMETRY and addr is None:
            self.send_odometry()
        elif msgid == ID_HEARTBEAT:
            mode = M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (M.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0)
            self.send(mav.heartbeat_encode(M.MAV_TYPE_HEXAROTOR, M.MAV_AUTOPILOT_GENERIC, mode, 0,
                                           M.MAV_STATE_ACTIVE if self.armed else M.MAV_STATE_STANDBY), addr)
        elif msgid == ID_ATTQ:
            self.send(mav.attitude_quaternion_encode(tb, x[3], x[4], x[5], x[6], x[7], x[8], x[9]), addr)
        elif msgid == ID_LPOS:
            # LOCAL_POSITION_NED carries the velocity in NED: v_ned = R v_frd
            R = self.S[layout.R]
            v = x[10:13]
            vn = [R[3 * i] * v[0] + R[3 * i + 1] * v[1] + R[3 * i + 2] * v[2] for i in range(3)]
            self.send(mav.local_position_ned_encode(tb, x[0], x[1], x[2], vn[0], vn[1], vn[2]), addr)
        elif msgid == ID_ODOMETRY:
            self.send(self.odometry(), addr)
        else:
            return False
        return True

    def autopilot_version(self):
        """AUTOPILOT_VERSION: what we are (MAVLink 2, float parameters, SET_ATTITUDE_TARGET);
        flight_sw_version 0.1.0 in PX4's layout (major << 24 | minor << 16 | patch << 8 | type,
        255 = release), uid = the system id."""
        return self.peer.mav.autopilot_version_encode(
            CAPABILITIES, (0 << 24) | (1 << 16) | (0 << 8) | 255, 0, 0, 0, [0] * 8, [0] * 8,
            [0] * 8, 0, 0, self.sysid)

    # ------------------------------------------------------------------ parameters (read-only)
    def params(self) -> list:
        """[(name, value)]: read-only REAL32 parameters, what a ground station may read."""
        srv = self.server
        odom = self.interval.get(ID_ODOMETRY)
        return [("SE3_SYSID", float(self.sysid)), ("SE3_MASS", self.mass),
                ("SE3_CTRL_STEP", srv.h), ("SE3_CMD_TMO", srv.command_timeout),
                ("SE3_ODOM_HZ", 1.0 / odom if odom else 0.0),
                ("SE3_LOCKSTEP", float(srv.lockstep))]

    def send_param(self, index: int, addr) -> bool:
        ps = self.params()
        if not 0 <= index < len(ps):
            return False
        name, value = ps[index]
        self.send(self.peer.mav.param_value_encode(name.encode(), float(value),
                                                   M.MAV_PARAM_TYPE_REAL32, len(ps), index), addr)
        return True

    def param_request(self, m, addr) -> None:
        if m.get_msgId() == M.MAVLINK_MSG_ID_PARAM_REQUEST_LIST:
            for i in range(len(self.params())):
                self.send_param(i, addr)
            return
        name = m.param_id if isinstance(m.param_id, str) else bytes(m.param_id).decode("ascii", "replace")
        name = name.split("\0", 1)[0]
        names = [n for n, _ in self.params()]
        index = m.param_index if m.param_index >= 0 else (names.index(name) if name in names else -1)
        if not self.send_param(index, addr):
            self.server.counters.reject("bad_command")   # no such parameter

    def param_list_allowed(self, addr, now: float) -> bool:
        """A ground station's PARAM_REQUEST_LIST is answered (six PARAM_VALUE to the sender's
        address, which without a key may be forged) at most once per `PARAM_LIST_PERIOD` per
        address and `PARAM_LISTS_PER_S` times per second in all."""
        pl = self.param_lists
        last = pl.get(addr)
        if last is not None and now - last < PARAM_LIST_PERIOD:
            return False
        for a in [a for a, t in pl.items() if now - t >= PARAM_LIST_PERIOD]:
            del pl[a]
        if len(pl) >= PARAM_LISTS_PER_S:
            return False
        pl[addr] = now
        return True

    def statustext(self, severity: int, text: str) -> None:
        self.send(self.peer.mav.statustext_encode(severity, text.encode()[:50]))

    def ack(self, command: int, result: int, m) -> None:
        """COMMAND_ACK to the sender of m (its address: `handle` notes it)."""
        self.send(self.peer.mav.command_ack_encode(command, result, 0, 0, m.get_srcSystem(),
                                                   m.get_srcComponent()), self._reply)

    # ------------------------------------------------------------------ streams
    def destination(self):
        """Where the commander's streams go: the commander's address (udpin, once it has
        talked) or the udpout target; None while nobody is there."""
        return self.gcs_addr or self.sock.remote

    def stream_period(self, msgid: int, addr=None):
        """The period (s) at which ``msgid`` goes to ``addr`` (None: the commander's
        destination), None if it does not. At the commander's destination the commander's
        interval holds, unless a ground station there asked otherwise: before the commander
        has been heard its request holds, afterwards it may only raise the rate."""
        dest = self.destination()
        if addr is not None and addr != dest:
            g = self.ground.get(addr)
            return None if g is None else g.interval.get(msgid)
        p = self.interval.get(msgid)
        g = self.ground.get(dest) if dest is not None else None
        if g is None or msgid not in g.interval:
            return p
        q = g.interval[msgid]
        if not self.commander_heard:
            return q
        if not p:
            return q
        return p if not q else min(p, q)

    def ground_request(self, mid: int, us: float, now: float) -> int:
        """A ground station's SET_MESSAGE_INTERVAL: its own stream of ``mid`` (to the sender's
        address); returns the COMMAND_ACK result."""
        srv = self.server
        addr = self._reply
        g = self.ground.get(addr)
        if g is None:
            self.expire_ground(now)
            if len(self.ground) >= MAX_GROUND_STATIONS:
                srv.counters.reject("no_stream_slot")
                return M.MAV_RESULT_TEMPORARILY_REJECTED
            g = self.ground[addr] = GroundStreams(now)
        if us < 0:
            g.interval[mid] = None
        else:
            g.interval[mid] = srv.default_interval(mid) if us == 0 else us * 1e-6
        g.due[mid] = now
        if addr == self.destination():
            self.due[mid] = now
        srv.ground_requests += 1
        return M.MAV_RESULT_ACCEPTED

    def expire_ground(self, now: float) -> None:
        for a in [a for a, g in self.ground.items() if now - g.seen > GROUND_STATION_TIMEOUT]:
            del self.ground[a]

    def emit_due(self, now: float, lockstep: bool = False) -> None:
        """The streams due now: the commander's (lockstep: not ODOMETRY, which answers each
        command), then each ground station's own, to its address."""
        dest = self.destination()
        for msgid in self.interval:
            if lockstep and msgid == ID_ODOMETRY:
                continue
            period = self.stream_period(msgid)
            if period is None or period <= 0:
                continue
            if now >= self.due[msgid]:
                self.send_message(msgid)
                nd = self.due[msgid] + period
                if lockstep:
                    self.due[msgid] = max(nd, now)
                else:
                    self.due[msgid] = nd if nd > now - period else now + period
        if not self.ground:
            return
        self.expire_ground(now)
        for addr, g in self.ground.items():
            if addr == dest:
                continue          # merged into the commander's streams (`stream_period`)
            for msgid, period in g.interval.items():
                if period is None or period <= 0 or now < g.due[msgid]:
                    continue
                self.send_message(msgid, addr)
                nd = g.due[msgid] + period
                g.due[msgid] = nd if nd > now - period else now + period

    # ------------------------------------------------------------------ in
    def set_controls(self, c, now: float) -> bool:
        # plain floats: numpy's per-call cost on one row was a quarter of the vehicle process
        # serving 64 vehicles (its every command); the same tests and products, the same bits
        c = [float(x) for x in c]
        if len(c) != 6 or not all(math.isfinite(x) and abs(x) <= 1.0 for x in c):
            self.server.counters.reject("bad_command")
            return False
        self.controls[:] = c
        if self.mapping.one_direct:
            self.wrench[:] = self.mapping.decode_row(c)
        else:
            self.wrench[:] = self.mapping.decode(np.array(c).reshape(1, 6))[0]
        self.commands += 1
        self.last_cmd = now
        if self.failsafe and self.server.started_commands.get(self.sysid):
            self.statustext(M.MAV_SEVERITY_NOTICE, "commands resumed")
        self.server.started_commands[self.sysid] = True
        self.failsafe = False
        return True

    def lockstep_command(self, stamp_ok: bool, stamp_prev: bool, c, now: float) -> None:
        if stamp_ok:
            if self.set_controls(c, now):
                self.step(self.server.h)
                self.send_odometry()
                self.last_odom = now
        elif stamp_prev:
            self.server.repeats += 1
            self.send_odometry()
        else:
            self.server.counters.reject("bad_command")

    def handle(self, m, addr, now: float, trusted: bool = True, commander: bool = True) -> None:
        """A packet that passed the link. ``trusted``: from the commander, or signed with the
        key; otherwise only telemetry configuration is obeyed (see the module docstring).
        ``commander``: it claims the commander's ids (its SET_MESSAGE_INTERVAL sets the
        commander's streams; anyone else's sets its own)."""
        srv = self.server
        mid = m.get_msgId()
        self._reply = addr
        self._from_commander = commander
        g = self.ground.get(addr)
        if g is not None and not commander:
            g.seen = now
        if mid == ID_HEARTBEAT:
            if trusted:
                self.gcs_seen = now
            return
        if not trusted and mid in ACTUATION_MSGS:
            srv.counters.reject("not_commander")
            return
        if mid in (M.MAVLINK_MSG_ID_PARAM_REQUEST_LIST, M.MAVLINK_MSG_ID_PARAM_REQUEST_READ):
            if m.target_system not in (0, self.sysid):
                srv.counters.reject("not_for_us")
                return
            if mid == M.MAVLINK_MSG_ID_PARAM_REQUEST_LIST and not commander \
                    and not self.param_list_allowed(addr, now):
                srv.counters.reject("rate_limited")
                return
            self.param_request(m, addr)
            return
        if mid == M.MAVLINK_MSG_ID_PARAM_SET:
            if m.target_system not in (0, self.sysid):
                srv.counters.reject("not_for_us")
                return
            srv.counters.reject("bad_command")             # the parameters are read-only
            names = [n for n, _ in self.params()]
            name = m.param_id if isinstance(m.param_id, str) else bytes(m.param_id).decode("ascii", "replace")
            if name.split("\0", 1)[0] in names:            # the value stays: say so
                self.send_param(names.index(name.split("\0", 1)[0]), addr)
            return
        if (mid, None) in PROFILE_BY_KEY:
            self.actuation(PROFILE_BY_KEY[(mid, None)], m, now)
            return
        if mid == M.MAVLINK_MSG_ID_COMMAND_LONG:
            if m.target_system not in (0, self.sysid):
                srv.counters.reject("not_for_us")
                return
            if not trusted and m.command in ACTUATION_COMMANDS:
                srv.counters.reject("not_commander")
                self.ack(m.command, M.MAV_RESULT_DENIED, m)
                return
            if (mid, m.command) in PROFILE_BY_KEY:
                self.actuation(PROFILE_BY_KEY[(mid, m.command)], m, now)
            else:
                self.command_long(m, now)
            return
        if mid == M.MAVLINK_MSG_ID_COMMAND_INT:
            self.ack(m.command, M.MAV_RESULT_UNSUPPORTED, m)

    def actuation(self, cls, m, now: float) -> None:
        """A command of output profile ``cls`` (any entry of `output.PROFILE_CLASSES`), decoded
        with the profile's own decoder against this vehicle's wire state: addressed to us, a
        profile this vehicle takes, valid contents, then its lockstep stamp or its time order."""
        srv = self.server
        if cls.target(m) not in (0, self.sysid):
            srv.counters.reject("not_for_us")
            return
        prof = self.profiles.get(cls.key())
        c = prof.decode(m, self.wire) if prof is not None else None
        if c is None:
            srv.counters.reject("bad_command")   # not this vehicle's profile, or out of range
            return
        if prof.name == DO_SET_ACTUATOR:   # NaN: "no change" there (MAVLink's definition); in any
            c = np.where(np.isnan(c), self.controls, c)   # other profile NaN is a bad command
        t_us = prof.time_us(m)
        if srv.lockstep:
            stamps = prof.stamps(m, self.k)
            if stamps is None:   # no stamp (MANUAL_CONTROL): lockstep by sequence, one step per command
                stamps = (True, False)
            self.lockstep_command(stamps[0], stamps[1], c, now)
        elif t_us is None:
            self.set_controls(c, now)
        elif self.future(t_us):
            return
        elif self.last_cmd_us is not None and t_us <= self.last_cmd_us \
                and self.last_cmd_us - t_us < 10_000_000:
            srv.counters.reject("out_of_order")   # overtaken by a newer command (jitter)
        elif self.set_controls(c, now):
            self.last_cmd_us = t_us

    def future(self, t_us: int) -> bool:
        """Real time: a command stamped more than MAX_AHEAD_US ahead of our clock (both sides
        stamp Unix time) is refused as ``future``; accepted, it would hold the ordering window
        and make every genuine command ``out_of_order`` until the clock caught up."""
        if t_us > time.time() * 1e6 + MAX_AHEAD_US:
            self.server.counters.reject("future")
            return True
        return False

    def command_long(self, m, now: float) -> None:
        srv = self.server
        cmd = m.command
        if cmd == M.MAV_CMD_COMPONENT_ARM_DISARM:
            if m.param1 in (0.0, 1.0):
                self.armed = m.param1 == 1.0
                self.ack(cmd, M.MAV_RESULT_ACCEPTED, m)
            else:
                self.ack(cmd, M.MAV_RESULT_DENIED, m)
            return
        if cmd == M.MAV_CMD_SET_MESSAGE_INTERVAL:
            mid, us = int(m.param1), m.param2
            if mid not in STREAMABLE or not math.isfinite(us):
                self.ack(cmd, M.MAV_RESULT_UNSUPPORTED if mid not in STREAMABLE else M.MAV_RESULT_DENIED, m)
                return
            if not self._from_commander:    # a ground station: its own streams only
                self.ack(cmd, self.ground_request(mid, us, now), m)
                return
            if us < 0:
                self.interval[mid] = None
            elif us == 0:
                self.interval[mid] = srv.default_interval(mid)
            else:
                self.interval[mid] = us * 1e-6
                self.due[mid] = now
            self.ack(cmd, M.MAV_RESULT_ACCEPTED, m)
            return
        if cmd == M.MAV_CMD_REQUEST_MESSAGE:
            mid = int(m.param1) if math.isfinite(m.param1) else -1
            ok = mid in STREAMABLE or mid == ID_AUTOPILOT_VERSION
            self.ack(cmd, M.MAV_RESULT_ACCEPTED if ok else M.MAV_RESULT_UNSUPPORTED, m)
            if ok:
                self.send_message(mid, self._reply)
            return
        if cmd == M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            self.ack(cmd, M.MAV_RESULT_ACCEPTED, m)
            self.send(self.autopilot_version(), self._reply)
            return
        if cmd == M.MAV_CMD_GET_MESSAGE_INTERVAL:
            mid = int(m.param1) if math.isfinite(m.param1) else -1
            if mid not in STREAMABLE:
                self.ack(cmd, M.MAV_RESULT_UNSUPPORTED, m)
                return
            self.ack(cmd, M.MAV_RESULT_ACCEPTED, m)
            # what the requester receives (the commander: its own streams)
            p = self.interval[mid] if self._from_commander else self.stream_period(mid, self._reply)
            self.send(self.peer.mav.message_interval_encode(mid, -1 if not p else int(round(p * 1e6))),
                      self._reply)
            return
        self.ack(cmd, M.MAV_RESULT_UNSUPPORTED, m)

    def check_timeout(self, now: float, scheduled: float | None = None) -> None:
        """Fails safe once no command came for longer than the command timeout. ``scheduled`` is
        the time this physics tick was due: the delay minus the tick's own lateness is what the
        design bounds (≤ timeout + one tick), whatever the scheduler did to this process."""
        if self.failsafe or self.last_cmd is None:
            return
        if now - self.last_cmd > self.server.command_timeout:
            self.failsafe = True
            self.failsafe_count += 1
            self.server.failsafe_delays.append(now - self.last_cmd)
            self.server.failsafe_tick_delays.append((now if scheduled is None else scheduled)
                                                    - self.last_cmd)
            self.statustext(M.MAV_SEVERITY_WARNING, "failsafe: commands timed out, zero wrench")

    def close(self):
        self.sock.close()
        self.fmu.close()


class VehicleServer:
    """Serves vehicles with system ids ``first_system_id .. first_system_id + count - 1``."""

    def __init__(self, count: int = 1, *, base_port: int | None = None, host: str | None = None,
                 endpoints=None, shared_port: bool = False, lockstep: bool = False, key: bytes | None = None,
                 scenario=None, rate: float = 250.0, aux_rate: float = 10.0, step: float | None = None,
                 command_timeout: float | None = None, first_system_id: int = 1, tlog=None,
                 allow_unsigned_heartbeat: bool = False, require_arm: bool = False,
                 gravity_ned=(0.0, 0.0, 0.0), quiet: bool = True, commander=None,
                 insecure: bool = False, signing_state=None, key_file=None):
        cfg = None
        base_port_arg, host_arg = base_port, host
        if scenario is not None:
            cfg = scenario.bridge or default_config(scenario.n_agents)
            count = scenario.n_agents
        base_port = base_port if base_port is not None else (cfg.base_port if cfg else 14540)
        host = host if host is not None else (cfg.host if cfg else "127.0.0.1")
        self.count = int(count)
        self.lockstep = bool(lockstep)
        self.live = None   # a callable(server) after each tick: the live view (bridge/live.py)
        self.key = key
        # only the commander (system, component; component 0 = any) may talk to the vehicles
        self.commander = tuple(commander) if commander is not None else \
            ((cfg.source_system, cfg.source_component) if cfg else DEFAULT_COMMANDER)
        self.signing = None
        self.allow_unsigned_heartbeat = allow_unsigned_heartbeat or bool(cfg and cfg.allow_unsigned_heartbeat)
        self.require_arm = require_arm
        self.rate = float(rate)
        self.odom_period = 1.0 / self.rate
        self.aux_period = 1.0 / aux_rate if aux_rate and aux_rate > 0 else None
        self.h = float(step if step is not None else (scenario.step if scenario is not None else 1.0 / self.rate))
        self.h_us = int(round(self.h * 1e6))
        self.command_timeout = float(command_timeout) if command_timeout is not None else 2.0 * self.h
        self.group_mlx = cfg.group_mlx if cfg else 0
        self.actuator_index_offset = cfg.actuator_index_offset if cfg else 0
        self.counters = Counters()
        self.tlog = TLog(tlog) if tlog else None
        self.encode_errors = 0
        self.repeats = 0
        self.ground_requests = 0          # SET_MESSAGE_INTERVAL of ground stations (their own streams)
        self.drain_deadline_hits = 0      # receive passes cut short by the tick deadline
        self._flooded = False             # the last receive pass found a socket flooded
        self.read_passes = 0              # receive passes (real time: one a tick, unless flooded)
        self.ticks = 0                    # real time: physics ticks since the first command
        self.late_ticks = 0               # ... of them more than one tick after they were due
        self.resyncs = 0                  # ... and times it fell 10 ticks behind and skipped them
        self.cpu_s = self.wall_s = None   # `run`: its CPU time (s) and its wall time
        self.ticking_cpu_s = self.ticking_s = None   # ... from the first counted tick on
        self._ticking_from = None
        self.failsafe_delays: list = []   # command timeout detected: seconds since the last command
        self.failsafe_tick_delays: list = []  # the same, from the time the detecting tick was due
        self.started_commands: dict = {}
        # real time, --start-file: a callable giving the swarm's step 0 (time.monotonic()) or
        # None while unknown; the ticks are locked to it once known (`locked_tick`)
        self.tick_origin = None
        self.tick_lead = TICK_LEAD * self.odom_period
        self.locked_at = None             # ... the step-0 time it was locked to (monotonic)
        self.locked_due: list = []        # ... the times the first ticks after it were due
        self.quiet = quiet
        self.t_boot = time.monotonic()
        self._stop = threading.Event()
        self.ready = threading.Event()
        self.vehicles: list[SimVehicle] = []

        if scenario is not None:
            masses, Js, S0, g = vehicle_setup(scenario, cfg.world_frame)
            specs = cfg.mappings
            sids = [v.system_id for v in cfg.vehicles]
            h_int = scenario.internal_step
            terms = scenario.plant_terms     # the optional ground and drag ([plant])
        else:
            masses = np.ones(self.count)
            Js = np.tile(np.diag([0.01, 0.01, 0.02]), (self.count, 1, 1))
            S0 = np.zeros((self.count, layout.S_WIDTH))
            S0[:, layout.S_P] = np.arange(self.count, dtype=float)
            S0[:, layout.R] = np.eye(3).ravel()
            g = np.asarray(gravity_ned, float)
            specs = [MappingSpec()] * self.count
            sids = list(range(first_system_id, first_system_id + self.count))
            h_int = min(self.h, 1e-3)
            terms = {}
        eps = []
        # with a scenario and no address given here, each vehicle is the other end of its
        # [bridge] endpoint (udpin:H:P there -> udpout:H:P here, and the reverse), so that
        # explicit per-vehicle endpoints ([[bridge.vehicle]], bridge.endpoints) are honoured
        mirror = cfg is not None and not endpoints and not shared_port and \
            base_port_arg is None and host_arg is None
        for i in range(self.count):
            if endpoints:
                eps.append(endpoints[i])
            elif mirror:
                mode, (h_, p_) = parse_endpoint(cfg.vehicles[i].endpoint)
                eps.append(f"{'udpout' if mode == 'udpin' else 'udpin'}:{h_}:{p_}")
            elif shared_port or (cfg is not None and cfg.routing == "shared"):
                eps.append(f"udpout:{host}:{base_port}")
            else:
                eps.append(f"udpout:{host}:{base_port + sids[i] - 1}")
        require_key_or_insecure(eps, key, insecure, "send this vehicle commands")
        self.signing = open_signing_state(key, signing_state, key_file, "vehicle")
        try:
            for i in range(self.count):
                self.vehicles.append(SimVehicle(self, i, sids[i], eps[i], specs[i], masses[i], Js[i], S0[i], g, h_int,
                                                terms))
        except Exception:
            self.close()
            raise
        self._by_fd = {v.sock.fileno(): v for v in self.vehicles}
        if scenario is not None:  # the scenario's output profiles (the wrench ones need its limits and J)
            for v, prof in zip(self.vehicles, profiles_for(cfg, scenario)):
                v.profiles[prof.key()] = prof

    def default_interval(self, mid):
        return {ID_HEARTBEAT: 1.0, ID_ODOMETRY: self.odom_period, ID_ATTQ: self.aux_period,
                ID_LPOS: self.aux_period}[mid]

    def stop(self) -> None:
        self._stop.set()

    @property
    def failsafe_count(self) -> int:
        return sum(v.failsafe_count for v in self.vehicles)

    def stats(self) -> dict:
        d = self.counters.as_dict()
        d.update(failsafe=self.failsafe_count, failsafe_active=[v.failsafe for v in self.vehicles],
                 commands=sum(v.commands for v in self.vehicles), steps=[v.k for v in self.vehicles],
                 repeats=self.repeats, encode_errors=self.encode_errors,
                 drain_deadline_hits=self.drain_deadline_hits, read_passes=self.read_passes,
                 commander=list(self.commander),
                 ticks=self.ticks, late_ticks=self.late_ticks, resyncs=self.resyncs,
                 tick_s=self.odom_period, cpu_s=self.cpu_s, wall_s=self.wall_s,
                 tick_lead_s=self.tick_lead if self.tick_origin is not None else None,
                 tick_locked=self.locked_at is not None,
                 ticking_cpu_s=self.ticking_cpu_s, ticking_s=self.ticking_s,
                 failsafe_delay_max=max(self.failsafe_delays) if self.failsafe_delays else None,
                 failsafe_delays=[round(x, 6) for x in self.failsafe_delays[:200]],
                 failsafe_tick_delays=[round(x, 6) for x in self.failsafe_tick_delays[:200]],
                 command_timeout=self.command_timeout, control_period=self.h,
                 ground_stations={"interval_requests": self.ground_requests,
                                  "streams": self._ground_streams()})
        return d

    def _ground_streams(self) -> dict:
        """{vehicle: {"host:port": {message: Hz (0 = off)}}}: the ground stations' own streams."""
        out = {}
        for v in self.vehicles:
            if v.ground:
                out[str(v.sysid)] = {
                    f"{a[0]}:{a[1]}": {M.mavlink_map[k].msgname if k in M.mavlink_map else str(k):
                                       (round(1.0 / p, 3) if p else 0.0) for k, p in g.interval.items()}
                    for a, g in v.ground.items()}
        return out

    def _receive(self, v: SimVehicle, now: float) -> None:
        c = self.counters
        csys, ccomp = self.commander
        keyed = self.key is not None

        def on_packet(pkt, addr):
            commander = pkt[5] == csys and (not ccomp or pkt[6] == ccomp)
            if commander and keyed and pkt[2] & IFLAG_SIGNED and pkt[-SIG_LEN] != v.link_id:
                # the commander signs each vehicle's link on its own stream (link id = the
                # vehicle's system id): a signed commander packet on another link id is another
                # vehicle's, replayed here (a HEARTBEAT would move where the streams go)
                c.reject("wrong_link")
                return
            if not commander and not keyed and \
                    (pkt[7] | (pkt[8] << 8) | (pkt[9] << 16)) in ACTUATION_MSGS:
                # refused before decoding (cheap): actuation from anyone but the commander
                if crc_ok(pkt) is False:
                    c.malformed += 1
                else:
                    c.reject("not_commander")
                return
            fast = _FAST_COMMANDS.get(pkt[7] | (pkt[8] << 8) | (pkt[9] << 16))
            if fast is not None:
                # the per-step commands: their fields without pymavlink's objects (a sixth of
                # this process's time serving 64 vehicles at 100 Hz went to building them)
                got = v.peer.accept_fields(pkt, fast)
                m = None if got is None else codec.Received(fast[got[0]], got[1], pkt)
            else:
                m = v.peer.accept(pkt)
            if m is None:
                return
            m0 = c.mark()
            try:
                # with a key, every packet that got here is signed with it (or an unsigned
                # HEARTBEAT that allow_unsigned_heartbeat lets in, which commands nothing)
                v.handle(m, addr, now, commander or keyed, commander=commander)
            except (ValueError, TypeError, OverflowError):  # e.g. int(nan) of a parameter
                c.reject("bad_command")
                return
            if c.refusals() == m0[0]:
                v.peer.commit()
                if commander:
                    self._accepted(v, addr)
            elif c.arrived_since(m0):
                v.peer.commit()         # overtaken by a newer command: it came, no loss

        return receive_datagrams(v.sock, c, on_packet)

    def _accepted(self, v: SimVehicle, addr) -> None:
        """A packet from the commander passed the link and its handler: only now may it
        (udpin) tell where to send the streams. With a key only a signed packet moves the
        address; udpout endpoints never move. (Its signature's replay window and sequence
        number were committed by the caller: `Peer.commit`.)"""
        if self.key is None or v.peer.last_signed:
            v.commander_heard = True
            if v.sock.mode == "udpin":
                v.gcs_addr = addr

    def _drain(self, ready, deadline: float) -> float:
        """One bounded pass over the ready sockets (each gives at most DRAIN_BUDGET datagrams),
        stopping early once the tick deadline has passed while a socket is flooded (it filled its
        budget) so that the timer (fail-safe, physics)
        keeps its deadline under a flood; the sockets are visited in rotating order so a flooded
        one cannot always go first. Returns time.monotonic() after the pass."""
        now = time.monotonic()
        n = len(ready)
        flooded = False
        self.read_passes += 1
        if n:
            self._rr = (getattr(self, "_rr", 0) + 1) % n
            for j in range(n):
                flooded |= self._receive(self._by_fd[ready[(self._rr + j) % n]], now) >= DRAIN_BUDGET
                now = time.monotonic()
                # without a flood every ready socket is read before the tick (no added latency)
                if flooded and now >= deadline and j < n - 1:
                    self.drain_deadline_hits += 1
                    break
        self._flooded = flooded
        return now

    def run(self, duration: float | None = None) -> dict:
        """Serves until stop(), SIGTERM/SIGINT (main thread) or ``duration`` seconds."""
        in_main = threading.current_thread() is threading.main_thread()
        old = None
        if in_main:
            old = signal.signal(signal.SIGTERM, lambda *a: (signals.note(signal.SIGTERM),
                                                            self._stop.set()))
        t0 = time.monotonic()
        # CPU time: the process's (`se3sync vehicle`), this thread's when served from another
        clock = time.process_time if in_main else time.thread_time
        cpu0 = clock()
        end = None if duration is None else t0 + duration
        tick = self.odom_period
        next_tick = t0
        next_look = t0
        fds = [v.sock.fileno() for v in self.vehicles]
        self.ready.set()
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                if end is not None and now >= end:
                    break
                if self.tick_origin is not None and self.locked_at is None \
                        and not self.lockstep and now >= next_look:
                    next_look = now + 0.02
                    origin = self.tick_origin()
                    if origin is not None:
                        # a state of each vehicle leaves just before each step is due, whatever
                        # the phase this process happened to start at: with an arbitrary phase a
                        # command that came after the tick waited a whole tick (for some agents
                        # every step), a delay the sampled loop does not have
                        self.locked_at = origin
                        next_tick = locked_tick(origin, now, tick, self.tick_lead)
                timeout = max(0.0, min(next_tick - now, 0.05))
                if self.lockstep or self._flooded:
                    # lockstep: each command steps the vehicles, read it as it comes
                    r, _, _ = select.select(fds, [], [], timeout)
                else:
                    if timeout > 0:
                        time.sleep(timeout)
                    r, _, _ = select.select(fds, [], [], 0.0)
                now = self._drain(r, next_tick)
                if self.signing is not None:
                    self.signing.tick(now)
                if now < next_tick:
                    continue
                if self.locked_at is not None and len(self.locked_due) < 50:
                    self.locked_due.append(next_tick)
                if not self.lockstep:
                    if self.ticks or any(v.last_cmd is not None for v in self.vehicles):
                        if not self.ticks:
                            self._ticking_from = (next_tick, clock())   # from when it was due
                        self.ticks += 1
                        if now - next_tick > tick:   # the machine could not keep the rate
                            self.late_ticks += 1
                    for v in self.vehicles:
                        v.check_timeout(now, next_tick)
                        v.step(tick)
                else:
                    for v in self.vehicles:  # idle: repeat the current state now and then
                        if v.last_odom is None or now - v.last_odom > 0.2:
                            v.send_odometry()
                            v.last_odom = now
                if self.live is not None:   # --live (bridge/live.py): at most its rate
                    self.live(self)
                for v in self.vehicles:
                    v.emit_due(now, lockstep=self.lockstep)
                next_tick += tick
                if now - next_tick > 10 * tick:  # fell far behind (suspended?): resynchronise
                    next_tick = now + tick if self.locked_at is None else \
                        locked_tick(self.locked_at, now, tick, self.tick_lead)   # on the grid
                    self.resyncs += 1
        except KeyboardInterrupt:
            pass
        finally:
            self.wall_s, self.cpu_s = time.monotonic() - t0, clock() - cpu0
            if self._ticking_from is not None:
                self.ticking_s = time.monotonic() - self._ticking_from[0]
                self.ticking_cpu_s = clock() - self._ticking_from[1]
            if in_main and old is not None:
                signal.signal(signal.SIGTERM, old)
        return self.stats()

    def close(self) -> None:
        for v in self.vehicles:
            try:
                v.close()
            except Exception:  # noqa: BLE001
                pass
        if self.tlog is not None:
            self.tlog.close()
        if self.signing is not None:
            self.signing.close()
            self.signing = None


def check_count(count, scenario) -> None:
    """--count with --scenario: the scenario decides the vehicles; a different count is refused."""
    if count is not None and count != scenario.n_agents:
        raise Se3SyncError(f"--count: {count} contradicts the scenario's {scenario.n_agents} vehicles "
                           f"(omit --count, or change the scenario's [agents] count)")


def run_vehicle_cli(args) -> int:
    """Handler of ``se3sync vehicle``."""
    scenario = None
    if args.scenario:
        scenario = load_scenario(args.scenario, args.set or [])
        check_count(args.count, scenario)
    key = read_key_file(args.key) if args.key else None
    g = [float(x) for x in args.gravity.split(",")] if args.gravity else (0.0, 0.0, 0.0)
    srv = VehicleServer(args.count or 1, base_port=args.base_port, host=args.host, endpoints=args.endpoint or None,
                        shared_port=args.shared_port, lockstep=args.lockstep, key=key, scenario=scenario,
                        rate=args.rate, aux_rate=args.aux_rate, step=args.step,
                        command_timeout=args.command_timeout, first_system_id=args.first_system_id,
                        tlog=args.tlog, allow_unsigned_heartbeat=args.allow_unsigned_heartbeat,
                        require_arm=args.require_arm, gravity_ned=g, commander=args.commander,
                        insecure=args.insecure, signing_state=args.signing_state, key_file=args.key)
    if getattr(args, "start_file", None) is not None:
        srv.tick_origin = start_file_origin(args.start_file)
    live = getattr(args, "live_target", None)
    if live is not None:
        srv.live = VehicleLive(scenario, live[0], live[1], rate=live[2],
                               step=srv.h if srv.lockstep else srv.odom_period)
        srv.live.announce()
    eps = ", ".join(v.sock.endpoint for v in srv.vehicles[:3]) + (" ..." if srv.count > 3 else "")
    print(f"se3sync vehicle: {srv.count} vehicle(s) ({'lockstep' if srv.lockstep else f'real time, {srv.rate:g} Hz'}) "
          f"-> {eps}", file=sys.stderr, flush=True)
    # what the set-up built lives as long as the process: frozen, the collector's full passes
    # skip it instead of stopping the vehicles' ticks to walk it (as `se3sync agent` does)
    gc.collect()
    gc.freeze()
    try:
        st = srv.run(args.duration)
    finally:
        srv.close()
        if srv.live is not None:
            srv.live.close()
    if args.stats:
        write_json_atomic(args.stats, st)
    print(f"se3sync vehicle: stopped; sent {st['sent']}, received {st['received']}, malformed {st['malformed']}, "
          f"rejected {st['rejected']}, failsafe {st['failsafe']}", file=sys.stderr, flush=True)
    return signals.exit_status() if signals.requested() else 0
