"""MCAP logs of a run: JSON messages on JSON-schema channels that Foxglove understands.

Channels (log time = nanoseconds of SIMULATED time in co-simulation, see the ``se3sync``
metadata record's ``time_base``):

- ``/tf``        foxglove.FrameTransforms: every agent's pose, parent "world", child "agent_i"
- ``/edges``     se3sync.Edges: per edge θ, μ_U, ‖I − R̄‖_F, ‖p̄‖, U and mode ("flow"/"jump")
- ``/agents``    se3sync.Agents: per agent ω, v (body frame), torque τ, force f
- ``/lyapunov``  se3sync.Lyapunov: V̄ and k_X ΣU
- ``/jumps``     se3sync.Jump: one message per jump, never decimated
- ``/link/stats`` se3sync.LinkStats: link statistics of a hardware plant, 1 Hz (only if any)
- ``/scene``     foxglove.SceneUpdate: bodies and graph edges, at ``scene_rate`` (cosim/foxglove.py)
- ``/trail/agent_i`` foxglove.PosesInFrame: agent i's recent poses, at ``scene_rate``

The foxglove.* channels carry Foxglove's published JSON schemas (cosim/foxglove_schemas/).
A Foxglove layout is attached (``foxglove_layout.json``) and written beside the log
(``LOG.layout.json``).

The file is written in chunks as the run goes (the summary section only on close), so the
messages of the complete chunks of a killed process stay readable by a streaming reader.
"""
from __future__ import annotations

import json
import math
import os
import struct
import time
import zlib
from itertools import chain
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import zstandard
from mcap.records import (Attachment, Channel, Chunk, ChunkIndex, Message, MessageIndex, Metadata,
                          Schema, Statistics)
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, IndexType, Writer

from controller import __version__
from controller import layout
from controller.errors import Se3SyncError

from ..files import atomic_path
from ..guards import outcome_metadata
from . import cdr
from . import foxglove as fg

__all__ = ["McapLogger", "SCHEMAS", "ENCODINGS", "read_log"]

