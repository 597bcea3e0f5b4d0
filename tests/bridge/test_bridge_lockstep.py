"""Lockstep hardware in the loop over real UDP: bit-faithful to the transport-quantised
co-simulation, converges with 6 vehicles, and the tlog is readable by mavlogdump.py."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

os.environ.setdefault("MAVLINK20", "1")

from _bridge import HIL, ROOT, VehicleProcess, VehicleThread, free_base_port, load  # noqa: E402


def _lockstep_pair(sc, n_steps, key=None, tlog=None):
    """Runs the same controller against MavlinkPlant (lockstep, vehicles in a thread) and against
    QuantizedPlant; returns the max |S_hil − S_ref| over every step and the plant stats."""
    from bridge.mavlink.plant import MavlinkPlant
    from bridge.mavlink.transport import QuantizedPlant
    from cosim.master import make_controller

    with VehicleThread(scenario=sc, lockstep=True, key=key, aux_rate=0):
        p = MavlinkPlant(sc, lockstep=True, key=key, tlog=tlog, connect_timeout=10, on_event=lambda s: None)
        q = QuantizedPlant(sc)
        try:
            p.connect()
            c1, c2 = make_controller("hybrid", sc), make_controller("hybrid", sc)
            diff = 0.0
            for _ in range(n_steps):
                S1, S2 = p.read(), q.read()
                diff = max(diff, float(np.abs(S1 - S2).max()))
                u1, _ = c1.step_state(S1, sc.step)
                p.apply(u1)
                u2, _ = c2.step_state(S2, sc.step)
                q.apply(u2)
                p.advance(sc.step)
                q.advance(sc.step)
            diff = max(diff, float(np.abs(p.read() - q.read()).max()))
            return diff, p.stats(), q.read().copy()
        finally:
            p.close()
            q.close()


@pytest.mark.realtime
def test_lockstep_matches_quantized_cosim_bitwise():
    port = free_base_port(6)
    sc = load([f"bridge.base_port={port}"])
    diff, st, S = _lockstep_pair(sc, 400)
    assert diff <= 1e-9, diff
    assert diff == 0.0  # in fact bit for bit
    assert st["rejected"] == 0 and st["malformed"] == 0 and st["sent"] >= 6 * 400


@pytest.mark.realtime
def test_lockstep_bitwise_enu_allocation_gravity_command_long():
    """ENU/FLU frames, a tilted-hexarotor allocation around the hover baseline, gravity with
    feed-forward compensation, and COMMAND_LONG DO_SET_ACTUATOR output."""
    port = free_base_port(6)
    sc = load([f"bridge.base_port={port}", "bridge.world_frame=\"enu\"", "bridge.mapping=\"allocation\"",
               "bridge.allocation={max_thrust = 60.0, arm_length = 0.3}",
               "bridge.gravity_compensation=true", "plant.gravity=[0.0, 0.0, -9.81]",
               "bridge.output=\"do_set_actuator\""])
    diff, st, S = _lockstep_pair(sc, 150)
    assert diff == 0.0, diff
    assert st["saturations"] > 0  # the initial transient saturates the rotors (direction kept)


@pytest.mark.slow
@pytest.mark.realtime
def test_lockstep_converges_cli_and_tlog(tmp_path):
    """`se3sync vehicle --lockstep` and `se3sync connect --lockstep` as processes, 6 vehicles, the
    full 20 s of hil_6uav: the hybrid loop converges; MCAP (in CDR) + summary + tlog are
    written."""
    port = free_base_port(6)
    sets = ["--set", f"bridge.base_port={port}"]
    summary = tmp_path / "s.json"
    tlog = tmp_path / "bridge.tlog"
    with VehicleProcess(["--scenario", HIL, "--lockstep", "--aux-rate", "0", *sets], tmp_path) as veh:
        r = subprocess.run([sys.executable, "-m", "cosim.cli", "connect", HIL, "--lockstep", *sets,
                            "--summary", str(summary), "--log", str(tmp_path / "l.mcap"), "--tlog", str(tlog),
                            "--log-encoding", "cdr", "--connect-timeout", "20"],
                           capture_output=True, text=True, timeout=240, cwd=str(ROOT))
        vst = veh.stop()
    assert r.returncode == 0, r.stderr
    s = json.loads(summary.read_text())
    assert s["steps"] == 5000 and s["n_jumps"] >= 5 and s["lockstep"]
    assert s["final"]["rot_err"] < 3e-3 and s["final"]["pos_err"] < 2e-4, s["final"]  # from 2.8, 0.19
    ln = s["link"]
    assert ln["rejected"] == 0 and ln["malformed"] == 0 and ln["sent"] >= 30000
    assert vst["commands"] >= 30000 and vst["steps"] == [5000] * 6
    # the MCAP has the link statistics
    from cosim.log.reader import read_log

    log = read_log(tmp_path / "l.mcap")
    assert log["messages"].get("/link/stats") and log["metadata"]["plant"] == "mavlink"
    # written in CDR (--log-encoding cdr), with the summary's last errors in its last record
    from mcap.reader import make_reader

    with open(tmp_path / "l.mcap", "rb") as f:
        enc = {c.topic: c.message_encoding for c in make_reader(f).get_summary().channels.values()}
    assert enc["/edges"] == enc["/tf"] == "cdr" and enc["/link/stats"] == "json"
    last = log["messages"]["/edges"][-1][1]["edges"]
    assert max(e["rot_err"] for e in last) < 3e-3
    # mavlogdump.py reads the tlog (both directions)
    mld = os.path.join(os.path.dirname(sys.executable), "mavlogdump.py")
    out = subprocess.run([sys.executable, mld, "--types", "ODOMETRY,SET_ACTUATOR_CONTROL_TARGET", str(tlog)],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.count("ODOMETRY") >= 30000 and out.stdout.count("SET_ACTUATOR_CONTROL_TARGET") >= 30000


def test_connect_exits_3_when_no_vehicle(tmp_path):
    port = free_base_port(6)
    r = subprocess.run([sys.executable, "-m", "cosim.cli", "connect", HIL, "--set", f"bridge.base_port={port}",
                        "--connect-timeout", "0.5"], capture_output=True, text=True, timeout=60, cwd=str(ROOT))
    assert r.returncode == 3
    lines = [x for x in r.stderr.splitlines() if x.strip()]
    assert len(lines) == 1 and "did not connect within 0.5 s" in lines[0], r.stderr


def _connect_lockstep(tmp_path, sets, duration):
    """`se3sync connect --lockstep --force` against `se3sync vehicle --lockstep` (processes):
    (exit status, stderr lines, summary, log path)."""
    port = free_base_port(6)
    sets = ["--set", f"bridge.base_port={port}", *(x for s in sets for x in ("--set", s))]
    summary, log = tmp_path / "s.json", tmp_path / "l.mcap"
    with VehicleProcess(["--scenario", HIL, "--lockstep", "--aux-rate", "0", *sets], tmp_path) as veh:
        r = subprocess.run([sys.executable, "-m", "cosim.cli", "connect", HIL, "--lockstep", *sets,
                            "--force", "--duration", str(duration), "--summary", str(summary),
                            "--log", str(log), "--connect-timeout", "20"],
                           capture_output=True, text=True, timeout=240, cwd=str(ROOT))
        veh.stop()
    lines = [x for x in r.stderr.splitlines() if x.strip()]
    assert "Traceback" not in r.stderr, r.stderr
    return r.returncode, lines, json.loads(summary.read_text()), log


@pytest.mark.realtime
def test_connect_says_when_the_jumps_exceed_the_bound(tmp_path):
    """Issue 28 §2 for `connect`: h = 40 ms (unstable above 19 ms, hence --force) chatters over
    the lockstep link without diverging: more jumps than Theorem 1's bound. The summary says so
    and so does one stderr line, as for `run`; the exit status stays 0."""
    rc, lines, s, _ = _connect_lockstep(tmp_path, ["simulation.step=0.04"], 30)
    assert s["n_jumps"] > s["jump_bound"] and s["jump_bound_exceeded"] is True, s["n_jumps"]
    assert s["diverged"] is None and s["steps"] == 750
    warn = [x for x in lines if "more than the bound" in x]
    assert len(warn) == 1 and warn[0].startswith("se3sync connect: warning: ")
    assert f"{s['n_jumps']} jumps" in warn[0] and f"= {s['jump_bound']} " in warn[0]
    assert rc == 0, lines


@pytest.mark.realtime
def test_connect_ends_a_diverging_run_with_its_status(tmp_path):
    """Issue 28 §2 for `connect`: h = 0.2 s drives the swarm apart over the lockstep link (the
    vehicles' wrench limits keep the state finite): the run stops at the first 1 s sample whose
    V̄ exceeds 100 V̄(0), exit 6, one line saying when and why, log and summary complete."""
    from cosim import guards
    from cosim.log.reader import read_log

    rc, lines, s, log = _connect_lockstep(tmp_path, ["simulation.step=0.2"], 60)
    assert rc == guards.EXIT_DIVERGED == 6, lines
    dv = s["diverged"]
    over = [x["t"] for x in s["samples"] if x["V"] > guards.DIVERGE_FACTOR * s["V0"]]
    assert over and dv["t"] == over[0] and "V̄" in dv["reason"]
    assert s["steps"] == dv["step"] < 300 and s["interrupted"] is False
    line = [x for x in lines if "diverged" in x]
    assert len(line) == 1 and line[0].startswith("se3sync connect: diverged at t = ")
    assert "exit status 6" in line[0]
    r = read_log(log)
    assert not r["truncated"] and r["outcome"]["diverged"] == dv
