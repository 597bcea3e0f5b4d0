"""Sub-command `ssp`: the closed loop (plant FMU + controller FMU) as an SSP 1.0 archive."""
from __future__ import annotations

import sys

from ..files import check_output
from . import require

__all__ = ["register"]


def register(sub) -> None:
    p = sub.add_parser(
        "ssp", help="write the closed loop (plant FMU + controller FMU) as an SSP system",
        description="Write SCENARIO's closed loop as an SSP 1.0 archive (System Structure and "
                    "Parameterization) for any FMI master: the plant FMU (C, FMI 2.0) and the "
                    "controller FMU (the hybrid law or the gradient baseline, pythonfmu, FMI "
                    "2.0; needs the 'fmi' extra, and a Python with se3sync installed wherever it "
                    "runs), their connections (state S to the controller, wrenches to the "
                    "plant), every parameter of each in an SSV file, and the communication step "
                    "as the default experiment. Tested in FMPy (fmpy.ssp.simulate_ssp) and "
                    "libcosim (libcosimpy): both reproduce `se3sync run --set "
                    "simulation.actuation_delay=1`, the one communication step of actuation delay "
                    "their fixed-step (Jacobi) exchange adds (docs/fmi-system.md). Written to a "
                    "temporary name and renamed. Exit codes: "
                    "0 ok, 2 bad input.")
    p.add_argument("scenario", help="scenario TOML file")
    p.add_argument("-o", "--output", required=True, metavar="SYSTEM.ssp",
                   help="the SSP archive to write")
    p.add_argument("--law", choices=("hybrid", "gradient"), default="hybrid",
                   help="the controller: the hybrid law (default) or the gradient baseline")
    p.add_argument("--duration", type=float, metavar="S",
                   help="stop time of the default experiment (default simulation.duration)")
    p.add_argument("--step", type=float, metavar="H",
                   help="communication step h in s (overrides simulation.step)")
    p.add_argument("--set", dest="overrides", action="append", default=[],
                   metavar="KEY.PATH=VALUE",
                   help="override a scenario value before validation (as for `se3sync run`)")
    p.set_defaults(func=_cmd_ssp)


def _cmd_ssp(args) -> int:
    from ..scenario import load_scenario

    check_output("--output", args.output, (".ssp",))
    require("pythonfmu")
    from ..fmi.ssp import write_ssp

    sc = load_scenario(args.scenario, args.overrides, duration=args.duration, step=args.step)
    out = write_ssp(sc, args.output, args.law)
    print(f"wrote {out} ({sc.name}: plant FMU of {sc.graph.n} bodies + {args.law} controller FMU, "
          f"{24 * sc.graph.n} connections, h = {sc.step:g} s, "
          f"stop time {sc.duration:g} s)", file=sys.stderr)
    return 0
