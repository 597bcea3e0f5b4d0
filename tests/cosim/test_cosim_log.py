"""MCAP logs: what is written is what is read back; a killed run leaves a readable file."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from cosim.run import run_scenario
from cosim.master import Master
from cosim.log.writer import McapLogger
from cosim.log.reader import read_log
from cosim.plants import FmuPlant
from cosim.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[2]
PAPER = ROOT / "scenarios" / "paper_6uav.toml"


class Tap:
    def __init__(self, inner):
        self.inner, self.n, self.k, self.states = inner, inner.n, 0, {}

    def read(self):
        S = self.inner.read()
        self.states[self.k] = S.copy()
        return S

    def apply(self, u):
        self.inner.apply(u)

    def advance(self, h):
        self.inner.advance(h)
        self.k += 1

    def model_description(self):
        return self.inner.model_description()

    def close(self):
        self.inner.close()


def test_log_reads_back_what_was_written(tmp_path):
    sc = load_scenario(PAPER, ["simulation.duration=0.5", "simulation.log_rate=50"])
    plant = Tap(FmuPlant.from_scenario(sc))
    log = tmp_path / "run.mcap"
    md = plant.model_description()
    assert md and "fmiModelDescription" in md
    try:
        logger = McapLogger(log, sc, controller="hybrid", model_description=md)
        summary = Master(sc, plant, "hybrid", logger).run(sc.n_steps())
        logger.close()
    finally:
        plant.close()
    back = read_log(log)
    counts = {t: len(v) for t, v in back["messages"].items()}
    assert counts == logger.counts
    # 0.5 s at 50 Hz: records at t = 0, 0.02, ..., 0.48
    for topic in ("/tf", "/edges", "/agents", "/lyapunov"):
        assert counts[topic] == 25
        times = [t for t, _ in back["messages"][topic]]
        assert times == [k * 20_000_000 for k in range(25)]
    assert counts["/jumps"] == summary["n_jumps"] >= 5
    # metadata and attachment
    meta = back["metadata"]
    assert meta["time_base"] == "simulated" and meta["scenario"] == PAPER.read_text()
    assert json.loads(meta["design"])["u_c1"] == list(sc.design.u_c1)
    assert meta["se3sync_version"]
    assert back["attachments"]["modelDescription.xml"].decode() == md
    # decoded values: the record at t = 0.2 s (step 2000) equals the plant state read then
    t_ns = 200_000_000
    S = plant.states[2000]
    tf = dict(back["messages"]["/tf"])[t_ns]["transforms"]
    assert [x["child_frame_id"] for x in tf] == [f"agent_{i}" for i in range(1, 7)]
    assert all(x["parent_frame_id"] == "world" for x in tf)
    assert tf[0]["timestamp"] == {"sec": 0, "nsec": 200_000_000}
    from controller import se3
    for i, x in enumerate(tf):
        assert [x["translation"][k] for k in "xyz"] == S[i, :3].tolist()
        q = np.array([x["rotation"][k] for k in "wxyz"])
        np.testing.assert_allclose(se3.quat_to_rot(q), S[i, 3:12].reshape(3, 3), atol=1e-12)
    ag = dict(back["messages"]["/agents"])[t_ns]["agents"]
    assert [a["omega"] + a["v"] for a in ag] == S[:, 12:].tolist()
    ed = dict(back["messages"]["/edges"])[0]["edges"]
    assert [e["mode"] for e in ed] == ["jump"] * 5
    np.testing.assert_allclose([e["theta"] for e in ed], [0.3 * np.pi] * 5)
    Rb = sc.graph.relative_poses(se3.T(S[:, 3:12].reshape(6, 3, 3), S[:, :3]))
    ed = dict(back["messages"]["/edges"])[t_ns]["edges"]
    np.testing.assert_allclose([e["rot_err"] for e in ed],
                               np.linalg.norm(np.eye(3) - Rb[:, :3, :3], axis=(1, 2)), rtol=1e-12)
    np.testing.assert_allclose([e["pos_err"] for e in ed],
                               np.linalg.norm(Rb[:, :3, 3], axis=1), rtol=1e-12)
    lyap = dict(back["messages"]["/lyapunov"])
    assert lyap[0]["V"] > lyap[400_000_000]["V"] > 0
    jumps = [m for _, m in back["messages"]["/jumps"]]
    assert [(j["edge"], j["t"]) for j in jumps] == [(j["edge"], j["t"]) for j in summary["jumps"]]


def test_log_has_summary_and_foxglove_schema(tmp_path):
    from mcap.reader import make_reader

    log = tmp_path / "a.mcap"
    run_scenario(str(PAPER), duration=0.05, log_path=log)
    with open(log, "rb") as f:
        r = make_reader(f)
        summ = r.get_summary()
        assert summ is not None and summ.statistics.message_count > 0
        schemas = {s.name: json.loads(s.data) for s in summ.schemas.values()}
        chans = {c.topic: summ.schemas[c.schema_id].name for c in summ.channels.values()}
    assert chans["/tf"] == "foxglove.FrameTransforms"
    fx = schemas["foxglove.FrameTransforms"]["properties"]["transforms"]["items"]["properties"]
    assert set(fx) == {"timestamp", "parent_frame_id", "child_frame_id", "translation", "rotation"}
    assert set(fx["rotation"]["properties"]) == set("xyzw")
    assert all(c.message_encoding == "json" for c in summ.channels.values())


def test_killed_run_leaves_a_readable_log(tmp_path):
    from mcap.stream_reader import StreamReader
    from mcap.records import Message

    log = tmp_path / "killed.mcap"
    proc = subprocess.Popen([sys.executable, "-m", "cosim.cli", "run", str(PAPER), "--log", str(log)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=tmp_path)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            if log.exists() and log.stat().st_size > 600_000:
                break
            if proc.poll() is not None:
                pytest.fail("the run ended before it could be killed")
            time.sleep(0.05)
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.wait()
    assert proc.returncode == -signal.SIGKILL
    n = 0
    with open(log, "rb") as f:
        try:
            for rec in StreamReader(f, skip_magic=False).records:
                if isinstance(rec, Message):
                    json.loads(rec.data)
                    n += 1
        except Exception:
            pass  # the torn tail of the file
    assert n > 100
    # and read_log copes with it too (a streaming fallback)
    back = read_log(log)
    assert back["metadata"]["time_base"] == "simulated"
    assert len(back["messages"]["/tf"]) > 10


@pytest.mark.parametrize("chunking", [True, False])
def test_message_appender_writes_the_bytes_of_mcaps_writer(chunking):
    """`MessageAppender.add` (the logger's fast path into mcap's chunk) against mcap's own
    `Writer.add_message`: the same messages (several channels, sizes across chunk boundaries,
    log times out of order) give byte-identical files; without chunking it is add_message."""
    import io

    from mcap.writer import CompressionType, Writer

    from cosim.log.appender import MessageAppender

    rng = np.random.default_rng(7)
    msgs = []
    for seq in range(1, 3001):
        ch = int(rng.integers(0, 3))
        t = int(rng.integers(0, 10**12)) if seq % 97 == 0 else seq * 1_000_000
        size = int(rng.choice([0, 5, 300, 70_000]))
        msgs.append((ch, t, rng.integers(0, 256, size, dtype=np.uint8).tobytes(), seq))

    def write(fast: bool) -> bytes:
        buf = io.BytesIO()
        w = Writer(buf, chunk_size=64 * 1024, compression=CompressionType.ZSTD,
                   use_chunking=chunking)
        w.start(profile="", library="test")
        sid = w.register_schema(name="s", encoding="jsonschema", data=b"{}")
        # one channel with metadata (non-ASCII too): the appender writes channel records
        ids = [w.register_channel(topic=f"/c{k}", message_encoding="json", schema_id=sid,
                                  metadata={"a": "b", "ключ": "значение"} if k == 1 else {})
               for k in range(3)]
        app = MessageAppender(w, level=3)   # mcap's zstd level: its bytes exactly
        assert (app.add != app._slow) == chunking   # the fast path needs mcap's chunk builder
        for ch, t, data, seq in msgs:
            if fast:
                app.add(ids[ch], t, data, seq)
            else:
                w.add_message(ids[ch], t, data, t, seq)
        w.finish()
        return buf.getvalue()

    slow, fast = write(False), write(True)
    assert fast == slow
    from mcap.reader import make_reader

    r = make_reader(io.BytesIO(fast))
    st = r.get_summary().statistics
    assert st.message_count == len(msgs)
    assert st.message_start_time == min(m[1] for m in msgs)
    assert [m.sequence for _, _, m in r.iter_messages(log_time_order=False)] == [m[3] for m in msgs]


def test_message_appender_chunks_at_its_own_zstd_level():
    """At the logger's zstd level (1, not mcap's 3) the file differs only inside the chunks:
    each chunk decompresses to the bytes of mcap's own chunk, with its CRC, indexes and
    statistics, and mcap's reader (CRCs checked) returns every message."""
    import io

    import zstandard
    from mcap.reader import make_reader
    from mcap.records import Chunk as ChunkRecord
    from mcap.stream_reader import StreamReader as SR
    from mcap.writer import CompressionType, Writer

    from cosim.log.appender import ZSTD_LEVEL, MessageAppender

    assert ZSTD_LEVEL != 3
    text = [json.dumps({"x": [float(v) for v in np.random.default_rng(s).standard_normal(40)]})
            .encode() for s in range(600)]

    def write(level):
        buf = io.BytesIO()
        w = Writer(buf, chunk_size=16 * 1024, compression=CompressionType.ZSTD)
        w.start(profile="", library="test")
        sid = w.register_schema(name="s", encoding="jsonschema", data=b"{}")
        ids = [w.register_channel(topic=f"/c{k}", message_encoding="json", schema_id=sid)
               for k in range(2)]
        app = MessageAppender(w, level=level)
        for q, data in enumerate(text):
            app.add(ids[q % 2], 1000 * q, data, q + 1)
        w.finish()
        return buf.getvalue()

    mine, theirs = write(ZSTD_LEVEL), write(3)
    assert mine != theirs

    def chunks(b):
        return [r for r in SR(io.BytesIO(b), skip_magic=False, emit_chunks=True).records
                if isinstance(r, ChunkRecord)]

    a, b = chunks(mine), chunks(theirs)
    assert len(a) == len(b) > 5
    for x, y in zip(a, b):
        assert x.data != y.data
        assert (zstandard.ZstdDecompressor().decompress(x.data, max_output_size=1 << 24)
                == zstandard.ZstdDecompressor().decompress(y.data, max_output_size=1 << 24))
        assert (x.uncompressed_crc, x.uncompressed_size, x.message_start_time) == \
            (y.uncompressed_crc, y.uncompressed_size, y.message_start_time)
    r = make_reader(io.BytesIO(mine), validate_crcs=True)
    got = [(m.log_time, m.data) for _, _, m in r.iter_messages()]
    assert got == [(1000 * q, d) for q, d in enumerate(text)]
    summary = r.get_summary()
    assert summary.statistics.chunk_count == len(a)
    assert [c.compressed_size for c in summary.chunk_indexes] == [len(c.data) for c in a]


