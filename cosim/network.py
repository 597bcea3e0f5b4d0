"""The ``[network]`` scenario table (inter-agent endpoints, link delay/jitter/loss, the age rule)
and `NetworkController`, the law run per agent on delayed, lossy neighbour data in co-simulation.

Delay contract (shared with the stability analysis). At communication step n agent i uses its own
state x_i(n) fresh and, from each neighbour j, the newest message it has received: j's message of
sample s carries X_j(s), ξ_j(s) and, for the edges k that j owns, θ_k(s) after the jump stage.
Over link j→i that message arrives at step s + d_ji + J_s, with d_ji = ⌈delay/h − 1e-9⌉ and J_s
= ⌈U[0, jitter]/h − 1e-9⌉ steps, and is lost with probability ``loss`` (both seeded). Until a
link's first message arrives the receiver uses the sender's initial state S0 and θ(0), as if a
message of sample 0 had arrived at step 0. Agent i then computes X̄_k from its fresh pose and the
received one, jumps and flows the θ_k it owns, and uses the received θ_k for the edges its
neighbour owns (`ex_controller`). With every delay, jitter and loss 0 this is the network step.

Age rule: data older than ``max_age`` is not used: the edge's term is held at its last value (an
owned θ_k is frozen) for ``hold`` more seconds, after which the agent fails safe (zero wrench)
until fresh data arrives again.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from controller import JumpEvent, layout
from controller.errors import ConfigError, Se3SyncError

from .controllers import EdgeState, law_name, require

__all__ = ["NetworkConfig", "LinkSpec", "parse_network", "check_links", "NetworkController",
           "networked", "DEFAULT_HOST", "DEFAULT_BASE_PORT"]

DEFAULT_HOST = "127.0.0.1"
DEFAULT_BASE_PORT = 15600
DEFAULT_HOLD = 0.5
KEYS = {"host", "base_port", "agent", "delay", "jitter", "loss", "seed", "link", "max_age", "hold"}
AGENT_KEYS = {"id", "address", "port"}
LINK_KEYS = {"from", "to", "delay", "jitter", "loss"}
AGE_BINS = 1 << 16  # used-data ages ≥ this many steps share the last histogram bin ...
AGE_MIN_BINS = 256  # ... or ≥ the longest transit + 1 if that is fewer, but at least this many
BUFFER_MAX_BYTES = 1 << 30  # delay line and age histograms: 8 × (L (18N + 3M) + 2M H) bytes
CHUNK = 4096        # steps of link schedule drawn at a time


@dataclass(frozen=True)
class LinkSpec:
    """Delay and jitter (s) and loss probability of one directed link."""

    delay: float = 0.0
    jitter: float = 0.0
    loss: float = 0.0


@dataclass(frozen=True)
class NetworkConfig:
    """The parsed ``[network]`` table. ``endpoints[i - 1]`` = (address, port) of agent i;
    ``links`` maps (from, to) (1-based) to the overriding LinkSpec."""

    endpoints: tuple
    default: LinkSpec
    seed: int
    links: dict = field(default_factory=dict)
    max_age: float = math.inf
    hold: float = DEFAULT_HOLD

    def link(self, frm: int, to: int) -> LinkSpec:
        return self.links.get((frm, to), self.default)

    def check_graph(self, graph) -> None:
        """Refuses a ``[[network.link]]`` between agents that are not graph neighbours (key
        paths relative to the table). The scenario loader calls it once the graph is known, so
        that every command (`check`, `run`, `agent`, `swarm`, ...) refuses the same tables."""
        nbrs = {frozenset(map(int, e)) for e in np.asarray(graph.edges) + 1}
        for idx, (frm, to) in enumerate(self.links):
            if frozenset((frm, to)) not in nbrs:
                raise ConfigError(f"link[{idx}]",
                                  f"agents {frm} and {to} are not neighbours in the graph")

    def worst_delay(self, graph, h: float) -> tuple:
        """(steps, key, spec): the longest transit d + J_max (d = ⌈delay/h − 1e-9⌉, J_max =
        ⌈jitter/h − 1e-9⌉) a message can take over any directed link of the graph's edges, the
        scenario key that sets it (``network.delay``, ``network.jitter`` or
        ``network.link[i]``) and that link's LinkSpec. (0, "network.delay", default) without
        edges or delays."""
        best = (0, "network.delay", self.default)
        for a, b in graph.edge_list:
            for ends in ((int(a), int(b)), (int(b), int(a))):
                spec = self.link(*ends)
                d = _steps(spec.delay, h) + _steps(spec.jitter, h)
                if d > best[0]:
                    best = (d, self.key_of(ends), spec)
        return best

    def key_of(self, ends) -> str:
        """The scenario key that sets the delay of directed link ``ends`` = (from, to)."""
        for i, e in enumerate(self.links):
            if e == tuple(ends):
                return f"network.link[{i}]"
        return "network.delay" if self.default.delay > 0 or not self.default.jitter else \
            "network.jitter"


def _is_num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


MAX_SECONDS = 1e6   # a delay, jitter, max_age or hold of more than ~11 days is a typo


def _seconds(key, v, *, allow_inf=False, positive=False) -> float:
    if not _is_num(v) or math.isnan(v) or (math.isinf(v) and not allow_inf):
        raise ConfigError(key, f"must be a {'number' if allow_inf else 'finite number'} of "
                               f"seconds, got {v!r}")
    v = float(v)
    if v < 0 or (positive and v == 0):
        raise ConfigError(key, f"must be {'> 0' if positive else '≥ 0'}, got {v!r}")
    if MAX_SECONDS < v < math.inf:
        raise ConfigError(key, f"must be at most {MAX_SECONDS:g} s"
                               f"{' (or inf)' if allow_inf else ''}, got {v!r}")
    return v


def _loss(key, v) -> float:
    if not _is_num(v) or not (0.0 <= float(v) < 1.0):
        raise ConfigError(key, f"must be a probability in [0, 1), got {v!r}")
    return float(v)


def _int(key, v, lo, hi) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
        raise ConfigError(key, f"must be an integer in {lo}..{hi}, got {v!r}")
    return int(v)


def _host(key, v) -> str:
    if not isinstance(v, str) or not v.strip() or any(c.isspace() for c in v):
        raise ConfigError(key, f"must be a host name or address without spaces, got {v!r}")
    return v


def _keys(prefix, table, allowed):
    if not isinstance(table, dict):
        raise ConfigError(prefix, f"must be a table, got {table!r}")
    for k in table:
        if k not in allowed:
            raise ConfigError(f"{prefix}.{k}" if prefix else k,
                              f"unknown key (allowed: {', '.join(sorted(allowed))})")


def _tables(key, v) -> list:
    if not isinstance(v, list) or not all(isinstance(x, dict) for x in v):
        raise ConfigError(key, f"must be an array of tables ([[network.{key}]])")
    return v


def parse_network(table: dict, n_agents: int) -> NetworkConfig:
    """``[network]`` → NetworkConfig (entry point ``se3sync.tables``); key paths in errors are
    relative to the table (the loader prefixes ``network.`` and the file name)."""
    _keys("", table, KEYS)
    host = _host("host", table.get("host", DEFAULT_HOST))
    base = _int("base_port", table.get("base_port", DEFAULT_BASE_PORT), 1, 65535 - (n_agents - 1))
    endpoints = [(host, base + i) for i in range(n_agents)]
    seen_ids = set()
    for idx, a in enumerate(_tables("agent", table.get("agent", []))):
        pre = f"agent[{idx}]"
        _keys(pre, a, AGENT_KEYS)
        if "id" not in a:
            raise ConfigError(f"{pre}.id", "missing (the agent's number, 1..N)")
        i = _int(f"{pre}.id", a["id"], 1, n_agents)
        if i in seen_ids:
            raise ConfigError(f"{pre}.id", f"agent {i} is given twice")
        seen_ids.add(i)
        addr = _host(f"{pre}.address", a.get("address", host))
        port = _int(f"{pre}.port", a.get("port", base + i - 1), 1, 65535)
        endpoints[i - 1] = (addr, port)
    owner = {}
    for i, ep in enumerate(endpoints, start=1):
        if ep in owner:
            raise ConfigError("agent", f"agents {owner[ep]} and {i} share the endpoint "
                                       f"{ep[0]}:{ep[1]}")
        owner[ep] = i
    default = LinkSpec(_seconds("delay", table.get("delay", 0.0)),
                       _seconds("jitter", table.get("jitter", 0.0)),
                       _loss("loss", table.get("loss", 0.0)))
    seed = _int("seed", table.get("seed", 0), 0, 2 ** 63 - 1)
    links = {}
    for idx, lk in enumerate(_tables("link", table.get("link", []))):
        pre = f"link[{idx}]"
        _keys(pre, lk, LINK_KEYS)
        for end in ("from", "to"):
            if end not in lk:
                raise ConfigError(f"{pre}.{end}", "missing (an agent number, 1..N)")
        frm = _int(f"{pre}.from", lk["from"], 1, n_agents)
        to = _int(f"{pre}.to", lk["to"], 1, n_agents)
        if frm == to:
            raise ConfigError(f"{pre}.to", f"a link joins two agents, got from = to = {frm}")
        if (frm, to) in links:
            raise ConfigError(pre, f"the link {frm} → {to} is given twice")
        links[(frm, to)] = LinkSpec(
            _seconds(f"{pre}.delay", lk.get("delay", default.delay)),
            _seconds(f"{pre}.jitter", lk.get("jitter", default.jitter)),
            _loss(f"{pre}.loss", lk.get("loss", default.loss)))
    max_age = _seconds("max_age", table.get("max_age", math.inf), allow_inf=True, positive=True)
    hold = _seconds("hold", table.get("hold", DEFAULT_HOLD))
    return NetworkConfig(tuple(endpoints), default, seed, links, max_age, hold)


def check_links(net: NetworkConfig, graph) -> None:
    """Refuses a ``[[network.link]]`` between agents that are not graph neighbours (key paths
    ``network.link[i]``): `NetworkConfig.check_graph`, which the scenario loader runs."""
    try:
        net.check_graph(graph)
    except ConfigError as exc:
        raise exc.under("network") from None


def _steps(seconds: float, h: float) -> int:
    return int(math.ceil(seconds / h - 1e-9)) if seconds > 0 else 0


class NetworkController:
    """The law of ``inner`` run per agent on neighbour data that crosses the ``[network]`` links:
    the `cosim.controllers.Controller` protocol, one compiled call per step of the law's delayed
    step (its ``delayed_step()`` capability; the paper's is
    `cosim.network_step.delayed_network_step`).

    Links are numbered 2k (edge k's positive end → negative end) and 2k + 1 (back). The schedule
    of each link (loss, jitter) comes from its own random stream, spawned from ``seed``, drawn
    CHUNK steps at a time: the same seed gives the same run, whatever else changes.
    """

    def __init__(self, scenario, inner, net: NetworkConfig, horizon: int | None = None):
        self._law = require(inner, "delayed_step", "[network]",
                            "the table runs a law per agent on delayed data")()
        check_links(net, scenario.graph)
        self.inner = inner
        self.net = net
        self.name = law_name(inner)
        self.edges = np.ascontiguousarray(scenario.graph.edges)
        self.N, self.M = scenario.graph.n, scenario.graph.M
        self.edge_state = getattr(inner, "edge_state", None)
        es = self._law.state or EdgeState.zeros(self.M)
        self.theta, self.theta_prev, self.theta_jump, self.mu, self.jumped = es
        self.u = self._law.u
        self.theta0 = self.theta.copy()
        M2 = 2 * self.M
        self.specs = [net.link(*self._ends(l)) for l in range(M2)]
        self.h = None
        # steps this controller will be stepped: a message arriving later never matters, so
        # the delay line holds at most this many samples (`_start`)
        self.horizon = max(1, int(scenario.n_steps() if horizon is None else horizon))
        self._buffers(float(scenario.step), scenario.path)
        self.counts = np.zeros((M2, 2), dtype=np.int64)
        self.age_hist = np.zeros((M2, 1), dtype=np.int64)
        self.failsafe = np.zeros((self.N, 4), dtype=np.int64)

    def _buffers(self, h: float, path=None) -> None:
        """The delay line's length L (samples kept) and the age histograms' bins H at step h.

        L = min(d + J_max, horizon) + 1: a message whose transit reaches past the run's last
        step is never used, so its transit is cut to the horizon (`_draw`). H = L + 1 (every
        transit's age), at least `AGE_MIN_BINS` and at most the horizon + 1 and `AGE_BINS`
        (older ages, which only losses make, share the last bin). Both grow with min(delay,
        run): more than `BUFFER_MAX_BYTES` together is refused (ConfigError naming the key that
        sets the longest transit, one line)."""
        d = [_steps(s.delay, h) + _steps(s.jitter, h) for s in self.specs]
        dmax = max(d, default=0)
        self.L = min(dmax, self.horizon) + 1
        self.H = int(min(AGE_BINS, self.horizon + 1, max(self.L + 1, AGE_MIN_BINS)))
        M2 = 2 * self.M
        need = 8 * (self.L * (self.N * layout.S_WIDTH + self.M + M2) + M2 * self.H)
        if need > BUFFER_MAX_BYTES:
            l = int(np.argmax(d))
            spec = self.specs[l]
            raise ConfigError(
                self.net.key_of(self._ends(l)),
                f"a delay of {spec.delay:g} s + jitter {spec.jitter:g} s ({dmax} steps of "
                f"h = {h:g} s) needs a delay line of {self.L} samples of {self.N} agents and "
                f"{M2} links, {need / 2 ** 30:.3g} GiB (at most {BUFFER_MAX_BYTES / 2 ** 30:g} "
                "GiB): use a shorter delay or a shorter run", path)

    def _ends(self, l: int) -> tuple:
        """(from, to), 1-based, of link l."""
        a, b = (int(x) + 1 for x in self.edges[l // 2])
        return (a, b) if l % 2 == 0 else (b, a)

    def write_wrench_into(self, buf):
        self.inner.write_wrench_into(buf)
        self._law = self.inner.delayed_step()
        self.u = self._law.u

    def reset(self, theta0=None) -> None:
        self.inner.reset(theta0)
        self.theta0 = self.theta.copy()
        self.h = None  # the link state starts again at the next step

    def _start(self, S, h: float) -> None:
        M2 = 2 * self.M
        self.h = h
        self.d = np.array([_steps(s.delay, h) for s in self.specs], dtype=np.int64)
        self.jmax = np.array([_steps(s.jitter, h) for s in self.specs], dtype=np.int64)
        self._buffers(h)
        L = self.L
        # transits cut to L − 1 = the horizon: stepping past it would use them
        self.cut = int((self.d + self.jmax).max(initial=0)) > L - 1
        self._last = self.horizon if self.cut else 2 ** 62
        self.max_age = _steps(self.net.max_age, h) if math.isfinite(self.net.max_age) else 2 ** 62
        self.hold = _steps(self.net.hold, h)
        self.ring_S = np.zeros((L, self.N, S.shape[1]))
        self.ring_theta = np.zeros((L, self.M))
        self.arrival = np.full((M2, L), -1, dtype=np.int64)
        self.held = np.full(M2, -1, dtype=np.int64)
        src = np.where(np.arange(M2) % 2 == 0, self.edges[:, 0].repeat(2), self.edges[:, 1].repeat(2))
        self.recv_S = np.ascontiguousarray(np.asarray(S, float)[src])
        self.recv_theta = self.theta0.repeat(2).copy()
        self.term = np.zeros((M2, 6))
        self.counts[:] = 0
        if self.age_hist.shape[1] != self.H:
            self.age_hist = np.zeros((M2, self.H), dtype=np.int64)
        self.age_hist[:] = 0
        self.failsafe[:] = 0
        seq = np.random.SeedSequence(self.net.seed)
        self.rngs = [np.random.default_rng(s) for s in seq.spawn(M2)]
        self.sched = np.zeros((CHUNK, M2), dtype=np.int64)
        self.r = CHUNK  # forces a draw at the first step
        self.n = 0

    def _draw(self) -> None:
        """The next CHUNK steps of every link's schedule: transit steps d + J, or −1 if lost."""
        h = self.h
        for l, (spec, rng) in enumerate(zip(self.specs, self.rngs)):
            col = np.full(CHUNK, self.d[l], dtype=np.int64)
            if spec.loss > 0 or spec.jitter > 0:
                x = rng.random((CHUNK, 2))  # one (loss, jitter) pair per step, in step order
                if spec.jitter > 0:
                    j = np.ceil(x[:, 1] * spec.jitter / h - 1e-9).astype(np.int64)
                    col += np.clip(j, 0, self.jmax[l])
                if spec.loss > 0:
                    col[x[:, 0] < spec.loss] = -1
            if self.cut:   # arrives at or after the horizon, never within the run
                np.minimum(col, self.L - 1, out=col)
            self.sched[:, l] = col
        self.r = 0

    def step_state(self, S, h: float):
        if self.h is None:
            self._start(S, float(h))
        elif h != self.h:
            raise Se3SyncError(f"network: the communication step changed from {self.h} to {h}")
        if self.n >= self._last:
            raise Se3SyncError(f"network: stepped past the {self.horizon} steps its delay line "
                               "was cut to (NetworkController(horizon=...))")
        if self.r == CHUNK:
            self._draw()
        nj = self._law.step(S, self.n, self.sched, self.r, self.ring_S, self.ring_theta,
                            self.arrival, self.held, self.recv_S, self.recv_theta, self.term,
                            self.max_age, self.hold, self.h, self.age_hist, self.counts,
                            self.failsafe)
        self.n += 1
        self.r += 1
        if nj == 0:
            return self.u, ()
        return self.u, tuple(
            JumpEvent(int(k) + 1, float(self.theta_prev[k]), float(self.theta_jump[k]),
                      float(self.mu[k]))
            for k in np.flatnonzero(self.jumped))

    def network_stats(self) -> dict:
        """The summary's ``"network"``: per directed link messages, losses and the nearest-rank
        p50/p99 of the age of the data used (steps and seconds), totals, and fail-safe counts."""
        h = self.h or 0.0
        links = []
        for l in range(2 * self.M):
            frm, to = self._ends(l)
            hist = self.age_hist[l]
            links.append({"from": frm, "to": to, "sent": int(self.counts[l, 0]),
                          "lost": int(self.counts[l, 1]), **_ages(hist, h)})
        total = self.age_hist.sum(axis=0)
        sent = int(self.counts[:, 0].sum())
        lost = int(self.counts[:, 1].sum())
        spec = self.net
        return {
            "delay": spec.default.delay, "jitter": spec.default.jitter,
            "loss": spec.default.loss, "seed": spec.seed,
            "max_age": spec.max_age if math.isfinite(spec.max_age) else None,
            "hold": spec.hold,
            "links": links,
            "total": {"sent": sent, "lost": lost, **_ages(total, h)},
            "failsafe_steps": [int(x) for x in self.failsafe[:, 2]],
            "failsafe_entries": [int(x) for x in self.failsafe[:, 3]],
        }


def _ages(hist, h) -> dict:
    n = int(hist.sum())
    if n == 0:
        return {"age_p50_steps": None, "age_p99_steps": None, "age_p50_s": None,
                "age_p99_s": None}
    c = np.cumsum(hist)
    p50 = int(np.searchsorted(c, math.ceil(0.50 * n)))
    p99 = int(np.searchsorted(c, math.ceil(0.99 * n)))
    return {"age_p50_steps": p50, "age_p99_steps": p99, "age_p50_s": p50 * h,
            "age_p99_s": p99 * h}


def networked(scenario, ctrl):
    """``ctrl`` itself, or wrapped in a NetworkController when the scenario has [network]."""
    net = scenario.tables.get("network")
    if net is None or isinstance(ctrl, NetworkController):
        return ctrl
    try:
        return NetworkController(scenario, ctrl, net)
    except ConfigError as exc:
        raise exc.with_file(scenario.path) from None
