"""One agent of the swarm in its own process (`se3sync agent`): the paper's law for agent i only,
on its own vehicle and on what its graph neighbours send it, driven by cosim's one master loop.

Agent i knows what `ex_controller` lets it know: its own state (from its vehicle, over MAVLink as
`se3sync connect` reads a vehicle), and from each neighbour j the samples j publishes over the
inter-agent link (`bridge.swarm.agent_link`: X_j, ξ_j and θ_k of the edges j owns). `AgentNode` holds the
three parts (a one-vehicle `MavlinkPlant`, an `AgentLink`, a `controller.AgentStepper`) and shows
them to `cosim.master.Master` as a plant and a controller of agent i's neighbourhood: the
scenario restricted to i and its neighbours (`cosim.scenario.restrict`), whose row 0 is the
vehicle and whose other rows are the neighbours as received. The master's log and summary are
then those of the neighbourhood, in the swarm's numbers.

Timeline. Step n of the swarm is due at ``start + n·h`` (wall clock, ``--start``, Unix time);
samples are stamped with n, so ages are counted in steps. An agent that starts late (or is
restarted) joins at the next whole sample period (``first_step``), after it has heard from
every neighbour. Lockstep has no clock: step n happens when the data of step n are there.

Per step n (real time):
    1. own row S_i(n) from the vehicle; each neighbour's newest sample and its age a = n − s;
    2. the age rule of ``[network]`` per neighbour: fresh (a ≤ max_age), hold (the edge's term
       and an owned θ_k are held), fail-safe (zero wrench) past max_age + hold;
    3. jumps of the owned edges on fresh data, then the sample (S_i(n), θ after the jump) goes to
       every neighbour in one datagram;
    4. u_i = −k_ξ ξ_i + Σ_k term_k (ascending k), sent to the vehicle; owned θ_k flow.
Lockstep splits 3 in two rounds, since θ after the jump needs the neighbours' poses of step n:
the pose goes out and every neighbour's pose of step n is awaited, then the jumps, then θ goes
out and every neighbour's θ of step n is awaited. That is the network step exactly, so a lockstep
swarm equals `se3sync run` on the float32 reference plant (`bridge.mavlink.transport.QuantizedPlant`).
"""
from __future__ import annotations

import dataclasses
import gc
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

from controller import AgentStepper, JumpEvent, LawParameters, layout
from controller.errors import Se3SyncError
from controller.kernels import FRESH, agent_step, metrics, network_U, relative_pose
from cosim import signals
from cosim.controllers import EdgeState, agent_view
from cosim.log.writer import McapLogger
from cosim.master import Master
from cosim.network import parse_network
from cosim.registry import LAWS
from cosim.run import finish_summary
from cosim.scenario import restrict
from cosim.threads import AGENT_THREADS, limit_process

from .agent_link import VERDICTS, AgentLink
from .sample_wire import held_rows
from .tick import T_AGAIN, T_CHANGED, T_FAILSAFE, T_HOLD, TICK_SLOTS, Workspace, agent_tick
from bridge.mavlink.config import check_endpoint, default_config, read_key_file
from bridge.mavlink.link import require_key_or_insecure
from bridge.live import feed_logger
from bridge.mavlink.plant import LinkError, MavlinkPlant

__all__ = ["AgentNode", "DEFAULT_MAX_AGE_STEPS", "LAWS", "join_step"]

# Without a max_age in [network], an agent process still never runs on data of unbounded age: the
# co-simulation's default (inf) is for studies; a vehicle's controller holds after this many steps.
DEFAULT_MAX_AGE_STEPS = 10
HOSTED_LEAD_S = 0.05     # a hosted agent hands its first step to the stepping thread this early
RESEND_S = 0.02          # lockstep: a step's messages go out again after this long without progress
# without --start (an agent run on its own, not by `swarm`): step 0 this long after the agent is
# ready, time to service its links once before the first deadline
LONE_START_S = 0.2


