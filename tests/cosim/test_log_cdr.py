"""The CDR log (--log-encoding cdr): the JSON log's values in ROS 2 CDR, each message the bytes
mcap-ros2-support's own encoder gives, and the bulk trail writer equal to the one-by-one one."""
import io
import math
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.records import Chunk, MessageIndex
from mcap.stream_reader import StreamReader

from controller.errors import Se3SyncError
from cosim.log import cdr
from cosim.log import foxglove as fg
from cosim.log.writer import McapLogger
from cosim.log.reader import read_log
from cosim.master import Master
from cosim.plants import FmuPlant
from cosim.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[2]
PAPER = ROOT / "scenarios" / "paper_6uav.toml"


def _log(tmp_path, sc, encoding, **kw):
    path = tmp_path / f"{encoding}.mcap"
    plant = FmuPlant.from_scenario(sc)
    lg = McapLogger(path, sc, encoding=encoding, **kw)
    try:
        Master(sc, plant, "hybrid", lg).run(sc.n_steps())
    finally:
        lg.close()
        plant.close()
    return path


# The tolerance between the two encodings of a run: none. Every float of every channel is
# computed once (the master's arrays, `foxglove.error_colors` for the scene's edge colours,
# the builders' constants) and encoded twice, so the CDR log decodes to the JSON log's values
# bit for bit on any CPU. A value computed twice, by two code paths (numpy's vectorised log10
# and math.log10 did this once), differs by an ulp on some CPUs: docs/testing.md.
ULP_TOLERANCE = 0


def _ulps(a: float, b: float) -> int:
    """How many doubles lie between a and b (0: the same double; ±0.0 count as the same)."""
    ia, ib = (struct.unpack("<q", struct.pack("<d", x))[0] for x in (a, b))
    ia, ib = (i if i >= 0 else -(i & 0x7FFFFFFFFFFFFFFF) for i in (ia, ib))
    return abs(ia - ib)


