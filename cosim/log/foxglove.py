"""Foxglove 3D messages for the MCAP log: bodies, graph edges, trails, and a layout.

The messages are JSON on ``jsonschema`` channels whose schema name and content are Foxglove's
published ones (``foxglove_schemas/``, copied unmodified from foxglove/foxglove-sdk). JSON rather
than Foxglove's protobuf schemas: the rest of the log is JSON already, the writer builds
messages as strings without an extra dependency, and Foxglove reads both.

- ``/scene``          foxglove.SceneUpdate: entity ``agent_i`` (frame ``agent_i``, frame-locked)
  with a box of agent i's inertia and its x/y/z axes; entity ``edge_k`` (frame ``world``) with
  one line from p_i to p_j coloured by ‖I − R̄_k‖_F, drawn thick and white with a label while
  edge k jumps.
- ``/trail/agent_i``  foxglove.PosesInFrame: agent i's last poses (its recent trail).

The builders are string templates: every constant part is formatted once per logger and each
message only inserts numbers (logging cost, see benchmarks/bench_see_log.py).
"""
from __future__ import annotations

import json
import math
from functools import lru_cache
from pathlib import Path

import numpy as np

from . import cdr

__all__ = ["SCENE", "TRAIL_PREFIX", "schema_bytes", "box_size", "error_colors", "error_color",
           "SceneBuilder", "CdrScene",
           "layout", "ERR_LO", "ERR_HI"]

SCENE = "/scene"
TRAIL_PREFIX = "/trail/agent_"
_SCHEMA_DIR = Path(__file__).with_name("foxglove_schemas")

# The edge colour scale: ‖I − R̄‖_F on a log scale from ERR_LO (green) to ERR_HI = 2√2, the
# largest value (R̄ a rotation by π), red. Log, because the errors fall exponentially.
ERR_LO = 1e-4
ERR_HI = 2.0 * math.sqrt(2.0)
_LOG_SPAN = math.log10(ERR_HI / ERR_LO)


@lru_cache(maxsize=None)
def schema_bytes(name: str) -> bytes:
    """Foxglove's JSON schema for ``foxglove.<name>`` (e.g. "SceneUpdate"), as published."""
    return (_SCHEMA_DIR / f"{name}.json").read_bytes()


def box_size(J, m) -> np.ndarray:
    """Edge lengths (a, b, c) of the uniform solid box of mass m whose inertia about its centre
    has the diagonal of J: J = m/12 diag(b²+c², a²+c², a²+b²), so a² = 6(J_y + J_z − J_x)/m, ….
    A non-box J (triangle inequality violated) gets a thin slab (length clamped to 1 cm)."""
    d = np.diag(np.asarray(J, float))
    s = d.sum()
    sq = 6.0 * (s - 2.0 * d) / float(m)
    return np.sqrt(np.maximum(sq, 1e-4))


def error_colors(err) -> np.ndarray:
    """(M, 3) array of (r, g, b) per edge error: x = log10(err/ERR_LO)/log10(ERR_HI/ERR_LO)
    clipped to [0, 1]; r = x, g = 1 − x, b = 0.2 (green at consensus, red at a rotation by π;
    NaN is red).

    The one computation of an edge's colour: the JSON scene (`SceneBuilder`) and the CDR scene
    (`CdrScene`) both encode what this returns, so the two logs carry the same bits. Two
    computations would not: numpy's vectorised log10 (SIMD, chosen by the CPU at run time)
    and the C library's `math.log10` differ by an ulp on some values on some CPUs
    (docs/testing.md)."""
    e = np.array(err, dtype=np.float64, ndmin=1)   # a fresh contiguous copy: one numpy loop
    with np.errstate(divide="ignore", invalid="ignore"):
        x = np.minimum(1.0, np.log10(e / ERR_LO) / _LOG_SPAN)
    x = np.where(e > ERR_LO, x, np.where(np.isnan(e), 1.0, 0.0))
    return np.stack((x, 1.0 - x, np.full_like(x, 0.2)), axis=1)


