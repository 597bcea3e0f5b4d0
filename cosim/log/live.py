"""The live view (`--live [HOST:]PORT`): the log's channels served over Foxglove's WebSocket
protocol while a run goes on (foxglove-sdk, extra ``live``).

What is served is what the MCAP log holds, the same messages on the same channels and schemas
(JSON or ROS 2 CDR, after ``--log-encoding``): /tf, /edges, /agents, /lyapunov, /jumps, /scene,
/trail/agent_i (and /link/stats from a hardware plant). The messages are made by the log's own
encoder, `McapLogger`, given a sink that hands them to foxglove-sdk's channels instead of a file.

Bounded rate. `LiveTee` wraps the run's logger (or stands in for it when there is no log) and
sees every record the master hands to it, a block at a time in the compiled loop: with a log, on
the log's writer thread; without one, in the loop's own thread between blocks, where it only
reads the clock (``inline``; frames are encoded on a thread of its own). A record becomes a
frame only when 1/rate s of wall time have passed since the last one (default 30 Hz), only its
newest row, and only while a client subscribes to some channel; jumps are always sent (they are
rare, and the view marks them). Without a log the run's records lie on a grid of the live rate
of simulated time (`live_only`), its blocks are a frame period long, and the compiled loop takes
a record only from a block that ends with a frame due (`LiveTee.frame_wanted`). Encoding takes
at most `LiveTee.CPU_SHARE` of a core (the frame rate falls when frames cost more). The messages
keep the log's time stamps (simulated time, or the wall clock's t = n·h of a hardware run).
docs/live.md measures what it costs the loop.

Access. The WebSocket has no authentication: a socket on a non-loopback address is refused
unless ``insecure`` (the MAVLink sockets' rule, `se3sync connect --insecure`).
"""
from __future__ import annotations

import dataclasses
import ipaddress
import math
import os
import queue
import shutil
import sys
import tempfile
import threading
import time

import numpy as np

from controller.errors import Se3SyncError

from .writer import McapLogger

__all__ = ["DEFAULT_RATE", "parse_live", "LiveServer", "LiveTee", "live_logger", "live_only"]

DEFAULT_RATE = 30.0          # Hz of wall time: live frames per second
WORKER_NICE = 10             # the live view's encoding thread, below the control loop
WATCH_CHECK_S = 0.25         # s of wall time between two looks for a subscribed client
LOCAL_NAMES = ("localhost",)


def _loopback(host: str) -> bool:
    if host in LOCAL_NAMES:
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def parse_live(text: str, insecure: bool = False, option: str = "--live") -> tuple[str, int]:
    """``[HOST:]PORT`` (an IPv6 host in brackets, [::1]:8765) → (host, port); PORT 0 lets the
    OS choose. The host defaults to 127.0.0.1; one that is not loopback needs ``insecure``.
    Raises Se3SyncError naming ``option``."""
    s = str(text).strip()
    host, port = "127.0.0.1", s
    if s.startswith("["):
        end = s.find("]")
        if end < 0 or s[end + 1:end + 2] != ":":
            raise Se3SyncError(f"{option}: expected [HOST:]PORT, got {text!r}")
        host, port = s[1:end], s[end + 2:]
    elif ":" in s:
        host, _, port = s.rpartition(":")
    try:
        p = int(port)
    except ValueError:
        raise Se3SyncError(f"{option}: expected [HOST:]PORT with PORT in 0..65535, got "
                           f"{text!r}") from None
    if not 0 <= p <= 65535 or not host:
        raise Se3SyncError(f"{option}: expected [HOST:]PORT with PORT in 0..65535, got {text!r}")
    if not insecure and not _loopback(host):
        raise Se3SyncError(f"{option}: {host}:{p} is reachable from other machines and the live "
                           "view has no authentication (anyone could watch the run); use a "
                           "loopback address (the default, 127.0.0.1) or --insecure")
    return host, p


