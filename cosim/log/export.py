"""`se3sync export`: a run log's time series as CSV, Parquet, NumPy .npz or MATLAB .mat.

What is exported (each part a ``--channels`` name, the log topic it comes from):

- ``edges`` (/edges): per edge k, θ_k after the jump stage, μ_U before it, ‖I − R̄_k‖_F, ‖p̄_k‖,
  U(X̄_k, θ_k) and whether the edge jumped at that record;
- ``tf`` (/tf): per agent, position p_i (world) and quaternion q_i (x, y, z, w);
- ``agents`` (/agents): per agent ω_i, v_i (body frame), τ_i, f_i;
- ``lyapunov`` (/lyapunov): V̄ and k_X Σ U;
- ``jumps`` (/jumps): every jump as an event (t, edge, θ⁻, θ⁺, μ_U), never decimated.

The records of the selected channels are joined on their log time (simulated time; a record
missing from one channel is NaN there), cut to ``tmin ≤ t ≤ tmax`` and decimated (every K-th
record). Numbers are the log's as `read_log` gives them (JSON and CDR logs alike), unchanged:
the CSV writes each as its shortest round-trip text, the other formats as float64.

Layouts. CSV and Parquet are one wide table, one row per record, columns ``t``, then per
quantity per edge / agent (``edge3.theta``, ``agent2.omega_z``, ``V``); the jumps go to a
second table beside it, ``STEM.jumps.csv`` / ``STEM.jumps.parquet``. The units: in the CSV a
comment line ``# units: s,rad,…`` (one per column, before the header) and a first comment line
naming the log; in Parquet each field's metadata ``unit`` and the schema's metadata
``se3sync`` (the log's metadata record) and ``units``. .npz and .mat hold everything in one
file: ``t`` (T,), ``edges.theta`` (T, M), ``agents.omega`` (T, N, 3), ``tf.q`` (T, N, 4), …,
``jumps.t`` …, ``edge_ids``, ``agent_ids``, ``units`` and ``metadata`` (JSON text in .npz,
MATLAB structs in .mat: ``edges.theta`` is field ``theta`` of struct ``edges``).

Every file appears whole or not at all (`cosim.files.atomic_path`).
"""
from __future__ import annotations

import json
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from controller.errors import Se3SyncError

from ..files import atomic_path
from .reader import read_log

__all__ = ["CHANNELS", "FORMATS", "UNITS", "Export", "load_export", "export_log", "jumps_path"]

# --channels name → log topic
CHANNELS = {"edges": "/edges", "tf": "/tf", "agents": "/agents", "lyapunov": "/lyapunov",
            "jumps": "/jumps"}
FORMATS = (".csv", ".parquet", ".npz", ".mat")

# per channel: its quantities, (name, unit, description, components)
_EDGE_Q = (("theta", "rad", "θ_k after the jump stage", None),
           ("mu_U", "1", "μ_U(X̄_k, θ_k) before any jump", None),
           ("rot_err", "1", "‖I − R̄_k‖_F", None),
           ("pos_err", "m", "‖p̄_k‖", None),
           ("U", "1", "U(X̄_k, θ_k) (the potential, in the units of the weighting matrix)", None),
           ("jump", "1", "1 when edge k jumped at this record, else 0", None))
_TF_Q = (("p", "m", "position p_i in the world frame", "xyz"),
         ("q", "1", "attitude quaternion of R_i (x, y, z, w)", "xyzw"))
_AGENT_Q = (("omega", "rad/s", "angular velocity ω_i (body frame)", "xyz"),
            ("v", "m/s", "linear velocity v_i (body frame)", "xyz"),
            ("torque", "N m", "torque τ_i (body frame)", "xyz"),
            ("force", "N", "force f_i (body frame)", "xyz"))
_LYAP_Q = (("V", "J", "V̄ = k_X Σ U + Σ ξᵀ𝕀ξ", None),
           ("kX_U", "J", "k_X Σ_k U(X̄_k, θ_k)", None))
_JUMP_Q = (("t", "s", "simulated time of the jump", None),
           ("edge", "1", "edge number k", None),
           ("theta_before", "rad", "θ_k before the jump", None),
           ("theta_after", "rad", "θ_k after the jump", None),
           ("mu", "1", "μ_U(X̄_k, θ_k⁻)", None))
_QUANTITIES = {"edges": _EDGE_Q, "tf": _TF_Q, "agents": _AGENT_Q, "lyapunov": _LYAP_Q,
               "jumps": _JUMP_Q}
UNITS = {"t": "s", **{f"{c}.{q[0]}": q[1] for c, qs in _QUANTITIES.items() for q in qs}}
DESCRIPTIONS = {"t": "simulated time", **{f"{c}.{q[0]}": q[2] for c, qs in _QUANTITIES.items()
                                           for q in qs}}