def _same(a, b, where, counts=None, topic=None):
    """a (from JSON) and b (from CDR) hold the same values: floats within ULP_TOLERANCE (JSON
    null is a non-finite value), the same sign; ``counts[topic]`` counts the floats compared."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and set(a) == set(b), (where, a, b)
        for k in a:
            _same(a[k], b[k], f"{where}.{k}", counts, topic)
    elif isinstance(a, list):
        assert isinstance(b, list) and len(a) == len(b), (where, a, b)
        for i, (x, y) in enumerate(zip(a, b)):
            _same(x, y, f"{where}[{i}]", counts, topic)
    elif a is None:
        assert isinstance(b, float) and not math.isfinite(b), (where, b)
    elif isinstance(a, float) or isinstance(b, float):
        assert isinstance(b, float), (where, a, b)
        if math.isfinite(b):
            assert _ulps(float(a), b) <= ULP_TOLERANCE, (where, a, b)
        else:
            assert not math.isfinite(a) or a != a, (where, a, b)
        assert math.copysign(1, a) == math.copysign(1, b), (where, a, b)
        if counts is not None:
            counts[topic] = counts.get(topic, 0) + 1
    else:
        assert a == b and type(a) is type(b), (where, a, b)


def test_cdr_log_holds_the_json_logs_values(tmp_path):
    """The paper scenario for 2 s (jumps, so edges in mode "jump" and scenes with jumping
    edges): every channel of the CDR log decodes to the JSON log's messages, at the same log
    times, under the same names, every float of every channel within ULP_TOLERANCE (0: bit
    for bit). The one difference is documented: each edge of a CDR scene carries its label,
    hidden (font size 0, alpha 0) while the edge flows."""
    sc = load_scenario(PAPER, ["simulation.duration=2"])
    js = read_log(_log(tmp_path, sc, "json"))
    cd = read_log(_log(tmp_path, sc, "cdr"))
    assert cd["metadata"]["log_encoding"] == "cdr" and js["metadata"]["log_encoding"] == "json"
    assert set(js["messages"]) == set(cd["messages"])
    edges = [m for _, msg in js["messages"]["/edges"] for m in msg["edges"]]
    assert any(e["mode"] == "jump" for e in edges)
    hidden = shown = 0
    counts = {}
    for topic, msgs in js["messages"].items():
        assert [t for t, _ in msgs] == [t for t, _ in cd["messages"][topic]], topic
        for (_, a), (_, b) in zip(msgs, cd["messages"][topic]):
            if topic == "/scene":
                for ea, eb in zip(a["entities"], b["entities"]):
                    if ea["id"].startswith("edge_") and not ea["texts"]:
                        (label,) = eb["texts"]
                        assert label["font_size"] == 0 and label["color"]["a"] == 0
                        eb = dict(eb, texts=[])
                        hidden += 1
                    elif ea["texts"]:
                        shown += 1
                    _same(ea, eb, topic, counts, topic)
                assert len(a["entities"]) == len(b["entities"])
            else:
                _same(a, b, topic, counts, topic)
    assert hidden and shown
    # every channel was compared, float by float (the trails: 7 per pose)
    assert set(counts) == set(js["messages"]), set(js["messages"]) - set(counts)
    assert counts["/edges"] == 5 * len(edges) and counts["/trail/agent_6"] >= 7 * 40
    with open(tmp_path / "cdr.mcap", "rb") as f:
        summary = make_reader(f).get_summary()
    enc = {c.topic: (c.message_encoding, summary.schemas[c.schema_id].encoding,
                     summary.schemas[c.schema_id].name) for c in summary.channels.values()}
    assert enc["/tf"] == ("cdr", "ros2msg", "foxglove_msgs/msg/FrameTransforms")
    assert enc["/scene"] == ("cdr", "ros2msg", "foxglove_msgs/msg/SceneUpdate")
    assert enc["/trail/agent_3"] == ("cdr", "ros2msg", "foxglove_msgs/msg/PosesInFrame")
    assert enc["/edges"][2] == "se3sync_msgs/msg/Edges" and enc["/jumps"][0] == "json"


def test_both_encodings_draw_the_edge_colour_error_colors_computes(tmp_path, monkeypatch):
    """What makes the test above hold on every CPU, checked on any CPU: both scene encoders
    write the colours `foxglove.error_colors` returns, and compute none of their own. With
    error_colors nudged by one ulp, the colour of every flowing edge in both logs is the nudged
    value of the edge errors the /edges record of that instant carries."""
    real = fg.error_colors

    def nudged(err):
        c = real(err)
        return np.nextafter(c, np.inf)

    monkeypatch.setattr(fg, "error_colors", nudged)
    sc = load_scenario(PAPER, ["simulation.duration=0.5"])
    checked = 0
    for enc in ("json", "cdr"):
        log = read_log(_log(tmp_path, sc, enc), topics=("/scene", "/edges"))
        errs = {t: [e["rot_err"] for e in m["edges"]] for t, m in log["messages"]["/edges"]}
        for t, m in log["messages"]["/scene"]:
            want = nudged(errs[t])
            for k, e in enumerate(x for x in m["entities"] if x["id"].startswith("edge_")):
                c = e["lines"][0]["color"]
                if (c["r"], c["g"], c["b"]) == (1.0, 1.0, 1.0):   # jumping: drawn white
                    continue
                assert [c["r"], c["g"], c["b"]] == want[k].tolist(), (enc, t, k)
                assert [c["r"], c["g"], c["b"]] != real(errs[t])[k].tolist()
                checked += 1
    assert checked > 2 * 5 * 5


def _raw(x):
    """A decoded message as a dict with its ROS 2 field names (what the encoder takes)."""
    slots = getattr(type(x), "__slots__", None)
    if slots is not None and hasattr(x, "_type"):
        return {k: _raw(getattr(x, k)) for k in slots}
    if isinstance(x, (list, tuple)):
        return [_raw(v) for v in x]
    return x


def test_every_cdr_message_is_the_library_encoding(tmp_path):
    """Each message of a CDR log (records, scenes, trails of every length until full) is the
    byte string mcap-ros2-support's encoder makes of its decoded value: the templates' padding,
    alignment and lengths are the library's."""
    sc = load_scenario(PAPER, ["simulation.duration=1.3"])
    path = _log(tmp_path, sc, "cdr", trail_seconds=0.5, trail_rate=10.0)
    lengths = set()
    n = 0
    with open(path, "rb") as f:
        for schema, channel, msg in make_reader(f).iter_messages():
            if channel.message_encoding != "cdr":
                continue
            enc, dec = cdr._codec(schema.name)
            value = dec(msg.data)
            assert enc(_raw(value)) == bytes(msg.data), channel.topic
            assert (repr(cdr.decode(schema.name, msg.data))
                    == repr(cdr.decode_reference(schema.name, msg.data))), channel.topic
            if channel.topic == "/trail/agent_2":
                lengths.add(len(value.poses))
            n += 1
    assert lengths == set(range(1, 7))   # 5 kept poses and the current one
    assert n > 500