class _Sink:
    """Takes `McapLogger`'s messages (the appender's interface) and logs them on foxglove-sdk
    channels of the server's context, one per log channel, made on first use.

    Messages go to the channel's native ``BaseChannel.log(bytes, log_time, sink_id)``, not
    through `foxglove.Channel.log`, whose Python checks (the encoding, the message's type) cost
    more than the log call itself: a 1000-agent frame is 1000 trail messages (26 of 43 ms per
    frame went there)."""

    def __init__(self, context):
        self.context = context
        self.logger = None
        self._chan = {}
        self._log = {}   # channel id -> the native channel's log
        self.sent = 0
        self._watching = False
        self._watch_until = -math.inf

    def _channel(self, cid):
        ch = self._chan.get(cid)
        if ch is None:
            import foxglove

            topic, menc, sid = self.logger.channels[cid]
            name, senc, data = self.logger.schemas[sid]
            ch = self._chan[cid] = foxglove.Channel(
                topic, schema=foxglove.Schema(name=name, encoding=senc, data=data),
                message_encoding=menc, context=self.context)
            self._log[cid] = ch.base.log
        return ch

    def watched(self) -> bool:
        """Whether any client subscribes to any channel (no viewer: nothing to encode). Asked
        of every channel (a 1000-agent view has 1000 trail channels) at most every
        `WATCH_CHECK_S` of wall time; a new viewer is seen that much later."""
        now = time.monotonic()
        if now < self._watch_until:
            return self._watching
        self._watching = any(ch.has_sinks() for ch in self._chan.values())
        self._watch_until = now + WATCH_CHECK_S
        return self._watching

    def _logger_of(self, cid):
        log = self._log.get(cid)
        if log is None:
            self._channel(cid)
            log = self._log[cid]
        return log

    def add(self, channel_id, log_time, data, sequence):
        self._logger_of(channel_id)(data if type(data) is bytes else bytes(data),
                                    int(log_time), None)
        self.sent += 1

    def add_rows(self, channel_ids, log_time, rows, sequence):
        t = int(log_time)
        logs = self._log
        for cid, row in zip(channel_ids, rows):
            log = logs.get(cid) or self._logger_of(cid)
            log(row.tobytes(), t, None)
        self.sent += len(rows)

    def close(self):
        chans, self._chan = self._chan, {}
        for ch in chans.values():
            ch.close()


class LiveServer:
    """A Foxglove WebSocket server for one run: ``LiveServer(scenario, host, port, rate=30,
    encoding="json", agent_ids=None, edge_ids=None)``; ``port`` is the port bound (the OS's
    choice for 0); ``url``; ``close()``."""

    def __init__(self, scenario, host: str = "127.0.0.1", port: int = 8765,
                 rate: float = DEFAULT_RATE, encoding: str = "json", agent_ids=None,
                 edge_ids=None, name: str = "se3sync"):
        import foxglove

        if not rate > 0:
            raise Se3SyncError(f"--live-rate: must be > 0, got {rate:g}")
        self.rate = float(rate)
        self.context = foxglove.Context()
        try:
            self.server = foxglove.start_server(name=name, host=host, port=int(port),
                                                context=self.context)
        except Exception as exc:  # noqa: BLE001 - e.g. the port is taken: one line
            raise Se3SyncError(f"--live: cannot serve on {host}:{port}: "
                               f"{' '.join(str(exc).split())}") from None
        self.host, self.port = host, int(self.server.port)
        self.sink = _Sink(self.context)
        # The log's encoder (the scene at the log's rate of simulated time, 20 Hz, at most one
        # per frame; an edge is drawn jumping for one scene period, as in the log). Its file
        # (MCAP header, schemas, channels; the messages go to the sink) is a private temporary
        # one, removed at the end. Never a shared path such as os.devnull: closing a discarded
        # log unlinks its file.
        self._dir = tempfile.mkdtemp(prefix="se3sync-live-")
        try:
            self.encoder = McapLogger(os.path.join(self._dir, "live.mcap"), scenario,
                                      encoding=encoding, layout_path=None, agent_ids=agent_ids,
                                      edge_ids=edge_ids, sink=self.sink)
        except BaseException:
            shutil.rmtree(self._dir, ignore_errors=True)
            self.server.stop()
            raise
        self.sink.logger = self.encoder
        for cid in list(self.encoder.channels):   # advertised now, before the first frame
            self.sink._channel(cid)
        # what the encoder would otherwise make at its first frames, while the loop runs: the
        # CDR layouts of the trails of every length (25 of them, 0.14 s at 1000 agents)
        warm = getattr(getattr(self.encoder, "_cdr_scene", None), "warm", None)
        if warm is not None:
            warm()
        self.frames = 0
        self._closed = False

    @property
    def url(self) -> str:
        h = f"[{self.host}]" if ":" in self.host else self.host
        return f"ws://{h}:{self.port}"

    def announce(self, command: str) -> None:
        print(f"{command}: live view on {self.url} (Foxglove: Open connection → Foxglove "
              f"WebSocket; at most {self.rate:g} frames/s)", file=sys.stderr, flush=True)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            self.encoder.close(discard=True)   # removes its private temporary file
        except OSError:
            pass
        finally:
            shutil.rmtree(self._dir, ignore_errors=True)
            self.sink.close()
            self.server.stop()


