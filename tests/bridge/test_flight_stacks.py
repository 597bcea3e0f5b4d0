"""Flight stacks on the plant (issue 30): frame presets equal to the stacks' own frame definitions,
their parameter files, a scripted flight (arm after the spool-up, climb to 2 m, hold, land,
detect the touchdown, disarm) through both simulator servers, and the servers surviving clients
that misbehave. The flight's autopilot and the protocol clients are in tests/sim_clients.py."""
from __future__ import annotations

import math
import os
import select
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("MAVLINK20", "1")

from sim_clients import ArduPilotClient, Px4Client, fly  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
SITL = str(ROOT / "scenarios" / "sitl_1uav.toml")
HIL = str(ROOT / "scenarios" / "hil_6uav.toml")
MASS, J = 3.0, np.diag([0.03, 0.03, 0.05])


def _load(overrides=(), path=SITL):
    from cosim.scenario import load_scenario

    return load_scenario(path, list(overrides))


def _frame(name, **kw):
    items = ", ".join([f'frame = "{name}"'] + [f"{k} = {v}" for k, v in kw.items()])
    return [f"bridge.allocation={{{items}}}"]


class _Serve:
    def __init__(self, srv):
        self.srv = srv
        self.t = threading.Thread(target=srv.run, daemon=True)

    def __enter__(self):
        self.t.start()
        self.srv.ready.wait(5)
        return self.srv

    def __exit__(self, *exc):
        self.srv.stop()
        self.t.join(10)
        self.srv.close()


# ------------------------------------------------------------------------------------- frames
# The stacks' frame definitions, motor 1..n: (angle° from the nose, positive to the right; spin
# seen from above). ArduPilot: libraries/AP_Motors/AP_MotorsMatrix.cpp (setup_quad_matrix,
# setup_hexa_matrix: MotorDef {angle, yaw factor CCW = +1 / CW = −1}). PX4: quad X =
# ROMFS/px4fmu_common/init.d-posix/airframes/10015_gazebo-classic_iris (CA_ROTOR0..3 in the
# front-right, back-left, front-left, back-right quadrants, KM +, +, −, −: positive = CCW);
# hexarotors = src/lib/mixer/MultirotorMixer/geometries/hex_plus.toml, hex_x.toml (positions on
# the unit circle, directions) — the same motor order as ArduPilot's.
STACK_TABLES = {
    "quad-x": {"ardupilot": [(45, "CCW"), (-135, "CCW"), (-45, "CW"), (135, "CW")],
               "px4": [(45, "CCW"), (-135, "CCW"), (-45, "CW"), (135, "CW")]},
    "hexa-plus": {"ardupilot": [(0, "CW"), (180, "CCW"), (-120, "CW"), (60, "CCW"), (-60, "CCW"), (120, "CW")],
                  "px4": [(0, "CW"), (180, "CCW"), (-120, "CW"), (60, "CCW"), (-60, "CCW"), (120, "CW")]},
    "hexa-x": {"ardupilot": [(90, "CW"), (-90, "CCW"), (-30, "CW"), (150, "CCW"), (30, "CCW"), (-150, "CW")],
               "px4": [(90, "CW"), (-90, "CCW"), (-30, "CW"), (150, "CCW"), (30, "CCW"), (-150, "CW")]},
}


def _wrapped(a):
    return (a + 180.0) % 360.0 - 180.0


@pytest.mark.parametrize("frame", sorted(STACK_TABLES))
@pytest.mark.parametrize("stack", ["ardupilot", "px4"])
def test_preset_geometry_equals_the_stacks_frame_definition(frame, stack):
    """Column k of the allocation (rotor k on output k) against the stack's motor k: a rotor at
    angle φ and arm L lifting T makes roll −L sin φ·T and pitch L cos φ·T, and yaws the body by
    +c·T (FRD z, clockwise seen from above) when it spins CCW, −c·T when CW; thrust straight up."""
    from bridge.mavlink.mapping import AllocationSpec, hexarotor_matrix

    L, T, c = 0.3, 12.0, 0.02
    A = hexarotor_matrix(AllocationSpec(frame=frame, tilt_deg=0.0, arm_length=L, max_thrust=T, torque_coeff=c))
    table = STACK_TABLES[frame][stack]
    assert not A[:, len(table):].any()
    for k, (ang, spin) in enumerate(table):
        a = math.radians(ang)
        expect = [-L * math.sin(a) * T, L * math.cos(a) * T, (c if spin == "CCW" else -c) * T, 0.0, 0.0, -T]
        assert np.allclose(A[:, k], expect, atol=1e-12), (frame, k)


