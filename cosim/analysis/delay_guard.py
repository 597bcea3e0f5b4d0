"""The worst-case inter-agent delay of a scenario's ``[network]`` table against the delay margin
of its loop: what `se3sync run` refuses before a run (docs/run-guards.md)."""
from __future__ import annotations

from controller.errors import ConfigError

from ..guards import RUN_DELAY_MAX_AGENTS
from .delay_margin import delay_margin

__all__ = ["delay_guard"]


def delay_guard(scenario, law="hybrid", max_agents: int = RUN_DELAY_MAX_AGENTS, progress=None,
                sweep=None) -> dict | None:
    """The worst-case inter-agent delay of the scenario's ``[network]`` table against the delay
    margin of the loop of ``law`` (a registered law name) linearised at consensus (`cosim.analysis.delay_margin`, what `check`
    prints), or None without the table. Raises ConfigError (one line naming the key that sets
    the longest transit and the margin) when the delay is beyond the margin.

    The worst case is the longest transit any message can take, d + J_max steps (the delay and
    the largest jitter, rounded up to steps as the links do) over every directed link; the
    margin is that of one constant delay on every link, so per-link delays are judged by their
    longest. Losses are not a delay (a lost message leaves older data in use: ``max_age``
    bounds that). The margin costs a few seconds at 1000 agents (`check`'s figures), so it is
    computed only when there is a delay and the graph has at most ``max_agents`` agents;
    otherwise the returned dict says why it was not checked."""
    net = scenario.tables.get("network")
    if net is None:
        return None
    h = float(scenario.step)
    d, key, spec = net.worst_delay(scenario.graph, h)
    out = {"worst_delay_steps": d, "worst_delay_s": round(d * h, 12), "key": key,
           "delay_margin_steps": None, "delay_margin_s": None, "checked": False, "why": ""}
    if d == 0:
        out.update(checked=True, why="no delay")
        return out
    if scenario.graph.n > max_agents:
        out["why"] = (f"not computed: {scenario.graph.n} agents > {max_agents} "
                      "(--delay-agents)")
        return out
    dm = delay_margin(scenario, law=law, progress=progress, sweep=sweep)   # BLAS: cosim/threads.py
    m = dm["delay_margin_steps"]
    out.update(delay_margin_steps=m, delay_margin_s=dm["delay_margin_s"])
    if m is None:
        upto = dm.get("stable_up_to_steps")
        if upto is not None and upto >= d:
            out.update(checked=True, why=f"stable for every delay up to {upto} steps tried")
        else:
            out["why"] = f"not computed: {dm['delay_method']}"
        return out
    out["checked"] = True
    if d <= m:
        out["why"] = "within the delay margin"
        return out
    what = (f"delay {spec.delay:g} s + jitter {spec.jitter:g} s" if spec.jitter > 0
            else f"delay {spec.delay:g} s")
    margin = ("the loop is unstable even without delay" if m < 0 else
              f"beyond the delay margin of {m * h:.4g} s ({m} steps; see se3sync check)")
    raise ConfigError(key, f"a worst-case delay of {d * h:.4g} s ({what}, {d} steps of h = "
                           f"{h:g} s) is {margin}: the linearised loop is unstable there; use a "
                           "smaller delay or --force", scenario.path)
