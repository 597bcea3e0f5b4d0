"""Real-time hardware in the loop through a fault-injecting UDP relay: 10 % loss, 5 ms jitter
(reordering), and a link cut (fail-safe within 3 control periods, loss reported, recovery)."""
from __future__ import annotations

import os

import pytest

os.environ.setdefault("MAVLINK20", "1")

from _machine import CpuShare, skip_if_deadline_missed  # noqa: E402
from _bridge import HIL, Relay, VehicleProcess, free_base_port, load  # noqa: E402


def _run(tmp_path, duration, loss=0.0, jitter=0.0, cut=None):
    """6 vehicles (a process) <-> relay (a thread) <-> bridge (this thread, cosim's Master).
    Also returns `skip_if_busy()`, which skips the test when the machine, busy with other
    work, could not keep the 250 Hz deadline (tests/_machine.py: the bridge's late steps, the
    vehicles' late ticks): called before the assertions that need the deadline kept."""
    import threading

    from bridge.mavlink.hil import run_hil
    from bridge.mavlink.plant import MavlinkPlant

    port = free_base_port(6)
    sc = load([f"bridge.base_port={port}", f"simulation.duration={duration}"])
    from bridge.cli import warm_up

    warm_up(sc)
    events = []
    with CpuShare() as cpu, Relay([port + i for i in range(6)], loss=loss, jitter=jitter) as relay:
        eps = [a for p in relay.ports for a in ("--endpoint", f"udpout:127.0.0.1:{p}")]
        with VehicleProcess(["--scenario", HIL, "--aux-rate", "0", *eps], tmp_path) as veh:
            plant = MavlinkPlant(sc, connect_timeout=20, on_event=events.append)
            try:
                plant.connect()
                timers = []
                if cut is not None:
                    t_cut, t_back = cut
                    timers = [threading.Timer(t_cut, setattr, (relay, "cut", True)),
                              threading.Timer(t_back, setattr, (relay, "cut", False))]
                    for t in timers:
                        t.start()
                summary = run_hil(sc, plant)
                for t in timers:
                    t.cancel()
                # every status text each vehicle sent (the printed events are thinned: one
                # fail-safe/resume line per vehicle per STATUS_QUIET_S)
                texts = [list(v.statustexts) for v in plant.vehicles]
            finally:
                plant.close()
            vst = veh.stop()

    def skip_if_busy():
        skip_if_deadline_missed(cpu, {"the bridge": (summary["link"]["late_steps"],
                                                     summary["steps"]),
                                      "the vehicles": (vst["late_ticks"], vst["ticks"])},
                                "real-time HIL through the relay")

    return summary, vst, events, relay, skip_if_busy, texts


@pytest.mark.slow
@pytest.mark.realtime
@pytest.mark.timeout(120)
def test_loss_jitter_reordering_still_converges(tmp_path):
    s, vst, events, relay, skip_if_busy, _ = _run(tmp_path, 8.0, loss=0.10, jitter=0.005)
    ln = s["link"]
    assert relay.dropped > 0.05 * (relay.forwarded + relay.dropped)
    assert ln["dropped"] > 0                       # seen as sequence gaps
    first, final = s["samples"][0], s["final"]
    assert first["rot_err"] > 2.5
    assert vst["received"] > 0 and vst["malformed"] == 0
    skip_if_busy()   # the rate of convergence needs the 250 Hz deadline kept
    # the co-simulation has rot_err 0.17, pos_err 0.007 at 8 s (0.75, 0.036 at 4 s)
    assert final["rot_err"] < 0.4 and final["pos_err"] < 0.03, final
    assert final["rot_err"] < s["samples"][4]["rot_err"] / 2   # still falling at the nominal rate


@pytest.mark.slow
@pytest.mark.realtime
@pytest.mark.timeout(120)
def test_link_cut_fails_safe_reports_and_recovers(tmp_path):
    s, vst, events, relay, skip_if_busy, texts = _run(tmp_path, 8.0, cut=(2.0, 3.0))
    h = 0.004
    ln = s["link"]
    # the vehicles failed safe, each within 3 control periods of its last command: the command
    # timeout is 2 h, checked every physics tick h. Counted from the time the detecting tick was
    # due this holds exactly; the wall-clock delay adds the tick's lateness, which is the
    # scheduler's (a loaded 2-core machine can deschedule a process for ms): it is measured by
    # benchmarks/bench_bridge_flood.py, and here only required not to come early. (A machine
    # that cannot keep the rate adds fail-safes outside the cut: the vehicle lists 200.)
    assert vst["failsafe"] >= 6
    d_tick, d_wall = vst["failsafe_tick_delays"], vst["failsafe_delays"]
    assert len(d_tick) == len(d_wall) == min(vst["failsafe"], 200)
    assert max(d_tick) <= 3 * h + 1e-6, d_tick
    assert min(d_wall) >= 2 * h - 1e-6, d_wall   # the stats round delays to µs
    # the bridge reported the loss and the recovery of every link
    assert ln["link_losses"] >= 6 and ln["link_recoveries"] >= 6 and ln["links_down"] == []
    assert sum("link lost" in e for e in events) >= 6 and sum("link recovered" in e for e in events) >= 6
    # (the vehicles' "failsafe" STATUSTEXTs are lost in the cut; "commands resumed" comes through
    # from every vehicle. The printed events show it unless the same vehicle already reported a
    # fail-safe or resume in the 5 s before, which a busy machine causes at the start: so the
    # vehicles' texts are counted, as the bridge received them)
    assert all(any("commands resumed" in x for x in tx) for tx in texts), texts
    skip_if_busy()   # the rate of convergence needs the 250 Hz deadline kept
    # ... and the loop recovered
    assert s["final"]["rot_err"] < 0.5 and s["final"]["pos_err"] < 0.05, s["final"]
    assert s["final"]["rot_err"] < s["samples"][2]["rot_err"] / 2


@pytest.mark.realtime
@pytest.mark.timeout(120)
def test_lockstep_over_lossy_reordering_link_stays_bit_faithful():
    """Lockstep through the relay (10 % loss, 2 ms jitter): lost commands/states are re-sent,
    stale duplicates are dropped, and the run still equals the quantised co-simulation exactly."""
    import numpy as np

    from bridge.mavlink.plant import MavlinkPlant
    from bridge.mavlink.transport import QuantizedPlant
    from cosim.master import make_controller
    from _bridge import VehicleThread

    port = free_base_port(6)
    sc = load([f"bridge.base_port={port}", "bridge.lockstep_resend=0.01"])
    with Relay([port + i for i in range(6)], loss=0.10, jitter=0.002, seed=3) as relay:
        eps = [f"udpout:127.0.0.1:{p}" for p in relay.ports]
        with VehicleThread(scenario=sc, lockstep=True, aux_rate=0, endpoints=eps):
            p = MavlinkPlant(sc, lockstep=True, connect_timeout=20, on_event=lambda s: None).connect()
            q = QuantizedPlant(sc)
            c1, c2 = make_controller("hybrid", sc), make_controller("hybrid", sc)
            try:
                diff = 0.0
                for _ in range(150):
                    S1, S2 = p.read(), q.read()
                    diff = max(diff, float(np.abs(S1 - S2).max()))
                    u1, _ = c1.step_state(S1, sc.step)
                    u2, _ = c2.step_state(S2, sc.step)
                    p.apply(u1)
                    q.apply(u2)
                    p.advance(sc.step)
                    q.advance(sc.step)
                st = p.stats()
            finally:
                p.close()
                q.close()
    assert diff == 0.0
    assert relay.dropped > 50 and st["lockstep_resends"] > 0
