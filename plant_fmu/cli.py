"""`se3sync fmu ...`: build the plant FMU."""
from __future__ import annotations

import argparse
from pathlib import Path

from controller.errors import Se3SyncError


def _cmd_build(args: argparse.Namespace) -> int:
    from . import build, layout

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
        help="build the plant FMU (rigid bodies on SE(3), FMI 2.0 or 3.0 Co-Simulation)",
        description="The plant: N rigid bodies on SE(3) as an FMI 2.0 (default) or FMI 3.0 Co-Simulation FMU "
        "compiled from C.",
    )
    sub = p.add_subparsers(dest="fmu_command", required=True, metavar="ACTION")
    b = sub.add_parser(
        "build",
        help="compile the FMU for N bodies with the system C compiler and write it to a .fmu file",
        description="Compile the plant FMU for N bodies with the system C compiler ($CC, cc or gcc) and "
        "write it to FILE.fmu (binaries for this platform plus the C sources). The file is written "
        "under a temporary name and renamed, so no half-written output is left behind.",
    )
    b.add_argument("--bodies", "-n", type=int, required=True, metavar="N",
                   help="number of rigid bodies in the FMU (1..100000)")
    b.add_argument("--output", "-o", required=True, metavar="FILE.fmu", help="path of the .fmu file to write")
    b.add_argument("--fmi", type=int, choices=(2, 3), default=2, metavar="{2,3}",
                   help="FMI version of the FMU: 2 (FMI 2.0 Co-Simulation, default) or 3 (FMI 3.0 "
                   "Co-Simulation; same model, variables and value references, plus the independent "
                   "variable time at value reference 0)")
    b.set_defaults(func=_cmd_build)
