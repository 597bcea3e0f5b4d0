"""Persistent MAVLink 2 signing state: the replay window survives a restart.

MAVLink 2 signing stamps every signed packet with a 48-bit timestamp in 10 µs units since
2015-01-01 00:00 UTC; a receiver keeps, per stream (link_id, sysid, compid), the last timestamp
it accepted and refuses anything at or below it. pymavlink keeps that table and the own
timestamp in memory only, so a restarted side would accept a captured session again (a new
stream is accepted if it is less than a minute behind the own timestamp). As autopilots do with
their key storage, we keep both in a small JSON file next to the key and restore them at start-up:

* the own timestamp: restored as max(wall clock, stored + ``margin``); the margin (10 s, ten
  write periods) covers what the own timestamp can advance between the last write and a crash
  (the wall clock, plus 10 µs per packet signed). It is kept well below the one minute within
  which a receiver accepts a new stream, so a restart does not put us so far ahead of the wall
  clock that a peer's fresh session (stamped with the wall clock) would be refused;
* the per-stream timestamps: restored as stored, so a replay of anything seen before the last
  write is refused as ``replay``.

Writes never happen on the per-packet path: ``tick(now)`` writes at most every ``period``
seconds (and also moves the own timestamp up to the wall clock, which pymavlink does not do),
``close()`` writes once more. Files are written to a temp file and renamed.
"""
from __future__ import annotations

import json
import os
import tempfile
import time

from controller.errors import Se3SyncError

EPOCH_2015 = 1420070400          # 2015-01-01 00:00:00 UTC, Unix seconds
UNITS_PER_S = 100_000            # signing timestamps count 10 µs
TS_MAX = (1 << 48) - 1


def wall_timestamp(t: float | None = None) -> int:
    """The signing timestamp of Unix time t (default: now)."""
    return int(((time.time() if t is None else t) - EPOCH_2015) * UNITS_PER_S)


def default_state_path(key_file, side: str) -> str:
    """Where a side's signing state is kept: beside the key, ``<key file>.<side>.signing.json``
    (one file per side: a bridge and a vehicle sharing a key file must not overwrite each other's
    replay window)."""
    return f"{os.fspath(key_file)}.{side}.signing.json"


class SigningState:
    """The signing state of one side (bridge or vehicle server) in ``path``; attach() every
    pymavlink MAVLink object that signs with the key, call tick() from the main loop and close()
    at exit."""

    def __init__(self, path, period: float = 1.0, margin: float = 10.0):
        self.path = os.fspath(path)
        self.period = float(period)
        self.margin_units = int(margin * UNITS_PER_S)
        self.mavs: list = []
        self.writes = 0
        self._next = 0.0
        self.timestamp, self.streams = self._load()

    def _load(self):
        try:
            with open(self.path, encoding="utf-8") as f:
                d = json.load(f)
        except FileNotFoundError:
            return 0, {}
        except (OSError, ValueError) as exc:
            raise Se3SyncError(f"signing state {self.path}: cannot read ({exc})") from None
        try:
            ts = int(d["timestamp"])
            streams = {(int(a), int(b), int(c)): int(t) for a, b, c, t in d["streams"]}
            if not 0 <= ts <= TS_MAX or any(not 0 <= t <= TS_MAX for t in streams.values()):
                raise ValueError("timestamp out of range")
        except (KeyError, TypeError, ValueError) as exc:
            raise Se3SyncError(f"signing state {self.path}: corrupt ({exc}); delete it only if no "
                               "captured traffic can be replayed") from None
        return ts, streams

    def attach(self, mav) -> None:
        """Restores the state into a MAVLink object whose signing is set up, and keeps it."""
        s = mav.signing
        s.timestamp = max(s.timestamp, wall_timestamp(), self.timestamp + self.margin_units)
        for k, t in self.streams.items():
            if t > s.stream_timestamps.get(k, -1):
                s.stream_timestamps[k] = t
        self.mavs.append(mav)

    def collect(self) -> None:
        for mav in self.mavs:
            s = mav.signing
            self.timestamp = max(self.timestamp, s.timestamp)
            for k, t in s.stream_timestamps.items():
                if t > self.streams.get(k, -1):
                    self.streams[k] = t

    def save(self) -> None:
        self.collect()
        d = {"format": "se3sync MAVLink 2 signing state", "version": 1, "timestamp": self.timestamp,
             "streams": [[*k, t] for k, t in sorted(self.streams.items())]}
        folder = os.path.dirname(os.path.abspath(self.path))
        fd, tmp = tempfile.mkstemp(prefix=".signing-", dir=folder)
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as f:
                json.dump(d, f)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, self.path)
        except BaseException:
            try:
                os.unlink(tmp)
            except OSError:
                pass
            raise
        self.writes += 1

    def tick(self, now: float) -> None:
        """From the main loop (now: time.monotonic()): at most every ``period`` s, move the own
        timestamps up to the wall clock and write the file."""
        if now < self._next:
            return
        self._next = now + self.period
        w = wall_timestamp()
        for mav in self.mavs:
            if mav.signing.timestamp < w:
                mav.signing.timestamp = w
        try:
            self.save()
        except OSError:
            pass  # a full disk must not stop the control loop; close() tries again and reports

    def close(self) -> None:
        if self.mavs:
            self.save()


def open_signing_state(key, path=None, key_file=None, side: str = "bridge") -> SigningState | None:
    """The persistent signing state of a side: at ``path`` if given, else beside the key file;
    None without a key, or with a key given as bytes and no path (nothing persisted)."""
    if key is None:
        return None
    if path is None and key_file is not None:
        path = default_state_path(key_file, side)
    return SigningState(path) if path is not None else None
