"""Output profiles (bridge.output, issue 14): encode -> MAVLink bytes -> the loopback vehicle's
decoder gives back the wrench within each profile's quantisation; the PX4 attitude approximation
against the plant; config errors; closed-loop lockstep HIL with each profile, bit-identical to the
quantised reference and converging."""
from __future__ import annotations

import math
import os

import numpy as np
import pytest

os.environ.setdefault("MAVLINK20", "1")

from _bridge import VehicleThread, free_base_port, load  # noqa: E402

from bridge.mavlink import output as out  # noqa: E402
from bridge.mavlink.link import mavlink2  # noqa: E402

M = mavlink2

EDGES = [(0, 1), (1, 2), (2, 3), (1, 4), (4, 5)]   # hil_6uav's graph, 0-based
J6 = np.diag([0.043, 0.041, 0.082])
MW = (50.0, 50.0, 50.0, 20.0, 20.0, 20.0)


def _roundtrip(msg):
    """Pack with one MAVLink object, parse with another (what the wire does)."""
    tx = mavlink2.MAVLink(None, srcSystem=255, srcComponent=191)
    rx = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    buf = msg.pack(tx)
    m = rx.parse_char(bytearray(buf))
    assert m is not None and m.get_type() == msg.get_type()
    return m


def _quat(rng):
    q = rng.normal(size=4)
    return q / np.linalg.norm(q)


def _wire(rng, omega_scale=3.0):
    w = np.zeros(13)
    w[0:3] = rng.normal(size=3)
    w[3:7] = _quat(rng)
    w[7:10] = omega_scale * rng.normal(size=3)
    w[10:13] = rng.normal(size=3)
    return w.astype(np.float32).astype(np.float64)   # what the vehicle sends


def test_ardusub_manual_control_roundtrip_within_quantisation():
    rng = np.random.default_rng(1)
    prof = out.profile(out.ARDUSUB_MANUAL_CONTROL, h=0.004, max_wrench=MW)
    mav = mavlink2.MAVLink(None, srcSystem=255, srcComponent=191)
    for _ in range(300):
        c = rng.uniform(-1, 1, 6)
        m = _roundtrip(prof.message(mav, c, target=3, k=0, lockstep=True))
        assert m.target == 3 and m.enabled_extensions == 0b11 and 0 <= m.z <= 1000
        d = prof.decode(m)
        # per axis: half a step of ±1000 (x, y, r, s, t) and of 0..1000 over [−1, 1] (z)
        assert np.all(np.abs(d[:5] - c[:5]) <= 0.5e-3 + 1e-12), d - c
        assert abs(d[5] - c[5]) <= 1e-3 + 1e-12
        assert np.array_equal(d, prof.quantize(c))   # the reference applies the same numbers
    # axis assignment: x forward = fx, z > 500 = up = −fz (FRD), t = roll τx, s = pitch τy, r = yaw τz
    x, y, z, r, s, t = out.manual_control_axes([0.1, 0.2, 0.3, 0.4, 0.5, 0.6])
    assert (x, y, z, r, s, t) == (400, 500, 200, 300, 200, 100)
    # without the enable bits, s and t carry nothing
    assert np.array_equal(out.manual_control_controls(0, 0, 500, 0, 700, 700, 0), np.zeros(6))


def test_px4_attitude_thrust_roundtrip_and_exact_inverse():
    rng = np.random.default_rng(2)
    h = 0.004
    prof = out.profile(out.PX4_ATTITUDE_THRUST, h=h, J=J6, max_wrench=MW)
    mav = mavlink2.MAVLink(None, srcSystem=255, srcComponent=191)
    # float32 rounding of q_d: each component moves by ≤ 2^-24 |q_i|, so the rotation between the
    # sent and received attitudes is ≤ 2·‖δq‖ ≤ 2·2^-24·2 rad; ω̇ = 2(w − ωh)/h² carries it ×2/h².
    dw = 4 * 2.0 ** -24 * 1.01
    bound = np.linalg.norm(J6, 2) * 2 * dw / h ** 2
    worst = 0.0
    for k in range(300):
        c = rng.uniform(-1, 1, 6)
        wire = _wire(rng)
        m = _roundtrip(prof.message(mav, c, target=2, k=k, lockstep=True, wire=wire))
        assert m.time_boot_ms == k * 4 and m.type_mask == out.PX4_TYPE_MASK
        d = prof.decode(m, wire)
        tau, tau_d = np.asarray(c[:3]) * MW[:3], d[:3] * MW[:3]
        worst = max(worst, float(np.abs(tau - tau_d).max()))
        assert np.all(np.abs(tau - tau_d) <= bound), (tau - tau_d, bound)
        assert np.array_equal(d[3:], np.float32(c[3:]).astype(float))   # thrust_body: float32 exactly
        assert np.array_equal(d, prof.quantize(c, wire))
    assert worst > 0  # the float32 attitude does quantise the torque
    # without the wire's rounding the inverse is exact to float64 rounding
    att = out.AttitudeThrust(J6, h, MW[:3])
    for _ in range(50):
        tau = rng.uniform(-50, 50, 3)
        q, om = _quat(rng), rng.normal(size=3) * 3
        back = att.torque(att.attitude_setpoint(tau, q, om), q, om)
        assert np.allclose(back, tau, rtol=0, atol=1e-6 * 50)


