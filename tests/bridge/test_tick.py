"""`bridge.swarm.tick`: the workspace's views are the owners' arrays, and `agent_tick` is the
three kernels it replaces (`age_rules`, `agent_step`, `publish_sample`) called one after the
other as `AgentNode._step_compiled` called them, bit for bit, over random neighbourhoods in
every verdict (fresh, hold, fail-safe, none yet) and in the age rule's cases left to Python."""
from __future__ import annotations

import contextlib

import numpy as np
import pytest

from bridge.mavlink.link import free_base_port
from bridge.swarm.agent import AgentNode
from bridge.swarm.sample_wire import AGE_BINS, age_rules, publish_sample
from bridge.swarm.tick import (O_FRAMES, O_JUMPS, T_AGAIN, T_CHANGED, T_FAILSAFE, T_HOLD,
                               TICK_SLOTS, Workspace, agent_tick)
from controller.kernels import agent_step
from cosim.scenario import load_scenario

from _agent_feed import HIL


@contextlib.contextmanager
def hil_node():
    """hil_6uav's agent 2 (3 neighbours, 3 edges, 2 of them owned), unconnected."""
    nb, bb = free_base_port(6), free_base_port(6)
    sc = load_scenario(HIL, [f"network.base_port={nb}", f"bridge.base_port={bb}"])
    nd = AgentNode(sc, 2, on_event=lambda s: None, insecure=True)
    try:
        yield nd
    finally:
        nd.close()


@pytest.fixture(scope="module")
def node():
    with hil_node() as nd:
        yield nd


def random_ticks(node, trials: int, seed: int):
    """`agent_tick`'s arguments (n, I, F, B, …) over copies of node's workspace with nothing to
    send on: random neighbourhoods, each neighbour's sample of an age in every verdict (none
    yet, fresh, hold, fail-safe, and those left to Python: past the histogram, from the
    future), random θ and last verdicts, and now and then a state beyond float32."""
    rng = np.random.default_rng(seed)
    hybrid, h, max_age, hold, future, h_us = node._tick_args
    I0, F0, B0 = node._ws.detached()
    for trial in range(trials):
        I, F, B = I0.copy(), F0.copy(), B0.copy()
        v = Workspace.views(I, F, B)
        n = int(rng.integers(0, 5000))
        m = v["held_step"].shape[0]
        for q in range(m):
            kind = rng.integers(0, 8)
            age = (0, 1, max_age, max_age + 1, max_age + hold, max_age + hold + 1,
                   AGE_BINS + 3, -future - 2)[kind] if trial % 3 else rng.integers(0, 3)
            v["held_step"][q] = -1 if rng.random() < 0.1 else n - age
        v["held"][:] += rng.normal(0.0, 0.05, v["held"].shape)
        v["S"][:] += rng.normal(0.0, 0.2, v["S"].shape)
        v["theta"][:] = rng.uniform(-1.0, 1.0, v["theta"].shape)
        v["last_verdict"][:] = rng.integers(0, 3, m)
        if trial % 50 == 7:
            v["S"][0, 0] = 1e300              # beyond float32: no frames, the caller's path
        yield (n, I, F, B, hybrid, h, max_age, hold, future, n * h_us, 7,
               int(rng.integers(0, 256)))


def test_the_owners_hold_views_of_the_workspace_with_their_values(node):
    ws = node._ws
    assert ws is not None and ws.intact()
    v = Workspace.views(ws.I, ws.F, ws.B)
    ctl, link = node.controller, node.link
    for name, arr in (("S", node._S), ("theta", ctl.theta), ("u", ctl.u), ("jumped", ctl.jumped),
                      ("owned", node._owned_mask), ("held", link.held_values),
                      ("held_step", link.held_steps), ("ages", link.ages_now)):
        assert np.shares_memory(v[name], arr) and v[name].dtype == arr.dtype, name
        assert v[name].shape == arr.shape and np.array_equal(v[name], arr, equal_nan=True), name
    # the constant copied in
    assert np.array_equal(v["P"], node.stepper.P)
    # an array assigned anew is seen
    keep = ctl.mu
    ctl.mu = keep.copy()
    assert not ws.intact()
    ctl.mu = keep
    assert ws.intact()


