"""The plant's optional terms (issue 30): the ground plane and linear drag, in the C model that every
vehicle mode and the co-simulation use. Checked against closed-form motion (free fall, constant
net force, exponential decay) and the contact rules of docs/reference/plant-fmu.md "Ground and drag"."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from plant_fmu.fast import FleetFMU, FMUError

G = 9.80665
M = 3.0
J = np.diag([0.03, 0.03, 0.05])
HIL = str(Path(__file__).resolve().parents[2] / "scenarios" / "hil_6uav.toml")


def _body(p0, *, R0=None, xi0=None, h_internal=1e-3, g=(0.0, 0.0, G), **terms):
    """One body in a NED world (gravity down = +z); a ground at height 0 means the plane z = 0."""
    S0 = np.zeros((1, 18))
    S0[0, 0:3] = p0
    S0[0, 3:12] = (np.eye(3) if R0 is None else np.asarray(R0)).ravel()
    if xi0 is not None:
        S0[0, 12:18] = xi0
    f = FleetFMU(1)
    f.set_initial_state(S0, mass=[M], J=J[None], gravity=list(g), h_internal=h_internal, **terms)
    f.initialize()
    return f


def _rot_x(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _run(f, u, h, n):
    """n steps of h with body wrench u; returns the states (n+1, 18) and the contact flags."""
    S, C = [f.get_state()[0].copy()], [bool(f.get_contact()[0])]
    for k in range(n):
        f.set_input(np.asarray(u, float).reshape(1, 6))
        f.do_step(k * h, h)
        S.append(f.get_state()[0].copy())
        C.append(bool(f.get_contact()[0]))
    return np.array(S), np.array(C)


@pytest.mark.parametrize("fraction", [0.0, 0.999])
def test_rests_on_the_ground_for_10_s(fraction):
    """Zero thrust and thrust just below the weight: the body stays put (issue: within 1 mm for 10 s)."""
    f = _body([0.0, 0.0, 0.0], ground=True)
    try:
        S, C = _run(f, [0.0, 0.0, 0.0, 0.0, 0.0, -fraction * M * G], 0.004, 2500)
    finally:
        f.close()
    assert C.all()
    assert np.abs(S[:, 0:3]).max() <= 1e-3
    assert np.abs(S[:, 12:18]).max() == 0.0           # resting: nothing moves at all
    assert np.array_equal(S[:, 3:12], np.tile(np.eye(3).ravel(), (len(S), 1)))


def test_released_when_thrust_exceeds_weight():
    """T = 1.01 m g up: it lifts off at once and climbs with a = (T − m g)/m (exact for RK4: a
    constant acceleration gives a quadratic)."""
    T = 1.01 * M * G
    h, n = 0.004, 250
    f = _body([0.0, 0.0, 0.0], ground=True)
    try:
        S, C = _run(f, [0.0, 0.0, 0.0, 0.0, 0.0, -T], h, n)
    finally:
        f.close()
    a = (T - M * G) / M
    t = np.arange(n + 1) * h
    assert C[0] and not C[1:].any()
    assert np.abs(-S[:, 2] - 0.5 * a * t ** 2).max() < 1e-9
    assert np.abs(-S[:, 17] - a * t).max() < 1e-9    # v_z (NED, body level): upward


@pytest.mark.parametrize("tilt_deg", [30.0, 60.0])
def test_tilted_body_lifts_off_when_the_vertical_thrust_exceeds_the_weight(tilt_deg):
    """The net force along up decides: thrust T along the body's −z at roll φ lifts off only when
    T cos φ > m g."""
    R0 = _rot_x(math.radians(tilt_deg))
    T_lift = M * G / math.cos(math.radians(tilt_deg))
    for factor, flies in ((0.999, False), (1.001, True)):
        f = _body([0.0, 0.0, 0.0], R0=R0, ground=True)
        try:
            S, C = _run(f, [0.0, 0.0, 0.0, 0.0, 0.0, -factor * T_lift], 0.004, 50)
        finally:
            f.close()
        assert C[-1] == (not flies)
        assert (S[-1, 2] < -1e-9) == flies and S[:, 2].max() <= 0.0


@pytest.mark.parametrize("h_internal, h", [(1e-4, 0.004), (1e-3, 0.004), (0.01, 0.01), (0.05, 0.1),
                                           (0.2, 0.2), (1.0, 1.0)])
def test_a_drop_from_2_m_stops_at_the_ground_at_every_step_size(h_internal, h):
    """Free fall from 2 m (0.64 s): at every step size, including steps longer than the whole fall
    (1 s: 4.9 m of free fall), the body never goes below the plane and ends resting on it, with no
    bounce (once down, it stays down)."""
    f = _body([0.0, 0.0, -2.0], xi0=[0.3, -0.2, 0.5, 0.4, -0.1, 0.0], h_internal=h_internal, ground=True)
    try:
        n = int(math.ceil(2.0 / h))
        S, C = _run(f, np.zeros(6), h, n)
    finally:
        f.close()
    assert S[:, 2].max() <= 1e-12                        # never below (NED: z > 0 is below)
    assert C[-1] and abs(S[-1, 2]) <= 1e-12 and np.abs(S[-1, 12:18]).max() == 0.0
    k = int(np.argmax(C))                                # first step that ends on the ground
    assert C[k:].all() and np.abs(S[k:, 2] - S[k, 2]).max() == 0.0
    # before touchdown it fell freely: z = −2 + g t²/2 (the spin does not matter for the centre of mass;
    # RKMK4's error on the spinning body's translation is O(h⁴): 1e-6 m at the 0.2 s steps)
    t = np.arange(k) * h
    assert np.abs(S[:k, 2] - (-2.0 + 0.5 * G * t ** 2)).max() < 1e-5


def test_ground_height_along_up_in_any_frame():
    """The plane is {p : e·p = ground_height}, e = −g/|g|: in an ENU-like world (g along −z) a ground
    at 5 m stops a body at z = 5; with gravity along a slanted axis, at e·p = height."""
    for g, height, p0 in (((0.0, 0.0, -G), 5.0, [1.0, 2.0, 7.0]),
                          ((G / math.sqrt(2), 0.0, -G / math.sqrt(2)), -1.0, [0.0, 0.0, 0.0])):
        e = -np.asarray(g) / np.linalg.norm(g)
        f = _body(p0, g=g, ground=True, ground_height=height)
        try:
            S, C = _run(f, np.zeros(6), 0.01, 300)
        finally:
            f.close()
        hgt = S[:, 0:3] @ e - height
        assert hgt.min() >= -1e-12 and C[-1] and abs(hgt[-1]) <= 1e-12


def test_linear_drag_decays_as_the_exponential():
    """Gravity-free, no ground: v(t) = v0 exp(−c t/m), ω(t) = ω0 exp(−c_w t/J) about a principal axis
    (RK4's error on exp is ~(h/T)⁵/120 per step: far below the tolerance)."""
    c, cw = 0.6, 0.004
    v0, w0 = 1.5, 2.0
    f = _body([0.0, 0.0, 0.0], xi0=[0.0, 0.0, w0, v0, 0.0, 0.0], g=(0.0, 0.0, 0.0), drag_linear=c,
              drag_angular=cw)
    try:
        S, C = _run(f, np.zeros(6), 0.01, 200)
    finally:
        f.close()
    t = np.arange(201) * 0.01
    assert not C.any()
    assert np.abs(np.linalg.norm(S[:, 15:18], axis=1) - v0 * np.exp(-c * t / M)).max() < 1e-9
    assert np.abs(S[:, 14] - w0 * np.exp(-cw * t / J[2, 2])).max() < 1e-9
    # the distance travelled: ∫v = v0 m/c (1 − exp(−c t/m)) (the body spins about z, v along body x)
    assert abs(np.linalg.norm(S[-1, 0:3]) - v0 * M / c * (1 - math.exp(-c * t[-1] / M))) < 1e-3


def test_terms_off_and_far_ground_give_the_plain_trajectory():
    """A ground far below and zero drag take the terms' code path (one body at a time) but must give
    the plain model's trajectory: the only extra operations subtract exact zeros."""
    xi0 = [0.7, -1.1, 0.4, 0.3, 0.2, -0.5]
    u = [0.01, -0.02, 0.03, 0.5, -0.4, -20.0]
    a = _body([0.0, 0.0, -5.0], xi0=xi0)
    b = _body([0.0, 0.0, -5.0], xi0=xi0, ground=True, ground_height=-1e5)
    try:
        Sa, _ = _run(a, u, 0.004, 300)
        Sb, Cb = _run(b, u, 0.004, 300)
    finally:
        a.close()
        b.close()
    assert not Cb.any()
    assert np.array_equal(Sa, Sb)


def test_contact_survives_fmu_state_round_trips():
    f = _body([0.0, 0.0, -0.5], ground=True)
    try:
        _run(f, np.zeros(6), 0.01, 100)                  # fallen and resting
        assert f.get_contact()[0]
        blob = f.serialize_fmu_state(f.get_fmu_state())
        S1, C1 = _run(f, [0, 0, 0, 0, 0, -2 * M * G], 0.01, 10)
        f.set_fmu_state(f.deserialize_fmu_state(blob))
        assert f.get_contact()[0]
        S2, C2 = _run(f, [0, 0, 0, 0, 0, -2 * M * G], 0.01, 10)
    finally:
        f.close()
    assert np.array_equal(S1, S2) and np.array_equal(C1, C2) and not C1[1:].any()


@pytest.mark.parametrize("terms, p0, g, message", [
    (dict(ground=True), [0.0, 0.0, 0.0], (0.0, 0.0, 0.0), "needs a nonzero gravity"),
    (dict(ground=True, ground_height=1.0), [0.0, 0.0, 0.0], (0.0, 0.0, G), "below the ground"),
    (dict(drag_linear=-1.0), [0.0, 0.0, -1.0], (0.0, 0.0, G), "drag_linear"),
    (dict(drag_linear=1e4), [0.0, 0.0, -1.0], (0.0, 0.0, G), "time constant"),
    (dict(drag_angular=100.0), [0.0, 0.0, -1.0], (0.0, 0.0, G), "time constant"),
])
def test_terms_are_validated_at_initialization(terms, p0, g, message):
    with pytest.raises(FMUError, match=message):
        _body(p0, g=g, **terms)


def test_ground_flag_is_zero_or_one():
    from plant_fmu import layout

    f = FleetFMU(1)
    try:
        f.set_real([layout.VR_GROUND], [0.5])
        with pytest.raises(FMUError, match="ground = 0.5 must be 0"):
            f.initialize()
    finally:
        f.close()


def test_scenario_keys_reach_every_plant():
    """[plant] ground/ground_height/drag_*: parsed, checked, passed to the co-simulation's plants (both
    modes) and to the vehicles' reference fleet; off by default (no terms at all)."""
    from bridge.mavlink.transport import VehicleFleet
    from cosim.plants import FmuPlant, PerBodyFmuPlant
    from cosim.scenario import load_scenario

    base = HIL
    assert load_scenario(base).plant_terms == {}
    sc = load_scenario(base, ["plant.gravity=[0.0, 0.0, 9.80665]", "plant.ground=true",
                              "plant.ground_height=-3.0", "plant.drag_linear=0.2"])
    assert sc.plant_terms == dict(ground=True, ground_height=-3.0, drag_linear=0.2)
    e = np.array([0.0, 0.0, -1.0])
    for plant in (FmuPlant.from_scenario(sc), PerBodyFmuPlant.from_scenario(sc)):
        try:
            for k in range(500):                     # 2 s: every body falls (< 3.1 m) onto the plane
                plant.apply(np.zeros((sc.n_agents, 6)))
                plant.advance(sc.step)
                hgt = plant.read()[:, 0:3] @ e + 3.0
                assert hgt.min() >= -1e-12
            assert np.abs(hgt).max() <= 1e-12 and np.abs(plant.read()[:, 12:18]).max() == 0.0
        finally:
            plant.close()
    fleet = VehicleFleet(sc, "ned")
    try:
        for k in range(500):
            fleet.step(np.zeros((sc.n_agents, 6)), sc.step)
        assert fleet.fmu.get_contact().all()
    finally:
        fleet.close()


@pytest.mark.parametrize("overrides, key", [
    (["plant.ground=true"], "plant.ground"),                                    # gravity-free
    (["plant.gravity=[0.0, 0.0, 9.8]", "plant.ground=1"], "plant.ground"),      # not a bool
    (["plant.gravity=[0.0, 0.0, 9.8]", "plant.ground=true", "plant.ground_height=4.0"], "plant.ground_height"),
    (["plant.ground_height=1.0"], "plant.ground_height"),                        # without a ground
    (["plant.drag_linear=-0.1"], "plant.drag_linear"),
    (["plant.drag_linear=1e5"], "plant.drag_linear"),                            # time constant < step
    (["plant.drag_angular=1e3"], "plant.drag_angular"),
])
def test_scenario_keys_are_checked_with_one_line(overrides, key):
    from cosim.scenario import ScenarioError, load_scenario

    with pytest.raises(ScenarioError) as exc:
        load_scenario(HIL, overrides)
    assert key in str(exc.value) and "\n" not in str(exc.value)


def test_loopback_vehicle_stands_on_the_ground():
    """The loopback vehicle (`se3sync vehicle --scenario`) uses the same plant terms: with zero thrust
    it rests on the plane; 1.2× its weight of thrust lifts it at (T − m g)/m."""
    import socket

    from bridge.vehicles.loopback import VehicleServer
    from cosim.scenario import load_scenario

    sc = load_scenario(str(Path(HIL).with_name("sitl_1uav.toml")), ["plant.drag_linear=0.0"])
    free = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    free.bind(("127.0.0.1", 0))
    srv = VehicleServer(scenario=sc, endpoints=[f"udpout:127.0.0.1:{free.getsockname()[1]}"], lockstep=True)
    try:
        v = srv.vehicles[0]
        v.armed, v.failsafe = True, False
        for k in range(250):
            v.step(sc.step)
        assert v.fmu.get_contact()[0] and np.abs(v.S[0:3]).max() == 0.0
        m = float(sc.masses[0])
        v.wrench[:] = [0.0, 0.0, 0.0, 0.0, 0.0, -1.2 * m * G]
        for k in range(100):
            v.step(sc.step)
        t = 100 * sc.step
        assert not v.fmu.get_contact()[0] and abs(-v.S[2] - 0.5 * 0.2 * G * t ** 2) < 1e-9
    finally:
        srv.close()
        free.close()
