"""Shared helpers of the bridge tests (no tests here): free ports, vehicles in threads or
processes, and a UDP relay that injects loss, jitter (hence reordering) and link cuts."""
from __future__ import annotations

import heapq
import json
import os
import random
import select
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

os.environ.setdefault("MAVLINK20", "1")

ROOT = Path(__file__).resolve().parents[1]
from bridge.mavlink.link import free_base_port  # noqa: E402,F401  (re-exported for the tests)

HIL = str(ROOT / "scenarios" / "hil_6uav.toml")


def bound_udp():
    """A UDP socket bound to 127.0.0.1 at a port the OS chose (port 0), and that port: for a
    test that is itself the listening end, nothing can take the port between choice and use.
    (Blocks of ports that processes under test bind themselves: `free_base_port`.)"""
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    return s, s.getsockname()[1]


def load(overrides=(), path=HIL, **kw):
    from cosim.scenario import load_scenario

    return load_scenario(path, list(overrides), **kw)


class VehicleThread:
    """VehicleServer in a thread of this process (context manager)."""

    def __init__(self, **kw):
        from bridge.vehicles.loopback import VehicleServer

        self.server = VehicleServer(**kw)
        self.thread = threading.Thread(target=self.server.run, daemon=True)

    def __enter__(self):
        self.thread.start()
        self.server.ready.wait(60)   # returns when ready: a guard, not a deadline
        return self.server

    def __exit__(self, *exc):
        self.server.stop()
        self.thread.join(5)
        self.server.close()


class VehicleProcess:
    """`se3sync vehicle ...` in a subprocess; stats read back from its --stats file."""

    def __init__(self, args, tmp_path, name="vehicle"):
        self.stats_path = Path(tmp_path) / f"{name}_stats.json"
        self.err_path = Path(tmp_path) / f"{name}_stderr.txt"
        self.cmd = [sys.executable, "-m", "cosim.cli", "vehicle", *map(str, args), "--stats", str(self.stats_path)]
        self.proc = None

    def __enter__(self):
        self._err = open(self.err_path, "w")
        self.proc = subprocess.Popen(self.cmd, stdout=subprocess.DEVNULL, stderr=self._err, cwd=str(ROOT))
        return self

    def wait_ready(self, timeout=60.0) -> None:
        """Until the vehicles are up (their start-up line is on stderr)."""
        t = time.monotonic()
        while "vehicle(s)" not in self.stderr:
            if self.proc.poll() is not None or time.monotonic() - t > timeout:
                raise RuntimeError(f"vehicle did not start: {self.stderr}")
            time.sleep(0.05)

    def stop(self, timeout=10.0) -> dict:
        if self.proc.poll() is None:
            self.proc.terminate()  # SIGTERM: a clean stop
        try:
            self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self._err.close()
        return json.loads(self.stats_path.read_text()) if self.stats_path.exists() else {}

    def __exit__(self, *exc):
        if self.proc is not None and self.proc.poll() is None:
            self.stop()

    @property
    def stderr(self) -> str:
        return self.err_path.read_text() if self.err_path.exists() else ""


class Relay:
    """Per vehicle: vehicle --> 127.0.0.1:relay_port[i] --> bridge 127.0.0.1:bridge_port[i], and
    back. Each datagram is dropped with probability ``loss`` and delayed by U(0, jitter) seconds
    (so datagrams overtake each other); ``cut = True`` drops everything."""

    def __init__(self, bridge_ports, loss=0.0, jitter=0.0, seed=1):
        self.rng = random.Random(seed)
        self.loss, self.jitter = loss, jitter
        self.cut = False
        self.pairs = []
        for bp in bridge_ports:
            a = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            a.bind(("127.0.0.1", 0))
            b = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            b.bind(("127.0.0.1", 0))
            a.setblocking(False)
            b.setblocking(False)
            self.pairs.append({"a": a, "b": b, "bridge": ("127.0.0.1", bp), "vehicle": None})
        self.ports = [p["a"].getsockname()[1] for p in self.pairs]
        self.forwarded = self.dropped = 0
        self._stop = False
        self._heap = []
        self._n = 0
        self.thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self._stop = True
        self.thread.join(5)
        for p in self.pairs:
            p["a"].close()
            p["b"].close()

    def _queue(self, sock, data, addr, now):
        if self.cut or (self.loss and self.rng.random() < self.loss):
            self.dropped += 1
            return
        d = self.rng.uniform(0, self.jitter) if self.jitter else 0.0
        self._n += 1
        heapq.heappush(self._heap, (now + d, self._n, sock, data, addr))

    def _run(self):
        fds = {}
        for p in self.pairs:
            fds[p["a"].fileno()] = (p, "a")
            fds[p["b"].fileno()] = (p, "b")
        while not self._stop:
            now = time.monotonic()
            timeout = 0.02
            if self._heap:
                timeout = max(0.0, min(timeout, self._heap[0][0] - now))
            r, _, _ = select.select(list(fds), [], [], timeout)
            now = time.monotonic()
            for fd in r:
                p, side = fds[fd]
                sock = p[side]
                while True:
                    try:
                        data, addr = sock.recvfrom(65535)
                    except (BlockingIOError, OSError):
                        break
                    if side == "a":
                        p["vehicle"] = addr
                        self._queue(p["b"], data, p["bridge"], now)
                    elif p["vehicle"] is not None:
                        self._queue(p["a"], data, p["vehicle"], now)
            while self._heap and self._heap[0][0] <= now:
                _, _, sock, data, addr = heapq.heappop(self._heap)
                try:
                    sock.sendto(data, addr)
                    self.forwarded += 1
                except OSError:
                    pass
