"""What `se3sync check` adds to the spectral radius: delay margin and convergence rate."""
from __future__ import annotations

import math

from controller.errors import Se3SyncError

from . import DELAY_MAX_AGENTS
from .convergence_rate import convergence
from .delay_margin import delay_margin


def check_options(from_error=None, delay_agents: int = DELAY_MAX_AGENTS) -> None:
    """The options of `check_extras`, refused before any work (Se3SyncError, one line)."""
    if from_error is not None and not (math.isfinite(from_error) and from_error > 0):
        raise Se3SyncError(f"--from-error: must be a finite number > 0, got {from_error:g}")
    if isinstance(delay_agents, bool) or not isinstance(delay_agents, int) or delay_agents < 0:
        raise Se3SyncError(f"--delay-agents: must be an integer >= 0, got {delay_agents!r}")


def check_extras(sc, st: dict, law, from_error=None, delay_agents: int = DELAY_MAX_AGENTS,
                 progress=None, sweep=None) -> dict:
    """law: a registered law name (True / False: hybrid / gradient), linearised from its own
    step (`linear`). delay_agents: compute the delay margin only up to this many agents (0:
    never); progress(d, ρ, seconds) is called after each of its eigenproblems, sweep(k, g, n)
    after each eigenproblem of its frequency sweep (`delay_margin.crossing_delay`)."""
    check_options(from_error, delay_agents)
    out = {"method": st.get("method")}
    if sc.graph.n <= delay_agents and st["stable"]:
        out["delay_margin"] = delay_margin(sc, law=law, progress=progress, sweep=sweep)
    else:
        why = ("not computed: unstable without delay" if not st["stable"]
               else "not computed: --delay-agents 0" if delay_agents == 0
               else f"not computed: {sc.graph.n} agents > {delay_agents} (--delay-agents)")
        out["delay_margin"] = {"delay_margin_steps": None, "delay_margin_s": None,
                               "delay_method": why}
    out["convergence"] = convergence(sc, law=law, e0=from_error)
    return out


def check_lines(out: dict) -> list:
    h = out["step"]
    dm = out["delay_margin"]
    c = out["convergence"]
    lines = [f"1 - rho         {1.0 - out['spectral_radius']:.3e}",
             f"method          {out['method']} (see docs/guide/analysis.md)"]
    if dm.get("delay_margin_steps") is None or dm["delay_margin_steps"] < 0:
        lines.append(f"delay_margin    {dm['delay_method']}")
    else:
        d = dm["delay_margin_steps"]
        if dm.get("rho_at_margin") is None:         # counted, not radii
            at = (f"roots outside the unit circle: {dm['outside_at_margin']} at {d}, "
                  f"{dm['outside_beyond']} at {d + 1}")
        else:
            at = (f"spectral radius {dm['rho_at_margin']:.8f} at {d}, "
                  f"{dm['rho_beyond']:.8f} at {d + 1}")
        lines.append(f"delay_margin    {d} steps = {d * h:.4g} s ({at})")
        lines.append(f"                {dm['delay_method']}")
    fr = c["slowest_mode"]
    lines.append(f"slowest_rate    {c['rate']:.6g} /s (time constant {c['time_constant']:.4g} s; "
                 f"mode: pose {fr['pose']:.2f}, velocity {fr['velocity']:.2f}, "
                 f"theta {fr['theta']:.2f})")
    lines.append(f"time_to_tol     {c['time_to_tolerance']:.4g} s from error "
                 f"{c['from_error']:.4g} to {c['tolerance']:g} (linear prediction)")
    sens = ", ".join(f"{k} {v:+.4f}" for k, v in c["sensitivity"].items())
    lines.append(f"d rate/d ln k   {sens} (limiting: {c['limiting_gain']})")
    return lines
