"""The live view of the bridge's processes (`--live` on `swarm` and `vehicle`; `connect` runs
cosim's master and uses `cosim.log.live` as `run` does).

`swarm --live`: the merged view of every agent. The swarm's parent serves the scenario's
channels (`cosim.log.live.LiveServer`) and listens on a loopback UDP feed; each agent process
(`agent --live-feed`, which `swarm` passes) sends it, at most ``rate`` times per second of wall
time, its own row (pose, velocity, wrench), θ, μ_U and the jump flags of the edges it owns, and
every jump of those edges (`FeedTee`). The parent (`SwarmLive`) keeps each agent's newest row
(the scenario's initial state until it has one), computes the edges' errors of the whole graph
(`cosim.master.NetworkMetrics`, as a run does) and publishes a merged frame, at most ``rate``
per second, with the log's messages.

The feed is network input: a datagram is taken only from a loopback address, with the right
magic, version and length, an agent id of the scenario, edges that agent owns, finite numbers
and a time stamp within a window of the view's current time (`AHEAD_S` plus `SPEED` times the
wall time since the last datagram taken; `FIRST_AHEAD_S` for the first): one forged stamp far
ahead would otherwise hold every later frame back (``future``); anything else is counted by
reason (`SwarmLive.rejected`) and dropped.

`vehicle --live`: the loopback vehicles' own state (their world frame, NED by default) with the
scenario's graph, at most ``rate`` frames per second (`VehicleLive`); θ, μ_U, U and V̄ are the
controller's and unknown to the vehicles: sent as NaN.
"""
from __future__ import annotations

import math
import socket
import struct
import threading
import time

import numpy as np

from cosim.log.live import DEFAULT_RATE, LiveServer
from cosim.master import NetworkMetrics

__all__ = ["SwarmLive", "FeedTee", "feed_logger", "VehicleLive"]

MAGIC = b"S3LF"
VERSION = 1
_HEAD = struct.Struct("<4sBHQ")          # magic, version, agent id, t_ns
_ROW = struct.Struct("<24d")             # S (18) then u (6)
_COUNT = struct.Struct("<H")
_EDGE = struct.Struct("<HddB")           # edge id, θ after the jump stage, μ_U, jumped
_JUMP = struct.Struct("<Hdddd")          # edge id, t, θ⁻, θ⁺, μ_U
MAX_DATAGRAM = 65000
FIRST_AHEAD_S = 10.0    # the first datagram's stamp: at most this far into the run
AHEAD_S = 2.0           # later ones: at most this far ahead of the view's current time…
SPEED = 50.0            # …plus this many times the wall time since the last one (lockstep runs
#                         faster than the wall clock)


def encode_feed(agent: int, t_ns: int, S_row, u_row, edges, jumps) -> bytes:
    """One feed datagram: ``edges`` [(edge id, θ, μ, jumped)], ``jumps`` [(edge id, t, θ⁻, θ⁺,
    μ)]."""
    parts = [_HEAD.pack(MAGIC, VERSION, agent, t_ns),
             _ROW.pack(*np.asarray(S_row, float).tolist(), *np.asarray(u_row, float).tolist()),
             _COUNT.pack(len(edges))]
    parts += [_EDGE.pack(int(k), float(th), float(mu), int(bool(j))) for k, th, mu, j in edges]
    parts.append(_COUNT.pack(len(jumps)))
    parts += [_JUMP.pack(int(k), *map(float, rest)) for k, *rest in jumps]
    return b"".join(parts)


def decode_feed(data: bytes):
    """(agent, t_ns, row (24,), edges, jumps) or a reason string when the datagram is bad."""
    if len(data) < _HEAD.size + _ROW.size + 2 * _COUNT.size:
        return "short"
    magic, ver, agent, t_ns = _HEAD.unpack_from(data, 0)
    if magic != MAGIC:
        return "magic"
    if ver != VERSION:
        return "version"
    off = _HEAD.size
    row = np.array(_ROW.unpack_from(data, off))
    off += _ROW.size
    (ne,) = _COUNT.unpack_from(data, off)
    off += _COUNT.size
    if len(data) < off + ne * _EDGE.size + _COUNT.size:
        return "length"
    edges = [_EDGE.unpack_from(data, off + q * _EDGE.size) for q in range(ne)]
    off += ne * _EDGE.size
    (nj,) = _COUNT.unpack_from(data, off)
    off += _COUNT.size
    if len(data) != off + nj * _JUMP.size:
        return "length"
    jumps = [_JUMP.unpack_from(data, off + q * _JUMP.size) for q in range(nj)]
    return agent, t_ns, row, edges, jumps


