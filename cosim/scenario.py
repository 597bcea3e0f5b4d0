"""Scenario files (TOML): schema, validation and the objects the co-simulation needs.

Every problem is reported as ONE line naming the file, the key path and the reason, e.g.
``scenarios/x.toml: gains.k_X: must be > 0, got -1``. Validation happens completely before any
output is written. Every key and its default: docs/reference/scenario.md.
"""
from __future__ import annotations

import copy
import dataclasses
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from controller import Gains, Graph, WeightingMatrix, design_synergy, layout, se3
from controller.errors import ConfigError, DesignError, GraphError, Se3SyncError, WeightingError

from . import plugins
from .initial import paper_state, random_state
from .registry import PLANTS

try:  # Python 3.11+
    import tomllib as _toml
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    import tomli as _toml

__all__ = ["ScenarioError", "design_summary", "Scenario", "load_scenario", "parse_scenario", "apply_overrides",
           "parse_override", "restrict", "with_timing", "SCHEMA", "DEFAULT_LOG_RATE",
           "MAX_DEFAULT_INTERNAL_STEP"]

DEFAULT_LOG_RATE = 100.0
# Ranges that keep every product of the law and the plant far from overflow and underflow; they
# are generous for any physical swarm (metres, kilograms, seconds).
MAX_MAGNITUDE = 1e6        # positions, velocities, gravity, box and ball sizes, θ(0)
MAX_AGENTS = 100_000       # the plant FMU's limit (plant_fmu.layout.MAX_BODIES)
MAX_GAIN = 1e9
MASS_RANGE = (1e-9, 1e9)   # kg; inertias: principal moments in this range too (kg m²)
WEIGHTING_RANGE = (1e-9, 1e9)
MAX_STEPS = 10 ** 9        # communication steps of one run
MAX_BODY_SUBSTEPS = 10 ** 6   # N · ⌈h / internal_step⌉ per step: the plant FMU's limit per doStep
MIN_INTERNAL_STEP = 1e-9      # s, the plant FMU's floor
# simulation.actuation_delay: steps a wrench waits before the plant applies it (the loop of a
# Jacobi FMI master: 1, docs/fmi-system.md); the held wrenches (delay × N × 6 floats) at most:
MAX_ACTUATION_DELAY = 10 ** 6
MAX_ACTUATION_BYTES = 1 << 30
# default internal step of the plant FMU: the communication step, but at most 1 ms
MAX_DEFAULT_INTERNAL_STEP = 1e-3


# A scenario problem: ``ScenarioError(keypath, reason)``; the loader adds the file name. The class
# lives in controller.errors so that packages owning a table raise it without importing cosim.
ScenarioError = ConfigError


# ----------------------------------------------------------------------------- schema
# section -> allowed keys (None: free-form table validated elsewhere)
SCHEMA: dict[str, Any] = {
    "agents": {"count", "mass", "inertia"},
    "graph": {"edges"},
    "weighting": {"A", "b", "d"},
    "synergy": {"Theta", "Theta_over_pi", "gamma", "delta", "u_c1", "alpha_signs"},
    "gains": {"k_X", "k_xi", "k_e", "k_theta"},
    "initial": {"generator", "axis", "eigenvector", "seed", "position_box", "velocity_ball",
                "agent", "theta0"},
    "simulation": {"duration", "step", "log_rate", "actuation_delay"},
    "plant": {"gravity", "internal_step", "mode", "ground", "ground_height", "drag_linear", "drag_angular"},
}
# Further tables ([bridge], ...) are owned by other packages: see cosim/plugins.py.
AGENT_KEYS = {"axis_angle", "quaternion", "position", "velocity"}
REQUIRED = ("agents", "graph", "weighting", "gains", "initial", "simulation")


def _fmtv(v) -> str:
    if isinstance(v, str):
        return repr(v)
    try:
        return repr(v) if not isinstance(v, (list, tuple)) else str(list(v))
    except Exception:  # pragma: no cover
        return "?"


