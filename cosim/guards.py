"""What keeps a run inside the region the analysis covers, or says that it left it
(docs/run-guards.md lists every guard, its limit, its message and its exit status).

* Before a run (`cosim.analysis.delay_guard`): a worst-case inter-agent delay (delay + jitter, the longest
  directed link) beyond the delay margin of `se3sync check` is refused, as an unstable step is.
* During a run (`cosim.master.Master`, both loops): a summary sample whose V̄ or errors are not
  finite, whose V̄ exceeds `DIVERGE_FACTOR` × V̄(0) (gravity-free scenarios) or whose largest
  velocity entry exceeds `XI_LIMIT` stops the run as diverged (`sample_divergence`); so does a
  plant that fails because its state is no longer finite. The summary says why (``"diverged"``)
  and `se3sync run` exits `EXIT_DIVERGED`.
* After a run: more jumps than Theorem 1's bound ⌈V̄(0)/(k_X δ)⌉ is reported
  (``"jump_bound_exceeded": true`` and a line on stderr).
* Memory: the summary keeps at most `MAX_SAMPLES` samples (thinned by halves, evenly spaced)
  and the first `MAX_JUMPS` jumps (every jump is counted and logged).
"""
from __future__ import annotations

import json
import math

__all__ = ["outcome_metadata", "EXIT_DIVERGED", "DIVERGE_FACTOR", "XI_LIMIT", "MAX_SAMPLES", "MAX_JUMPS",
           "RUN_DELAY_MAX_AGENTS", "V_limit", "sample_divergence"]

EXIT_DIVERGED = 6          # `se3sync run`: stopped because the run diverged
# V̄ is non-increasing along the paper's closed loop (gravity-free), so V̄(t) ≤ V̄(0); the sampled
# and delayed loops of the shipped scenarios stay below 1.0000000000000004 V̄(0). A hundredfold
# growth (errors about ten times their start) is far outside that region.
DIVERGE_FACTOR = 100.0
XI_LIMIT = 1e6             # |ξ| entries (rad/s, m/s): the scenario's input range (MAX_MAGNITUDE)
MAX_SAMPLES = 10_000       # summary samples kept (the summary of a long run stays ~1.5 MB)
MAX_JUMPS = 10_000         # jumps listed in the summary (all are counted, and logged)
# `run` computes the delay margin before a run with a delay up to this many agents unless
# --delay-agents says otherwise (tree of 1000 agents: 6-10 s on 2 cores; see `check`)
RUN_DELAY_MAX_AGENTS = 1000
# (the margin's BLAS threads: cosim/threads.py, as for every analysis)


OUTCOME_KEYS = ("steps", "sim_time_s", "interrupted", "stopped_during", "diverged", "n_jumps",
                "jump_bound", "jump_bound_exceeded", "timed_out")


def outcome_metadata(summary: dict) -> dict:
    """How a run ended, as the ``se3sync.outcome`` metadata record of its log (JSON values)."""
    return {k: json.dumps(summary[k], default=float) for k in OUTCOME_KEYS if k in summary}


def V_limit(V0: float, gravity) -> float:
    """The V̄ above which a run has diverged: `DIVERGE_FACTOR` × V̄(0), or ∞ when V̄(0) is 0 or not
    finite or the scenario has gravity (V̄ is a Lyapunov function of the gravity-free loop only:
    with gravity the damped swarm falls and its kinetic energy grows to that of its terminal
    speed)."""
    if not (math.isfinite(V0) and V0 > 0) or any(float(g) != 0.0 for g in gravity):
        return math.inf
    return DIVERGE_FACTOR * V0


def sample_divergence(rec: dict, v_limit: float) -> str | None:
    """Why the summary sample ``rec`` ({t, rot_err, pos_err, xi_max, V, ...}) shows a diverged
    run, or None."""
    vals = (rec["V"], rec["xi_max"], rec["rot_err"], rec["pos_err"])
    if not all(math.isfinite(x) for x in vals):
        return ("the state is no longer finite (V̄ = {:.4g}, max|ξ| = {:.4g}, rot_err {:.4g}, "
                "pos_err {:.4g})".format(*vals))
    if rec["V"] > v_limit:
        return (f"V̄ = {rec['V']:.4g} exceeds {DIVERGE_FACTOR:g} × V̄(0) = {v_limit:.4g} "
                f"(rot_err {rec['rot_err']:.3g}, pos_err {rec['pos_err']:.3g})")
    if rec["xi_max"] > XI_LIMIT:
        return f"max|ξ| = {rec['xi_max']:.4g} exceeds {XI_LIMIT:g}"
    return None
