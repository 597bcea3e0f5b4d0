"""What the MAVLink path does to numbers, as plain functions, and the reference plant that
applies exactly the same transformations without a network.

The state travels as float32 (ODOMETRY: position NED, quaternion w-first, body FRD rates and
velocity); the wrench travels as float32 actuator controls in [-1, 1] (or rotor thrusts). An
unmodified co-simulation therefore cannot match a HIL run to 1e-9. `QuantizedPlant` wraps a
fleet of bodies simulated in the vehicles' NED/FRD frames and passes every number through the
very functions the MAVLink path uses (float32 rounding, frame conversion, quaternion ->
rotation matrix, feed-forward, mapping, float32 controls, inverse mapping), so the lockstep HIL
run and this reference agree bit for bit.

The "wire" state of a vehicle is 13 numbers: [x, y, z, qw, qx, qy, qz, ωx, ωy, ωz, vx, vy, vz]
(NED position, quaternion of R_ned_frd, FRD body rates and velocity), each a float32 value.
"""
from __future__ import annotations

import math

import numpy as np

from controller import layout
from plant_fmu.fast import FleetFMU

from controller.se3 import quat_to_rot_row

from . import frames
from .config import default_config
from .mapping import FleetMapping
from .output import profile

WIRE = 13


def f32(x: np.ndarray) -> np.ndarray:
    """Round to float32 and back (what a MAVLink float field does)."""
    return np.asarray(x, dtype=np.float64).astype(np.float32).astype(np.float64)


def state_to_wire(S_ned: np.ndarray, q: np.ndarray) -> np.ndarray:
    """The vehicle side: (n,18) NED/FRD states and (n,4) quaternions -> (n,13) float32 values."""
    S_ned = np.asarray(S_ned, dtype=np.float64)
    out = np.empty((S_ned.shape[0], WIRE))
    out[:, 0:3] = S_ned[:, layout.P]
    out[:, 3:7] = q
    out[:, 7:13] = S_ned[:, layout.XI]
    return f32(out)


def wire_row_to_state(w, world: str) -> list:
    """`wire_to_state` of one wire row (13 floats) as a list of 18 floats: the same operations in
    the same order (`quat_to_rot_row`; the frame change only permutes and negates), so the same
    bits, without numpy's per-call cost (a vehicle's state and each neighbour's, every step)."""
    w = [float(x) for x in w]
    R = quat_to_rot_row(w[3], w[4], w[5], w[6])
    if world == "ned":
        return w[0:3] + R + w[7:13]
    # ENU/FLU: p = P_W p, R = P_W R P_B (rows 1, 0, −2; then columns 1, 2 negated), ξ = P_B ξ
    return [w[1], w[0], -w[2],
            R[3], -R[4], -R[5], R[0], -R[1], -R[2], -R[6], R[7], R[8],
            w[7], -w[8], -w[9], w[10], -w[11], -w[12]]


def wire_to_state(wire: np.ndarray, world: str) -> np.ndarray:
    """The bridge side: (n,13) wire values -> (n,18) [p, R, ξ] in the scenario's frames."""
    wire = np.asarray(wire, dtype=np.float64)
    if wire.shape[0] == 1:
        return np.array([wire_row_to_state(wire[0].tolist(), world)])
    S = np.empty((wire.shape[0], layout.S_WIDTH))
    S[:, layout.P] = wire[:, 0:3]
    S[:, layout.R] = frames.quat_to_rot(wire[:, 3:7])
    S[:, layout.XI] = wire[:, 7:13]
    return frames.state_ned_to_world(S, world)


def gravity_feedforward(S: np.ndarray, masses: np.ndarray, g: np.ndarray) -> np.ndarray:
    """(n,3) body force −m Rᵀ g that cancels gravity g (world frame, the plant's gravity)."""
    R = S[:, layout.R]
    out = np.empty((S.shape[0], 3))
    for i in range(3):  # (Rᵀ g)_i = R[0,i] g0 + R[1,i] g1 + R[2,i] g2, in that order
        out[:, i] = -masses * (R[:, i] * g[0] + R[:, 3 + i] * g[1] + R[:, 6 + i] * g[2])
    return out


class Transport:
    """The numeric path of the bridge for a fleet: state in, wrench out (and its inverse)."""

    def __init__(self, mappings, world: str = "ned", masses=None, gravity=None,
                 gravity_compensation: bool = False):
        self.mapping = mappings if isinstance(mappings, FleetMapping) else FleetMapping(mappings)
        self.n = self.mapping.n
        self.world = world
        self.masses = np.ones(self.n) if masses is None else np.asarray(masses, float)
        self.gravity = np.zeros(3) if gravity is None else np.asarray(gravity, float)
        self.gravity_compensation = bool(gravity_compensation)
        self.nan_commands = 0

    def controls(self, u: np.ndarray, S: np.ndarray) -> np.ndarray:
        """Controller wrench u (n,6) [τ; f] in the scenario body frame, at state S (scenario
        frames) -> actuator controls (n,6), float64 (the wire rounds them to float32)."""
        if self.mapping.one_direct:
            return np.array([self.controls_row(u, S)])
        u = np.asarray(u, dtype=np.float64)
        if not np.all(np.isfinite(u)):
            self.nan_commands += 1
            u = np.where(np.isfinite(u), u, 0.0)
        w = frames.body_to_frd(u, self.world)
        base = None
        if self.gravity_compensation:
            ff = np.zeros((self.n, 6))
            ff[:, 3:6] = gravity_feedforward(S, self.masses, self.gravity)
            base = frames.body_to_frd(ff, self.world)
        return self.mapping.encode(w, base)

    def controls_row(self, u, S) -> list:
        """`controls` of one vehicle with the direct mapping (``mapping.one_direct``), in plain
        floats (the same operations in the same order as the fleet's numpy path, so the same
        bits)."""
        u = np.asarray(u, dtype=np.float64).reshape(6).tolist()
        if not all(math.isfinite(x) for x in u):
            self.nan_commands += 1
            u = [x if math.isfinite(x) else 0.0 for x in u]
        enu = self.world != "ned"
        if enu:   # body_to_frd: P_B on each group of 3
            u = [u[0], -u[1], -u[2], u[3], -u[4], -u[5]]
        base = None
        if self.gravity_compensation:
            R = np.asarray(S, dtype=np.float64).reshape(-1)[layout.R].tolist()
            m = float(self.masses[0])
            g0, g1, g2 = self.gravity.tolist()
            f = [-m * (R[i] * g0 + R[3 + i] * g1 + R[6 + i] * g2) for i in range(3)]
            # body_to_frd of [0, f] (P_B negates the zero torque too: −0.0, as numpy does)
            base = [0.0, -0.0, -0.0, f[0], -f[1], -f[2]] if enu else [0.0, 0.0, 0.0, *f]
        return self.mapping.encode_row(u, base)

    def wrench_frd(self, controls: np.ndarray) -> np.ndarray:
        """Vehicle side: controls (n,6) as received (float32 values) -> FRD wrench."""
        return self.mapping.decode(controls)