def test_message_appender_falls_back_when_not_proven(monkeypatch):
    """The fast path is used only after `proven` wrote the same bytes both ways; otherwise the
    appender is mcap's own add_message."""
    import io

    from mcap.writer import Writer

    from cosim.log import appender as mlog

    assert mlog.proven() is True          # on the mcap installed here
    monkeypatch.setattr(mlog, "PROOF", [False])
    w = Writer(io.BytesIO())
    app = mlog.MessageAppender(w)
    assert app.add == app._slow


def _zstd_threads():
    import threading

    return [t for t in threading.enumerate() if t.name.startswith("se3sync-zstd")]


def _small_log(path, n_records):
    """A paper-scenario logger with 4 KiB chunks and n_records random records in it (so several
    chunks have gone to its compression thread)."""
    sc = load_scenario(PAPER, ["simulation.duration=0.2"])
    lg = McapLogger(path, sc, chunk_size=4096)
    rng = np.random.default_rng(3)
    N, M = sc.graph.n, sc.graph.M
    for r in range(n_records):
        lg.record(10_000_000 * r, rng.standard_normal((N, 18)), rng.standard_normal((N, 6)),
                  *rng.random((2, M)), np.zeros(M, bool), *rng.random((3, M)),
                  rng.standard_normal((N, 4)), 1.0, 0.5)
    return lg


@pytest.mark.parametrize("discard", [False, True])
def test_logger_close_stops_its_compression_thread(tmp_path, discard):
    """Chunks are compressed on a thread of the logger's own: closing the log, or discarding
    it, ends that thread; a finished log holds every message, a discarded one is gone."""
    before = len(_zstd_threads())
    path = tmp_path / "c.mcap"
    lg = _small_log(path, 40)
    assert len(_zstd_threads()) == before + 1
    lg.close(discard=discard)
    assert len(_zstd_threads()) == before
    assert path.exists() != discard
    if not discard:
        assert len(read_log(path)["messages"]["/lyapunov"]) == 40


def test_a_log_that_cannot_be_finished_is_removed(tmp_path):
    """close() whose finishing write fails (a full disk: OSError) removes the log, stops the
    compression thread and raises the error: nothing is left that looks whole."""
    import errno

    before = len(_zstd_threads())
    path = tmp_path / "f.mcap"
    lg = _small_log(path, 20)
    assert len(_zstd_threads()) == before + 1

    def full():
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    lg._w.finish = full
    with pytest.raises(OSError, match="No space left"):
        lg.close()
    assert not path.exists()
    assert len(_zstd_threads()) == before
