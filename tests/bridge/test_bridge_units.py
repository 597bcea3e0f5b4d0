"""Bridge pieces without a network: [bridge] schema, mappings, frames, state checks, framing."""
from __future__ import annotations

import os

import numpy as np
import pytest

os.environ.setdefault("MAVLINK20", "1")

from bridge.mavlink import frames  # noqa: E402
from bridge.mavlink.config import parse_bridge, read_key_file  # noqa: E402
from bridge.mavlink.link import Counters, Peer, split_datagram  # noqa: E402
from bridge.mavlink.mapping import AllocationSpec, FleetMapping, MappingSpec, hexarotor_matrix  # noqa: E402
from bridge.mavlink.state import StateTracker  # noqa: E402
from bridge.mavlink.transport import Transport, f32, state_to_wire, wire_to_state  # noqa: E402
from controller import se3  # noqa: E402
from controller.errors import Se3SyncError  # noqa: E402
from cosim.scenario import ScenarioError  # noqa: E402
from _bridge import HIL  # noqa: E402


# ----------------------------------------------------------------------------- schema
def test_defaults_and_px4_ports():
    cfg = parse_bridge({}, 3)
    assert cfg.world_frame == "ned" and cfg.output == "actuator_control_target"
    assert [v.endpoint for v in cfg.vehicles] == [f"udpin:127.0.0.1:{14540 + i}" for i in range(3)]
    assert [v.system_id for v in cfg.vehicles] == [1, 2, 3]
    shared = parse_bridge({"routing": "shared", "base_port": 15000}, 2)
    assert {v.endpoint for v in shared.vehicles} == {"udpin:127.0.0.1:15000"}


@pytest.mark.parametrize("table, key", [
    ({"foo": 1}, "bridge.foo"),
    ({"world_frame": "xyz"}, "bridge.world_frame"),
    ({"max_wrench": [1, 2, 3]}, "bridge.max_wrench"),
    ({"max_wrench": [1, 1, 1, 1, 1, -1]}, "bridge.max_wrench[6]"),
    ({"allocation": {"tilt_deg": 90}}, "bridge.allocation.tilt_deg"),
    ({"allocation": {"frame": "octo-x"}}, "bridge.allocation.frame"),
    ({"allocation": {"bogus": 1}}, "bridge.allocation.bogus"),
    ({"base_port": 70000}, "bridge.base_port"),
    ({"endpoints": ["udpin:127.0.0.1:1", "tcp:x:2"]}, "bridge.endpoints[2]"),
    ({"system_ids": [1, 1]}, "bridge.system_ids"),
    ({"vehicle": [{"id": 3}]}, "bridge.vehicle[1].id"),
    ({"vehicle": [{"id": 1, "mass": 3}]}, "bridge.vehicle[1].mass"),
    ({"lockstep": "yes"}, "bridge.lockstep"),
    ({"stale_after": -1}, "bridge.stale_after"),
])
def test_bad_tables_name_the_key(table, key):
    with pytest.raises(ScenarioError) as ei:
        parse_bridge(table, 2)
    assert ei.value.keypath == key
    assert "\n" not in str(ei.value)


def test_loader_reports_file_and_key():
    from cosim.scenario import load_scenario

    with pytest.raises(ScenarioError) as ei:
        load_scenario(HIL, ["bridge.nonsense=1"])
    msg = str(ei.value)
    assert msg.startswith(HIL) and "bridge.nonsense" in msg and "unknown key" in msg
    sc = load_scenario(HIL, ["bridge.vehicle=[{id = 2, mapping = \"allocation\"}]"])
    assert sc.bridge.vehicles[1].mapping.kind == "allocation" and sc.bridge.vehicles[0].mapping.kind == "direct"


def test_key_file_formats(tmp_path):
    key = bytes(range(32))
    (tmp_path / "raw").write_bytes(key)
    (tmp_path / "hex").write_text(key.hex() + "\n")
    (tmp_path / "bad").write_text("abc")
    assert read_key_file(tmp_path / "raw") == key
    assert read_key_file(tmp_path / "hex") == key
    with pytest.raises(Se3SyncError):
        read_key_file(tmp_path / "bad")


