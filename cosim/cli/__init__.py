"""The `se3sync` command line: one sub-command per job, each registered by the module that owns it.

Sub-command modules are found through the ``se3sync.commands`` entry points (cosim/plugins.py),
so this package names none of them. Imports follow one rule: a command module imports only
argparse-level things at the top and imports the job it runs inside its handler, because the jobs
pull in numba-compiled kernels, fmpy, matplotlib, Dask, pyarrow or pymavlink, and `se3sync --help`
must not pay for them. Everywhere else the project's own modules are imported at the top. An
optional third-party dependency that is missing surfaces as one line naming the extra that
installs it (`require`, and the ModuleNotFoundError handler in `main`).
"""
from __future__ import annotations

import signal as _signal


_loading: list = []   # signals received while the command line loaded (`main` notes them)


def _interrupted_while_loading(signum, frame):
    # Ctrl-C or SIGTERM while the command line itself loads: noted, and `main` stops the command
    # as soon as its arguments are read (`run` still writes the summary and log asked for); a
    # second one leaves at once with the signal's status, without the traceback of an
    # interrupted import
    if _loading:
        raise SystemExit(130 if _loading[0] == _signal.SIGINT else 143)
    _loading.append(signum)


try:   # only while this module's imports load (restored after them); `main` installs the real ones
    _before = {s: _signal.signal(s, _interrupted_while_loading)
               for s in (_signal.SIGINT, _signal.SIGTERM)}
except ValueError:   # not the main thread: leave signals alone
    _before = None

import argparse  # noqa: E402
import importlib  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import sys  # noqa: E402

from controller.errors import Se3SyncError  # noqa: E402

from .. import plugins, signals  # noqa: E402

if _before is not None:
    for _s, _h in _before.items():
        _signal.signal(_s, _h)

__all__ = ["main", "entry", "build_parser", "require", "install_hint"]

# Optional dependencies and the extra that installs them.
_EXTRAS = {"pymavlink": "mavlink", "fastcrc": "mavlink", "dask": "sweep", "distributed": "sweep",
           "pyarrow": "sweep", "pythonfmu": "fmi", "foxglove": "live"}


def install_hint(extra: str) -> str:
    """How to install an extra: from the checkout when se3sync was installed from one."""
    try:
        from importlib.metadata import distribution

        url = json.loads(distribution("se3sync").read_text("direct_url.json") or "{}")
        if url.get("dir_info", {}).get("editable") or str(url.get("url", "")).startswith("file:"):
            return f"pip install -e '.[{extra}]' in the se3sync checkout"
    except Exception:  # noqa: BLE001 - a hint must never fail
        pass
    return f"pip install 'se3sync[{extra}]'"


class MissingExtra(Exception):
    def __init__(self, module: str):
        self.module = module
        super().__init__(module)


def require(module: str) -> None:
    """Import an optional dependency now, or fail with the one-line hint naming its extra."""
    try:
        importlib.import_module(module)
    except ModuleNotFoundError:
        raise MissingExtra(module) from None


def _missing(command: str, name: str) -> int:
    extra = _EXTRAS.get(name.split(".")[0])
    what = f"the '{extra}' extra ({install_hint(extra)})" if extra else f"the package {name}"
    print(f"se3sync {command}: error: needs {what}: no module named {name!r}", file=sys.stderr)
    return 2


class _Parser(argparse.ArgumentParser):
    """Usage errors as one line (exit 2), like every other error."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {' '.join(message.split())} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    from controller import __version__

    parser = _Parser(
        prog="se3sync",
        description="Distributed hybrid pose synchronisation on SE(3): co-simulation, "
        "plant FMU, MAVLink bridge and sweeps.",
    )
    parser.add_argument("--version", action="version", version=f"se3sync {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND",
                                parser_class=_Parser)
    for name in plugins.command_modules():
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Exit status: 0 ok, 2 bad input (one line on stderr), 130 SIGINT, 143 SIGTERM (outputs
    finished, summaries with "interrupted": true); some commands add their own (see --help).

    A signal while the command line loads or reads its arguments is held until they are read;
    then a command that declares ``stops_cleanly`` (`run`: it writes the outputs asked for)
    starts and stops at once, any other is interrupted before it starts."""
    old = signals.install()
    for s in _loading:
        signals.note(s)
    _loading.clear()
    command = "se3sync"
    try:
        with signals.deferred():
            parser = build_parser()
            args = parser.parse_args(argv)
        command = f"se3sync {args.command}"
        if signals.requested() and not getattr(args, "stops_cleanly", False):
            raise KeyboardInterrupt
        rc = _dispatch(args)
    except KeyboardInterrupt:
        print(f"{command}: interrupted ({signals.received() or 'SIGINT'})", file=sys.stderr)
        return signals.exit_status()
    finally:
        signals.uninstall(old)
    if rc == 130 and signals.received() == "SIGTERM":
        rc = 143
    return rc


def _dispatch(args) -> int:
    try:
        rc = args.func(args)
        sys.stdout.flush()  # a closed pipe surfaces here, inside the handlers below
    except Se3SyncError as exc:
        print(f"se3sync {args.command}: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    except MissingExtra as exc:
        return _missing(args.command, exc.module)
    except ModuleNotFoundError as exc:
        if (exc.name or "").split(".")[0] not in _EXTRAS:
            raise
        return _missing(args.command, exc.name)
    except BrokenPipeError:
        # The reader of our output went away (`se3sync check --json | head`): not our error.
        # Point stdout at /dev/null so the interpreter's final flush does not raise again.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    return int(rc or 0)


def entry() -> None:
    """The `se3sync` executable: main(), then exit with its status. After a signal the status is
    made final with os._exit (exit handlers run first): the interpreter would otherwise turn a
    KeyboardInterrupt it saw anywhere, even one handled, into death by SIGINT (status −2)."""
    rc = main()
    if rc in (130, 143):
        import atexit

        sys.stdout.flush()
        sys.stderr.flush()
        atexit._run_exitfuncs()
        os._exit(rc)
    sys.exit(rc)


if __name__ == "__main__":  # pragma: no cover
    entry()
