"""The inter-agent link: what one agent's controller process sends to and receives from its graph
neighbours (and only them) over MAVLink 2 / UDP, signed when a key is given (issue 9).

One sample of agent j at step s is what the delay contract of `cosim.network` calls "j's message
of sample s": X_j(s), ξ_j(s) and θ_k(s) after the jump stage for the edges j owns (k ∈ M_j⁺). On
the wire it is two standard common-dialect messages, packed into **one UDP datagram** per
neighbour (so they arrive together or not at all):

* **ODOMETRY (#331)**: time_usec = s · round(h·1e6) (µs of simulated time, the sample stamp),
  frame_id MAV_FRAME_LOCAL_NED, child_frame_id MAV_FRAME_BODY_FRD, x y z, q (w, x, y, z), body
  rates and body velocity, converted from the scenario's world/body frames exactly as the bridge
  converts vehicle state (`bridge.mavlink.frames`, ``bridge.world_frame``); the receiver rebuilds the same
  float32-rounded row S_j as `bridge.mavlink.transport.wire_to_state`.
* **DEBUG_FLOAT_ARRAY (#350)** carries θ: time_usec = the same stamp, name ``"theta"``,
  array_id = the sender's agent id, data[0..] = θ_k for the sender's owned edges in ascending
  edge order, NaN-padded (the receiver maps them to edges with the graph). Why this message: θ_k
  is a controller-internal scalar per edge with no semantic message of its own; DEBUG_FLOAT_ARRAY
  is the common dialect's one message made for an application array, carries a 64-bit sample
  stamp (NAMED_VALUE_FLOAT has only a 32-bit millisecond boot time, too coarse for h < 1 ms and
  one message per edge) and 58 floats at once. An agent owning more than 58 edges sends further
  chunks named ``"theta1"``, ``"theta2"``, … (edges 58c … 58c+57 of its owned list). An agent that
  owns no edge sends ODOMETRY only.

System id = agent id; component id = `AGENT_COMPONENT` = 191 (MAV_COMP_ID_ONBOARD_COMPUTER: the
controller runs as the vehicle's companion computer, which shares the vehicle's system id). No
HEARTBEAT is sent: a link's liveness is the age of its newest sample (`age_steps`).

Receiving (`poll`) is untrusted input and never raises. In order, cheapest first: a datagram
that does not start with MAVLink 2's magic byte is ``malformed``; one whose sender address is not
a neighbour's endpoint is ``wrong_address`` (every agent sends from the socket bound at its own
endpoint); both before any parsing, so a flood of junk costs little (`poll` drains by a time
budget, not a count). Then a packet whose system id is not a neighbour's (or whose component is
not `AGENT_COMPONENT`), or not the system of the endpoint it came from, is ``not_neighbour``;
with a key, unsigned, wrong-key and replayed packets are counted by `bridge.mavlink.link.Peer`; a decoded
message is counted ``nan``, ``non_unit_quaternion`` (| ‖q‖ − 1 | > 1e-3), ``bad_frame`` (other
frame ids), ``bad_stamp`` (time_usec not a whole step), ``future`` (stamped more than
``future_steps`` ahead of the receiver's own step, `set_step`/`set_timeline`: never used, never
moves the ordering window), ``bad_theta`` (wrong name or array_id), ``unexpected_message`` (any
other message), ``out_of_order`` (older than the held or assembling sample) or ``duplicate``
(same stamp as the held sample). Every refusal of a packet that names a neighbour is also
counted on that neighbour's link (`stats()["links"][j]["rejected_by_reason"]`).

Per neighbour only the NEWEST complete sample is held (`neighbour`); a newer sample replaces an
incomplete one in assembly (counted ``incomplete``), an older arrival never replaces newer data.
A neighbour that restarted on another timeline stamps far back (more than 10 s of sample time)
and keeps stamping forward from there: `RESTART_SAMPLES` consecutive complete samples of that
kind, each newer than the one before, are taken as its restart (``restarts`` per link); one
packet never is.

The lockstep history (``history``) keeps the first pose and θ chunks of each step; a later copy
that differs from them is never used and is counted (``conflicts``, per link and in total): two
versions of one step's data, i.e. a forgery or a misbehaving sender (an identical resend is not).
"""
from __future__ import annotations

import heapq
import math
import socket
import time
from collections import Counter
from dataclasses import dataclass

import numpy as np

from controller import layout
from controller.errors import Se3SyncError
from controller.kernels import FRESH, rot_to_quat_rows

from bridge.mavlink import codec, frames
from bridge.mavlink.link import (DRAIN_BUDGET, Counters, Peer, UdpSocket, mavlink2, packet_ids,
                   receive_datagrams, take_datagram)
from bridge.mavlink.state import QUAT_TOL
from bridge.mavlink.transport import wire_row_to_state
from bridge.mavlink.udp_io import send_all

from .sample_wire import (AGE_BINS, D_BATCH, D_DATAGRAMS, D_DROPPED, D_K, D_LEN, D_RECEIVED,
                          D_STEP, D_WIDTH, PACK_BYTES, SCAN_STATE, SCAN_WIDTH, age_rules,
                          drain_samples, pack_sample, publish_sample, scan_sample)

__all__ = ["AgentLink", "NeighbourSample", "AGENT_COMPONENT", "THETA_NAME", "THETA_PER_MESSAGE",
           "encode_sample", "theta_name"]

AGENT_COMPONENT = mavlink2.MAV_COMP_ID_ONBOARD_COMPUTER   # 191
THETA_NAME = "theta"
THETA_PER_MESSAGE = 58                                     # DEBUG_FLOAT_ARRAY.data has 58 floats
ID_ODOMETRY = mavlink2.MAVLINK_MSG_ID_ODOMETRY
ID_DEBUG_FLOAT_ARRAY = mavlink2.MAVLINK_MSG_ID_DEBUG_FLOAT_ARRAY
RESTART_S = 10.0                                           # a stamp this far back: the sender restarted…
RESTART_SAMPLES = 3                                        # …if this many such samples in a row say so
FUTURE_S = 0.02            # how far (s) a sample may be stamped ahead of the receiver's own step
FUTURE_MIN_STEPS = 2       # …and at least this many steps (lockstep neighbours are ≤ 1 step ahead)
POLL_BUDGET = 0.25         # a poll reads the neighbours' sockets for at most this fraction of a step
JUNK_BUDGET = 0.1          # …and the catch-all socket (strangers, junk) for at most this fraction
NAN21 = [math.nan] + [0.0] * 20                            # covariance unknown (first element NaN)
_TYPES = {ID_ODOMETRY: codec.ODOMETRY, ID_DEBUG_FLOAT_ARRAY: codec.DEBUG_FLOAT_ARRAY}
# ODOMETRY after the body velocity: covariances unknown, frames, reset counter, estimator, quality
_ODO_TAIL = (*NAN21, *NAN21, mavlink2.MAV_FRAME_LOCAL_NED, mavlink2.MAV_FRAME_BODY_FRD, 0,
             mavlink2.MAV_ESTIMATOR_TYPE_NAIVE, 100)