def test_tilted_hexarotor_is_the_existing_default_and_tilt_zero_is_allowed():
    """The paper's hexarotor is unchanged (fully actuated, rank 6); tilt_deg = 0 is a plain hexa +
    geometry (rank 4: no sideways force); a negative tilt tilts the other way."""
    from bridge.mavlink.config import parse_bridge
    from bridge.mavlink.mapping import AllocationSpec, hexarotor_matrix

    A30 = hexarotor_matrix(AllocationSpec())
    assert np.linalg.matrix_rank(A30) == 6
    flat = parse_bridge({"mapping": "allocation", "allocation": {"tilt_deg": 0}}, 1).mappings[0].allocation
    A0 = hexarotor_matrix(flat)
    assert np.linalg.matrix_rank(A0) == 4 and np.allclose(A0[3:5], 0)
    Am = hexarotor_matrix(AllocationSpec(tilt_deg=-30.0))
    assert np.allclose(Am[3:5], -A30[3:5]) and np.allclose(Am[5], A30[5])
    # with +30° each rotor's net yaw is opposite to its drag torque's (the runaway), with −30° the same sign
    drag_sign = np.array([-1, 1, -1, 1, -1, 1])                  # rotor k even: CW
    assert np.all(np.sign(A30[2]) == -drag_sign) and np.all(np.sign(Am[2]) == drag_sign)


@pytest.mark.parametrize("frame, tilt", [("quad-x", 0), ("hexa-plus", 0), ("hexa-x", 0), ("hexa-x", -10),
                                         ("hexa-tilted", 1), ("hexa-tilted", -30)])
@pytest.mark.parametrize("stack", ["ardupilot", "px4"])
def test_parameter_files_round_trip(frame, tilt, stack):
    """The written file, parsed back, drives the same rotors on the same outputs (ArduPilot through
    its frame table and SERVOn_FUNCTION; PX4 through CA_ROTOR* and PWM_MAIN_FUNCn); PX4's matrix from
    CA_ROTOR* is ours; the hover throttle is the weight over the rotors' lift."""
    from bridge.mavlink.airframes import allocation_matrix, geometry_from_params, params_text, parse_params, rotors
    from bridge.mavlink.mapping import AllocationSpec

    spec = AllocationSpec(frame=frame, tilt_deg=float(tilt), arm_length=0.25, max_thrust=15.0, torque_coeff=0.016)
    p = parse_params(params_text(stack, spec, MASS, 9.80665, "header"))
    A = allocation_matrix(spec)
    ours = [(math.degrees(math.atan2(r.position[1], r.position[0])), float(np.sign(A[2, k])))
            for k, r in enumerate(rotors(spec))]
    theirs = geometry_from_params(stack, p)
    assert len(theirs) == len(ours)
    for (a1, s1), (a2, s2) in zip(ours, theirs):
        assert abs(_wrapped(a1 - a2)) < 1e-6 and s1 == s2
    c_h = MASS * 9.80665 / -A[5].sum()
    if stack == "px4":
        from bridge.mavlink.airframes import px4_matrix_from_params

        assert np.allclose(px4_matrix_from_params(p), A, atol=1e-7)
        assert p["CA_R_REV"] == 0 and p["THR_MDL_FAC"] == 0 and abs(p["MPC_THR_HOVER"] - c_h) < 1e-6
    else:
        assert p["MOT_THST_EXPO"] == 0 and p["MOT_PWM_MIN"] == 1000 and p["MOT_PWM_MAX"] == 2000
        # ArduPilot's output: pwm = 1000 + 1000 (spin_min + (spin_max − spin_min) throttle)
        pwm = 1000 + 1000 * (p["MOT_SPIN_MIN"] + (p["MOT_SPIN_MAX"] - p["MOT_SPIN_MIN"]) * p["MOT_THST_HOVER"])
        assert abs(pwm - (1000 + 1000 * c_h)) < 1e-3