def error_color(err: float) -> tuple[float, float, float]:
    """`error_colors` of one value, as a tuple (for drawing one edge; the logs use
    `error_colors` of all edges at once)."""
    r, g, b = error_colors(float(err))[0].tolist()
    return r, g, b


def _f(x: float) -> str:
    s = float.__repr__(float(x))
    return s if s[-1].isdigit() else "0.0"


_EMPTY = '"arrows":[],"cubes":[],"spheres":[],"cylinders":[],"lines":[],"triangles":[],' \
         '"texts":[],"models":[]'
_KEYS = ("arrows", "cubes", "spheres", "cylinders", "lines", "triangles", "texts", "models")
_IDQ = '"orientation":{"x":0,"y":0,"z":0,"w":1}'
_C = 0.7071067811865476
# an arrow points along +x at identity: y axis = +90° about z, z axis = −90° about y
_AXES = ((1.0, 0.2, 0.2, (0, 0, 0, 1)), (0.2, 1.0, 0.2, (0, 0, _C, _C)),
         (0.2, 0.4, 1.0, (0, -_C, 0, _C)))


_POSE_TPL = '{"position":{"x":%r,"y":%r,"z":%r},"orientation":{"x":%r,"y":%r,"z":%r,"w":%r}}'


def _entity(ts: str, frame: str, eid: str, frame_locked: bool, parts: dict) -> str:
    body = ",".join(f'"{k}":[{",".join(parts.get(k, ()))}]' for k in _KEYS)
    return (f'{{"timestamp":{ts},"frame_id":"{frame}","id":"{eid}",'
            f'"lifetime":{{"sec":0,"nsec":0}},"frame_locked":{"true" if frame_locked else "false"},'
            f'"metadata":[],{body}}}')