def _random_value(t, defs, rng, depth=0):
    """A random message of type t ("pkg/Name") with the ROS 2 field names: every number kind
    at its extremes, NaN, ±inf and −0.0 among the floats, strings empty, one byte or non-ASCII,
    sequences of 0 to 3 elements."""
    ints = {"int8": (-128, 127), "char": (-128, 127), "uint8": (0, 255), "byte": (0, 255),
            "int16": (-2**15, 2**15 - 1), "uint16": (0, 2**16 - 1), "int32": (-2**31, 2**31 - 1),
            "uint32": (0, 2**32 - 1), "int64": (-2**63, 2**63 - 1), "uint64": (0, 2**64 - 1)}
    special = [math.nan, math.inf, -math.inf, -0.0, 5e-324, 1.7976931348623157e308]

    def one(base):
        if base == "bool":
            return bool(rng.integers(2))
        if base in ints:
            lo, hi = ints[base]
            mid = lo + int.from_bytes(rng.bytes(8), "little") % (hi - lo + 1)
            return [lo, hi, mid][int(rng.integers(3))]
        if base in ("float32", "float64"):
            x = rng.choice(special) if rng.random() < 0.3 else rng.standard_normal() * 1e3
            with np.errstate(over="ignore"):
                return float(np.float32(x)) if base == "float32" else float(x)
        if base == "string":
            return str(rng.choice(["", "a", "agent12", "θ_k ✓", "x" * int(rng.integers(2, 9))]))
        return _random_value(base, defs, rng, depth + 1)

    out = {}
    for name, base, kind, n in defs[t]:
        if kind == "one":
            out[name] = one(base)
        else:
            k = n if kind == "fixed" else int(rng.integers(0, 4 if depth < 2 else 2))
            vals = [one(base) for _ in range(k)]
            out[name] = bytes(vals) if base in ("uint8", "byte") else vals
    return out


