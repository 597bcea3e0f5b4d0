"""The inter-agent link (bridge/swarm/agent_link.py): what reaches whom, exactly which numbers, the
newest-sample rule, signing and untrusted input. In-process, over loopback UDP.

Expectations are computed here from the definitions: the scenario → NED/FRD conversion with the
matrices P_W, P_B written out below, float32 rounding, and `bridge.mavlink.transport.wire_to_state` (what
the bridge makes of a vehicle's ODOMETRY).
"""
import math
import os
import socket
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bridge.mavlink import frames
from bridge.swarm.agent_link import AGENT_COMPONENT, AgentLink
from bridge.mavlink.link import Counters, Peer, free_base_port, mavlink2
from bridge.mavlink.transport import wire_to_state
from controller import Se3SyncError, layout
from cosim.scenario import parse_scenario
from _net import wait_queued

ROOT = Path(__file__).resolve().parents[2]
HIL = (ROOT / "scenarios" / "hil_6uav.toml").read_text()  # edges (1,2) (2,3) (3,4) (2,5) (5,6)
H_US = 4000                                                # h = 4 ms
P_W = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])  # ENU -> NED
P_B = np.diag([1.0, -1.0, -1.0])                                       # FLU -> FRD
KEY = bytes(range(32))


def scenario(world="ned"):
    base = free_base_port(6)
    text = HIL.replace('world_frame = "ned"', f'world_frame = "{world}"')
    return parse_scenario(text + f"\n[network]\nbase_port = {base}\n", name="al", path="al.toml")


def endpoint(sc, i):
    host, port = sc.tables["network"].endpoints[i - 1]
    return host, port


def f32(x):
    return np.asarray(x, float).astype(np.float32).astype(float)


def random_row(rng):
    S = np.empty(18)
    S[layout.P] = rng.normal(size=3) * 3.0
    S[layout.R] = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix().reshape(9)
    S[layout.XI] = rng.normal(size=6)
    return S


def expected_row(S, world):
    """What the receiver must hold: the row converted to NED/FRD, put on the float32 wire
    [p, q(w first), ω, v] and decoded by the bridge's wire_to_state."""
    p, R, w, v = S[layout.P], S[layout.R].reshape(3, 3), S[layout.OMEGA], S[layout.V]
    if world == "enu":
        p, R, w, v = P_W @ p, P_W @ R @ P_B, P_B @ w, P_B @ v
    q = frames.rot_to_quat(R.reshape(1, 9))[0]
    wire = f32(np.concatenate([p, q, w, v]))
    return wire_to_state(wire[None, :], world)[0]


def raw_socket(sc, i):
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(endpoint(sc, i))
    s.setblocking(False)
    return s


def drain_raw(s):
    out = []
    while True:
        try:
            out.append(s.recvfrom(65535)[0])
        except BlockingIOError:
            return out


def poll_until(link, pred, timeout=3.0):
    """Polls until pred() holds (loopback delivery is immediate; the deadline only stops a hang)."""
    end = time.monotonic() + timeout
    while True:
        link.poll()
        if pred() or time.monotonic() > end:
            return pred()
        time.sleep(0.001)


def send_raw(sc, to, data: bytes, frm=2):
    """A datagram to agent ``to`` from agent ``frm``'s endpoint (where a neighbour sends from;
    ``frm=None``: from an ephemeral port, as a stranger would)."""
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        if frm is not None:
            s.bind(endpoint(sc, frm))
        s.sendto(data, endpoint(sc, to))
    finally:
        s.close()


def odometry(mav, t_us, x=0.0, q=(1.0, 0.0, 0.0, 0.0), frame=None, child=None):
    return mav.odometry_encode(
        t_us, mavlink2.MAV_FRAME_LOCAL_NED if frame is None else frame,
        mavlink2.MAV_FRAME_BODY_FRD if child is None else child,
        x, 0.5, -0.25, list(q), 0.1, 0.2, 0.3, 0.01, 0.02, 0.03,
        [math.nan] + [0.0] * 20, [math.nan] + [0.0] * 20, 0, 0, 0)


def theta_msg(mav, t_us, values, name=b"theta", array_id=2):
    return mav.debug_float_array_encode(t_us, name, array_id,
                                        list(values) + [math.nan] * (58 - len(values)))


