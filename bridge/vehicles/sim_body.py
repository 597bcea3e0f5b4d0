"""One rigid body of the plant FMU as a flight stack's simulator sees it (shared by
`bridge.vehicles.sim_px4` and `bridge.vehicles.sim_ardupilot`): NED world, FRD body, actuator outputs decoded with
the scenario's mapping, sensors (specific force, rates, magnetic field, pressure, geodetic
position) plus optional white noise (`Noise`).

The ground. With ``[plant] ground = true`` the plant FMU has a ground plane (docs/reference/plant-fmu.md,
"Ground and drag"): the body rests on it until the thrust lifts it, touches down without bouncing,
and its accelerometer reads the support force −Rᵀg while it rests (``landed``). Without a ground
plane (the paper's gravity-free scenarios, or gravity with ``ground = false``) the body is *held*
at its initial pose — not moving, reading −Rᵀg — until the stack arms/spins its motors
(`release()`), and from then on it falls freely under the decoded wrench and gravity.

Divergence. A step whose result is not finite, or leaves |p| ≤ 1e6 m, |v| ≤ 1000 m/s,
|ω| ≤ 1000 rad/s (no multirotor gets there; a stack's mixer fighting a wrong frame can), raises
`Diverged`; the servers then put that body back at its initial state (`reset()`), count it and say
so, and the other vehicles go on.
"""
from __future__ import annotations

import math

import numpy as np

from controller import layout
from controller.errors import Se3SyncError
from plant_fmu.fast import FleetFMU, FMUError

from bridge.mavlink.config import default_config
from bridge.mavlink.mapping import FleetMapping
from bridge.mavlink.transport import vehicle_setup

# Home and Earth model. PX4's Gazebo worlds start at this point (Zürich); the magnetic field is an
# approximation of the World Magnetic Model there (declination ≈ 3°, inclination ≈ 63.5°,
# ≈ 0.48 gauss): good enough for a heading, not a survey.
HOME_LAT, HOME_LON, HOME_ALT = 47.397742, 8.545594, 488.0
EARTH_RADIUS = 6378137.0
MAG_DECL, MAG_INCL, MAG_GAUSS = math.radians(3.0), math.radians(63.5), 0.48
B_NED = MAG_GAUSS * np.array([math.cos(MAG_INCL) * math.cos(MAG_DECL), math.cos(MAG_INCL) * math.sin(MAG_DECL),
                              math.sin(MAG_INCL)])
G0 = 9.80665


def isa_pressure_hpa(alt_m: float) -> float:
    """International Standard Atmosphere (troposphere) static pressure at altitude (m), hPa."""
    return 1013.25 * (1.0 - 2.25577e-5 * alt_m) ** 5.25588


def isa_temperature_c(alt_m: float) -> float:
    return 15.0 - 0.0065 * alt_m


def ned_to_geodetic(p_ned, clamped: list | None = None) -> tuple:
    """Flat-Earth (local tangent plane) NED -> (lat°, lon°, alt m) around the home point (latitude
    clamped to ±90°, longitude wrapped to ±180°: any position gives a valid fix; a clamped latitude
    appends "lat" to ``clamped``)."""
    lat = HOME_LAT + math.degrees(p_ned[0] / EARTH_RADIUS)
    lon = HOME_LON + math.degrees(p_ned[1] / (EARTH_RADIUS * math.cos(math.radians(HOME_LAT))))
    if clamped is not None and not -90.0 <= lat <= 90.0:
        clamped.append("lat")
    return min(90.0, max(-90.0, lat)), (lon + 180.0) % 360.0 - 180.0, HOME_ALT - p_ned[2]


class Noise:
    """White-noise standard deviations per sample (0 = off). Defaults: the noise densities of the
    IMU model PX4's Gazebo simulation uses (gyro 3.4e-4 rad/s/√Hz, accelerometer 4e-3 m/s²/√Hz),
    converted to a per-sample σ = density/√h; magnetometer 5e-3 gauss; barometer 0.01 hPa."""

    def __init__(self, h: float, enabled: bool = True, seed: int = 0):
        k = 1.0 if enabled else 0.0
        self.h = float(h)
        self.gyro = k * 3.4e-4 / math.sqrt(h)
        self.accel = k * 4e-3 / math.sqrt(h)
        self.mag = k * 5e-3
        self.baro = k * 0.01
        self.rng = np.random.default_rng(seed)

    def add(self, x, sigma):
        return x + self.rng.normal(0.0, sigma, np.shape(x)) if sigma > 0 else np.asarray(x, float)


MAX_POSITION, MAX_SPEED, MAX_RATE = 1e6, 1e3, 1e3     # m, m/s, rad/s: beyond, a body has diverged


class Diverged(Se3SyncError):
    """A body's state is not finite or out of any physical range (see the module docstring)."""