def test_decode_is_the_library_decoder_on_random_messages_of_every_type():
    """`cdr.decode` (a decoder generated per type) against mcap-ros2-support's decoder, on
    random messages of every type the schemas hold (Foxglove's primitives with their numbers,
    strings, byte data and nested sequences), and no dict from a message cut short."""
    from cosim.log.cdr_decode import parse_msg

    defs = {}
    for f in sorted((Path(cdr.__file__).parent / "ros2_schemas").glob("*/*.msg")):
        defs[f"{f.parent.name}/{f.stem}"] = parse_msg(f.parent.name, f.read_text())
    assert len(defs) >= 25
    rng = np.random.default_rng(7)
    cut_checked = 0
    for t in defs:
        name = t.replace("/", "/msg/")
        enc, _ = cdr._codec(name)
        for _ in range(12):
            data = enc(_random_value(t, defs, rng))
            got, ref = cdr.decode(name, data), cdr.decode_reference(name, data)
            assert repr(got) == repr(ref), t
            assert type(got) is dict
        for cut in range(4, len(data)):          # every prefix of the last one
            with pytest.raises((ValueError, struct.error)):
                cdr.decode(name, data[:cut])
            cut_checked += 1
        for at in range(4, len(data) - 3, 4):    # a count of 2³² − 1 anywhere: no huge list
            bad = data[:at] + b"\xff\xff\xff\xff" + data[at + 4:]
            try:
                cdr.decode(name, bad)
            except (ValueError, struct.error):
                pass
    assert cut_checked > 1000
    with pytest.raises(ValueError, match="not little-endian CDR"):
        cdr.decode("geometry_msgs/msg/Point", b"\x00\x00\x00\x00" + bytes(24))


# every primitive, alone, in fixed arrays, sequences and bounded sequences, mixed sizes (so the
# alignment moves), bounded strings, constants, default values, an empty message and fixed
# arrays of messages: what the ROS 2 grammar allows beyond what our schemas use
_ALL = """\
uint8 FLAG=3
string NAME="x=y"
bool b
char c
byte y
int8 i8
float64 f64 1.5
uint8 u8
int16 i16
uint16 u16
int32 i32
float32 f32
uint32 u32
int64 i64
uint64 u64
string s
string<=5 sb
char[2] c2
int16[3] i16x3
float32[] f32s
int64[<=4] i64s
bool[] bs
byte[] ys
uint8[3] u8x3
string[2] s2
string<=3[] sbs
Empty e
Empty[] es
Mixed[2] m2
Mixed[] ms
================================================================================
MSG: test_msgs/Empty
================================================================================
MSG: test_msgs/Mixed
uint8 a
float64 x
uint16 b
"""


def test_decode_covers_the_ros2_grammar():
    """The generated decoder against mcap-ros2-support's on random messages of a type that
    uses every primitive and every array form."""
    from mcap_ros2._dynamic import generate_dynamic, serialize_dynamic

    from cosim.log.cdr_decode import decoder, parse_msg

    parts = _ALL.split("=" * 80 + "\n")
    defs = {"test_msgs/All": parse_msg("test_msgs", parts[0])}
    for part in parts[1:]:
        head, _, body = part.partition("\n")
        defs[head.split()[1]] = parse_msg("test_msgs", body)
    assert [f[0] for f in defs["test_msgs/All"]][:3] == ["b", "c", "y"]   # constants dropped
    enc = serialize_dynamic("test_msgs/msg/All", _ALL)["test_msgs/msg/All"]
    ref = generate_dynamic("test_msgs/msg/All", _ALL)["test_msgs/msg/All"]
    dec = decoder("test_msgs/msg/All", defs, {})
    rng = np.random.default_rng(11)
    for _ in range(200):
        value = _random_value("test_msgs/All", defs, rng)
        value["sb"] = value["sb"][:5]
        value["sbs"] = [x[:3] for x in value["sbs"]]
        value["i64s"] = value["i64s"][:4]
        data = enc(value)
        assert repr(dec(data)) == repr(cdr._plain(ref(data)))