def jumps_path(out) -> Path:
    """Where a CSV or Parquet export puts its jumps: ``STEM.jumps.SUFFIX`` beside it."""
    out = Path(out)
    return out.with_name(f"{out.stem}.jumps{out.suffix}")


@dataclass
class Export:
    """The exported data: ``t`` (T,), ``series`` {"edges.theta": (T, M), "agents.omega":
    (T, N, 3), "lyapunov.V": (T,), …}, ``jumps`` {"t": (J,), "edge", "theta_before",
    "theta_after", "mu"} (None when not selected), ``edge_ids``, ``agent_ids``, ``metadata``
    (the log's se3sync record) and ``channels`` (the names selected)."""

    t: np.ndarray
    series: dict
    jumps: dict | None
    edge_ids: list
    agent_ids: list
    metadata: dict
    channels: list
    source: str = ""
    units: dict = field(default_factory=lambda: dict(UNITS))

    def columns(self):
        """The flat table: (name, unit, 1-D array) per column, ``t`` first; per quantity, one
        column per edge (``edge3.theta``) or per agent and component (``agent2.omega_z``)."""
        out = [("t", "s", self.t)]
        for key, a in self.series.items():
            chan, q = key.split(".", 1)
            unit = UNITS[key]
            if a.ndim == 1:
                out.append((q, unit, a))
                continue
            comps = dict((x[0], x[3]) for x in _QUANTITIES[chan])[q]
            ids, who = (self.edge_ids, "edge") if chan == "edges" else (self.agent_ids, "agent")
            for j, ident in enumerate(ids):
                if comps is None:
                    out.append((f"{who}{ident}.{q}", unit, a[:, j]))
                else:
                    for c, comp in enumerate(comps):
                        out.append((f"{who}{ident}.{q}_{comp}", unit, a[:, j, c]))
        return out


def _parse_channels(channels) -> list | None:
    if channels is None:
        return None
    if isinstance(channels, str):
        channels = [c for c in channels.split(",")]
    names = []
    for c in channels:
        c = c.strip().lstrip("/")
        if c not in CHANNELS:
            raise Se3SyncError(f"--channels: unknown channel {c!r} (choose from "
                               f"{', '.join(CHANNELS)})")
        if c not in names:
            names.append(c)
    if not names:
        raise Se3SyncError("--channels: no channel given")
    return names


def _rows(msgs):
    """A topic's messages sorted by log time: (times ns int64, messages)."""
    msgs = sorted(msgs, key=lambda m: m[0])
    return np.array([m[0] for m in msgs], np.int64), [m[1] for m in msgs]


def _series_of(chan, payloads):
    """{quantity: array (R, …)} of one record channel's decoded messages, and the ids."""
    if chan == "edges":
        rows = [m["edges"] for m in payloads]
        ids = [e.get("edge", k + 1) for k, e in enumerate(rows[0])]
        out = {q: np.array([[e[q] for e in r] for r in rows], float)
               for q in ("theta", "mu_U", "rot_err", "pos_err", "U")}
        out["jump"] = np.array([[e.get("mode") == "jump" for e in r] for r in rows], float)
        return out, ids
    if chan == "tf":
        rows = [m["transforms"] for m in payloads]
        ids = []
        for i, x in enumerate(rows[0]):
            name = str(x.get("child_frame_id", ""))
            ids.append(int(name[6:]) if name.startswith("agent_") and name[6:].isdigit()
                       else i + 1)
        p = np.array([[[x["translation"][c] for c in "xyz"] for x in r] for r in rows], float)
        q = np.array([[[x["rotation"][c] for c in "xyzw"] for x in r] for r in rows], float)
        return {"p": p, "q": q}, ids
    if chan == "agents":
        rows = [m["agents"] for m in payloads]
        ids = [a.get("agent", i + 1) for i, a in enumerate(rows[0])]
        return {q: np.array([[a[q] for a in r] for r in rows], float)
                for q in ("omega", "v", "torque", "force")}, ids
    # lyapunov
    return {q: np.array([m.get(q) for m in payloads], float) for q in ("V", "kX_U")}, None