def sample_datagram(mav, t_us, x, theta=(0.5, -0.5)):
    """Agent 2's sample (it owns edges 2 and 4): ODOMETRY + DEBUG_FLOAT_ARRAY in one datagram."""
    return bytes(odometry(mav, t_us, x).pack(mav)) + bytes(theta_msg(mav, t_us, theta).pack(mav))


@pytest.fixture
def closing():
    opened = []
    yield opened
    for o in opened:
        o.close()


# ------------------------------------------------------------------ round trip, only neighbours

@pytest.mark.parametrize("world", ["ned", "enu"])
def test_round_trip_reaches_exactly_the_neighbours(world, closing):
    sc = scenario(world)
    assert sc.graph.neighbours(2) == [1, 3, 5] and sc.graph.M_plus(2) == [2, 4]
    links = {i: AgentLink.from_scenario(sc, i) for i in (1, 2, 3, 5)}
    closing.extend(links.values())
    outsiders = {i: raw_socket(sc, i) for i in (4, 6)}   # where non-neighbours listen
    closing.extend(outsiders.values())
    rng = np.random.default_rng(7)
    S = random_row(rng)
    theta = {2: 0.7123456789, 4: -2.2}
    assert links[2].publish(11, S, theta) == 3
    want = expected_row(S, world)
    assert np.max(np.abs(want - S)) < 1e-5          # float32 rounding only
    for i in (1, 3, 5):
        links[i].set_step(11)
        assert poll_until(links[i], lambda i=i: links[i].neighbour(2) is not None)
        got = links[i].neighbour(2)
        assert got.step == 11
        assert np.array_equal(got.S, want)
        assert np.array_equal(got.xi, want[layout.XI])
        assert got.theta == {k: float(np.float32(v)) for k, v in theta.items()}
        assert links[i].age_steps(2, 14) == 3
        st = links[i].stats()
        assert st["datagrams"] == 1 and st["received"] == 2 and st["rejected"] == 0
    for s in outsiders.values():
        assert drain_raw(s) == []
    st2 = links[2].stats()
    assert {j: st2["links"][str(j)]["sent"] for j in (1, 3, 5)} == {1: 1, 3: 1, 5: 1}
    assert st2["sent"] == 3 * 2                          # two packets to each neighbour


def test_only_odometry_and_theta_on_the_wire(closing):
    sc = scenario()
    sender = AgentLink.from_scenario(sc, 2)
    leaf = AgentLink.from_scenario(sc, 4)                # owns no edge: sends ODOMETRY only
    closing.extend([sender, leaf])
    sockets = {i: raw_socket(sc, i) for i in (1, 3, 5, 6)}
    closing.extend(sockets.values())
    rng = np.random.default_rng(3)
    for n in range(5):
        sender.publish(n, random_row(rng), {2: 0.1 * n, 4: -0.1 * n})
    leaf.publish(9, random_row(rng), {})
    got = {i: [] for i in sockets}
    end = time.monotonic() + 3.0
    while sum(map(len, got.values())) < 16 and time.monotonic() < end:
        for i, s in sockets.items():
            got[i] += drain_raw(s)
        time.sleep(0.001)
    assert {i: len(d) for i, d in got.items()} == {1: 5, 3: 6, 5: 5, 6: 0}
    ids = set()
    for i, datagrams in got.items():
        for data in datagrams:
            parser = mavlink2.MAVLink(None)
            msgs = parser.parse_buffer(data) or []
            assert sum(len(m.get_msgbuf()) for m in msgs) == len(data)  # nothing else inside
            for m in msgs:
                ids.add(m.get_msgId())
                assert m.get_srcComponent() == AGENT_COMPONENT
                if m.get_srcSystem() == 4:
                    assert m.get_msgId() == mavlink2.MAVLINK_MSG_ID_ODOMETRY and i == 3
                    assert m.time_usec == 9 * H_US
                    continue
                assert m.get_srcSystem() == 2
                n = m.time_usec // H_US
                assert m.time_usec == n * H_US
                if m.get_msgId() == mavlink2.MAVLINK_MSG_ID_ODOMETRY:
                    assert (m.frame_id, m.child_frame_id) == (mavlink2.MAV_FRAME_LOCAL_NED,
                                                              mavlink2.MAV_FRAME_BODY_FRD)
                else:
                    assert m.name == "theta" and m.array_id == 2
                    assert list(m.data[:2]) == [float(np.float32(0.1 * n)), float(np.float32(-0.1 * n))]
                    assert all(math.isnan(x) for x in m.data[2:])
    assert ids == {mavlink2.MAVLINK_MSG_ID_ODOMETRY, mavlink2.MAVLINK_MSG_ID_DEBUG_FLOAT_ARRAY}