# quad X, 4 × 15 N: ArduPilot's MOT_THST_HOVER = (c − 0.15)/0.8 must lie in 0.125..0.6875
# (AP_MOTORS_THST_HOVER_MIN/MAX, libraries/AP_Motors/AP_MotorsMulticopter.h), i.e. each rotor's share
# c = m g/60 N in 0.25..0.70: 1.53..4.28 kg; PX4's MPC_THR_HOVER = c in 0.1..0.8
# (src/modules/mc_pos_control/multicopter_position_control_params.yaml): 0.61..4.89 kg
@pytest.mark.parametrize("stack, mass, refused", [
    ("ardupilot", 1.6, None), ("ardupilot", 4.2, None),
    ("ardupilot", 1.4, ("MOT_THST_HOVER", "0.09853")), ("ardupilot", 5.0, ("MOT_THST_HOVER", "0.834")),
    ("px4", 0.7, None), ("px4", 4.8, None),
    ("px4", 0.5, ("MPC_THR_HOVER", "0.08172")), ("px4", 5.0, ("MPC_THR_HOVER", "0.8172"))])
def test_hover_throttle_outside_the_stacks_range_is_refused(stack, mass, refused):
    """A hover throttle the stack would clamp (ArduPilot) or not accept (PX4) is refused on one line
    naming the parameter and its value; inside the range the file is written and round-trips."""
    from bridge.mavlink.airframes import params_text, parse_params
    from bridge.mavlink.mapping import AllocationSpec
    from controller.errors import Se3SyncError

    spec = AllocationSpec(frame="quad-x", tilt_deg=0.0, arm_length=0.25, max_thrust=15.0, torque_coeff=0.016)
    if refused is None:
        p = parse_params(params_text(stack, spec, mass, 9.80665))
        key = "MOT_THST_HOVER" if stack == "ardupilot" else "MPC_THR_HOVER"
        lo, hi = (0.125, 0.6875) if stack == "ardupilot" else (0.1, 0.8)
        assert lo <= p[key] <= hi
        return
    with pytest.raises(Se3SyncError) as exc:
        params_text(stack, spec, mass, 9.80665)
    msg = str(exc.value)
    key, value = refused
    assert f"{key} = {value} " in msg and "\n" not in msg


def test_ardupilot_params_for_the_tilted_hexarotor():
    """The order SITL.md worked out by hand (SERVO1..6 = 33, 36, 38, 34, 35, 37, HEXA/PLUS) comes out
    of the geometry; the issue's tilt of +30° is refused with the reason, on one line."""
    from bridge.mavlink.airframes import params_text, parse_params
    from bridge.mavlink.mapping import AllocationSpec
    from controller.errors import Se3SyncError

    p = parse_params(params_text("ardupilot", AllocationSpec(tilt_deg=1.0), MASS, 9.80665))
    assert (p["FRAME_CLASS"], p["FRAME_TYPE"]) == (2, 0)
    assert [p[f"SERVO{k}_FUNCTION"] for k in range(1, 7)] == [33, 36, 38, 34, 35, 37]
    with pytest.raises(Se3SyncError) as exc:
        params_text("ardupilot", AllocationSpec(tilt_deg=30.0), MASS, 9.80665)
    assert "reverses every rotor's yaw" in str(exc.value) and "\n" not in str(exc.value)


def test_write_params_command_line(tmp_path):
    """`vehicle --sim-protocol … --write-params FILE` writes the file of the scenario's airframe (one
    per vehicle with '{i}') and exits 0; the file parses back to the scenario's geometry."""
    from bridge.mavlink.airframes import geometry_from_params, parse_params

    out = tmp_path / "v{i}.parm"
    r = subprocess.run([sys.executable, "-m", "cosim.cli", "vehicle", "--scenario", SITL, "--sim-protocol",
                        "ardupilot", "--set", 'bridge.allocation={frame = "hexa-x"}', "--write-params", str(out)],
                       capture_output=True, text=True, timeout=120, cwd=str(ROOT))
    assert r.returncode == 0, r.stderr
    p = parse_params((tmp_path / "v1.parm").read_text())
    assert (p["FRAME_CLASS"], p["FRAME_TYPE"]) == (2, 1)
    assert geometry_from_params("ardupilot", p) == [(a, 1.0 if s == "CCW" else -1.0)
                                                    for a, s in STACK_TABLES["hexa-x"]["ardupilot"]]