TIME = {"type": "object", "title": "time",
        "properties": {"sec": {"type": "integer", "minimum": 0},
                       "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999}}}
VEC3 = {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3}

FRAME_TRANSFORMS = {
    "title": "foxglove.FrameTransforms",
    "description": "An array of FrameTransform messages",
    "type": "object",
    "properties": {
        "transforms": {
            "type": "array",
            "items": {
                "title": "foxglove.FrameTransform",
                "description": "A transform between two reference frames in 3D space",
                "type": "object",
                "properties": {
                    "timestamp": dict(TIME, description="Timestamp of transform"),
                    "parent_frame_id": {"type": "string", "description": "Name of the parent frame"},
                    "child_frame_id": {"type": "string", "description": "Name of the child frame"},
                    "translation": {
                        "title": "foxglove.Vector3",
                        "description": "Translation component of the transform",
                        "type": "object",
                        "properties": {k: {"type": "number", "description": f"{k} coordinate length"}
                                       for k in "xyz"},
                    },
                    "rotation": {
                        "title": "foxglove.Quaternion",
                        "description": "Rotation component of the transform",
                        "type": "object",
                        "properties": {k: {"type": "number", "description": f"{k} value"}
                                       for k in "xyzw"},
                    },
                },
            },
            "description": "Array of transforms",
        }
    },
}

EDGES = {
    "title": "se3sync.Edges",
    "description": "Per-edge state of the hybrid controller at a communication point",
    "type": "object",
    "properties": {
        "timestamp": TIME,
        "edges": {"type": "array", "items": {"type": "object", "properties": {
            "edge": {"type": "integer", "description": "edge number k (from 1)"},
            "positive": {"type": "integer"}, "negative": {"type": "integer"},
            "theta": {"type": "number", "description": "θ_k after the jump stage (rad)"},
            "mu_U": {"type": "number", "description": "μ_U(X̄_k, θ_k) before any jump"},
            "rot_err": {"type": "number", "description": "‖I − R̄_k‖_F"},
            "pos_err": {"type": "number", "description": "‖p̄_k‖ (m)"},
            "U": {"type": "number", "description": "U(X̄_k, θ_k)"},
            "mode": {"type": "string", "enum": ["flow", "jump"]},
        }}},
    },
}

AGENTS = {
    "title": "se3sync.Agents",
    "description": "Per-agent body velocity and applied wrench (body frame)",
    "type": "object",
    "properties": {
        "timestamp": TIME,
        "agents": {"type": "array", "items": {"type": "object", "properties": {
            "agent": {"type": "integer"},
            "omega": dict(VEC3, description="angular velocity ω_i (rad/s)"),
            "v": dict(VEC3, description="linear velocity v_i (m/s)"),
            "torque": dict(VEC3, description="τ_i (N m)"),
            "force": dict(VEC3, description="f_i (N)"),
        }}},
    },
}

LYAPUNOV = {
    "title": "se3sync.Lyapunov",
    "type": "object",
    "properties": {"timestamp": TIME,
                   "V": {"type": "number", "description": "V̄ = k_X Σ U + Σ ξᵀ𝕀ξ"},
                   "kX_U": {"type": "number", "description": "k_X Σ_k U(X̄_k, θ_k)"}},
}

JUMP = {
    "title": "se3sync.Jump",
    "type": "object",
    "properties": {"timestamp": TIME, "t": {"type": "number"}, "edge": {"type": "integer"},
                   "theta_before": {"type": "number"}, "theta_after": {"type": "number"},
                   "mu": {"type": "number"}},
}

LINK_STATS = {"title": "se3sync.LinkStats", "type": "object",
              "properties": {"timestamp": TIME}, "additionalProperties": True}

# channels whose schema is Foxglove's published one (cosim/foxglove_schemas/), by type name
_FOXGLOVE = {"/tf": "FrameTransforms", "/scene": "SceneUpdate"}

SCHEMAS = {"/tf": FRAME_TRANSFORMS, "/edges": EDGES, "/agents": AGENTS, "/lyapunov": LYAPUNOV,
           "/jumps": JUMP, "/link/stats": LINK_STATS}

try:  # optional (extra "fastlog"): McapLogger.record_fast formats numbers with it
    import orjson as _orjson
except ImportError:  # pragma: no cover
    _orjson = None

_dumps = json.dumps
_FMT = float.__repr__

# zstd level of the log's chunks (see _MessageAppender)
ZSTD_LEVEL = 1

# zstd level of a CDR log's chunks: binary numbers compress little. On the chunks of a 1000-agent
# run (51 MB): level 1 2.00× in 118 ms, -3 1.88× in 51 ms, -7 1.82× in 39 ms, -20 1.66× in 27 ms
CDR_ZSTD_LEVEL = -7

# the message encodings of the per-record channels: JSON text, or ROS 2 CDR (cosim/log/cdr.py)
ENCODINGS = ("json", "cdr")


class _CdrRecords:
    """The /tf, /edges, /agents and /lyapunov layouts of a CDR log (cdr.compile_layout): the
    messages `McapLogger.record` writes in JSON, with the same names and numbers."""

    def __init__(self, aid, eid, edge_list):
        xyz, xyzw = "xyz", "xyzw"
        S = cdr.SCHEMA
        self.tf = cdr.compile_layout(S["/tf"], lambda f, t, m: {"transforms": [
            {"timestamp": t(), "parent_frame_id": "world", "child_frame_id": f"agent_{i}",
             "translation": {k: f() for k in xyz}, "rotation": {k: f() for k in xyzw}}
            for i in aid]})
        self.edges = cdr.compile_layout(S["/edges"], lambda f, t, m: {"timestamp": t(), "edges": [
            {"edge": eid[k], "positive": aid[a - 1], "negative": aid[b - 1], "theta": f(),
             "mu_u": f(), "rot_err": f(), "pos_err": f(), "u": f(), "mode": m()}
            for k, (a, b) in enumerate(edge_list)]})
        self.agents = cdr.compile_layout(S["/agents"], lambda f, t, m: {
            "timestamp": t(), "agents": [
                {"agent": i, **{k: [f(), f(), f()] for k in ("omega", "v", "torque", "force")}}
                for i in aid]})
        self.lyapunov = cdr.compile_layout(S["/lyapunov"], lambda f, t, m: {
            "timestamp": t(), "v": f(), "kx_u": f()})


class _MessageIndex(MessageIndex):
    """mcap's MessageIndex record, written with one pack for the whole record instead of two
    calls per entry (a chunk of 1000 trail channels has 1000 of them): the same bytes."""

    def write(self, stream):
        n = 16 * len(self.records)
        stream.write(struct.pack("<BQHI", 0x07, 6 + n, self.channel_id, n))
        if n:
            stream.write(np.asarray(self.records, dtype="<u8").tobytes())


class _Counted:
    """The log file as mcap's writer sees it: ``tell`` counts the bytes written instead of
    asking the OS (lseek, twice per chunk, and a wait for the GIL after each)."""

    def __init__(self, f):
        self._f, self._pos = f, f.tell()

    def write(self, data):
        n = self._f.write(data)
        self._pos += n
        return n

    def tell(self):
        return self._pos

    def flush(self):
        self._f.flush()


def _map_bytes(keys, vals) -> bytes:
    """An MCAP map<uint16, uint64> (its byte length, then the pairs)."""
    m = np.empty(len(keys), np.dtype([("k", "<u2"), ("v", "<u8")]))
    m["k"], m["v"] = keys, vals
    return struct.pack("<I", 10 * len(keys)) + m.tobytes()


class _Channel(Channel):
    """mcap's Channel record written with one pack: the summary section repeats every channel
    (1000 trails) and mcap writes each field through its own call."""

    def write(self, stream):
        t, e = self.topic.encode(), self.message_encoding.encode()
        meta = b"".join(struct.pack(f"<I{len(k)}sI{len(v)}s", len(k), k, len(v), v)
                        for k, v in ((k.encode(), v.encode()) for k, v in self.metadata.items()))
        body = struct.pack(f"<HHI{len(t)}sI{len(e)}sI", self.id, self.schema_id, len(t), t,
                           len(e), e, len(meta)) + meta
        stream.write(struct.pack("<BQ", 0x04, len(body)) + body)


class _Statistics(Statistics):
    """mcap's Statistics record with its per-channel message counts packed at once."""

    def write(self, stream):
        c = self.channel_message_counts
        body = struct.pack("<QHIIIIQQ", self.message_count, self.schema_count,
                           self.channel_count, self.attachment_count, self.metadata_count,
                           self.chunk_count, self.message_start_time, self.message_end_time
                           ) + _map_bytes(list(c), list(c.values()))
        stream.write(struct.pack("<BQ", 0x0B, len(body)) + body)


class _ChunkIndex(ChunkIndex):
    """mcap's ChunkIndex record with its channel → offset map packed at once: the same bytes
    (a chunk of a CDR log's trails maps 1000 channels, written by mcap one field at a time when
    the file is finished)."""

    def write(self, stream):
        offs = self.message_index_offsets
        c = self.compression.encode()
        body = (struct.pack("<QQQQ", self.message_start_time, self.message_end_time,
                            self.chunk_start_offset, self.chunk_length)
                + _map_bytes(list(offs), list(offs.values()))
                + struct.pack(f"<QI{len(c)}sQQ", self.message_index_length, len(c), c,
                              self.compressed_size, self.uncompressed_size))
        stream.write(struct.pack("<BQ", 0x08, len(body)) + body)


class _PackedRecord:
    """A summary-section record (a chunk index) kept as its bytes until the file is finished:
    a long log has one per chunk (16,000 for a 467 MB log), and as mcap's objects with their
    channel → offset dicts they held ~2.3 KB each, the run's memory growing with the log."""

    __slots__ = ("data",)

    def __init__(self, record):
        parts = []
        record.write(_Sink(parts.append))
        self.data = b"".join(parts)

    def write(self, stream):
        stream.write(self.data)


class _Sink:
    __slots__ = ("write",)

    def __init__(self, write):
        self.write = write


class _MessageAppender:
    """``add(channel_id, log_time, data, sequence)``: what ``Writer.add_message(channel_id,
    log_time, data, log_time, sequence)`` does, the same bytes in the same file, at ~1/10 of the
    cost. Why our own: mcap's writer builds a Message object and writes each field through its
    own call (≈ 24 µs per message, most of a record's cost at N = 6); here one struct.pack writes
    the record header into the writer's current chunk and the chunk's message index, time bounds
    and the file statistics are updated as the writer does. That needs the writer's chunk builder
    and statistics (private to mcap). The first appender of a process proves it on the installed
    mcap: a small file written both ways must come out byte for byte the same (`_proven`);
    when it does not, or the writer's parts are missing (another mcap, chunking off), ``add`` is
    the writer's own add_message. `tests/test_cosim_log.py` checks both ways on a larger file.

    On the fast path the appender also finishes the writer's zstd chunks (`_finalize_chunk`,
    mcap's own steps) at zstd ``level``: mcap compresses at zstd's default level 3, and on our
    JSON level 1 is 2.2× faster and compresses better (4.39 against 4.01 on a 1000-agent run's
    132 MB; benchmarks/bench_fastloop.py), which matters because compression is the largest
    part of a record at N = 1000. At level 3 the file is mcap's, byte for byte."""

    _HDR = struct.Struct("<BQHIQQ")   # opcode 0x05, record length, channel, sequence, log, publish

    def __init__(self, writer, level: int = ZSTD_LEVEL, frame_checksum: bool = False):
        self._w = writer
        cb = getattr(writer, "_Writer__chunk_builder", None)
        st = getattr(writer, "_Writer__statistics", None)
        size = getattr(writer, "_Writer__chunk_size", None)
        flush = getattr(writer, "_Writer__finalize_chunk", None)
        ok = (cb is not None and st is not None and isinstance(size, int) and callable(flush)
              and all(hasattr(cb, a) for a in ("message_indices", "record_writer",
                                                "num_messages", "message_start_time",
                                                "message_end_time"))
              and hasattr(cb.record_writer, "_buffer")
              and all(hasattr(st, a) for a in ("message_count", "message_start_time",
                                                "message_end_time", "channel_message_counts")))
        if not ok or not _proven():
            self.add = self._slow
            return
        self._cb, self._st, self._size, self._finalize = cb, st, size, flush
        # the summary's statistics and channels (the channels made so far) written faster
        if type(st) is Statistics:
            st.__class__ = _Statistics
        for ch in getattr(writer, "_Writer__channels", {}).values():
            if type(ch) is Channel:
                ch.__class__ = _Channel
        if getattr(writer, "_Writer__compression", None) == CompressionType.ZSTD:
            self._own_chunks(level, frame_checksum)

    def _own_chunks(self, level, frame_checksum=False):
        """From now on the writer's chunks are finished by `_finalize_chunk` at zstd ``level``
        (an instance attribute shadows the name-mangled method: add_message, finish and flush
        all call it), and compressed on a thread of their own: a chunk is compressed while the
        messages of the next one are encoded, and written when that one is finished (or by
        finish/flush). The file's bytes do not depend on the thread's timing: chunk k is always
        written by the call that finishes chunk k + 1."""
        w = self._w
        # frame_checksum: each chunk's zstd frame carries zstd's own checksum of its content
        # (XXH64, checked by every zstd decoder) and the chunk's CRC-32 is 0 ("not computed",
        # as MCAP allows): on 50 MB per simulated second of a CDR log, CRC-32 took 15-23 ms of
        # the compression thread's 75-110 ms
        zc = zstandard.ZstdCompressor(level=level, write_checksum=frame_checksum)
        crcs = bool(w._Writer__enable_crcs) and not frame_checksum

        def pack(data):   # zstd and zlib release the GIL on large buffers
            return zc.compress(data), (zlib.crc32(data) if crcs else 0)

        self._pack = pack
        self._stretches = []   # add_rows' messages of the current chunk (see _row_indexes)
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="se3sync-zstd")
        self._pending = None
        finish, flush = w.finish, w.flush

        def finish_all():
            self._finalize_chunk()
            self._drain()
            self._pool.shutdown(wait=True)
            finish()

        def flush_all():
            self._finalize_chunk()
            self._drain()
            flush()

        w._Writer__finalize_chunk = self._finalize = self._finalize_chunk
        w.finish, w.flush = finish_all, flush_all

    def close(self):
        """Stops the compression thread of a writer that will not be finished (a discarded
        log); a finished writer has stopped it already."""
        pool = getattr(self, "_pool", None)
        if pool is not None:
            self._pending = None
            pool.shutdown(wait=True)

    def _finalize_chunk(self):
        """mcap's Writer.__finalize_chunk (mcap 1.x): the chunk's bytes and indexes are taken
        here and the chunk builder reset; compressing and writing are `_write`'s."""
        cb = self._cb
        if cb.num_messages == 0:
            return
        self._st.chunk_count += 1
        data = cb.end()
        job = (self._pool.submit(self._pack, data), len(data), cb.message_start_time,
               cb.message_end_time, list(cb.message_indices.items()), self._stretches)
        self._stretches = []
        cb.reset()
        prev, self._pending = self._pending, job
        if prev is not None:
            self._write(prev)

    def _drain(self):
        prev, self._pending = self._pending, None
        if prev is not None:
            self._write(prev)

    def _write(self, job):
        """The chunk record, its message indexes and its chunk index, as mcap writes them."""
        w = self._w
        fut, size, t0, t1, indices, stretches = job
        packed, crc = fut.result()
        flush, rb = w._Writer__flush, w._Writer__record_builder
        flush()
        start = w._Writer__stream.tell()
        if w._Writer__enable_data_crcs:   # the data section's CRC is kept by mcap's flush
            Chunk(compression="zstd", data=packed, message_start_time=t0, message_end_time=t1,
                  uncompressed_crc=crc, uncompressed_size=size).write(rb)
            length = rb.count
        else:   # Chunk.write's bytes, the compressed data written as it is, not copied
            hdr = struct.pack("<BQQQQII4sQ", 0x06, 44 + len(packed), t0, t1, size, crc, 4,
                              b"zstd", len(packed))
            w._Writer__stream.write(hdr)
            w._Writer__stream.write(packed)
            length = len(hdr) + len(packed)
        index = _ChunkIndex(message_start_time=t0, message_end_time=t1, chunk_start_offset=start,
                           chunk_length=length, message_index_offsets={},
                           message_index_length=0, compression="zstd",
                           compressed_size=len(packed), uncompressed_size=size)
        flush()
        index_start = w._Writer__stream.tell()
        if w._Writer__index_types & IndexType.MESSAGE:
            # the chunk's message indexes (as _MessageIndex.write) in one write: a chunk of a
            # CDR log's trails has one per agent
            off, parts, offsets = index_start + rb.count, [], index.message_index_offsets
            for cid, idx in indices:
                recs = idx.records
                n = 16 * len(recs)
                offsets[cid] = off
                parts.append(struct.pack("<BQHI", 0x07, 6 + n, cid, n))
                parts.append(struct.pack(f"<{2 * len(recs)}Q", *chain.from_iterable(recs))
                             if len(recs) < 16 else np.asarray(recs, dtype="<u8").tobytes())
                off += 15 + n
            if stretches:
                data, offs = self._row_indexes(stretches, off)
                parts.append(data)
                offsets.update(offs)
            rb.write(b"".join(parts))
        index.message_index_length = rb.count
        flush()
        w._Writer__chunk_indices.append(_PackedRecord(index))

    def _slow(self, channel_id, log_time, data, sequence):
        self._w.add_message(channel_id, log_time, bytes(data), log_time, sequence)

    def add(self, channel_id, log_time, data, sequence):
        st, cb = self._st, self._cb
        # the file's and the chunk's time bounds, as mcap's add_message and ChunkBuilder keep
        # them; written out twice rather than through a helper: this runs once per message
        if st.message_count == 0:
            st.message_start_time = log_time
        elif log_time < st.message_start_time:
            st.message_start_time = log_time
        if log_time > st.message_end_time:
            st.message_end_time = log_time
        st.channel_message_counts[channel_id] += 1
        st.message_count += 1
        if cb.num_messages == 0:
            cb.message_start_time = log_time
        elif log_time < cb.message_start_time:
            cb.message_start_time = log_time
        if log_time > cb.message_end_time:
            cb.message_end_time = log_time
        buf = cb.record_writer._buffer   # a new buffer after every chunk
        idx = cb.message_indices.get(channel_id)
        if not idx:
            idx = cb.message_indices[channel_id] = _MessageIndex(channel_id=channel_id, records=[])
        idx.records.append((log_time, buf.tell()))
        cb.num_messages += 1
        buf.write(self._HDR.pack(0x05, 22 + len(data), channel_id, sequence, log_time, log_time))
        buf.write(data)
        if buf.tell() > self._size:
            self._finalize()

    _IDX_DT = np.dtype([("op", "u1"), ("len", "<u8"), ("ch", "<u2"), ("n", "<u4")])
    _ENT_DT = np.dtype([("t", "<u8"), ("o", "<u8")])
    _ONE_DT = np.dtype([("op", "u1"), ("len", "<u8"), ("ch", "<u2"), ("n", "<u4"), ("t", "<u8"),
                        ("o", "<u8")])

    @classmethod
    def _row_indexes(cls, stretches, base):
        """The message index records of the messages `add_rows` put in a chunk, built at once:
        ``stretches`` are (channel ids, first offset, record length, log time), one channel
        at most once per stretch; records start at file offset ``base``. Returns their bytes
        and {channel: offset}: what _MessageIndex.write gives for each channel, entries in
        the order they were added."""
        if len(stretches) == 1:   # the usual case: each channel once, one 31-byte record each
            c, o, s, t = stretches[0]
            n = len(c)
            rec = np.empty(n, cls._ONE_DT)
            rec["op"], rec["len"], rec["ch"], rec["n"] = 0x07, 22, c, 16
            rec["t"], rec["o"] = t, o + s * np.arange(n, dtype=np.int64)
            return rec.tobytes(), dict(zip(c, range(base, base + 31 * n, 31)))
        cids = np.concatenate([np.asarray(c, np.int64) for c, _, _, _ in stretches])
        offs = np.concatenate([o + s * np.arange(len(c), dtype=np.int64)
                               for c, o, s, _ in stretches])
        ts = np.concatenate([np.full(len(c), t, np.int64) for c, _, _, t in stretches])
        order = np.argsort(cids, kind="stable")
        ch, first, count = np.unique(cids[order], return_index=True, return_counts=True)
        size = 15 + 16 * count
        start = np.concatenate(([0], np.cumsum(size)[:-1]))
        out = np.empty(int(size.sum()), np.uint8)
        hdr = np.empty(len(ch), cls._IDX_DT)
        hdr["op"], hdr["len"], hdr["ch"], hdr["n"] = 0x07, 6 + 16 * count, ch, 16 * count
        out[(start[:, None] + np.arange(15)).ravel()] = hdr.view(np.uint8)
        ent = np.empty(len(cids), cls._ENT_DT)
        ent["t"], ent["o"] = ts[order], offs[order]
        rank = np.repeat(np.arange(len(ch)), count)
        pos = start[rank] + 15 + 16 * (np.arange(len(cids)) - first[rank])
        out[(pos[:, None] + np.arange(16)).ravel()] = ent.view(np.uint8)
        return out.tobytes(), dict(zip(ch.tolist(), (base + start).tolist()))

    _HDR_DT = np.dtype([("op", "u1"), ("len", "<u8"), ("ch", "<u2"), ("seq", "<u4"),
                        ("log", "<u8"), ("pub", "<u8")])   # packed: _HDR's 31 bytes

    def add_rows(self, channel_ids, log_time, rows, sequence):
        """``add(channel_ids[r], log_time, rows[r].tobytes(), sequence + r)`` for each row of
        the uint8 array ``rows`` (messages of one length, e.g. the trails of a CDR log): the
        same bytes, chunks cut at the same messages, but one write per stretch of a chunk."""
        n, L = rows.shape
        if n == 0:
            return
        if self.add == self._slow or getattr(self, "_pool", None) is None:
            for r in range(n):
                self._slow(channel_ids[r], log_time, rows[r].tobytes(), sequence + r)
            return
        hdr = np.zeros(n, self._HDR_DT)
        hdr["op"], hdr["len"], hdr["ch"] = 0x05, 22 + L, channel_ids
        hdr["seq"] = np.arange(sequence, sequence + n) & 0xFFFFFFFF
        hdr["log"] = hdr["pub"] = log_time
        recs = np.empty((n, 31 + L), np.uint8)
        recs[:, :31] = hdr.view(np.uint8).reshape(n, 31)
        recs[:, 31:] = rows
        st = self._st
        if st.message_count == 0 or log_time < st.message_start_time:
            st.message_start_time = log_time
        if log_time > st.message_end_time:
            st.message_end_time = log_time
        counts = st.channel_message_counts
        for c in channel_ids:
            counts[c] += 1
        st.message_count += n
        size, step, r = self._size, 31 + L, 0
        while r < n:
            cb = self._cb
            if cb.num_messages == 0 or log_time < cb.message_start_time:
                cb.message_start_time = log_time
            if log_time > cb.message_end_time:
                cb.message_end_time = log_time
            buf = cb.record_writer._buffer
            pos = buf.tell()
            # add() finishes the chunk after the first message that ends past `size`
            k = n - r if pos + (n - r) * step <= size else min(n - r, (size - pos) // step + 1)
            # their message indexes are made with the chunk's (_row_indexes)
            self._stretches.append((channel_ids[r:r + k], pos, step, log_time))
            cb.num_messages += k
            buf.write(recs[r:r + k].data)
            r += k
            if buf.tell() > size:
                self._finalize()


_PROOF = []


def _proven() -> bool:
    """Whether `_MessageAppender.add` and its `_finalize_chunk` (at mcap's zstd level 3) write
    what mcap's own add_message writes, on the mcap installed: three channels, chunk
    boundaries and out-of-order times, written both ways (once per process, ~2 ms)."""
    if not _PROOF:
        import io

        def write(fast):
            buf = io.BytesIO()
            w = Writer(buf, chunk_size=600, compression=CompressionType.ZSTD)
            w.start(profile="", library="proof")
            sid = w.register_schema(name="s", encoding="jsonschema", data=b"{}")
            ch = [w.register_channel(topic=f"/{k}", message_encoding="json", schema_id=sid)
                  for k in range(3)]
            app = _MessageAppender.__new__(_MessageAppender)
            app._w = w
            if fast:
                app._cb, app._st = w._Writer__chunk_builder, w._Writer__statistics
                app._size, app._finalize = w._Writer__chunk_size, w._Writer__finalize_chunk
                app._own_chunks(3)   # mcap's level: the chunks must be its bytes too
            for q in range(40):
                t = (q * 7919) % 23 * 1000 + q
                data = bytes(range(q % 7 * 37 % 256)) * (1 + q % 3)
                (app.add if fast else app._slow)(ch[q % 3], t, data, q + 1)
            w.finish()
            return buf.getvalue()

        try:
            _PROOF.append(write(True) == write(False))
        except Exception:  # mcap's internals are not what the appender expects
            _PROOF.append(False)
    return _PROOF[0]


def _with_modes(vals, jumped, flow, jump) -> list:
    """An /edges record's values (five per edge) with each edge's mode after its five."""
    out = []
    for q, j in enumerate(jumped):
        out += vals[5 * q:5 * q + 5]
        out.append(jump if j else flow)
    return out


def _r(x: float) -> str:
    """A float as JSON (repr is shortest round-trip; non-finite values become null)."""
    s = _FMT(x)
    return s if s[-1].isdigit() else "null"


class McapLogger:
    """Streams a run to an MCAP file.

    ``McapLogger(path, scenario, controller="hybrid", model_description=None,
    chunk_size=256 KiB)``; call ``record(...)``, ``jump(...)``, ``link_stats(...)`` and finally
    ``close()`` (also a context manager).

    ``scene_rate`` (Hz of simulated time, 0 = off) is the rate of the /scene and /trail
    messages, ``trail_seconds`` the length of a trail and ``trail_rate`` (Hz) the spacing of its
    kept poses (each message adds the current pose); ``layout_path`` is where the Foxglove
    layout is written ("auto": beside the log as LOG.layout.json; None: not written).

    ``agent_ids`` and ``edge_ids`` name the scenario's agents and edges in the messages (frames
    ``agent_<id>``, ``"edge": <id>``, the scene's entities, the trails' topics and the jumps)
    when they are part of a larger swarm (an agent process logs its own neighbourhood with the
    swarm's numbers); by default they are 1..N and 1..M. `jump` takes the edge's position
    (1..M) and writes its id.
    """

    def __init__(self, path, scenario, controller: str = "hybrid", model_description=None,
                 chunk_size: int = 256 * 1024, extra_metadata: dict | None = None,
                 scene_rate: float = 20.0, trail_seconds: float = 5.0, trail_rate: float = 5.0,
                 layout_path="auto", agent_ids=None, edge_ids=None, encoding: str = "json",
                 sink=None):
        if encoding not in ENCODINGS:
            raise Se3SyncError(f"log encoding {encoding!r}: expected one of "
                               f"{', '.join(ENCODINGS)}")
        self.encoding = encoding
        self._cdr = None   # the CDR record layouts (encoding "cdr"), made below
        self.path = str(path)
        n, M = scenario.graph.n, scenario.graph.M
        aid = list(range(1, n + 1)) if agent_ids is None else [int(x) for x in agent_ids]
        eid = list(range(1, M + 1)) if edge_ids is None else [int(x) for x in edge_ids]
        if len(aid) != n or len(eid) != M:
            raise Se3SyncError(f"McapLogger: {len(aid)} agent ids for {n} agents, {len(eid)} edge "
                               f"ids for {M} edges")
        self._aid, self._eid = aid, eid
        self._f = open(self.path, "wb")
        try:
            self._w = w = Writer(_Counted(self._f), chunk_size=chunk_size,
                                 compression=CompressionType.ZSTD)
            w.start(profile="", library=f"se3sync {__version__}")
            self._ch = {}
            self._schema_ids = {}
            # channel id → (topic, message encoding, schema id); schema id → (name, encoding,
            # bytes): what a `sink` needs to describe the channels elsewhere (cosim/log/live.py)
            self.channels, self.schemas = {}, {}
            for topic in ("/tf", "/edges", "/agents", "/lyapunov", "/jumps"):
                self._channel(topic)
            meta = {
                "scenario": scenario.text,
                "scenario_name": scenario.name,
                "scenario_path": str(scenario.path),
                "overrides": json.dumps(list(scenario.overrides)),
                "design": json.dumps(scenario.design.as_dict()),
                "se3sync_version": __version__,
                "time_base": "simulated",
                "time_unit": "ns",
                "controller": controller,
                "step": repr(float(scenario.step)),
                "log_rate": repr(float(scenario.log_rate)),
                "n_agents": str(scenario.graph.n),
                "edges": json.dumps([list(e) for e in scenario.graph.edge_list]),
                "created_unix": repr(time.time()),
                "masses": json.dumps(np.asarray(scenario.masses, float).tolist()),
                "inertias": json.dumps(np.asarray(scenario.inertias, float).tolist()),
                "scene_rate": repr(float(scene_rate)),
                "log_encoding": encoding,
            }
            if agent_ids is not None or edge_ids is not None:
                meta["agent_ids"] = json.dumps(aid)
                meta["edge_ids"] = json.dumps(eid)
            if extra_metadata:
                meta.update({str(k): str(v) for k, v in extra_metadata.items()})
            w.add_metadata("se3sync", meta)
            if model_description:
                data = model_description.encode() if isinstance(model_description, str) else bytes(model_description)
                w.add_attachment(create_time=time.time_ns(), log_time=0,
                                 name="modelDescription.xml", media_type="application/xml",
                                 data=data)
            self._layout = fg.layout_json(aid, eid, encoding)
            w.add_attachment(create_time=time.time_ns(), log_time=0, name="foxglove_layout.json",
                             media_type="application/json", data=self._layout.encode())
            self._scene = None
            if scene_rate and scene_rate > 0:
                self._scene = fg.SceneBuilder(
                    [list(e) for e in scenario.graph.edge_list], np.asarray(scenario.inertias, float),
                    np.asarray(scenario.masses, float),
                    trail_len=max(1, int(round(trail_seconds * min(trail_rate, scene_rate)))),
                    agent_ids=aid, edge_ids=eid)
                self._channel(fg.SCENE)
                for i in aid:
                    self._channel(f"{fg.TRAIL_PREFIX}{i}")
            if encoding == "cdr":
                self._cdr = _CdrRecords(aid, eid, scenario.graph.edge_list)
                self._cdr_scene = None if self._scene is None else fg.CdrScene(
                    self._scene, np.asarray(scenario.inertias, float),
                    np.asarray(scenario.masses, float))
        except BaseException:
            self._f.close()
            raise
        self._seq = 0
        self._closed = False
        self._agent_names = [f"agent_{i}" for i in aid]
        self._tf_pre = [f'{{"timestamp":%s,"parent_frame_id":"world","child_frame_id":"agent_{i}",'
                        for i in aid]
        self._edge_pre = [f'{{"edge":{eid[k]},"positive":{aid[a - 1]},"negative":{aid[b - 1]},'
                          for k, (a, b) in enumerate(scenario.graph.edge_list)]
        # ``sink``: an object with the appender's add(channel_id, log_time, data, sequence),
        # add_rows(channel_ids, log_time, rows, sequence) and close() that takes the messages
        # instead of the file (the live view encodes its records with this class)
        self._app = (sink if sink is not None else _MessageAppender(w) if encoding == "json"
                     else _MessageAppender(w, CDR_ZSTD_LEVEL, frame_checksum=True))
        self._add = self._app.add
        self.counts = {}
        self.orjson = True  # record_fast may use orjson (False: the bytes of `record`)
        self._scene_dt = round(1e9 / scene_rate) if scene_rate and scene_rate > 0 else 0
        self._next_scene = 0
        self._trail_dt = round(1e9 / trail_rate) if trail_rate and trail_rate > 0 else 0
        self._next_trail = 0
        self._jump_until = [-1] * scenario.graph.M  # edge k is drawn as jumping until this t_ns
        self._trail_topics = [f"{fg.TRAIL_PREFIX}{i}" for i in aid]
        self._trail_ids = [self._ch.get(t) for t in self._trail_topics]
        self._layout_path = None
        if layout_path == "auto":
            p = Path(self.path)
            layout_path = p.with_name(p.name[:-5] if p.name.endswith(".mcap") else p.name)
            layout_path = layout_path.with_name(layout_path.name + ".layout.json")
        if layout_path is not None:
            self._layout_path = Path(layout_path)

    def _register(self, topic, name, schema_encoding, data, message_encoding):
        """The channel ``topic`` on the schema ``name``, registered once per name (``data()``
        gives its bytes)."""
        sid = self._schema_ids.get(name)
        if sid is None:
            b = data()
            sid = self._schema_ids[name] = self._w.register_schema(
                name=name, encoding=schema_encoding, data=b)
            self.schemas[sid] = (name, schema_encoding, b)
        cid = self._ch[topic] = self._w.register_channel(
            topic=topic, message_encoding=message_encoding, schema_id=sid)
        self.channels[cid] = (topic, message_encoding, sid)

    def _channel(self, topic):
        if topic in self._ch:
            return self._ch[topic]
        trail = topic.startswith(fg.TRAIL_PREFIX)
        name = cdr.SCHEMA.get("trail" if trail else topic) if self.encoding == "cdr" else None
        if name is not None:   # a CDR log's per-record channels; /jumps and /link/stats are JSON
            self._register(topic, name, "ros2msg", lambda: cdr.schema_text(name).encode(), "cdr")
            return self._ch[topic]
        fox = _FOXGLOVE.get(topic) or ("PosesInFrame" if trail else None)
        if fox is not None:  # Foxglove's own schema, name and content as published
            name, data = f"foxglove.{fox}", lambda: fg.schema_bytes(fox)
        else:
            name, data = SCHEMAS[topic]["title"], lambda: json.dumps(SCHEMAS[topic]).encode()
        self._register(topic, name, "jsonschema", data, "json")
        return self._ch[topic]

    def add_channel(self, topic: str, schema: dict) -> None:
        """A channel of another kind of JSON message (``schema``: a JSON schema with a
        ``title``), for `message`."""
        if topic not in self._ch:
            self._register(topic, schema["title"], "jsonschema",
                           lambda: json.dumps(schema).encode(), "json")

    def message(self, topic: str, t_ns: int, obj: dict) -> None:
        """One JSON message (``obj`` plus its timestamp) on a channel made by `add_channel`."""
        ts = {"sec": t_ns // 1_000_000_000, "nsec": t_ns % 1_000_000_000}
        self._msg(topic, t_ns, _dumps(dict(obj, timestamp=ts), default=float))

    def _msg(self, topic, t_ns, payload: str):
        self._seq += 1
        self._add(self._ch[topic], t_ns, payload.encode(), self._seq)
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def record(self, t_ns: int, S, u, theta, mu, jumped, rot_err, pos_err, U, quat, V, kX_U):
        """One decimated record: /tf, /edges, /agents, /lyapunov at simulated time t_ns."""
        if self._cdr is not None:
            return self.record_block([t_ns], *(np.asarray(x)[None] for x in (
                S, u, theta, mu, jumped, rot_err, pos_err, U, quat, V, kX_U)))
        ts = f'{{"sec":{t_ns // 1_000_000_000},"nsec":{t_ns % 1_000_000_000}}}'
        Sl = S.tolist()
        ql = quat.tolist()
        ul = u.tolist()
        r = _r
        tf = ",".join(
            pre % ts + f'"translation":{{"x":{r(s[0])},"y":{r(s[1])},"z":{r(s[2])}}},'
            f'"rotation":{{"x":{r(q[0])},"y":{r(q[1])},"z":{r(q[2])},"w":{r(q[3])}}}}}'
            for pre, s, q in zip(self._tf_pre, Sl, ql))
        self._msg("/tf", t_ns, f'{{"transforms":[{tf}]}}')
        th, mul, jl, rl, pl, Ul = theta.tolist(), mu.tolist(), jumped.tolist(), rot_err.tolist(), \
            pos_err.tolist(), U.tolist()
        ed = ",".join(
            f'{pre}"theta":{r(a)},"mu_U":{r(b)},"rot_err":{r(c)},"pos_err":{r(d)},"U":{r(e)},'
            f'"mode":"{"jump" if j else "flow"}"}}'
            for pre, a, b, c, d, e, j in zip(self._edge_pre, th, mul, rl, pl, Ul, jl))
        self._msg("/edges", t_ns, f'{{"timestamp":{ts},"edges":[{ed}]}}')
        ag = ",".join(
            f'{{"agent":{i},"omega":[{r(s[12])},{r(s[13])},{r(s[14])}],'
            f'"v":[{r(s[15])},{r(s[16])},{r(s[17])}],'
            f'"torque":[{r(w[0])},{r(w[1])},{r(w[2])}],"force":[{r(w[3])},{r(w[4])},{r(w[5])}]}}'
            for i, s, w in zip(self._aid, Sl, ul))
        self._msg("/agents", t_ns, f'{{"timestamp":{ts},"agents":[{ag}]}}')
        self._msg("/lyapunov", t_ns, f'{{"timestamp":{ts},"V":{r(V)},"kX_U":{r(kX_U)}}}')
        if self._scene is not None and t_ns >= self._next_scene:
            self._next_scene = t_ns + self._scene_dt
            self.scene(t_ns, ts, S, quat, rot_err, jumped)

    def scene(self, t_ns, ts, S, quat, rot_err, jumped):
        """The /scene and /trail messages at t_ns (called by record at scene_rate). An edge is
        drawn as jumping if it jumped at this record or within one scene period before it."""
        ju = self._jump_until
        jl = jumped.tolist()
        jumping = [j or t_ns <= u for j, u in zip(jl, ju)]
        keep = t_ns >= self._next_trail
        if self._cdr is not None:
            cs = self._cdr_scene
            self._msg_bytes("/scene", t_ns, cs.scene(t_ns, S, rot_err, jumping))
            if keep:
                self._next_trail = t_ns + self._trail_dt
            rows = cs.trails(t_ns, S, quat, keep)
            self._app.add_rows(self._trail_ids, t_ns, rows, self._seq + 1)
            self._seq += len(rows)
            counts = self.counts
            for topic in self._trail_topics:
                counts[topic] = counts.get(topic, 0) + 1
            return
        self._msg("/scene", t_ns, self._scene.scene(ts, S, rot_err, jumping))
        if keep:
            self._next_trail = t_ns + self._trail_dt
        # one message per agent: `_msg` inlined (at N = 1000 the per-call cost shows)
        add, seq, counts, cids = self._add, self._seq, self.counts, self._trail_ids
        for topic, cid, m in zip(self._trail_topics, cids,
                                 self._scene.trails(ts, S, quat, keep)):
            seq += 1
            add(cid, t_ns, m.encode(), seq)
            counts[topic] = counts.get(topic, 0) + 1
        self._seq = seq

    def _templates(self):
        """%-format templates of the /tf, /edges (all edges flowing) and /agents messages with
        the timestamp as @TS@: one C-level format call per message instead of one Python
        call per value. %r of a Python float is float.__repr__, as in `record`."""
        tf = ",".join(
            f'{{"timestamp":@TS@,"parent_frame_id":"world","child_frame_id":"agent_{i}",'
            '"translation":{"x":%r,"y":%r,"z":%r},"rotation":{"x":%r,"y":%r,"z":%r,"w":%r}}'
            for i in self._aid)
        ed = ",".join(
            pre.replace("%", "%%") + '"theta":%r,"mu_U":%r,"rot_err":%r,"pos_err":%r,"U":%r,'
            '"mode":"flow"}' for pre in self._edge_pre)
        ag = ",".join(
            f'{{"agent":{i},"omega":[%r,%r,%r],"v":[%r,%r,%r],'
            '"torque":[%r,%r,%r],"force":[%r,%r,%r]}' for i in self._aid)
        # /edges of a record with a jump: each edge's mode is a sixth slot
        edj = ed.replace('"mode":"flow"}', '"mode":"%s"}')
        self._tpl = (f'{{"transforms":[{tf}]}}', f'{{"timestamp":@TS@,"edges":[{ed}]}}',
                     f'{{"timestamp":@TS@,"agents":[{ag}]}}', f'{{"timestamp":@TS@,"edges":[{edj}]}}')
        return self._tpl

    def _bytes_templates(self):
        tb = getattr(self, "_tpl_b", None)
        if tb is None:
            tpl = getattr(self, "_tpl", None) or self._templates()
            tb = self._tpl_b = tuple(t.replace("%r", "%s").encode() for t in tpl)
        return tb

    def _scene_due(self, t_ns, ts, S, quat, rot_err, jumped):
        """The /scene and /trail part of `record`, for the fast encoders."""
        if self._scene is not None and t_ns >= self._next_scene:
            self._next_scene = t_ns + self._scene_dt
            self.scene(t_ns, ts, S, quat, rot_err, jumped)

    def _msg_bytes(self, topic, t_ns, payload: bytes):
        self._seq += 1
        self._add(self._ch[topic], t_ns, payload, self._seq)
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def record_fast(self, t_ns: int, S, u, theta, mu, jumped, rot_err, pos_err, U, quat, V, kX_U):
        """`record` with the same messages, encoded through templates (the compiled loop's
        writer calls it). With orjson installed (extra "fastlog") and ``self.orjson`` true,
        the numbers are formatted by orjson's shortest round-trip printer: the messages decode
        to the same values bit for bit, but the text of some numbers differs (0.00001 for
        1e-05); without it they are the same bytes as `record`'s. A record with a jump in it
        or a non-finite value goes through `record` (rare)."""
        if self._cdr is not None:
            return self.record(t_ns, S, u, theta, mu, jumped, rot_err, pos_err, U, quat, V, kX_U)
        tf_v = np.concatenate((S[:, layout.P], quat), axis=1)
        ed_v = np.stack((theta, mu, rot_err, pos_err, U), axis=1)
        ag_v = np.concatenate((S[:, layout.XI], u), axis=1)
        if not (np.isfinite(tf_v).all() and np.isfinite(ed_v).all() and np.isfinite(ag_v).all()):
            return self.record(t_ns, S, u, theta, mu, jumped, rot_err, pos_err, U, quat, V,
                               kX_U)
        tpl = getattr(self, "_tpl", None) or self._templates()
        ts = f'{{"sec":{t_ns // 1_000_000_000},"nsec":{t_ns % 1_000_000_000}}}'
        jl = jumped.tolist() if jumped.any() else None
        if self.orjson and _orjson is not None:
            # orjson prints a whole array in C (~10× faster than float.__repr__ per value);
            # the pieces go into byte templates with %s
            tb = self._bytes_templates()
            tsb = ts.encode()
            opt = _orjson.OPT_SERIALIZE_NUMPY
            for topic, t, v in (("/tf", tb[0], tf_v), ("/edges", tb[1], ed_v),
                                ("/agents", tb[2], ag_v)):
                vals = _orjson.dumps(np.ascontiguousarray(v).ravel(), option=opt)[1:-1].split(b",")
                if topic == "/edges" and jl is not None:
                    t, vals = tb[3], _with_modes(vals, jl, b"flow", b"jump")
                self._msg_bytes(topic, t_ns, t.replace(b"@TS@", tsb) % tuple(vals))
            self._msg("/lyapunov", t_ns, f'{{"timestamp":{ts},"V":{_r(V)},"kX_U":{_r(kX_U)}}}')
            self._scene_due(t_ns, ts, S, quat, rot_err, jumped)
            return
        ed = ed_v.ravel().tolist()
        ed_msg = (tpl[1] % tuple(ed) if jl is None
                  else tpl[3] % tuple(_with_modes(ed, jl, "flow", "jump")))
        self._msg("/tf", t_ns, tpl[0].replace("@TS@", ts) % tuple(tf_v.ravel().tolist()))
        self._msg("/edges", t_ns, ed_msg.replace("@TS@", ts))
        self._msg("/agents", t_ns, tpl[2].replace("@TS@", ts) % tuple(ag_v.ravel().tolist()))
        self._msg("/lyapunov", t_ns, f'{{"timestamp":{ts},"V":{_r(V)},"kX_U":{_r(kX_U)}}}')
        self._scene_due(t_ns, ts, S, quat, rot_err, jumped)

    def jump(self, t_ns: int, t: float, edge: int, theta_before: float, theta_after: float, mu: float):
        if 1 <= edge <= len(self._jump_until):
            self._jump_until[edge - 1] = t_ns + self._scene_dt
            edge = self._eid[edge - 1]
        ts = {"sec": t_ns // 1_000_000_000, "nsec": t_ns % 1_000_000_000}
        self._msg("/jumps", t_ns, _dumps({"timestamp": ts, "t": t, "edge": edge,
                                          "theta_before": theta_before,
                                          "theta_after": theta_after, "mu": mu}))

    def record_block(self, t_ns, S, u, theta, mu, jumped, rot_err, pos_err, U, quat, V, kX_U):
        """`record_fast` for R consecutive records at once (t_ns a list of R ints, every other
        argument stacked on a first axis of length R): one orjson call per channel for the
        whole block. Rows with a non-finite value go through `record`."""
        R = len(t_ns)
        if R == 0:
            return
        if self._cdr is not None:
            return self._record_cdr(t_ns, S, u, theta, mu, jumped, rot_err, pos_err, U, quat, V,
                                    kX_U)
        if not (self.orjson and _orjson is not None):
            for r in range(R):
                self.record_fast(t_ns[r], S[r], u[r], theta[r], mu[r], jumped[r], rot_err[r],
                                 pos_err[r], U[r], quat[r], V[r], kX_U[r])
            return
        tf_v = np.concatenate((S[:, :, layout.P], quat), axis=2)
        ed_v = np.stack((theta, mu, rot_err, pos_err, U), axis=2)
        ag_v = np.concatenate((S[:, :, layout.XI], u), axis=2)
        plain = np.ones(R, np.bool_)
        for v in (tf_v, ed_v, ag_v):
            plain &= np.isfinite(v).all(axis=(1, 2))
        any_jump = jumped.any(axis=1).tolist()
        tb = self._bytes_templates()
        opt = _orjson.OPT_SERIALIZE_NUMPY
        chans = []
        for topic, t, v in (("/tf", tb[0], tf_v), ("/edges", tb[1], ed_v),
                            ("/agents", tb[2], ag_v)):
            parts = _orjson.dumps(np.ascontiguousarray(v).ravel(), option=opt)[1:-1].split(b",")
            chans.append((topic, t, parts, v.shape[1] * v.shape[2]))
        msg_b, msg, r_ = self._msg_bytes, self._msg, _r
        for r in range(R):
            tn = t_ns[r]
            if not plain[r]:
                self.record(tn, S[r], u[r], theta[r], mu[r], jumped[r], rot_err[r], pos_err[r],
                            U[r], quat[r], V[r], kX_U[r])
                continue
            ts = f'{{"sec":{tn // 1_000_000_000},"nsec":{tn % 1_000_000_000}}}'
            tsb = ts.encode()
            for topic, t, parts, k in chans:
                vals = parts[r * k:(r + 1) * k]
                if any_jump[r] and topic == "/edges":
                    t, vals = tb[3], _with_modes(vals, jumped[r].tolist(), b"flow", b"jump")
                msg_b(topic, tn, t.replace(b"@TS@", tsb) % tuple(vals))
            msg("/lyapunov", tn, f'{{"timestamp":{ts},"V":{r_(V[r])},"kX_U":{r_(kX_U[r])}}}')
            self._scene_due(tn, ts, S[r], quat[r], rot_err[r], jumped[r])

    def _record_cdr(self, t_ns, S, u, theta, mu, jumped, rot_err, pos_err, U, quat, V, kX_U):
        """`record_block` in CDR: each channel's R messages filled at once (`_CdrRecords`)."""
        c = self._cdr
        S, quat = np.asarray(S, np.float64), np.asarray(quat, np.float64)
        rows = {"/tf": c.tf.fill(np.concatenate((S[:, :, layout.P], quat), axis=2)
                                 .reshape(len(t_ns), -1), t_ns),
                "/edges": c.edges.fill(np.stack((theta, mu, rot_err, pos_err, U), axis=2)
                                       .reshape(len(t_ns), -1), t_ns,
                                       np.where(jumped, cdr.MODE["jump"], cdr.MODE["flow"])),
                "/agents": c.agents.fill(np.concatenate((S[:, :, layout.XI], u), axis=2)
                                         .reshape(len(t_ns), -1), t_ns),
                "/lyapunov": c.lyapunov.fill(np.stack((V, kX_U), axis=1), t_ns)}
        msg_b = self._msg_bytes
        for r, tn in enumerate(t_ns):
            for topic in ("/tf", "/edges", "/agents", "/lyapunov"):
                msg_b(topic, tn, rows[topic][r])   # a row of bytes: copied into the chunk
            if self._scene is not None and tn >= self._next_scene:
                self._next_scene = tn + self._scene_dt
                self.scene(tn, None, S[r], quat[r], rot_err[r], jumped[r])

    _JUMP_TPL = ('{"timestamp": {"sec": %d, "nsec": %d}, "t": %r, "edge": %d, '
                 '"theta_before": %r, "theta_after": %r, "mu": %r}')

    def jump_fast(self, t_ns: int, t: float, edge: int, theta_before: float,
                  theta_after: float, mu: float):
        """`jump` with the same message byte for byte (json.dumps's default separators and
        float repr) through one template; non-finite values go through `jump`."""
        if not (math.isfinite(t) and math.isfinite(theta_before) and math.isfinite(theta_after)
                and math.isfinite(mu)):
            return self.jump(t_ns, t, edge, theta_before, theta_after, mu)
        if 1 <= edge <= len(self._jump_until):  # as `jump`: the scene draws the edge jumping
            self._jump_until[edge - 1] = t_ns + self._scene_dt
            edge = self._eid[edge - 1]
        self._msg("/jumps", t_ns, self._JUMP_TPL % (t_ns // 1_000_000_000, t_ns % 1_000_000_000,
                                                    t, edge, theta_before, theta_after, mu))

    def link_stats(self, t_ns: int, stats: dict):
        self._channel("/link/stats")
        ts = {"sec": t_ns // 1_000_000_000, "nsec": t_ns % 1_000_000_000}
        self._msg("/link/stats", t_ns, _dumps(dict(stats, timestamp=ts), default=float))

    def outcome(self, summary: dict) -> None:
        """A metadata record ``se3sync.outcome`` with how the run ended (steps, interrupted,
        stopped_during, diverged, n_jumps, jump_bound_exceeded), written before `close`."""
        self._w.add_metadata("se3sync.outcome", outcome_metadata(summary))

    def close(self, discard: bool = False):
        """Finishes the file (and writes the layout beside it); ``discard=True`` removes the
        log instead: a run that failed leaves nothing that looks whole. A log that cannot be
        finished (OSError, e.g. a full disk) is removed too, and the error raised."""
        if self._closed:
            return
        self._closed = True
        err = None
        try:
            if not discard:
                self._w.finish()
        except OSError as exc:  # e.g. no space left: a log that cannot be finished is removed
            err, discard = exc, True
        finally:
            try:
                self._app.close()
            finally:
                try:
                    self._f.close()   # flushes the buffer: fails again on a full disk
                except OSError as exc:
                    if not discard:
                        err, discard = exc, True
        if discard:
            try:
                os.unlink(self.path)
            except OSError:
                pass
            if err is not None:
                raise err
            return
        if self._layout_path is not None:
            with atomic_path(self._layout_path) as tmp:
                Path(tmp).write_text(self._layout, encoding="utf-8")

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def read_log(path, topics=None) -> dict:
    """Reads an se3sync MCAP back: {"metadata": {...}, "attachments": {name: bytes},
    "messages": {topic: [(log_time_ns, decoded JSON), ...]}, "truncated": bool, "outcome":
    {steps, interrupted, diverged, ...} or None (`McapLogger.outcome`)}. A CDR message
    is decoded to the dict its JSON message would give (`cdr.decode`). ``topics``: decode the
    messages of these topics only (the scene and 1000 trails of a large log are most of it).

    One streaming pass (mcap's StreamReader), so a file without a summary section, or with a
    torn tail (a killed run), yields every record before the tear. Raises Se3SyncError (one
    line) when the file is unreadable or is not an se3sync log.
    """
    out = {"metadata": None, "attachments": {}, "messages": {}, "truncated": False,
           "outcome": None}
    channels, schemas = {}, {}
    n_records = 0
    try:
        f = open(path, "rb")
    except FileNotFoundError:
        raise Se3SyncError(f"{path}: no such file") from None
    except OSError as exc:
        raise Se3SyncError(f"{path}: cannot read: {exc.strerror or exc}") from None
    with f:
        try:
            for rec in StreamReader(f, skip_magic=False).records:
                n_records += 1
                if isinstance(rec, Message):
                    ch = channels.get(rec.channel_id)
                    if ch is not None:
                        topic, ros2 = ch
                        out["messages"].setdefault(topic, []).append(
                            (rec.log_time, json.loads(rec.data) if ros2 is None
                             else cdr.decode(ros2, rec.data)))
                elif isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    sch = schemas.get(rec.schema_id)
                    if rec.message_encoding == "json":
                        channels[rec.id] = (rec.topic, None)
                    elif (rec.message_encoding == "cdr" and sch is not None
                          and sch.encoding == "ros2msg" and sch.name in cdr.SCHEMA.values()):
                        channels[rec.id] = (rec.topic, sch.name)
                    if topics is not None and rec.topic not in topics:
                        channels.pop(rec.id, None)
                elif isinstance(rec, Metadata):
                    if rec.name == "se3sync":
                        out["metadata"] = dict(rec.metadata)
                    elif rec.name == "se3sync.outcome":
                        out["outcome"] = {k: json.loads(v) for k, v in rec.metadata.items()}
                elif isinstance(rec, Attachment):
                    out["attachments"][rec.name] = bytes(rec.data)
        except Exception as exc:  # mcap raises assorted errors on garbage or torn input
            if n_records == 0 or out["metadata"] is None:
                raise Se3SyncError(f"{path}: not a readable MCAP file ({type(exc).__name__}: "
                                   f"{' '.join(str(exc).split())[:160]})") from None
            out["truncated"] = True
    if out["metadata"] is None:
        raise Se3SyncError(f"{path}: not an se3sync log (no 'se3sync' metadata record)")
    return out