# ----------------------------------------------------------------------------- mappings
def test_direct_roundtrip_and_saturation():
    m = FleetMapping([MappingSpec(max_wrench=(1, 2, 3, 4, 5, 6))] * 2)
    w = np.array([[0.5, -1, 1.5, 2, -2.5, 3], [2, 0, 0, 0, 0, -12]])
    c = m.encode(w)
    assert np.allclose(c[0], [0.5, -0.5, 0.5, 0.5, -0.5, 0.5])
    assert np.allclose(c[1], [1, 0, 0, 0, 0, -1]) and m.saturations == 1
    assert np.allclose(m.decode(c)[0], w[0])


def test_hexarotor_is_fully_actuated_and_saturation_keeps_direction():
    spec = AllocationSpec(arm_length=0.25, tilt_deg=30, max_thrust=15, torque_coeff=0.016)
    A = hexarotor_matrix(spec)
    assert np.linalg.matrix_rank(A) == 6 and np.linalg.cond(A) < 50
    m = FleetMapping([MappingSpec(kind="allocation", allocation=spec)])
    # hover baseline: 2 kg under 9.81 m/s² (FRD: thrust up = −z)
    base = np.array([[0, 0, 0, 0, 0, -2 * 9.81]])
    w = np.array([[0.05, -0.02, 0.01, 1.0, 0.5, -1.0]])
    c = m.encode(w, base)
    assert np.all(c >= 0) and np.all(c <= 1) and m.saturations == 0
    assert np.allclose(m.decode(c), w + base)
    big = 100 * w
    c = m.encode(big, base)
    assert m.saturations == 1 and np.all(c >= -1e-12) and np.all(c <= 1 + 1e-12)
    got = m.decode(c) - base
    s = got[0] @ big[0] / (big[0] @ big[0])
    assert 0 < s < 1 and np.allclose(got, s * big, atol=1e-9)   # direction kept
    # no baseline and unidirectional rotors: a downward force cannot be made -> clipped
    c = m.encode(np.array([[0, 0, 0, 0, 0, 5.0]]))
    assert np.all(c >= 0) and m.saturations == 2
    rev = FleetMapping([MappingSpec(kind="allocation", allocation=AllocationSpec(reversible=True))])
    c = rev.encode(np.array([[0, 0, 0, 0, 0, 5.0]]))
    assert rev.saturations == 0 and np.allclose(rev.decode(c), [[0, 0, 0, 0, 0, 5.0]])


def test_batched_mapping_is_bitwise_per_vehicle():
    rng = np.random.default_rng(0)
    specs = [MappingSpec(kind="allocation", allocation=AllocationSpec(reversible=True)),
             MappingSpec(max_wrench=(3, 3, 3, 30, 30, 30))] * 3
    m = FleetMapping(specs)
    c = f32(rng.uniform(-1, 1, (6, 6)))
    whole = m.decode(c)
    for i in range(6):
        assert np.array_equal(FleetMapping([specs[i]]).decode(c[i:i + 1])[0], whole[i])


# ----------------------------------------------------------------------------- frames
def test_enu_conversion_exact_and_involutive():
    rng = np.random.default_rng(1)
    R = se3.random_rotation(rng, 5)
    S = np.concatenate([rng.normal(size=(5, 3)), R.reshape(5, 9), rng.normal(size=(5, 6))], axis=1)
    T = frames.state_world_to_ned(S, "enu")
    assert np.array_equal(frames.state_ned_to_world(T, "enu"), S)
    Rn = T[:, 3:12].reshape(5, 3, 3)
    assert np.allclose(Rn, frames.P_W @ R @ frames.P_B, atol=0)
    assert np.allclose(np.linalg.det(Rn), 1)
    assert np.array_equal(frames.state_world_to_ned(S, "ned"), S)


def test_wire_roundtrip_is_float32():
    rng = np.random.default_rng(2)
    R = se3.random_rotation(rng, 4)
    S = np.concatenate([rng.normal(size=(4, 3)), R.reshape(4, 9), rng.normal(size=(4, 6))], axis=1)
    q = se3.rot_to_quat(R)
    wire = state_to_wire(S, q)
    assert np.array_equal(wire, wire.astype(np.float32).astype(np.float64))
    back = wire_to_state(wire, "ned")
    assert np.allclose(back, S, atol=1e-6)
    assert np.abs(np.einsum("nji,njk->nik", back[:, 3:12].reshape(4, 3, 3),
                            back[:, 3:12].reshape(4, 3, 3)) - np.eye(3)).max() < 1e-15