@pytest.mark.parametrize("stack, key, value", [("ardupilot", "MOT_THST_HOVER", "0.834"),
                                                ("px4", "MPC_THR_HOVER", "0.8172")])
def test_write_params_refuses_a_hover_throttle_out_of_range(tmp_path, stack, key, value):
    """5 kg on sitl_1uav's quad X (4 × 15 N) needs 0.82 of each rotor to hover: `--write-params`
    exits 2 with one line naming the parameter and its value, and writes nothing."""
    out = tmp_path / "heavy.parm"
    r = subprocess.run([sys.executable, "-m", "cosim.cli", "vehicle", "--scenario", SITL, "--sim-protocol", stack,
                        "--set", "agents.mass=5.0", "--write-params", str(out)],
                       capture_output=True, text=True, timeout=120, cwd=str(ROOT))
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1, r.stderr
    assert f"{key} = {value} " in lines[0] and not out.exists() and not list(tmp_path.iterdir())


# ------------------------------------------------------------------------------ scripted flight
@pytest.mark.realtime
@pytest.mark.parametrize("stack, frame", [("ardupilot", "hexa-x"), ("px4", "quad-x")])
def test_scripted_flight(stack, frame):
    """Arm, spool up for 2 s, climb to 2 m, hold 3 s, land at 0.5 m/s, detect the touchdown, disarm,
    1 s on the ground — in lockstep through the simulator server, on the plant's ground. The
    autopilot mixes with the stack's published motor table (sim_clients.STACK_FRAMES)."""
    from bridge.vehicles.sim_ardupilot import ArduPilotJsonServer
    from bridge.vehicles.sim_px4 import Px4SimServer

    sc = _load(_frame(frame))
    if stack == "px4":
        srv, h = Px4SimServer(sc, port=0, step=0.004, noise=True, lockstep_timeout=3600.0), 0.004
    else:
        srv, h = ArduPilotJsonServer(sc, port=0, noise=True), 0.004        # SITL at 250 Hz
    with _Serve(srv):
        r = fly(stack, srv.links[0].port, frame, MASS, J, h=h)
        st = srv.stats()
    t, down, vz, phase = r["t"], r["down"], r["vz"], r["phase"]
    ph = np.array(phase)
    assert st["diverged"] == 0 and st["malformed"] == 0
    if stack == "px4":
        assert st["lockstep_timeouts"] == 0 and st["ignored"] == 0 and st["streamed_steps"] >= 1
    # never below the ground (PX4: altitude in mm; ArduPilot: exact floats)
    assert down.max() <= (5e-4 if stack == "px4" else 1e-9)
    # spool-up: the motors turn (10 % thrust) and the vehicle stays on the ground, its accelerometer
    # reading the support force −g (body level: (0, 0, −g)) within the documented noise
    spool = ph == "spool"
    assert spool.sum() > 1.5 / h and np.abs(down[spool]).max() <= 5e-4
    acc = np.array(r["acc"])[spool]
    assert np.abs(acc.mean(axis=0) - [0, 0, -9.80665]).max() < 5 * 4e-3 / math.sqrt(h) / math.sqrt(spool.sum())
    # hold within 5 cm of 2 m
    hold = ph == "hold"
    assert hold.sum() * h > 2.9 and np.abs(down[hold] + 2.0).max() <= 0.05
    # touchdown: the first step resting on the ground while landing; detected within 1 s; < 1 m/s
    land = np.flatnonzero(ph == "land")
    i_c = land[np.flatnonzero((np.abs(down[land]) <= 5e-4) & (np.abs(vz[land]) < 1e-9))[0]]
    assert 0.0 <= r["touchdown_detected"] - t[i_c] <= 1.0
    assert 0.0 < vz[i_c - 1] < 1.0
    # disarmed on the ground, and it stays there
    done = ph == "done"
    assert done.sum() >= int(1.0 / h) and np.abs(down[done]).max() <= 5e-4 and np.abs(vz[done]).max() == 0.0


