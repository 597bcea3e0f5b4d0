"""The live view (`--live`): a real WebSocket client speaking Foxglove's protocol receives the
log's channels while a run goes on, message for message what the log holds; the rate bound;
the log is the same with and without the live view; loopback only unless --insecure."""
import json
import os
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cosim.cli import main
from cosim.log import live as L
from cosim.log.reader import read_log
from cosim.run import run_scenario
from cosim.scenario import load_scenario

pytest.importorskip("foxglove")
websocket = pytest.importorskip("websocket")   # websocket-client

ROOT = Path(__file__).resolve().parents[2]
PAPER = ROOT / "scenarios" / "paper_6uav.toml"
SE3SYNC = Path(sys.executable).with_name("se3sync")
SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]


@pytest.mark.parametrize("text, insecure, want", [
    ("8765", False, ("127.0.0.1", 8765)),
    ("0", False, ("127.0.0.1", 0)),
    ("localhost:9000", False, ("localhost", 9000)),
    ("127.0.0.2:1", False, ("127.0.0.2", 1)),
    ("[::1]:8765", False, ("::1", 8765)),
    ("0.0.0.0:8765", True, ("0.0.0.0", 8765)),
    ("192.168.1.5:0", True, ("192.168.1.5", 0)),
])
def test_parse_live(text, insecure, want):
    assert L.parse_live(text, insecure) == want


@pytest.mark.parametrize("text", ["0.0.0.0:8765", "192.168.1.5:1", "[::]:9", "example.org:80"])
def test_non_loopback_needs_insecure(text):
    with pytest.raises(Exception) as e:
        L.parse_live(text)
    assert str(e.value).startswith("--live: ") and "--insecure" in str(e.value)


@pytest.mark.parametrize("text", ["", "x", "70000", "host:", "[::1]8765", "-1"])
def test_bad_live_values(text):
    with pytest.raises(Exception) as e:
        L.parse_live(text)
    assert str(e.value).startswith("--live: ")


HIL = ROOT / "scenarios" / "hil_6uav.toml"
# every command that serves a live view, with an output it would write (TMP: the test's dir)
LIVE_COMMANDS = {
    "run": ["run", str(PAPER), "--duration", "0.01", "--log", "TMP/x.mcap"],
    "connect": ["connect", str(HIL), "--duration", "0.01", "--log", "TMP/x.mcap",
                "--connect-timeout", "0.5"],
    "swarm": ["swarm", str(HIL), "--duration", "0.01", "--log", "TMP/x.mcap",
              "--vehicles", "loopback"],
    "vehicle": ["vehicle", "--scenario", str(HIL), "--duration", "0.01", "--stats",
                "TMP/x.json"],
}