def test_gravity_feedforward_cancels_gravity():
    rng = np.random.default_rng(3)
    R = se3.random_rotation(rng, 2)
    S = np.zeros((2, 18))
    S[:, 3:12] = R.reshape(2, 9)
    g = np.array([0, 0, -9.81])
    t = Transport([MappingSpec(max_wrench=(1, 1, 1, 100, 100, 100))] * 2, "enu", masses=[2.0, 3.0],
                  gravity=g, gravity_compensation=True)
    c = t.controls(np.zeros((2, 6)), S)
    f_body_frd = t.wrench_frd(c)[:, 3:]
    f_world = np.einsum("nij,nj->ni", R, frames.body_to_frd(np.concatenate([np.zeros((2, 3)), f_body_frd], 1), "enu")[:, 3:])
    assert np.allclose(f_world + np.array([2.0, 3.0])[:, None] * g, 0, atol=1e-12)


# ----------------------------------------------------------------------------- state checks
class _Odo:
    def __init__(self, t, q=(1, 0, 0, 0), x=0.0, frame=1, child=12):
        self.time_usec, self.q, self.x, self.y, self.z = t, list(q), x, 0.0, 0.0
        self.vx = self.vy = self.vz = self.rollspeed = self.pitchspeed = self.yawspeed = 0.0
        self.frame_id, self.child_frame_id = frame, child


def test_state_tracker_rejections():
    c = Counters()
    tr = StateTracker(c, stale_after=0.05)
    assert tr.on_odometry(_Odo(1_000_000), 10.0)
    assert not tr.on_odometry(_Odo(900_000), 10.01)                       # out of order
    assert not tr.on_odometry(_Odo(1_000_000), 10.01) and tr.duplicates == 1
    assert not tr.on_odometry(_Odo(1_100_000, x=float("nan")), 10.1)     # NaN
    assert not tr.on_odometry(_Odo(1_100_000, q=(1.01, 0, 0, 0)), 10.1)  # |q| = 1.01
    assert tr.on_odometry(_Odo(1_100_000, q=(1.0004, 0, 0, 0)), 10.1)    # within 1e-3
    assert not tr.on_odometry(_Odo(1_200_000), 10.3)                     # 0.1 s late: stale
    assert not tr.on_odometry(_Odo(1_300_000, frame=99), 10.3)
    assert dict(c.rejected) == {"out_of_order": 1, "nan": 1, "non_unit_quaternion": 1, "stale": 1,
                                "bad_frame": 1}
    # a vehicle reboot: time jumps back by more than 10 s and goes on from there; the third such
    # state in a row is taken, one or two never are
    c2 = Counters()
    tr2 = StateTracker(c2, check_stale=False)
    assert tr2.on_odometry(_Odo(50_000_000), 0)
    assert [tr2.on_odometry(_Odo(t), 0) for t in (1000, 2000, 50_000_001, 3000, 4000, 5000)] == \
        [False, False, True, False, False, True]
    assert tr2.reboots == 1 and tr2.time_usec == 5000 and dict(c2.rejected) == {"out_of_order": 4}


class _Att:
    def __init__(self, t_ms):
        self.time_boot_ms, self.q1, self.q2, self.q3, self.q4 = t_ms, 1.0, 0.0, 0.0, 0.0
        self.rollspeed = self.pitchspeed = self.yawspeed = 0.0


class _Pos:
    def __init__(self, t_ms, x=0.0):
        self.time_boot_ms, self.x, self.y, self.z = t_ms, x, 0.0, 0.0
        self.vx = self.vy = self.vz = 0.0