def _is_num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _num(key, v, *, positive=False, nonneg=False, integer=False, maximum=None) -> float:
    if integer:
        if isinstance(v, bool) or not isinstance(v, int):
            raise ScenarioError(key, f"must be an integer, got {_fmtv(v)}")
    elif not _is_num(v):
        raise ScenarioError(key, f"must be a number, got {_fmtv(v)}")
    if not math.isfinite(v):
        raise ScenarioError(key, f"must be finite, got {v}")
    if positive and not v > 0:
        raise ScenarioError(key, f"must be > 0, got {v}")
    if nonneg and not v >= 0:
        raise ScenarioError(key, f"must be >= 0, got {v}")
    if maximum is not None and not v <= maximum:
        raise ScenarioError(key, f"must be <= {maximum:g}, got {v:g}")
    return v if integer else float(v)


def _array(key, v, shape, maximum=MAX_MAGNITUDE) -> np.ndarray:
    """A nested list of numbers with exactly this shape, each of magnitude <= maximum."""
    def shp(x):
        if isinstance(x, list):
            subs = [shp(e) for e in x]
            if any(s != subs[0] for s in subs[1:]):
                return None
            if subs and subs[0] is None:
                return None
            return (len(x),) + (subs[0] if subs else ())
        return ()

    if not isinstance(v, list):
        raise ScenarioError(key, f"must be an array of shape {_shape_txt(shape)}, got {_fmtv(v)}")
    s = shp(v)
    if s is None or s != tuple(shape):
        got = "a ragged array" if s is None else f"shape {_shape_txt(s)}"
        raise ScenarioError(key, f"must be an array of shape {_shape_txt(shape)}, got {got}")
    flat = np.asarray(v, dtype=object).ravel() if shape else [v]
    for x in flat:
        if not _is_num(x):
            raise ScenarioError(key, f"must hold numbers only, got {_fmtv(x)}")
    a = np.asarray(v, dtype=float)
    if not np.all(np.isfinite(a)):
        raise ScenarioError(key, "must hold finite numbers only")
    if maximum is not None and a.size and np.abs(a).max() > maximum:
        raise ScenarioError(key, f"must hold numbers of magnitude <= {maximum:g}, got "
                                 f"{float(np.abs(a).max()):g}")
    return a


def _shape_txt(s) -> str:
    return "×".join(str(x) for x in s) if s else "scalar"


def _table(key, v) -> dict:
    if not isinstance(v, dict):
        raise ScenarioError(key, f"must be a table, got {_fmtv(v)}")
    return v


def _check_keys(prefix, table, allowed):
    for k in table:
        if k not in allowed:
            raise ScenarioError(f"{prefix}.{k}" if prefix else k,
                                f"unknown key (allowed: {', '.join(sorted(allowed))})")


def _require(prefix, table, key):
    if key not in table:
        raise ScenarioError(f"{prefix}.{key}", "missing required key")
    return table[key]


# ----------------------------------------------------------------------------- overrides
def parse_override(item: str):
    """'key.path=value' -> (['key', 'path'], value). The value is a TOML value; a bare word
    that is not valid TOML is taken as a string (``--set plant.mode=per-body``)."""
    if "=" not in item:
        raise ScenarioError(f"--set {item}", "expected key.path=value")
    key, _, raw = item.partition("=")
    key = key.strip()
    parts = key.split(".")
    if not key or any(not p.strip() for p in parts):
        raise ScenarioError(f"--set {item}", "expected key.path=value")
    raw = raw.strip()
    try:
        value = _toml.loads(f"v = {raw}")["v"]
    except _toml.TOMLDecodeError:
        if raw and all(c.isalnum() or c in "-_." for c in raw):
            value = raw
        else:
            raise ScenarioError(key, f"--set value {raw!r} is not a TOML value") from None
    return [p.strip() for p in parts], value


def apply_overrides(data: dict, overrides) -> dict:
    """Applies --set overrides to the parsed TOML (a deep copy); unknown keys are refused."""
    data = copy.deepcopy(data)
    for item in overrides or ():
        parts, value = parse_override(item)
        path = ".".join(parts)
        sec = parts[0]
        if sec not in SCHEMA and sec not in plugins.table_names():
            raise ScenarioError(path, f"unknown key (from --set {item})")
        allowed = SCHEMA.get(sec)
        if allowed is not None:
            if len(parts) != 2 or parts[1] not in allowed or parts[1] == "agent":
                raise ScenarioError(path, f"unknown key (from --set {item})")
        node = data
        for p in parts[:-1]:
            nxt = node.setdefault(p, {})
            if not isinstance(nxt, dict):
                raise ScenarioError(path, f"cannot set inside a non-table (from --set {item})")
            node = nxt
        node[parts[-1]] = value
    return data


