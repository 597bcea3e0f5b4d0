"""The log's fast path into mcap's chunks: `MessageAppender` writes what mcap's own
``Writer.add_message`` writes, the same bytes, at ~1/10 of the cost, and mcap's summary-section
records written with one pack each. Used by `cosim.log.writer.McapLogger`."""
from __future__ import annotations

import struct
import zlib
from concurrent.futures import ThreadPoolExecutor
from itertools import chain

import numpy as np
import zstandard
from mcap.records import Channel, Chunk, ChunkIndex, MessageIndex, Statistics
from mcap.writer import CompressionType, IndexType, Writer

# zstd level of the log's chunks (see MessageAppender)
ZSTD_LEVEL = 1

# zstd level of a CDR log's chunks: binary numbers compress little. On the chunks of a 1000-agent
# run (51 MB): level 1 2.00× in 118 ms, -3 1.88× in 51 ms, -7 1.82× in 39 ms, -20 1.66× in 27 ms
CDR_ZSTD_LEVEL = -7


class _MessageIndex(MessageIndex):
    """mcap's MessageIndex record, written with one pack for the whole record instead of two
    calls per entry (a chunk of 1000 trail channels has 1000 of them): the same bytes."""

    def write(self, stream):
        n = 16 * len(self.records)
        stream.write(struct.pack("<BQHI", 0x07, 6 + n, self.channel_id, n))
        if n:
            stream.write(np.asarray(self.records, dtype="<u8").tobytes())


class Counted:
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


class MessageAppender:
    """``add(channel_id, log_time, data, sequence)``: what ``Writer.add_message(channel_id,
    log_time, data, log_time, sequence)`` does, the same bytes in the same file, at ~1/10 of the
    cost. Why our own: mcap's writer builds a Message object and writes each field through its
    own call (≈ 24 µs per message, most of a record's cost at N = 6); here one struct.pack writes
    the record header into the writer's current chunk and the chunk's message index, time bounds
    and the file statistics are updated as the writer does. That needs the writer's chunk builder
    and statistics (private to mcap). The first appender of a process proves it on the installed
    mcap: a small file written both ways must come out byte for byte the same (`proven`);
    when it does not, or the writer's parts are missing (another mcap, chunking off), ``add`` is
    the writer's own add_message. `tests/cosim/test_cosim_log.py` checks both ways on a larger file.

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
        if not ok or not proven():
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


PROOF = []


def proven() -> bool:
    """Whether `MessageAppender.add` and its `_finalize_chunk` (at mcap's zstd level 3) write
    what mcap's own add_message writes, on the mcap installed: three channels, chunk
    boundaries and out-of-order times, written both ways (once per process, ~2 ms)."""
    if not PROOF:
        import io

        def write(fast):
            buf = io.BytesIO()
            w = Writer(buf, chunk_size=600, compression=CompressionType.ZSTD)
            w.start(profile="", library="proof")
            sid = w.register_schema(name="s", encoding="jsonschema", data=b"{}")
            ch = [w.register_channel(topic=f"/{k}", message_encoding="json", schema_id=sid)
                  for k in range(3)]
            app = MessageAppender.__new__(MessageAppender)
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
            PROOF.append(write(True) == write(False))
        except Exception:  # mcap's internals are not what the appender expects
            PROOF.append(False)
    return PROOF[0]