def test_a_slot_of_the_wrong_kind_or_order_is_refused():
    class O:
        pass
    o = O()
    slots = [(name, None, np.zeros(2, np.int64 if kind == 0 else np.float64 if kind == 1
                                   else np.uint8)) for name, kind in TICK_SLOTS]
    Workspace(slots)
    bad = list(slots)
    bad[0] = ("held_step", None, np.zeros(2))          # float64 where int64 goes
    with pytest.raises(ValueError, match="held_step"):
        Workspace(bad)
    with pytest.raises(ValueError, match="TICK_SLOTS"):
        Workspace(slots[1:] + slots[:1])
    o.x = np.zeros((2, 3))[:, :2]                       # not C-contiguous
    bad = list(slots)
    bad[5] = ("held", o, "x")
    with pytest.raises(ValueError, match="held"):
        Workspace(bad)


def _separately(n, I, F, B, hybrid, h, max_age, hold, future, t_us, sysid, seq) -> int:
    """What `_step_compiled` did before `agent_tick`, on the buffers' views."""
    v = Workspace.views(I, F, B)
    if age_rules(n, v["held_step"], max_age, hold, future, v["ages"], v["verdict"], v["mode"],
                 v["hist"], v["held"], v["rx"], v["rx_q"], v["rx_r"], v["rx_c"]):
        return T_AGAIN
    vs = v["verdict"].tolist()
    flags = (T_CHANGED if vs != v["last_verdict"].tolist() else 0) \
        | (T_FAILSAFE if 2 in vs else 0) | (T_HOLD if 1 in vs else 0)
    v["last_verdict"][:] = vs
    v["out"][O_JUMPS] = agent_step(v["S"], v["ea"], v["eb"], v["owned"], v["nbr"], v["mode"],
                                   hybrid, v["P"], h, 3, 2 in vs, v["theta"], v["rx"],
                                   v["theta_prev"], v["theta_jump"], v["mu"], v["jumped"],
                                   v["term"], v["rel"], v["u"])
    v["out"][O_FRAMES] = publish_sample(v["pbuf"], t_us, v["S"], v["theta_jump"], v["own_r"],
                                        v["pth"], sysid, seq, v["pf32"], v["ends"], v["sfds"],
                                        v["sok"], v["pst"])
    return flags


def test_agent_tick_is_the_three_calls_bit_for_bit(node):
    hybrid, h, max_age, hold, future, h_us = node._tick_args
    assert max_age >= 0 and hold > 0
    seen = set()
    for trial, (n, I, F, B, *rest) in enumerate(random_ticks(node, 400, 31)):
        I2, F2, B2 = I.copy(), F.copy(), B.copy()
        a = agent_tick(n, I, F, B, *rest)
        b = _separately(n, I2, F2, B2, *rest)
        assert a == b, trial
        assert I.tobytes() == I2.tobytes() and F.tobytes() == F2.tobytes() \
            and B.tobytes() == B2.tobytes(), trial
        out = Workspace.views(I, F, B)["out"]
        seen.add((a & T_AGAIN, a & T_FAILSAFE, a & T_HOLD, a & T_CHANGED,
                  bool(out[O_JUMPS]) if not a & T_AGAIN else None,
                  int(out[O_FRAMES]) < 0 if not a & T_AGAIN else None))
    # every case came up: left to Python, fail-safe, hold, all fresh, a verdict changed or
    # not, jumps, and a value beyond float32
    assert (T_AGAIN, 0, 0, 0, None, None) in seen
    assert any(s[1] for s in seen) and any(s[2] for s in seen)
    assert any(not s[0] and not s[1] and not s[2] for s in seen)
    assert any(s[3] for s in seen) and any(not s[0] and not s[3] for s in seen)
    assert any(s[4] for s in seen) and any(s[5] for s in seen)