def test_publish_refuses_a_wrong_theta_set(closing):
    sc = scenario()
    link = AgentLink.from_scenario(sc, 2)
    closing.append(link)
    with pytest.raises(Se3SyncError, match="owns edges"):
        link.publish(0, sc.S0[1], {2: 0.0})
    with pytest.raises(Se3SyncError, match="not a neighbour"):
        link.neighbour(4)


# ------------------------------------------------------------------ newest sample

def test_newest_sample_never_goes_backwards(closing):
    sc = scenario()
    rx = AgentLink.from_scenario(sc, 1)
    closing.append(rx)
    rx.set_step(20)
    mav = mavlink2.MAVLink(None, srcSystem=2, srcComponent=AGENT_COMPONENT)
    stamps = [5, 3, 8, 8, 6, 12, 2, 13, 13, 9]
    held = []
    for k, s in enumerate(stamps):
        send_raw(sc, 1, sample_datagram(mav, s * H_US, x=float(s), theta=(s, -s)))
        poll_until(rx, lambda k=k: rx.stats()["datagrams"] == k + 1)
        held.append(rx.neighbour(2).step)
    running_max = list(np.maximum.accumulate(stamps))
    assert held == running_max
    late = sum(1 for k, s in enumerate(stamps) if s < max(stamps[:k + 1]))
    dup = sum(1 for k, s in enumerate(stamps) if k and s == max(stamps[:k]))
    by = rx.stats()["rejected_by_reason"]
    assert by.get("out_of_order", 0) == 2 * late == 8    # both messages of each late sample
    assert by.get("duplicate", 0) == 2 * dup == 4
    got = rx.neighbour(2)
    assert got.S[0] == 13.0 and got.theta == {2: 13.0, 4: -13.0}   # the data of the newest
    assert rx.stats()["links"]["2"]["samples"] == len(set(running_max))

    # a sample split over two datagrams completes; an incomplete one is replaced by a newer one
    send_raw(sc, 1, bytes(odometry(mav, 20 * H_US, 20.0).pack(mav)))
    poll_until(rx, lambda: rx.stats()["datagrams"] == len(stamps) + 1)
    assert rx.neighbour(2).step == 13                     # no θ yet: not a sample
    send_raw(sc, 1, bytes(theta_msg(mav, 20 * H_US, (1.0, 2.0)).pack(mav)))
    assert poll_until(rx, lambda: rx.neighbour(2).step == 20)
    send_raw(sc, 1, bytes(odometry(mav, 22 * H_US, 22.0).pack(mav)))
    send_raw(sc, 1, sample_datagram(mav, 23 * H_US, 23.0))
    assert poll_until(rx, lambda: rx.neighbour(2).step == 23)
    assert rx.stats()["rejected_by_reason"]["incomplete"] == 1


def test_age_percentiles_are_nearest_rank_of_the_recorded_ages(closing):
    sc = scenario()
    rx = AgentLink.from_scenario(sc, 1)
    closing.append(rx)
    mav = mavlink2.MAVLink(None, srcSystem=2, srcComponent=AGENT_COMPONENT)
    assert rx.age_steps(2, 0) is None and rx.neighbour(2) is None
    rx.set_step(10)
    send_raw(sc, 1, sample_datagram(mav, 10 * H_US, 1.0))
    assert poll_until(rx, lambda: rx.neighbour(2) is not None)
    ns = [10, 11, 11, 12, 15, 30, 10, 13, 14, 200]
    ages = [rx.age_steps(2, n) for n in ns]
    assert ages == [n - 10 for n in ns]
    srt = sorted(ages)
    link = rx.stats()["links"]["2"]
    assert link["age_p50_steps"] == srt[math.ceil(0.5 * len(srt)) - 1]
    assert link["age_p99_steps"] == srt[math.ceil(0.99 * len(srt)) - 1]