_NAN58 = (math.nan,) * THETA_PER_MESSAGE
_ODO_FRAME = 56   # ODOMETRY's wire order: time_usec, x y z, q[4], vx vy vz, rates, 2×21 cov, frame ids
VERDICTS = ("fresh", "hold", "failsafe")     # `age_rules`' verdict codes
LINK_REASONS = ("not_neighbour", "wrong_address", "bad_stamp", "future", "bad_theta",
                "unexpected_message", "duplicate", "incomplete")


def theta_name(chunk: int) -> str:
    """DEBUG_FLOAT_ARRAY name of θ chunk c (edges 58c … 58c+57 of the owned list)."""
    return THETA_NAME if chunk == 0 else f"{THETA_NAME}{chunk}"


# θ chunk of a received name (a sender owns at most its graph's edges: 58 per chunk)
_CHUNK_OF = {theta_name(i): i for i in range(1024)}


def _finite(vals) -> bool:
    """Every value finite, for float32 values (as MAVLink's floats decode): their sum is finite
    exactly when each is (|x| < 3.5e38, so no sum of a few of them overflows a double; a NaN
    or an infinity makes the sum NaN or infinite), at the cost of one sum."""
    return math.isfinite(sum(vals))


def stamp_us(n: int, h_us: int) -> int:
    """time_usec of sample step n."""
    return int(n) * h_us