def load_export(path, channels=None, tmin=None, tmax=None, every: int = 1) -> Export:
    """The data `export_log` writes, from the log at ``path`` (see the module's docstring).
    Raises Se3SyncError (one line naming the option or the file) on a bad request."""
    names = _parse_channels(channels)
    every = int(every)
    if every < 1:
        raise Se3SyncError(f"--every: must be >= 1, got {every}")
    for opt, v in (("--tmin", tmin), ("--tmax", tmax)):
        if v is not None and not np.isfinite(v):
            raise Se3SyncError(f"{opt}: must be a finite number of seconds, got {v}")
    if tmin is not None and tmax is not None and not tmax >= tmin:
        raise Se3SyncError(f"--tmax: must be >= --tmin ({tmin:g}), got {tmax:g}")
    wanted = names or list(CHANNELS)
    log = read_log(path, topics=tuple(CHANNELS[c] for c in wanted))
    msgs = log["messages"]
    present = [c for c in wanted if msgs.get(CHANNELS[c]) or c == "jumps"]
    if names is not None:
        missing = [c for c in names if c not in present]
        if missing:
            raise Se3SyncError(f"--channels: {path}: the log has no {CHANNELS[missing[0]]} "
                               "messages")
    records = [c for c in present if c != "jumps"]
    if not records and "jumps" not in present:
        raise Se3SyncError(f"{path}: the log has none of the channels "
                           f"{', '.join(CHANNELS[c] for c in wanted)}")
    parts, edge_ids, agent_ids = {}, [], []
    for c in records:
        times, payloads = _rows(msgs[CHANNELS[c]])
        vals, ids = _series_of(c, payloads)
        parts[c] = (times, vals)
        if c == "edges":
            edge_ids = ids
        elif ids is not None and not agent_ids:
            agent_ids = ids
    # the records of every channel joined on their log time
    t_ns = (np.unique(np.concatenate([p[0] for p in parts.values()])) if parts
            else np.zeros(0, np.int64))
    keep = np.ones(len(t_ns), bool)
    t = t_ns * 1e-9
    if tmin is not None:
        keep &= t >= tmin
    if tmax is not None:
        keep &= t <= tmax
    sel = np.flatnonzero(keep)[::every]
    if parts and len(sel) == 0:
        raise Se3SyncError(f"--tmin/--tmax: no record of {path} in the window (the log has "
                           f"{t[0]:g}..{t[-1]:g} s)")
    series = {}
    for c in records:
        times, vals = parts[c]
        at = np.searchsorted(t_ns, times)
        for q in (x[0] for x in _QUANTITIES[c]):
            a = vals[q]
            full = np.full((len(t_ns),) + a.shape[1:], np.nan)
            full[at] = a
            series[f"{c}.{q}"] = full[sel]
    jumps = None
    if "jumps" in present:
        js = sorted((m for _, m in msgs.get("/jumps", [])), key=lambda j: (j["t"], j["edge"]))
        jt = np.array([j["t"] for j in js], float)
        ok = np.ones(len(js), bool)
        if tmin is not None:
            ok &= jt >= tmin
        if tmax is not None:
            ok &= jt <= tmax
        js = [j for j, k in zip(js, ok) if k]
        jumps = {"t": np.array([j["t"] for j in js], float),
                 "edge": np.array([j["edge"] for j in js], np.int64),
                 "theta_before": np.array([j["theta_before"] for j in js], float),
                 "theta_after": np.array([j["theta_after"] for j in js], float),
                 "mu": np.array([j["mu"] for j in js], float)}
    return Export(t=t[sel], series=series, jumps=jumps, edge_ids=list(edge_ids),
                  agent_ids=list(agent_ids), metadata=dict(log["metadata"]),
                  channels=[c for c in present], source=str(path))


# ------------------------------------------------------------------ writers

def _csv_table(f, names, units, cols, headline):
    f.write(f"# {headline}\n")
    f.write("# units: " + ",".join(units) + "\n")
    f.write(",".join(names) + "\n")
    # str of a Python float is its repr: the shortest text that reads back to the same float
    # (ints, the jumps' edge numbers, stay ints)
    for row in zip(*(np.asarray(c).tolist() for c in cols)):
        f.write(",".join(map(str, row)))
        f.write("\n")


def _jump_cols(ex):
    j = ex.jumps
    return ([q[0] for q in _JUMP_Q], [q[1] for q in _JUMP_Q], [j[q[0]] for q in _JUMP_Q])


def _headline(ex, what="the records"):
    md = ex.metadata
    return (f"se3sync export of {Path(ex.source).name}: {what} (scenario "
            f"{md.get('scenario_name', '?')}, controller {md.get('controller', '?')}, "
            f"time t = simulated time)")


def _write_csv(ex, out, jout):
    with ExitStack() as stack:
        tmp = stack.enter_context(atomic_path(out))
        jtmp = stack.enter_context(atomic_path(jout)) if jout is not None else None
        if len(ex.series):
            cols = ex.columns()
            with open(tmp, "w", encoding="utf-8", newline="") as f:
                _csv_table(f, [c[0] for c in cols], [c[1] for c in cols], [c[2] for c in cols],
                           _headline(ex))
        else:   # only the jumps were asked for: they are the table
            names, units, cols = _jump_cols(ex)
            with open(tmp, "w", encoding="utf-8", newline="") as f:
                _csv_table(f, names, units, cols, _headline(ex, "the jumps"))
        if jtmp is not None:
            names, units, cols = _jump_cols(ex)
            with open(jtmp, "w", encoding="utf-8", newline="") as f:
                _csv_table(f, names, units, cols, _headline(ex, "the jumps"))