def test_odometry_after_the_fallback_starts_its_own_clock():
    """A vehicle sends ODOMETRY (time_usec: here the Unix epoch) and, more slowly, the fallback
    pair (time_boot_ms). When the pair is taken first, the ODOMETRY that follows is on another
    clock: it must not be judged by the pair's (it was refused as `future` for good, and the
    vehicle stayed on the fallback). From the first ODOMETRY on, the pair is not used."""
    c = Counters()
    tr = StateTracker(c, stale_after=0.1)
    w0, epoch_us = 100.0, 1_795_000_000_000_000
    assert not tr.on_attitude_quaternion(_Att(180), w0)
    assert tr.on_local_position_ned(_Pos(180, x=1.0), w0) and tr.source == "fallback"
    for k in range(1, 50):                      # ODOMETRY at 250 Hz from the next instant on
        assert tr.on_odometry(_Odo(epoch_us + 4000 * k, x=2.0), w0 + 0.004 * k), k
        assert tr.source == "odometry" and tr.wire[0] == 2.0
        if k % 5 == 0:                          # the pair still comes: ignored, never refused
            assert not tr.on_attitude_quaternion(_Att(180 + 4 * k), w0 + 0.004 * k)
            assert not tr.on_local_position_ned(_Pos(180 + 4 * k, x=9.0), w0 + 0.004 * k)
    assert tr.n_odometry == 49 and tr.wire[0] == 2.0 and not c.rejected
    # a vehicle on the fallback alone keeps its clock: a stale pair is still refused
    c2 = Counters()
    tr2 = StateTracker(c2, stale_after=0.1)
    tr2.on_attitude_quaternion(_Att(1000), w0)
    assert tr2.on_local_position_ned(_Pos(1000), w0)
    tr2.on_attitude_quaternion(_Att(1004), w0 + 0.5)
    assert not tr2.on_local_position_ned(_Pos(1004), w0 + 0.5) and dict(c2.rejected) == {"stale": 1}


def test_one_future_stamped_state_holds_no_window():
    """Issue 29 (the same fault as the agents' link, at the bridge): one ODOMETRY stamped 5 s
    ahead made every genuine state out of order (and, through the stale reference, stale)."""
    c = Counters()
    tr = StateTracker(c, stale_after=0.1)
    t0, w0 = 1_000_000, 100.0
    assert tr.on_odometry(_Odo(t0), w0)
    assert not tr.on_odometry(_Odo(t0 + 5_000_000, x=9.0), w0 + 0.004)       # forged: refused
    assert dict(c.rejected) == {"future": 1} and tr.wire[0] == 0.0
    for k in range(1, 200):                     # the genuine stream, 4 ms apart, never refused
        assert tr.on_odometry(_Odo(t0 + 4000 * k), w0 + 0.004 * k), k
    # one forged state within the tolerance (0.5 s ahead) is taken (nothing tells it from a
    # genuine one without a key); the genuine states then look stale, but only until the offset's
    # window has passed (≤ 2 s), never for good
    t1, w1 = t0 + 4000 * 199, w0 + 0.004 * 199
    assert tr.on_odometry(_Odo(t1 + 500_000), w1 + 0.004)
    c.rejected.clear()
    ok = [tr.on_odometry(_Odo(t1 + 4000 * k), w1 + 0.004 * k) for k in range(2, 1000)]
    first = ok.index(True)
    assert (first + 2) * 0.004 <= 2.0 + 0.008 and all(ok[first:])   # back within 2 s, for good
    assert set(c.rejected) == {"out_of_order", "stale"}
    lock = StateTracker(Counters(), check_stale=False)
    lock.max_time_usec = 8000
    assert not lock.on_odometry(_Odo(10**12), 0) and lock.on_odometry(_Odo(8000), 0)


def test_framing_and_untrusted_bytes():
    c = Counters()
    tx = Peer(1, 1, Counters())
    rx = Peer(255, 191, c)
    pkt = tx.pack(tx.mav.heartbeat_encode(13, 0, 0, 0, 4))
    pkts, err = split_datagram(pkt + pkt)
    assert err is None and len(pkts) == 2
    assert split_datagram(pkt[:-1])[1] == "truncated"
    assert split_datagram(b"\xfe" + pkt[1:])[1] == "mavlink1"
    bad = bytearray(pkt)
    bad[12] ^= 0xFF  # payload byte: CRC fails
    assert rx.accept(bytes(bad)) is None and c.malformed == 1
    assert rx.accept(pkt).get_type() == "HEARTBEAT" and c.received == 1