# ------------------------------------------------------------------ signing

def test_signed_link_rejects_forged_and_unsigned(closing):
    sc = scenario()
    rx = AgentLink.from_scenario(sc, 1, key=KEY)
    tx = AgentLink.from_scenario(sc, 2, key=KEY)
    closing.extend([rx, tx])
    rng = np.random.default_rng(5)
    S1 = random_row(rng)
    tx.publish(1, S1, {2: 0.25, 4: 0.5})
    assert poll_until(rx, lambda: rx.neighbour(2) is not None)
    before = rx.neighbour(2)
    forger = Peer(2, AGENT_COMPONENT, Counters(), key=bytes(32 - i for i in range(32)))
    plain = mavlink2.MAVLink(None, srcSystem=2, srcComponent=AGENT_COMPONENT)
    # from agent 2's own endpoint (a spoofed source address), so that only the signature tells
    tx.sock.send(bytes(forger.pack(odometry(forger.mav, 3 * H_US, 9.0)))
                 + bytes(forger.pack(theta_msg(forger.mav, 3 * H_US, (9.0, 9.0)))), endpoint(sc, 1))
    tx.sock.send(sample_datagram(plain, 4 * H_US, 9.0), endpoint(sc, 1))
    poll_until(rx, lambda: rx.stats()["datagrams"] == 3)
    by = rx.stats()["rejected_by_reason"]
    assert by.get("bad_signature") == 2 and by.get("unsigned") == 2
    after = rx.neighbour(2)
    assert after is before and after.step == 1 and np.array_equal(after.S, expected_row(S1, "ned"))
    S2 = random_row(rng)
    tx.publish(2, S2, {2: -0.25, 4: -0.5})                # genuine and signed: accepted
    assert poll_until(rx, lambda: rx.neighbour(2).step == 2)
    assert np.array_equal(rx.neighbour(2).S, expected_row(S2, "ned"))
    assert rx.neighbour(2).theta == {2: -0.25, 4: -0.5}


def test_non_neighbour_system_is_refused(closing):
    sc = scenario()
    rx = AgentLink.from_scenario(sc, 1)
    closing.append(rx)
    # agent 4 from its own endpoint (not a neighbour's: refused before parsing), agent 2's
    # endpoint claiming agent 3, and agent 2's endpoint with another component
    for frm, sys_id, comp in ((4, 4, AGENT_COMPONENT), (2, 3, AGENT_COMPONENT), (2, 2, 1)):
        mav = mavlink2.MAVLink(None, srcSystem=sys_id, srcComponent=comp)
        send_raw(sc, 1, sample_datagram(mav, 5 * H_US, 1.0), frm=frm)
    send_raw(sc, 1, sample_datagram(mavlink2.MAVLink(None, srcSystem=2, srcComponent=191),
                                    5 * H_US, 1.0), frm=None)      # from a stranger's port
    poll_until(rx, lambda: rx.stats()["datagrams"] == 4)
    assert rx.stats()["rejected_by_reason"] == {"not_neighbour": 4, "wrong_address": 2}
    assert rx.stats()["links"]["2"]["rejected"] == 0   # refused before anything names agent 2
    assert rx.neighbour(2) is None


# ------------------------------------------------------------------ untrusted input

