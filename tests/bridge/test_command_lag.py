"""How late each command leaves after its step's deadline (`MavlinkPlant`, real time): the lag,
and the commands later than (1 − VEHICLE_TICK_LEAD) of a step, which reach a loopback vehicle
locked to the swarm's timeline after the tick they were meant for and act a step late (a step
whose command is that late is not a late step: it ended before the next deadline). The plant's
clock is a stand-in here, so each command's lag is exactly the one chosen."""
from __future__ import annotations

import time

import numpy as np
import pytest

from _bridge import free_base_port, load

from bridge.mavlink import plant as plant_mod
from bridge.mavlink.config import VEHICLE_TICK_LEAD
from bridge.mavlink.plant import HIST_BIN, LATE_KEPT, MavlinkPlant


class _Clock:
    """time.monotonic() as the test sets it; the rest of the time module as it is."""

    def __init__(self, t):
        self.t = t

    def monotonic(self):
        return self.t

    def __getattr__(self, name):
        return getattr(time, name)


@pytest.mark.parametrize("seed", range(3))
def test_command_lag_and_the_commands_past_the_vehicles_tick(seed, monkeypatch):
    rng = np.random.default_rng(seed)
    sc = load([f"bridge.base_port={free_base_port(6)}"])
    clock = _Clock(1000.0)
    monkeypatch.setattr(plant_mod, "time", clock)
    p = MavlinkPlant(sc, connect_timeout=1, on_event=lambda s: None)
    try:
        h = p.h
        t0 = 1000.0
        p.pace_from(t0)
        n = 200
        # lags around the tick's edge, a few early (the host steps up to 0.1 ms early), and
        # past the next deadline
        lags = rng.uniform(-1e-4, 1.3 * h, size=n)
        lags[:5] = (1.0 - VEHICLE_TICK_LEAD) * h + np.array([-2e-6, 2e-6, -1e-9, 0.5e-6, 0.0])
        u = np.zeros((p.n, 6))
        for k in range(n):
            p.k = k
            clock.t = t0 + k * h + lags[k]
            p.apply(u)
            p._S = None
        st = p.stats()
        # the same decisions from the same clock readings, computed here
        got_lags = [(t0 + k * h + lags[k]) - (t0 + k * h) for k in range(n)]
        past = [k for k in range(n) if got_lags[k] > (1.0 - VEHICLE_TICK_LEAD) * h]
        assert st["commands_past_tick"] == len(past)
        assert st["past_tick_first"] == past[:LATE_KEPT]
        assert st["command_lag_ms_max"] == pytest.approx(max(got_lags) * 1e3, abs=1e-9)
        # the quantiles of a histogram of 10 µs bins (negative lags count as 0)
        pos = np.maximum(got_lags, 0.0)
        for q, key in ((0.5, "command_lag_ms_p50"), (0.99, "command_lag_ms_p99")):
            want = np.quantile(pos, q, method="inverted_cdf")
            assert abs(st[key] - want * 1e3) <= HIST_BIN * 1e3 + 1e-9, (key, st[key], want)
    finally:
        p.close()


def test_lockstep_commands_have_no_lag(monkeypatch):
    sc = load([f"bridge.base_port={free_base_port(6)}"])
    p = MavlinkPlant(sc, connect_timeout=1, on_event=lambda s: None, lockstep=True)
    try:
        p.t0 = 0.0
        for k in range(5):
            p.k = k
            p.apply(np.zeros((p.n, 6)))
            p._S = None
        st = p.stats()
        assert st["commands_past_tick"] == 0 and st["command_lag_ms_max"] is None
    finally:
        p.close()