# --------------------------------------------------------------------------------- PX4 clients
@pytest.mark.realtime
def test_px4_first_sensor_is_stamped_h_and_streams_until_the_first_controls():
    """Start-up as PX4 needs it: the first HIL_SENSOR is stamped h (not 0) and the server keeps
    streaming, one step per h of wall time, while the client sends nothing; judged from the stamps
    received (consecutive multiples of h), not from the wall clock."""
    from bridge.vehicles.sim_px4 import Px4SimServer

    srv = Px4SimServer(_load(), port=0, step=0.004, noise=False, lockstep_timeout=3600.0)
    with _Serve(srv):
        cl = Px4Client(srv.links[0].port)
        try:
            stamps = [cl.step()[-1].time_usec for _ in range(10)]
        finally:
            cl.close()
    assert stamps == [4000 * (k + 1) for k in range(10)]


@pytest.mark.realtime
def test_px4_lockstep_timeout_steps_anyway_and_says_so():
    """A client that stops answering: after lockstep_timeout the server steps anyway (counted, one
    message per stall); when the client answers again lockstep resumes."""
    from bridge.vehicles.sim_px4 import Px4SimServer

    events = []
    srv = Px4SimServer(_load(), port=0, step=0.004, noise=False, lockstep_timeout=0.6, on_event=events.append)
    with _Serve(srv):
        cl = Px4Client(srv.links[0].port)
        try:
            cl.start()
            t0 = cl.clock_us
            stamps = [cl.step()[-1].time_usec for _ in range(3)]      # no answers: stepped anyway
            cl.send([0.0] * 16, armed=False)
            cl.drain(0.05)
        finally:
            cl.close()
    st = srv.stats()
    assert stamps == [t0 + 4000, t0 + 8000, t0 + 12000]
    assert st["lockstep_timeouts"] >= 3
    assert sum("stepping anyway" in e for e in events) == 1 and any("lockstep resumed" in e for e in events)


def _scenario_two():
    """sitl_1uav with a second vehicle 5 m north of the first."""
    from cosim.scenario import parse_scenario

    text = Path(SITL).read_text().replace("count = 1", "count = 2").replace("edges = []", "edges = [[1, 2]]")
    text = text.replace("[[initial.agent]]\n", "[[initial.agent]]\nposition = [5.0, 0.0, 0.0]\n[[initial.agent]]\n", 1)
    return parse_scenario(text, name="two", path="two.toml")


def _genuine_steps(port: int, n: int) -> list:
    cl = Px4Client(port)
    try:
        cl.start()
        out = []
        for _ in range(n):
            cl.send([0.0] * 16, armed=False)
            out.append(cl.step()[-1].time_usec)
        return out
    finally:
        cl.close()


@pytest.mark.realtime
def test_px4_client_that_never_reads_is_dropped_and_others_keep_stepping():
    """Vehicle 1's client ends its start-up, then floods HIL_ACTUATOR_CONTROLS that answer each next
    step (it guesses the stamps) and reads nothing: the server does not block on it (non-blocking
    sends, a bounded buffer: the client is dropped and counted) and vehicle 2's genuine client gets
    its 300 lockstep steps."""
    from bridge.vehicles.sim_px4 import Px4SimServer
    from sim_clients import px4_controls_blob

    srv = Px4SimServer(_scenario_two(), port=0, step=0.004, noise=False, lockstep_timeout=3600.0,
                       send_buffer=32 * 1024)
    with _Serve(srv):
        bad = Px4Client(srv.links[0].port, rcvbuf=4096)
        bad.start()
        flood = px4_controls_blob(bad.mav, [bad.clock_us + 4000 * j for j in range(20000)])
        bad.sock.setblocking(False)
        sent = 0
        result = {}
        th = threading.Thread(target=lambda: result.setdefault("steps", _genuine_steps(srv.links[1].port, 300)))
        th.start()
        while sent < len(flood):
            try:
                sent += bad.sock.send(flood[sent:])
            except BlockingIOError:
                select.select([], [bad.sock], [], 0.05)
            except OSError:
                break                        # dropped by the server
            if srv.stats()["slow_clients"]:
                break
        th.join(120)
        bad.close()
        st = srv.stats()
    assert st["slow_clients"] == 1
    steps = result["steps"]
    assert len(steps) == 300 and np.all(np.diff(steps) == 4000)