class _Gate:
    """At most ``rate`` openings per second of wall time."""

    def __init__(self, rate):
        self.period = 1.0 / float(rate)
        self.next = 0.0

    def open(self) -> bool:
        now = time.monotonic()
        if now < self.next:
            return False
        self.next = now + self.period
        return True


class SwarmLive:
    """The swarm's merged live view: ``SwarmLive(scenario, host, port, rate, encoding)``;
    ``feed`` is the "127.0.0.1:PORT" the agents send to; ``close()``."""

    def __init__(self, scenario, host="127.0.0.1", port=8765, rate=DEFAULT_RATE,
                 encoding="json"):
        sc = scenario
        self.sc = sc
        self.server = LiveServer(sc, host, port, rate=rate, encoding=encoding)
        self.enc = self.server.encoder
        N, M = sc.graph.n, sc.graph.M
        self.owner = {k + 1: int(a) for k, (a, _) in enumerate(sc.graph.edge_list)}
        self.S = np.array(sc.S0, float)
        self.u = np.zeros((N, 6))
        self.theta = np.array(sc.theta0, float)
        self.mu = np.full(M, np.nan)
        self.jumped = np.zeros(M, bool)
        self.metrics = NetworkMetrics(sc)
        self.t_ns = 0
        self._t_wall = None     # time.monotonic() of the last datagram taken
        self._last = -1
        self.received = 0
        self.rejected = {}
        self._gate = _Gate(rate)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.2)
        self.feed = f"127.0.0.1:{self.sock.getsockname()[1]}"
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="se3sync-swarm-live",
                                        daemon=True)
        self._thread.start()

    def announce(self, command="se3sync swarm"):
        self.server.announce(command)

    def _reject(self, why):
        self.rejected[why] = self.rejected.get(why, 0) + 1

    def accept(self, data: bytes, addr) -> bool:
        """Checks and applies one feed datagram; False (counted by reason) when refused."""
        host = addr[0] if addr else ""
        if not host.startswith("127."):
            self._reject("address")
            return False
        d = decode_feed(data)
        if isinstance(d, str):
            self._reject(d)
            return False
        agent, t_ns, row, edges, jumps = d
        N = self.sc.graph.n
        if not 1 <= agent <= N:
            self._reject("agent")
            return False
        now = time.monotonic()
        ahead = FIRST_AHEAD_S if self._t_wall is None else AHEAD_S + SPEED * (now - self._t_wall)
        if int(t_ns) > self.t_ns + ahead * 1e9:
            self._reject("future")
            return False
        if not np.isfinite(row).all():
            self._reject("non_finite")
            return False
        for k, th, mu, _ in edges:
            if self.owner.get(k) != agent:
                self._reject("not_owner")
                return False
            if not (math.isfinite(th) and (math.isfinite(mu) or math.isnan(mu))):
                self._reject("non_finite")
                return False
        for k, t, a, b, mu in jumps:
            if self.owner.get(k) != agent:
                self._reject("not_owner")
                return False
            if not (math.isfinite(t) and math.isfinite(a) and math.isfinite(b)):
                self._reject("non_finite")
                return False
        # accepted: the agent's newest row, its edges, its jumps
        self.received += 1
        self.S[agent - 1] = row[:18]
        self.u[agent - 1] = row[18:]
        for k, th, mu, j in edges:
            self.theta[k - 1], self.mu[k - 1], self.jumped[k - 1] = th, mu, bool(j)
        for k, t, a, b, mu in jumps:
            self.enc.jump(round(t * 1e9), t, k, a, b, mu)
        self.t_ns = max(self.t_ns, int(t_ns))
        self._t_wall = now
        return True

    def _frame(self):
        if self.t_ns <= self._last or not self.server.sink.watched():
            return   # nothing newer than the last frame, or nobody watching
        self._last = self.t_ns
        m = self.metrics
        V, _ = m.compute(np.ascontiguousarray(self.S), self.theta)
        self.enc.record(self.t_ns, self.S, self.u, self.theta, self.mu, self.jumped, m.rot,
                        m.pos, m.U, m.quat, float(V), float(m.kX * m.U.sum()))
        self.server.frames += 1

    def _loop(self):
        while not self._stop.is_set():
            try:
                data, addr = self.sock.recvfrom(MAX_DATAGRAM)
            except socket.timeout:
                continue
            except OSError:
                return
            try:
                if self.accept(data, addr) and self._gate.open():
                    self._frame()
            except Exception:  # noqa: BLE001 - the view must never stop the swarm
                self._reject("error")

    def close(self):
        self._stop.set()
        self._thread.join(timeout=2)
        self.sock.close()
        self.server.close()