class SceneBuilder:
    """Builds the /scene and /trail messages of one run.

    ``SceneBuilder(edges, inertias, masses, trail_len=100)``: edges (M, 2) 1-based agent
    numbers (positive, negative). ``scene(ts, S, rot_err, jumping)`` returns the SceneUpdate
    JSON; ``trails(ts, S, quat)`` appends the current poses and returns one PosesInFrame JSON per
    agent. ts is the JSON time object ``{"sec":…,"nsec":…}``; S (N, ≥3) has p_i in S[i, :3];
    quat (N, 4) is (x, y, z, w); jumping a sequence of M booleans.
    """

    def __init__(self, edges, inertias, masses, trail_len: int = 100, agent_ids=None,
                 edge_ids=None):
        self.edges = [(int(a), int(b)) for a, b in edges]
        N = len(masses)
        self.agent_ids = list(range(1, N + 1)) if agent_ids is None else list(agent_ids)
        self.edge_ids = list(range(1, len(self.edges) + 1)) if edge_ids is None else list(edge_ids)
        self.N, self.M = N, len(self.edges)
        self.trail_len = int(trail_len)
        self._agents = []
        for i in range(N):
            a, b, c = box_size(inertias[i], masses[i])
            L = 0.75 * float(max(a, b, c))  # axis arrows reach beyond the box
            cube = (f'{{"pose":{{"position":{{"x":0,"y":0,"z":0}},{_IDQ}}},'
                    f'"size":{{"x":{_f(a)},"y":{_f(b)},"z":{_f(c)}}},'
                    f'"color":{{"r":0.55,"g":0.6,"b":0.7,"a":0.85}}}}')
            arrows = [f'{{"pose":{{"position":{{"x":0,"y":0,"z":0}},"orientation":'
                      f'{{"x":{q[0]},"y":{q[1]},"z":{q[2]},"w":{q[3]}}}}},'
                      f'"shaft_length":{_f(0.8 * L)},"shaft_diameter":{_f(0.04 * L)},'
                      f'"head_length":{_f(0.2 * L)},"head_diameter":{_f(0.1 * L)},'
                      f'"color":{{"r":{r},"g":{g},"b":{bb},"a":1}}}}'
                      for r, g, bb, q in _AXES]
            # the entity is constant apart from its time stamp: split the template there
            name = f"agent_{self.agent_ids[i]}"
            pre, post = _entity("\0", name, name, True,
                                {"cubes": [cube], "arrows": arrows}).split("\0")
            self._agents.append((pre, post))
        # edge line thickness: a tenth of the largest body
        self._scale = 0.1 * max(float(max(box_size(inertias[i], masses[i]))) for i in range(N))
        self._trail = [[] for _ in range(N)]

    def edge_line(self, k: int, p_i, p_j, color, jumping: bool) -> str:
        """The LINE_LIST primitive of edge k (0-based) from p_i to p_j, in ``color`` (r, g, b:
        a row of `error_colors`), white when jumping."""
        r, g, b = (1.0, 1.0, 1.0) if jumping else color
        th = 3 * self._scale if jumping else self._scale
        return (f'{{"type":2,"pose":{{"position":{{"x":0,"y":0,"z":0}},{_IDQ}}},'
                f'"thickness":{_f(th)},"scale_invariant":false,'
                f'"points":[{{"x":{_f(p_i[0])},"y":{_f(p_i[1])},"z":{_f(p_i[2])}}},'
                f'{{"x":{_f(p_j[0])},"y":{_f(p_j[1])},"z":{_f(p_j[2])}}}],'
                f'"color":{{"r":{_f(r)},"g":{_f(g)},"b":{_f(b)},"a":1}},"colors":[],"indices":[]}}')

    def _edge_templates(self):
        """Per edge, its entity around the time stamp and the line (what `_entity` writes for a
        flowing edge), and the line's %-template: one C-level format per edge at scene time."""
        self._edge_tpl = []
        for k in range(self.M):
            pre, mid, post = _entity("\0", "world", f"edge_{self.edge_ids[k]}", False,
                                     {"lines": ["\1"]}).replace("\1", "\0").split("\0")
            self._edge_tpl.append((pre, mid, post))
        self._line_tpl = ('{"type":2,"pose":{"position":{"x":0,"y":0,"z":0},' + _IDQ + '},'
                          '"thickness":' + _f(self._scale) + ',"scale_invariant":false,'
                          '"points":[{"x":%r,"y":%r,"z":%r},{"x":%r,"y":%r,"z":%r}],'
                          '"color":{"r":%r,"g":%r,"b":%r,"a":1},"colors":[],"indices":[]}')
        return self._edge_tpl

    def scene(self, ts: str, S, rot_err, jumping) -> str:
        Pa = np.asarray(S)[:, :3]
        P = Pa.tolist()
        ents = [pre + ts + post for pre, post in self._agents]
        cols = error_colors(rot_err).tolist()   # as CdrScene: the same function, the same bits
        # every value finite: templates with %r (float.__repr__, the bytes of _f); else _f's
        # replacement of a non-finite value by 0.0 on the path below
        fast = bool(np.isfinite(Pa).all())
        if fast:
            etpl = getattr(self, "_edge_tpl", None) or self._edge_templates()
            ltpl = self._line_tpl
        for k, (a, b) in enumerate(self.edges):
            pi, pj = P[a - 1], P[b - 1]
            if fast and not jumping[k]:
                pre, mid, post = etpl[k]
                x = cols[k]
                ents.append(pre + ts + mid + ltpl % (pi[0], pi[1], pi[2], pj[0], pj[1], pj[2],
                                                     x[0], x[1], x[2]) + post)
                continue
            parts = {"lines": [self.edge_line(k, pi, pj, cols[k], bool(jumping[k]))]}
            if jumping[k]:
                mid = [(x + y) / 2 for x, y in zip(pi, pj)]
                parts["texts"] = [f'{{"pose":{{"position":{{"x":{_f(mid[0])},"y":{_f(mid[1])},'
                                  f'"z":{_f(mid[2])}}},{_IDQ}}},"billboard":true,"font_size":14,'
                                  f'"scale_invariant":true,"color":{{"r":1,"g":1,"b":1,"a":1}},'
                                  f'"text":"θ_{self.edge_ids[k]} jumps"}}']
            ents.append(_entity(ts, "world", f"edge_{self.edge_ids[k]}", False, parts))
        return f'{{"deletions":[],"entities":[{",".join(ents)}]}}'

    def trails(self, ts: str, S, quat, keep: bool = True) -> list[str]:
        """One PosesInFrame per agent: the kept poses (at most trail_len) and the current one,
        which is kept too when ``keep`` (the trail is thinned to the caller's trail rate)."""
        Pa, Qa = np.asarray(S)[:, :3], np.asarray(quat)
        n = self.trail_len
        if bool(np.isfinite(Pa).all() and np.isfinite(Qa).all()):
            # every pose in one format call (%r is _f's bytes for finite values), split after
            tpl = getattr(self, "_poses_tpl", None)
            if tpl is None:
                tpl = self._poses_tpl = "\0".join([_POSE_TPL] * self.N)
            curs = (tpl % tuple(np.concatenate((Pa, Qa), axis=1).ravel().tolist())).split("\0")
        else:
            curs = [f'{{"position":{{"x":{_f(p[0])},"y":{_f(p[1])},"z":{_f(p[2])}}},'
                    f'"orientation":{{"x":{_f(q[0])},"y":{_f(q[1])},"z":{_f(q[2])},'
                    f'"w":{_f(q[3])}}}}}' for p, q in zip(Pa.tolist(), Qa.tolist())]
        joined = getattr(self, "_joined", None)
        if joined is None:  # each trail's kept poses, joined once per kept pose, not per message
            joined = self._joined = [",".join(tr) for tr in self._trail]
        pre = f'{{"timestamp":{ts},"frame_id":"world","poses":['
        if keep:
            for k, (tr, cur) in enumerate(zip(self._trail, curs)):
                tr.append(cur)
                if len(tr) > n:
                    del tr[0]
                joined[k] = ",".join(tr)
            return [pre + j + "]}" for j in joined]
        return [pre + (j + "," + cur if j else cur) + "]}" for j, cur in zip(joined, curs)]


