"""`se3sync fmu ...`: build the plant FMU."""
from __future__ import annotations

import argparse
from pathlib import Path

from controller.errors import Se3SyncError


def _builder(name: str):
    """The FMU builder another package registers under ``name`` (entry point group
    ``se3sync.fmu_builders``): the controller FMU is cosim's (it needs a scenario), and
    plant_fmu imports neither cosim nor bridge."""
    from importlib import import_module
    from importlib.metadata import distribution

    for ep in distribution("se3sync").entry_points:
        if ep.group == "se3sync.fmu_builders" and ep.name == name:
            mod, _, attr = ep.value.partition(":")
            return getattr(import_module(mod), attr)
    raise Se3SyncError(f"--controller: no FMU builder {name!r} is installed")


def _cmd_build(args: argparse.Namespace) -> int:
    from . import build, layout

    if args.controller is not None:
        if args.fmi != 2:
            raise Se3SyncError("--fmi: the controller FMU is FMI 2.0 only (pythonfmu)")
        if not str(args.output).lower().endswith(".fmu"):
            raise Se3SyncError(f"--output: {args.output!r} must end in .fmu")
        o = Path(args.output)
        if o.is_dir():
            raise Se3SyncError(f"--output: {args.output!r} is a directory")
        if not (o.parent if str(o.parent) else Path(".")).is_dir():
            raise Se3SyncError(f"--output: {args.output!r}: directory {str(o.parent)!r} does "
                               "not exist")
        print(_builder("controller")(args.controller, args.output, args.law, args.overrides))
        return 0
    if args.law != "hybrid" or args.overrides:
        raise Se3SyncError("--law/--set: only with --controller SCENARIO")
    n = args.bodies
    if not 1 <= n <= layout.MAX_BODIES:
        raise Se3SyncError(f"--bodies must be in 1..{layout.MAX_BODIES}, got {n}")
    v = args.fmi
    o = Path(args.output)
    if o.is_dir():
        raise Se3SyncError(f"--output: {args.output!r} is a directory")
    if not (o.parent if str(o.parent) else Path(".")).is_dir():
        raise Se3SyncError(f"--output: {args.output!r}: directory {str(o.parent)!r} does not exist")
    out = build.build_fmu(n, args.output, fmi_version=v)
    token = "GUID" if v == 2 else "instantiationToken"
    print(f"wrote {out} ({n} bod{'y' if n == 1 else 'ies'}, FMI {v}.0 Co-Simulation, "
          f"modelIdentifier {build.MODEL_IDENTIFIER}, {token} {build.guid(n, v)})")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "fmu",
        help="build the plant FMU (rigid bodies on SE(3), FMI 2.0 or 3.0 Co-Simulation) or a "
             "scenario's controller FMU",
        description="The plant: N rigid bodies on SE(3) as an FMI 2.0 (default) or FMI 3.0 Co-Simulation FMU "
        "compiled from C; or, with --controller, a scenario's law as an FMI 2.0 Co-Simulation FMU.",
    )
    sub = p.add_subparsers(dest="fmu_command", required=True, metavar="ACTION")
    b = sub.add_parser(
        "build",
        help="build the plant FMU for N bodies (C), or the controller FMU of a scenario (Python)",
        description="--bodies N: compile the plant FMU for N bodies with the system C compiler "
        "($CC, cc or gcc) and write it to FILE.fmu (binaries for this platform plus the C "
        "sources). --controller SCENARIO: write the scenario's network controller (the hybrid "
        "law or the gradient baseline, its design and gains as parameters; the state S in, the "
        "wrenches, theta and the jumps out) as an FMI 2.0 Co-Simulation FMU built by pythonfmu "
        "(the 'fmi' extra); it runs in the host's Python, which must have se3sync installed "
        "(docs/fmi-system.md). The file is written under a temporary name and renamed, so no "
        "half-written output is left behind.",
    )
    what = b.add_mutually_exclusive_group(required=True)
    what.add_argument("--bodies", "-n", type=int, metavar="N",
                      help="number of rigid bodies in the plant FMU (1..100000)")
    what.add_argument("--controller", metavar="SCENARIO",
                      help="build the controller FMU of this scenario TOML file instead")
    b.add_argument("--law", choices=("hybrid", "gradient"), default="hybrid",
                   help="with --controller: the hybrid law (default) or the gradient baseline")
    b.add_argument("--set", dest="overrides", action="append", default=[],
                   metavar="KEY.PATH=VALUE",
                   help="with --controller: override a scenario value (as for `se3sync run`)")
    b.add_argument("--output", "-o", required=True, metavar="FILE.fmu", help="path of the .fmu file to write")
    b.add_argument("--fmi", type=int, choices=(2, 3), default=2, metavar="{2,3}",
                   help="FMI version of the FMU: 2 (FMI 2.0 Co-Simulation, default) or 3 (FMI 3.0 "
                   "Co-Simulation; same model, variables and value references, plus the independent "
                   "variable time at value reference 0); the controller FMU is FMI 2.0 only")
    b.set_defaults(func=_cmd_build)