def test_random_and_broken_datagrams_are_counted_and_dropped(closing):
    sc = scenario()
    rx = AgentLink.from_scenario(sc, 1)
    closing.append(rx)
    rx.set_step(9)
    mav = mavlink2.MAVLink(None, srcSystem=2, srcComponent=AGENT_COMPONENT)
    send_raw(sc, 1, sample_datagram(mav, 4 * H_US, 3.0))
    assert poll_until(rx, lambda: rx.neighbour(2) is not None)
    held = rx.neighbour(2)
    S_held = held.S.copy()
    rng = np.random.default_rng(11)
    genuine = sample_datagram(mav, 9 * H_US, 7.0)
    bad = []
    for _ in range(2000):                                  # random bytes, some with a v2 magic
        d = bytearray(rng.integers(0, 256, size=int(rng.integers(0, 300)), dtype=np.uint8).tobytes())
        if d and rng.random() < 0.5:
            d[0] = 0xFD
        bad.append(bytes(d))
    # each genuine frame alone (an intact frame inside a damaged datagram is still taken)
    frames_ = [bytes(odometry(mav, 9 * H_US, 7.0).pack(mav)),
               bytes(theta_msg(mav, 9 * H_US, (0.5, -0.5)).pack(mav))]
    for f in frames_:
        for cut in range(1, len(f), 3):                    # truncated
            bad.append(f[:cut])
        for pos in range(1, len(f)):                       # one flipped byte: framing or CRC fails
            d = bytearray(f)
            d[pos] ^= 0x5A
            bad.append(bytes(d))
    bad.append(b"\xfe" + genuine[1:])                       # MAVLink 1 magic
    c0 = rx.stats()
    refused0 = rx.counters.refusals()
    total = 0
    for b0 in range(0, len(bad), 100):                     # batches: the socket buffer is finite
        for d in bad[b0:b0 + 100]:
            send_raw(sc, 1, d)
        total += len(bad[b0:b0 + 100])
        assert poll_until(rx, lambda: rx.stats()["datagrams"] - c0["datagrams"] == total)
    assert rx.neighbour(2) is held and held.step == 4 and np.array_equal(held.S, S_held)
    assert rx.counters.refusals() - refused0 >= len(bad)   # every datagram refused at least once
    assert rx.stats()["links"]["2"]["samples"] == 1
    # and the link still works
    send_raw(sc, 1, genuine)
    assert poll_until(rx, lambda: rx.neighbour(2).step == 9)


@pytest.mark.parametrize("case,reason", [
    ("nan", "nan"), ("quaternion", "non_unit_quaternion"), ("frame", "bad_frame"),
    ("stamp", "bad_stamp"), ("theta_nan", "nan"), ("theta_name", "bad_theta"),
    ("theta_array", "bad_theta"), ("other", "unexpected_message")])
def test_bad_values_from_a_neighbour_are_rejected_with_the_reason(case, reason, closing):
    sc = scenario()
    rx = AgentLink.from_scenario(sc, 1)
    closing.append(rx)
    rx.set_step(8)
    mav = mavlink2.MAVLink(None, srcSystem=2, srcComponent=AGENT_COMPONENT)
    send_raw(sc, 1, sample_datagram(mav, 4 * H_US, 3.0))
    assert poll_until(rx, lambda: rx.neighbour(2) is not None)
    held = rx.neighbour(2)
    t = 8 * H_US
    msg = {
        "nan": lambda: odometry(mav, t, math.nan),
        "quaternion": lambda: odometry(mav, t, q=(1.0, 0.1, 0.0, 0.0)),
        "frame": lambda: odometry(mav, t, frame=mavlink2.MAV_FRAME_LOCAL_FRD),
        "stamp": lambda: odometry(mav, t + 1),
        "theta_nan": lambda: theta_msg(mav, t, (0.5, math.nan)),
        "theta_name": lambda: theta_msg(mav, t, (0.5, 0.5), name=b"thetaX"),
        "theta_array": lambda: theta_msg(mav, t, (0.5, 0.5), array_id=3),
        "other": lambda: mav.heartbeat_encode(0, 0, 0, 0, 0),
    }[case]()
    send_raw(sc, 1, bytes(msg.pack(mav)))
    poll_until(rx, lambda: rx.stats()["datagrams"] == 2)
    assert rx.stats()["rejected_by_reason"] == {reason: 1}
    assert rx.stats()["links"]["2"]["rejected_by_reason"] == {reason: 1}   # on agent 2's link
    assert rx.neighbour(2) is held


def test_a_poll_drains_by_time_not_by_count(closing):
    sc = scenario()
    rx = AgentLink.from_scenario(sc, 1, drain_budget=16)
    closing.append(rx)
    for _ in range(40):
        send_raw(sc, 1, b"\x00" + os.urandom(19), frm=None)     # junk from a stranger
    wait_queued(rx.sock.sock, 40, 20)
    # time enough (its budget at h = 4 ms is 0.4 ms, which a busy machine's preemption alone
    # can spend between two batches): batches of 16 until empty
    rx.poll_budget_s = rx.junk_budget_s = 60.0
    assert rx.poll() == 40 and rx.stats()["drain_capped"] == 0
    assert rx.stats()["malformed"] == 40                           # refused on the first byte
    for _ in range(40):
        send_raw(sc, 1, b"\x00" + os.urandom(19), frm=None)
    wait_queued(rx.sock.sock, 40, 20)
    rx.poll_budget_s = rx.junk_budget_s = 0.0                      # no time left: one batch
    assert rx.poll() == 16 and rx.stats()["drain_capped"] == 1


