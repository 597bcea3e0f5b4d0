"""The light agent's per-step fast paths (issue 31) against the paths they shortcut, bit for bit:
one vehicle's wire row to its state row, and one vehicle's wrench to its controls (the direct
mapping), in plain floats instead of numpy's one-row arrays. (The whole agent against the
reference, over a lockstep run, is tests/test_agents.py's lockstep swarm = `run` on the float32
plant.)"""
from __future__ import annotations

import numpy as np
import pytest

from bridge.mavlink import frames
from bridge.mavlink.mapping import FleetMapping, MappingSpec
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


@pytest.mark.parametrize("encoding", ["json", "cdr"])
def test_the_agents_block_encoded_log_is_the_per_record_log(tmp_path, encoding):
    """The agent's log buffers records and encodes them in blocks (off the per-step path): it
    holds the messages the per-record logger wrote, value for value and in each topic's order,
    with NaN μ (the edges it does not own), jumps and link statistics in between."""
    from bridge.mavlink.link import free_base_port
    from bridge.swarm.agent import NEIGHBOURS, AgentNode, _agent_logger
    from cosim.log.reader import read_log
    from cosim.log.writer import McapLogger
    from cosim.scenario import load_scenario

    root = __import__("pathlib").Path(__file__).resolve().parents[2]
    sc = load_scenario(root / "scenarios" / "hil_6uav.toml",
                       [f"network.base_port={free_base_port(6)}",
                        f"bridge.base_port={free_base_port(6)}"])
    node = AgentNode(sc, 2, on_event=lambda s: None)
    try:
        loc = node.local
        N, M = loc.graph.n, loc.graph.M
        got = _agent_logger(tmp_path / "block.mcap", node, {}, encoding, block=7)
        ref = McapLogger(tmp_path / "ref.mcap", loc, controller=node.law, agent_ids=node.agents,
                         edge_ids=node.edge_ids, encoding=encoding)
        ref.add_channel("/neighbours", NEIGHBOURS)
        rng = np.random.default_rng(3)
        for r in range(40):
            t_ns = r * 20_000_000
            S = rng.normal(size=(N, layout.S_WIDTH))
            args = (S, rng.normal(size=(N, 6)), rng.normal(size=M),
                    np.where(rng.random(M) < 0.5, np.nan, rng.random(M)), rng.random(M) < 0.1,
                    rng.random(M), rng.random(M), rng.random(M), rng.normal(size=(N, 4)),
                    float(rng.random()), float(rng.random()))
            node.used = {j: (r - 1, 1) for j in node.neighbours}
            node._state = {j: ("fresh", "hold", "failsafe")[(r + j) % 3] for j in node.neighbours}
            node.failsafe = r % 4 == 0
            if r in (5, 23):
                for lg in (got, ref):
                    lg.jump(t_ns, t_ns * 1e-9, 1, 0.1, 0.2, 0.3)
            if r % 10 == 0:
                for lg in (got, ref):
                    lg.link_stats(t_ns, {"sent": r})
            got.record(t_ns, *args)
            ref.record(t_ns, *args)
            ref.message("/neighbours", t_ns, {"agent": node.i, "failsafe": node.failsafe,
                                              "neighbours": [{"agent": j, "sample_step": r - 1,
                                                              "age_steps": 1,
                                                              "state": node._state[j]}
                                                             for j in node.neighbours]})
            S[:] = 0.0     # the master reuses its arrays: the buffer holds copies
        got.close()
        ref.close()
        a, b = read_log(tmp_path / "block.mcap"), read_log(tmp_path / "ref.mcap")
        assert set(a["messages"]) == set(b["messages"])
        same = __import__("json").dumps   # NaN (CDR's μ) compares equal as text
        for topic, msgs in b["messages"].items():
            assert same(a["messages"][topic], sort_keys=True) == same(msgs, sort_keys=True), topic
        assert len(a["messages"]["/tf"]) == 40 and len(a["messages"]["/jumps"]) == 2
    finally:
        node.close()


def test_one_vehicles_decode_is_the_fleet_paths_bits():
    """The loopback vehicle's row path (`FleetMapping.decode_row`, its every command) against
    numpy's fleet path: the same products, every bit, signed zeros and NaN included."""
    rng = np.random.default_rng(4)
    spec = MappingSpec(max_wrench=(50.0, 50.0, 50.0, 20.0, 20.0, 20.0))
    one = FleetMapping([spec])
    two = FleetMapping([spec, spec])
    assert one.one_direct
    for trial in range(2000):
        c = rng.uniform(-1, 1, 6).astype(np.float32).astype(float)
        if trial % 5 == 0:
            c[rng.integers(0, 6, 2)] = rng.choice((0.0, -0.0, 1.0, -1.0, np.nan), 2)
        row = one.decode_row(c.tolist())
        assert _bits(np.array(row)) == _bits(two.decode(np.vstack([c, c]))[0])