def _arrow_table(names, units, cols, meta):
    import pyarrow as pa

    fields = [pa.field(n, pa.int64() if np.asarray(c).dtype.kind == "i" else pa.float64(),
                       metadata={"unit": u}) for n, u, c in zip(names, units, cols)]
    schema = pa.schema(fields, metadata={k: json.dumps(v) if not isinstance(v, str) else v
                                         for k, v in meta.items()})
    return pa.Table.from_arrays([pa.array(np.asarray(c)) for c in cols], schema=schema)


def _write_parquet(ex, out, jout):
    import pyarrow.parquet as pq   # the CLI names the extra ("sweep") when it is missing

    meta = {"se3sync": json.dumps(ex.metadata), "source": ex.source}
    with ExitStack() as stack:
        tmp = stack.enter_context(atomic_path(out))
        jtmp = stack.enter_context(atomic_path(jout)) if jout is not None else None
        if len(ex.series):
            cols = ex.columns()
            table = _arrow_table([c[0] for c in cols], [c[1] for c in cols],
                                 [c[2] for c in cols],
                                 dict(meta, units=json.dumps({c[0]: c[1] for c in cols})))
        else:
            names, units, cols = _jump_cols(ex)
            table = _arrow_table(names, units, cols, dict(meta, units=json.dumps(
                dict(zip(names, units)))))
        pq.write_table(table, tmp)
        if jtmp is not None:
            names, units, cols = _jump_cols(ex)
            pq.write_table(_arrow_table(names, units, cols, dict(meta, units=json.dumps(
                dict(zip(names, units))))), jtmp)


def _arrays(ex) -> dict:
    """The .npz / .mat contents as flat names ("edges.theta") → arrays."""
    out = {"t": ex.t, **ex.series}
    if ex.jumps is not None:
        out.update({f"jumps.{k}": v for k, v in ex.jumps.items()})
    out["edge_ids"] = np.asarray(ex.edge_ids, np.int64)
    out["agent_ids"] = np.asarray(ex.agent_ids, np.int64)
    return out


def _write_npz(ex, out):
    arrs = _arrays(ex)
    units = {n: UNITS.get(n, "1") for n in arrs if n not in ("edge_ids", "agent_ids")}
    with atomic_path(out) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrs, units=np.array(json.dumps(units)),
                                descriptions=np.array(json.dumps(
                                    {n: DESCRIPTIONS[n] for n in units})),
                                metadata=np.array(json.dumps(ex.metadata)))


def _write_mat(ex, out):
    import scipy.io

    arrs = _arrays(ex)
    mat, units = {}, {}
    for name, a in arrs.items():
        a = np.asarray(a)
        if "." in name:
            group, q = name.split(".", 1)
            mat.setdefault(group, {})[q] = a
            units.setdefault(group, {})[q] = UNITS[name]
        else:
            mat[name] = a
            if name == "t":
                units["t"] = "s"
    # MATLAB field names: letters, digits and underscores, starting with a letter
    meta = {k if k[0].isalpha() else f"x{k}": str(v) for k, v in ex.metadata.items()}
    mat["units"] = units
    mat["metadata"] = meta
    with atomic_path(out) as tmp:
        with open(tmp, "wb") as f:
            scipy.io.savemat(f, mat, do_compression=True, oned_as="column",
                             long_field_names=True)


def export_log(path, out, channels=None, tmin=None, tmax=None, every: int = 1) -> dict:
    """Writes the export of the log ``path`` to ``out`` (the format from its suffix: .csv,
    .parquet, .npz, .mat); CSV and Parquet put the jumps beside it (`jumps_path`). Returns
    {"rows", "columns", "jumps", "files"}."""
    out = Path(out)
    fmt = out.suffix.lower()
    if fmt not in FORMATS:
        raise Se3SyncError(f"--output: {str(out)!r} must end in {' or '.join(FORMATS)}")
    ex = load_export(path, channels, tmin, tmax, every)
    jout = None
    if fmt in (".csv", ".parquet") and ex.jumps is not None and ex.series:
        jout = jumps_path(out)
    {".csv": lambda: _write_csv(ex, out, jout), ".parquet": lambda: _write_parquet(ex, out, jout),
     ".npz": lambda: _write_npz(ex, out), ".mat": lambda: _write_mat(ex, out)}[fmt]()
    return {"rows": len(ex.t), "columns": len(ex.columns()) if ex.series else 0,
            "jumps": None if ex.jumps is None else len(ex.jumps["t"]),
            "files": [str(out)] + ([str(jout)] if jout is not None else [])}