# ----------------------------------------------------------------------------- result
@dataclass
class Scenario:
    """A validated scenario and everything derived from it."""

    name: str
    path: str
    text: str
    values: dict
    graph: Any
    weighting: Any
    design: Any
    gains: Any
    masses: np.ndarray           # (N,)
    inertias: np.ndarray         # (N, 3, 3)
    S0: np.ndarray               # (N, 18) rows as controller.layout
    theta0: np.ndarray           # (M,)
    duration: float
    step: float
    log_rate: float
    gravity: np.ndarray          # (3,)
    internal_step: float
    plant_mode: str              # "fleet" | "per-body"
    tables: dict = field(default_factory=dict)   # parsed tables owned by other packages
    overrides: tuple = field(default=())
    # the plant's optional terms ([plant] ground, ground_height, drag_linear, drag_angular) as
    # FleetFMU.set_parameters keywords; empty when all are off (the paper's runs)
    plant_terms: dict = field(default_factory=dict)
    # simulation.actuation_delay: the plant applies u(t_{n−d}) over [t_n, t_{n+1}] (0 before
    # t_d); `cosim.plants.make_plant` wraps the plant in `DelayedActuation` when d > 0
    actuation_delay: int = 0

    @property
    def bridge(self):
        """The parsed [bridge] table (bridge.mavlink.config.BridgeConfig) or None."""
        return self.tables.get("bridge")

    @property
    def n_agents(self) -> int:
        return self.graph.n

    @property
    def inertia6(self) -> np.ndarray:
        """(N, 6, 6) blkdiag(J_i, m_i I) -- the 𝕀 of V̄."""
        N = self.graph.n
        out = np.zeros((N, 6, 6))
        out[:, :3, :3] = self.inertias
        out[:, 3:, 3:] = self.masses[:, None, None] * np.eye(3)
        return out

    def n_steps(self, duration: float | None = None, step: float | None = None) -> int:
        d = self.duration if duration is None else float(duration)
        h = self.step if step is None else float(step)
        return max(0, int(math.ceil(d / h - 1e-9)))


def _timing(duration: float, step: float, N: int, internal_step=None) -> float:
    """The plant's internal step, once duration and step h have passed every limit: h ≤ duration,
    at most MAX_STEPS steps, at most MAX_BODY_SUBSTEPS body-substeps per step (the internal step
    given, ``plant.internal_step``, or h capped at MAX_DEFAULT_INTERNAL_STEP). The one place h is
    validated: the loader and `with_timing` both come here."""
    if step > duration:
        raise ScenarioError("simulation.step", f"must be <= simulation.duration = {duration:g}, got {step:g}")
    n_steps = math.ceil(duration / step - 1e-9)
    if n_steps > MAX_STEPS:
        raise ScenarioError("simulation.step", f"h = {step:g} s gives {n_steps:.3g} steps for "
                                               f"{duration:g} s (at most {MAX_STEPS:.0e})")
    internal = min(step, MAX_DEFAULT_INTERNAL_STEP)
    key = "simulation.step"
    if internal_step is not None:
        key = "plant.internal_step"
        internal = _num("plant.internal_step", internal_step, positive=True)
        if internal < MIN_INTERNAL_STEP:
            raise ScenarioError(key, f"must be >= {MIN_INTERNAL_STEP:g} s, got {internal:g}")
    sub = math.ceil(step / internal - 1e-9)
    if N * sub > MAX_BODY_SUBSTEPS:
        raise ScenarioError(key, f"h = {step:g} s with internal step {internal:g} s gives {N} × "
                                 f"{sub:.3g} body-substeps per step, above the plant's "
                                 f"{MAX_BODY_SUBSTEPS:.0e}")
    return internal


def with_timing(scenario: Scenario, duration=None, step=None) -> Scenario:
    """A copy of the scenario with another duration and/or communication step, checked against
    every limit the loader applies (`_timing`); the internal step follows h unless the scenario
    sets plant.internal_step."""
    if duration is None and step is None:
        return scenario
    try:
        d = scenario.duration if duration is None else _num("simulation.duration", duration,
                                                               positive=True)
        h = scenario.step if step is None else _num("simulation.step", step, positive=True)
        internal = _timing(d, h, scenario.graph.n,
                           scenario.values.get("plant", {}).get("internal_step"))
    except ScenarioError as exc:
        raise exc.with_file(scenario.path) from None
    return dataclasses.replace(scenario, duration=d, step=h, internal_step=internal)


