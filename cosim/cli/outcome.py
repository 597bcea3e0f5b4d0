"""How a run ended, said the same way by every command that runs the loop (`run`, `connect`,
`swarm`): the lines on stderr after the command's own summary line, and the exit status they
imply (docs/run-guards.md)."""
from __future__ import annotations

import sys

from ..guards import EXIT_DIVERGED

__all__ = ["report_outcome", "EXIT_INTERRUPTED"]

EXIT_INTERRUPTED = 130   # `cosim.cli.main` makes it 143 when the signal was SIGTERM


def report_outcome(command: str, summary: dict, file=None) -> int:
    """Prints what the summary says about the run's end, each on one line prefixed
    ``se3sync COMMAND:``, and returns the exit status it implies.

    * a [network] delay that was not checked against the delay margin (``"delay_check"``);
    * more jumps than Theorem 1's bound ⌈V̄(0)/(k_X δ)⌉ (``"jump_bound_exceeded"``): a warning,
      the status stays 0;
    * an interrupted run (``"interrupted"``): `EXIT_INTERRUPTED`;
    * a diverged run (``"diverged"``: when, why): `EXIT_DIVERGED`.
    """
    out = sys.stderr if file is None else file
    who = f"se3sync {command}"
    dc = summary.get("delay_check")
    if dc and not dc.get("checked") and dc.get("why") != "--force":
        print(f"{who}: warning: the worst-case delay of {dc['worst_delay_s']:.4g} s "
              f"({dc['key']}) was not checked against the delay margin: {dc['why']}", file=out)
    if summary.get("jump_bound_exceeded"):
        print(f"{who}: warning: {summary['n_jumps']} jumps, more than the bound "
              f"⌈V̄(0)/(k_X δ)⌉ = {summary['jump_bound']} of Theorem 1: the run left the region "
              "the analysis covers (\"jump_bound_exceeded\": true)", file=out)
    if summary.get("interrupted"):
        print(f"{who}: interrupted after {summary['sim_time_s']:.4g} s simulated", file=out)
        return EXIT_INTERRUPTED
    dv = summary.get("diverged")
    if dv:
        where = f" (agent {dv['agent']})" if dv.get("agent") is not None else ""
        print(f"{who}: diverged at t = {dv['t']:.6g} s (step {dv['step']}){where}: "
              f"{dv['reason']}; stopped after {summary['steps']} steps (exit status "
              f"{EXIT_DIVERGED})", file=out)
        return EXIT_DIVERGED
    return 0