def test_layout_fill_is_the_library_encoding():
    """`Layout.fill` of random rows (NaN, ±inf, −0.0, subnormals, large time stamps, modes)
    against the library's encoding of the same dicts, for a message with strings of every
    length mod 4 before its numbers (so every alignment case occurs)."""
    rng = np.random.default_rng(5)
    names = ["a", "bb", "ccc", "dddd", "eeeee"]

    def edges(f, t, m):
        return {"timestamp": t(), "edges": [
            {"edge": k + 1, "positive": 1, "negative": 2, "theta": f(), "mu_u": f(),
             "rot_err": f(), "pos_err": f(), "u": f(), "mode": m()} for k in range(5)]}

    def frames(f, t, m):
        return {"transforms": [{"timestamp": t(), "parent_frame_id": "w" * (k + 1),
                                "child_frame_id": nm, "translation": {c: f() for c in "xyz"},
                                "rotation": {c: f() for c in "xyzw"}}
                               for k, nm in enumerate(names)]}

    for name, build, K, M in (("se3sync_msgs/msg/Edges", edges, 25, 5),
                              ("foxglove_msgs/msg/FrameTransforms", frames, 35, 0)):
        lay = cdr.compile_layout(name, build)
        R = 7
        v = rng.standard_normal((R, K)) * 10.0 ** rng.integers(-300, 300, (R, K))
        v.flat[rng.choice(v.size, 12, replace=False)] = [np.nan, np.inf, -np.inf, -0.0, 0.0,
                                                          5e-324, -5e-324, 1e308, -1e-308,
                                                          np.pi, 1.0, -1.0]
        t = rng.integers(0, 2**31 - 1, R) * 1_000_000_000 + rng.integers(0, 10**9, R)
        modes = rng.choice([cdr.MODE["flow"], cdr.MODE["jump"]], (R, M))
        rows = lay.fill(v, t, modes if M else None)
        enc, _ = cdr._codec(name)
        for r in range(R):
            vals = iter(v[r].tolist())
            ts = {"sec": int(t[r] // 10**9), "nanosec": int(t[r] % 10**9)}
            md = iter("jump" if x == cdr.MODE["jump"] else "flow" for x in modes[r])
            msg = build(lambda: next(vals), lambda: dict(ts), lambda: next(md))
            assert rows[r].tobytes() == enc(msg), (name, r)


def test_add_rows_is_add_message_by_message():
    """`MessageAppender.add_rows` (the trails of a CDR log, one write per stretch of a chunk)
    against `add` row by row, with other channels in between and chunks cut inside the rows:
    the same chunks byte for byte and the same message indexes, and mcap's reader finds every
    message of every channel."""
    from mcap.writer import CompressionType, Writer

    from cosim.log.appender import MessageAppender

    n_ch = 40

    def write(bulk: bool) -> bytes:
        rng = np.random.default_rng(3)
        buf = io.BytesIO()
        w = Writer(buf, chunk_size=3000, compression=CompressionType.ZSTD)
        w.start(profile="", library="test")
        sid = w.register_schema(name="s", encoding="ros2msg", data=b"")
        other = w.register_channel(topic="/o", message_encoding="cdr", schema_id=sid)
        ids = [w.register_channel(topic=f"/r{k}", message_encoding="cdr", schema_id=sid)
               for k in range(n_ch)]
        app = MessageAppender(w, level=3)
        assert app.add != app._slow
        seq = 0
        for tick in range(30):
            t = 10_000_000 * tick
            seq += 1
            app.add(other, t, b"o" * int(rng.integers(1, 400)), seq)
            L = int(rng.integers(1, 200))
            rows = rng.integers(0, 256, (n_ch, L), dtype=np.uint8)
            if bulk:
                app.add_rows(ids, t, rows, seq + 1)
            else:
                for r in range(n_ch):
                    app.add(ids[r], t, rows[r].tobytes(), seq + 1 + r)
            seq += n_ch
        w.finish()
        return buf.getvalue()

    def parts(data):
        chunks, indexes = [], set()
        for rec in StreamReader(io.BytesIO(data), skip_magic=False, emit_chunks=True).records:
            if isinstance(rec, Chunk):
                chunks.append(bytes(rec.data))
            elif isinstance(rec, MessageIndex):
                indexes.add((len(chunks), rec.channel_id, tuple(rec.records)))
        return chunks, indexes

    one, bulk = write(False), write(True)
    c1, i1 = parts(one)
    c2, i2 = parts(bulk)
    assert len(c1) > 10 and c1 == c2 and i1 == i2
    r = make_reader(io.BytesIO(bulk))
    for k in (0, 17, n_ch - 1):
        got = [m.log_time for _, _, m in r.iter_messages(topics=[f"/r{k}"])]
        assert got == [10_000_000 * t for t in range(30)]


def test_error_colors_is_the_formula():
    """error_colors against its definition evaluated with math.log10 (another log10: equal
    within a few ulps, not to the bit), the clipping and the special values exactly, and
    error_color of one value is error_colors' row."""
    rng = np.random.default_rng(4)
    e = np.concatenate((10.0 ** rng.uniform(-4, 0.5, 2000),
                        [0.0, -1.0, 1e-5, fg.ERR_LO, 2e-4, 0.1, 1.0, fg.ERR_HI, 5.0, np.nan,
                         np.inf, -np.inf]))
    got = fg.error_colors(e)
    assert got.shape == (len(e), 3) and (got[:, 2] == 0.2).all()
    assert np.array_equal(got[:, 1], 1.0 - got[:, 0])
    span = math.log10(fg.ERR_HI / fg.ERR_LO)
    for x, (r, _, _) in zip(e.tolist(), got):
        if x > fg.ERR_LO:
            assert r == pytest.approx(min(1.0, math.log10(x / fg.ERR_LO) / span), abs=1e-15), x
        else:
            assert r == (1.0 if x != x else 0.0), x
    assert got[-3:, 0].tolist() == [1.0, 1.0, 0.0]          # NaN and +inf red, −inf green
    assert fg.error_colors([]).shape == (0, 3)
    for x in (0.0, 3e-3, 0.7, np.nan):
        assert fg.error_color(x) == tuple(fg.error_colors([x])[0].tolist())


def test_unknown_encoding_is_refused(tmp_path):
    sc = load_scenario(PAPER, ["simulation.duration=0.01"])
    with pytest.raises(Se3SyncError, match="log encoding 'xml'"):
        McapLogger(tmp_path / "x.mcap", sc, encoding="xml")
    assert not (tmp_path / "x.mcap").exists()
    p = subprocess.run([sys.executable, "-m", "cosim.cli", "run", str(PAPER), "--duration",
                        "0.01", "--log", str(tmp_path / "y.mcap"), "--log-encoding", "xml"],
                       capture_output=True, text=True)
    assert p.returncode == 2
    assert "--log-encoding" in p.stderr.strip().splitlines()[-1]
    assert not (tmp_path / "y.mcap").exists()


def test_run_cli_writes_a_cdr_log(tmp_path):
    out = tmp_path / "c.mcap"
    p = subprocess.run([sys.executable, "-m", "cosim.cli", "run", str(PAPER), "--duration",
                        "0.2", "--log", str(out), "--log-encoding", "cdr"],
                       capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    log = read_log(out)
    assert log["metadata"]["log_encoding"] == "cdr"
    tf = log["messages"]["/tf"]
    assert len(tf) == 20 and len(tf[0][1]["transforms"]) == 6
    assert tf[-1][1]["transforms"][0]["timestamp"] == {"sec": 0, "nsec": tf[-1][0]}


def test_cdr_chunks_carry_zstds_checksum_instead_of_crc32(tmp_path):
    """A CDR log's chunks are checked by zstd's frame checksum (verified on decompression)
    rather than MCAP's CRC-32 of the uncompressed chunk (0: not computed): the integrity check
    stays, at a fraction of the cost. A JSON log keeps the CRC-32."""
    import zlib

    import zstandard

    sc = load_scenario(PAPER, ["simulation.duration=0.3"])
    for enc in ("json", "cdr"):
        chunks = []
        with open(_log(tmp_path, sc, enc), "rb") as f:
            for rec in StreamReader(f, skip_magic=False, emit_chunks=True).records:
                if isinstance(rec, Chunk):
                    chunks.append(rec)
        assert chunks
        for c in chunks:
            data = zstandard.ZstdDecompressor().decompress(c.data,
                                                           max_output_size=c.uncompressed_size)
            has = zstandard.get_frame_parameters(c.data).has_checksum
            if enc == "cdr":
                assert has and c.uncompressed_crc == 0
            else:
                assert not has and c.uncompressed_crc == zlib.crc32(data)
    bad = bytearray(c.data)
    bad[-2] ^= 0xFF   # inside the checksum: only the check itself can notice
    with pytest.raises(zstandard.ZstdError):
        zstandard.ZstdDecompressor().decompress(bytes(bad), max_output_size=c.uncompressed_size)


def test_layout_plots_fields_the_cdr_messages_have(tmp_path):
    """Every path a CDR log's Foxglove layout plots resolves in the messages as Foxglove sees
    them (ROS 2 names: /lyapunov.v, not .V), and so does the JSON layout in the JSON log."""
    import json
    import re

    sc = load_scenario(PAPER, ["simulation.duration=0.1"])
    for enc in ("json", "cdr"):
        path = _log(tmp_path, sc, enc)
        layout = json.loads(read_log(path)["attachments"]["foxglove_layout.json"])
        plotted = [p["value"] for k, c in layout["configById"].items() if k.startswith("Plot!")
                   for p in c["paths"]]
        last = {}
        with open(path, "rb") as f:
            for schema, channel, msg in make_reader(f).iter_messages():
                if channel.message_encoding == "cdr":
                    last[channel.topic] = _raw(cdr._codec(schema.name)[1](msg.data))
                else:
                    last[channel.topic] = json.loads(msg.data)
        assert len(plotted) == 2 * sc.graph.M + 1
        for p in plotted:
            topic, rest = p.split(".", 1)
            node = last[topic]
            for name, idx in re.findall(r"([A-Za-z_]+)(?:\[(\d+)\])?", rest):
                node = node[name]
                if idx:
                    node = node[int(idx)]
            assert isinstance(node, float), (enc, p)


def test_read_log_decodes_only_the_topics_asked_for(tmp_path):
    sc = load_scenario(PAPER, ["simulation.duration=0.2"])
    for enc in ("json", "cdr"):
        path = _log(tmp_path, sc, enc)
        whole = read_log(path)
        part = read_log(path, topics=("/edges", "/jumps", "/nothing"))
        assert set(part["messages"]) == {"/edges"} | ({"/jumps"} & set(whole["messages"]))
        assert part["messages"]["/edges"] == whole["messages"]["/edges"]
        assert part["metadata"] == whole["metadata"] and part["attachments"] == whole["attachments"]


def test_a_torn_cdr_log_reads_to_its_last_whole_chunk(tmp_path):
    """A CDR log cut anywhere (a killed run) reads back as the whole log's first messages of
    each topic, flagged truncated: no message is made from part of a chunk."""
    sc = load_scenario(PAPER, ["simulation.duration=1.0"])
    path = _log(tmp_path, sc, "cdr", chunk_size=20_000)
    whole = read_log(path)
    assert not whole["truncated"]
    data = path.read_bytes()
    cut_path = tmp_path / "cut.mcap"
    seen = []
    for frac in (0.2, 0.35, 0.5, 0.65, 0.8, 0.95):
        cut_path.write_bytes(data[:int(len(data) * frac)])
        part = read_log(cut_path)
        assert part["truncated"] and part["metadata"] == whole["metadata"]
        n = {t: len(m) for t, m in part["messages"].items()}
        for topic, msgs in part["messages"].items():
            assert repr(msgs) == repr(whole["messages"][topic][:len(msgs)]), (frac, topic)
        seen.append(sum(n.values()))
    total = sum(len(m) for m in whole["messages"].values())
    assert seen == sorted(set(seen)) and seen[0] < total / 4 and seen[-1] <= total
