"""The `se3sync` command line: one sub-command per job, each registered by the module that owns it."""
from __future__ import annotations

import argparse
import importlib
import os
import sys

# Modules that add sub-commands. Each exposes register(subparsers) and keeps its heavy
# imports inside the handlers so that `se3sync --help` stays fast.
_COMMAND_MODULES = (
    "cosim.commands",
    "plant_fmu.cli",
    "bridge.cli",
    "cosim.sweep",
    "cosim.animate",
)


# Optional dependencies and the extra that installs them.
_EXTRAS = {"pymavlink": "mavlink", "fastcrc": "mavlink", "dask": "sweep", "distributed": "sweep",
           "pyarrow": "sweep"}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="se3sync",
        description="Distributed hybrid pose synchronisation on SE(3): co-simulation, "
        "plant FMU, MAVLink bridge and sweeps.",
    )
    from controller import __version__

    parser.add_argument("--version", action="version", version=f"se3sync {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in _COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    from controller.errors import Se3SyncError

    try:
        rc = args.func(args)
        sys.stdout.flush()  # a closed pipe surfaces here, inside the handlers below
    except Se3SyncError as exc:
        print(f"se3sync {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"se3sync {args.command}: interrupted", file=sys.stderr)
        return 130
    except ModuleNotFoundError as exc:
        extra = _EXTRAS.get((exc.name or "").split(".")[0])
        if extra is None:
            raise
        print(f"se3sync {args.command}: error: needs the '{extra}' extra "
              f"(pip install 'se3sync[{extra}]'): {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        # The reader of our output went away (`se3sync check --json | head`): not our error.
        # Point stdout at /dev/null so the interpreter's final flush does not raise again.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    return int(rc or 0)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