@pytest.mark.parametrize("name", out.PROFILES)
def test_every_profile_keeps_the_tables_contract(name):
    """Every entry of the profile table (the bridge and the loopback vehicle use nothing else):
    its message, packed and parsed, carries the key it is dispatched on and the target; it
    decodes to exactly what `quantize` gives the reference; its lockstep stamp says "this step"
    at k and "a repeat" one step later; invalid contents decode to None, not to a command."""
    rng = np.random.default_rng(7)
    cls = out.PROFILE_CLASSES[name]
    assert out.PROFILE_BY_KEY[cls.key()] is cls and (name in out.WRENCH_PROFILES) == cls.carries_wrench
    prof = out.profile(name, h=0.004, J=J6, max_wrench=MW, group_mlx=0, actuator_index_offset=0)
    mav = mavlink2.MAVLink(None, srcSystem=255, srcComponent=191)
    for k in range(1, 50):
        c, wire = rng.uniform(-1, 1, 6), _wire(rng)
        m = _roundtrip(prof.message(mav, c, target=4, k=k, lockstep=True, wire=wire))
        assert (m.get_msgId(), getattr(m, "command", None) if cls.command is not None else None) == cls.key()
        assert cls.target(m) == 4
        assert np.array_equal(prof.decode(m, wire), prof.quantize(c, wire))
        stamps = prof.stamps(m, k)
        if stamps is None:
            assert not cls.resend_ok   # no stamp: lockstep by sequence, never re-sent
        else:
            assert stamps == (True, False) and prof.stamps(m, k + 1) == (False, True)
            assert prof.stamp(k) != prof.stamp(k + 1)
    # contents no vehicle may act on
    bad = {out.ACTUATOR_CONTROL_TARGET: lambda: mav.set_actuator_control_target_encode(0, 3, 1, 1, [0.0] * 8),
           out.DO_SET_ACTUATOR: lambda: mav.command_long_encode(1, 1, M.MAV_CMD_DO_SET_ACTUATOR, 0,
                                                                0, 0, 0, 0, 0, 0, 7.0),
           out.ARDUSUB_MANUAL_CONTROL: lambda: mav.manual_control_encode(1, 0, 0, 1500, 0, 0, 0, 3, 0, 0),
           out.PX4_ATTITUDE_THRUST: lambda: out.AttitudeTargetMessage(0, 1, 1, out.PX4_TYPE_MASK,
                                                                       [2.0, 0, 0, 0], [0, 0, 0])}
    assert prof.decode(_roundtrip(bad[name]()), _wire(rng)) is None


def _rot(q):
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def test_px4_attitude_setpoint_against_the_plant_is_third_order():
    """R_d = R exp(ωh + ½ω̇h²) vs the plant FMU driven by the constant torque for h: the angle
    between them is O(h³) (halving h divides it by ≈ 8)."""
    from plant_fmu.fast import FleetFMU

    rng = np.random.default_rng(3)
    q0 = _quat(rng)
    R0 = _rot(q0)
    om0 = np.array([2.0, -1.5, 1.0])
    tau = np.array([3.0, -2.0, 1.5])
    errs = []
    for h in (0.016, 0.008, 0.004):
        att = out.AttitudeThrust(J6, h, MW[:3])
        Rd = _rot(att.attitude_setpoint(tau, q0, om0))
        f = FleetFMU(1, instance_name="approx")
        try:
            f.set_parameters(mass=[2.4], J=J6.reshape(1, 3, 3), p0=np.zeros((1, 3)), R0=R0.reshape(1, 3, 3),
                             xi0=np.concatenate([om0, np.zeros(3)]).reshape(1, 6), gravity=np.zeros(3),
                             h_internal=h / 64)
            f.initialize(0.0)
            f.set_input(np.concatenate([tau, np.zeros(3)]).reshape(1, 6))
            f.do_step(0.0, h)
            Rh = f.get_state()[0, 3:12].reshape(3, 3)
        finally:
            f.close()
        cosang = (np.trace(Rd.T @ Rh) - 1) / 2
        errs.append(math.acos(min(1.0, cosang)) if cosang < 1 else 0.0)
    print("px4_attitude_thrust: attitude error vs plant for h = 16, 8, 4 ms:", errs)
    assert errs[0] < 1e-3
    for a, b in zip(errs, errs[1:]):
        assert 5.0 < a / b < 12.0, errs   # third order: ratio 8