@pytest.mark.parametrize("command", list(LIVE_COMMANDS))
@pytest.mark.parametrize("where", ["0.0.0.0:0", "192.168.1.5:8765", "[::]:0"])
def test_a_public_live_socket_is_refused_on_one_line(command, where, tmp_path, capsys):
    """Every command that serves a live view refuses a non-loopback --live without --insecure:
    one line naming --live and --insecure, exit 2, before anything is started or written."""
    argv = [a.replace("TMP/", f"{tmp_path}/") for a in LIVE_COMMANDS[command]]
    assert main([*argv, "--live", where]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--live" in err and "--insecure" in err, err
    assert os.listdir(tmp_path) == []
    assert main([*argv, "--live", "0", "--live-rate", "0"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--live-rate" in err, err
    assert os.listdir(tmp_path) == []


class FakeClock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def test_tee_sends_the_newest_record_at_most_rate_times_per_second(monkeypatch):
    """LiveTee's bound, on a fake wall clock: 1000 records 2 ms apart at 30 Hz: the first
    record, then the first one at least 1/30 s after the previous frame."""
    clock = FakeClock()
    monkeypatch.setattr(L.time, "monotonic", clock)
    sent = []

    class Enc:
        def record(self, t_ns, *a):
            sent.append(t_ns)

    class Sink:
        @staticmethod
        def watched():
            return True

    class Server:
        rate = 30.0
        encoder = Enc()
        frames = 0
        sink = Sink()

    class Inner:   # a log beside the view: the tee encodes where it is called
        counts = {}

        def record(self, *a):
            pass

    tee = L.LiveTee(Inner(), Server())
    for k in range(1000):
        clock.t = 100.0 + k * 0.002
        tee.record(k, None)
    # a frame every ⌈(1/30) / 0.002⌉ = 17 records: the first record at or after the previous
    # frame + 1/30 s
    assert sent == list(range(0, 1000, 17))


def test_frames_that_cost_more_cpu_than_the_share_come_less_often(monkeypatch):
    """The view's CPU budget: a frame that takes E of the encoding thread's CPU time delays the
    next one to E / CPU_SHARE after it began. Frames of 10 ms of CPU at a share of 0.2: one
    every 50 ms instead of every 1/30 s (records 2 ms apart: every 25th)."""
    clock = FakeClock()
    cpu = [0.0]
    monkeypatch.setattr(L.time, "monotonic", clock)
    monkeypatch.setattr(L.time, "thread_time", lambda: cpu[0])
    sent = []

    class Enc:
        def record(self, t_ns, *a):
            sent.append(t_ns)
            cpu[0] += 0.010

    class Sink:
        @staticmethod
        def watched():
            return True

    class Server:
        rate = 30.0
        encoder = Enc()
        frames = 0
        sink = Sink()

    class Inner:
        counts = {}

        def record(self, *a):
            pass

    assert L.LiveTee.CPU_SHARE == 0.2
    tee = L.LiveTee(Inner(), Server())
    for k in range(1000):
        clock.t = 100.0 + k * 0.002
        tee.record(k, None)
    assert sent == list(range(0, 1000, 25))


def test_inline_tee_encodes_copies_on_its_own_thread_and_drops_when_behind(monkeypatch):
    """Without a log the tee is `inline` (the loop calls it in its own thread): a frame is a
    copy of the record (the loop reuses its buffers) encoded on the tee's thread; while two
    frames wait, later ones are dropped, never waited for; jumps are never dropped."""
    import threading

    import numpy as np

    clock = FakeClock()
    monkeypatch.setattr(L.time, "monotonic", clock)
    gate = threading.Event()
    frames, jumps = [], []

    class Enc:
        def record_block(self, t_ns, S):
            gate.wait(30)
            frames.append((list(t_ns), S.copy()))

        def jump(self, *a):
            jumps.append(a)

    class Sink:
        @staticmethod
        def watched():
            return True

    class Server:
        rate = 30.0
        encoder = Enc()
        frames = 0
        sink = Sink()

        def close(self):
            pass

    tee = L.LiveTee(None, Server())
    assert tee.inline
    buf = np.zeros((2, 3))
    for k in range(5):   # 5 frames due while the encoder is stuck on the first
        clock.t += 1.0
        buf[:] = k
        tee.record_block([k, k], buf)
        tee.jump(k, 0.0, 1, 0.0, 1.0, 0.5)
    gate.set()
    tee.close()
    # the first frame (taken before the encoder blocked) and one more were queued, the rest
    # dropped; each is the record as it was when taken
    assert tee.dropped + len(frames) == 5 and len(frames) <= 3 and tee.dropped >= 2
    for t, S in frames:
        assert t == [t[0]] and (S == t[0]).all() and S.shape == (1, 3)
    assert len(jumps) == 5


def test_the_log_is_the_same_with_and_without_live(tmp_path):
    """The live view rides the log's path: the records it sees are the log's, which it passes
    on unchanged (the JSON messages, byte for byte)."""
    sc = load_scenario(PAPER, duration=0.3)
    a, b = tmp_path / "plain.mcap", tmp_path / "live.mcap"
    run_scenario(sc, log_path=a)
    run_scenario(sc, log_path=b, live=("127.0.0.1", 0, 30.0))
    ma, mb = read_log(a)["messages"], read_log(b)["messages"]
    assert ma.keys() == mb.keys() and ma == mb


def _messages_with_bytes(path):
    """{(topic, log_time): bytes} of an MCAP log."""
    from mcap.reader import make_reader

    out = {}
    with open(path, "rb") as f:
        for _, ch, msg in make_reader(f).iter_messages():
            out[(ch.topic, msg.log_time)] = bytes(msg.data)
    return out


def _collect(url, want_tf, deadline_s=120):
    """A Foxglove WebSocket client: subscribe to every advertised channel and gather
    (topic, log_time, payload) until ``want_tf`` /tf messages came (or the deadline, which
    only a hung server reaches)."""
    ws = websocket.create_connection(url, subprotocols=SUBPROTOCOLS, timeout=deadline_s)
    chans, subs, got = {}, {}, []
    info = None
    t0 = time.monotonic()
    try:
        while time.monotonic() - t0 < deadline_s:
            m = ws.recv()
            if isinstance(m, str):
                o = json.loads(m)
                if o.get("op") == "serverInfo":
                    info = o
                elif o.get("op") == "advertise":
                    new = []
                    for c in o["channels"]:
                        chans[c["id"]] = c
                        subs[len(subs) + 1] = c["id"]
                        new.append({"id": len(subs), "channelId": c["id"]})
                    ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
                continue
            if m[0] == 1:   # MessageData: op, subscription id, log time, payload
                sid, t = struct.unpack_from("<IQ", m, 1)
                got.append((chans[subs[sid]]["topic"], t, bytes(m[13:])))
                if sum(1 for g in got if g[0] == "/tf") >= want_tf:
                    break
    finally:
        ws.close()
    return info, chans, got, time.monotonic() - t0


@pytest.mark.timeout(300)
@pytest.mark.parametrize("encoding", ["json", "cdr"])
def test_a_websocket_client_receives_the_logs_channels(tmp_path, encoding):
    log = tmp_path / "run.mcap"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    p = subprocess.Popen([str(SE3SYNC), "run", str(PAPER), "--duration", "2000", "--log",
                          str(log), "--log-encoding", encoding, "--live", "127.0.0.1:0",
                          "--live-rate", "20"],
                         stderr=subprocess.PIPE, text=True, env=env)
    try:
        url = None
        for line in p.stderr:
            if "live view on ws://" in line:
                url = line.split("live view on ")[1].split()[0]
                break
        assert url is not None and not url.endswith(":0")
        info, chans, got, window = _collect(url, want_tf=12)
    finally:
        p.send_signal(signal.SIGINT)
        rest = p.communicate(timeout=120)[1]
    assert p.returncode == 130, rest
    topics = {c["topic"] for c in chans.values()}
    assert {"/tf", "/edges", "/agents", "/lyapunov", "/jumps", "/scene"} <= topics
    assert {f"/trail/agent_{i}" for i in range(1, 7)} <= topics
    for c in chans.values():   # the log's schemas: Foxglove's and ours, JSON or ROS 2 msg
        if c["topic"] == "/tf":
            assert c["schemaName"] in ("foxglove.FrameTransforms",
                                       "foxglove_msgs/msg/FrameTransforms")
            assert c["encoding"] == ("json" if encoding == "json" else "cdr")
    # every record message received is the log's message at that time, byte for byte
    logged = _messages_with_bytes(log)
    rec = [g for g in got if g[0] in ("/tf", "/edges", "/agents", "/lyapunov")]
    assert sum(1 for g in rec if g[0] == "/tf") == 12
    for topic, t, data in rec:
        assert logged[(topic, t)] == data, (topic, t)
    assert any(g[0] == "/scene" for g in got)
    # the rate bound (an upper bound: load can only lower the count)
    n_tf = sum(1 for g in got if g[0] == "/tf")
    assert n_tf <= 20 * window + 2


@pytest.mark.timeout(300)
def test_without_a_log_each_frame_is_the_record_a_log_holds_at_its_step(tmp_path):
    """Without --log the compiled loop takes a record only from a block that ends with a frame
    due (`LiveTee.frame_wanted`), the block's last one on the record grid (the live rate of
    simulated time): each /tf, /edges, /agents and /lyapunov message received is, byte for
    byte, the message a log of the same run (records on the same grid) holds at its time."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    p = subprocess.Popen([str(SE3SYNC), "run", str(PAPER), "--duration", "2000",
                          "--live", "127.0.0.1:0", "--live-rate", "20"],
                         stderr=subprocess.PIPE, text=True, env=env)
    try:
        url = None
        for line in p.stderr:
            if "live view on ws://" in line:
                url = line.split("live view on ")[1].split()[0]
                break
        assert url is not None
        _, _, got, _ = _collect(url, want_tf=8)
    finally:
        p.send_signal(signal.SIGINT)
        rest = p.communicate(timeout=120)[1]
    assert p.returncode == 130, rest
    rec = [g for g in got if g[0] in ("/tf", "/edges", "/agents", "/lyapunov")]
    times = sorted({t for _, t, _ in rec})
    assert len(times) >= 8
    grid = 50_000_000                     # records at 20 Hz of simulated time
    assert all(t % grid == 0 for t in times), times
    log = tmp_path / "same.mcap"
    assert main(["run", str(PAPER), "--duration", f"{times[-1] / 1e9 + 0.05:.4f}",
                 "--set", "simulation.log_rate=20", "--log", str(log)]) == 0
    logged = _messages_with_bytes(log)
    for topic, t, data in rec:
        assert logged[(topic, t)] == data, (topic, t)