def test_junk_overflowing_its_socket_crowds_out_no_neighbour_sample(closing):
    """Issue 29, 3: junk from strangers fills only the catch-all socket (the kernel hands each
    neighbour's datagrams to a socket connected to it), so a flood the agent cannot read in time
    is dropped by the kernel, counted, and every genuine sample is still there."""
    sc = scenario()
    rx = AgentLink.from_scenario(sc, 1)
    closing.append(rx)
    rx.set_step(100)
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    junk = b"\xfd" + bytes(200)
    for _ in range(20_000):                         # far beyond the 1 MiB receive buffer
        s.sendto(junk, endpoint(sc, 1))
    s.close()
    mav = mavlink2.MAVLink(None, srcSystem=2, srcComponent=AGENT_COMPONENT)
    for k in range(60, 100):
        send_raw(sc, 1, sample_datagram(mav, k * H_US, float(k)))
    rx.junk_budget_s = 0.0                          # the junk gets one batch per poll at most
    assert poll_until(rx, lambda: rx.neighbour(2) is not None and rx.neighbour(2).step == 99)
    st = rx.stats()
    assert st["links"]["2"]["samples"] == 40 and st["links"]["2"]["rejected"] == 0, st
    assert st["kernel_drops"] > 10_000                # the flood's loss, reported
    assert st["links"]["2"]["kernel_drops"] == 0


def test_freshness_follows_max_age_then_hold_then_failsafe_and_rejoins(closing):
    base = free_base_port(6)
    sc = parse_scenario(HIL + f"\n[network]\nbase_port = {base}\nmax_age = 0.02\nhold = 0.01\n",
                        name="al", path="al.toml")
    rx = AgentLink.from_scenario(sc, 1)
    closing.append(rx)
    rx.set_step(100)
    assert (rx.max_age_steps, rx.hold_steps) == (5, 3)    # 20 ms and 10 ms at h = 4 ms
    # before any sample: counted from S0 at step 0
    assert [rx.freshness(2, n) for n in (5, 6, 8, 9)] == ["fresh", "hold", "hold", "failsafe"]
    mav = mavlink2.MAVLink(None, srcSystem=2, srcComponent=AGENT_COMPONENT)
    send_raw(sc, 1, sample_datagram(mav, 100 * H_US, 1.0))
    assert poll_until(rx, lambda: rx.neighbour(2) is not None)
    assert [rx.freshness(2, n) for n in (100, 105, 106, 108, 109)] == \
        ["fresh", "fresh", "hold", "hold", "failsafe"]
    rx.set_step(109)
    send_raw(sc, 1, sample_datagram(mav, 107 * H_US, 1.0))   # fresh data again: rejoin
    assert poll_until(rx, lambda: rx.neighbour(2).step == 107)
    assert rx.freshness(2, 109) == "fresh"


def test_endpoint_errors_are_one_line(closing):
    sc = scenario()
    busy = raw_socket(sc, 1)
    closing.append(busy)
    with pytest.raises(Se3SyncError, match=r"network: agent 1's endpoint 127\.0\.0\.1:\d+ cannot be bound"):
        AgentLink.from_scenario(sc, 1)
    base = free_base_port(6)
    bad = parse_scenario(HIL + f"\n[network]\nbase_port = {base}\n[[network.agent]]\nid = 2\n"
                         "address = \"no-such-host.invalid\"\n", name="al", path="al.toml")
    with pytest.raises(Se3SyncError,
                       match="network: agent 2's address 'no-such-host.invalid' does not resolve"):
        AgentLink.from_scenario(bad, 1)
    with pytest.raises(Se3SyncError, match="no \\[network\\] table"):
        AgentLink.from_scenario(parse_scenario(HIL, name="al", path="al.toml"), 1)


