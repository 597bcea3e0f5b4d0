"""Ctrl-C and SIGTERM stop every command the same way: the outputs are finished, the summary says
``"interrupted": true`` and the exit status is 130 (SIGINT) or 143 (SIGTERM).

`install` (called by the command line) makes both signals note themselves and raise
KeyboardInterrupt, as Ctrl-C does by default. The master loop swaps in `note_only` while it runs,
so that a signal stops it between two blocks instead of in the middle of an FMU call; a second
signal there raises at once. A signal that arrives while Python runs inside a callback from C
(a ctypes callback, or llvmlite's as numba writes its cache) raises a KeyboardInterrupt that
Python can only swallow; `install`'s unraisable hook keeps it from printing a traceback, the
signal is still noted, and the master stops as soon as it starts: nothing is lost silently.
"""
from __future__ import annotations

import os
import signal
import sys
import threading

__all__ = ["install", "uninstall", "note", "requested", "pending", "received", "exit_status", "reset",
           "catching", "deferred", "interruptible", "set_stage", "stage_at_signal", "MAX_BLOCK",
           "die_with"]

_received: list = []
_installed: list = []
_stage: list = [None]      # what the command is doing (`set_stage`), for a stop before any step
_stage_at: list = []       # ... when the first signal arrived
STATUS = {"SIGINT": 130, "SIGTERM": 143}
MAX_BLOCK = 1000  # steps of the master loop between two checks for a signal / progress updates
PR_SET_PDEATHSIG = 1      # linux/prctl.h


def note(signum) -> None:
    name = signal.Signals(signum).name if isinstance(signum, int) else str(signum)
    if not _received:
        _stage_at.append(_stage[0])
    _received.append(name)


def set_stage(name: str | None) -> None:
    """Names what the command is doing now; a signal remembers the stage it arrived in."""
    _stage[0] = name


def stage_at_signal() -> str | None:
    """The stage (`set_stage`) in which the first signal arrived, or None."""
    return _stage_at[0] if _stage_at else None


def requested() -> bool:
    return bool(_received)


def pending() -> bool:
    """A signal arrived while the command line's handlers were installed (see `install`)."""
    return bool(_installed) and bool(_received)


def received() -> str | None:
    """The first signal received, or None."""
    return _received[0] if _received else None


def exit_status() -> int:
    return STATUS.get(received() or "SIGINT", 130)


def reset() -> None:
    _received.clear()
    _stage_at.clear()
    _stage[0] = None


def _raise(signum, frame):
    note(signum)
    raise KeyboardInterrupt


def _unraisable(hook):
    """sys.unraisablehook that drops the KeyboardInterrupt `_raise` raised inside a callback
    from C (numba writing its cache through llvmlite, a ctypes callback): Python can only print
    it there, with a traceback, and the signal is already noted, so the command stops as soon
    as it is back in Python. Every other exception goes to ``hook``."""
    def unraisable(info):
        if issubclass(info.exc_type, KeyboardInterrupt) and _received:
            return
        hook(info)
    return unraisable


def install() -> dict:
    """SIGINT and SIGTERM: note, then raise KeyboardInterrupt (main thread only). Returns the
    previous handlers for `uninstall`."""
    old = {}
    if threading.current_thread() is threading.main_thread():
        reset()
        for s in (signal.SIGINT, signal.SIGTERM):
            old[s] = signal.signal(s, _raise)
        old["unraisablehook"] = sys.unraisablehook
        sys.unraisablehook = _unraisable(sys.unraisablehook)
        _installed[:] = [True]
    return old


def uninstall(old: dict) -> None:
    for s, h in old.items():
        if s == "unraisablehook":
            sys.unraisablehook = h
        else:
            signal.signal(s, h)
    _installed.clear()


class catching:
    """``with catching(on_signal):`` SIGINT and SIGTERM call ``on_signal()`` (after noting the
    signal) instead of raising, in the main thread; the previous handlers come back on exit."""

    def __init__(self, on_signal):
        self.on_signal = on_signal
        self.old = {}

    def _handler(self, signum, frame):
        note(signum)
        self.on_signal()

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            for s in (signal.SIGINT, signal.SIGTERM):
                try:
                    self.old[s] = signal.signal(s, self._handler)
                except ValueError:  # pragma: no cover - not the main interpreter
                    pass
        return self

    def __exit__(self, *exc):
        for s, h in self.old.items():
            signal.signal(s, h)
        return False


class deferred(catching):
    """``with deferred():`` a SIGINT or SIGTERM is only noted (`requested` then says so, and
    the work after the block decides how to stop); a second one raises KeyboardInterrupt at
    once. For short stretches that must not be cut, such as the command line's parsing."""

    def __init__(self):
        super().__init__(self._again)

    @staticmethod
    def _again():
        if len(_received) > 1:
            raise KeyboardInterrupt


def interruptible(fn, *args):
    """fn(*args), computed in a daemon thread while this one waits in short joins.

    For the long LAPACK calls of the analysis: a dense eigenproblem of 4000 states is one call
    of 20–30 s, and Python runs a signal handler only between bytecodes, so Ctrl-C or SIGTERM
    would wait for it to return. LAPACK runs without the GIL, so the waiting thread takes the
    signal at once (or, under `deferred`, sees it noted within 0.1 s); the abandoned computation
    ends with the process (`se3sync` exits with os._exit after a signal)."""
    box = {}

    def work():
        try:
            box["value"] = fn(*args)
        except BaseException as exc:   # handed to the caller, whatever it is
            box["error"] = exc

    t = threading.Thread(target=work, name="se3sync-lapack", daemon=True)
    t.start()
    while t.is_alive():
        t.join(0.1)
        if _received:   # noted under `deferred` (as `run` sets itself up): stop here
            raise KeyboardInterrupt
    if "error" in box:
        raise box["error"]
    return box["value"]


def die_with(parent: int):
    """A child process's set-up before exec (``preexec_fn``; Linux, else None): the kernel kills
    it (SIGKILL) when ``parent`` dies, however it dies (SIGKILL, OOM, a crash): a parent that
    cannot stop its children cannot finish their outputs either, and a child left running would
    hold the next run's ports or files. prctl survives exec; the parent dying between fork and
    prctl is caught by the parent id check. (The swarm's agents and vehicles, an agent's kernel
    build: `bridge.swarm.aot`.)"""
    if not sys.platform.startswith("linux"):
        return None
    import ctypes      # (only a process that starts children pays its import)

    libc = ctypes.CDLL(None, use_errno=True)

    def setup():
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
        if os.getppid() != parent:
            os._exit(1)
    return setup
