"""One rigid body of the plant FMU as a flight stack's simulator sees it (shared by
`bridge.sim_px4` and `bridge.sim_ardupilot`): NED world, FRD body, actuator outputs decoded with
the scenario's mapping, ideal sensors (specific force, rates, magnetic field, pressure, geodetic
position) plus optional white noise.

The plant has no ground contact. A flight stack expects to start at rest on the ground (its
pre-arm checks read the accelerometer's −g), so the body is *held* — it does not move and its
accelerometer reads the support force −Rᵀg — until the stack arms/spins its motors
(`release()`); from then on it moves freely under the decoded wrench and gravity.
"""
from __future__ import annotations

import math

import numpy as np

from controller import layout
from plant_fmu.fast import FleetFMU

from .config import default_config
from .mapping import FleetMapping
from .transport import vehicle_setup

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


def ned_to_geodetic(p_ned) -> tuple:
    """Flat-Earth (local tangent plane) NED -> (lat°, lon°, alt m) around the home point."""
    lat = HOME_LAT + math.degrees(p_ned[0] / EARTH_RADIUS)
    lon = HOME_LON + math.degrees(p_ned[1] / (EARTH_RADIUS * math.cos(math.radians(HOME_LAT))))
    return lat, lon, HOME_ALT - p_ned[2]


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


class SimBody:
    """A single-body FleetFMU in NED/FRD with the scenario's mass, inertia, pose and mapping."""

    def __init__(self, mass, J, S0_ned, g_ned, h_internal: float, mapping_spec, name: str = "sim"):

        self.mass = float(mass)
        self.g = np.asarray(g_ned, float)
        self.mapping = FleetMapping([mapping_spec])
        self.fmu = FleetFMU(1, instance_name=name)
        S0 = np.asarray(S0_ned, float).reshape(1, layout.S_WIDTH)
        self.fmu.set_initial_state(S0, mass=[self.mass], J=np.asarray(J, float).reshape(1, 3, 3),
                                   gravity=self.g, h_internal=h_internal)
        self.fmu.initialize(0.0)
        self.t = 0.0
        self.held = True
        self.wrench = np.zeros(6)
        self._read()

    def _read(self):
        self.S = self.fmu.get_state()[0].copy()
        self.q = self.fmu.get_quat()[0].copy()

    def release(self) -> None:
        self.held = False

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
        """What an accelerometer at the centre of mass reads (body FRD): f/m when free, −Rᵀg held."""
        if self.held:
            return -(self.R.T @ self.g)
        return self.wrench[3:6] / self.mass

    def step(self, controls, h: float) -> None:
        """Decode the actuator outputs with the mapping and advance h (held: time only)."""
        c = np.asarray(controls, float)[:6]
        c = np.where(np.isfinite(c), np.clip(c, -1.0, 1.0), 0.0)
        if not self.held:
            self.wrench = self.mapping.decode(c.reshape(1, 6))[0]
            self.fmu.set_input(self.wrench.reshape(1, 6))
            self.fmu.do_step(self.t, h)
            self._read()
        self.t += h

    def close(self) -> None:
        self.fmu.close()


def bodies_from_scenario(scenario, name: str):
    """One SimBody per agent, in NED/FRD (`transport.vehicle_setup`), with its mapping."""

    cfg = scenario.bridge or default_config(scenario.n_agents)
    m, J, S0, g = vehicle_setup(scenario, cfg.world_frame)
    return [SimBody(m[i], J[i], S0[i], g, scenario.internal_step, cfg.mappings[i], f"{name}{i + 1}")
            for i in range(scenario.n_agents)]