def test_config_errors_name_the_key():
    from cosim.scenario import ScenarioError

    from bridge.mavlink.config import parse_bridge

    with pytest.raises(ScenarioError) as e:
        parse_bridge({"output": "ardusub_manual_control"}, 2)
    assert "bridge.max_wrench" in str(e.value) and "limits" in str(e.value)
    with pytest.raises(ScenarioError) as e:
        parse_bridge({"output": "px4_attitude_thrust", "mapping": "allocation", "max_wrench": list(MW)}, 2)
    assert "bridge.mapping" in str(e.value)
    with pytest.raises(ScenarioError) as e:
        parse_bridge({"vehicle": [{"id": 2, "output": "px4_attitude_thrust"}]}, 2)
    assert "bridge.max_wrench" in str(e.value) and "vehicle 2" in str(e.value)
    with pytest.raises(ScenarioError) as e:
        parse_bridge({"output": "manual"}, 2)
    assert "bridge.output" in str(e.value)
    cfg = parse_bridge({"vehicle": [{"id": 2, "output": "px4_attitude_thrust", "max_wrench": list(MW)}]}, 2)
    assert [v.output for v in cfg.vehicles] == ["actuator_control_target", "px4_attitude_thrust"]


def _hil_vs_reference(sc, n_steps):
    """Lockstep HIL (vehicles in a thread) and QuantizedPlant under the same controller: returns
    max |S_hil − S_ref|, the per-step max |vehicle wrench − controller wrench| (N, N·m), the HIL
    sync errors at the start and end, and the plant stats."""
    from bridge.mavlink.plant import MavlinkPlant
    from bridge.mavlink.transport import QuantizedPlant
    from cosim.master import make_controller

    with VehicleThread(scenario=sc, lockstep=True, aux_rate=0) as srv:
        p = MavlinkPlant(sc, lockstep=True, connect_timeout=10, on_event=lambda s: None)
        q = QuantizedPlant(sc)
        mw = np.array([v.mapping.max_wrench for v in p.cfg.vehicles])
        try:
            p.connect()
            c1, c2 = make_controller("hybrid", sc), make_controller("hybrid", sc)
            diff, werr = 0.0, []
            for _ in range(n_steps):
                S1, S2 = p.read(), q.read()
                diff = max(diff, float(np.abs(S1 - S2).max()))
                u1, _ = c1.step_state(S1, sc.step)
                p.apply(u1)
                q.apply(c2.step_state(S2, sc.step)[0])
                p.advance(sc.step)
                q.advance(sc.step)
                wv = np.stack([v.wrench for v in srv.vehicles])
                werr.append(np.abs(wv - p._controls * mw).max(axis=0))
            diff = max(diff, float(np.abs(p.read() - q.read()).max()))
            return diff, np.array(werr), p.stats(), srv.stats(), p.read().copy()
        finally:
            p.close()
            q.close()


def _sync_error(S, edges):
    """max over the graph's edges of ‖I − R_jᵀR_i‖_F + ‖R_jᵀ(p_i − p_j)‖ (the pose of X_j⁻¹X_i
    against the identity: zero when synchronised)."""
    e = 0.0
    for i, j in edges:
        Ri, Rj = S[i, 3:12].reshape(3, 3), S[j, 3:12].reshape(3, 3)
        e = max(e, np.linalg.norm(np.eye(3) - Rj.T @ Ri) + np.linalg.norm(Rj.T @ (S[i, 0:3] - S[j, 0:3])))
    return float(e)


MIXED = ("bridge.vehicle=[{id = 1, output = \"px4_attitude_thrust\"}, {id = 2, output = \"px4_attitude_thrust\"}, "
         "{id = 3, output = \"actuator_control_target\"}, {id = 4, output = \"do_set_actuator\"}]")