class SimBody:
    """A single-body FleetFMU in NED/FRD with the scenario's mass, inertia, pose, mapping and
    optional plant terms (``terms``: ground, ground_height, drag_linear, drag_angular)."""

    def __init__(self, mass, J, S0_ned, g_ned, h_internal: float, mapping_spec, name: str = "sim",
                 terms=None):
        self.mass = float(mass)
        self.g = np.asarray(g_ned, float)
        self.terms = dict(terms or {})
        self.ground = bool(self.terms.get("ground", False))
        self.drag_linear = float(self.terms.get("drag_linear", 0.0))
        self.mapping = FleetMapping([mapping_spec])
        self._init = dict(S0=np.asarray(S0_ned, float).reshape(1, layout.S_WIDTH), mass=[self.mass],
                          J=np.asarray(J, float).reshape(1, 3, 3), gravity=self.g, h_internal=h_internal,
                          **self.terms)
        self.name = name
        self.fmu = FleetFMU(1, instance_name=name)
        self._start()
        self.t = 0.0
        self.resets = 0

    def _start(self) -> None:
        kw = dict(self._init)
        self.fmu.set_initial_state(kw.pop("S0"), **kw)
        self.fmu.initialize(0.0)
        self.held = not self.ground     # without a ground plane: held until the stack arms
        self.wrench = np.zeros(6)
        self._read()

    def _read(self):
        self.S = self.fmu.get_state()[0].copy()
        self.q = self.fmu.get_quat()[0].copy()
        self.contact = bool(self.fmu.get_contact()[0]) if self.ground else False

    def release(self) -> None:
        self.held = False

    def reset(self, clock: bool = False) -> None:
        """Back to the initial state (after a divergence the clock goes on; ``clock``: it restarts
        at 0 too, when the stack restarted)."""
        try:
            self.fmu.reset()
        except Se3SyncError:
            self.fmu.close()
            self.fmu = FleetFMU(1, instance_name=self.name)
        self._start()
        self.resets += 1
        if clock:
            self.t = 0.0

    @property
    def landed(self) -> bool:
        """Resting on the ground (or held there, without a ground plane)."""
        return self.held or self.contact

    @property
    def R(self) -> np.ndarray:
        return layout.rotations(self.S)

    @property
    def omega(self) -> np.ndarray:
        return self.S[layout.OMEGA] if not self.held else np.zeros(3)

    @property
    def v_ned(self) -> np.ndarray:
        return self.R @ self.S[layout.V] if not self.held else np.zeros(3)

    def specific_force(self) -> np.ndarray:
        """What an accelerometer at the centre of mass reads (body FRD): the support force −Rᵀg on the
        ground; in flight (f + f_drag)/m with the force of the step just taken and the drag at its end."""
        if self.landed:
            return -(self.R.T @ self.g)
        f = self.wrench[3:6]
        if self.drag_linear:
            f = f - self.drag_linear * self.S[layout.V]
        return f / self.mass

    def step(self, controls, h: float) -> None:
        """Decode the actuator outputs with the mapping and advance h (held: time only). Raises
        Diverged (the body is then unusable until reset())."""
        c = np.asarray(controls, float)[:6]
        c = np.where(np.isfinite(c), np.clip(c, -1.0, 1.0), 0.0)
        if not self.held:
            self.wrench = self.mapping.decode(c.reshape(1, 6))[0]
            self.fmu.set_input(self.wrench.reshape(1, 6))
            try:
                self.fmu.do_step(self.t, h)
            except FMUError as exc:
                self.t += h
                raise Diverged(f"{self.name}: {exc}") from None
            self._read()
            S = self.S
            if not (np.all(np.isfinite(S)) and np.abs(S[layout.P]).max() <= MAX_POSITION
                    and np.abs(S[layout.V]).max() <= MAX_SPEED and np.abs(S[layout.OMEGA]).max() <= MAX_RATE):
                self.t += h
                raise Diverged(f"{self.name}: state out of range at t = {self.t:.6g} s (|p| <= {MAX_POSITION:g} m, "
                               f"|v| <= {MAX_SPEED:g} m/s, |ω| <= {MAX_RATE:g} rad/s)")
        self.t += h

    def close(self) -> None:
        self.fmu.close()


def bodies_from_scenario(scenario, name: str):
    """One SimBody per agent, in NED/FRD (`transport.vehicle_setup`), with its mapping."""

    cfg = scenario.bridge or default_config(scenario.n_agents)
    m, J, S0, g = vehicle_setup(scenario, cfg.world_frame)
    terms = getattr(scenario, "plant_terms", {})
    return [SimBody(m[i], J[i], S0[i], g, scenario.internal_step, cfg.mappings[i], f"{name}{i + 1}", terms)
            for i in range(scenario.n_agents)]
