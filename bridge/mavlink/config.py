"""The scenario's ``[bridge]`` table: schema, defaults and validation (`parse_bridge`).

Every problem raises ``controller.errors.ConfigError("bridge.<key path>", reason)``; the scenario
loader prefixes the file name. The table is registered with the scenario loader as the entry point
``se3sync.tables: bridge`` (pyproject.toml). Every key: docs/reference/scenario.md (``[bridge]``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

from .frames import WORLD_FRAMES
from .airframes import FRAMES
from .mapping import DIRECT, MAPPINGS, AllocationSpec, MappingSpec
from .output import PROFILES, WRENCH_PROFILES

from controller.errors import ConfigError as ScenarioError
from controller.errors import Se3SyncError

OUTPUTS = PROFILES
ROUTINGS = ("per_vehicle", "shared")

# key -> default (documented in docs/reference/scenario.md)
# a loopback vehicle locked to a swarm's timeline (`se3sync vehicle --start-file`) ticks this
# share of a step before each step is due: the tick's states must reach the agents before their
# deadline, and each command then has the rest of the period to arrive before the tick that
# applies it (`MavlinkPlant` counts the commands that did not: ``commands_past_tick``)
VEHICLE_TICK_LEAD = 0.3

DEFAULTS = {
    "world_frame": "ned",
    "output": "actuator_control_target",
    "group_mlx": 0,
    "actuator_index_offset": 0,
    "mapping": "direct",
    "max_wrench": [1.0, 1.0, 1.0, 10.0, 10.0, 10.0],
    "allocation": None,
    "gravity_compensation": False,
    "routing": "per_vehicle",
    "host": "127.0.0.1",
    "base_port": 14540,
    "endpoints": None,
    "system_ids": None,
    "source_system": 255,
    "source_component": 191,
    "heartbeat_period": 1.0,
    "heartbeat_timeout": 3.0,
    "stale_after": 0.1,
    "link_timeout": 0.5,
    "connect_timeout": 10.0,
    "lockstep": False,
    "lockstep_resend": 0.05,
    "lockstep_timeout": 5.0,
    "key_file": None,
    "signing_state": None,
    "allow_unsigned_heartbeat": False,
    "tlog": None,
    "arm": False,
    "odometry_rate": 0.0,
    "vehicle": None,
}
ALLOCATION_KEYS = {"arm_length", "tilt_deg", "max_thrust", "torque_coeff", "reversible", "frame"}
VEHICLE_KEYS = {"id", "system_id", "endpoint", "mapping", "max_wrench", "allocation", "output"}


@dataclass
class VehicleLinkSpec:
    agent: int                 # 1-based agent index in the scenario
    system_id: int
    endpoint: str              # the bridge's side, pymavlink syntax (udpin:HOST:PORT | udpout:HOST:PORT)
    mapping: MappingSpec
    output: str = "actuator_control_target"   # the vehicle's output profile (bridge.output)


@dataclass
class BridgeConfig:
    n_agents: int
    vehicles: list = field(default_factory=list)       # [VehicleLinkSpec]
    world_frame: str = "ned"
    output: str = "actuator_control_target"
    group_mlx: int = 0
    actuator_index_offset: int = 0
    gravity_compensation: bool = False
    routing: str = "per_vehicle"
    host: str = "127.0.0.1"
    base_port: int = 14540
    source_system: int = 255
    source_component: int = 191
    heartbeat_period: float = 1.0
    heartbeat_timeout: float = 3.0
    stale_after: float = 0.1
    link_timeout: float = 0.5
    connect_timeout: float = 10.0
    lockstep: bool = False
    lockstep_resend: float = 0.05
    lockstep_timeout: float = 5.0
    key_file: str | None = None
    signing_state: str | None = None   # persisted signing timestamps (default: <key_file>.bridge.signing.json)
    allow_unsigned_heartbeat: bool = False
    tlog: str | None = None
    arm: bool = False
    odometry_rate: float = 0.0

    @property
    def mappings(self) -> list:
        return [v.mapping for v in self.vehicles]

    def with_endpoints(self, endpoints) -> "BridgeConfig":
        """A copy whose vehicles use these bridge-side endpoints (from the command line)."""
        if len(endpoints) != self.n_agents:
            raise ScenarioError("bridge.endpoints", f"need one endpoint per vehicle ({self.n_agents}), "
                                f"got {len(endpoints)}")
        vs = [replace(v, endpoint=check_endpoint("--vehicle", e)) for v, e in zip(self.vehicles, endpoints)]
        return replace(self, vehicles=vs)


def default_endpoint(system_id: int, base_port: int, host: str, routing: str) -> str:
    """PX4 SITL convention: instance n (system id n+1) talks to HOST:base_port+n."""
    if routing == "shared":
        return f"udpin:{host}:{base_port}"
    return f"udpin:{host}:{base_port + system_id - 1}"


def check_endpoint(key: str, e) -> str:
    if not isinstance(e, str):
        raise ScenarioError(key, f"must be an endpoint string like \"udpin:127.0.0.1:14540\", got {e!r}")
    parts = e.split(":")
    if len(parts) != 3 or parts[0] not in ("udpin", "udpout", "udp"):
        raise ScenarioError(key, f"must be udpin:HOST:PORT or udpout:HOST:PORT, got {e!r}")
    try:
        port = int(parts[2])
    except ValueError:
        port = -1
    if not 0 <= port <= 65535:
        raise ScenarioError(key, f"port must be an integer in 0..65535, got {parts[2]!r}")
    return e


def _bool(key, v) -> bool:
    if not isinstance(v, bool):
        raise ScenarioError(key, f"must be true or false, got {v!r}")
    return v


def _int(key, v, lo=None, hi=None) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise ScenarioError(key, f"must be an integer, got {v!r}")
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        raise ScenarioError(key, f"must be in {lo}..{hi}, got {v}")
    return v


def _float(key, v, positive=False, nonneg=False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ScenarioError(key, f"must be a number, got {v!r}")
    v = float(v)
    if not math.isfinite(v):
        raise ScenarioError(key, f"must be finite, got {v}")
    if positive and not v > 0:
        raise ScenarioError(key, f"must be > 0, got {v:g}")
    if nonneg and not v >= 0:
        raise ScenarioError(key, f"must be >= 0, got {v:g}")
    return v


def _choice(key, v, choices) -> str:
    if v not in choices:
        raise ScenarioError(key, f"must be one of {', '.join(repr(c) for c in choices)}, got {v!r}")
    return v


def _str(key, v) -> str:
    if not isinstance(v, str) or not v:
        raise ScenarioError(key, f"must be a non-empty string, got {v!r}")
    return v


def _max_wrench(key, v) -> tuple:
    if not isinstance(v, list) or len(v) != 6:
        raise ScenarioError(key, f"must be an array of 6 numbers (τx, τy, τz, fx, fy, fz), got {v!r}")
    return tuple(_float(f"{key}[{i + 1}]", x, positive=True) for i, x in enumerate(v))


def _allocation(key, v, base: AllocationSpec) -> AllocationSpec:
    if not isinstance(v, dict):
        raise ScenarioError(key, f"must be a table, got {v!r}")
    for k in v:
        if k not in ALLOCATION_KEYS:
            raise ScenarioError(f"{key}.{k}", f"unknown key (allowed: {', '.join(sorted(ALLOCATION_KEYS))})")
    kw = {}
    for k in ("arm_length", "max_thrust"):
        if k in v:
            kw[k] = _float(f"{key}.{k}", v[k], positive=True)
    if "frame" in v:
        if v["frame"] not in FRAMES:
            raise ScenarioError(f"{key}.frame", f"must be one of {', '.join(repr(f) for f in FRAMES)}, "
                                f"got {v['frame']!r}")
        kw["frame"] = v["frame"]
        kw["tilt_deg"] = FRAMES[v["frame"]].default_tilt
    if "tilt_deg" in v:
        t = _float(f"{key}.tilt_deg", v["tilt_deg"])
        if not -90 < t < 90:
            raise ScenarioError(f"{key}.tilt_deg", f"must be in (-90, 90) (0: untilted, not fully actuated; "
                                f"< 0: tilted the other way), got {t:g}")
        kw["tilt_deg"] = t
    if "torque_coeff" in v:
        kw["torque_coeff"] = _float(f"{key}.torque_coeff", v["torque_coeff"], nonneg=True)
    if "reversible" in v:
        kw["reversible"] = _bool(f"{key}.reversible", v["reversible"])
    return replace(base, **kw)


def parse_bridge(table: dict, n_agents: int) -> BridgeConfig:
    """Validates a ``[bridge]`` table for ``n_agents`` vehicles."""
    if table is None:
        table = {}
    if not isinstance(table, dict):
        raise ScenarioError("bridge", f"must be a table, got {table!r}")
    for k in table:
        if k not in DEFAULTS:
            raise ScenarioError(f"bridge.{k}", f"unknown key (allowed: {', '.join(sorted(DEFAULTS))})")
    t = {**DEFAULTS, **table}
    N = int(n_agents)
    cfg = BridgeConfig(n_agents=N)
    cfg.world_frame = _choice("bridge.world_frame", t["world_frame"], WORLD_FRAMES)
    cfg.output = _choice("bridge.output", t["output"], OUTPUTS)
    cfg.group_mlx = _int("bridge.group_mlx", t["group_mlx"], 0, 255)
    cfg.actuator_index_offset = _int("bridge.actuator_index_offset", t["actuator_index_offset"], 0, 250)
    cfg.gravity_compensation = _bool("bridge.gravity_compensation", t["gravity_compensation"])
    cfg.routing = _choice("bridge.routing", t["routing"], ROUTINGS)
    cfg.host = _str("bridge.host", t["host"])
    cfg.base_port = _int("bridge.base_port", t["base_port"], 1, 65535)
    cfg.source_system = _int("bridge.source_system", t["source_system"], 1, 255)
    cfg.source_component = _int("bridge.source_component", t["source_component"], 0, 255)
    for k in ("heartbeat_period", "heartbeat_timeout", "stale_after", "link_timeout", "connect_timeout",
              "lockstep_resend", "lockstep_timeout"):
        setattr(cfg, k, _float(f"bridge.{k}", t[k], positive=True))
    cfg.lockstep = _bool("bridge.lockstep", t["lockstep"])
    cfg.allow_unsigned_heartbeat = _bool("bridge.allow_unsigned_heartbeat", t["allow_unsigned_heartbeat"])
    cfg.arm = _bool("bridge.arm", t["arm"])
    cfg.odometry_rate = _float("bridge.odometry_rate", t["odometry_rate"], nonneg=True)
    if t["key_file"] is not None:
        cfg.key_file = _str("bridge.key_file", t["key_file"])
    if t["signing_state"] is not None:
        cfg.signing_state = _str("bridge.signing_state", t["signing_state"])
    if t["tlog"] is not None:
        cfg.tlog = _str("bridge.tlog", t["tlog"])

    kind = _choice("bridge.mapping", t["mapping"], MAPPINGS)
    mw = _max_wrench("bridge.max_wrench", t["max_wrench"])
    alloc = AllocationSpec()
    if t["allocation"] is not None:
        alloc = _allocation("bridge.allocation", t["allocation"], alloc)
    base_map = MappingSpec(kind=kind, max_wrench=mw, allocation=alloc)

    if t["system_ids"] is None:
        sids = list(range(1, N + 1))
    else:
        v = t["system_ids"]
        if not isinstance(v, list) or len(v) != N:
            raise ScenarioError("bridge.system_ids", f"must be an array of {N} system ids, got {v!r}")
        sids = [_int(f"bridge.system_ids[{i + 1}]", x, 1, 254) for i, x in enumerate(v)]
    if t["endpoints"] is None:
        eps = [default_endpoint(s, cfg.base_port, cfg.host, cfg.routing) for s in sids]
    else:
        v = t["endpoints"]
        if not isinstance(v, list) or len(v) != N:
            raise ScenarioError("bridge.endpoints", f"must be an array of {N} endpoint strings, got {v!r}")
        eps = [check_endpoint(f"bridge.endpoints[{i + 1}]", e) for i, e in enumerate(v)]
    maps = [base_map] * N
    outs = [cfg.output] * N
    mw_given = ["max_wrench" in table] * N

    if t["vehicle"] is not None:
        vl = t["vehicle"]
        if not isinstance(vl, list) or not all(isinstance(x, dict) for x in vl):
            raise ScenarioError("bridge.vehicle", "must be an array of tables ([[bridge.vehicle]])")
        for j, vt in enumerate(vl, start=1):
            kp = f"bridge.vehicle[{j}]"
            for k in vt:
                if k not in VEHICLE_KEYS:
                    raise ScenarioError(f"{kp}.{k}", f"unknown key (allowed: {', '.join(sorted(VEHICLE_KEYS))})")
            if "id" not in vt:
                raise ScenarioError(f"{kp}.id", "missing required key (the agent number, 1..N)")
            i = _int(f"{kp}.id", vt["id"], 1, N) - 1
            m = maps[i]
            if "mapping" in vt:
                m = replace(m, kind=_choice(f"{kp}.mapping", vt["mapping"], MAPPINGS))
            if "max_wrench" in vt:
                m = replace(m, max_wrench=_max_wrench(f"{kp}.max_wrench", vt["max_wrench"]))
                mw_given[i] = True
            if "output" in vt:
                outs[i] = _choice(f"{kp}.output", vt["output"], OUTPUTS)
            if "allocation" in vt:
                m = replace(m, allocation=_allocation(f"{kp}.allocation", vt["allocation"], m.allocation))
            maps[i] = m
            if "system_id" in vt:
                sids[i] = _int(f"{kp}.system_id", vt["system_id"], 1, 254)
                if t["endpoints"] is None:
                    eps[i] = default_endpoint(sids[i], cfg.base_port, cfg.host, cfg.routing)
            if "endpoint" in vt:
                eps[i] = check_endpoint(f"{kp}.endpoint", vt["endpoint"])
    if len(set(sids)) != N:
        raise ScenarioError("bridge.system_ids", f"system ids must be distinct, got {sids}")
    if cfg.source_system in sids:
        raise ScenarioError("bridge.source_system", f"{cfg.source_system} is also a vehicle's system id")
    if cfg.routing == "per_vehicle" and len(set(eps)) != N:
        raise ScenarioError("bridge.endpoints", "with routing = \"per_vehicle\" every vehicle needs its own "
                            f"endpoint, got {eps}")
    _check_wrench_profiles(outs, maps, mw_given)
    cfg.vehicles = [VehicleLinkSpec(agent=i + 1, system_id=sids[i], endpoint=eps[i], mapping=maps[i],
                                    output=outs[i]) for i in range(N)]
    return cfg


def _check_wrench_profiles(outs, maps, mw_given) -> None:
    """The ArduSub and PX4 profiles carry the wrench normalised per axis: the flight stack allocates,
    so the mapping must be direct and the limits (the wrench at ±1) must be the vehicle's own."""
    for i, (o, m, given) in enumerate(zip(outs, maps, mw_given)):
        if o not in WRENCH_PROFILES:
            continue
        if m.kind != DIRECT:
            raise ScenarioError("bridge.mapping", f"vehicle {i + 1}: output {o!r} sends the normalised wrench "
                                f"(the flight stack allocates), so the mapping must be \"direct\", got {m.kind!r}")
        if not given:
            raise ScenarioError("bridge.max_wrench", f"vehicle {i + 1}: output {o!r} needs the vehicle's wrench "
                                "limits (τx, τy, τz in N·m, fx, fy, fz in N at ±1 per axis): set bridge.max_wrench "
                                "or [[bridge.vehicle]] max_wrench")


def default_config(n_agents: int) -> BridgeConfig:
    return parse_bridge({}, n_agents)


def read_key_file(path) -> bytes:
    """A signing key file: exactly 32 raw bytes, or 64 hexadecimal characters (whitespace and a
    trailing newline allowed). Raises Se3SyncError on anything else."""
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise Se3SyncError(f"key file {path}: cannot read: {exc.strerror or exc}") from None
    if len(data) == 32:
        return data
    try:
        text = "".join(data.decode("ascii").split())
        if len(text) == 64:
            return bytes.fromhex(text)
    except (UnicodeDecodeError, ValueError):
        pass
    raise Se3SyncError(f"key file {path}: must hold 32 raw bytes or 64 hex characters, "
                       f"got {len(data)} bytes")