def test_more_than_58_owned_edges_travel_in_chunks(closing):
    from controller import Graph
    from cosim.network import parse_network

    n = 62                                              # agent 1 owns 61 edges: chunks of 58 + 3
    graph = Graph(n, [(1, j) for j in range(2, n + 1)])
    net = parse_network({"base_port": free_base_port(n)}, n)
    tx = AgentLink(1, net, graph, step=0.004)
    rx = AgentLink(7, net, graph, step=0.004)
    closing.extend([tx, rx])
    theta = {k: 0.01 * k - 0.3 for k in graph.M_plus(1)}
    rng = np.random.default_rng(2)
    S = random_row(rng)
    tx.publish(3, S, theta)
    assert poll_until(rx, lambda: rx.neighbour(1) is not None)
    got = rx.neighbour(1)
    assert got.theta == {k: float(np.float32(v)) for k, v in theta.items()}
    assert np.array_equal(got.S, expected_row(S, "ned"))
    assert rx.stats()["received"] == 3                  # ODOMETRY + "theta" + "theta1"


def test_a_restart_is_a_run_of_samples_far_back_never_one_packet(closing):
    sc = scenario()
    rx = AgentLink.from_scenario(sc, 1)
    closing.append(rx)
    rx.set_step(5000)
    assert rx.restart_steps == 2500                      # 10 s at h = 4 ms
    mav = mavlink2.MAVLink(None, srcSystem=2, srcComponent=AGENT_COMPONENT)
    n = 0

    def send(s):
        nonlocal n
        send_raw(sc, 1, sample_datagram(mav, s * H_US, float(s)))
        n += 1
        poll_until(rx, lambda: rx.stats()["datagrams"] == n)
        return rx.neighbour(2).step

    # one far-back sample (or two in a row) is not a restart; a newer genuine sample ends the run
    assert [send(s) for s in (5000, 2500, 2499, 1000, 1001, 5001, 1002, 1003)] == \
        [5000] * 5 + [5001] * 3
    st = rx.stats()
    assert rx.neighbour(2).step == 5001 and st["links"]["2"]["restarts"] == 0
    # a sender restarted on another timeline: its samples keep coming from far back, each newer
    # than the last; the third in a row is taken (and what it carries)
    assert [send(s) for s in (1000, 1001, 1002, 1003)] == [5001, 5001, 1002, 1003]
    assert rx.neighbour(2).S[0] == 1003.0
    st = rx.stats()
    assert st["links"]["2"]["restarts"] == 1
    # every refused message was counted: 2500 (near: late), 2499, 1000, 1001, 1002, 1003 (far,
    # runs broken by 5001 or too short), 1000, 1001: two messages each
    assert st["rejected_by_reason"] == {"out_of_order": 2 * 8}, st["rejected_by_reason"]


def test_a_future_stamp_is_refused_never_used_and_never_moves_the_window(closing):
    """Issue 29, 1: one unsigned sample of agent 2 stamped 10 s ahead took over agent 1's view
    of agent 2 (899 of 1,200 genuine samples then refused as out_of_order)."""
    sc = scenario()
    rx = AgentLink.from_scenario(sc, 1)
    closing.append(rx)
    fs = rx.future_steps
    assert fs == 5                                        # 20 ms at h = 4 ms
    mav = mavlink2.MAVLink(None, srcSystem=2, srcComponent=AGENT_COMPONENT)
    n = 0

    def send(s, x=None):
        nonlocal n
        send_raw(sc, 1, sample_datagram(mav, s * H_US, float(s) if x is None else x))
        n += 1
        poll_until(rx, lambda: rx.stats()["datagrams"] == n)

    rx.set_step(100)
    send(100)
    for forged in (100 + 2500, 100 + 10**9, 100 + fs + 1):
        send(forged, x=5.0)
        got = rx.neighbour(2)
        assert got.step == 100 and got.S[0] == 100.0     # never used
    assert rx.stats()["links"]["2"]["rejected_by_reason"] == {"future": 3 * 2}
    for k in range(101, 131):                            # the genuine stream goes on untouched
        rx.set_step(k)
        send(k)
        assert rx.neighbour(2).step == k and rx.freshness(2, k) == "fresh"
    assert rx.stats()["rejected_by_reason"] == {"future": 6}
    send(130 + fs)                                       # the tolerance itself is accepted
    assert rx.neighbour(2).step == 130 + fs
    assert rx.freshness(2, 130) == "fresh"               # −fs steps: a clock that is a bit ahead