def restrict(scenario: Scenario, agents) -> tuple:
    """The part of a scenario that a set of agents spans: ``(sub, edges)`` where ``sub`` is a
    Scenario of those agents (numbered 1.. in the order given) with every edge joining two of
    them, and ``edges`` lists those edges' numbers in the full graph (ascending, the order of
    ``sub``'s edges). Masses, inertias, initial states and θ(0) follow; the design, gains and
    timing are the scenario's. The agents must span a connected subtree (an agent with its
    neighbours does). Tables owned by other packages (``[bridge]``, ``[network]``) describe the
    full swarm and are dropped."""
    agents = [int(a) for a in agents]
    local = {g: r for r, g in enumerate(agents, start=1)}
    if len(local) != len(agents) or not all(1 <= a <= scenario.graph.n for a in agents):
        raise Se3SyncError(f"restrict: agents must be distinct numbers in 1..{scenario.graph.n}, "
                           f"got {agents}")
    edges = [k for k, (a, b) in enumerate(scenario.graph.edge_list, start=1)
             if a in local and b in local]
    graph = Graph(len(agents), [(local[scenario.graph.edge_list[k - 1][0]],
                                 local[scenario.graph.edge_list[k - 1][1]]) for k in edges])
    rows = [a - 1 for a in agents]
    sub = dataclasses.replace(
        scenario, graph=graph, masses=scenario.masses[rows].copy(),
        inertias=scenario.inertias[rows].copy(), S0=scenario.S0[rows].copy(),
        theta0=scenario.theta0[[k - 1 for k in edges]].copy(), tables={})
    return sub, tuple(edges)


def _check_inertia(J, agent: int) -> None:
    """What the plant refuses, said here first: J symmetric, positive definite, principal moments
    in MASS_RANGE and obeying the triangle inequality (λ₁ + λ₂ ≥ λ₃: a rigid body's mass cannot
    lie further from an axis than the other two allow). Checks are relative to J's own scale."""
    key = "agents.inertia"
    scale = float(np.abs(J).max())
    if scale == 0:
        raise ScenarioError(key, f"is zero (agent {agent})")
    Js = J / scale
    if np.abs(Js - Js.T).max() > 1e-12:
        raise ScenarioError(key, f"must be symmetric (agent {agent})")
    lam = np.linalg.eigvalsh(0.5 * (Js + Js.T)) * scale
    if lam[0] <= 1e-14 * lam[2]:
        raise ScenarioError(key, f"must be positive definite (agent {agent}), principal moments "
                                 f"{[float(f'{x:.6g}') for x in lam]}")
    if not (MASS_RANGE[0] <= lam[0] and lam[2] <= MASS_RANGE[1]):
        raise ScenarioError(key, f"principal moments must lie in [{MASS_RANGE[0]:g}, "
                                 f"{MASS_RANGE[1]:g}] kg m², got {[float(f'{x:.6g}') for x in lam]} "
                                 f"(agent {agent})")
    if lam[0] + lam[1] < lam[2] * (1 - 1e-9):
        raise ScenarioError(key, f"principal moments {[float(f'{x:.6g}') for x in lam]} break the "
                                 f"triangle inequality J1 + J2 >= J3 (agent {agent}): no rigid body "
                                 "has this inertia")


