"""`MavlinkPlant`: the cosim Plant protocol over MAVLink links to N vehicles.

read() -> the latest valid state of every vehicle (scenario frames); apply(u) -> actuator
commands sent at once; advance(h) -> real time: wait (servicing the links) until the wall-clock
deadline t0 + (n+1)·h; lockstep: wait until every vehicle has answered with its state at
t = (n+1)·h, re-sending the command to any that has not within ``lockstep_resend``.
"""
from __future__ import annotations

import select
import sys
import time

import numpy as np

from controller import layout
from controller.errors import Se3SyncError
from cosim import signals

from . import codec
from .config import VEHICLE_TICK_LEAD, default_config, read_key_file
from .link import (DRAIN_BUDGET, IFLAG_SIGNED, Counters, Peer, TLog, UdpSocket, crc_ok,
                   mavlink2, parse_endpoint, receive_datagrams, require_key_or_insecure,
                   take_datagram)
from .signing_state import open_signing_state
from .state import StateTracker
from .state_wire import (COMMAND_BYTES, ODOMETRY_SIZE, T_DROPPED, T_READS, T_TAKEN, TAKE_FULL,
                         TAKE_SCANNED, TAKE_SLOTS, TAKE_STOP, command_row, pack_command,
                         recv_state, scan_odometry, take_states, wire_to_state_ned)
from .udp_io import send_all
from .transport import WIRE, Transport, profiles_for, wire_to_state

M = mavlink2
ID_HEARTBEAT = M.MAVLINK_MSG_ID_HEARTBEAT
ID_ODOMETRY = M.MAVLINK_MSG_ID_ODOMETRY
ID_ATTQ = M.MAVLINK_MSG_ID_ATTITUDE_QUATERNION
ID_LPOS = M.MAVLINK_MSG_ID_LOCAL_POSITION_NED
ID_ACK = M.MAVLINK_MSG_ID_COMMAND_ACK
ID_STATUSTEXT = M.MAVLINK_MSG_ID_STATUSTEXT
_ODOMETRY = {ID_ODOMETRY: codec.ODOMETRY}   # its struct layout (bridge.mavlink.codec)


class _Odometry:
    """ODOMETRY's fields (wire order, `Peer.accept_fields`) under pymavlink's attribute names,
    for `StateTracker.on_odometry`."""

    __slots__ = ("time_usec", "x", "y", "z", "q", "vx", "vy", "vz", "rollspeed", "pitchspeed",
                 "yawspeed", "frame_id", "child_frame_id")

    def __init__(self, f):
        (self.time_usec, self.x, self.y, self.z) = f[0:4]
        self.q = f[4:8]
        (self.vx, self.vy, self.vz, self.rollspeed, self.pitchspeed, self.yawspeed) = f[8:14]
        self.frame_id, self.child_frame_id = f[56], f[57]

    @staticmethod
    def get_msgId():
        return ID_ODOMETRY


HEARTBEAT_ASK_S = 0.2  # connect: how often a vehicle with a state but no HEARTBEAT is asked for one
ZERO_CONTROLS = (0.0,) * 6   # what `OutputProfile.compiled_fields` is asked for its other fields
LATE_KEPT = 16            # late steps noted by number in the link statistics (the first ones)
HIST_BIN = 1e-5        # latency histograms: 10 µs bins up to 0.2 s (the last bin is "more")
HIST_N = 20_001


def _hist_add(hist, seconds: float) -> None:
    i = int(seconds / HIST_BIN)
    hist[i if 0 <= i < HIST_N else HIST_N - 1] += 1


def _hist_pct(hist, q: float):
    """The q-quantile (0..1) of a histogram, in milliseconds (bin centre), or None if empty."""
    hist = np.asarray(hist)
    total = int(hist.sum())
    if total == 0:
        return None
    i = int(np.searchsorted(np.cumsum(hist), q * total, side="left"))
    return (min(i, HIST_N - 1) + 0.5) * HIST_BIN * 1e3


def _output_profiles(cfg, scenario, lockstep: bool) -> list:
    """Each vehicle's output profile (bridge.output); lockstep stamps must be exact."""

    profiles = profiles_for(cfg, scenario)
    if lockstep:
        for p in profiles:
            if p.lockstep_error() is not None:
                raise Se3SyncError(p.lockstep_error())
    return profiles


class ConnectError(Se3SyncError):
    """A vehicle never connected (or never sent a state) within the connect timeout."""


class LinkError(Se3SyncError):
    """Lockstep: a vehicle stopped answering."""


OTHER_SOURCE_PACKETS = 3   # packets from a second source that make connect() refuse
# connect() listens this long once every vehicle is ready, for a second process claiming one:
# with the HEARTBEAT asked for, it would otherwise be done before a second source is heard
CLAIM_LISTEN_S = 0.15
STATUS_QUIET_S = 5.0       # a vehicle's repeated fail-safe reports: one line per this long


class _Vehicle:
    __slots__ = ("i", "sysid", "sock", "peer", "tracker", "addr", "hb", "connected", "lost",
                 "t_cmd", "last_buf", "t_sent", "acks", "statustexts", "losses", "recoveries",
                 "failsafe_reports", "src", "src_t", "others", "status_t", "status_quiet",
                 "state_seqs", "state_compid")

    def __init__(self, i, sysid, sock, peer, tracker):
        self.i, self.sysid, self.sock, self.peer, self.tracker = i, sysid, sock, peer, tracker
        self.addr = sock.remote
        self.hb = None
        self.connected = False
        self.lost = False
        self.t_cmd = None       # send time of the latest command awaiting a state (latency)
        self.last_buf = None
        self.t_sent = 0.0
        self.acks = 0
        self.statustexts = []
        self.losses = 0
        self.recoveries = 0
        self.failsafe_reports = 0
        self.src = None         # the address the vehicle's accepted packets come from
        self.src_t = None       # …and when the latest came
        self.others = {}        # another source claiming this vehicle -> packets refused
        self.status_t = None    # when a fail-safe report was last printed
        self.status_quiet = 0   # reports not printed since
        # where compiled code takes its states whole (`state_wire.take_states`): the component
        # its ODOMETRY comes from and that stream's last sequence number (`Peer.sequence_array`)
        self.state_seqs = None
        self.state_compid = -1