def encode_sample(mav, n: int, h_us: int, S_row, theta, world: str = "ned") -> list:
    """The messages of one sample: ODOMETRY (unless ``S_row`` is None), then one
    DEBUG_FLOAT_ARRAY per 58 owned θ (none if ``theta`` is empty or None), as
    `bridge.mavlink.codec` messages (pymavlink's bytes, without its objects). ``theta`` lists
    θ_k of the owned edges in ascending k; ``mav`` is the sender's MAVLink object (its system
    id is the agent id)."""
    t = stamp_us(n, h_us)
    out = []
    if S_row is not None:
        S = np.asarray(S_row, float).reshape(1, layout.S_WIDTH)
        if world != "ned":
            S = frames.state_world_to_ned(S, world)
        # one row, every step: the compiled conversion (numpy's per-call cost is most of it)
        q = np.empty((1, 4))
        rot_to_quat_rows(np.ascontiguousarray(S[:, layout.R]), q)
        r = S[0].tolist()
        out.append(codec.ODOMETRY.encoded(t, *r[layout.P], *q[0].tolist(), *r[layout.V],
                                          *r[layout.OMEGA], *_ODO_TAIL))
    theta = [float(x) for x in (theta if theta is not None else ())]
    for c in range(0, len(theta), THETA_PER_MESSAGE):
        chunk = theta[c:c + THETA_PER_MESSAGE]
        out.append(codec.DEBUG_FLOAT_ARRAY.encoded(
            t, mav.srcSystem, theta_name(c // THETA_PER_MESSAGE).encode(), *chunk,
            *_NAN58[len(chunk):]))
    return out


@dataclass
class NeighbourSample:
    """The newest complete sample of a neighbour j: S_j (scenario frames, float32-rounded values),
    ξ_j (= S_j[ξ]), θ_k (float32 values) for the edges j owns, its step and our wall arrival time
    (``clock()``, time.monotonic by default)."""

    step: int
    S: np.ndarray
    xi: np.ndarray
    theta: dict
    t_arrival: float


class _Assembly:
    """A sample being put together from its messages (normally all in one datagram)."""

    __slots__ = ("step", "wire", "chunks")

    def __init__(self, step: int):
        self.step = step
        self.wire = None
        self.chunks = {}


def _resolve(j: int, host: str, port: int) -> tuple:
    """(IPv4 address, port) of agent j's endpoint, resolved once (not at every sendto)."""
    try:
        return socket.gethostbyname(host), int(port)
    except OSError as exc:
        raise Se3SyncError(f"network: agent {j}'s address {host!r} does not resolve: "
                           f"{exc.strerror or exc}") from None


def _steps(seconds: float, h: float) -> int:
    return int(math.ceil(seconds / h - 1e-9)) if seconds > 0 else 0


def _nearest_rank(hist: Counter, p: float):
    total = sum(hist.values())
    if total == 0:
        return None
    rank = max(1, math.ceil(p / 100.0 * total))
    acc = 0
    for age in sorted(hist):
        acc += hist[age]
        if acc >= rank:
            return int(age)
    return int(max(hist))


class AgentLink:
    """Agent ``agent_id``'s end of the inter-agent links (see the module docstring).

    ``network`` is the parsed ``[network]`` table (`cosim.network.NetworkConfig`): the socket is
    bound on ``network.endpoints[agent_id − 1]`` and samples go to the endpoints of the agent's
    graph neighbours only. ``step`` is the control period h (s) that turns sample steps into
    time_usec; ``world`` the scenario's world frame ("ned" or "enu", ``bridge.world_frame``).
    ``key`` (32 bytes) signs everything sent and requires valid signatures on everything received.

    ``history`` (steps) keeps, besides the newest sample, every valid pose and θ message of the
    last ``history`` steps per neighbour (`pose_at`, `theta_at`): lockstep asks for exactly the
    data of step n, whatever order the messages came in. ``emulate`` applies the ``[network]``
    table's delay, jitter and loss of each outgoing link on the sending side (seeded per directed
    link from ``network.seed``): a message of step n leaves at step n + d + J (`release`) or is
    dropped, as in the co-simulation, on top of what the real network does.

    ``compiled`` (default) takes the common case of a real-time link, one neighbour's whole
    sample in one datagram, through a compiled decoder (`bridge.swarm.sample_wire`) that
    leaves every other datagram to the reference path; ``compiled=False`` is the reference path
    alone (the tests compare the two).
    """

    def __init__(self, agent_id: int, network, graph, *, step: float, key: bytes | None = None,
                 counters: Counters | None = None, world: str = "ned",
                 drain_budget: int = DRAIN_BUDGET, signing_state=None, clock=time.monotonic,
                 history: int = 0, emulate: bool = False, compiled: bool = True):
        n = graph.n
        if isinstance(agent_id, bool) or not isinstance(agent_id, (int, np.integer)) \
                or not 1 <= agent_id <= n:
            raise Se3SyncError(f"agent_link: agent id must be 1..{n}, got {agent_id!r}")
        if len(network.endpoints) != n:
            raise Se3SyncError(f"agent_link: [network] has {len(network.endpoints)} endpoints for "
                               f"{n} agents")
        h_us = round(float(step) * 1e6) if math.isfinite(float(step)) else 0
        if h_us < 1:
            raise Se3SyncError(f"agent_link: step must be ≥ 1 µs, got {step!r}")
        if world not in frames.WORLD_FRAMES:
            raise Se3SyncError(f"agent_link: world frame must be one of {frames.WORLD_FRAMES}, "
                               f"got {world!r}")
        self.id = int(agent_id)
        self.graph = graph
        self.world = world
        self.h_us = h_us
        self.drain_budget = int(drain_budget)
        self.clock = clock
        self.neighbours = tuple(graph.neighbours(self.id))
        self.owned = tuple(graph.M_plus(self.id))                       # M_i⁺, ascending
        self._owned_set = frozenset(self.owned)
        self.owned_by = {j: tuple(graph.M_plus(j)) for j in self.neighbours}
        self.addr = {j: _resolve(j, *network.endpoints[j - 1]) for j in self.neighbours}
        # the age rule in steps, rounded as cosim.network rounds it (⌈s/h − 1e-9⌉)
        h = float(step)
        self.max_age_steps = _steps(network.max_age, h) if math.isfinite(network.max_age) else None
        self.hold_steps = _steps(network.hold, h)
        self.restart_steps = _steps(RESTART_S, h)
        self.future_steps = max(FUTURE_MIN_STEPS, _steps(FUTURE_S, h))
        self.poll_budget_s = POLL_BUDGET * h
        self.junk_budget_s = JUNK_BUDGET * h
        self._own_step = 0          # the receiver's own step (`set_step`)
        self._limit = self.future_steps
        self._timeline = None       # (Unix time of step 0, h): real time, the step from the clock
        self._wall = time.time
        # who may send to us: each neighbour's endpoint, and which system it must claim
        self._from = {a: j for j, a in self.addr.items()}
        self._from_port = {a[1]: j for j, a in self.addr.items() if a[0] == "0.0.0.0"}
        host, port = network.endpoints[self.id - 1]
        self.counters = counters if counters is not None else Counters()
        self.peer = Peer(self.id, AGENT_COMPONENT, self.counters, key=key,
                         signing_state=signing_state)
        ep = f"udpin:{host}:{port}"
        try:
            UdpSocket(ep).close()        # free? (the sockets below share it among themselves)
            self.sock = UdpSocket(ep, reuse_port=True)
        except OSError as exc:
            raise Se3SyncError(f"network: agent {self.id}'s endpoint {host}:{port} cannot be "
                               f"bound: {exc.strerror or exc}") from None
        # one more socket per neighbour on the same port, connected to its endpoint: the kernel
        # hands it that neighbour's datagrams and nothing else, so junk from anywhere else
        # (which lands on self.sock) can fill only its own buffer, never delay or crowd out a
        # neighbour's samples. Where the kernel does not prefer connected sockets, the
        # neighbours' datagrams land on self.sock and are taken there as well.
        self._nsock = {}
        try:
            for j, a in self.addr.items():
                if a[0] != "0.0.0.0":
                    s = UdpSocket(ep, reuse_port=True, connect_to=a)
                    # what reached it before its connect (anyone's: `UdpSocket`) and what waits
                    # on the catch-all, in the order it arrived, for `poll_neighbours` to take
                    # before anything newer on the neighbours' sockets
                    self.sock.merge_backlog(s)
                    self._nsock[j] = s
        except OSError as exc:
            self.close()
            raise Se3SyncError(f"network: agent {self.id}'s endpoint {host}:{port} cannot be "
                               f"bound: {exc.strerror or exc}") from None
        self._held: dict = {j: None for j in self.neighbours}
        self._asm: dict = {j: None for j in self.neighbours}
        self._packets = {j: 0 for j in self.neighbours}      # accepted packets per neighbour
        self._samples = {j: 0 for j in self.neighbours}      # complete samples taken
        self._sent = {j: 0 for j in self.neighbours}         # datagrams sent per neighbour
        self._sent_all = 0         # …plus these, sent to every neighbour (`publish_rows`)
        self._published = 0        # samples (steps) published to every neighbour
        self._last_published = -1
        self._restarts = {j: 0 for j in self.neighbours}     # restarts recognised (RESTART_SAMPLES)
        self._back = {j: None for j in self.neighbours}      # (newest far-back step, run length)
        self._rej = {j: Counter() for j in self.neighbours}  # refusals by reason, per neighbour
        self._ages = {j: Counter() for j in self.neighbours}  # ages (steps) of the data used
        self.history = int(history)
        self._hist = {j: {} for j in self.neighbours}          # step -> [S or None, θ chunks]
        self._conflicts = {j: 0 for j in self.neighbours}      # differing copies of a history entry
        self._emu = {}                                          # j -> (d, jmax, jitter, loss, rng)
        self._queue = []                                        # (release step, seq, j, data)
        self._qseq = 0
        self._emu_lost = {j: 0 for j in self.neighbours}
        if emulate:
            streams = np.random.SeedSequence(network.seed).spawn(n * n)
            for j in self.neighbours:
                spec = network.link(self.id, j)
                if spec.delay > 0 or spec.jitter > 0 or spec.loss > 0:
                    rng = np.random.default_rng(streams[(self.id - 1) * n + (j - 1)])
                    self._emu[j] = (_steps(spec.delay, h), _steps(spec.jitter, h), spec.jitter,
                                    spec.loss, rng)
        # the compiled common case: real time (the lockstep history keeps every message: the
        # reference path's), at most one θ chunk per sample; a signature and its replay window
        # stay with `Peer`
        self._scan = None
        self.scanned = 0            # samples the compiled path took
        if compiled and not self.history and self.peer.tlog is None:
            self._scan_nt = {j: len(o) for j, o in self.owned_by.items()
                             if len(o) <= THETA_PER_MESSAGE}
            self._scratch = np.zeros(256, np.uint8)
            self._scan_out = np.zeros(SCAN_WIDTH)
            self._scan_seqs = np.zeros(4, np.int64)
            self._signed = int(key is not None)
            self._scan = self._take_sample
        # …and the neighbours' own sockets read by compiled code too
        # (`sample_wire.drain_samples`): the reads, the checks and the counts of a step's
        # samples in one call (signed: the signatures then checked here, by `Peer`); held
        # samples then live in arrays until asked for (`neighbour`)
        self._drain = None
        if self._scan is not None and world == "ned" \
                and len(self._nsock) == len(self._scan_nt) == len(self.neighbours):
            nb = self.neighbours
            m = len(nb)
            self._dq = {j: q for q, j in enumerate(nb)}
            self._dfds = np.array([self._nsock[j].fileno() for j in nb], np.int64)
            self._dsys = np.array(nb, np.int64)
            self._dnt = np.array([self._scan_nt.get(j, -1) for j in nb], np.int64)
            self._dnt_now = self._dnt.copy()     # −1 while j's sample is in assembly
            self._dbuf = np.zeros(65535, np.uint8)
            self._hstep = np.full(m, -1, np.int64)     # the held sample's step (−1: none)
            self._hrow = np.zeros((m, SCAN_WIDTH))     # …its values (scan_sample's out)
            self._htime = np.zeros(m)                  # …its arrival (clock())
            self._dcount = np.zeros((m, 2), np.int64)  # packets and samples taken compiled
            self._dseen = [0] * m                      # _dcount[q, 1] when last read
            self._dtot = np.zeros(D_WIDTH, np.int64)
            self._dseq = self.peer.sequence_array([(j, AGENT_COMPONENT) for j in nb])
            self._age_hist = np.zeros((m, AGE_BINS), np.int64)   # ages used (`age_rules`)
            self._ages_now = np.zeros(m, np.int64)
            self._drain = self._drain_neighbours
            self.drain_kernel = drain_samples    # (the ahead-of-time module's, in a test)
        # …and its mirror for what this agent sends (`sample_wire.pack_sample`), sent on the
        # neighbours' connected sockets by one compiled call (`bridge.mavlink.udp_io.send_all`)
        self._sfds = None
        if compiled and len(self._nsock) == len(self.neighbours) and self.neighbours:
            self._sfds = np.array([self._nsock[j].fileno() for j in self.neighbours], np.int64)
            self._sok = np.zeros(len(self.neighbours), np.int64)
            self.send_kernel = send_all
        self._pack = None
        if compiled and self.peer.tlog is None and len(self.owned) <= THETA_PER_MESSAGE:
            self._pbuf = np.zeros(PACK_BYTES, np.uint8)
            self._pf32 = np.zeros(THETA_PER_MESSAGE, np.float32)
            self._ends = np.zeros(2, np.int64)
            self._pth = np.zeros(max(1, len(self.owned)))
            self._pnull = np.zeros(layout.S_WIDTH)
            self._pack = self._pack_sample
            self._pst = np.zeros(1, np.int64)
        self._fast_publish = None      # `publish_rows`' choice, made at its first call

    @property
    def drained(self) -> int:
        """Samples the compiled drain took whole (`sample_wire.drain_samples`; of `scanned`)."""
        return 0 if self._drain is None else int(self._dcount[:, 1].sum())

    def warm_up(self) -> None:
        """Loads (or compiles) the compiled sample decoder now, with the argument types of the
        run, rather than at the first neighbour sample of step 0: on a cold cache that took
        about a second while the swarm stepped."""
        if self._sfds is not None:      # to no socket: its types, no send
            none = np.zeros(0, np.int64)
            send_all(none, np.zeros(1, np.uint8), 0, none)
            if self._pack is not None:
                publish_sample(self._pbuf, 0, np.zeros((1, layout.S_WIDTH)), np.zeros(1), none,
                               self._pth, 1, 0, self._pf32, self._ends, none, none,
                               self._pst.copy())
        if self._scan is None or not self._scan_nt:
            return
        nt = next(iter(self._scan_nt.values()))
        junk = bytes(16)
        scan_sample(np.frombuffer(junk, np.uint8), len(junk), self._signed, 1, nt, self.h_us,
                    int(self._limit), self._scratch.copy(), self._scan_out.copy(),
                    self._scan_seqs.copy())
        if self._drain is not None:     # over no socket: its types, no read
            none = np.zeros(0, np.int64)
            age_rules(0, none, 0, 0, 0, none, none, none, np.zeros((0, AGE_BINS), np.int64),
                      np.zeros((0, SCAN_WIDTH)), np.zeros(0), none, none, none)
            drain_samples(0, 0, none, none, none, self.h_us, int(self._limit), self._signed, 1,
                          0.0, self._dbuf, self._scratch.copy(), self._scan_out.copy(),
                          self._scan_seqs.copy(), none, np.zeros((0, SCAN_WIDTH)), np.zeros(0),
                          np.zeros((0, 2), np.int64), none, np.zeros(D_WIDTH, np.int64))

    @classmethod
    def from_scenario(cls, scenario, agent_id: int, **kw) -> "AgentLink":
        """The link of agent ``agent_id`` from a loaded scenario: its ``[network]`` table, graph,
        step and ``bridge.world_frame`` (default "ned")."""
        net = scenario.tables.get("network")
        if net is None:
            raise Se3SyncError(f"{scenario.path}: network: the scenario has no [network] table "
                               "(the agents' endpoints)")
        br = scenario.tables.get("bridge")
        kw.setdefault("world", br.world_frame if br is not None else "ned")
        return cls(agent_id, net, scenario.graph, step=scenario.step, **kw)

    # ------------------------------------------------------------------ out
    def publish(self, n: int, S_row, theta_owned: dict | None) -> int:
        """Sends sample n (own row S_row in scenario frames, {k: θ_k} for every owned edge after
        the jump stage) to every neighbour, one datagram each. Returns the datagrams sent (or
        queued by the emulated delay). ``S_row=None`` sends θ only, ``theta_owned=None`` the pose
        only: lockstep sends the two in turn, since θ after the jump needs the neighbours'
        poses of the same step."""
        if theta_owned is not None and theta_owned.keys() != self._owned_set:
            missing = [k for k in self.owned if k not in theta_owned]
            extra = [k for k in theta_owned if k not in self.owned]
            if missing or extra:
                raise Se3SyncError(f"agent_link: agent {self.id} owns edges {list(self.owned)}; "
                                   f"theta_owned has {sorted(theta_owned)}")
        if n < 0:
            raise Se3SyncError(f"agent_link: sample step must be ≥ 0, got {n}")
        self.release(n)
        got = None if self._pack is None else self._pack(n, S_row, theta_owned)
        if got is not None:
            data, n_msgs = got
        else:
            theta = None if theta_owned is None else [theta_owned[k] for k in self.owned]
            msgs = encode_sample(self.peer.mav, n, self.h_us, S_row, theta, self.world)
            bufs = [self.peer.pack(m) for m in msgs]
            data = b"".join(bytes(b) for b in bufs)
            n_msgs = len(bufs)
        if not n_msgs:
            return 0
        if S_row is not None and n > self._last_published:   # a new sample (not a resend)
            self._last_published = n
            self._published += 1
        if got is not None and self._sfds is not None and not self._emu:
            # the datagram is in _pbuf: one compiled call sends it to every neighbour
            ok = self.send_kernel(self._sfds, self._pbuf, len(data), self._sok)
            c = self.counters
            c.sent += ok * n_msgs
            if ok == len(self.neighbours):
                for j in self.neighbours:
                    self._sent[j] += 1
            else:
                c.send_errors += len(self.neighbours) - ok
                for j, y in zip(self.neighbours, self._sok.tolist()):
                    self._sent[j] += y
            return ok
        ok = 0
        for j in self.neighbours:
            emu = self._emu.get(j)
            if emu is not None:
                d, jmax, jitter, loss, rng = emu
                x = rng.random(2)
                if loss > 0 and x[0] < loss:
                    self._emu_lost[j] += 1
                    continue
                wait = d + (min(jmax, _steps(x[1] * jitter, self.h_us * 1e-6)) if jitter > 0 else 0)
                if wait > 0:
                    self._qseq += 1
                    heapq.heappush(self._queue, (n + wait, self._qseq, j, data, n_msgs))
                    ok += 1
                    continue
            ok += self._send(j, data, n_msgs)
        return ok

    @property
    def publishes_compiled(self) -> bool:
        """An unsigned link in the NED world with compiled sends and no emulated delay: a
        sample is gathered, encoded and sent by one compiled call (`publish_rows`,
        `bridge.swarm.tick.agent_tick`)."""
        fast = self._fast_publish
        if fast is None:
            fast = self._fast_publish = (
                self._pack is not None and self._sfds is not None and not self._emu
                and self.world == "ned" and not self.peer.mav.signing.sign_outgoing)
        return fast

    def publish_rows(self, n: int, S, theta, rows) -> int:
        """`publish` of sample n with the own row S[0] (S: C-ordered rows in scenario frames)
        and θ of owned edge q (`owned` order) at theta[rows[q]]. Where `publishes_compiled`,
        gathering θ, encoding and sending are one compiled call (`sample_wire.publish_sample`:
        the same bytes); otherwise `publish`."""
        if not self.publishes_compiled or n < 0:
            return self.publish(n, S[0], {k: float(theta[r]) for k, r in zip(self.owned, rows)})
        mav = self.peer.mav
        nf = publish_sample(self._pbuf, stamp_us(n, self.h_us), S, theta, rows, self._pth,
                            mav.srcSystem, mav.seq, self._pf32, self._ends, self._sfds,
                            self._sok, self._pst)
        return self.published(n, nf, S, theta, rows)

    def published(self, n: int, nf: int, S, theta, rows) -> int:
        """What `publish_rows` records of sample n that `publish_sample` framed as ``nf``
        frames and sent (its sockets' outcomes in the link's arrays); returns the neighbours
        reached. ``nf`` < 0 (a value beyond float32, nothing sent): the reference path raises
        as struct.pack does."""
        if nf < 0:
            return self.publish(n, S[0], {k: float(theta[r]) for k, r in zip(self.owned, rows)})
        mav = self.peer.mav
        mav.seq = (mav.seq + nf) & 0xFF
        if n > self._last_published:
            self._last_published = n
            self._published += 1
        ok = int(self._pst[0])
        m = len(self.neighbours)
        self.counters.sent += ok * nf
        if ok == m:
            self._sent_all += 1
        else:
            self.counters.send_errors += m - ok
            for j, y in zip(self.neighbours, self._sok.tolist()):
                self._sent[j] += y
        return ok

    def workspace_slots(self) -> list:
        """The link's arrays that `bridge.swarm.tick.Workspace` may move, as (slot, owner,
        attribute) for `TICK_SLOTS`' names: the drain's held samples and ages, the publish's
        buffers. Empty unless the link drains and `publishes_compiled`."""
        if self._drain is None or not self.publishes_compiled:
            return []
        return [(name, self, attr) for name, attr in (
            ("held_step", "_hstep"), ("ages", "_ages_now"), ("hist", "_age_hist"),
            ("held", "_hrow"), ("pbuf", "_pbuf"), ("pth", "_pth"), ("pf32", "_pf32"),
            ("ends", "_ends"), ("sfds", "_sfds"), ("sok", "_sok"), ("pst", "_pst"))]

    @property
    def tick_header(self) -> tuple:
        """(system id, next sequence number) of the samples this link sends."""
        mav = self.peer.mav
        return mav.srcSystem, mav.seq

    def _pack_sample(self, n: int, S_row, theta_owned):
        """`encode_sample` and `Peer.pack` of sample n compiled (`sample_wire.pack_sample`, the
        same bytes): (datagram, messages in it), or None for a value beyond float32, which the
        reference path refuses as `struct.pack` does."""
        nt = 0
        th = self._pth
        if theta_owned is not None:
            for r, k in enumerate(self.owned):
                th[r] = theta_owned[k]
            nt = len(self.owned)
        if S_row is None:
            S = self._pnull
        else:
            S = np.asarray(S_row, float).reshape(layout.S_WIDTH)
            if self.world != "ned":
                S = frames.state_world_to_ned(S.reshape(1, layout.S_WIDTH), self.world)[0]
            S = np.ascontiguousarray(S)
        mav = self.peer.mav
        signed = 1 if mav.signing.sign_outgoing else 0
        buf, ends = self._pbuf, self._ends
        nf = pack_sample(buf, stamp_us(n, self.h_us), S, S_row is not None, th, nt,
                         mav.srcSystem, mav.seq, signed, self._pf32, ends)
        if nf < 0:
            return None
        if nf == 0:
            return b"", 0
        if signed:
            start = 0
            for k in range(nf):
                codec.sign_frame(mav, buf, start, int(ends[k]))
                start = int(ends[k])
        mav.seq = (mav.seq + nf) & 0xFF
        return buf[:ends[nf - 1]].tobytes(), nf

    def _send(self, j: int, data: bytes, n_msgs: int) -> int:
        c = self.counters
        if self.sock.send(data, self.addr[j]):
            c.sent += n_msgs
            self._sent[j] += 1
            return 1
        c.send_errors += 1
        return 0

    def release(self, n: int) -> int:
        """Sends the datagrams the emulated delay holds whose time (step ≤ n) has come."""
        q = self._queue
        sent = 0
        while q and q[0][0] <= n:
            _, _, j, data, n_msgs = heapq.heappop(q)
            sent += self._send(j, data, n_msgs)
        return sent

    # ------------------------------------------------------------------ in
    # ------------------------------------------------------------------ the receiver's step
    def set_step(self, n: int) -> None:
        """The receiver's own step n (lockstep: the step being exchanged; real time: the step
        being computed). Samples stamped after n + `future_steps` are refused as ``future``, and
        the lockstep history keeps steps n − ``history`` … n + `future_steps` only."""
        self._own_step = int(n)

    def set_timeline(self, start: float, clock=time.time) -> None:
        """Real time: step n is due at ``start + n·h`` (Unix time); the receiver's step is then
        at least the wall clock's, so a late process does not refuse its neighbours' newest
        samples (a genuine sample is never stamped ahead of the sender's clock)."""
        self._timeline = (float(start), self.h_us * 1e-6)
        self._wall = clock

    def current_step(self) -> int:
        """The receiver's step: the larger of `set_step`'s and the wall clock's (`set_timeline`)."""
        n = self._own_step
        tl = self._timeline
        if tl is not None:
            w = int(math.floor((self._wall() - tl[0]) / tl[1]))
            if w > n:
                n = w
        return n

    # ------------------------------------------------------------------ in
    def poll(self, limit: int | None = None) -> int:
        """Reads what is pending and takes what is valid: datagrams in batches of ``limit``
        (default the drain budget), from each neighbour's socket until it is empty or
        ``POLL_BUDGET`` of a step has been spent, then from the catch-all socket for at most
        ``JUNK_BUDGET`` of a step (the rest waits for the next poll). Never raises on network
        input. Returns the number of datagrams read."""
        return self.poll_neighbours(limit) + self.poll_catch_all(limit)

    def poll_neighbours(self, limit: int | None = None) -> int:
        """`poll`'s first half: the neighbours' own sockets (never behind junk)."""
        self._limit = self.current_step() + self.future_steps
        lim = self.drain_budget if limit is None else int(limit)
        deadline = time.monotonic() + self.poll_budget_s
        n = self._take_backlogs() if self.sock.backlog else 0
        if self._drain is not None:
            return n + self._drain(lim, deadline)
        for s in self._nsock.values():
            n += receive_datagrams(s, self.counters, self._on_packet, lim, deadline=deadline,
                                   accept_from=self._accept_from, fast=self._scan)
        return n

    def _take_backlogs(self) -> int:
        """What the catch-all holds from before the neighbours' sockets were connected
        (`UdpSocket`), older than anything on them: by the reference path, with each datagram's
        true sender (the drain reads no addresses)."""
        n = 0
        for data, addr in self.sock.take_backlog():
            take_datagram(data, addr, self.counters, self._on_packet, self._accept_from,
                          self._scan)
            n += 1
        if self._drain is not None:
            for j in self.neighbours:
                self._resync(j)
        return n

    def poll_catch_all(self, limit: int | None = None) -> int:
        """`poll`'s second half: the catch-all socket (strangers, junk, and a neighbour's
        datagrams where the kernel does not prefer connected sockets) for at most its budget
        (the rest of a flood waits, then the kernel drops it and `kernel_drops` says how much)."""
        self._limit = self.current_step() + self.future_steps
        lim = self.drain_budget if limit is None else int(limit)
        got = receive_datagrams(self.sock, self.counters, self._on_packet, lim,
                                deadline=time.monotonic() + self.junk_budget_s,
                                accept_from=self._accept_from, fast=self._scan)
        if got and self._drain is not None:
            for j in self.neighbours:   # a neighbour's datagram may have come this way too
                self._resync(j)
        return got

    def readers(self) -> list:
        """[(socket, what reads it)] to wait on (select) and call when it is readable, the
        neighbours' sockets first; `poll` reads them all."""
        return [*((s.fileno(), self.poll_neighbours) for s in self._nsock.values()),
                (self.sock.fileno(), self.poll_catch_all)]

    receive = poll

    def _accept_from(self, addr) -> bool:
        return addr in self._from or addr[1] in self._from_port

    def _take_sample(self, data, addr) -> bool:
        """The compiled common case (`sample_wire`): a neighbour's whole sample, newer than what
        is held, nothing in assembly. Does what `_on_packet` does with its two packets (the
        counts, the sequence numbers, the held sample); False leaves the datagram to it."""
        j = self._from.get(addr)
        if j is None:
            j = self._from_port.get(addr[1])
        nt = self._scan_nt.get(j)
        if nt is None or self._asm[j] is not None:
            return False
        out = self._scan_out
        seqs = self._scan_seqs
        s = scan_sample(np.frombuffer(data, np.uint8), len(data), self._signed, j, nt, self.h_us,
                        self._limit, self._scratch, out, seqs)
        held = self.neighbour(j)
        if s < 0 or (held is not None and s <= held.step):
            return False
        npk = 2 if nt else 1
        if self._signed:
            if not self.peer.take_signed(data, seqs[2:2 + npk].tolist(), j, AGENT_COMPONENT):
                return False
        else:
            self.peer.took(j, AGENT_COMPONENT, seqs[:npk].tolist())
        self._packets[j] += npk
        self._back[j] = None
        self._hold(j, self._sample_of(j, s, out, self.clock()))
        self._samples[j] += 1
        self.scanned += 1
        return True

    def _sample_of(self, j: int, s: int, out, t: float) -> NeighbourSample:
        """The held sample of `scan_sample`'s ``out`` (sample s of j)."""
        if self.world == "ned":     # the compiled decoder's row: wire_row_to_state's bits
            S = out[SCAN_STATE:SCAN_STATE + layout.S_WIDTH].copy()
        else:
            S = np.array(wire_row_to_state(out[:13].tolist(), self.world))
        nt = len(self.owned_by[j])
        return NeighbourSample(s, S, S[layout.XI].copy(),
                               dict(zip(self.owned_by[j], out[13:13 + nt].tolist())), t)

    def _hold(self, j: int, sample: NeighbourSample | None) -> None:
        """j's held sample is now ``sample`` (the compiled drain's arrays follow)."""
        self._held[j] = sample
        if self._drain is not None:
            q = self._dq[j]
            self._dseen[q] = int(self._dcount[q, 1])
            if sample is None:
                self._hstep[q] = -1
                return
            self._hstep[q] = sample.step
            row = self._hrow[q]
            row[SCAN_STATE:SCAN_STATE + layout.S_WIDTH] = sample.S
            for i, k in enumerate(self.owned_by[j]):
                row[13 + i] = sample.theta[k]

    def _drain_neighbours(self, lim: int, deadline: float) -> int:
        """The neighbours' sockets read by `drain_samples`, each datagram it does not take
        handed to the reference path in its turn; returns the datagrams read."""
        tot = self._dtot
        c = self.counters
        n = 0
        q = k = 0
        now = self.clock()
        while True:
            r = self.drain_kernel(q, k, self._dfds, self._dsys, self._dnt_now, self.h_us,
                                  self._limit, self._signed, lim, now, self._dbuf,
                                  self._scratch, self._scan_out, self._scan_seqs, self._hstep,
                                  self._hrow, self._htime, self._dcount, self._dseq, tot)
            if r < 0:
                break
            q, kind = divmod(r, 3)
            if kind == 1:       # a full batch: on while the poll's time lasts
                k = 0
                if time.monotonic() >= deadline:
                    c.drain_capped += 1
                    q += 1
                continue
            k = int(tot[D_K])
            j = self.neighbours[q]
            n += 1
            data = self._dbuf[:tot[D_LEN]].tobytes()
            if kind == 2:       # signed, whole and newer: taken if its signatures are
                npk = 2 if self._dnt[q] > 0 else 1
                if self.peer.take_signed(data, self._scan_seqs[2:2 + npk].tolist(), j,
                                         AGENT_COMPONENT):
                    self._hstep[q] = tot[D_STEP]
                    self._hrow[q] = self._scan_out
                    self._htime[q] = now
                    self._dcount[q] += (npk, 1)
                    c.datagrams += 1
                    self.scanned += 1
                    continue
            take_datagram(data, self.addr[j], c, self._on_packet)
            self._resync(j)
        d = tot.tolist()
        tot[:] = 0
        c.datagrams += d[D_DATAGRAMS]
        c.received += d[D_RECEIVED]
        c.dropped += d[D_DROPPED]
        if d[D_BATCH] > c.drain_max:
            c.drain_max = d[D_BATCH]
        self.scanned += d[D_DATAGRAMS]
        return n + d[D_DATAGRAMS]

    def _resync(self, j: int) -> None:
        """After the reference path took (or refused) a datagram of j: the drain's view of j."""
        q = self._dq[j]
        held = self.neighbour(j)
        self._hstep[q] = -1 if held is None else held.step
        self._dnt_now[q] = -1 if self._asm[j] is not None else self._dnt[q]

    def _on_packet(self, pkt, addr) -> None:
        c = self.counters
        _, sysid, compid, _, _ = packet_ids(pkt)
        j = self._from.get(addr)
        if j is None:
            j = self._from_port.get(addr[1])
        if sysid != j or compid != AGENT_COMPONENT:
            c.reject("not_neighbour")
            return
        c.scope = self._rej[j]
        try:
            got = self.peer.accept_fields(pkt, _TYPES)
            if got is None:
                return
            m0 = c.mark()
            mid, f = got
            if mid == ID_ODOMETRY:
                ok = self._on_odometry(j, f)
            else:
                ok = self._on_theta(j, f)
            if ok:
                self.peer.commit()
                self._packets[j] += 1
            elif c.arrived_since(m0):
                self.peer.commit()      # a resent or overtaken sample's: it came, no loss
        finally:
            c.scope = None

    def _step_of(self, t_us) -> int | None:
        t_us = int(t_us)
        if t_us < 0 or t_us % self.h_us:
            self.counters.reject("bad_stamp")
            return None
        s = t_us // self.h_us
        if s > self._limit:
            # the limit is the poll's; the clock may have moved on since (a process descheduled
            # in the middle of a poll): look again before refusing
            self._limit = self.current_step() + self.future_steps
            if s > self._limit:
                self.counters.reject("future")
                return None
        return s

    def _assembly(self, j: int, s: int):
        """The assembly for sample s of j, or None (counted) when s is not newer than what is held
        or being assembled. Stamps more than `RESTART_S` of sample time older than that, in a run
        of `RESTART_SAMPLES` distinct increasing steps with nothing newer between them, are j
        restarting on another timeline: the last one is taken, counted in ``restarts``."""
        c = self.counters
        held = self.neighbour(j)      # (first: it settles what the compiled drain took)
        a = self._asm[j]
        if a is not None and a.step == s:
            return a
        steps = [x.step for x in (held, a) if x is not None]
        newest = max(steps) if steps else None
        if newest is not None and s <= newest:
            if newest - s <= self.restart_steps:
                c.reject("duplicate" if held is not None and s == held.step else "out_of_order")
                return None
            back = self._back[j]
            if back is None or s < back[0]:
                run = 1
            else:   # the same sample's other message keeps the run, a newer one extends it
                run = back[1] + (s > back[0])
            self._back[j] = (s, run)
            if run < RESTART_SAMPLES:
                c.reject("out_of_order")
                return None
            self._restarts[j] += 1
            self._hold(j, None)
        self._back[j] = None
        if a is not None:
            c.reject("incomplete")   # a newer sample starts before the older one was complete
        a = self._asm[j] = _Assembly(s)
        return a

    def _remember(self, j: int, s: int, what, value) -> None:
        """Lockstep history: the pose (what = None) or θ chunk c of neighbour j's step s."""
        if not self.history:
            return
        h = self._hist[j]
        e = h.get(s)
        if e is None:
            # the window is the receiver's own step's (`set_step`), never the newest stamp seen:
            # _step_of has refused anything after n + future_steps, and older than n − history
            # is of no use to a lockstep step
            lo = self._own_step - self.history
            if s < lo:
                return
            e = h[s] = [None, {}]
            for old in [x for x in h if x < lo]:
                del h[old]
        # the first of a step's pose (θ chunk) is kept: a later copy (a resend, or a forgery
        # arriving after the genuine message) never replaces what a lockstep step may have used;
        # a copy that differs from it (a forgery, or a sender that changed its mind) is counted
        # (``conflicts``): two versions of one step's data
        if what is None:
            if e[0] is None:
                e[0] = value
            elif not np.array_equal(e[0], value):
                self._conflicts[j] += 1
        elif what not in e[1]:
            e[1][what] = value
        elif e[1][what] != value:
            self._conflicts[j] += 1

    def pose_at(self, j: int, n: int):
        """Neighbour j's row S_j of step n (scenario frames, float32-rounded values) if its pose
        message has arrived (needs ``history``), else None."""
        e = self._hist[j].get(n)
        if e is None or e[0] is None:
            return None
        return np.array(wire_row_to_state(e[0], self.world))   # = wire_to_state's row (float32 values)

    def theta_at(self, j: int, n: int):
        """{k: θ_k} of the edges neighbour j owns, as j published them for step n ({} if j owns
        none), or None while a θ chunk of step n is missing (needs ``history``)."""
        owned = self.owned_by[j]
        if not owned:
            return {}
        e = self._hist[j].get(n)
        if e is None or len(e[1]) < -(-len(owned) // THETA_PER_MESSAGE):
            return None
        vals = [v for c in sorted(e[1]) for v in e[1][c]]
        return {k: float(v) for k, v in zip(owned, vals)}

    def _on_odometry(self, j: int, f: tuple) -> bool:
        """f: ODOMETRY's fields in wire order (`_ODO`)."""
        c = self.counters
        if f[_ODO_FRAME] != mavlink2.MAV_FRAME_LOCAL_NED \
                or f[_ODO_FRAME + 1] != mavlink2.MAV_FRAME_BODY_FRD:
            c.reject("bad_frame")
            return False
        # the wire row: x y z, q (w x y z), body rates, body velocity
        vals = [*f[1:8], *f[11:14], *f[8:11]]
        if not _finite(vals):
            c.reject("nan")
            return False
        q = vals[3:7]
        if abs(math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]) - 1.0) > QUAT_TOL:
            c.reject("non_unit_quaternion")
            return False
        s = self._step_of(f[0])
        if s is None:
            return False
        wire = vals    # float32 values (struct-unpacked): f32 leaves them as they are
        self._remember(j, s, None, wire)
        a = self._assembly(j, s)
        if a is None:
            return False
        if a.wire is not None:
            c.reject("duplicate")
            return False
        a.wire = wire
        self._complete(j, a)
        return True

    def _on_theta(self, j: int, f: tuple) -> bool:
        """f: DEBUG_FLOAT_ARRAY's fields in wire order (time_usec, array_id, name, data[58])."""
        c = self.counters
        owned = self.owned_by[j]
        n_chunks = -(-len(owned) // THETA_PER_MESSAGE)
        name = f[2].split(b"\0", 1)[0].decode("ascii", "replace")
        chunk = _CHUNK_OF.get(name)
        if chunk is None or chunk >= n_chunks or f[1] != j:
            c.reject("bad_theta")
            return False
        count = min(THETA_PER_MESSAGE, len(owned) - THETA_PER_MESSAGE * chunk)
        vals = list(f[3:3 + count])
        if len(vals) != count or not _finite(vals):
            c.reject("nan")
            return False
        s = self._step_of(f[0])
        if s is None:
            return False
        self._remember(j, s, chunk, vals)
        a = self._assembly(j, s)
        if a is None:
            return False
        if chunk in a.chunks:
            c.reject("duplicate")
            return False
        a.chunks[chunk] = vals
        self._complete(j, a)
        return True

    def _complete(self, j: int, a: _Assembly) -> None:
        owned = self.owned_by[j]
        if a.wire is None or len(a.chunks) < -(-len(owned) // THETA_PER_MESSAGE):
            return
        # one row in plain floats (`wire_row_to_state`: wire_to_state's bits); the wire values
        # are float32 values already (f32 is the identity on them)
        S = np.array(wire_row_to_state(a.wire, self.world))
        theta_vals = [v for i in sorted(a.chunks) for v in a.chunks[i]]
        self._hold(j, NeighbourSample(a.step, S, S[layout.XI].copy(),
                                      {k: float(v) for k, v in zip(owned, theta_vals)},
                                      self.clock()))
        self._asm[j] = None
        self._samples[j] += 1

    # ------------------------------------------------------------------ queries
    def neighbour(self, j: int) -> NeighbourSample | None:
        """The newest complete sample of neighbour j (None before the first one)."""
        if j not in self._held:
            raise Se3SyncError(f"agent_link: agent {j} is not a neighbour of agent {self.id} "
                               f"(neighbours: {list(self.neighbours)})")
        if self._drain is not None:
            q = self._dq[j]
            taken = int(self._dcount[q, 1])
            if taken != self._dseen[q]:     # the compiled drain took a newer one since
                self._dseen[q] = taken
                self._back[j] = None
                self._held[j] = self._sample_of(j, int(self._hstep[q]), self._hrow[q],
                                                float(self._htime[q]))
        return self._held[j]

    def held_step(self, j: int) -> int | None:
        """The step of j's newest complete sample (None before the first one), without building
        the sample (`neighbour`)."""
        if self._drain is not None:
            q = self._dq.get(j)
            if q is not None:
                s = int(self._hstep[q])
                return None if s < 0 else s
        held = self.neighbour(j)
        return None if held is None else held.step

    @property
    def held_values(self):
        """The held samples as one array, or None where the link keeps them as objects only
        (no compiled drain): row q is neighbour q's (`neighbours` order) newest sample while
        its `held_step` is not None, θ of the edges it owns (ascending) at [13:13 + count] and
        its state row S_j at [SCAN_STATE:SCAN_STATE + 18]. It changes as samples arrive."""
        return None if self._drain is None else self._hrow

    @property
    def held_steps(self):
        """`held_step` of every neighbour (`neighbours` order; −1: none yet) as the array the
        compiled drain keeps, or None where there is none (`held_values`)."""
        return None if self._drain is None else self._hstep

    def age_rules(self, n: int, verdict, mode, rx, rx_index) -> np.ndarray:
        """`age_rule` of every neighbour at step n in one compiled call (`held_values` links):
        verdict[q] the index of its verdict in `VERDICTS`, mode[q] `agent_step`'s mode, and the
        held θ copied into rx (rx_index: arrays (q, r, column): rx[r] = held_values[q, column]).
        Returns the ages (where `held_steps` is not −1), valid until the next call."""
        ages = self._ages_now
        q_, r_, c_ = rx_index
        if age_rules(n, self._hstep, -1 if self.max_age_steps is None else self.max_age_steps,
                     self.hold_steps, self.future_steps, ages, verdict, mode, self._age_hist,
                     self._hrow, rx, q_, r_, c_):
            self.finish_age_rules(n, verdict, mode)
        return ages

    @property
    def ages_now(self) -> np.ndarray:
        """The ages the last `age_rules` found (where `held_steps` is not −1)."""
        return self._ages_now

    def finish_age_rules(self, n: int, verdict, mode) -> np.ndarray:
        """What `age_rules` leaves to Python when its kernel says so: the ages past its
        histogram and the samples stamped too far ahead, recorded and judged here."""
        ages = self._ages_now
        for q, j in enumerate(self.neighbours):
            s, age = int(self._hstep[q]), int(ages[q])
            if s >= 0 and (max(age, 0) >= AGE_BINS - 1 or age < -self.future_steps):
                self._ages[j][max(age, 0)] += 1
                v = VERDICTS.index(self._verdict(s, n))
                verdict[q] = v
                mode[q] = FRESH if v == 0 else FRESH + 1
        return ages

    def _age_counts(self, j: int) -> Counter:
        """The ages recorded for j: `age_steps`' and `age_rules`'."""
        if self._drain is None:
            return self._ages[j]
        row = self._age_hist[self._dq[j]]
        out = Counter({int(a): int(row[a]) for a in np.flatnonzero(row)})
        out.update(self._ages[j])
        return out

    def age_rule(self, j: int, n: int) -> tuple:
        """(`held_step`, `age_steps`, `freshness`) of j at step n, the age recorded: what a
        control step asks of each neighbour, in one call."""
        s = self.held_step(j)
        age = None
        if s is not None:
            age = int(n) - s
            self._ages[j][max(age, 0)] += 1
        return s, age, self._verdict(s, n)

    def age_steps(self, j: int, n: int, record: bool = True) -> int | None:
        """n − (step of j's newest sample), or None before the first one. With ``record`` the age
        counts as "used at step n" in the link's age percentiles (call it once per control step)."""
        s = self.held_step(j)
        if s is None:
            return None
        age = int(n) - s
        if record:
            self._ages[j][max(age, 0)] += 1
        return age

    def freshness(self, j: int, n: int) -> str:
        """The age rule of ``[network]`` for neighbour j at step n: "fresh" (age ≤ max_age: use
        the data), "hold" (up to ``hold`` more: hold the edge's term, freeze an owned θ_k) or
        "failsafe" (older still: zero wrench until fresh data arrives, then rejoin). Before the
        first sample the age counts from step 0, as if the sender's S0 and θ(0) had arrived then
        (the delay contract of `cosim.network`). Does not record the age."""
        return self._verdict(self.held_step(j), n)

    def _verdict(self, held: int | None, n: int) -> str:
        """`freshness` of a neighbour whose newest sample is of step ``held``."""
        age = int(n) - (0 if held is None else held)
        if held is not None and age < -self.future_steps \
                and held - self.current_step() > self.future_steps:
            # from the future even for the wall clock: never data to steer by (the receive path
            # refuses such stamps; this holds whatever moved the receiver's step back)
            return "failsafe"
        if self.max_age_steps is None or age <= self.max_age_steps:
            return "fresh"
        return "hold" if age <= self.max_age_steps + self.hold_steps else "failsafe"

    def stats(self) -> dict:
        """Counters (JSON-friendly): the link counters of `bridge.mavlink.link.Counters` plus, per
        neighbour, datagrams sent, samples published to it (one per step, resends and the
        emulated losses included), packets and complete samples accepted from it, the newest
        step held and the nearest-rank p50/p99 of the recorded ages (steps)."""
        out = self.counters.as_dict()
        # dropped by the kernel: on the catch-all socket (junk, strangers), and per neighbour
        out["kernel_drops"] = self.sock.kernel_drops()
        out["future_steps"] = self.future_steps
        out["conflicts"] = sum(self._conflicts.values())
        out["agent"] = self.id
        out["neighbours"] = list(self.neighbours)
        links = {}
        for j in self.neighbours:
            held = self.neighbour(j)
            fast = (0, 0) if self._drain is None else self._dcount[self._dq[j]].tolist()
            ages = self._age_counts(j)
            links[str(j)] = {"sent": self._sent[j] + self._sent_all, "published": self._published,
                             "received": self._packets[j] + fast[0],
                             "samples": self._samples[j] + fast[1],
                             "restarts": self._restarts[j],
                             "conflicts": self._conflicts[j],
                             "last_step": None if held is None else held.step,
                             "age_p50_steps": _nearest_rank(ages, 50),
                             "age_p99_steps": _nearest_rank(ages, 99),
                             "rejected": int(sum(self._rej[j].values())),
                             "kernel_drops": self._nsock[j].kernel_drops() if j in self._nsock
                             else None,
                             "rejected_by_reason": dict(sorted(self._rej[j].items())),
                             **({"emulated_lost": self._emu_lost[j]} if j in self._emu else {})}
        out["links"] = links
        return out

    def close(self) -> None:
        for s in getattr(self, "_nsock", {}).values():
            s.close()
        self.sock.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