# ----------------------------------------------------------------------------- loading
def load_scenario(path, overrides=(), *, duration=None, step=None) -> Scenario:
    """Reads, overrides (--set), validates and designs. Raises ScenarioError (one line)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ScenarioError(None, "no such file", str(path)) from None
    except IsADirectoryError:
        raise ScenarioError(None, "is a directory, not a scenario file", str(path)) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ScenarioError(None, f"cannot read: {getattr(exc, 'strerror', None) or exc}",
                            str(path)) from None
    return parse_scenario(text, name=p.stem, path=str(path), overrides=overrides,
                          duration=duration, step=step)


def parse_scenario(text: str, name: str = "scenario", path: str = "<string>", overrides=(),
                   *, duration=None, step=None) -> Scenario:
    try:
        data = _toml.loads(text)
    except _toml.TOMLDecodeError as exc:
        raise ScenarioError(None, f"invalid TOML: {exc}", path) from None
    except RecursionError:
        raise ScenarioError(None, "invalid TOML: nested too deeply", path) from None
    try:
        data = apply_overrides(data, overrides)
        for key, value in (("duration", duration), ("step", step)):
            if value is not None:
                _table("simulation", data.setdefault("simulation", {}))[key] = value
        return _validate(data, text, name, path, tuple(overrides or ()))
    except ScenarioError as exc:
        raise exc.with_file(path) from None
    except (ArithmeticError, np.linalg.LinAlgError, RecursionError, MemoryError) as exc:
        # a combination of in-range values the mathematics still cannot evaluate
        raise ScenarioError(None, f"cannot be evaluated: {type(exc).__name__}: "
                                  f"{' '.join(str(exc).split())[:200]}", path) from None


def _validate(data: dict, text: str, name: str, path: str, overrides: tuple) -> Scenario:
    # the entry points are read only when the scenario has a table of another package
    plugin_tables = plugins.table_names() if set(data) - set(SCHEMA) else frozenset()
    _check_keys("", data, set(SCHEMA) | plugin_tables)
    for sec in REQUIRED:
        if sec not in data:
            raise ScenarioError(sec, "missing required table")
    for sec, allowed in SCHEMA.items():
        if sec in data:
            _table(sec, data[sec])
            _check_keys(sec, data[sec], allowed)

    # [agents]
    ag = data["agents"]
    N = _num("agents.count", _require("agents", ag, "count"), integer=True)
    if not 1 <= N <= MAX_AGENTS:
        raise ScenarioError("agents.count", f"must be in 1..{MAX_AGENTS}, got {N}")
    mass = _require("agents", ag, "mass")
    if isinstance(mass, list):
        masses = _array("agents.mass", mass, (N,), None)
    else:
        masses = np.full(N, _num("agents.mass", mass))
    for i, m in enumerate(masses):
        if not m > 0:
            raise ScenarioError("agents.mass", f"must be > 0, got {m:g} (agent {i + 1})")
        if not MASS_RANGE[0] <= m <= MASS_RANGE[1]:
            raise ScenarioError("agents.mass", f"must be in [{MASS_RANGE[0]:g}, {MASS_RANGE[1]:g}] "
                                               f"kg, got {m:g} (agent {i + 1})")
    inert = _require("agents", ag, "inertia")
    if isinstance(inert, list) and len(inert) == 3 and all(_is_num(x) for x in inert):
        inertias = np.tile(np.diag(_array("agents.inertia", inert, (3,), None)), (N, 1, 1))
    elif isinstance(inert, list) and len(inert) == 3 and all(
            isinstance(r, list) and len(r) == 3 and all(_is_num(x) for x in r) for r in inert):
        inertias = np.tile(_array("agents.inertia", inert, (3, 3), None), (N, 1, 1))
    elif isinstance(inert, list) and len(inert) == N and all(isinstance(r, list) for r in inert):
        inertias = _array("agents.inertia", inert, (N, 3, 3), None)
    else:
        raise ScenarioError("agents.inertia",
                            f"must be a 3-vector (diagonal), a 3×3 matrix or a list of {N} 3×3 "
                            f"matrices, got {_fmtv(inert)}")
    for i, J in enumerate(inertias):
        _check_inertia(J, i + 1)

    # [graph]
    gr = data["graph"]
    edges = _require("graph", gr, "edges")
    if not isinstance(edges, list):
        raise ScenarioError("graph.edges", f"must be an array of [positive, negative] pairs, got {_fmtv(edges)}")
    for k, e in enumerate(edges, start=1):
        if not (isinstance(e, list) and len(e) == 2 and all(isinstance(x, int) and not isinstance(x, bool) for x in e)):
            raise ScenarioError("graph.edges", f"edge {k} must be a pair of agent numbers [i, j], got {_fmtv(e)}")
    try:
        graph = Graph(N, [tuple(e) for e in edges])
    except GraphError as exc:
        raise ScenarioError("graph.edges", str(exc).removeprefix("graph: ")) from None

    # [weighting]
    wt = data["weighting"]
    A = _array("weighting.A", _require("weighting", wt, "A"), (3, 3), None)
    b = _array("weighting.b", _require("weighting", wt, "b"), (3,), None)
    d = _num("weighting.d", _require("weighting", wt, "d"))
    for key, x in (("weighting.A", A), ("weighting.b", b)):
        if x.size and np.abs(x).max() > WEIGHTING_RANGE[1]:
            raise ScenarioError(key, f"must hold numbers of magnitude <= {WEIGHTING_RANGE[1]:g}")
    if d > 0 and not WEIGHTING_RANGE[0] <= d <= WEIGHTING_RANGE[1]:
        raise ScenarioError("weighting.d", f"must be in [{WEIGHTING_RANGE[0]:g}, "
                                           f"{WEIGHTING_RANGE[1]:g}], got {d:g}")
    try:
        weighting = WeightingMatrix.from_blocks(A, b, d)
    except WeightingError as exc:
        raise ScenarioError("weighting", str(exc)) from None

    # [synergy]
    sy = data.get("synergy", {})
    if "Theta" in sy and "Theta_over_pi" in sy:
        raise ScenarioError("synergy.Theta_over_pi", "give synergy.Theta or synergy.Theta_over_pi, not both")
    Theta = None
    theta_key = "synergy.Theta"
    for key, scale in (("Theta", 1.0), ("Theta_over_pi", math.pi)):
        if key in sy:
            theta_key = f"synergy.{key}"
            v = sy[key]
            if _is_num(v):
                v = [v]
            if not isinstance(v, list) or not v:
                raise ScenarioError(theta_key, f"must be a non-empty array of angles, got {_fmtv(v)}")
            Theta = _array(theta_key, v, (len(v),)) * scale
    gamma = _num("synergy.gamma", sy["gamma"]) if "gamma" in sy else None
    delta = _num("synergy.delta", sy["delta"]) if "delta" in sy else None
    u_c1 = _array("synergy.u_c1", sy["u_c1"], (3,)) if "u_c1" in sy else None
    signs = (1, 1, 1)
    if "alpha_signs" in sy:
        s = _array("synergy.alpha_signs", sy["alpha_signs"], (3,))
        if not np.all(np.abs(s) == 1):
            raise ScenarioError("synergy.alpha_signs", f"must be three values of 1 or -1, got {s.tolist()}")
        signs = tuple(int(x) for x in s)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            design = design_synergy(weighting, Theta=Theta, gamma=gamma, delta=delta, u_c1=u_c1,
                                    alpha_signs=signs)
    except DesignError as exc:
        key = {"gamma": "synergy.gamma", "delta": "synergy.delta", "Theta": theta_key,
               "u_c1": "synergy.u_c1", "alpha_signs": "synergy.alpha_signs",
               "W": "weighting"}.get(exc.param, "synergy")
        raise ScenarioError(key, str(exc)) from None

    # [gains]
    gn = data["gains"]
    vals = {}
    for k in ("k_X", "k_xi", "k_e"):
        vals[k] = _num(f"gains.{k}", _require("gains", gn, k), positive=True, maximum=MAX_GAIN)
    vals["k_theta"] = _num("gains.k_theta", gn.get("k_theta", 1.0), positive=True,
                           maximum=MAX_GAIN)
    try:
        gains = Gains(**vals)
    except Se3SyncError as exc:  # pragma: no cover - checked above already
        raise ScenarioError("gains", str(exc)) from None

    # [simulation]
    sim = data["simulation"]
    duration = _num("simulation.duration", _require("simulation", sim, "duration"), positive=True)
    step = _num("simulation.step", _require("simulation", sim, "step"), positive=True)
    log_rate = _num("simulation.log_rate", sim.get("log_rate", DEFAULT_LOG_RATE), positive=True)
    actuation_delay = _actuation_delay(sim.get("actuation_delay", 0), N)

    # [plant]
    pl = data.get("plant", {})
    gravity = _array("plant.gravity", pl.get("gravity", [0.0, 0.0, 0.0]), (3,))
    internal = _timing(duration, step, N, pl.get("internal_step"))
    mode = pl.get("mode", "fleet")
    if not isinstance(mode, str) or mode not in PLANTS:
        raise ScenarioError("plant.mode", "must be " + " or ".join(f'"{k}"' for k in PLANTS)
                            + f", got {_fmtv(mode)}")

    # [initial]
    S0, theta0 = _initial(data["initial"], N, graph, weighting)
    plant_terms = _plant_terms(pl, gravity, S0, masses, inertias, internal)

    # tables owned by other packages ([bridge], ...)
    tables = {}
    for sec in sorted(plugin_tables & set(data)):
        try:
            tables[sec] = plugins.table_parser(sec)(_table(sec, data[sec]), N)
            check_graph = getattr(tables[sec], "check_graph", None)
            if check_graph is not None:   # e.g. [[network.link]] only between neighbours
                check_graph(graph)
        except ConfigError as exc:
            raise exc.under(sec) from None

    return Scenario(name=name, path=path, text=text, values=data, graph=graph,
                    weighting=weighting, design=design, gains=gains, masses=masses,
                    inertias=inertias, S0=S0, theta0=theta0, duration=duration, step=step,
                    log_rate=log_rate, gravity=gravity, internal_step=internal,
                    plant_mode=mode, tables=tables, overrides=overrides, plant_terms=plant_terms,
                    actuation_delay=actuation_delay)


def _actuation_delay(v, N: int) -> int:
    """simulation.actuation_delay: whole communication steps, 0 … MAX_ACTUATION_DELAY, and the
    wrenches it holds (d × N × 6 doubles) within MAX_ACTUATION_BYTES."""
    key = "simulation.actuation_delay"
    d = _num(key, v, integer=True, nonneg=True, maximum=MAX_ACTUATION_DELAY)
    need = d * N * 6 * 8
    if need > MAX_ACTUATION_BYTES:
        raise ScenarioError(key, f"{d} steps of {N} agents' wrenches need {need / 2 ** 30:.3g} GiB "
                                 f"(at most {MAX_ACTUATION_BYTES / 2 ** 30:g} GiB): use a shorter delay")
    return d


def _plant_terms(pl: dict, gravity, S0, masses, inertias, internal: float) -> dict:
    """[plant] ground (bool), ground_height (m along −g), drag_linear (N·s/m), drag_angular
    (N·m·s/rad): the plant FMU's optional terms (docs/reference/plant-fmu.md "Ground and drag"), checked
    here as the plant checks them. Only the terms that are on are returned."""
    terms = {}
    ground = pl.get("ground", False)
    if not isinstance(ground, bool):
        raise ScenarioError("plant.ground", f"must be true or false, got {_fmtv(ground)}")
    height = _num("plant.ground_height", pl.get("ground_height", 0.0), maximum=MAX_MAGNITUDE)
    if height < -MAX_MAGNITUDE:
        raise ScenarioError("plant.ground_height", f"must be >= {-MAX_MAGNITUDE:g}, got {height:g}")
    if "ground_height" in pl and not ground:
        raise ScenarioError("plant.ground_height", "needs plant.ground = true")
    if ground:
        gn = float(np.linalg.norm(gravity))
        if not gn > 0:
            raise ScenarioError("plant.ground", "needs a nonzero plant.gravity (it defines which way is up)")
        up = -np.asarray(gravity, float) / gn
        hgt = S0[:, layout.P] @ up - height
        low = np.flatnonzero(hgt < -1e-9 * (1.0 + abs(height)))
        if low.size:
            i = int(low[0])
            raise ScenarioError("plant.ground_height", f"agent {i + 1} starts {-hgt[i]:.6g} m below the ground "
                                f"at {height:g} m")
        terms.update(ground=True, ground_height=height)
    # the plant refuses a drag whose time constant the internal step cannot resolve (RK4 is stable
    # on x' = -x/T for h/T < 2.78; it asks h/T <= 2.5): said here first, naming the key
    smallest = {"drag_linear": (lambda: float(np.min(masses)), "mass", "N·s/m"),
                "drag_angular": (lambda: float(np.linalg.eigvalsh(np.asarray(inertias, float))[:, 0].min()),
                                 "principal moment", "N·m·s/rad")}
    for key, (low, what, unit) in smallest.items():
        if key in pl:
            c = _num(f"plant.{key}", pl[key], nonneg=True, maximum=MAX_MAGNITUDE)
            lo = low() if c > 0 else 1.0
            if c > 0 and c * internal / lo > 2.5:
                raise ScenarioError(f"plant.{key}", f"{c:g} {unit} with the smallest {what} {lo:g} gives a time "
                                    f"constant {lo / c:.3g} s, shorter than the internal step / 2.5 "
                                    f"({internal:g} s / 2.5): use a smaller drag or plant.internal_step")
            if c > 0:
                terms[key] = c
    return terms


def _initial(ini: dict, N: int, graph, weighting):
    S0 = np.zeros((N, layout.S_WIDTH))
    gen = ini.get("generator")
    M = graph.M
    if "theta0" in ini:
        v = ini["theta0"]
        if _is_num(v):
            v = [v] * M
        theta0 = _array("initial.theta0", v, (M,), maximum=1e3)
    else:
        theta0 = np.zeros(M)
    used = {"generator", "theta0"}

    def only(keys, what):
        for k in ini:
            if k not in used | set(keys):
                raise ScenarioError(f"initial.{k}", f"not used with {what}")

    if gen is None:
        if "agent" not in ini:
            raise ScenarioError("initial.generator",
                                "missing: give generator = \"paper\" or \"random\", or [[initial.agent]] tables")
        only({"agent"}, "explicit [[initial.agent]] tables")
        agents = ini["agent"]
        if not isinstance(agents, list) or not all(isinstance(a, dict) for a in agents):
            raise ScenarioError("initial.agent", "must be an array of tables ([[initial.agent]])")
        if len(agents) != N:
            raise ScenarioError("initial.agent", f"must have one table per agent ({N}), got {len(agents)}")
        for i, a in enumerate(agents):
            kp = f"initial.agent[{i + 1}]"
            _check_keys(kp, a, AGENT_KEYS)
            if "axis_angle" in a and "quaternion" in a:
                raise ScenarioError(f"{kp}.quaternion", "give axis_angle or quaternion, not both")
            R = np.eye(3)
            if "axis_angle" in a:
                aa = _array(f"{kp}.axis_angle", a["axis_angle"], (4,))
                ax = aa[:3]
                if np.linalg.norm(ax) == 0:
                    raise ScenarioError(f"{kp}.axis_angle", "axis must be non-zero")
                R = se3.R_a(aa[3], ax / np.linalg.norm(ax))
            elif "quaternion" in a:
                q = _array(f"{kp}.quaternion", a["quaternion"], (4,))
                if np.linalg.norm(q) == 0:
                    raise ScenarioError(f"{kp}.quaternion", "must be non-zero")
                R = se3.quat_to_rot(q)
            p = _array(f"{kp}.position", a.get("position", [0.0, 0.0, 0.0]), (3,))
            xi = _array(f"{kp}.velocity", a.get("velocity", [0.0] * 6), (6,))
            S0[i, layout.P] = p
            S0[i, layout.R] = R.ravel()
            S0[i, layout.XI] = xi
        return S0, theta0
    if gen == "paper":
        only({"axis", "eigenvector"}, "generator = \"paper\"")
        if ("axis" in ini) == ("eigenvector" in ini):
            raise ScenarioError("initial.axis", "generator = \"paper\" needs exactly one of axis or eigenvector")
        if "axis" in ini:
            v = _array("initial.axis", ini["axis"], (3,))
            if np.linalg.norm(v) == 0:
                raise ScenarioError("initial.axis", "must be non-zero")
            v = v / np.linalg.norm(v)
        else:
            e = _num("initial.eigenvector", ini["eigenvector"], integer=True)
            if e not in (1, 2, 3):
                raise ScenarioError("initial.eigenvector", f"must be 1, 2 or 3, got {e}")
            v = weighting.eig()[1][:, e - 1]
        return paper_state(N, v, weighting), theta0
    if gen == "random":
        only({"seed", "position_box", "velocity_ball"}, "generator = \"random\"")
        seed = _num("initial.seed", ini.get("seed", 0), integer=True)
        if seed < 0:
            raise ScenarioError("initial.seed", f"must be >= 0, got {seed}")
        box = _num("initial.position_box", ini.get("position_box", 1.0), nonneg=True,
                   maximum=MAX_MAGNITUDE)
        ball = _num("initial.velocity_ball", ini.get("velocity_ball", 0.0), nonneg=True,
                    maximum=MAX_MAGNITUDE)
        return random_state(np.random.default_rng(seed), N, box, ball), theta0
    raise ScenarioError("initial.generator", f"must be \"paper\" or \"random\", got {_fmtv(gen)}")


DESIGN_KEYS = ("case", "u_c1", "u_c2", "delta_star", "gamma", "delta", "gamma_bound",
               "delta_bound", "exact_gap", "warnings", "Theta", "eigenvalues_W")


def design_summary(scenario) -> dict:
    """The synergy design as the summary, `check` and the log report it."""
    d = scenario.design.as_dict()
    return {k: d[k] for k in DESIGN_KEYS}