def test_real_time_receiver_step_follows_the_wall_clock(closing):
    sc = scenario()
    rx = AgentLink.from_scenario(sc, 1)
    closing.append(rx)
    now = [1000.0]
    rx.set_timeline(1000.0 - 50 * 0.004 - 1e-9, clock=lambda: now[0])
    assert rx.current_step() == 50
    rx.set_step(40)                       # a late process: the clock's step still counts
    assert rx.current_step() == 50
    mav = mavlink2.MAVLink(None, srcSystem=2, srcComponent=AGENT_COMPONENT)
    send_raw(sc, 1, sample_datagram(mav, 55 * H_US, 1.0))
    send_raw(sc, 1, sample_datagram(mav, 56 * H_US, 1.0))
    poll_until(rx, lambda: rx.stats()["datagrams"] == 2)
    assert rx.neighbour(2).step == 55 and rx.stats()["rejected_by_reason"] == {"future": 2}
    # the data are newer than the late step 40 (age −15) but not than the clock's: fresh
    assert rx.freshness(2, 40) == "fresh"
    now[0] -= 1.0                         # the clock stepped back 1 s: a sample 250 steps ahead
    rx.set_step(-200)
    assert rx.freshness(2, -200) == "failsafe"


def test_lockstep_history_is_kept_around_the_own_step_not_the_newest_stamp(closing):
    """Issue 29, 2: one sample stamped 10⁹ steps ahead emptied a lockstep agent's history, so it
    waited for data it had already received and the swarm exited."""
    sc = scenario()
    rx = AgentLink.from_scenario(sc, 1, history=4)
    closing.append(rx)
    mav = mavlink2.MAVLink(None, srcSystem=2, srcComponent=AGENT_COMPONENT)
    rx.set_step(10)
    sent = 0
    for s in (8, 9, 10, 11, 10 + 10**9, 10 + rx.future_steps + 1):
        send_raw(sc, 1, sample_datagram(mav, s * H_US, float(s)))
        sent += 1
    poll_until(rx, lambda: rx.stats()["datagrams"] == sent)
    assert rx.stats()["rejected_by_reason"] == {"future": 4}
    for s in (8, 9, 10, 11):
        assert rx.pose_at(2, s)[0] == float(s) and rx.theta_at(2, s) == {2: 0.5, 4: -0.5}
    rx.set_step(14)                       # steps before 14 − 4 are let go
    send_raw(sc, 1, sample_datagram(mav, 14 * H_US, 14.0))
    poll_until(rx, lambda: rx.stats()["datagrams"] == sent + 1)
    assert rx.pose_at(2, 9) is None and rx.pose_at(2, 10)[0] == 10.0 and rx.pose_at(2, 14)[0] == 14.0


def test_a_differing_copy_of_a_history_entry_is_counted_never_used(closing):
    """Audit of issue 29, 7: a later copy of a step's pose or θ that differed from the first was
    dropped silently; it is now counted (``conflicts``, per link), the first copy kept, and an
    identical resend is not a conflict."""
    sc = scenario()
    rx = AgentLink.from_scenario(sc, 1, history=4)
    closing.append(rx)
    mav = mavlink2.MAVLink(None, srcSystem=2, srcComponent=AGENT_COMPONENT)
    rx.set_step(10)
    sends = [sample_datagram(mav, 10 * H_US, 1.0),
             sample_datagram(mav, 10 * H_US, 1.0),                    # a resend: the same
             sample_datagram(mav, 10 * H_US, 5.0, theta=(0.9, -0.5))]  # another pose and θ
    for d in sends:
        send_raw(sc, 1, d)
    poll_until(rx, lambda: rx.stats()["datagrams"] == len(sends))
    st = rx.stats()
    assert st["conflicts"] == 2 and st["links"]["2"]["conflicts"] == 2, st
    assert rx.pose_at(2, 10)[0] == 1.0 and rx.theta_at(2, 10) == {2: 0.5, 4: -0.5}