def _copy(x):
    """A record argument for another thread: the loop reuses its buffers."""
    return x.copy() if isinstance(x, np.ndarray) else (list(x) if isinstance(x, list) else x)


class LiveTee:
    """The run's logger as the master sees it: every call goes to ``inner`` (the McapLogger of
    ``--log``, or None) and, at most ``server.rate`` times per second of wall time and only
    while a client watches, the newest record goes to the live view too; every jump does.

    With a log, the tee runs where the log's records are encoded (the compiled loop's writer
    thread) and encodes its frames there. Without one it is ``inline``: the compiled loop calls
    it in its own thread instead of handing every block to the writer thread (a thread switch
    per block, +12 % of the loop's CPU time at N = 6), it only checks the clock there, and the
    frames it takes (copies of one record) are encoded on a thread of its own; at most two wait,
    later ones are dropped, so the loop never waits for the view. Inline, the compiled loop
    asks `frame_wanted` before each block and takes a record only from a block that ends with
    a frame due, and only its last one.

    CPU budget: encoding a frame takes thread CPU time E (a 1000-agent frame: its scene and
    1000 trails); the next frame is not due before E / `CPU_SHARE` after this one began, so the
    view's encoding takes at most that share of one core, whatever N, and the frame rate falls
    below the live rate when a frame costs more than ``CPU_SHARE / rate`` (docs/live.md)."""

    MAX_PENDING = 2
    CPU_SHARE = 0.2

    def __init__(self, inner, server: LiveServer):
        self.inner = inner
        self.server = server
        self.enc = server.encoder
        self._period = 1.0 / server.rate
        self._next = 0.0
        self.counts = inner.counts if inner is not None else {}
        self.inline = inner is None
        # inline, the loop's blocks need be no shorter than a frame period (the writer thread's
        # 10 ms blocks are for a log's encoding): fewer returns to Python per second
        self.block_seconds = self._period if self.inline else None
        if not self.inline:   # with a log, every record is the log's: none to skip
            self.frame_wanted = None
        self.dropped = 0
        self._q = self._worker = None
        self._pending = 0
        self._asked = None       # when the loop last asked `frame_wanted`
        self._granted = False    # ... and was told yes: its next record is the frame
        if self.inline:
            self._q = queue.Queue()
            self._worker = threading.Thread(target=self._work, name="se3sync-live",
                                            daemon=True)
            self._worker.start()

    def __getattr__(self, name):   # anything else a logger offers (add_channel, message, …)
        inner = self.__dict__.get("inner")
        if inner is None:
            raise AttributeError(name)
        return getattr(inner, name)

    def _work(self):
        # the view must not take CPU time from the control loop: this thread runs at a lower
        # scheduling priority (Linux: a thread is a task with its own nice value; best effort)
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), WORKER_NICE)
        except (AttributeError, OSError):
            pass
        while True:
            item = self._q.get()
            if item is None:
                return
            fn, args, frame = item
            self._call(fn, args, frame)
            if frame:
                self._pending -= 1

    def _call(self, fn, args, frame):
        """Encodes (and sends) one item; a frame pushes the next one back by its CPU cost."""
        t0, c0 = time.monotonic(), time.thread_time()
        try:
            fn(*args)
        except Exception:  # noqa: BLE001 - the view must never stop the run
            pass
        if frame:
            self._next = max(self._next, t0 + (time.thread_time() - c0) / self.CPU_SHARE)

    def _emit(self, fn, args, frame):
        if self._q is None:
            self._call(fn, args, frame)
        elif not frame:
            self._q.put((fn, tuple(_copy(a) for a in args), False))
        elif self._pending < self.MAX_PENDING:
            self._pending += 1
            self._q.put((fn, tuple(_copy(a) for a in args), True))
        else:
            self.dropped += 1

    def _due(self) -> bool:
        now = time.monotonic()
        if now < self._next:
            return False
        self._next = now + self._period
        if not self.server.sink.watched():   # nobody is looking: no frame to encode
            return False
        self.server.frames += 1
        return True

    def frame_wanted(self) -> bool:
        """Whether the block the compiled loop is about to run should give a record for a
        frame: a frame falls due before the block ends (its end is guessed from the last
        block's length, the time since the last call), one can be queued, and someone watches.
        The loop takes no record from a block it is told no (`cosim.fastloop.run_compiled`),
        and the last record of one it is told yes: that record is the frame. Inline only."""
        now = time.monotonic()
        lead = 0.0 if self._asked is None else now - self._asked
        self._asked = now
        self._granted = (now + lead >= self._next and self._pending < self.MAX_PENDING
                         and self.server.sink.watched())
        return self._granted

    def _take(self) -> bool:
        """The record of a block `frame_wanted` said yes to is the frame; the next one falls
        due a frame period after this one was due (or after now, if that is later)."""
        if not self._granted:
            return False
        self._granted = False
        self._next = max(self._next, time.monotonic()) + self._period
        self.server.frames += 1
        return True

    def record(self, t_ns, *a):
        if self.inner is not None:
            self.inner.record(t_ns, *a)
        if self._due():
            self._emit(self.enc.record, (t_ns, *a), True)

    def record_fast(self, t_ns, *a):
        if self.inner is not None:
            getattr(self.inner, "record_fast", self.inner.record)(t_ns, *a)
        if self._due():
            self._emit(self.enc.record_fast, (t_ns, *a), True)

    def record_block(self, t_ns, *a):
        inner = self.inner
        if inner is not None:
            if hasattr(inner, "record_block"):
                inner.record_block(t_ns, *a)
            else:
                for r in range(len(t_ns)):
                    inner.record(t_ns[r], *(x[r] for x in a))
        if len(t_ns) and (self._take() or self._due()):
            self._emit(self.enc.record_block, (t_ns[-1:], *(x[-1:] for x in a)), True)

    def jump(self, *a):
        if self.inner is not None:
            self.inner.jump(*a)
        self._emit(self.enc.jump, a, False)

    def jump_fast(self, *a):
        if self.inner is not None:
            getattr(self.inner, "jump_fast", self.inner.jump)(*a)
        self._emit(self.enc.jump_fast, a, False)

    def link_stats(self, t_ns, stats):
        if self.inner is not None:
            self.inner.link_stats(t_ns, stats)
        self._emit(self.enc.link_stats, (t_ns, dict(stats)), False)

    def outcome(self, summary) -> None:
        """The run's outcome record goes to the log (a live view shows the run, not its end)."""
        if self.inner is not None:
            self.inner.outcome(summary)

    def close(self, discard: bool = False):
        try:
            if self.inner is not None:
                self.inner.close(discard=discard)
        finally:
            if self._worker is not None:
                self._q.put(None)
                self._worker.join()
            self.server.close()


