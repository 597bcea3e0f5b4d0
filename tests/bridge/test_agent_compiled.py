"""The agent process's compiled step (`AgentNode(compiled=True)`, `controller.kernels.agent_step`)
against its reference (``compiled=False``: `AgentStepper` per edge on dicts), over the same
deterministic feed (tests/bridge/_agent_feed.py), its vehicle's link included (the state read and
the command framed and sent by compiled code, or by the reference paths): every datagram the node
sends to its vehicle and to its neighbours, the controller's outputs of every step, the summary and the age-rule counters
are identical, bit for bit, through jumps, holds, fail-safes and rejoins."""
from __future__ import annotations

import json

import numpy as np
import pytest

from _agent_feed import AGE_RULE, HIL, run_pair, vehicle_commands

STEPS = 300
REF, NEW = {"compiled": False}, {"compiled": True}
ARRAYS = ("S", "u", "theta", "theta_prev", "theta_jump", "mu", "jumped")


def _same_json(a, b) -> bool:
    # (NaN μ of the edges an agent does not own compares equal as text)
    return json.dumps(a, sort_keys=True, default=repr) == json.dumps(b, sort_keys=True,
                                                                     default=repr)


def assert_identical(ref: dict, new: dict, lockstep: bool) -> None:
    assert ref["node"].pop("compiled") is False and new["node"].pop("compiled") is True
    # the neighbours' samples: the link's Python path, and (real time) its compiled decoder
    # (bridge/swarm/sample_wire.py), with the same counts
    assert ref["node"].pop("scanned") == 0
    assert new["node"].pop("scanned") == (0 if lockstep else sum(new["sent"]["samples"].values()))
    # the vehicle's link: its reference paths, and (real time) the state read and the command
    # sent by compiled code (bridge/mavlink/state_wire.py)
    assert ref["node"].pop("vehicle_compiled") == (0, 0, 0)
    reads, commands, taken = new["node"].pop("vehicle_compiled")
    assert (reads > 0 and commands >= STEPS) or (lockstep and commands == 0)
    # real time, most states taken whole (`take_states`): all but the first, and the ones the
    # reference path decided
    assert taken > STEPS // 2 or (lockstep and taken == 0)
    assert len(ref["steps"]) == len(new["steps"]) == STEPS
    for n, (a, b) in enumerate(zip(ref["steps"], new["steps"])):
        for f in ARRAYS:
            assert a[f].dtype == b[f].dtype and a[f].tobytes() == b[f].tobytes(), (n, f, a[f], b[f])
        assert a["events"] == b["events"], n
        assert (a["failsafe"], a["state"], a["used"]) == (b["failsafe"], b["state"], b["used"]), n
    assert vehicle_commands(ref["vehicle"], lockstep) == vehicle_commands(new["vehicle"], lockstep)
    assert len(vehicle_commands(ref["vehicle"], lockstep)) >= STEPS
    assert ref["neighbours"].keys() == new["neighbours"].keys()
    for j in ref["neighbours"]:
        assert ref["neighbours"][j] == new["neighbours"][j], j     # (step, datagram) bytes
        assert len(ref["neighbours"][j]) >= STEPS
    assert _same_json(ref["summary"], new["summary"])
    assert _same_json(ref["node"], new["node"])
    assert ref["events"] == new["events"]


def _owned_rows(agent: int) -> set:
    """Rows (1-based, as in JumpEvent.edge) of the edges agent owns among its neighbourhood's."""
    from cosim.scenario import load_scenario
    g = load_scenario(HIL).graph
    local = sorted(g.local_edges(agent))
    return {r for r, k in enumerate(local, start=1) if k in g.M_plus(agent)}


@pytest.mark.parametrize("law", ["hybrid", "gradient"])
@pytest.mark.parametrize("agent", [1, 2, 4])
def test_compiled_step_is_the_reference_step_through_holds_fail_safes_and_jumps(agent, law):
    """hil_6uav, agents 1 (owns its one edge), 2 (owns two of three) and 4 (owns none)."""
    ref, new = run_pair(agent, STEPS, REF, NEW, law=law, overrides=AGE_RULE)
    # the reference run went through every case, so the comparison is not vacuous
    nd = ref["node"]
    assert nd["hold_steps"] > 0 and nd["failsafe_entries"] >= 2 and nd["failsafe_steps"] > 0
    assert any(e.startswith("rejoined") for e in ref["events"])
    states = {s for _, _, s in nd["transitions"]}
    assert states == {"fresh", "hold", "failsafe"}
    steps = ref["steps"]
    assert any(s["failsafe"] and not np.any(s["u"]) for s in steps)      # zero wrench
    jumps = [e for s in steps for e in s["events"]]
    if law == "hybrid" and _owned_rows(agent):
        assert {e.edge for e in jumps} == _owned_rows(agent)             # every owned edge
        assert len(jumps) >= 3 and all(e.mu >= 0 for e in jumps)
        # a jump right after a hold or fail-safe (θ frozen, then moving again)
        held = [n for n, s in enumerate(steps) if any(v != "fresh" for v in s["state"].values())]
        assert held and any(n > held[0] for n, s in enumerate(steps) if s["events"])
    else:
        assert jumps == [] and ref["summary"]["n_jumps"] == 0
    # θ moved: the owned θ jumping and flowing, θ received from the neighbours changing
    moved = len({s["theta"].tobytes() for s in steps}) > STEPS // 2
    assert moved == (law == "hybrid" or len(steps[0]["theta"]) > len(_owned_rows(agent)))
    assert_identical(ref, new, lockstep=False)


@pytest.mark.parametrize("law", ["hybrid", "gradient"])
def test_compiled_lockstep_step_is_the_reference_step(law):
    """Lockstep: two compiled calls per step, θ after the jump published between them."""
    ref, new = run_pair(2, STEPS, REF, NEW, law=law, lockstep=True)
    jumps = [e for s in ref["steps"] for e in s["events"]]
    assert (len(jumps) >= 3) == (law == "hybrid")
    assert all(len(v) == 2 * STEPS for v in ref["neighbours"].values())  # pose, then θ
    assert_identical(ref, new, lockstep=True)


def test_a_law_without_agent_stepper_runs_the_reference():
    """The decoupled law's per-agent view is its own (`DecoupledAgent`): no compiled step."""
    from bridge.mavlink.link import free_base_port
    from bridge.swarm.agent import AgentNode
    from cosim.scenario import load_scenario

    sc = load_scenario(HIL, [f"network.base_port={free_base_port(6)}",
                             f"bridge.base_port={free_base_port(6)}"])
    for law, compiled in (("decoupled", False), ("hybrid", True), ("gradient", True)):
        node = AgentNode(sc, 2, law=law, on_event=lambda s: None)
        try:
            assert node.compiled is compiled, law
        finally:
            node.close()
