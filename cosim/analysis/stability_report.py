"""What `se3sync check` adds to the spectral radius: delay margin and convergence rate."""
from __future__ import annotations

import math

from controller.errors import Se3SyncError

from ..controllers import make_controller
from .convergence_rate import convergence
from .delay_margin import delay_margin

# The delayed loop does not decouple by graph modes (agent i weighs its own fresh state by its
# degree and its neighbours' delayed ones by the adjacency, and D and Adj do not commute), so
# its augmented state has 12N + M + d(6N + M) entries, and its radius needs dense eigenproblems
# (`delay_margin.DENSE_MAX`: ARPACK misses eigenvalues in this clustered spectrum). Above this N,
# `check` skips it. On 2 cores, with the search started from `crossing_delay`'s guess, `check`
# takes 6.6 s on a 12-agent and 12.8 s on a 16-agent random tree (16 s and 50 s without it); at
# 20 agents the augmented state passes DENSE_MAX.
DELAY_MAX_AGENTS = 16


def check_extras(sc, st: dict, law, from_error=None) -> dict:
    """law: a registered law name (decides whether θ is a state of the loop) or a bool."""
    hybrid = make_controller(law, sc).hybrid if isinstance(law, str) else bool(law)

    if from_error is not None and not (math.isfinite(from_error) and from_error > 0):
        raise Se3SyncError(f"--from-error: must be a finite number > 0, got {from_error:g}")
    out = {"method": st.get("method")}
    if sc.graph.n <= DELAY_MAX_AGENTS and st["stable"]:
        out["delay_margin"] = delay_margin(sc, hybrid=hybrid)
    else:
        why = (f"not computed: {sc.graph.n} agents > {DELAY_MAX_AGENTS}" if st["stable"]
               else "not computed: unstable without delay")
        out["delay_margin"] = {"delay_margin_steps": None, "delay_margin_s": None,
                               "delay_method": why}
    out["convergence"] = convergence(sc, hybrid=hybrid, e0=from_error)
    return out


def check_lines(out: dict) -> list:
    h = out["step"]
    dm = out["delay_margin"]
    c = out["convergence"]
    lines = [f"1 - rho         {1.0 - out['spectral_radius']:.3e}",
             f"method          {out['method']} (see README: check)"]
    if dm.get("delay_margin_steps") is None or dm["delay_margin_steps"] < 0:
        lines.append(f"delay_margin    {dm['delay_method']}")
    else:
        d = dm["delay_margin_steps"]
        lines.append(f"delay_margin    {d} steps = {d * h:.4g} s (spectral radius "
                     f"{dm['rho_at_margin']:.8f} at {d}, {dm['rho_beyond']:.8f} at {d + 1})")
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