def _flooder(*args) -> subprocess.Popen:
    """tests/sim_clients.py's flooding client in a process of its own (no GIL shared with the server)."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH")) if p))
    return subprocess.Popen([sys.executable, str(ROOT / "tests" / "sim_clients.py"), *map(str, args)], cwd=str(ROOT),
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def _wait_for(cond, what: str, guard: float = 60.0) -> None:
    """A hang guard, not a deadline."""
    deadline = time.monotonic() + guard
    while not cond():
        assert time.monotonic() < deadline, f"{what}: nothing after {guard:g} s"
        time.sleep(0.01)


@pytest.mark.realtime
@pytest.mark.parametrize("mode", ["stale", "guess"])
def test_px4_flooding_client_takes_at_most_its_share(mode):
    """Vehicle 1's client (another process) reads everything the server sends and floods
    HIL_ACTUATOR_CONTROLS: stamped 0 ("stale": they answer no step) or stamped with the next 2,000
    steps' times ("guess"). While it floods, vehicle 2's genuine client gets its 300 lockstep steps;
    no vehicle took more than one step per round of the server's loop; the stale controls are
    counted and took no step (vehicle 1 stepped only while streaming and on the one message that
    ended its start-up); the guessing client was not read while its backlog was large (counted)."""
    from bridge.vehicles.sim_px4 import Px4SimServer

    events = []
    srv = Px4SimServer(_scenario_two(), port=0, step=0.004, noise=False, lockstep_timeout=3600.0,
                       on_event=events.append)
    with _Serve(srv):
        fl = _flooder("px4-flood", srv.links[0].port, mode)
        try:
            _wait_for(lambda: srv.stats()["received"] >= 2000 or fl.poll() is not None, "the flood")
            got = _genuine_steps(srv.links[1].port, 300)
            flooding = fl.poll() is None
            st = srv.stats()
        finally:
            fl.kill()
            fl.wait()
    assert flooding, "the flooding client stopped before vehicle 2's client was done"
    assert len(got) == 300 and np.all(np.diff(got) == 4000)
    if mode == "stale":                 # vehicle 1's connection: no step for any of its ≥ 2,000 messages
        assert st["step_index"][0] <= st["streamed_steps"] + 1
    v1, v2 = st["vehicles"]
    assert v2["steps"] >= 300
    assert v1["steps"] <= st["rounds"] and v2["steps"] <= st["rounds"]
    if mode == "stale":
        assert v1["steps"] == v1["streamed_steps"] + 1
        assert v1["stale_controls"] >= 1999
        assert sum(e.startswith("vehicle 1:") and "stale_controls" in e for e in events) == 1
    else:
        assert v1["backlog_pauses"] >= 1 and v1["steps"] > v1["streamed_steps"] + 1


@pytest.mark.realtime
def test_px4_fields_clamped_through_the_server_are_counted_and_said_once():
    """Vehicle 1 starts 1 km up flying north at 400 m/s: its NED velocity (cm/s in int16) and
    HIL_GPS's ground speed overflow their fields. Served by the loop, its messages still encode, the
    clamps are counted per vehicle and said once; vehicle 2, at home, keeps stepping, unclamped."""
    from cosim.scenario import parse_scenario

    from bridge.vehicles.sim_px4 import Px4SimServer

    text = Path(SITL).read_text().replace("count = 1", "count = 2").replace("edges = []", "edges = [[1, 2]]")
    text = text.replace("[[initial.agent]]\n", "[[initial.agent]]\nposition = [0.0, 0.0, -1000.0]\n"
                        "velocity = [0.0, 0.0, 0.0, 400.0, 0.0, 0.0]\n[[initial.agent]]\n", 1)
    text = text.replace("position = [0.0, 0.0, 0.0]       # NED", "position = [5.0, 0.0, 0.0]       # NED")
    sc = parse_scenario(text, name="fast", path="fast.toml")
    events = []
    srv = Px4SimServer(sc, port=0, step=0.004, noise=False, lockstep_timeout=3600.0, on_event=events.append)
    with _Serve(srv):
        result = {}
        th = threading.Thread(target=lambda: result.setdefault("home", _genuine_steps(srv.links[1].port, 100)))
        th.start()
        fast = Px4Client(srv.links[0].port)
        try:
            fast.start()
            for _ in range(50):
                fast.send([0.0] * 16, armed=False)
                fast.step()
        finally:
            fast.close()
        th.join(120)
        st = srv.stats()
    v1, v2 = st["vehicles"]
    gps = [m for m in fast.messages if m.get_type() == "HIL_GPS"]
    assert gps and all(m.vn == 32767 for m in gps)
    assert v1["clamped_fields"] >= 50 and v2["clamped_fields"] == 0 and st["clamped_fields"] == v1["clamped_fields"]
    said = [e for e in events if "clamped" in e]
    assert len(said) == 1 and said[0].startswith("vehicle 1:") and "vn" in said[0]
    home = result["home"]
    assert len(home) == 100 and np.all(np.diff(home) == 4000)


@pytest.mark.realtime
def test_px4_idle_client_is_dropped_and_the_vehicle_served_again():
    """A client that connects and never sends a HIL_ACTUATOR_CONTROLS holds its vehicle only until the
    idle timeout; then a genuine client gets the vehicle (from its initial state), and the other
    vehicle was served throughout."""
    from bridge.vehicles.sim_px4 import Px4SimServer

    srv = Px4SimServer(_scenario_two(), port=0, step=0.004, noise=False, lockstep_timeout=3600.0,
                       idle_timeout=0.3)
    retries = []

    def genuine(port, n):
        """`_genuine_steps`, again (at most twice more) when the server dropped this client
        itself as idle: this process was starved for the idle timeout (the machine's load, as
        the server's count of idle drops says), not a fault of the server."""
        for attempt in range(3):
            drops = srv.stats()["idle_drops"]
            try:
                return _genuine_steps(port, n)
            except OSError:
                if attempt == 2 or srv.stats()["idle_drops"] == drops:
                    raise
                retries.append(port)

    with _Serve(srv):
        idle = socket.create_connection(("127.0.0.1", srv.links[0].port))
        other = genuine(srv.links[1].port, 100)
        deadline = time.monotonic() + 60
        while not srv.stats()["idle_drops"] and time.monotonic() < deadline:
            time.sleep(0.05)
        mine = genuine(srv.links[0].port, 50)
        idle.close()
        st = srv.stats()
    assert st["idle_drops"] >= 1 and st["connections"] == 3 + len(retries)
    assert len(other) == 100 and len(mine) == 50 and np.all(np.diff(mine) == 4000)


@pytest.mark.realtime
def test_px4_out_of_range_fields_are_clamped():
    """A body 30,000 km north, 3,000 km up, at 700 m/s and spinning: every HIL_* message still
    encodes (integer fields clamped to their types, latitude to ±90°), never a struct.error."""
    from bridge.vehicles.sim_px4 import Px4SimServer

    srv = Px4SimServer(_load(), port=0, step=0.004, noise=False)
    try:
        ln = srv.links[0]
        b = ln.body
        b.held, b.contact = False, False
        b.S[0:3] = [3e7, -2e7, -3e6]
        b.S[12:15] = [50.0, -60.0, 70.0]
        b.S[15:18] = [700.0, -500.0, 400.0]
        b.wrench[3:6] = [1e6, 0.0, -1e6]
        for k in (0, 1):                                   # with and without HIL_GPS
            ln.k = k
            for m in srv.sensor_messages(ln):
                m.pack(ln.mav)
        ln.k = 0
        msgs = {m.get_type(): m for m in srv.sensor_messages(ln)}
        gps, st = msgs["HIL_GPS"], msgs["HIL_STATE_QUATERNION"]
        clamped = srv.stats()["vehicles"][0]["clamped_fields"]
        # a course a hair west of north is 0 cdeg (359.99994° rounds to 36000: wrapped, not clamped)
        b.S[0:3], b.S[12:15], b.S[15:18], b.wrench[3:6] = 0.0, 0.0, [10.0, -1e-5, 0.0], 0.0
        cog = {m.get_type(): m for m in srv.sensor_messages(ln)}["HIL_GPS"].cog
        clamped_after = srv.stats()["vehicles"][0]["clamped_fields"]
    finally:
        srv.close()
    assert gps.lat == 900000000 and gps.vel == 65534 and gps.alt == 2 ** 31 - 1
    assert (gps.vn, gps.ve, gps.vd) == (32767, -32768, 32767) and (st.vx, st.vy, st.vz) == (32767, -32768, 32767)
    assert st.xacc in (32767, -32768) and abs(st.lon) <= 1800000000
    assert clamped >= 3 * 8 and cog == 0 and clamped_after == clamped   # lat, abs_pressure, alt, vn, ve, vd, xacc, zacc


# ---------------------------------------------------------------------------------- ArduPilot
@pytest.mark.realtime
def test_ardupilot_divergence_resets_one_vehicle_and_the_others_go_on():
    """Vehicle 1 gets full PWM on its six channels (direct mapping: the full wrench) until its body
    leaves any physical range; it is reset to its initial state, counted and reported, the server
    keeps answering both, and vehicle 2 (neutral PWM) steps normally throughout."""
    from bridge.vehicles.sim_ardupilot import ArduPilotJsonServer

    from cosim.scenario import load_scenario

    events = []
    sc = load_scenario(HIL, ["plant.gravity=[0.0, 0.0, 9.81]"])
    srv = ArduPilotJsonServer(sc, port=0, noise=False, on_event=events.append)
    with _Serve(srv):
        a, b = ArduPilotClient(srv.links[0].port), ArduPilotClient(srv.links[1].port)
        try:
            ra = [a.frame([2000] * 6) for _ in range(2400)]          # 6 s at 400 Hz
            rb = [b.frame([1500] * 6) for _ in range(400)]
        finally:
            a.close()
            b.close()
        st = srv.stats()
    assert st["diverged_vehicles"][0] >= 1 and st["diverged_vehicles"][1] == 0 and st["diverged"] >= 1
    assert any("vehicle 1 diverged" in e for e in events)
    assert len(ra) == 2400 and len(rb) == 400
    assert all(np.all(np.isfinite(d["position"])) and np.abs(d["imu"]["gyro"]).max() <= 1e3 for d in ra)
    assert np.allclose([d["timestamp"] for d in rb], np.arange(1, 401) / 400)


@pytest.mark.realtime
def test_ardupilot_flooding_client_takes_at_most_its_share():
    """Vehicle 1's port is flooded with servo packets of new frames by another process that never
    waits for a reply. While it floods, vehicle 2's SITL-like client gets its 400 lockstep frames,
    and no vehicle took more than one step per round of the server's loop (before, one round
    stepped vehicle 1 up to 64 times)."""
    from bridge.vehicles.sim_ardupilot import ArduPilotJsonServer

    srv = ArduPilotJsonServer(_scenario_two(), port=0, noise=False)
    with _Serve(srv):
        fl = _flooder("ardupilot-flood", srv.links[0].port)
        try:
            _wait_for(lambda: srv.stats()["received"] >= 2000 or fl.poll() is not None, "the flood")
            cl = ArduPilotClient(srv.links[1].port)
            try:
                frames = [cl.frame([1000] * 4) for _ in range(400)]
            finally:
                cl.close()
            flooding = fl.poll() is None
            st = srv.stats()
        finally:
            fl.kill()
            fl.wait()
    assert flooding, "the flooding client stopped before vehicle 2's client was done"
    assert np.allclose([d["timestamp"] for d in frames], np.arange(1, 401) / 400)
    v1, v2 = st["vehicles"]
    assert v2["steps"] == 400 and v1["steps"] >= 2000
    assert v1["steps"] <= st["rounds"]


# ---------------------------------------------------------------------------------- the command
@pytest.mark.realtime
@pytest.mark.parametrize("stack, proto", [("ardupilot", "UDP"), ("px4", "TCP")])
def test_sim_protocol_sigterm_exits_143_with_stats(tmp_path, stack, proto):
    """`vehicle --sim-protocol ardupilot|px4 --sim-port 0`: the start-up line names the port the OS
    assigned (not ":0"); SIGTERM stops it with status 143 (as docs/flight-stacks.md says) and the
    --stats file written, with that port in it."""
    import json

    stats = tmp_path / "st.json"
    p = subprocess.Popen([sys.executable, "-m", "cosim.cli", "vehicle", "--scenario", SITL, "--sim-protocol",
                          stack, "--sim-port", "0", "--stats", str(stats)], cwd=str(ROOT),
                         stderr=subprocess.PIPE, text=True)
    try:
        line = p.stderr.readline()
        assert "simulator interface" in line and "no authentication" in line, line
        p.send_signal(signal.SIGTERM)
        rc = p.wait(60)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    assert rc == 143 and stats.exists()
    port = json.loads(stats.read_text())["ports"][0]
    assert port > 0 and f"{proto} 127.0.0.1:{port} " in line, line
