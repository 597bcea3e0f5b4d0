"""The light agent's per-step fast paths (issue 31) against the paths they shortcut, bit for bit:
one vehicle's wire row to its state row, and one vehicle's wrench to its controls (the direct
mapping), in plain floats instead of numpy's one-row arrays. (The whole agent against the
reference, over a lockstep run, is tests/test_agents.py's lockstep swarm = `run` on the float32
plant.)"""
from __future__ import annotations

import numpy as np
import pytest

from bridge.mavlink import frames
from bridge.mavlink.mapping import MappingSpec
from bridge.mavlink.transport import Transport, wire_row_to_state, wire_to_state
from controller import layout
from controller.se3 import quat_to_rot_row

EDGE = (0.0, -0.0, 1.0, -1.0, 1e-40, float(np.finfo(np.float32).max))


def _bits(a) -> bytes:
    return np.ascontiguousarray(np.asarray(a, dtype=np.float64)).tobytes()


def _reference_state(w, world):
    """wire_to_state's numpy path for one row (before the fast path)."""
    w = np.asarray(w, float)[None, :]
    S = np.empty((1, layout.S_WIDTH))
    S[:, layout.P] = w[:, 0:3]
    S[:, layout.R] = np.array([quat_to_rot_row(*w[0, 3:7].tolist())])
    S[:, layout.XI] = w[:, 7:13]
    return frames.state_ned_to_world(S, world)


@pytest.mark.parametrize("world", frames.WORLD_FRAMES)
def test_one_wire_row_is_the_fleet_paths_bits(world):
    rng = np.random.default_rng(1)
    for trial in range(2000):
        w = rng.normal(size=13) * 10.0 ** rng.integers(-3, 4)
        q = rng.normal(size=4)
        w[3:7] = q / np.linalg.norm(q)
        if trial % 5 == 0:
            w[rng.integers(0, 13, 4)] = rng.choice(EDGE, 4)
            w[3:7] = rng.choice([-0.0, 0.0, 1.0], 4) if trial % 10 == 0 else w[3:7]
            if not np.any(w[3:7]):
                w[3] = 1.0
        w = w.astype(np.float32).astype(float)
        ref = _reference_state(w, world)
        assert _bits(wire_row_to_state(w.tolist(), world)) == _bits(ref[0])
        assert _bits(wire_to_state(w[None, :], world)) == _bits(ref)


@pytest.mark.parametrize("gravity", [False, True])
@pytest.mark.parametrize("world", frames.WORLD_FRAMES)
def test_one_vehicles_controls_are_the_fleet_paths_bits(world, gravity):
    """Transport of one vehicle (the fast path) against the same vehicle as row 0 of a fleet of
    two (numpy's path): controls, saturation and NaN counters."""
    rng = np.random.default_rng(2)
    spec = MappingSpec(max_wrench=(50.0, 50.0, 50.0, 20.0, 20.0, 20.0))
    g = np.array([0.0, 0.0, 9.81]) if world == "ned" else np.array([0.0, 0.0, -9.81])
    one = Transport([spec], world, np.array([2.4]), g, gravity)
    two = Transport([spec, spec], world, np.array([2.4, 2.4]), g, gravity)
    assert one.mapping.one_direct and not two.mapping.one_direct
    for trial in range(3000):
        u = rng.normal(size=6) * 10.0 ** rng.integers(-2, 3)
        if trial % 4 == 0:
            u[rng.integers(0, 6, 3)] = rng.choice((0.0, -0.0, np.nan, np.inf, -np.inf, 1e3), 3)
        S = np.zeros((1, layout.S_WIDTH))
        q = rng.normal(size=4)
        S[0, layout.R] = np.array(quat_to_rot_row(*(q / np.linalg.norm(q)).tolist()))
        if trial % 50 == 0:
            S[0, layout.R] = np.nan
        c1 = one.controls(u[None, :], S)
        c2 = two.controls(np.vstack([u, np.zeros(6)]), np.vstack([S, S]))
        assert c1.shape == (1, 6)
        assert _bits(c1[0]) == _bits(c2[0]), (u, c1, c2)
        assert one.mapping.last_saturated[0] == two.mapping.last_saturated[0]
    # (the fleet counts a step once whichever vehicle saturated: compare vehicle 1's count)
    assert one.mapping.saturations == one.mapping.saturated_vehicles[0] \
        == two.mapping.saturated_vehicles[0] > 0
    assert one.nan_commands == two.nan_commands > 0