@pytest.mark.realtime
@pytest.mark.parametrize("profile", ["ardusub_manual_control", "px4_attitude_thrust", "mixed"])
def test_closed_loop_lockstep_each_profile(profile):
    """hil_6uav for 2 s (500 steps) over UDP with the profile: bit-identical to the quantised
    reference, the vehicles' wrench equals the controller's within the profile's quantisation,
    and the synchronisation error falls as in the unquantised co-simulation."""
    from cosim.master import Master
    from cosim.plants import FmuPlant

    port = free_base_port(6)
    if profile == "mixed":   # per-vehicle profiles: 1, 2 PX4; 3 #139; 4 #187; 5, 6 ArduSub
        sc = load([f"bridge.base_port={port}", "bridge.output=\"ardusub_manual_control\"", MIXED])
        assert [v.output for v in sc.bridge.vehicles] == ["px4_attitude_thrust"] * 2 + [
            "actuator_control_target", "do_set_actuator"] + ["ardusub_manual_control"] * 2
    else:
        sc = load([f"bridge.base_port={port}", f"bridge.output=\"{profile}\""])
    n = 500
    diff, werr, st, vst, S_hil = _hil_vs_reference(sc, n)
    assert diff == 0.0, diff
    assert st["rejected"] == 0 and st["malformed"] == 0 and vst["rejected"] == 0
    assert min(vst["steps"]) == max(vst["steps"]) == n
    ardusub = np.array([0.5e-3 * 50] * 3 + [0.5e-3 * 20] * 2 + [1e-3 * 20]) * (1 + 1e-9)
    dw = 4 * 2.0 ** -24 * 1.01
    px4 = np.array([np.linalg.norm(J6, 2) * 2 * dw / sc.step ** 2] * 3 + [20 * 2.0 ** -24] * 3)
    bound = ardusub if profile == "ardusub_manual_control" else px4 if profile == "px4_attitude_thrust" \
        else np.maximum(ardusub, px4)
    assert np.all(werr <= bound), (werr.max(axis=0), bound)
    print(f"{profile}: |vehicle wrench - controller wrench| over {n} steps (τx τy τz N·m, fx fy fz N): "
          f"max {werr.max(axis=0)}, rms {np.sqrt((werr ** 2).mean(axis=0))}")
    # convergence: the synchronisation error falls like the exact (unquantised) co-simulation's
    fp = FmuPlant.from_scenario(sc)
    try:
        e0 = _sync_error(fp.read(), EDGES)
        Master(sc, fp, "hybrid").run(n)
        e_exact = _sync_error(fp.read(), EDGES)
    finally:
        fp.close()
    e_hil = _sync_error(S_hil, EDGES)
    print(f"{profile}: sync error {e0:.4g} -> HIL {e_hil:.4g}, exact co-simulation {e_exact:.4g}")
    assert e_exact < 0.8 * e0
    assert abs(e_hil - e_exact) < 0.05 * (e0 - e_exact)


def _attitude_thrust_torque_error(h: float, T: float = 1.0):
    """hil_6uav under the hybrid law for T s at step h on the exact plant: per step and vehicle,
    the torque a vehicle realising px4_attitude_thrust's R_d exactly would apply, minus the
    controller's torque. The exact torque τ* reaches R_d from (R, ω) in h; the plant with τ reaches
    R(h), so τ* − τ = (2/h²) J log(R(h)ᵀ R_d) to leading order (∂R(h)/∂τ = (h²/2) J⁻¹ + O(h³))."""
    from controller import se3
    from cosim.controllers import make_controller
    from cosim.plants import FmuPlant

    sc = load([f"simulation.step={h}"])
    fp = FmuPlant.from_scenario(sc)
    ctrl = make_controller("hybrid", sc)
    atts = [out.AttitudeThrust(J, h, MW[:3]) for J in sc.inertias]
    dtau, tau = [], []
    try:
        for _ in range(int(round(T / h))):
            S = fp.read().copy()
            u = np.array(ctrl.step_state(S, h)[0], copy=True)
            fp.apply(u)
            fp.advance(h)
            S1 = fp.read()
            for i, att in enumerate(atts):
                R, om = S[i, 3:12].reshape(3, 3), S[i, 12:15]
                Rd = se3.quat_to_rot(np.array(att.attitude_setpoint(u[i, :3], se3.rot_to_quat(R), om)))
                e = se3.log_so3(S1[i, 3:12].reshape(3, 3).T @ Rd)
                dtau.append(2.0 / h ** 2 * np.asarray(sc.inertias[i]) @ e)
                tau.append(u[i, :3])
    finally:
        fp.close()
    return np.array(dtau), np.array(tau)


def test_px4_attitude_thrust_torque_error_over_a_run():
    """The approximation's wrench error against the exact wrench over a closed-loop run: first
    order in h (the attitude error is third order, divided by h²), and small against the torque."""
    e4, t4 = _attitude_thrust_torque_error(0.004)
    e2, _ = _attitude_thrust_torque_error(0.002)
    rms4, rms2 = np.sqrt((e4 ** 2).mean()), np.sqrt((e2 ** 2).mean())
    print(f"px4_attitude_thrust over 1 s of hil_6uav: |τ* − τ| max {np.abs(e4).max():.3g} N·m, "
          f"rms {rms4:.3g} N·m at h = 4 ms (max |τ| {np.abs(t4).max():.3g} N·m); "
          f"max {np.abs(e2).max():.3g}, rms {rms2:.3g} at h = 2 ms")
    assert 1.7 < rms4 / rms2 < 2.4, (rms4, rms2)
    assert np.abs(e4).max() < 0.01 * np.abs(t4).max()