def join_step(start: float, now: float, h: float, period: int, lead: float = 0.5) -> int:
    """The first step an agent takes part in: 0 if it is there before the start (with ``lead``
    seconds to spare), else the first multiple of ``period`` steps at least ``lead`` ahead (so
    that its log and summary ticks fall on the swarm's)."""
    ahead = now + lead - start
    if ahead <= 0:
        return 0
    n = int(math.ceil(ahead / h))
    return -(-n // period) * period


class _NeighbourhoodPlant:
    """The cosim Plant face: the neighbourhood's state (row 0: the vehicle; rows 1..: the
    neighbours as received), the wrench of row 0 to the vehicle."""

    def __init__(self, node: "AgentNode"):
        self.node = node
        self.n = len(node.agents)
        self.max_block = node.vehicle.max_block
        # read() and advance(h), called at every step: the node's and the vehicle's own, one
        # call each rather than two
        self.read = node._read
        self.advance = node.vehicle.advance

    def apply(self, u) -> None:
        self.node.vehicle.apply(np.asarray(u)[0:1])

    def stats(self) -> dict:
        return self.node.stats()

    def close(self) -> None:
        pass


class _AgentLaw:
    """The cosim Controller face: agent i's wrench (row 0) and θ of its edges (the owned ones as
    it runs them, the others as received)."""

    def __init__(self, node: "AgentNode"):
        self.node = node
        self.name = node.law
        self.hybrid = node.stepper.hybrid
        M = len(node.edge_ids)
        self.theta = node.local.theta0.copy() if self.hybrid else np.zeros(M)
        self.theta_jump = self.theta.copy()
        self.theta_prev = self.theta.copy()
        self.mu = np.full(M, np.nan)
        self.jumped = np.zeros(M, dtype=bool)
        self.u = np.zeros((len(node.agents), 6))
        self._step = node._step_compiled if node.compiled else node._step
        if node.compiled:       # the master calls it at every step: one call rather than two
            self.step_state = node._step_compiled

    @property
    def edge_state(self) -> EdgeState:
        """θ of the neighbourhood's edges, as the master logs them."""
        return EdgeState(self.theta, self.theta_prev, self.theta_jump, self.mu, self.jumped)

    def step_state(self, S, h: float):
        return self._step(S, float(h))

    def reset(self, theta0=None) -> None:
        raise Se3SyncError("an agent process cannot restart its run (start a new process)")


class AgentNode:
    """Agent ``agent_id`` of ``scenario`` (see the module docstring).

    ``AgentNode(scenario, i, law="hybrid", lockstep=False, key_file=None, insecure=False,
    vehicle=None, connect_timeout=None, signing_state=None, tlog=None, on_event=None,
    compiled=True, stop=None)``; then ``connect()``, then drive ``plant`` and ``controller`` with
    `cosim.master.Master` (``run`` does it all), then ``close()``. ``vehicle`` overrides the
    vehicle's bridge-side endpoint (default: vehicle i of the scenario's ``[bridge]`` table).

    ``stop``: a `threading.Event` that stops the agent as a signal would (`bridge.swarm.host`:
    another agent of the same process failed).

    ``compiled``: the law's arithmetic of a step in one compiled call over preallocated arrays
    (`controller.kernels.agent_step`; two in lockstep, θ's publish between them), with the same
    kernels as the reference, and the neighbours' samples decoded by compiled code
    (`bridge.swarm.sample_wire`, real time), the vehicle's state read and its command sent by
    compiled code (`bridge.mavlink.state_wire`); ``compiled=False``: the reference, `AgentStepper`'s
    calls per edge on dicts (`_step`) and the link's Python receive path. A law whose per-agent
    view is not `AgentStepper` (``decoupled``) always runs the reference step (``self.compiled``
    says which runs).
    """

    def __init__(self, scenario, agent_id: int, *, law: str = "hybrid", lockstep: bool = False,
                 key_file=None, insecure: bool = False, vehicle: str | None = None,
                 connect_timeout: float | None = None, signing_state=None, tlog=None,
                 on_event=None, compiled: bool = True, stop=None):
        sc = scenario
        N = sc.graph.n
        if isinstance(agent_id, bool) or not isinstance(agent_id, (int, np.integer)) \
                or not 1 <= agent_id <= N:
            raise Se3SyncError(f"--id: must be an agent number in 1..{N}, got {agent_id!r}")
        if law not in LAWS:
            raise Se3SyncError(f"--controller: must be one of {', '.join(LAWS)}, got {law!r}")
        self.stepper = agent_view(law, sc, int(agent_id))   # or: what the law lacks, one line
        self.sc = sc
        self.i = i = int(agent_id)
        self.law = law
        self.lockstep = bool(lockstep)
        self.stop = stop   # threading.Event of the process hosting several agents, or None
        self.h = h = float(sc.step)
        self.on_event = on_event or (lambda s: print(f"se3sync agent {i}: {s}", file=sys.stderr,
                                                     flush=True))
        self.neighbours = tuple(sc.graph.neighbours(i))
        self.agents = (i, *self.neighbours)
        self.row = {j: r for r, j in enumerate(self.agents)}
        self.local, self.edge_ids = restrict(sc, self.agents)
        self.ends = {k: sc.graph.edge_list[k - 1] for k in self.edge_ids}
        self.other = {k: (b if a == i else a) for k, (a, b) in self.ends.items()}
        self.owned = tuple(k for k in self.edge_ids if self.ends[k][0] == i)

        net = sc.tables.get("network") or parse_network({}, N)
        if not math.isfinite(net.max_age):
            net = dataclasses.replace(net, max_age=DEFAULT_MAX_AGE_STEPS * h)
        if self.lockstep:
            lossy = [(f"network.{k}", v) for k, v in (("delay", net.default.delay),
                                                      ("jitter", net.default.jitter),
                                                      ("loss", net.default.loss)) if v]
            lossy += [(f"network.link ({a} → {b})", "delay, jitter or loss")
                      for (a, b), s in net.links.items() if s.delay or s.jitter or s.loss]
            if lossy:
                raise Se3SyncError(f"{sc.path}: {lossy[0][0]}: lockstep exchanges every step's "
                                   f"data exactly; an emulated delay, jitter or loss "
                                   f"({lossy[0][1]}) contradicts it")
        self.net = net
        key = read_key_file(key_file) if key_file is not None else None
        cfg = sc.bridge or default_config(N)
        vs = cfg.vehicles[i - 1]
        if vehicle is not None:
            vs = dataclasses.replace(vs, endpoint=check_endpoint("--vehicle", vehicle))
        cfg = dataclasses.replace(cfg, n_agents=1, vehicles=[vs], tlog=None)
        host, port = net.endpoints[i - 1]
        require_key_or_insecure([f"udpin:{host}:{port}"], key, insecure,
                                "feed this agent false neighbour states")
        if key_file is not None and signing_state is None:
            signing_state = f"{key_file}.agent{i}.signing.json"
        one, _ = restrict(sc, [i])
        self.vehicle = MavlinkPlant(one, cfg, lockstep=self.lockstep, key=key, tlog=tlog,
                                    connect_timeout=connect_timeout, on_event=self.on_event,
                                    insecure=insecure, signing_state=signing_state)
        # the vehicle's link too: the state read and decoded, the command framed and sent, by
        # compiled code or (``compiled=False``) by the reference paths
        self.vehicle.compiled_state = self.vehicle.compiled_command = bool(compiled)
        try:
            self.link = AgentLink(i, net, sc.graph, step=h, key=key,
                                  world=cfg.world_frame, signing_state=self.vehicle.signing,
                                  history=4 if self.lockstep else 0,
                                  emulate=not self.lockstep, compiled=bool(compiled))
        except BaseException:
            self.vehicle.close()
            raise
        for fd, read in self.link.readers():
            self.vehicle.add_reader(fd, read)
        self.vehicle.drain_per_step = True
        self.lockstep_timeout = float(cfg.lockstep_timeout)
        design = sc.design if self.stepper.hybrid else None
        self.params = LawParameters.of(sc.weighting, design, sc.gains)   # the metrics' U
        self.first_step = 0
        self.n_steps = None
        self._S = self.local.S0.copy()
        self._term = {k: np.zeros(6) for k in self.edge_ids}
        self._relbuf = {k: (np.zeros((3, 3)), np.zeros(3)) for k in self.edge_ids}
        self._state = {j: "fresh" for j in self.neighbours}   # the age rule's last verdict
        self._theta_rx = {k: float(sc.theta0[k - 1]) if design is not None else 0.0
                          for k in self.edge_ids if k not in self.owned}
        self.failsafe = False
        self.failsafe_steps = 0
        self.failsafe_entries = 0
        self.hold_steps = 0
        self.transitions: list = []        # (step, neighbour, new verdict of the age rule)
        self.used = {j: (None, None) for j in self.neighbours}   # (sample step, age)
        self._last_verdict = np.zeros(len(self.neighbours), np.int64)   # (`VERDICTS` indices)
        self.own_samples: list = []
        self.compiled = bool(compiled) and type(self.stepper) is AgentStepper
        self._held_values = None
        self._ws = None
        if self.compiled:
            self._tables()
        self.plant = _NeighbourhoodPlant(self)
        self.controller = _AgentLaw(self)
        if self.compiled:
            th = self.controller.theta
            # the owned θ live in the controller's θ from now on (the stepper's stay at θ(0))
            for k, r in self._own_rows:
                th[r] = self.stepper.theta[k]
            self._ws = self._workspace()
            self._calls = self._agent_step_calls(self._S, self.h)
        self.sample_every = None
        self._closed = False

    def _tables(self) -> None:
        """The compiled step's index tables and buffers (rows r of the edges in ascending k)."""
        E = len(self.edge_ids)
        nb = {j: q for q, j in enumerate(self.neighbours)}
        self._ea = np.array([self.row[self.ends[k][0]] for k in self.edge_ids], dtype=np.int64)
        self._eb = np.array([self.row[self.ends[k][1]] for k in self.edge_ids], dtype=np.int64)
        self._owned_mask = np.array([k in self.owned for k in self.edge_ids], dtype=np.bool_)
        self._nbr = np.array([nb[self.other[k]] for k in self.edge_ids], dtype=np.int64)
        self._mode = np.zeros(len(self.neighbours), dtype=np.int64)   # FRESH, or stale
        self._rx = np.array([self._theta_rx.get(k, 0.0) for k in self.edge_ids])
        self._termbuf = np.zeros((E, 6))
        self._relrows = np.zeros((E, 12))
        self._own_rows = tuple((k, r) for r, k in enumerate(self.edge_ids) if k in self.owned)
        assert tuple(k for k, _ in self._own_rows) == tuple(self.link.owned)   # one order
        self._own_r = np.array([r for _, r in self._own_rows], np.int64)
        # per neighbour q: (j, ((k, r) of the neighbourhood's edges j owns: their θ is received))
        self._rx_rows = tuple((j, tuple((k, r) for r, k in enumerate(self.edge_ids)
                                        if k not in self.owned and self.ends[k][0] == j))
                              for j in self.neighbours)
        self._seen = [None] * len(self.neighbours)   # the sample θ was last taken from
        # …or, where the link holds its samples in arrays (`AgentLink.held_values`), the held θ
        # of neighbour q's edge k (column c of its row) goes to rx[r]: arrays (q, r, c), for
        # `AgentLink.age_rules`
        self._held_values = None if self.lockstep else self.link.held_values
        cols = [(q, r, 13 + self.link.owned_by[j].index(k))
                for q, (j, pairs) in enumerate(self._rx_rows) for k, r in pairs]
        self._rx_q, self._rx_r, self._rx_c = (np.array([c[i] for c in cols], np.int64)
                                              for i in range(3))
        self._rx_index = (self._rx_q, self._rx_r, self._rx_c)
        self._verdict = np.zeros(len(self.neighbours), np.int64)
        self._pub = {k: 0.0 for k in self.owned}     # θ after the jump, as published

    def _workspace(self):
        """The arrays of the step's compiled part moved into one `Workspace` (`agent_tick`:
        one call of 3 arrays rather than three of 36), or None where the step is not that call:
        lockstep, a link that keeps its samples as objects or does not publish compiled."""
        link = self.link
        slots = {name: (name, owner, attr) for name, owner, attr in link.workspace_slots()}
        if self.lockstep or self._held_values is None or not slots or not self.neighbours:
            return None
        ctl = self.controller
        for name, owner, attr in (
                ("verdict", self, "_verdict"), ("mode", self, "_mode"), ("rx", self, "_rx"),
                ("rx_q", self, "_rx_q"), ("rx_r", self, "_rx_r"), ("rx_c", self, "_rx_c"),
                ("last_verdict", self, "_last_verdict"), ("S", self, "_S"),
                ("ea", self, "_ea"), ("eb", self, "_eb"), ("owned", self, "_owned_mask"),
                ("nbr", self, "_nbr"), ("P", None, self.stepper.P), ("theta", ctl, "theta"),
                ("theta_prev", ctl, "theta_prev"), ("theta_jump", ctl, "theta_jump"),
                ("mu", ctl, "mu"), ("jumped", ctl, "jumped"), ("term", self, "_termbuf"),
                ("rel", self, "_relrows"), ("u", ctl, "u"), ("own_r", self, "_own_r"),
                ("out", self, "_tick_out")):
            slots[name] = (name, owner, attr)
        self._tick_out = np.zeros(2, np.int64)
        ws = Workspace(slots[name] for name, _ in TICK_SLOTS)
        self._rx_index = (self._rx_q, self._rx_r, self._rx_c)
        self._held_values = link.held_values
        self._tick_args = (bool(self.stepper.hybrid), self.h,
                           -1 if link.max_age_steps is None else int(link.max_age_steps),
                           int(link.hold_steps), int(link.future_steps), int(link.h_us))
        return ws

    # ------------------------------------------------------------------ set-up
    @property
    def used(self) -> dict:
        """{neighbour: (step of the sample the last step used, None: none yet; its age in
        steps)}. The compiled step keeps it as the link's arrays were at that step (made into
        this dict when asked: the log asks at its records, not at every step)."""
        snap = self._used_at
        if snap is None:
            return self._used
        n, steps, ages = snap
        return {j: (None, n) if s < 0 else (s, a)
                for j, s, a in zip(self.neighbours, steps, ages)}

    @used.setter
    def used(self, d: dict) -> None:
        self._used = d
        self._used_at = None

    @property
    def k(self) -> int:
        """Steps done by this process."""
        return self.vehicle.k

    @property
    def n(self) -> int:
        """The swarm's step number of the current step."""
        return self.first_step + self.vehicle.k

    @property
    def theta_owned(self) -> dict:
        """{k: θ_k} of the owned edges now (after the last step's flow)."""
        if self.compiled:
            th = self.controller.theta
            return {k: float(th[r]) for k, r in self._own_rows}
        return self.stepper.theta_owned

    def connect(self) -> "AgentNode":
        """Waits for the vehicle (HEARTBEAT and a first state; lockstep: the state at t = 0)."""
        self.vehicle.connect()
        return self

    def join(self, start: float | None, sample_every: int, timeout: float = 10.0,
             lead: float = 0.0) -> None:
        """Real time: picks the first step (`join_step`) and paces the vehicle from it; a late
        joiner first waits for a sample from every neighbour (it must not start on S0). Returns
        when the first step is due, or ``lead`` seconds before (a hosted agent: the process's
        stepping thread waits the rest)."""
        self.sample_every = int(sample_every)
        if self.lockstep:
            return
        start_given = start is not None
        if not start_given:   # a lone agent: step 0 shortly after it is ready
            start = time.time() + LONE_START_S
        # the receiver's step follows the wall clock from now on: a neighbour's sample stamped
        # beyond it (+ the link's tolerance) is refused as `future`
        self.link.set_timeline(start)
        if start_given:
            self.first_step = join_step(start, time.time(), self.h, self.sample_every)
        else:
            self.first_step = 0
        if self.first_step > 0:
            # heard by the neighbours meanwhile (its pose now and its θ(0)), so that agents that
            # are all late wait for each other only once
            t_end = time.monotonic() + timeout
            next_pub = 0.0
            while any(self.link.neighbour(j) is None for j in self.neighbours):
                now = time.monotonic()
                if now > t_end:
                    missing = [j for j in self.neighbours if self.link.neighbour(j) is None]
                    raise LinkError(f"joining at step {self.first_step}: no sample from "
                                    f"neighbour(s) {missing} within {timeout:g} s")
                if now >= next_pub:
                    n_now = max(0, int((time.time() - start) / self.h))
                    self.link.publish(n_now, self.vehicle.read()[0], self.theta_owned)
                    next_pub = now + self.h
                self._check_stop()
                self.vehicle.poll(min(0.01, self.h))
            self.first_step = join_step(start, time.time(), self.h, self.sample_every)
        t_first = start + self.first_step * self.h
        mono = time.monotonic() + (t_first - time.time())
        self.vehicle.pace_from(mono)
        while time.monotonic() < mono - lead:   # service both links until step n₀ is due
            self._check_stop()
            self.vehicle.poll(min(0.05, mono - lead - time.monotonic()))
        if self.first_step:
            self.on_event(f"joined the swarm at step {self.first_step} (t = "
                          f"{self.first_step * self.h:g} s)")

    def wait_start(self, path, timeout: float = 300.0) -> float:
        """The swarm's start time from a file (`se3sync swarm` writes it once every agent is
        connected): announces this agent ready (``PATH.ready<i>``), then services both links
        until PATH holds a Unix time."""

        p = Path(path)
        Path(f"{p}.ready{self.i}").write_text(f"{time.time()!r}\n", encoding="utf-8")
        t_end = time.monotonic() + timeout
        while True:
            try:
                return float(p.read_text(encoding="utf-8"))
            except (OSError, ValueError):
                pass
            if time.monotonic() > t_end:
                raise LinkError(f"--start-file: {p} did not appear within {timeout:g} s")
            self._check_stop()
            self.vehicle.poll(0.02)

    def _check_stop(self) -> None:
        if self._stopped():
            raise KeyboardInterrupt

    def _stopped(self) -> bool:
        """A signal arrived, or the process hosting this agent asked it to stop (``stop``)."""
        return signals.requested() or (self.stop is not None and self.stop.is_set())

    # ------------------------------------------------------------------ the step
    def _wait(self, ready, what: str, resend) -> None:
        """Lockstep: services both links until ``ready()`` (re-sending this step's messages
        every RESEND_S); LinkError after the lockstep timeout."""
        t_start = last = time.monotonic()
        while not ready():
            now = time.monotonic()
            if now - t_start > self.lockstep_timeout:
                missing = [j for j in self.neighbours if not ready(j)]
                raise LinkError(f"lockstep: agent {self.i} waited {self.lockstep_timeout:g} s for "
                                f"the {what} of step {self.n} from neighbour(s) {missing}")
            if now - last > RESEND_S:
                resend()
                last = now
            self._check_stop()
            self.vehicle.poll(0.005)

    def _read(self):
        """S of the neighbourhood at step n (row 0 fresh from the vehicle)."""
        S = self._S
        n = self.first_step + self.vehicle.k
        self.link.set_step(n)
        hv = self._held_values
        if hv is not None:       # the link's arrays: row q + 1 is neighbour q's (one call)
            held_rows(S, self.vehicle.read(), self.link.held_steps, hv)
            return S
        own = self.vehicle.read()[0]
        S[0] = own
        if self.lockstep:
            if (self.n_steps is not None and self.k >= self.n_steps) or self._stopped():
                # the end (the master's final read, or a stop was asked for): no step n to
                # exchange, the last data stay
                return S
            pub = lambda: self.link.publish(n, own, None)  # noqa: E731
            pub()

            def ready(j=None):
                js = self.neighbours if j is None else (j,)
                return all(self.link.pose_at(x, n) is not None for x in js)

            self._wait(ready, "pose", lambda: (pub(), self._resend_theta()))
            for j in self.neighbours:
                S[self.row[j]] = self.link.pose_at(j, n)
                self.used[j] = (n, 0)
            return S
        for j in self.neighbours:
            smp = self.link.neighbour(j)
            if smp is not None:
                S[self.row[j]] = smp.S
        return S

    def _resend_theta(self) -> None:
        last = getattr(self, "_last_theta", None)
        if last is not None:
            self.link.publish(last[0], None, last[1])

    def _rel(self, S, k):
        """X̄_k = X_b⁻¹X_a from the neighbourhood's rows, as (R̄, p̄) (the network step's products)."""
        a, b = self.ends[k]
        R, p = self._relbuf[k]
        relative_pose(S, self.row[a], S, self.row[b], R, p)
        return R, p

    def _step(self, S, h: float):
        n = self.n
        st = self.stepper
        ctl = self.controller
        link = self.link
        # 1. the age rule per neighbour (lockstep data are always of this step)
        mode = {}
        for j in self.neighbours:
            if self.lockstep:
                mode[j] = "fresh"
                continue
            age = link.age_steps(j, n)
            smp = link.neighbour(j)
            self.used[j] = (None if smp is None else smp.step, n if age is None else age)
            mode[j] = link.freshness(j, n)
            if mode[j] != self._state[j]:
                self._state[j] = mode[j]
                self.transitions.append((n, j, mode[j]))
                if len(self.transitions) > 1000:
                    del self.transitions[:500]
        fresh_edges = {k for k in self.edge_ids if mode[self.other[k]] == "fresh"}
        rel = {k: self._rel(S, k) for k in fresh_edges}
        # 2. jump stage (owned edges on fresh data)
        for r, k in enumerate(self.edge_ids):
            ctl.theta_prev[r] = ctl.theta[r]
        owned_fresh = [k for k in self.owned if k in fresh_edges]
        events = st.jump(rel, owned_fresh)
        mu = st.last_mu
        jumped = {e.edge for e in events}
        theta_owned = st.theta_owned
        # 3. publish, and (lockstep) the neighbours' θ of this step
        if self.lockstep:
            self._last_theta = (n, theta_owned)
            if self.owned:
                link.publish(n, None, theta_owned)

            def ready(j=None):
                js = self.neighbours if j is None else (j,)
                return all(link.theta_at(x, n) is not None for x in js)

            self._wait(ready, "θ", lambda: (self._resend_theta(),
                                           link.publish(n, S[0], None)))
            for j in self.neighbours:
                self._theta_rx.update(link.theta_at(j, n))
                link.age_steps(j, n)   # 0 in lockstep: counted for the link statistics
        else:
            link.publish(n, S[0], theta_owned)
            for j in self.neighbours:
                smp = link.neighbour(j)
                if smp is not None:
                    self._theta_rx.update({k: v for k, v in smp.theta.items()
                                           if k in self._theta_rx})
        # 4. the wrench: fresh terms computed, stale ones held; fail-safe past max_age + hold
        xi_i = S[0, layout.XI]
        xi = {j: S[self.row[j], layout.XI] for j in self.neighbours}
        self._term.update(st.terms(rel, xi_i, xi, self._theta_rx, fresh_edges))
        fs = any(m == "failsafe" for m in mode.values())
        if fs:
            self.failsafe_steps += 1
            if not self.failsafe:
                self.failsafe_entries += 1
                self.on_event(f"fail-safe at step {n}: no fresh data from neighbour(s) "
                              f"{[j for j in self.neighbours if mode[j] == 'failsafe']}")
        elif self.failsafe:
            self.on_event(f"rejoined at step {n}: fresh data from every neighbour")
        self.failsafe = fs
        if any(m == "hold" for m in mode.values()):
            self.hold_steps += 1
        u = ctl.u
        u[:] = 0.0
        if not fs:
            u[0] = st.wrench_of(xi_i, self._term)
        # θ of the neighbourhood's edges after the jump stage, then the flow of the owned ones
        for r, k in enumerate(self.edge_ids):
            ctl.theta_jump[r] = theta_owned[k] if k in theta_owned else self._theta_rx[k]
            ctl.mu[r] = mu.get(k, np.nan) if k in self.owned else np.nan
            ctl.jumped[r] = k in jumped
        st.flow(rel, h, owned_fresh)
        for r, k in enumerate(self.edge_ids):
            ctl.theta[r] = st.theta[k] if k in st.theta else self._theta_rx[k]
        if self.sample_every and self.k % self.sample_every == 0:
            self.own_samples.append({"step": n, "S": S[0].tolist(),
                                     "theta": {str(k): theta_owned[k] for k in self.owned}})
        if not events:
            return u, ()
        r_of = {k: r for r, k in enumerate(self.edge_ids)}
        return u, tuple(JumpEvent(r_of[e.edge] + 1, e.theta_before, e.theta_after, e.mu)
                        for e in events)

    def _agent_step_calls(self, S, h: float) -> tuple:
        """`agent_step`'s arguments for (stage 1, stage 2, stages 1–2, stages 1–2 in fail-safe)."""
        ctl = self.controller
        head = (S, self._ea, self._eb, self._owned_mask, self._nbr, self._mode,
                self.stepper.hybrid, self.stepper.P, float(h))
        out = (ctl.theta, self._rx, ctl.theta_prev, ctl.theta_jump, ctl.mu, ctl.jumped,
               self._termbuf, self._relrows, ctl.u)
        return tuple((*head, stages, fs, *out) for stages, fs in ((1, False), (2, False),
                                                                  (3, False), (3, True)))

    def _step_compiled(self, S, h: float):
        """`_step` with the law's arithmetic in `agent_step` (same kernels, same numbers): the
        age rule and θ received per neighbour in Python, the rest over the index tables."""
        n = self.n
        ctl = self.controller
        link = self.link
        mode = self._mode
        rx = self._rx
        fs = hold = False
        ticked = False
        if self._held_values is not None:
            ws = self._ws
            if ws is not None and S is self._S and h == self.h and n >= 0:
                # the age rule, the law and the publish in one compiled call (`agent_tick`)
                hybrid, h_, max_age, hold_n, future, h_us = self._tick_args
                sysid, seq = link.tick_header
                flags = agent_tick(n, ws.I, ws.F, ws.B, hybrid, h_, max_age, hold_n, future,
                                   n * h_us, sysid, seq)
                ticked = not flags & T_AGAIN
                ages = link.finish_age_rules(n, self._verdict, mode) if not ticked \
                    else link.ages_now
            else:
                # the link's arrays: the age rule and the held θ in one compiled call
                ages = link.age_rules(n, self._verdict, mode, rx, self._rx_index)
            self._used_at = (n, link.held_steps.tolist(), ages.tolist())
            if ticked:
                changed = flags & T_CHANGED
                fs = bool(flags & T_FAILSAFE)
                hold = bool(flags & T_HOLD)
            else:
                vs = self._verdict.tolist()
                changed = vs != self._last_verdict.tolist()
                if changed:
                    self._last_verdict[:] = vs
                fs = 2 in vs
                hold = 1 in vs
            if changed:      # a neighbour's verdict changed
                state = self._state
                for j, v in zip(self.neighbours, self._verdict.tolist()):
                    m = VERDICTS[v]
                    if m != state[j]:
                        state[j] = m
                        self.transitions.append((n, j, m))
                        if len(self.transitions) > 1000:
                            del self.transitions[:500]
        elif not self.lockstep:
            state = self._state
            q = 0
            for j, pairs in self._rx_rows:
                s, age, m = link.age_rule(j, n)
                self.used[j] = (s, n if age is None else age)
                if m != state[j]:
                    state[j] = m
                    self.transitions.append((n, j, m))
                    if len(self.transitions) > 1000:
                        del self.transitions[:500]
                if m == "fresh":
                    mode[q] = FRESH
                else:
                    mode[q] = FRESH + 1
                    if m == "failsafe":
                        fs = True
                    else:
                        hold = True
                if s is not None:
                    smp = link.neighbour(j)
                    if smp is not self._seen[q]:
                        self._seen[q] = smp
                        th = smp.theta
                        for k, r in pairs:
                            rx[r] = th[k]
                q += 1
        call = self._calls if S is self._S and h == self.h else self._agent_step_calls(S, h)
        pub = self._pub
        if self.lockstep:
            n_jumps = agent_step(*call[0])
            for k, r in self._own_rows:
                pub[k] = float(ctl.theta_jump[r])
            self._last_theta = (n, pub)
            if self.owned:
                link.publish(n, None, pub)

            def ready(j=None):
                js = self.neighbours if j is None else (j,)
                return all(link.theta_at(x, n) is not None for x in js)

            self._wait(ready, "θ", lambda: (self._resend_theta(),
                                           link.publish(n, S[0], None)))
            for j, pairs in self._rx_rows:
                th = link.theta_at(j, n)
                for k, r in pairs:
                    rx[r] = th[k]
                link.age_steps(j, n)   # 0 in lockstep: counted for the link statistics
            agent_step(*call[1])
        elif ticked:
            n_jumps, nf = self._tick_out.tolist()
            link.published(n, nf, S, ctl.theta_jump, self._own_r)
        else:
            n_jumps = agent_step(*call[3 if fs else 2])
            link.publish_rows(n, S, ctl.theta_jump, self._own_r)
        if fs:
            self.failsafe_steps += 1
            if not self.failsafe:
                self.failsafe_entries += 1
                self.on_event(f"fail-safe at step {n}: no fresh data from neighbour(s) "
                              f"{[j for j in self.neighbours if self._state[j] == 'failsafe']}")
        elif self.failsafe:
            self.on_event(f"rejoined at step {n}: fresh data from every neighbour")
        self.failsafe = fs
        if hold:
            self.hold_steps += 1
        if self.sample_every and self.k % self.sample_every == 0:
            self.own_samples.append({"step": n, "S": S[0].tolist(),
                                     "theta": {str(k): float(ctl.theta_jump[r])
                                               for k, r in self._own_rows}})
        if not n_jumps:
            return ctl.u, ()
        return ctl.u, tuple(JumpEvent(r + 1, float(ctl.theta_prev[r]), float(ctl.theta_jump[r]),
                                      float(ctl.mu[r]))
                            for k, r in self._own_rows if ctl.jumped[r])

    # ------------------------------------------------------------------ results
    def stats(self) -> dict:
        d = self.vehicle.stats()
        d["agent_link"] = self.link.stats()
        d["failsafe"] = self.failsafe
        return d

    def own_final(self) -> dict:
        """The agent's own row and θ of its owned edges at the end (what the swarm merges)."""
        return {"step": self.n, "S": self.vehicle.read()[0].tolist(),
                "theta": {str(k): v for k, v in self.theta_owned.items()}}

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            self.link.close()
        finally:
            self.vehicle.close()


# ---------------------------------------------------------------------------------- the log
NEIGHBOURS = {
    "title": "se3sync.Neighbours",
    "description": "What an agent process used of its neighbours at a communication point",
    "type": "object",
    "properties": {
        "timestamp": {"type": "object"},
        "agent": {"type": "integer"},
        "failsafe": {"type": "boolean", "description": "zero wrench: a neighbour's data too old"},
        "neighbours": {"type": "array", "items": {"type": "object", "properties": {
            "agent": {"type": "integer"},
            "sample_step": {"type": ["integer", "null"],
                            "description": "swarm step of the newest sample used (null: S0)"},
            "age_steps": {"type": "integer", "description": "n − sample_step"},
            "state": {"type": "string", "enum": ["fresh", "hold", "failsafe"]},
        }}},
    },
}


LOG_BLOCK = 50   # records per block (1 s at hil_6uav's 50 Hz log rate)


def _agent_logger(path, node: AgentNode, extra_metadata: dict, encoding: str = "json",
                  block: int = LOG_BLOCK):
    """The neighbourhood's McapLogger (the swarm's numbers) with a /neighbours channel written
    at every record: the sample of each neighbour used, its age and the age rule's verdict.

    Off the control path (issue 31): a record is copied into a buffer at its step and the
    buffer is encoded ``block`` records at a time by `McapLogger.record_block` (the compiled
    co-simulation's block encoder), at the latest before a jump, link statistics or the end
    are written, so that each topic keeps its time order and the scene sees the jumps when it
    did; the messages are those `record` writes, value for value."""
    class AgentLogger(McapLogger):
        def __init__(self, *a, **kw):
            super().__init__(*a, **kw)
            self._block = []
            self._flushing = False

        def record(self, t_ns, S, u, theta, mu, jumped, rot_err, pos_err, U, quat, V, kX_U):
            if self._flushing:   # the block encoder's own fallback (a non-finite row)
                return McapLogger.record(self, t_ns, S, u, theta, mu, jumped, rot_err, pos_err,
                                         U, quat, V, kX_U)
            nb = []
            used = node.used
            for j in node.neighbours:
                s, age = used[j]
                nb.append({"agent": j, "sample_step": s, "age_steps": age,
                           "state": node._state[j]})
            self._block.append((t_ns, np.array(S), np.array(u), np.array(theta), np.array(mu),
                                np.array(jumped), np.array(rot_err), np.array(pos_err),
                                np.array(U), np.array(quat), float(V), float(kX_U),
                                {"agent": node.i, "failsafe": node.failsafe, "neighbours": nb}))
            if len(self._block) >= block:
                self.flush()

        def flush(self) -> None:
            """Encodes the buffered records (and their /neighbours messages)."""
            rows, self._block = self._block, []
            if not rows:
                return
            cols = list(zip(*rows))
            self._flushing = True
            try:
                McapLogger.record_block(self, list(cols[0]), *(np.stack(c) for c in cols[1:10]),
                                        np.array(cols[10]), np.array(cols[11]),
                                        finite_only=False)
            finally:
                self._flushing = False
            for t_ns, nbs in zip(cols[0], cols[12]):
                self.message("/neighbours", t_ns, nbs)

        def jump(self, *a, **kw):
            self.flush()
            super().jump(*a, **kw)

        def link_stats(self, *a, **kw):
            self.flush()
            super().link_stats(*a, **kw)

        def outcome(self, *a, **kw):
            self.flush()
            super().outcome(*a, **kw)

        def close(self, discard: bool = False):
            if not discard and not self._closed:
                self.flush()
            super().close(discard=discard)

    lg = AgentLogger(path, node.local, controller=node.law, agent_ids=node.agents,
                     edge_ids=node.edge_ids, extra_metadata=extra_metadata, encoding=encoding)
    lg.add_channel("/neighbours", NEIGHBOURS)
    return lg


def _process_age() -> float | None:
    """Seconds since this process started (Linux: /proc, 10 ms resolution), or None."""
    try:
        with open("/proc/self/stat", encoding="ascii") as f:
            start = int(f.read().rpartition(")")[2].split()[19])   # field 22: start time, ticks
        with open("/proc/uptime", encoding="ascii") as f:
            up = float(f.read().split()[0])
        return up - start / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


def _max_rss_mb() -> float | None:
    """This process's peak resident memory (MB), or None where getrusage does not say."""
    try:
        import resource
    except ImportError:  # pragma: no cover - not POSIX
        return None
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


_STATUS_MB = {"VmHWM": "vm_hwm_mb", "VmRSS": "vm_rss_mb", "RssAnon": "rss_anon_mb",
              "RssFile": "rss_file_mb", "RssShmem": "rss_shmem_mb"}
_ROLLUP_MB = {"Pss": "pss_mb", "Pss_Anon": "pss_anon_mb", "Pss_File": "pss_file_mb"}


def _memory() -> dict:
    """This process's memory now (MB; Linux /proc, None elsewhere): its peak resident set
    (``vm_hwm_mb``, the kernel's VmHWM), the resident set and its parts (``rss_anon_mb``: private
    heap and stacks; ``rss_file_mb``: mapped files, mostly shared libraries that every agent
    process maps from the same pages: libLLVM, numpy's; ``rss_shmem_mb``), the proportional set
    size (``pss_mb``: each resident page divided by the number of processes mapping it, so the
    PSS of all processes add up to what they hold together; its anonymous and file parts) and the
    unique set (``uss_mb``: the private pages, what ending the process frees)."""
    out = dict.fromkeys([*_STATUS_MB.values(), *_ROLLUP_MB.values(), "uss_mb"])
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                key, _, rest = line.partition(":")
                if key in _STATUS_MB:
                    out[_STATUS_MB[key]] = int(rest.split()[0]) / 1024.0   # kB
    except (OSError, ValueError, IndexError):
        pass
    try:
        uss = 0
        with open("/proc/self/smaps_rollup", encoding="ascii") as f:
            for line in f:
                key, _, rest = line.partition(":")
                if key in _ROLLUP_MB:
                    out[_ROLLUP_MB[key]] = int(rest.split()[0]) / 1024.0
                elif key in ("Private_Clean", "Private_Dirty"):
                    uss += int(rest.split()[0])
                    out["uss_mb"] = uss / 1024.0
    except (OSError, ValueError, IndexError):
        pass
    return out


def _warm_up(node: AgentNode) -> None:
    """The compiled kernels the steps use, loaded (or compiled) now rather than while the vehicle
    and the neighbours wait for the first step."""
    if not node.compiled:
        agent_view(node.law, node.sc, node.i).wrench(
            {k: node._rel(node.local.S0, k) for k in node.edge_ids}, np.zeros(6),
            {j: np.zeros(6) for j in node.neighbours}, {k: 0.0 for k in node.edge_ids})
    else:   # on copies: the node's state stays as it is
        ctl = node.controller
        agent_step(node.local.S0.copy(), node._ea, node._eb, node._owned_mask, node._nbr,
                   node._mode.copy(), node.stepper.hybrid, node.stepper.P, node.h, 3, False,
                   ctl.theta.copy(), node._rx.copy(), ctl.theta_prev.copy(),
                   ctl.theta_jump.copy(), ctl.mu.copy(), ctl.jumped.copy(), node._termbuf.copy(),
                   node._relrows.copy(), ctl.u.copy())
        if node._held_values is not None:
            held_rows(node._S.copy(), node._S[:1].copy(), node.link.held_steps.copy(),
                      node._held_values.copy())
        if node._ws is not None:
            hybrid, h, max_age, hold, future, _ = node._tick_args
            agent_tick(0, *node._ws.detached(), hybrid, h, max_age, hold, future, 0, 1, 0)
    node.link.warm_up()
    node.vehicle.warm_up()
    loc = node.local
    N, M = loc.graph.n, loc.graph.M
    U = np.zeros(M)
    network_U(loc.S0, loc.theta0.copy(), loc.graph.edges, node.params.P, U)
    metrics(loc.S0, loc.graph.edges, U, float(loc.gains.k_X), np.ascontiguousarray(loc.masses),
            np.ascontiguousarray(loc.inertias), np.zeros(M), np.zeros(M), np.zeros((N, 4)))


def _freeze_heap() -> int:
    """What the start-up built (the modules, numba's registries, the links) lives as long as the
    process: collected once, then frozen (`gc.freeze`), so the collector's full passes walk only
    what the steps allocate. Without it a full pass walked all of it while the loop waited: 50–200
    ms with 16 agents in a process at 100 Hz (2 such passes a run in each process, each 5–20
    periods late at once for all its agents). Returns how many objects are frozen."""
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


def run_agent(scenario, agent_id: int, *, law: str = "hybrid", lockstep: bool = False,
              start: float | None = None, start_file=None, key_file=None, insecure: bool = False,
              vehicle: str | None = None, connect_timeout: float | None = None,
              signing_state=None, tlog=None, log_path=None, summary_path=None,
              log_encoding: str = "json", progress: bool = False, on_event=None,
              live_feed=None, host=None, kernels: str | None = None) -> dict:
    """Agent ``agent_id`` from its vehicle's connection to its summary (see the module
    docstring); the library entry point of `se3sync agent`. Raises ConnectError (the vehicle
    never connected) and LinkError (lockstep: a vehicle or neighbour stopped answering; a late
    joiner heard nothing). A run that fails removes its log; an interrupted one keeps it.

    ``host``: the `bridge.swarm.host.Host` of a process running several agents (one thread
    each): its ``stop`` event stops this agent as a signal would, its master loop is registered
    with it (so that it can be asked to stop), and the summary's ``cpu_s`` is this thread's own,
    with the process's in ``host``. Meant for a process of its own (`se3sync agent`): before
    its loop it freezes the process's heap (`_freeze_heap`). ``kernels``: what `se3sync agent`
    chose (`bridge.swarm.aot.use`), recorded in the summary's ``startup``."""
    hosted = host is not None
    if not hosted:   # (a host sets it once for its agents)
        limit_process(AGENT_THREADS)   # one job per process: BLAS threads would only compete
    node = AgentNode(scenario, agent_id, law=law, lockstep=lockstep, key_file=key_file,
                     insecure=insecure, vehicle=vehicle, connect_timeout=connect_timeout,
                     signing_state=signing_state, tlog=tlog, on_event=on_event,
                     stop=host.stop if hosted else None)
    stepped = hosted and not lockstep
    if stepped:
        # the process's stepping thread waits for the deadlines (bridge.swarm.host)
        node.vehicle.paced_by_host = True
    logger = None
    failed = False
    sc = scenario
    h = node.h
    startup = {} if kernels is None else {"kernels": kernels}
    try:
        _warm_up(node)
        startup["warm_s"] = _process_age()        # imports, set-up, the compiled kernels loaded
        node.connect()
        startup["connected_s"] = _process_age()   # …and the vehicle's first state
        startup["ready_s"] = _process_age()       # …ready to step: the swarm's start awaited
        startup["frozen_objects"] = _freeze_heap()
        if start_file is not None and not lockstep:
            start = node.wait_start(start_file)
        spl = max(1, int(round(1.0 / h)))
        dec = max(1, int(round(1.0 / (sc.log_rate * h))))
        # hosted: at the start, one thread of the process wakes (the stepping thread), not one
        # per agent (all at once, on a machine running the whole swarm: its first steps late)
        node.join(start, math.lcm(spl, dec), lead=HOSTED_LEAD_S if stepped else 0.0)
        n_steps = sc.n_steps() - node.first_step
        if n_steps <= 0:
            raise Se3SyncError(f"--start: the swarm's run ({sc.n_steps()} steps from "
                               f"{start}) is over")
        node.n_steps = n_steps
        requested = []
        with signals.catching(lambda: requested.append(True)):
            if log_path is not None:
                logger = _agent_logger(log_path, node, {
                    "plant": "mavlink", "agent": node.i,
                    "time_base": "simulated (lockstep)" if lockstep else
                                 "wall (paced: t = n·h from the swarm's start)",
                    "first_step": node.first_step, "start_unix": "" if start is None else repr(start)},
                    log_encoding)
            logger = feed_logger(logger, live_feed, node)   # swarm --live (bridge/live.py)
            master = Master(node.local, node.plant, node.controller, logger,
                            first_step=node.first_step)
        if hosted:
            host.register(master)
        if requested or node._stopped():
            master.request_stop()
        startup["first_step_s"] = _process_age()  # step n₀ due (real time: paced by join)
        cpu0, pcpu0 = time.thread_time(), time.process_time()
        if stepped:
            summary, cpu = host.drive(master.steps(n_steps, progress=progress), node.vehicle,
                                      due=node.vehicle.t0)
        else:
            summary = master.run(n_steps, progress=progress)
            cpu = None
        # one agent per process: the process's CPU (its log's encoding included); hosted, the
        # CPU its steps took (real time: of the stepping thread; lockstep: its own thread's) —
        # the process's is shared by its agents
        if cpu is None:
            cpu = (time.thread_time() - cpu0) if hosted else (time.process_time() - pcpu0)
        pcpu = time.process_time() - pcpu0
    except BaseException as exc:
        failed = not isinstance(exc, KeyboardInterrupt)
        raise
    finally:
        try:
            if logger is not None:
                logger.close(discard=failed)
        finally:
            try:
                own = node.own_final() if not failed else None
            except Exception:  # noqa: BLE001 - the vehicle may be gone
                own = None
            node.close()
    pos = dict(enumerate(node.edge_ids, start=1))
    for j in summary["jumps"]:
        j["edge"] = pos[j["edge"]]
    summary.update({
        "plant": "mavlink", "lockstep": bool(lockstep), "agent": node.i,
        "agents": list(node.agents), "neighbours": list(node.neighbours),
        "edges": list(node.edge_ids), "owned_edges": list(node.owned),
        "first_step": node.first_step, "start": start, "duration_steps": sc.n_steps(),
        "cpu_s": cpu, "cpu_fraction": cpu / summary["wall_time_s"] if summary["wall_time_s"] else None,
        "max_rss_mb": _max_rss_mb(), "memory": _memory(),
        "startup": {**startup, "numba_loaded": "numba" in sys.modules},   # (at the end)
        **({"host": {"agents": list(host.ids), "cpu_s": pcpu,
                     "cpu_fraction": pcpu / summary["wall_time_s"] if summary["wall_time_s"]
                     else None}} if hosted else {}),
        "own": {"samples": node.own_samples, "final": own},
        "failsafe": {"steps": node.failsafe_steps, "entries": node.failsafe_entries,
                     "hold_steps": node.hold_steps,
                     "transitions": [{"step": s, "neighbour": j, "state": m}
                                     for s, j, m in node.transitions]},
        "network": {"max_age": node.net.max_age, "hold": node.net.hold,
                    "max_age_steps": node.link.max_age_steps, "hold_steps": node.link.hold_steps},
    })
    return finish_summary(summary, logger, log_path, summary_path)
