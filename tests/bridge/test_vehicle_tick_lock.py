"""The loopback vehicle's ticks locked to a swarm's steps (`se3sync vehicle --start-file`,
bridge/vehicles/loopback.py): each tick falls TICK_LEAD of a tick before a step of the swarm,
whatever phase the process started at, and stays on that grid after it fell behind."""
from __future__ import annotations

import os
import random
import time

import pytest

os.environ.setdefault("MAVLINK20", "1")

from _bridge import VehicleThread, free_base_port  # noqa: E402

from bridge.vehicles.loopback import TICK_LEAD, locked_tick, start_file_origin  # noqa: E402


def _on_grid(t, origin, tick, lead):
    m = (t - (origin - lead)) / tick
    return abs(m - round(m)) < 1e-6


@pytest.mark.parametrize("seed", range(5))
def test_locked_tick_is_the_first_grid_time_not_before_now(seed):
    rng = random.Random(seed)
    for _ in range(200):
        tick = rng.choice([0.004, 0.01, 0.02, 1 / 3])
        lead = rng.uniform(0.0, 0.9) * tick
        origin = rng.uniform(0.0, 1e4)
        now = origin + rng.uniform(-50.0, 50.0) * tick
        t = locked_tick(origin, now, tick, lead)
        assert now <= t < now + tick + 1e-9
        assert _on_grid(t, origin, tick, lead)
    # exactly on the grid: that very time
    assert locked_tick(10.0, 10.0 - 0.001, 0.01, 0.001) == pytest.approx(10.0 - 0.001)


def test_start_file_origin_reads_the_swarm_start_as_monotonic_time(tmp_path):
    p = tmp_path / "start"
    origin = start_file_origin(p)
    assert origin() is None                      # not written yet
    p.write_text("not a time", encoding="utf-8")
    assert origin() is None
    p.write_text("nan", encoding="utf-8")
    assert origin() is None
    start = time.time() + 2.0
    p.write_text(repr(start), encoding="utf-8")
    o = origin()
    # the same instant on the other clock (two clock reads apart: generous, a loaded machine)
    assert abs(o - (time.monotonic() + (start - time.time()))) < 0.5


@pytest.mark.realtime
def test_vehicle_ticks_lock_to_the_swarm_steps_and_stay_locked_after_falling_behind():
    tick = 0.01
    origin = time.monotonic() + 0.123   # an arbitrary phase against the process's start
    stalled = []

    def live(server):   # once locked, the process stalls 15 ticks once (as a starved one would)
        if server.locked_at is not None and len(server.locked_due) == 10 and not stalled:
            stalled.append(True)
            time.sleep(15 * tick)

    with VehicleThread(count=1, base_port=free_base_port(1), rate=1 / tick,
                       aux_rate=0) as srv:
        srv.tick_origin = lambda: origin
        srv.live = live
        t_end = time.monotonic() + 30.0
        while len(srv.locked_due) < 30 and time.monotonic() < t_end:
            time.sleep(0.02)
        due = list(srv.locked_due)
        st = srv.stats()
    assert srv.locked_at == origin and st["tick_locked"] and st["tick_lead_s"] == TICK_LEAD * tick
    assert len(due) >= 30 and stalled
    assert st["resyncs"] >= 1, "the stall was meant to make the vehicle resynchronise"
    lead = TICK_LEAD * tick
    assert all(_on_grid(t, origin, tick, lead) for t in due), [
        ((t - (origin - lead)) / tick) for t in due]
    # whole ticks apart, and a jump of more than ten where it resynchronised (more than one
    # only if this machine stalled it again)
    gaps = [round((b - a) / tick) for a, b in zip(due, due[1:])]
    assert all(g >= 1 for g in gaps) and sum(g > 10 for g in gaps) >= 1, gaps
