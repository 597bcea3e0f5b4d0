"""MCAP logs of a run: JSON messages on JSON-schema channels that Foxglove understands.

Channels (log time = nanoseconds of SIMULATED time in co-simulation, see the ``se3sync``
metadata record's ``time_base``):

- ``/tf``        foxglove.FrameTransforms: every agent's pose, parent "world", child "agent_i"
- ``/edges``     se3sync.Edges: per edge θ, μ_U, ‖I − R̄‖_F, ‖p̄‖, U and mode ("flow"/"jump")
- ``/agents``    se3sync.Agents: per agent ω, v (body frame), torque τ, force f
- ``/lyapunov``  se3sync.Lyapunov: V̄ and k_X ΣU
- ``/jumps``     se3sync.Jump: one message per jump, never decimated
- ``/link/stats`` se3sync.LinkStats: link statistics of a hardware plant, 1 Hz (only if any)
- ``/scene``     foxglove.SceneUpdate: bodies and graph edges, at ``scene_rate`` (cosim/foxglove.py)
- ``/trail/agent_i`` foxglove.PosesInFrame: agent i's recent poses, at ``scene_rate``

The foxglove.* channels carry Foxglove's published JSON schemas (cosim/foxglove_schemas/).
A Foxglove layout is attached (``foxglove_layout.json``) and written beside the log
(``LOG.layout.json``).

The file is written in chunks as the run goes (the summary section only on close), so the
messages of the complete chunks of a killed process stay readable by a streaming reader.
"""
from __future__ import annotations

import json
import math
import os
import time
from pathlib import Path

import numpy as np
from mcap.writer import CompressionType, Writer

from controller import __version__
from controller import layout
from controller.errors import Se3SyncError

from ..files import atomic_path
from ..guards import outcome_metadata
from . import cdr
from . import foxglove as fg
from .appender import CDR_ZSTD_LEVEL, MessageAppender, Counted
from .schemas import FOXGLOVE, SCHEMAS

__all__ = ["McapLogger", "SCHEMAS", "ENCODINGS"]

try:  # optional (extra "fastlog"): McapLogger.record_fast formats numbers with it
    import orjson as _orjson
except ImportError:  # pragma: no cover
    _orjson = None

_dumps = json.dumps
_FMT = float.__repr__

# the message encodings of the per-record channels: JSON text, or ROS 2 CDR (cosim/log/cdr.py)
ENCODINGS = ("json", "cdr")


class _CdrRecords:
    """The /tf, /edges, /agents and /lyapunov layouts of a CDR log (cdr.compile_layout): the
    messages `McapLogger.record` writes in JSON, with the same names and numbers."""

    def __init__(self, aid, eid, edge_list):
        xyz, xyzw = "xyz", "xyzw"
        S = cdr.SCHEMA
        self.tf = cdr.compile_layout(S["/tf"], lambda f, t, m: {"transforms": [
            {"timestamp": t(), "parent_frame_id": "world", "child_frame_id": f"agent_{i}",
             "translation": {k: f() for k in xyz}, "rotation": {k: f() for k in xyzw}}
            for i in aid]})
        self.edges = cdr.compile_layout(S["/edges"], lambda f, t, m: {"timestamp": t(), "edges": [
            {"edge": eid[k], "positive": aid[a - 1], "negative": aid[b - 1], "theta": f(),
             "mu_u": f(), "rot_err": f(), "pos_err": f(), "u": f(), "mode": m()}
            for k, (a, b) in enumerate(edge_list)]})
        self.agents = cdr.compile_layout(S["/agents"], lambda f, t, m: {
            "timestamp": t(), "agents": [
                {"agent": i, **{k: [f(), f(), f()] for k in ("omega", "v", "torque", "force")}}
                for i in aid]})
        self.lyapunov = cdr.compile_layout(S["/lyapunov"], lambda f, t, m: {
            "timestamp": t(), "v": f(), "kx_u": f()})