class MavlinkPlant:
    """``MavlinkPlant(scenario, config=None, *, lockstep=None, key=None, tlog=None,
    connect_timeout=None, on_event=None)`` then ``connect()``; the cosim Plant protocol after.

    config: a BridgeConfig (default: the scenario's [bridge] table, else the defaults);
    lockstep/key/tlog/connect_timeout override it; key: bytes or a key file path;
    on_event(str): link events (default: printed to stderr).
    """

    def __init__(self, scenario, config=None, *, lockstep=None, key=None, tlog=None,
                 connect_timeout=None, on_event=None, insecure=False, signing_state=None):
        cfg = config if config is not None else (scenario.bridge or default_config(scenario.n_agents))
        self.cfg = cfg
        self.n = n = scenario.n_agents
        if len(cfg.vehicles) != n:
            raise Se3SyncError(f"bridge: {len(cfg.vehicles)} vehicles configured for {n} agents")
        self.h = float(scenario.step)
        self.h_us = int(round(self.h * 1e6))
        self.lockstep = cfg.lockstep if lockstep is None else bool(lockstep)
        if self.lockstep and abs(self.h_us - self.h * 1e6) > 1e-6:
            raise Se3SyncError(f"lockstep needs a step that is a whole number of microseconds, got {self.h}")
        self.connect_timeout = cfg.connect_timeout if connect_timeout is None else float(connect_timeout)
        if key is None and cfg.key_file:
            key = cfg.key_file
        key_path = None
        if isinstance(key, (str,)) or hasattr(key, "__fspath__"):
            key_path = key
            key = read_key_file(key)
        self.key = key
        require_key_or_insecure([vs.endpoint for vs in cfg.vehicles], key, insecure)
        self.signing = open_signing_state(key, signing_state or getattr(cfg, "signing_state", None), key_path)
        tl = tlog if tlog is not None else cfg.tlog
        self.tlog = TLog(tl) if tl else None
        self.on_event = on_event or (lambda s: print(f"se3sync connect: {s}", file=sys.stderr, flush=True))
        self.counters = Counters()
        self.transport = Transport(cfg.mappings, cfg.world_frame, scenario.masses, scenario.gravity,
                                   cfg.gravity_compensation)
        self.world = cfg.world_frame
        self.wire = np.zeros((n, WIRE))
        self.wire[:, 3] = 1.0
        self._S = None
        self._controls = np.zeros((n, 6))
        self.k = 0
        self.t0 = None
        # (lists: a numpy element's increment cost more than the rest of `_hist_add`)
        self.lat_hist = [0] * HIST_N     # command sent -> next state received
        self.age_hist = [0] * HIST_N     # age of the oldest state used at a step
        self.events: list = []
        self.late_steps = 0          # real time: steps whose deadline had already passed
        self.late_first = []         # …the first LATE_KEPT of them (when: at the start, or later)
        # real time: how long after its step's deadline each command left (a step is late only
        # past the next deadline, but a loopback vehicle locked to the timeline ticks
        # VEHICLE_TICK_LEAD of a step before it: a command later than that acts a step later
        # than in `run`, a step of actuation delay the sampled loop does not have)
        self.lag_hist = [0] * HIST_N
        self._past_tick_s = (1.0 - VEHICLE_TICK_LEAD) * self.h
        self.lag_max = 0.0
        self.past_tick = 0
        self.past_tick_first = []    # …their steps, the first LATE_KEPT
        self.lockstep_resends = 0
        self._closed = False
        self.socks: list[UdpSocket] = []
        self.vehicles: list[_Vehicle] = []
        self._route: dict = {}       # fd -> {sysid: _Vehicle}
        self._sock_by_fd: dict = {}
        # per-source isolation: a udpin endpoint's socket is the catch-all (first contact,
        # strangers, junk); once a vehicle's source address is known it gets a socket of its
        # own on the same port, connected to that address (SO_REUSEPORT), which the kernel
        # hands that address's datagrams and nothing else: junk fills only the catch-all's
        # buffer, never the vehicle's. {(catch-all fd, addr): [UdpSocket, {vehicle index}]}
        self._src_socks: dict = {}
        self._src_fds: set = set()
        self._settle: set = set()    # catch-alls to empty once (a source socket was just opened)
        self.source_socket_errors = 0
        self._dead_drops = 0         # kernel drops of source sockets closed since
        try:
            by_ep: dict = {}
            for i, vs in enumerate(cfg.vehicles):
                sock = by_ep.get(vs.endpoint)
                if sock is None:
                    if parse_endpoint(vs.endpoint)[0] == "udpin":
                        UdpSocket(vs.endpoint).close()   # free? (a port in use is an error)
                        sock = UdpSocket(vs.endpoint, reuse_port=True)
                    else:
                        sock = UdpSocket(vs.endpoint)    # connected to the vehicle
                    by_ep[vs.endpoint] = sock
                    self.socks.append(sock)
                    self._sock_by_fd[sock.fileno()] = sock
                    self._route[sock.fileno()] = {}
                # each commander-vehicle link signs on its own stream (link id, system,
                # component): link id = the vehicle's system id, so that one agent's commands,
                # replayed into another vehicle, are on a stream that vehicle never accepts
                # from its own commander (every agent of a swarm has the same system and
                # component id, 255:191)
                peer = Peer(cfg.source_system, cfg.source_component, self.counters, key=self.key,
                            allow_unsigned_heartbeat=cfg.allow_unsigned_heartbeat,
                            link_id=vs.system_id & 0xFF, tlog=self.tlog,
                            signing_state=self.signing)
                tr = StateTracker(self.counters, cfg.stale_after, check_stale=not self.lockstep,
                                  fallback=not self.lockstep)
                if self.lockstep:
                    tr.max_time_usec = 0   # connect: the state at t = 0
                v = _Vehicle(i, vs.system_id, sock, peer, tr)
                self.vehicles.append(v)
                self._route[sock.fileno()][vs.system_id] = v
        except OSError as exc:
            self.close()
            raise Se3SyncError(f"bridge: cannot open {vs.endpoint}: {exc.strerror or exc}") from None
        # the vehicles' ODOMETRY datagrams are decoded by compiled code
        # (`state_wire.scan_odometry`; False: the reference path alone, which tests compare)
        self.compiled_state = True
        self.scanned_states = 0      # datagrams it took
        self.read_compiled = 0       # datagrams read by compiled code (`state_wire.recv_state`)
        self._scan_scratch = np.zeros(ODOMETRY_SIZE, np.uint8)   # `scan_odometry`'s buffers
        self._scan_row = np.zeros(WIRE)
        self._scan_meta = np.zeros(6, np.int64)
        self._rx_buf = np.zeros(1 << 16, np.uint8)    # `recv_state`'s (a datagram's most)
        self.taken_states = 0        # states taken whole by compiled code (`take_states`)
        self._take_tot = np.zeros(TAKE_SLOTS, np.int64)
        self._no_seqs = np.full(1, -1, np.int64)
        # real time, the commands framed by compiled code and sent by libc on the socket
        # connected to the vehicle (`OutputProfile.compiled_fields`, `state_wire.pack_command`,
        # `udp_io.send_all`; the same bytes; False: `Peer.pack` and the socket's `send` alone,
        # which tests compare)
        self.compiled_command = True
        self.packed_commands = 0     # commands it sent
        self._cmd_buf = np.zeros(COMMAND_BYTES, np.uint8)
        self._cmd_f32 = np.zeros(8, np.float32)
        self._cmd_fd = np.zeros(1, np.int64)
        self._cmd_ok = np.zeros(1, np.int64)
        self._cmd_key = None         # (v.addr, v.src, _socks_moved) that `_cmd_fd_now` is for
        self._cmd_fd_now = -1
        self._socks_moved = 0        # vehicles' sources moved and sockets closed so far
        self._takers: dict = {}      # `_taker`'s answers: addr -> (_socks_moved, vehicle)
        self._fused = False          # `_fused_command`'s, once asked
        self._readers: dict = {}     # other sockets serviced while waiting: fd -> callback()
        self._refresh_fds()
        # steps between the master's checks for Ctrl-C and SIGTERM: about 0.1 s of the wall
        # clock (lockstep steps take at least a round trip, so the same count is shorter)
        self.max_block = max(1, int(round(0.1 / self.h)))
        # real time: read the sockets once per step at the deadline (an agent process) instead
        # of whenever a datagram arrives (latency measured on arrival, as `connect` reports it)
        self.drain_per_step = False
        # real time, one of several agents of a process (bridge.swarm.host): `advance` does
        # not wait; it sets `due`, the process's one stepping thread waits for it and calls
        # `resume`
        self.paced_by_host = False
        self.due = None
        self.read_budget_s = 0.25 * self.h   # a poll reads the vehicles' own sockets this long at most
        self.junk_budget_s = 0.1 * self.h    # …and the catch-alls (first contact, junk) this long
        self._rr = 0
        self._commanded = False      # the first command has gone out (vehicle reports printed)
        self._paced_from = None      # real time: step 0's wall-clock deadline, if fixed
        self._next_hb = 0.0
        self.profiles = _output_profiles(cfg, scenario, self.lockstep)

    # ------------------------------------------------------------------ events
    def _event(self, text: str) -> None:
        self.events.append({"wall": time.time(), "step": self.k, "text": text})
        if len(self.events) > 1000:
            del self.events[:500]
        self.on_event(text)

    # ------------------------------------------------------------------ I/O
    def _send(self, v: _Vehicle, msg) -> bytes | None:
        buf = v.peer.pack(msg)
        if v.sock.send(buf, v.addr):
            self.counters.sent += 1
            return buf
        self.counters.send_errors += 1
        return None

    def _send_raw(self, v: _Vehicle, buf: bytes) -> None:
        if v.sock.send(buf, v.addr):
            self.counters.sent += 1
        else:
            self.counters.send_errors += 1

    def _command_out(self, v: _Vehicle, c) -> bool:
        """Real time: vehicle v's command c framed by compiled code (`state_wire.pack_command` of
        its profile's `compiled_fields`; signed here, as `Peer.pack` signs) and sent, on the
        socket connected to the vehicle where there is one; False where the profile sends
        another message, a control does not fit a float32 or a tlog records the link (the
        caller then takes `message` and `_send`). (No `last_buf`: only lockstep resends.)"""
        peer = v.peer
        if peer.tlog is not None:
            return False
        mav = peer.mav
        signed = 1 if mav.signing.sign_outgoing else 0
        buf = self._cmd_buf
        f = self.profiles[v.i].compiled_fields(c, target=v.sysid, k=self.k, lockstep=False)
        if f is None:
            return False
        n = pack_command(buf, *f, mav.seq, mav.srcSystem, mav.srcComponent, signed,
                         self._cmd_f32)
        if n < 0:
            return False
        if signed:
            codec.sign_frame(mav, buf, 0, n)
        mav.seq = (mav.seq + 1) & 0xFF
        self.packed_commands += 1
        fd = self._connected_fd(v)
        if fd < 0:
            self._send_raw(v, buf[:n].tobytes())
        else:
            self._cmd_fd[0] = fd
            if send_all(self._cmd_fd, buf, n, self._cmd_ok):
                self.counters.sent += 1
            else:
                self.counters.send_errors += 1
        return True

    def warm_up(self) -> None:
        """Loads (or compiles) the compiled read and command paths now, with the types of the
        run, rather than at the first state or step: reads no socket, frames a command into
        scratch and sends it to no socket."""
        if self.compiled_state:     # a closed descriptor: EBADF, nothing read
            recv_state(-1, self._rx_buf, 0, self._scan_scratch, self._scan_row, self._scan_meta)
        if not self.compiled_command or self.lockstep:
            return
        for v, prof in zip(self.vehicles, self.profiles):
            f = prof.compiled_fields([0.0] * 6, target=v.sysid, k=0, lockstep=False)
            if f is not None:
                pack_command(self._cmd_buf, *f, 0, 1, 1, 0, self._cmd_f32)
        none = np.zeros(0, np.int64)
        send_all(none, self._cmd_buf, 0, none)
        fused = self._fused_command()
        if fused is not None:       # to no socket (fd −1): its types, no send
            enu, gc, mass, g, mw, st = fused
            command_row(np.zeros(6), np.zeros((1, layout.S_WIDTH)), mw, enu, gc, mass, g,
                        np.zeros((1, 6)), 0, 0, 0, 0, 0, 1, 1, self._cmd_buf, self._cmd_f32,
                        np.full(1, -1, np.int64), self._cmd_ok, st.copy())

    def _connected_fd(self, v: _Vehicle) -> int:
        """The socket connected to where v's packets go (``v.addr``), or −1: a udpout
        endpoint's own, or on udpin the source socket of v's source while that is ``v.addr``."""
        s = v.sock
        if s.mode != "udpin":
            return s.fileno()
        if v.src is None or v.addr != v.src:
            return -1
        e = self._src_socks.get((s.fileno(), v.src))
        return -1 if e is None else e[0].fileno()

    def _heartbeats(self, now: float) -> None:
        if now < self._next_hb:
            return
        self._next_hb = now + self.cfg.heartbeat_period
        for v in self.vehicles:
            if v.addr is not None:
                self._send(v, v.peer.mav.heartbeat_encode(M.MAV_TYPE_ONBOARD_CONTROLLER,
                                                          M.MAV_AUTOPILOT_INVALID, 0, 0, M.MAV_STATE_ACTIVE))

    def _receive(self, fd: int, now: float, deadline: float) -> None:
        sock = self._sock_by_fd.get(fd)
        if sock is None:
            return                # a source socket closed earlier in this poll (a restart)
        src = sock.connected_to
        if src is not None and self.compiled_state and not sock.backlog \
                and fd not in self._settle:
            v = self._taker(src)
            if v is not None:
                self._take_batches(v, fd, src, now, deadline)
                return
        on_packet, fast = self._handlers(fd, now)
        c = self.counters
        if fast is not None and src is not None and not sock.backlog:
            self._receive_compiled(sock, src, on_packet, deadline)
        else:
            receive_datagrams(sock, c, on_packet, deadline=deadline, fast=fast)
        while fd in self._settle:
            # a source socket was opened while this catch-all was read: what its source sent
            # before lies here (merged, `_source_socket`), older than anything on the new socket:
            # read it now, so that the next poll (the vehicles' sockets first) cannot take a
            # newer state first. Taking it may open more source sockets: hence the loop
            self._settle.discard(fd)
            receive_datagrams(sock, c, on_packet, deadline=time.monotonic() + 0.05, fast=fast)

    def _handlers(self, fd: int, now: float) -> tuple:
        """(on_packet, fast) for the datagrams of socket ``fd`` read at ``now``: the reference
        path's handler of one frame, and the compiled decoder of a whole state datagram in
        front of it (None without `compiled_state`)."""
        route = self._route[fd]
        c = self.counters
        alive = self.cfg.link_timeout

        def on_packet(pkt, addr, row=None):
            v = route.get(pkt[5])
            if v is None:
                if crc_ok(pkt) is False:
                    c.malformed += 1     # corrupted, not a stranger: its system id is noise
                else:
                    c.reject("wrong_system")
                return
            signed = self.key is None or bool(pkt[2] & IFLAG_SIGNED)
            if v.src is not None and addr != v.src and now - v.src_t <= alive:
                # a second process claims this vehicle while the first is alive (a leftover
                # vehicle on the same ports, a spoofer): never used, counted, reported once.
                # With a key only a fresh signed packet is evidence of a second process (the
                # refusal at connect); an unsigned HEARTBEAT or a replay proves nothing
                if v.peer.authentic(pkt):
                    if signed and self.key is not None and not v.peer.fresh(pkt):
                        c.reject("replay")
                    else:
                        self._other_source(v, addr, evidence=signed)
                return
            m0 = c.mark()
            if row is not None:
                # the state stream's common case, checked and decoded by `fast` below
                seq, sysid, compid, t_us, _, _ = self._scan_meta.tolist()
                used = v.peer.accepted(pkt, seq, sysid, compid) \
                    and v.tracker.on_odometry_row(row, t_us, now)
                if used:
                    self._state_taken(v, now)
            elif pkt[7] | (pkt[8] << 8) | (pkt[9] << 16) == ID_ODOMETRY:
                # the state stream, every step: its fields without building pymavlink's object
                got = v.peer.accept_fields(pkt, _ODOMETRY)
                used = got is not None and self._dispatch(v, _Odometry(got[1]), now)
            else:
                m = v.peer.accept(pkt)
                used = m is not None and self._dispatch(v, m, now)
            if c.arrived_since(m0):
                # authentic and refused by nothing (a fallback message ignored while ODOMETRY
                # comes is not refused), or only for being old (a state read after a stall):
                # its sequence number counts, its signature's window moves
                v.peer.commit()
            if c.refusals() == m0[0]:
                # with a key only a signed packet sets the vehicle's source or keeps it alive:
                # an unsigned HEARTBEAT (allow_unsigned_heartbeat) from anyone would otherwise
                # take the slot and lock the genuine, signed vehicle out as `other_source`
                if not signed:
                    pass
                elif addr == v.src:
                    v.src_t = now
                elif v.src is None or used:   # new, or the first source was silent for a link
                    old, v.src, v.src_t = v.src, addr, now    # timeout: a restart
                    self._source_socket(v, old)
            if used:
                self._accepted(v, addr)

        fast = None
        if self.compiled_state:
            # a vehicle's ODOMETRY datagrams checked and decoded by compiled code
            # (`state_wire.scan_odometry`), what that declines by the reference path above; a
            # datagram is taken by one or the other, whole
            scratch, out, meta = self._scan_scratch, self._scan_row, self._scan_meta
            keyed = 0 if self.key is None else 1       # (signatures: `Peer.accepted`)

            def fast(data, addr):
                if not scan_odometry(np.frombuffer(data, np.uint8), len(data), keyed, scratch,
                                     out, meta):
                    return False
                self.scanned_states += 1
                try:
                    on_packet(data, addr, out)
                except Exception:  # noqa: BLE001 - untrusted input never crashes us
                    c.malformed += 1
                return True

        return on_packet, fast

    def _receive_compiled(self, sock: UdpSocket, addr, on_packet, deadline: float) -> None:
        """`receive_datagrams` of a source socket (connected: every datagram is from ``addr``)
        with each read and scan one compiled call (`state_wire.recv_state`): the same datagrams
        to the same handlers, counted the same, without a bytes object and address tuple per
        read or an exception for the empty socket."""
        c = self.counters
        buf = self._rx_buf
        scratch, out, meta = self._scan_scratch, self._scan_row, self._scan_meta
        fd = sock.fileno()
        keyed = 0 if self.key is None else 1       # (signatures: `Peer.accepted`)
        limit = DRAIN_BUDGET
        while True:
            nb = 0          # datagrams of this batch (its reads: at most limit)
            for _ in range(limit):
                r = recv_state(fd, buf, keyed, scratch, out, meta)
                if r == 0 or r == -1:
                    break
                if r == -2:
                    continue
                nb += 1
                self.read_compiled += 1
                data = buf[:meta[5]].tobytes()
                if r == 1:
                    c.datagrams += 1
                    self.scanned_states += 1
                    try:
                        on_packet(data, addr, out)
                    except Exception:  # noqa: BLE001 - untrusted input never crashes us
                        c.malformed += 1
                else:
                    take_datagram(data, addr, c, on_packet)
            if nb > c.drain_max:
                c.drain_max = nb
            if nb < limit:
                return
            if time.monotonic() >= deadline:
                c.drain_capped += 1
                return

    def _taker(self, addr):
        """The vehicle whose states from ``addr`` compiled code may take whole
        (`_take_batches`), or None: the one vehicle coming from there, no key, no tlog, real
        time."""
        if self.key is not None:
            return None
        if len(self.vehicles) == 1:
            v = self.vehicles[0]
            if v.src != addr:
                return None
        else:
            # which vehicle comes from addr changes only when a source moves: asked again then
            hit = self._takers.get(addr)
            if hit is None or hit[0] != self._socks_moved:
                vs = [v for v in self.vehicles if v.src == addr]
                hit = self._takers[addr] = (self._socks_moved, vs[0] if len(vs) == 1 else None)
            v = hit[1]
            if v is None:
                return None
        tr = v.tracker
        if v.peer.tlog is not None or tr.max_time_usec is not None or not tr.check_stale:
            return None
        return v

    def _take_batches(self, v: _Vehicle, fd: int, addr, now: float, deadline: float) -> None:
        """`_receive_compiled` of v's source socket ``fd`` (connected to ``addr``) by
        `state_wire.take_states`: v's states taken whole in compiled code and recorded here as
        the reference path records them, every other datagram handed to that path in its turn;
        the same batches, counts and time budget."""
        c = self.counters
        tr = v.tracker
        buf, scratch, out, meta = self._rx_buf, self._scan_scratch, self._scan_row, \
            self._scan_meta
        tot = self._take_tot
        stale_us = tr.stale_after * 1e6
        limit = DRAIN_BUDGET
        on_packet = None          # the reference path's handler, made when first needed
        while True:
            tot[:] = 0
            while True:           # a batch: at most limit reads
                # before the tracker has taken an ODOMETRY of its own (and a stream to count),
                # every state goes the reference path's way (the first one starts the clock)
                compid = v.state_compid if tr.n_odometry and tr.stamped else -1
                r = take_states(fd, buf, scratch, out, meta, v.sysid, compid, limit, now,
                                stale_us, tr.clock, tr.stamp,
                                v.state_seqs if compid >= 0 else self._no_seqs, tr.wire, tot)
                if tot[T_TAKEN]:
                    self._took_states(v, addr, now, tot)
                if r == TAKE_STOP or r == TAKE_FULL:
                    break
                data = buf[:meta[5]].tobytes()
                if on_packet is None:
                    on_packet = self._handlers(fd, now)[0]
                if r != TAKE_SCANNED:
                    take_datagram(data, addr, c, on_packet)
                    continue
                c.datagrams += 1
                self.scanned_states += 1
                n0 = tr.n_odometry
                try:
                    on_packet(data, addr, out)
                except Exception:  # noqa: BLE001 - untrusted input never crashes us
                    c.malformed += 1
                if v.state_seqs is None and tr.n_odometry > n0:
                    # the stream this vehicle's states come on, counted in compiled code now on
                    v.state_compid = int(meta[2])
                    v.state_seqs = v.peer.sequence_array([(int(meta[1]), v.state_compid)])
            nb = int(tot[T_READS])
            self.read_compiled += nb
            if nb > c.drain_max:
                c.drain_max = nb
            if nb < limit:
                return
            if time.monotonic() >= deadline:
                c.drain_capped += 1
                return

    def _took_states(self, v: _Vehicle, addr, now: float, tot) -> None:
        """What the reference path records of each state `take_states` took (tot's counts)."""
        n, dropped = int(tot[T_TAKEN]), int(tot[T_DROPPED])
        tot[T_TAKEN] = tot[T_DROPPED] = 0
        self.counters.datagrams += n
        self.scanned_states += n
        self.taken_states += n
        v.peer.took_counted(n, dropped)
        v.tracker.took(n, now)
        self._state_taken(v, now)
        v.src_t = now
        self._accepted(v, addr)

    def _source_socket(self, v: _Vehicle, old) -> None:
        """Vehicle v's source changed from ``old`` (or None) to ``v.src``: on a udpin endpoint,
        the socket connected to its new source (shared by the vehicles that come from that
        address, e.g. behind a router); the old one is closed when no vehicle uses it."""
        self._socks_moved += 1
        base = v.sock
        if base.mode != "udpin":
            return                # udpout: the socket is connected to the vehicle already
        bfd = base.fileno()
        if old is not None:
            e = self._src_socks.get((bfd, old))
            if e is not None:
                e[1].discard(v.i)
                if not e[1]:
                    del self._src_socks[(bfd, old)]
                    self._forget(e[0])
        e = self._src_socks.get((bfd, v.src))
        if e is None:
            try:
                s = UdpSocket(f"udpin:{base.local[0]}:{base.local[1]}", reuse_port=True,
                              connect_to=v.src)
            except OSError:
                self.source_socket_errors += 1    # it stays on the catch-all (still checked)
                return
            # what reached the new socket before its connect (anyone's, `UdpSocket`) and what
            # waits on the catch-all, in the order it arrived, for the catch-all's next read
            # (the settle below): a vehicle's first states otherwise came out of order (its
            # older ones refused, counted lost)
            base.merge_backlog(s)
            fd = s.fileno()
            self._sock_by_fd[fd] = s
            self._route[fd] = self._route[bfd]
            self._src_fds.add(fd)
            self._refresh_fds()
            self._settle.add(bfd)
            e = self._src_socks[(bfd, v.src)] = [s, set()]
        e[1].add(v.i)

    def _forget(self, s: UdpSocket) -> None:
        fd = s.fileno()
        self._socks_moved += 1
        self._dead_drops += s.kernel_drops() or 0
        for d in (self._sock_by_fd, self._route):
            d.pop(fd, None)
        self._src_fds.discard(fd)
        s.close()
        self._refresh_fds()

    def _refresh_fds(self) -> None:
        self._fds = [s.fileno() for s in self.socks] + sorted(self._src_fds) + list(self._readers)

    def _other_source(self, v: _Vehicle, addr, evidence: bool = True) -> None:
        """Counts a packet from a second source; with ``evidence`` (no key, or signed) it is
        also recorded per address (`other_sources`, the refusal at connect, the report)."""
        self.counters.reject("other_source")
        if not evidence:
            return
        if addr not in v.others and len(v.others) >= 16:
            addr = ("*", 0)          # many addresses (spoofed at random): counted together
        n = v.others.get(addr, 0) + 1
        v.others[addr] = n
        if n == 1 and len(v.others) <= 3:   # reported for the first few addresses only
            self._event(f"vehicle {v.i + 1} (system {v.sysid}): packets from {addr[0]}:{addr[1]} "
                        f"too, while {v.src[0]}:{v.src[1]} is its source: a second process on "
                        f"{v.sock.endpoint} (a leftover vehicle?); refused and counted "
                        "(other_source)")

    def _accepted(self, v: _Vehicle, addr) -> None:
        """A packet passed the link and was used: only now may it (udpin) tell where the
        vehicle is. With a key only a signed packet moves the address (an unsigned HEARTBEAT
        let in by allow_unsigned_heartbeat does not); udpout endpoints never move."""
        if v.sock.mode == "udpin" and addr != v.addr and (self.key is None or v.peer.last_signed):
            v.addr = addr

    def _dispatch(self, v: _Vehicle, m, now: float) -> bool:
        """Hands a message to its consumer; True if it was used (a state accepted, a heartbeat,
        an acknowledgement or a status text), False if refused or not (yet) used."""
        mid = m.get_msgId()
        tr = v.tracker
        ok = False
        if mid == ID_ODOMETRY:
            ok = tr.on_odometry(m, now)
        elif mid == ID_HEARTBEAT:
            v.hb = now
            if not v.connected:
                v.connected = True
        elif mid == ID_ATTQ:
            ok = tr.on_attitude_quaternion(m, now)
        elif mid == ID_LPOS:
            ok = tr.on_local_position_ned(m, now)
        elif mid == ID_ACK:
            if m.command == M.MAV_CMD_COMPONENT_ARM_DISARM:   # (the arming retries stop)
                v.acks += 1
        elif mid == ID_STATUSTEXT:
            txt = m.text if isinstance(m.text, str) else bytes(m.text).decode("utf-8", "replace")
            v.statustexts.append(txt)
            if len(v.statustexts) > 50:
                del v.statustexts[:25]
            failsafe = "failsafe" in txt
            if failsafe:
                v.failsafe_reports += 1
            if self.t0 is not None and self._commanded:
                # the vehicle's fail-safe and resume reports, printed from the first command
                # on (before it, a vehicle without commands is in fail-safe by design), and
                # then at most one line per STATUS_QUIET_S while they repeat
                if failsafe or "resumed" in txt:
                    if v.status_t is not None and now - v.status_t < STATUS_QUIET_S:
                        v.status_quiet += 1
                        return True
                    if v.status_quiet:
                        txt += f" ({v.status_quiet} more fail-safe/resume reports in the last " \
                               f"{now - v.status_t:.3g} s; all in the summary's vehicle_failsafes)"
                    v.status_t, v.status_quiet = now, 0
                self._event(f"vehicle {v.i + 1} (system {v.sysid}): {txt}")
        if ok:
            self._state_taken(v, now)
        return ok or mid in (ID_HEARTBEAT, ID_ACK, ID_STATUSTEXT)

    def _state_taken(self, v: _Vehicle, now: float) -> None:
        """Vehicle v's tracker took a new state."""
        self.wire[v.i] = v.tracker.wire
        if v.t_cmd is not None:
            _hist_add(self.lat_hist, now - v.t_cmd)
            v.t_cmd = None
        if v.lost:
            v.lost = False
            v.recoveries += 1
            self._event(f"vehicle {v.i + 1} (system {v.sysid}): link recovered")

    def add_reader(self, fd: int, callback) -> None:
        """Services another socket while this plant waits: ``callback()`` is called whenever
        ``fd`` is readable (an agent process reads its neighbours' link this way)."""
        self._readers[int(fd)] = callback
        self._refresh_fds()

    def pace_from(self, t0: float) -> None:
        """Real time: step k is due at ``t0 + k·h`` (time.monotonic()), instead of counting from
        the first command: agents of a swarm keep one timeline."""
        self._paced_from = float(t0)
        self.t0 = float(t0)

    def poll(self, timeout: float) -> None:
        """Services the links for at most ``timeout`` seconds (returns after the first batch)."""
        r, _, _ = select.select(self._fds, [], [], max(0.0, timeout))
        now = time.monotonic()
        deadline = now + self.read_budget_s
        # the vehicles' own sockets first, then the other readers, then the catch-alls (in
        # turn, sharing a smaller budget: junk never delays a vehicle's states)
        src, catch, called = [], [], []
        srcs, route, readers = self._src_fds, self._route, self._readers
        for fd in r:
            if fd in srcs:
                src.append(fd)
            elif fd in route:
                catch.append(fd)
            else:
                cb = readers.get(fd)
                if cb is not None and cb not in called:   # one reader may own several sockets
                    called.append(cb)
        if len(catch) > 1:
            self._rr = (self._rr + 1) % len(catch)
            catch = catch[self._rr:] + catch[:self._rr]
        for fd in src:
            self._receive(fd, now, deadline)
        for cb in called:
            cb()
        if self._settle:
            # a source socket opened while another socket was read: its catch-all holds what
            # came before it, to be read now, whether or not its own socket signalled
            catch += [fd for fd in self._settle if fd not in catch]
        if catch:
            junk_deadline = min(max(deadline, time.monotonic()), time.monotonic() + self.junk_budget_s)
            for fd in catch:
                self._receive(fd, now, junk_deadline)
        if self.signing is not None:
            self.signing.tick(now)

    # ------------------------------------------------------------------ connection
    def connect(self) -> "MavlinkPlant":
        """Waits for a HEARTBEAT and a first valid state from every vehicle (lockstep: the state
        at t = 0). Raises ConnectError naming the vehicles that did not connect."""
        t_end = time.monotonic() + self.connect_timeout
        t_settle = None
        armed_sent = 0.0
        hb_asked = {}
        while True:
            now = time.monotonic()
            self._heartbeats(now)
            for v in self.vehicles:
                # a state but no HEARTBEAT yet: ask for one (at once, then every
                # HEARTBEAT_ASK_S) rather than wait up to a second for the periodic one (most of
                # an agent's start-up); a vehicle that does not answer MAV_CMD_REQUEST_MESSAGE
                # sends its periodic one anyway
                if v.addr is not None and v.tracker.have and not v.connected \
                        and now - hb_asked.get(v.i, -HEARTBEAT_ASK_S) >= HEARTBEAT_ASK_S:
                    hb_asked[v.i] = now
                    self._send(v, v.peer.mav.command_long_encode(
                        v.sysid, 1, M.MAV_CMD_REQUEST_MESSAGE, 0, ID_HEARTBEAT, 0, 0, 0, 0, 0, 0))
            for v in self.vehicles:
                other = next((a for a, k in v.others.items() if k >= OTHER_SOURCE_PACKETS), None)
                if other is not None:
                    raise Se3SyncError(
                        f"bridge: {v.sock.endpoint}: vehicle {v.i + 1} (system {v.sysid}) is "
                        f"claimed by two processes, {v.src[0]}:{v.src[1]} and {other[0]}:{other[1]}"
                        " (a leftover vehicle or bridge on these ports?); stop the other one or "
                        "use other ports")
            ready = [v.connected and v.tracker.have and (not self.lockstep or v.tracker.time_usec == 0)
                     for v in self.vehicles]
            if all(ready):
                # listen CLAIM_LISTEN_S more in any case (a second process claiming a vehicle,
                # e.g. a leftover one on these ports, is heard then: a vehicle streams at tens
                # of Hz), and when a second source was seen, up to half a second for the
                # evidence (one stray packet costs half a second, never a refusal)
                if t_settle is None:
                    t_ready, t_settle = now, now + 0.5
                if (now < t_ready + CLAIM_LISTEN_S
                        or any(v.others for v in self.vehicles)) and now < t_settle:
                    self.poll(0.01)
                    continue
                break
            if now >= t_end:
                missing = [v for v, r in zip(self.vehicles, ready) if not r]
                what = ", ".join(f"{v.i + 1} (system {v.sysid}, {v.sock.endpoint}"
                                 f"{'' if v.connected else ', no heartbeat'}"
                                 f"{'' if v.tracker.have else ', no state'})" for v in missing[:4])
                more = f" and {len(missing) - 4} more" if len(missing) > 4 else ""
                raise ConnectError(f"vehicle(s) {what}{more} did not connect within {self.connect_timeout:g} s")
            if self.cfg.arm and now - armed_sent > 0.5:
                armed_sent = now
                for v in self.vehicles:
                    if v.addr is not None and v.acks == 0:
                        self._send(v, v.peer.mav.command_long_encode(
                            v.sysid, 1, M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0))
            self.poll(0.01)
        if self.cfg.odometry_rate > 0:
            for v in self.vehicles:
                self._send(v, v.peer.mav.command_long_encode(
                    v.sysid, 1, M.MAV_CMD_SET_MESSAGE_INTERVAL, 0, ID_ODOMETRY,
                    1e6 / self.cfg.odometry_rate, 0, 0, 0, 0, 0))
        self._S = wire_to_state(self.wire, self.world)
        now = time.monotonic()
        self.t0 = now if self._paced_from is None else self._paced_from
        for v in self.vehicles:
            v.hb = now
        self._event(f"{self.n} vehicle(s) connected ({'lockstep' if self.lockstep else 'real time'}, "
                    f"h = {self.h:g} s)")
        return self

    # ------------------------------------------------------------------ Plant protocol
    def read(self) -> np.ndarray:
        if self._S is None:
            if self.world == "ned":     # compiled, the same bits (`state_wire`)
                self._S = np.empty((self.n, layout.S_WIDTH))
                wire_to_state_ned(self.wire, self._S)
            else:
                self._S = wire_to_state(self.wire, self.world)
        return self._S

    def apply(self, u) -> None:
        S = self.read()
        fused = None
        if self.compiled_command and not self.lockstep:
            fused = self._fused if self._fused is not False else self._fused_command()
        if fused is not None:
            # one vehicle's whole command in one compiled call (`state_wire.command_row`)
            now = time.monotonic()
            self._pace_and_time(now)
            if self._command_row(u, S, fused, now):
                return
            c = (self._controls[0].tolist(),)      # the reference path sends it (below)
        else:
            tr = self.transport
            if tr.mapping.one_direct:   # one vehicle (an agent's): plain floats, the same bits
                c = (tr.controls_row(u, S),)
                self._controls[0] = c[0]
            else:
                c = tr.controls(u, S)
                self._controls[:] = c
            now = time.monotonic()
            self._pace_and_time(now)
        fast = self.compiled_command and not self.lockstep and fused is None
        for v in self.vehicles:
            if v.addr is None:
                continue
            if fast and self._command_out(v, c[v.i]):
                v.t_sent = now
                if v.t_cmd is None:
                    v.t_cmd = now
                continue
            msg = self.profiles[v.i].message(v.peer.mav, c[v.i], target=v.sysid, k=self.k,
                                             lockstep=self.lockstep, wire=self.wire[v.i])
            self._send(v, msg)
            v.last_buf = msg
            v.t_sent = now
            if v.t_cmd is None:
                v.t_cmd = now

    def _pace_and_time(self, now: float) -> None:
        """A step's command at ``now``: pacing starts (the first command), the age of the states
        it used and how long after its deadline it left are recorded."""
        if self.k == 0 and not self.lockstep and self._paced_from is None:
            self.t0 = now  # pacing starts with the first command (not at connect)
        oldest = min((v.tracker.t_arrival or now) for v in self.vehicles) if self.n > 1 \
            else (self.vehicles[0].tracker.t_arrival or now)
        _hist_add(self.age_hist, now - oldest)
        if not self.lockstep:
            lag = now - (self.t0 + self.k * self.h)
            if lag > 0.0:
                i = int(lag / HIST_BIN)   # `_hist_add` inline: this runs at every step
                self.lag_hist[i if i < HIST_N else HIST_N - 1] += 1
                if lag > self.lag_max:
                    self.lag_max = lag
                if lag > self._past_tick_s:
                    self.past_tick += 1
                    if len(self.past_tick_first) < LATE_KEPT:
                        self.past_tick_first.append(self.k)
            else:
                self.lag_hist[0] += 1
        self._commanded = True

    def _fused_command(self):
        """What `_command_row` needs that does not change (the transport's mapping and frames),
        or None where the command takes the paths of `apply` below: more than one vehicle, a
        mapping other than direct, a profile that sends another message, a signed link, a tlog."""
        f = self._fused
        if f is False:
            tr = self.transport
            v = self.vehicles[0]
            f = None
            if self.n == 1 and tr.mapping.one_direct and v.peer.tlog is None \
                    and not v.peer.mav.signing.sign_outgoing \
                    and self.profiles[0].compiled_fields(ZERO_CONTROLS, target=v.sysid, k=0,
                                                         lockstep=False) is not None:
                f = (tr.world != "ned", bool(tr.gravity_compensation), float(tr.masses[0]),
                     np.array(tr.gravity, np.float64), np.array(tr.mapping._mw, np.float64),
                     np.zeros(3, np.int64))
            self._fused = f
        return f

    def _command_row(self, u, S, fused, now: float) -> bool:
        """`Transport.controls_row`, `_command_out` and the send of vehicle 0's command as one
        compiled call (`state_wire.command_row`, the same controls and bytes); the counters
        updated as those update them. False when the reference path must send it (a control
        beyond float32): the controls are in ``_controls[0]``."""
        enu, gc, mass, g, mw, st = fused
        v = self.vehicles[0]
        tr = self.transport
        mav = v.peer.mav
        key = (v.addr, v.src, self._socks_moved)
        if key != self._cmd_key:     # where the command goes changed (or never asked)
            self._cmd_key = key
            self._cmd_fd_now = self._connected_fd(v) if v.addr is not None else -1
        self._cmd_fd[0] = fd = self._cmd_fd_now
        f = self.profiles[0].compiled_fields(ZERO_CONTROLS, target=v.sysid, k=self.k,
                                             lockstep=False)
        n = command_row(np.asarray(u, dtype=np.float64).reshape(6), S, mw, enu, gc, mass, g,
                        self._controls, f[0], f[7], f[8], f[9], mav.seq, mav.srcSystem,
                        mav.srcComponent, self._cmd_buf, self._cmd_f32, self._cmd_fd,
                        self._cmd_ok, st)
        nan, sat, ok = st.tolist()
        if nan:
            tr.nan_commands += 1
        mp = tr.mapping
        if sat:
            mp.saturations += 1
            mp.saturated_vehicles[0] += 1
        if mp.last_saturated[0] != sat:
            mp.last_saturated = np.array([bool(sat)])
        if v.addr is None:
            return True
        if n < 0:
            return False
        mav.seq = (mav.seq + 1) & 0xFF
        self.packed_commands += 1
        if fd < 0:
            self._send_raw(v, self._cmd_buf[:n].tobytes())
        elif ok:
            self.counters.sent += 1
        else:
            self.counters.send_errors += 1
        v.t_sent = now
        if v.t_cmd is None:
            v.t_cmd = now
        return True

    def advance(self, h: float) -> None:
        if self.t0 is None:
            raise Se3SyncError("MavlinkPlant: call connect() first")
        if self.lockstep:
            self._advance_lockstep()
        else:
            self._advance_realtime()
        self.k += 1
        self._S = None

    def _advance_realtime(self) -> None:
        deadline = self.t0 + (self.k + 1) * self.h
        now = time.monotonic()
        if now > deadline:
            self.late_steps += 1
            if len(self.late_first) < LATE_KEPT:
                self.late_first.append(self.k + 1)
        self.due = deadline
        if self.paced_by_host:
            return    # the host waits until `due`, then calls `resume`
        if self.drain_per_step:
            # wake once per step: what arrived meanwhile waits in the sockets and is read in one
            # pass at the deadline (the step uses nothing newer anyway); each wake-up costs a
            # select and a Python dispatch, which several processes per core cannot afford
            if deadline > now:
                time.sleep(deadline - now)
            self.poll(0.0)
            now = time.monotonic()
        while now < deadline:
            self.poll(deadline - now)
            now = time.monotonic()
        self._heartbeats(now)
        self._check_links(now)

    def resume(self) -> None:
        """Real time, paced by the host (``paced_by_host``): the wait for ``due`` is over; what
        `advance` does after it (the links drained in one pass, heartbeats, link checks)."""
        self.poll(0.0)
        now = time.monotonic()
        self._heartbeats(now)
        self._check_links(now)

    def _check_links(self, now: float) -> None:
        cfg = self.cfg
        for v in self.vehicles:
            ta = v.tracker.t_arrival
            silent = ta is None or now - ta > cfg.link_timeout
            hb_lost = v.hb is not None and now - v.hb > cfg.heartbeat_timeout
            if (silent or hb_lost) and not v.lost:
                v.lost = True
                v.losses += 1
                why = "no state" if silent else "no heartbeat"
                self._event(f"vehicle {v.i + 1} (system {v.sysid}): link lost ({why} for "
                            f"{(now - (ta if silent and ta else v.hb)):.3g} s)")

    def _advance_lockstep(self) -> None:
        target = (self.k + 1) * self.h_us
        for v in self.vehicles:   # a state stamped after the step waited for is refused
            v.tracker.max_time_usec = target
        t_start = time.monotonic()
        while True:
            waiting = [v for v in self.vehicles if v.tracker.time_usec is None or v.tracker.time_usec < target]
            if not waiting:
                return
            now = time.monotonic()
            if now - t_start > self.cfg.lockstep_timeout:
                raise LinkError(f"lockstep: vehicle(s) {', '.join(str(v.i + 1) for v in waiting[:6])} did not "
                                f"answer step {self.k} within {self.cfg.lockstep_timeout:g} s")
            if signals.requested():
                # Ctrl-C or SIGTERM while a vehicle is awaited (it may be the one stopping):
                # stop now, as the master would between two steps, not after the timeout
                raise KeyboardInterrupt
            for v in waiting:
                if now - v.t_sent > self.cfg.lockstep_resend and v.last_buf is not None \
                        and self.profiles[v.i].resend_ok:
                    self._send(v, v.last_buf)  # re-packed: a new sequence number and signature
                    v.t_sent = now
                    self.lockstep_resends += 1
            self._heartbeats(now)
            self.poll(0.005)

    # ------------------------------------------------------------------ stats
    def stats(self) -> dict:
        d = self.counters.as_dict()
        d["latency_ms_p50"] = _hist_pct(self.lat_hist, 0.50)
        d["latency_ms_p99"] = _hist_pct(self.lat_hist, 0.99)
        d["latency_samples"] = sum(self.lat_hist)
        d["state_age_ms_p50"] = _hist_pct(self.age_hist, 0.50)
        d["state_age_ms_p99"] = _hist_pct(self.age_hist, 0.99)
        d["saturations"] = int(self.transport.mapping.saturations)
        d["nan_commands"] = int(self.transport.nan_commands)
        d["late_steps"] = int(self.late_steps)
        d["late_first"] = list(self.late_first)
        d["command_lag_ms_p50"] = _hist_pct(self.lag_hist, 0.50)
        d["command_lag_ms_p99"] = _hist_pct(self.lag_hist, 0.99)
        d["command_lag_ms_max"] = self.lag_max * 1e3 if sum(self.lag_hist) else None
        d["commands_past_tick"] = int(self.past_tick)
        d["past_tick_first"] = list(self.past_tick_first)
        d["lockstep_resends"] = int(self.lockstep_resends)
        d["link_losses"] = int(sum(v.losses for v in self.vehicles))
        d["link_recoveries"] = int(sum(v.recoveries for v in self.vehicles))
        d["links_down"] = [v.i + 1 for v in self.vehicles if v.lost]
        d["duplicates"] = int(sum(v.tracker.duplicates for v in self.vehicles))
        d["vehicle_failsafes"] = int(sum(v.failsafe_reports for v in self.vehicles))
        d["other_sources"] = {f"{v.i + 1}": {f"{a[0]}:{a[1]}": k for a, k in v.others.items()}
                              for v in self.vehicles if v.others}
        d["kernel_drops"] = sum(x or 0 for x in (s.kernel_drops() for s in self.socks))
        # of them on the vehicles' own sockets (only a flood with a vehicle's forged address, or
        # a reader far behind, fills those), counting the sockets closed since
        own = [e[0].kernel_drops() for e in self._src_socks.values()]
        d["kernel_drops_sources"] = self._dead_drops + sum(x or 0 for x in own)
        d["kernel_drops"] += d["kernel_drops_sources"]
        d["source_sockets"] = len(self._src_socks)
        return d

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for s in self.socks:
            s.close()
        for e in getattr(self, "_src_socks", {}).values():
            e[0].close()
        if getattr(self, "signing", None) is not None:
            self.signing.close()
        if self.tlog is not None:
            self.tlog.close()