class FeedTee:
    """An agent's logger as its master sees it: every call to ``inner`` (the agent's own log, or
    None), and its own row and owned edges to the swarm's feed at most ``rate`` times per second
    (the next record after a jump goes out at once, with the jump)."""

    def __init__(self, inner, addr, node, rate=DEFAULT_RATE):
        self.inner = inner
        self.addr = addr
        self.i = int(node.i)
        self.row = list(node.agents).index(self.i)
        ids = list(node.edge_ids)
        self.ids = ids
        self.own_pos = [ids.index(k) for k in node.owned]
        self._gate = _Gate(rate)
        self._jumps = []
        self.counts = inner.counts if inner is not None else {}
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)

    def __getattr__(self, name):
        inner = self.__dict__.get("inner")
        if inner is None:
            raise AttributeError(name)
        return getattr(inner, name)

    def record(self, t_ns, S, u, theta, mu, jumped, *rest):
        if self.inner is not None:
            self.inner.record(t_ns, S, u, theta, mu, jumped, *rest)
        if self._gate.open() or self._jumps:
            edges = [(self.ids[q], theta[q], mu[q], jumped[q]) for q in self.own_pos]
            self._send(encode_feed(self.i, int(t_ns), S[self.row], u[self.row], edges,
                                   self._jumps))
            self._jumps = []

    def _send(self, data):
        try:
            self.sock.sendto(data, self.addr)
        except OSError:
            pass   # the view is best effort: a full buffer never stops the agent

    def jump(self, t_ns, t, edge, before, after, mu):
        if self.inner is not None:
            self.inner.jump(t_ns, t, edge, before, after, mu)
        if 1 <= edge <= len(self.ids):
            self._jumps.append((self.ids[edge - 1], t, before, after, mu))

    def link_stats(self, t_ns, stats):
        if self.inner is not None:
            self.inner.link_stats(t_ns, stats)

    def close(self, discard=False):
        try:
            if self.inner is not None:
                self.inner.close(discard=discard)
        finally:
            self.sock.close()


def feed_logger(logger, feed, node):
    """``logger`` unchanged without a feed; else a `FeedTee` (``feed``: (host, port, rate))."""
    if feed is None:
        return logger
    host, port, rate = feed
    return FeedTee(logger, (host, int(port)), node, rate)


class VehicleLive:
    """The loopback vehicles' state as a live view: call it with the `VehicleServer` after each
    tick; at most ``rate`` frames per second are encoded, only while a client watches."""

    def __init__(self, scenario, host="127.0.0.1", port=8765, rate=DEFAULT_RATE,
                 encoding="json", step=None):
        self.sc = scenario
        self.server = LiveServer(scenario, host, port, rate=rate, encoding=encoding)
        self.enc = self.server.encoder
        self.metrics = NetworkMetrics(scenario)
        M = scenario.graph.M
        self._nan = np.full(M, np.nan)
        self._no = np.zeros(M, bool)
        self._gate = _Gate(rate)
        self.step = step

    def announce(self, command="se3sync vehicle"):
        self.server.announce(command)

    def __call__(self, srv) -> None:
        if not self._gate.open() or not self.server.sink.watched():
            return
        vs = srv.vehicles
        S = np.ascontiguousarray(np.stack([v.S for v in vs]))
        u = np.stack([v.wrench for v in vs])
        m = self.metrics
        m.compute(S, np.zeros(self.sc.graph.M))   # the geometry: rot_err, pos_err, quat
        h = self.step if self.step is not None else srv.odom_period
        t_ns = round(vs[0].k * h * 1e9)
        nan = self._nan
        self.enc.record(t_ns, S, u, nan, nan, self._no, m.rot, m.pos, nan, m.quat,
                        float("nan"), float("nan"))
        self.server.frames += 1

    def close(self):
        self.server.close()