def _with_modes(vals, jumped, flow, jump) -> list:
    """An /edges record's values (five per edge) with each edge's mode after its five."""
    out = []
    for q, j in enumerate(jumped):
        out += vals[5 * q:5 * q + 5]
        out.append(jump if j else flow)
    return out


def _r(x: float) -> str:
    """A float as JSON (repr is shortest round-trip; non-finite values become null)."""
    s = _FMT(x)
    return s if s[-1].isdigit() else "null"


class McapLogger:
    """Streams a run to an MCAP file.

    ``McapLogger(path, scenario, controller="hybrid", model_description=None,
    chunk_size=256 KiB)``; call ``record(...)``, ``jump(...)``, ``link_stats(...)`` and finally
    ``close()`` (also a context manager).

    ``scene_rate`` (Hz of simulated time, 0 = off) is the rate of the /scene and /trail
    messages, ``trail_seconds`` the length of a trail and ``trail_rate`` (Hz) the spacing of its
    kept poses (each message adds the current pose); ``layout_path`` is where the Foxglove
    layout is written ("auto": beside the log as LOG.layout.json; None: not written).

    ``agent_ids`` and ``edge_ids`` name the scenario's agents and edges in the messages (frames
    ``agent_<id>``, ``"edge": <id>``, the scene's entities, the trails' topics and the jumps)
    when they are part of a larger swarm (an agent process logs its own neighbourhood with the
    swarm's numbers); by default they are 1..N and 1..M. `jump` takes the edge's position
    (1..M) and writes its id.
    """

    def __init__(self, path, scenario, controller: str = "hybrid", model_description=None,
                 chunk_size: int = 256 * 1024, extra_metadata: dict | None = None,
                 scene_rate: float = 20.0, trail_seconds: float = 5.0, trail_rate: float = 5.0,
                 layout_path="auto", agent_ids=None, edge_ids=None, encoding: str = "json",
                 sink=None):
        if encoding not in ENCODINGS:
            raise Se3SyncError(f"log encoding {encoding!r}: expected one of "
                               f"{', '.join(ENCODINGS)}")
        self.encoding = encoding
        self._cdr = None   # the CDR record layouts (encoding "cdr"), made below
        self.path = str(path)
        n, M = scenario.graph.n, scenario.graph.M
        aid = list(range(1, n + 1)) if agent_ids is None else [int(x) for x in agent_ids]
        eid = list(range(1, M + 1)) if edge_ids is None else [int(x) for x in edge_ids]
        if len(aid) != n or len(eid) != M:
            raise Se3SyncError(f"McapLogger: {len(aid)} agent ids for {n} agents, {len(eid)} edge "
                               f"ids for {M} edges")
        self._aid, self._eid = aid, eid
        self._f = open(self.path, "wb")
        try:
            self._w = w = Writer(Counted(self._f), chunk_size=chunk_size,
                                 compression=CompressionType.ZSTD)
            w.start(profile="", library=f"se3sync {__version__}")
            self._ch = {}
            self._schema_ids = {}
            # channel id → (topic, message encoding, schema id); schema id → (name, encoding,
            # bytes): what a `sink` needs to describe the channels elsewhere (cosim/log/live.py)
            self.channels, self.schemas = {}, {}
            for topic in ("/tf", "/edges", "/agents", "/lyapunov", "/jumps"):
                self._channel(topic)
            meta = {
                "scenario": scenario.text,
                "scenario_name": scenario.name,
                "scenario_path": str(scenario.path),
                "overrides": json.dumps(list(scenario.overrides)),
                "design": json.dumps(scenario.design.as_dict()),
                "se3sync_version": __version__,
                "time_base": "simulated",
                "time_unit": "ns",
                "controller": controller,
                "step": repr(float(scenario.step)),
                "log_rate": repr(float(scenario.log_rate)),
                "n_agents": str(scenario.graph.n),
                "edges": json.dumps([list(e) for e in scenario.graph.edge_list]),
                "created_unix": repr(time.time()),
                "masses": json.dumps(np.asarray(scenario.masses, float).tolist()),
                "inertias": json.dumps(np.asarray(scenario.inertias, float).tolist()),
                "scene_rate": repr(float(scene_rate)),
                "log_encoding": encoding,
            }
            if agent_ids is not None or edge_ids is not None:
                meta["agent_ids"] = json.dumps(aid)
                meta["edge_ids"] = json.dumps(eid)
            if extra_metadata:
                meta.update({str(k): str(v) for k, v in extra_metadata.items()})
            w.add_metadata("se3sync", meta)
            if model_description:
                data = model_description.encode() if isinstance(model_description, str) else bytes(model_description)
                w.add_attachment(create_time=time.time_ns(), log_time=0,
                                 name="modelDescription.xml", media_type="application/xml",
                                 data=data)
            self._layout = fg.layout_json(aid, eid, encoding)
            w.add_attachment(create_time=time.time_ns(), log_time=0, name="foxglove_layout.json",
                             media_type="application/json", data=self._layout.encode())
            self._scene = None
            if scene_rate and scene_rate > 0:
                self._scene = fg.SceneBuilder(
                    [list(e) for e in scenario.graph.edge_list], np.asarray(scenario.inertias, float),
                    np.asarray(scenario.masses, float),
                    trail_len=max(1, int(round(trail_seconds * min(trail_rate, scene_rate)))),
                    agent_ids=aid, edge_ids=eid)
                self._channel(fg.SCENE)
                for i in aid:
                    self._channel(f"{fg.TRAIL_PREFIX}{i}")
            if encoding == "cdr":
                self._cdr = _CdrRecords(aid, eid, scenario.graph.edge_list)
                self._cdr_scene = None if self._scene is None else fg.CdrScene(
                    self._scene, np.asarray(scenario.inertias, float),
                    np.asarray(scenario.masses, float))
        except BaseException:
            self._f.close()
            raise
        self._seq = 0
        self._closed = False
        self._agent_names = [f"agent_{i}" for i in aid]
        self._tf_pre = [f'{{"timestamp":%s,"parent_frame_id":"world","child_frame_id":"agent_{i}",'
                        for i in aid]
        self._edge_pre = [f'{{"edge":{eid[k]},"positive":{aid[a - 1]},"negative":{aid[b - 1]},'
                          for k, (a, b) in enumerate(scenario.graph.edge_list)]
        # ``sink``: an object with the appender's add(channel_id, log_time, data, sequence),
        # add_rows(channel_ids, log_time, rows, sequence) and close() that takes the messages
        # instead of the file (the live view encodes its records with this class)
        self._app = (sink if sink is not None else MessageAppender(w) if encoding == "json"
                     else MessageAppender(w, CDR_ZSTD_LEVEL, frame_checksum=True))
        self._add = self._app.add
        self.counts = {}
        self.orjson = True  # record_fast may use orjson (False: the bytes of `record`)
        self._scene_dt = round(1e9 / scene_rate) if scene_rate and scene_rate > 0 else 0
        self._next_scene = 0
        self._trail_dt = round(1e9 / trail_rate) if trail_rate and trail_rate > 0 else 0
        self._next_trail = 0
        self._jump_until = [-1] * scenario.graph.M  # edge k is drawn as jumping until this t_ns
        self._trail_topics = [f"{fg.TRAIL_PREFIX}{i}" for i in aid]
        self._trail_ids = [self._ch.get(t) for t in self._trail_topics]
        self._layout_path = None
        if layout_path == "auto":
            p = Path(self.path)
            layout_path = p.with_name(p.name[:-5] if p.name.endswith(".mcap") else p.name)
            layout_path = layout_path.with_name(layout_path.name + ".layout.json")
        if layout_path is not None:
            self._layout_path = Path(layout_path)

    def _register(self, topic, name, schema_encoding, data, message_encoding):
        """The channel ``topic`` on the schema ``name``, registered once per name (``data()``
        gives its bytes)."""
        sid = self._schema_ids.get(name)
        if sid is None:
            b = data()
            sid = self._schema_ids[name] = self._w.register_schema(
                name=name, encoding=schema_encoding, data=b)
            self.schemas[sid] = (name, schema_encoding, b)
        cid = self._ch[topic] = self._w.register_channel(
            topic=topic, message_encoding=message_encoding, schema_id=sid)
        self.channels[cid] = (topic, message_encoding, sid)

    def _channel(self, topic):
        if topic in self._ch:
            return self._ch[topic]
        trail = topic.startswith(fg.TRAIL_PREFIX)
        name = cdr.SCHEMA.get("trail" if trail else topic) if self.encoding == "cdr" else None
        if name is not None:   # a CDR log's per-record channels; /jumps and /link/stats are JSON
            self._register(topic, name, "ros2msg", lambda: cdr.schema_text(name).encode(), "cdr")
            return self._ch[topic]
        fox = FOXGLOVE.get(topic) or ("PosesInFrame" if trail else None)
        if fox is not None:  # Foxglove's own schema, name and content as published
            name, data = f"foxglove.{fox}", lambda: fg.schema_bytes(fox)
        else:
            name, data = SCHEMAS[topic]["title"], lambda: json.dumps(SCHEMAS[topic]).encode()
        self._register(topic, name, "jsonschema", data, "json")
        return self._ch[topic]

    def add_channel(self, topic: str, schema: dict) -> None:
        """A channel of another kind of JSON message (``schema``: a JSON schema with a
        ``title``), for `message`."""
        if topic not in self._ch:
            self._register(topic, schema["title"], "jsonschema",
                           lambda: json.dumps(schema).encode(), "json")

    def message(self, topic: str, t_ns: int, obj: dict) -> None:
        """One JSON message (``obj`` plus its timestamp) on a channel made by `add_channel`."""
        ts = {"sec": t_ns // 1_000_000_000, "nsec": t_ns % 1_000_000_000}
        self._msg(topic, t_ns, _dumps(dict(obj, timestamp=ts), default=float))

    def _msg(self, topic, t_ns, payload: str):
        self._seq += 1
        self._add(self._ch[topic], t_ns, payload.encode(), self._seq)
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def record(self, t_ns: int, S, u, theta, mu, jumped, rot_err, pos_err, U, quat, V, kX_U):
        """One decimated record: /tf, /edges, /agents, /lyapunov at simulated time t_ns."""
        if self._cdr is not None:
            return self.record_block([t_ns], *(np.asarray(x)[None] for x in (
                S, u, theta, mu, jumped, rot_err, pos_err, U, quat, V, kX_U)))
        ts = f'{{"sec":{t_ns // 1_000_000_000},"nsec":{t_ns % 1_000_000_000}}}'
        Sl = S.tolist()
        ql = quat.tolist()
        ul = u.tolist()
        r = _r
        tf = ",".join(
            pre % ts + f'"translation":{{"x":{r(s[0])},"y":{r(s[1])},"z":{r(s[2])}}},'
            f'"rotation":{{"x":{r(q[0])},"y":{r(q[1])},"z":{r(q[2])},"w":{r(q[3])}}}}}'
            for pre, s, q in zip(self._tf_pre, Sl, ql))
        self._msg("/tf", t_ns, f'{{"transforms":[{tf}]}}')
        th, mul, jl, rl, pl, Ul = theta.tolist(), mu.tolist(), jumped.tolist(), rot_err.tolist(), \
            pos_err.tolist(), U.tolist()
        ed = ",".join(
            f'{pre}"theta":{r(a)},"mu_U":{r(b)},"rot_err":{r(c)},"pos_err":{r(d)},"U":{r(e)},'
            f'"mode":"{"jump" if j else "flow"}"}}'
            for pre, a, b, c, d, e, j in zip(self._edge_pre, th, mul, rl, pl, Ul, jl))
        self._msg("/edges", t_ns, f'{{"timestamp":{ts},"edges":[{ed}]}}')
        ag = ",".join(
            f'{{"agent":{i},"omega":[{r(s[12])},{r(s[13])},{r(s[14])}],'
            f'"v":[{r(s[15])},{r(s[16])},{r(s[17])}],'
            f'"torque":[{r(w[0])},{r(w[1])},{r(w[2])}],"force":[{r(w[3])},{r(w[4])},{r(w[5])}]}}'
            for i, s, w in zip(self._aid, Sl, ul))
        self._msg("/agents", t_ns, f'{{"timestamp":{ts},"agents":[{ag}]}}')
        self._msg("/lyapunov", t_ns, f'{{"timestamp":{ts},"V":{r(V)},"kX_U":{r(kX_U)}}}')
        if self._scene is not None and t_ns >= self._next_scene:
            self._next_scene = t_ns + self._scene_dt
            self.scene(t_ns, ts, S, quat, rot_err, jumped)

    def scene(self, t_ns, ts, S, quat, rot_err, jumped):
        """The /scene and /trail messages at t_ns (called by record at scene_rate). An edge is
        drawn as jumping if it jumped at this record or within one scene period before it."""
        ju = self._jump_until
        jl = jumped.tolist()
        jumping = [j or t_ns <= u for j, u in zip(jl, ju)]
        keep = t_ns >= self._next_trail
        if self._cdr is not None:
            cs = self._cdr_scene
            self._msg_bytes("/scene", t_ns, cs.scene(t_ns, S, rot_err, jumping))
            if keep:
                self._next_trail = t_ns + self._trail_dt
            rows = cs.trails(t_ns, S, quat, keep)
            self._app.add_rows(self._trail_ids, t_ns, rows, self._seq + 1)
            self._seq += len(rows)
            counts = self.counts
            for topic in self._trail_topics:
                counts[topic] = counts.get(topic, 0) + 1
            return
        self._msg("/scene", t_ns, self._scene.scene(ts, S, rot_err, jumping))
        if keep:
            self._next_trail = t_ns + self._trail_dt
        # one message per agent: `_msg` inlined (at N = 1000 the per-call cost shows)
        add, seq, counts, cids = self._add, self._seq, self.counts, self._trail_ids
        for topic, cid, m in zip(self._trail_topics, cids,
                                 self._scene.trails(ts, S, quat, keep)):
            seq += 1
            add(cid, t_ns, m.encode(), seq)
            counts[topic] = counts.get(topic, 0) + 1
        self._seq = seq

    def _templates(self):
        """%-format templates of the /tf, /edges (all edges flowing) and /agents messages with
        the timestamp as @TS@: one C-level format call per message instead of one Python
        call per value. %r of a Python float is float.__repr__, as in `record`."""
        tf = ",".join(
            f'{{"timestamp":@TS@,"parent_frame_id":"world","child_frame_id":"agent_{i}",'
            '"translation":{"x":%r,"y":%r,"z":%r},"rotation":{"x":%r,"y":%r,"z":%r,"w":%r}}'
            for i in self._aid)
        ed = ",".join(
            pre.replace("%", "%%") + '"theta":%r,"mu_U":%r,"rot_err":%r,"pos_err":%r,"U":%r,'
            '"mode":"flow"}' for pre in self._edge_pre)
        ag = ",".join(
            f'{{"agent":{i},"omega":[%r,%r,%r],"v":[%r,%r,%r],'
            '"torque":[%r,%r,%r],"force":[%r,%r,%r]}' for i in self._aid)
        # /edges of a record with a jump: each edge's mode is a sixth slot
        edj = ed.replace('"mode":"flow"}', '"mode":"%s"}')
        self._tpl = (f'{{"transforms":[{tf}]}}', f'{{"timestamp":@TS@,"edges":[{ed}]}}',
                     f'{{"timestamp":@TS@,"agents":[{ag}]}}', f'{{"timestamp":@TS@,"edges":[{edj}]}}')
        return self._tpl

    def _bytes_templates(self):
        tb = getattr(self, "_tpl_b", None)
        if tb is None:
            tpl = getattr(self, "_tpl", None) or self._templates()
            tb = self._tpl_b = tuple(t.replace("%r", "%s").encode() for t in tpl)
        return tb

    def _scene_due(self, t_ns, ts, S, quat, rot_err, jumped):
        """The /scene and /trail part of `record`, for the fast encoders."""
        if self._scene is not None and t_ns >= self._next_scene:
            self._next_scene = t_ns + self._scene_dt
            self.scene(t_ns, ts, S, quat, rot_err, jumped)

    def _msg_bytes(self, topic, t_ns, payload: bytes):
        self._seq += 1
        self._add(self._ch[topic], t_ns, payload, self._seq)
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def record_fast(self, t_ns: int, S, u, theta, mu, jumped, rot_err, pos_err, U, quat, V, kX_U):
        """`record` with the same messages, encoded through templates (the compiled loop's
        writer calls it). With orjson installed (extra "fastlog") and ``self.orjson`` true,
        the numbers are formatted by orjson's shortest round-trip printer: the messages decode
        to the same values bit for bit, but the text of some numbers differs (0.00001 for
        1e-05); without it they are the same bytes as `record`'s. A record with a jump in it
        or a non-finite value goes through `record` (rare)."""
        if self._cdr is not None:
            return self.record(t_ns, S, u, theta, mu, jumped, rot_err, pos_err, U, quat, V, kX_U)
        tf_v = np.concatenate((S[:, layout.P], quat), axis=1)
        ed_v = np.stack((theta, mu, rot_err, pos_err, U), axis=1)
        ag_v = np.concatenate((S[:, layout.XI], u), axis=1)
        if not (np.isfinite(tf_v).all() and np.isfinite(ed_v).all() and np.isfinite(ag_v).all()):
            return self.record(t_ns, S, u, theta, mu, jumped, rot_err, pos_err, U, quat, V,
                               kX_U)
        tpl = getattr(self, "_tpl", None) or self._templates()
        ts = f'{{"sec":{t_ns // 1_000_000_000},"nsec":{t_ns % 1_000_000_000}}}'
        jl = jumped.tolist() if jumped.any() else None
        if self.orjson and _orjson is not None:
            # orjson prints a whole array in C (~10× faster than float.__repr__ per value);
            # the pieces go into byte templates with %s
            tb = self._bytes_templates()
            tsb = ts.encode()
            opt = _orjson.OPT_SERIALIZE_NUMPY
            for topic, t, v in (("/tf", tb[0], tf_v), ("/edges", tb[1], ed_v),
                                ("/agents", tb[2], ag_v)):
                vals = _orjson.dumps(np.ascontiguousarray(v).ravel(), option=opt)[1:-1].split(b",")
                if topic == "/edges" and jl is not None:
                    t, vals = tb[3], _with_modes(vals, jl, b"flow", b"jump")
                self._msg_bytes(topic, t_ns, t.replace(b"@TS@", tsb) % tuple(vals))
            self._msg("/lyapunov", t_ns, f'{{"timestamp":{ts},"V":{_r(V)},"kX_U":{_r(kX_U)}}}')
            self._scene_due(t_ns, ts, S, quat, rot_err, jumped)
            return
        ed = ed_v.ravel().tolist()
        ed_msg = (tpl[1] % tuple(ed) if jl is None
                  else tpl[3] % tuple(_with_modes(ed, jl, "flow", "jump")))
        self._msg("/tf", t_ns, tpl[0].replace("@TS@", ts) % tuple(tf_v.ravel().tolist()))
        self._msg("/edges", t_ns, ed_msg.replace("@TS@", ts))
        self._msg("/agents", t_ns, tpl[2].replace("@TS@", ts) % tuple(ag_v.ravel().tolist()))
        self._msg("/lyapunov", t_ns, f'{{"timestamp":{ts},"V":{_r(V)},"kX_U":{_r(kX_U)}}}')
        self._scene_due(t_ns, ts, S, quat, rot_err, jumped)

    def jump(self, t_ns: int, t: float, edge: int, theta_before: float, theta_after: float, mu: float):
        if 1 <= edge <= len(self._jump_until):
            self._jump_until[edge - 1] = t_ns + self._scene_dt
            edge = self._eid[edge - 1]
        ts = {"sec": t_ns // 1_000_000_000, "nsec": t_ns % 1_000_000_000}
        self._msg("/jumps", t_ns, _dumps({"timestamp": ts, "t": t, "edge": edge,
                                          "theta_before": theta_before,
                                          "theta_after": theta_after, "mu": mu}))

    def record_block(self, t_ns, S, u, theta, mu, jumped, rot_err, pos_err, U, quat, V, kX_U,
                     finite_only: bool = True):
        """`record_fast` for R consecutive records at once (t_ns a list of R ints, every other
        argument stacked on a first axis of length R): one orjson call per channel for the
        whole block. Rows with a non-finite value go through `record`, unless ``finite_only``
        is false: orjson writes them as `record` does, null (an agent's log has μ = NaN on
        every edge it does not own, at every record)."""
        R = len(t_ns)
        if R == 0:
            return
        if self._cdr is not None:
            return self._record_cdr(t_ns, S, u, theta, mu, jumped, rot_err, pos_err, U, quat, V,
                                    kX_U)
        if not (self.orjson and _orjson is not None):
            for r in range(R):
                self.record_fast(t_ns[r], S[r], u[r], theta[r], mu[r], jumped[r], rot_err[r],
                                 pos_err[r], U[r], quat[r], V[r], kX_U[r])
            return
        tf_v = np.concatenate((S[:, :, layout.P], quat), axis=2)
        ed_v = np.stack((theta, mu, rot_err, pos_err, U), axis=2)
        ag_v = np.concatenate((S[:, :, layout.XI], u), axis=2)
        plain = np.ones(R, np.bool_)
        if finite_only:
            for v in (tf_v, ed_v, ag_v):
                plain &= np.isfinite(v).all(axis=(1, 2))
        any_jump = jumped.any(axis=1).tolist()
        tb = self._bytes_templates()
        opt = _orjson.OPT_SERIALIZE_NUMPY
        chans = []
        for topic, t, v in (("/tf", tb[0], tf_v), ("/edges", tb[1], ed_v),
                            ("/agents", tb[2], ag_v)):
            parts = _orjson.dumps(np.ascontiguousarray(v).ravel(), option=opt)[1:-1].split(b",")
            chans.append((topic, t, parts, v.shape[1] * v.shape[2]))
        msg_b, msg, r_ = self._msg_bytes, self._msg, _r
        for r in range(R):
            tn = t_ns[r]
            if not plain[r]:
                self.record(tn, S[r], u[r], theta[r], mu[r], jumped[r], rot_err[r], pos_err[r],
                            U[r], quat[r], V[r], kX_U[r])
                continue
            ts = f'{{"sec":{tn // 1_000_000_000},"nsec":{tn % 1_000_000_000}}}'
            tsb = ts.encode()
            for topic, t, parts, k in chans:
                vals = parts[r * k:(r + 1) * k]
                if any_jump[r] and topic == "/edges":
                    t, vals = tb[3], _with_modes(vals, jumped[r].tolist(), b"flow", b"jump")
                msg_b(topic, tn, t.replace(b"@TS@", tsb) % tuple(vals))
            msg("/lyapunov", tn, f'{{"timestamp":{ts},"V":{r_(V[r])},"kX_U":{r_(kX_U[r])}}}')
            self._scene_due(tn, ts, S[r], quat[r], rot_err[r], jumped[r])

    def _record_cdr(self, t_ns, S, u, theta, mu, jumped, rot_err, pos_err, U, quat, V, kX_U):
        """`record_block` in CDR: each channel's R messages filled at once (`_CdrRecords`)."""
        c = self._cdr
        S, quat = np.asarray(S, np.float64), np.asarray(quat, np.float64)
        rows = {"/tf": c.tf.fill(np.concatenate((S[:, :, layout.P], quat), axis=2)
                                 .reshape(len(t_ns), -1), t_ns),
                "/edges": c.edges.fill(np.stack((theta, mu, rot_err, pos_err, U), axis=2)
                                       .reshape(len(t_ns), -1), t_ns,
                                       np.where(jumped, cdr.MODE["jump"], cdr.MODE["flow"])),
                "/agents": c.agents.fill(np.concatenate((S[:, :, layout.XI], u), axis=2)
                                         .reshape(len(t_ns), -1), t_ns),
                "/lyapunov": c.lyapunov.fill(np.stack((V, kX_U), axis=1), t_ns)}
        msg_b = self._msg_bytes
        for r, tn in enumerate(t_ns):
            for topic in ("/tf", "/edges", "/agents", "/lyapunov"):
                msg_b(topic, tn, rows[topic][r])   # a row of bytes: copied into the chunk
            if self._scene is not None and tn >= self._next_scene:
                self._next_scene = tn + self._scene_dt
                self.scene(tn, None, S[r], quat[r], rot_err[r], jumped[r])

    _JUMP_TPL = ('{"timestamp": {"sec": %d, "nsec": %d}, "t": %r, "edge": %d, '
                 '"theta_before": %r, "theta_after": %r, "mu": %r}')

    def jump_fast(self, t_ns: int, t: float, edge: int, theta_before: float,
                  theta_after: float, mu: float):
        """`jump` with the same message byte for byte (json.dumps's default separators and
        float repr) through one template; non-finite values go through `jump`."""
        if not (math.isfinite(t) and math.isfinite(theta_before) and math.isfinite(theta_after)
                and math.isfinite(mu)):
            return self.jump(t_ns, t, edge, theta_before, theta_after, mu)
        if 1 <= edge <= len(self._jump_until):  # as `jump`: the scene draws the edge jumping
            self._jump_until[edge - 1] = t_ns + self._scene_dt
            edge = self._eid[edge - 1]
        self._msg("/jumps", t_ns, self._JUMP_TPL % (t_ns // 1_000_000_000, t_ns % 1_000_000_000,
                                                    t, edge, theta_before, theta_after, mu))

    def link_stats(self, t_ns: int, stats: dict):
        self._channel("/link/stats")
        ts = {"sec": t_ns // 1_000_000_000, "nsec": t_ns % 1_000_000_000}
        self._msg("/link/stats", t_ns, _dumps(dict(stats, timestamp=ts), default=float))

    def outcome(self, summary: dict) -> None:
        """A metadata record ``se3sync.outcome`` with how the run ended (steps, interrupted,
        stopped_during, diverged, n_jumps, jump_bound_exceeded), written before `close`."""
        self._w.add_metadata("se3sync.outcome", outcome_metadata(summary))

    def close(self, discard: bool = False):
        """Finishes the file (and writes the layout beside it); ``discard=True`` removes the
        log instead: a run that failed leaves nothing that looks whole. A log that cannot be
        finished (OSError, e.g. a full disk) is removed too, and the error raised."""
        if self._closed:
            return
        self._closed = True
        err = None
        try:
            if not discard:
                self._w.finish()
        except OSError as exc:  # e.g. no space left: a log that cannot be finished is removed
            err, discard = exc, True
        finally:
            try:
                self._app.close()
            finally:
                try:
                    self._f.close()   # flushes the buffer: fails again on a full disk
                except OSError as exc:
                    if not discard:
                        err, discard = exc, True
        if discard:
            try:
                os.unlink(self.path)
            except OSError:
                pass
            if err is not None:
                raise err
            return
        if self._layout_path is not None:
            with atomic_path(self._layout_path) as tmp:
                Path(tmp).write_text(self._layout, encoding="utf-8")

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