class VehicleFleet:
    """N bodies in one FleetFMU, simulated in the vehicles' NED/FRD frames, exactly as the
    loopback vehicle sets up each of its single-body FMUs."""

    def __init__(self, scenario, world: str, fmu_path=None):
        n = scenario.n_agents
        self.n = n
        self.fmu = FleetFMU(n, fmu_path=fmu_path, instance_name="reference")
        m, J, S0, g = vehicle_setup(scenario, world)
        self.fmu.set_initial_state(S0, mass=m, J=J, gravity=g, h_internal=scenario.internal_step,
                                   **scenario.plant_terms)
        self.fmu.initialize(0.0)
        self.k = 0

    def wire(self) -> np.ndarray:
        return state_to_wire(self.fmu.get_state(), self.fmu.get_quat())

    def step(self, wrench_frd: np.ndarray, h: float) -> None:
        self.fmu.set_input(wrench_frd)
        self.fmu.do_step(self.k * h, h)
        self.k += 1

    def close(self) -> None:
        self.fmu.close()


def vehicle_setup(scenario, world: str):
    """(mass, J_frd, S0_ned, g_ned) per vehicle, as both the loopback vehicle and the reference
    fleet use them."""
    S0 = frames.state_world_to_ned(scenario.S0, world)
    g = frames.world_to_ned_p(np.asarray(scenario.gravity, float)[None, :], world)[0]
    J = np.stack([frames.P_B @ J @ frames.P_B for J in scenario.inertias]) if world == "enu" \
        else np.asarray(scenario.inertias, float)
    return np.asarray(scenario.masses, float), J, S0, g


class QuantizedPlant:
    """A cosim Plant that is the MAVLink path without the network: the reference for lockstep HIL.

    ``read()`` returns the state the bridge would decode; ``apply(u)`` maps the wrench exactly as
    the bridge, rounds the controls to float32 and inverts the mapping as the vehicle does.
    """

    def __init__(self, scenario, config=None, fmu_path=None):
        cfg = config if config is not None else (scenario.bridge or default_config(scenario.n_agents))
        self.config = cfg
        self.n = scenario.n_agents
        self.world = cfg.world_frame
        self.transport = Transport(cfg.mappings, cfg.world_frame, scenario.masses, scenario.gravity,
                                   cfg.gravity_compensation)
        # the vehicle decodes with its own (identical) mapping, one vehicle at a time or not:
        self.vehicle_mapping = FleetMapping(cfg.mappings)
        self.fleet = VehicleFleet(scenario, cfg.world_frame, fmu_path=fmu_path)
        self._wire = self.fleet.wire()
        self._S = wire_to_state(self._wire, self.world)
        self._w = np.zeros((self.n, 6))
        # each vehicle's output profile quantises its command its own way (bridge.output)
        self.profiles = profiles_for(cfg, scenario)
        self._per_profile = any(p.carries_wrench for p in self.profiles)

    def read(self) -> np.ndarray:
        return self._S

    def apply(self, u) -> None:
        c = self.transport.controls(u, self._S)
        if self._per_profile:
            cq = np.stack([p.quantize(c[i], self._wire[i]) for i, p in enumerate(self.profiles)])
        else:
            cq = f32(c)
        self._w = self.vehicle_mapping.decode(cq)

    def advance(self, h: float) -> None:
        self.fleet.step(self._w, h)
        self._wire = self.fleet.wire()
        self._S = wire_to_state(self._wire, self.world)

    def stats(self) -> dict:
        m = self.transport.mapping
        return {"saturations": int(m.saturations), "nan_commands": int(self.transport.nan_commands)}

    def close(self) -> None:
        self.fleet.close()


def profiles_for(config, scenario) -> list:
    """One output profile (`output.OutputProfile`) per vehicle of a BridgeConfig (J in FRD: `transport.vehicle_setup`)."""
    _, J, _, _ = vehicle_setup(scenario, config.world_frame)
    return [profile(v.output, h=scenario.step, J=J[i], max_wrench=v.mapping.max_wrench,
                    group_mlx=config.group_mlx, actuator_index_offset=config.actuator_index_offset)
            for i, v in enumerate(config.vehicles)]