def live_only(scenario, live):
    """The scenario a run with a live view and no log steps: its records (the master takes them
    at ``simulation.log_rate`` of simulated time) at most at the live rate, since no more
    frames than that are shown per second of wall time in a run at real time or faster; the
    rest of the scenario unchanged. With a log, or without ``live``, the scenario itself."""
    if live is None:
        return scenario
    rate = live[2] if not isinstance(live, str) and len(live) > 2 else DEFAULT_RATE
    if scenario.log_rate <= rate:
        return scenario
    return dataclasses.replace(scenario, log_rate=float(rate))


def live_logger(logger, live, scenario, *, command: str = "se3sync", encoding: str = "json",
                rate: float = DEFAULT_RATE, insecure: bool = False, agent_ids=None,
                edge_ids=None):
    """``logger`` unchanged when ``live`` is None; else a `LiveTee` around it (``live``: the
    ``[HOST:]PORT`` text or a (host, port) pair) serving on a new `LiveServer`."""
    if live is None:
        return logger
    if isinstance(live, str):
        host, port = parse_live(live, insecure)
    else:
        host, port, *r = live
        rate = r[0] if r else rate
    server = LiveServer(scenario, host, port, rate=rate, encoding=encoding,
                        agent_ids=agent_ids, edge_ids=edge_ids)
    server.announce(command)
    return LiveTee(logger, server)