_ID_POSE = {"position": {"x": 0.0, "y": 0.0, "z": 0.0},
            "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}
_NO_PARTS = {k: [] for k in _KEYS}


class CdrScene:
    """The /scene and /trail messages of `SceneBuilder` in ROS 2 CDR (cosim/log/cdr.py), for a
    log written with ``encoding="cdr"``: the same bodies, edges and trails. One difference, so
    that every scene of a run has the same shape: each edge always carries its "θ_k jumps"
    label, with font size 0 and alpha 0 while the edge flows."""

    def __init__(self, sb: SceneBuilder, inertias, masses):
        self.sb = sb
        N, M = sb.N, sb.M
        ai = np.array([a for a, _ in sb.edges], np.int64) - 1 if M else np.zeros(0, np.int64)
        bi = np.array([b for _, b in sb.edges], np.int64) - 1 if M else np.zeros(0, np.int64)
        self._a, self._b = ai, bi
        agents = []
        for i in range(N):
            a, b, c = (float(v) for v in box_size(inertias[i], masses[i]))
            L = 0.75 * max(a, b, c)
            name = f"agent_{sb.agent_ids[i]}"
            cube = {"pose": _ID_POSE, "size": {"x": a, "y": b, "z": c},
                    "color": {"r": 0.55, "g": 0.6, "b": 0.7, "a": 0.85}}
            arrows = [{"pose": {"position": _ID_POSE["position"],
                                "orientation": dict(zip("xyzw", map(float, q)))},
                       "shaft_length": 0.8 * L, "shaft_diameter": 0.04 * L,
                       "head_length": 0.2 * L, "head_diameter": 0.1 * L,
                       "color": {"r": r, "g": g, "b": bb, "a": 1.0}} for r, g, bb, q in _AXES]
            agents.append((name, cube, arrows))

        def build(f, t, mode):
            ents = [dict(_NO_PARTS, timestamp=t(), frame_id=name, id=name,
                         lifetime={"sec": 0, "nanosec": 0}, frame_locked=True, metadata=[],
                         cubes=[cube], arrows=arrows) for name, cube, arrows in agents]
            for k in range(M):
                line = {"type": 2, "pose": _ID_POSE, "thickness": f(), "scale_invariant": False,
                        "points": [{"x": f(), "y": f(), "z": f()} for _ in range(2)],
                        "color": {"r": f(), "g": f(), "b": f(), "a": 1.0}, "colors": [],
                        "indices": []}
                text = {"pose": {"position": {"x": f(), "y": f(), "z": f()},
                                 "orientation": _ID_POSE["orientation"]},
                        "billboard": True, "font_size": f(), "scale_invariant": True,
                        "color": {"r": 1.0, "g": 1.0, "b": 1.0, "a": f()},
                        "text": f"θ_{sb.edge_ids[k]} jumps"}
                ents.append(dict(_NO_PARTS, timestamp=t(), frame_id="world",
                                 id=f"edge_{sb.edge_ids[k]}", lifetime={"sec": 0, "nanosec": 0},
                                 frame_locked=False, metadata=[], lines=[line], texts=[text]))
            return {"deletions": [], "entities": ents}

        self._scene = cdr.compile_layout(cdr.SCHEMA["/scene"], build)
        self._trail = {}   # layout by number of poses
        self._kept = np.zeros((N, sb.trail_len, 7))
        self._nkept = 0

    def scene(self, t_ns: int, S, rot_err, jumping) -> np.ndarray:
        """The SceneUpdate at t_ns (``jumping``: M booleans), as a uint8 row valid until the next
        scene (`cdr.Layout.fill`)."""
        sb = self.sb
        # as SceneBuilder: a non-finite coordinate or colour is drawn as 0
        P = np.nan_to_num(np.asarray(S, np.float64)[:, :3], nan=0.0, posinf=0.0, neginf=0.0)
        J = np.asarray(jumping, np.bool_)
        pi, pj = P[self._a], P[self._b]
        col = np.where(J[:, None], 1.0, error_colors(rot_err))
        th = np.where(J, 3 * sb._scale, sb._scale)
        font, alpha = np.where(J, 14.0, 0.0), J.astype(np.float64)
        v = np.concatenate((th[:, None], pi, pj, col, (pi + pj) / 2, font[:, None],
                            alpha[:, None]), axis=1)
        return self._scene.fill(v.ravel(), t_ns)[0]

    def trails(self, t_ns: int, S, quat, keep: bool = True) -> np.ndarray:
        """One PosesInFrame per agent as the rows of a uint8 array (`SceneBuilder.trails`)."""
        cur = np.concatenate((np.asarray(S, np.float64)[:, :3], np.asarray(quat, np.float64)),
                             axis=1)
        cur = np.nan_to_num(cur, nan=0.0, posinf=0.0, neginf=0.0)
        n = self.sb.trail_len
        if keep:
            if self._nkept == n:
                self._kept[:, :-1] = self._kept[:, 1:]
                self._kept[:, -1] = cur
            else:
                self._kept[:, self._nkept] = cur
                self._nkept += 1
            poses = self._kept[:, :self._nkept]
        else:
            poses = np.concatenate((self._kept[:, :self._nkept], cur[:, None]), axis=1)
        return self._trail_layout(poses.shape[1]).fill(poses.reshape(len(poses), -1), t_ns)

    def _trail_layout(self, L: int):
        """The layout of a trail of L poses, made on first use."""
        lay = self._trail.get(L)
        if lay is None:
            lay = self._trail[L] = cdr.compile_layout(cdr.SCHEMA["trail"], lambda f, t, m: {
                "timestamp": t(), "frame_id": "world",
                "poses": [{"position": {"x": f(), "y": f(), "z": f()},
                           "orientation": {"x": f(), "y": f(), "z": f(), "w": f()}}
                          for _ in range(L)]})
        return lay

    def warm(self) -> None:
        """Makes the trail layouts of every length now (a trail has 1 … trail_len + 1 poses),
        so that none is made while a run steps (the live view: cosim/log/live.py)."""
        for L in range(1, self.sb.trail_len + 2):
            self._trail_layout(L)


# ------------------------------------------------------------------ layout
_PALETTE = ("#4e98e2", "#f5774d", "#f7df71", "#5cd6a9", "#b87fe2", "#e2606d", "#9fd65c",
            "#61cbe8")


def _plot(title: str, paths: list[tuple[str, str]]) -> dict:
    return {"title": title, "paths": [
        {"id": f"{title}-{i}", "timestampMethod": "receiveTime", "value": v, "enabled": True,
         "color": _PALETTE[i % len(_PALETTE)], "label": lab}
        for i, (v, lab) in enumerate(paths)], "showLegend": True, "legendDisplay": "floating",
        "isSynced": True}


def _ids(x) -> list:
    return list(range(1, x + 1)) if isinstance(x, int) else [int(v) for v in x]


def layout(agents, edges, encoding: str = "json") -> dict:
    """A Foxglove layout: a 3D panel following ``world`` with /tf, /scene and the trails, beside
    plots of ‖I − R̄_k‖_F per edge, θ_k per edge and V̄ (log time = simulated time). ``agents``
    and ``edges``: their numbers (lists), or their counts (numbered from 1)."""
    agents, edges = _ids(agents), _ids(edges)
    topics = {SCENE: {"visible": True}}
    for r, i in enumerate(agents):
        topics[f"{TRAIL_PREFIX}{i}"] = {"visible": True, "type": "line", "lineWidth": 0.03,
                                       "gradient": [_PALETTE[r % len(_PALETTE)] + "20",
                                                    _PALETTE[r % len(_PALETTE)] + "ff"]}
    three_d = {
        "followTf": "world", "fixedFrame": "world", "followMode": "follow-none",
        "cameraState": {"perspective": True, "distance": 25, "phi": 60, "thetaOffset": 45,
                        "target": [0, 0, 0], "targetOffset": [0, 0, 0],
                        "targetOrientation": [0, 0, 0, 1], "fovy": 45, "near": 0.05,
                        "far": 5000},
        "scene": {"transforms": {"showLabel": True, "axisScale": 0.5}},
        "transforms": {}, "topics": topics, "layers": {
            "grid": {"layerId": "foxglove.Grid", "instanceId": "grid", "visible": True,
                     "frameId": "world", "size": 20, "divisions": 20}},
    }
    cfg = {
        "3D!se3sync": three_d,
        "Plot!rot_err": _plot("edge error ‖I − R̄_k‖_F",
                              [(f"/edges.edges[{r}].rot_err", f"k={k}") for r, k in enumerate(edges)]),
        "Plot!theta": _plot("θ_k (rad)",
                            [(f"/edges.edges[{r}].theta", f"k={k}") for r, k in enumerate(edges)]),
        # a CDR log's field is `v` (ROS 2 names are lower case, cosim/log/cdr.py)
        "Plot!V": _plot("V̄", [("/lyapunov.V" if encoding == "json" else "/lyapunov.v", "V̄")]),
    }
    return {
        "configById": cfg,
        "layout": {"direction": "row", "splitPercentage": 60, "first": "3D!se3sync",
                   "second": {"direction": "column", "first": "Plot!rot_err",
                              "second": {"direction": "column", "first": "Plot!theta",
                                         "second": "Plot!V"}}},
        "globalVariables": {}, "userNodes": {},
        "playbackConfig": {"speed": 1},
    }


def layout_json(agents, edges, encoding: str = "json") -> str:
    return json.dumps(layout(agents, edges, encoding), indent=1, ensure_ascii=False)
