"""MAVLink 2 links over non-blocking UDP sockets, with signing, counters and a tlog.

We do not use pymavlink's ``mavutil`` connection objects: one ``udpin`` mavfile sends every
message to every peer that ever talked to it, it writes no tlog for UDP, and its parser keeps state
across datagrams. Instead each link is a plain non-blocking socket, every datagram is framed on
its own (UDP carries whole packets), and each peer gets its own
``pymavlink.dialects.v20.common.MAVLink`` object for encoding and decoding. Signing uses
pymavlink's ``setup_signing`` (as `bridge.mavlink.codec.setup_signing`) and pymavlink's own
signing state (its per-stream timestamps and own timestamp, ``mav.signing``), but the checks are
ours: we verify the HMAC first, so that (a) a bad signature can be told from a replay in the
counters and (b) a forged packet never touches a replay window (pymavlink's ``check_signature``
records the stream timestamp *before* it compares the signature: one forged packet with a huge
timestamp would lock the stream out); and a replay window (the stream's last timestamp) moves
only when the application has accepted the packet in full (`Peer.commit`): a genuine packet
replayed where it does not belong (another vehicle, a refused command) changes no window, so it
cannot make the genuine stream's next packets look like replays.

Network input is untrusted: a datagram that cannot be framed or decoded is counted once as
``malformed`` and dropped; nothing here raises on input.
"""
from __future__ import annotations

import errno
import hashlib
import os
import random
import socket
import struct
import sys
import time
from collections import defaultdict

import numpy as np

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import common as mavlink2  # noqa: E402

from controller.errors import Se3SyncError  # noqa: E402

from . import codec  # noqa: E402
from .sequence import seq_last, seq_step  # noqa: E402

MAGIC_V2 = 0xFD
MAGIC_V1 = 0xFE
HEADER_LEN = 10
SIG_LEN = 13
IFLAG_SIGNED = 0x01
MSG_HEARTBEAT = 0

REJECT_REASONS = ("unsigned", "bad_signature", "replay", "wrong_system", "not_for_us",
                  "unknown_message", "stale", "out_of_order", "nan", "non_unit_quaternion",
                  "bad_frame", "bad_command", "not_commander", "future", "other_source",
                  "wrong_address", "wrong_link", "no_stream_slot", "rate_limited")
# refusals of a packet that passed the link's checks for being old, not for what it claims: it
# came, so its sequence number counts as come (`Counters.arrived_since`), not as a loss
LATE_REASONS = frozenset(("stale", "out_of_order", "duplicate"))
NEW_STREAM_UNITS = 6_000_000   # pymavlink's rule: a new signing stream at most 60 s (10 µs units) behind
LOOPBACK_HOSTS = ("localhost",)


class Counters:
    """Traffic counters of one side of a set of links (JSON-friendly via `as_dict`).

    ``scope``: while a caller handles a packet it can attribute (the inter-agent link: the claimed
    neighbour), a dict {reason: count} that every refusal is also counted in."""

    def __init__(self):
        self.scope = None
        self.sent = 0                # packets sent
        self.send_errors = 0         # sendto failed (no route, buffer full)
        self.received = 0            # packets accepted (framed, signed if required, decoded)
        self.datagrams = 0           # datagrams read from the sockets
        self.malformed = 0           # datagrams dropped: bad magic, MAVLink 1, truncated, bad CRC, ...
        self.dropped = 0             # packets lost on the way (gaps in the senders' sequence numbers)
        self.rejected = defaultdict(int)   # packets refused, by reason
        self.drain_max = 0           # most datagrams read in one pass over a socket
        self.drain_capped = 0        # passes that stopped at the per-pass budget (the rest waits)
        self.n_rejected = 0          # sum of `rejected` (kept, not summed per packet)
        self.n_late = 0              # …of which for LATE_REASONS

    def reject(self, reason: str) -> None:
        self.rejected[reason] += 1
        self.n_rejected += 1
        if reason in LATE_REASONS:
            self.n_late += 1
        if self.scope is not None:
            self.scope[reason] += 1

    def bad_packet(self) -> None:
        """A framed packet that does not check out (checksum, layout): one more ``malformed``."""
        self.malformed += 1
        if self.scope is not None:
            self.scope["malformed"] += 1

    def as_dict(self) -> dict:
        return {"sent": self.sent, "send_errors": self.send_errors, "received": self.received,
                "datagrams": self.datagrams, "malformed": self.malformed, "dropped": self.dropped,
                "rejected": int(sum(self.rejected.values())),
                "rejected_by_reason": {k: int(v) for k, v in sorted(self.rejected.items())},
                "drain_max": self.drain_max, "drain_capped": self.drain_capped}

    def refusals(self) -> int:
        """Packets refused so far (rejected or malformed): a handler accepted a packet iff this
        did not change while it ran."""
        return self.malformed + self.n_rejected

    def mark(self) -> tuple[int, int]:
        """Where the counts stand (refusals, late ones) before a handler runs."""
        return self.malformed + self.n_rejected, self.n_late

    def arrived_since(self, mark) -> bool:
        """Since ``mark`` nothing was refused, or only for being old (LATE_REASONS): the packet
        the handler had passed the link's checks and came; its sequence number counts
        (`Peer.commit`), and a stall that leaves a backlog of old states is not reported as
        that many lost (it was: ``dropped`` 1622 beside ``stale`` 1622 after a 1 s stall)."""
        return self.malformed + self.n_rejected - mark[0] == self.n_late - mark[1]


class TLog:
    """A telemetry log readable by mavlogdump.py: per packet, an 8-byte big-endian timestamp in
    microseconds since the epoch, then the raw packet (both directions, one file)."""

    def __init__(self, path):
        self.path = str(path)
        self.f = open(self.path, "ab", buffering=1 << 16)
        self._pack = struct.Struct(">Q").pack

    def write(self, pkt: bytes, t: float | None = None) -> None:
        if self.f is None:
            return
        us = int((time.time() if t is None else t) * 1e6)
        self.f.write(self._pack(us) + bytes(pkt))

    def close(self) -> None:
        if self.f is not None:
            self.f.close()
            self.f = None


def split_datagram(data: bytes):
    """Frames a datagram into MAVLink 2 packets. Returns (packets, error) where error is None or
    a short reason; on error the packets framed before the bad bytes are still returned."""
    out = []
    i, n = 0, len(data)
    if n == 0:
        return out, "empty"
    while i < n:
        b = data[i]
        if b != MAGIC_V2:
            return out, "mavlink1" if b == MAGIC_V1 else "bad_magic"
        if n - i < HEADER_LEN + 2:
            return out, "truncated"
        plen = data[i + 1]
        flags = data[i + 2]
        if flags & ~IFLAG_SIGNED:
            return out, "bad_incompat_flags"
        total = HEADER_LEN + plen + 2 + (SIG_LEN if flags & IFLAG_SIGNED else 0)
        if n - i < total:
            return out, "truncated"
        out.append(data[i:i + total])
        i += total
    return out, None


def packet_ids(pkt: bytes):
    """(seq, sysid, compid, msgid, signed) of a framed packet."""
    return pkt[4], pkt[5], pkt[6], pkt[7] | (pkt[8] << 8) | (pkt[9] << 16), bool(pkt[2] & IFLAG_SIGNED)


class Peer:
    """Encoding and decoding for one remote system: a pymavlink MAVLink object, signing, sequence
    tracking, the shared counters and tlog."""

    def __init__(self, src_system: int, src_component: int, counters: Counters, key: bytes | None = None,
                 allow_unsigned_heartbeat: bool = False, link_id: int = 0, tlog: TLog | None = None,
                 signing_state=None):
        self.mav = mavlink2.MAVLink(None, srcSystem=src_system, srcComponent=src_component)
        self.mav.robust_parsing = True
        self._decoder = mavlink2.MAVLink(None, srcSystem=src_system, srcComponent=src_component)
        self._decoder.robust_parsing = True
        self.counters = counters
        self.tlog = tlog
        self.key = key
        self.allow_unsigned_heartbeat = allow_unsigned_heartbeat
        self._last_seq: dict = {}
        self._seq_slot: dict = {}      # keys kept in _seq_arr instead (`sequence_array`)
        self._seq_arr = None
        if key is not None:
            allow = (lambda mav, msgid: msgid == MSG_HEARTBEAT) if allow_unsigned_heartbeat else None
            codec.setup_signing(self.mav, key, allow_unsigned_callback=allow, link_id=link_id)
            if signing_state is not None:
                signing_state.attach(self.mav)
        self.rx_errors: dict = defaultdict(int)
        self._pending_seq = None
        self._pending_sig = None     # (stream, timestamp) of the latest signed packet, until commit
        self.last_signed = False     # the latest accepted packet carried a valid signature

    # ------------------------------------------------------------------ out
    def pack(self, msg) -> bytes:
        """Encodes (and signs) a message object made by ``self.mav.<name>_encode(...)``."""
        buf = msg.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) & 0xFF
        if self.tlog is not None:
            self.tlog.write(buf)
        return buf

    # ------------------------------------------------------------------ in
    def _count_seq(self, sysid, compid, seq) -> None:
        """One more packet of (sysid, compid) numbered ``seq``: losses counted as `seq_step`
        counts them (a gap, less what comes late)."""
        key = (sysid, compid)
        slot = self._seq_slot.get(key) if self._seq_slot else None
        if slot is not None:
            st, lost = seq_step(int(self._seq_arr[slot]), seq)
            self._seq_arr[slot] = st
        else:
            st, lost = seq_step(self._last_seq.get(key, -1), seq)
            self._last_seq[key] = st
        self.counters.dropped += lost

    def sequence_array(self, keys) -> np.ndarray:
        """From now on the sequence state (`bridge.mavlink.sequence`) of each of ``keys``
        ((system, component)) lives in the returned int64 array (−1: none yet), in that order,
        where compiled code that takes packets itself (`bridge.swarm.sample_wire.drain_samples`)
        counts them as `_count_seq` does; the rest of this peer reads and moves the same
        numbers."""
        if self._seq_slot:
            raise Se3SyncError("Peer.sequence_array: this peer keeps an array already")
        keys = [tuple(int(x) for x in k) for k in keys]
        arr = np.array([self._last_seq.pop(k, -1) for k in keys], np.int64)
        self._seq_slot = {k: i for i, k in enumerate(keys)}
        self._seq_arr = arr
        return arr

    def sequences(self) -> dict:
        """{(system, component): the newest sequence number counted} (what `commit` and `took`
        have recorded, wherever it is kept)."""
        out = {k: seq_last(v) for k, v in self._last_seq.items()}
        for k, i in self._seq_slot.items():
            if self._seq_arr[i] >= 0:
                out[k] = seq_last(int(self._seq_arr[i]))
        return out

    def commit(self) -> None:
        """The latest packet this peer passed was accepted in full by the application (target,
        contents), or refused by it only for being old (`Counters.arrived_since`: it came):
        only now does its signing stream's replay window move to its timestamp (and the own
        timestamp with it, as pymavlink does), and only now does its sequence number count
        (`seq_step`). A packet refused for anything else leaves both as they were."""
        if self._pending_seq is not None:
            self._count_seq(*self._pending_seq)
            self._pending_seq = None
        ps = self._pending_sig
        if ps is not None:
            self._pending_sig = None
            sig = self.mav.signing
            stream, ts = ps
            if ts > sig.stream_timestamps.get(stream, -1):
                sig.stream_timestamps[stream] = ts
            if ts > sig.timestamp:
                sig.timestamp = ts

    commit_sequence = commit

    def _fresh(self, pkt: bytes, sysid: int, compid: int) -> bool:
        """The signature's timestamp is newer than its stream's window (pymavlink's rule: a new
        stream may be at most a minute behind our own timestamp); nothing is recorded here
        (`commit`). Its stream is (link id, system, component), as in the MAVLink 2 spec."""
        sig = self.mav.signing
        stream = (pkt[-13], sysid, compid)
        ts = int.from_bytes(pkt[-12:-6], "little")
        last = sig.stream_timestamps.get(stream)
        if last is not None:
            if ts <= last:
                return False
        elif ts + NEW_STREAM_UNITS < sig.timestamp:
            return False
        self._pending_sig = (stream, ts)
        return True

    def fresh(self, pkt: bytes) -> bool:
        """A signed packet's timestamp is newer than its stream's window (`_fresh`); nothing is
        recorded and nothing is counted (a packet the caller refuses anyway)."""
        ok = self._fresh(pkt, pkt[5], pkt[6])
        self._pending_sig = None
        return ok

    def authentic(self, pkt: bytes) -> bool:
        """Without a key always; with one: signed with it (or an allowed unsigned HEARTBEAT);
        a refusal is counted (``unsigned``, ``bad_signature``). Touches no replay window."""
        return self._authentic(pkt, packet_ids(pkt)[3], bool(pkt[2] & IFLAG_SIGNED))

    def _authentic(self, pkt: bytes, msgid: int, signed: bool) -> bool:
        """With a key: signed (or an allowed unsigned HEARTBEAT) and the signature right; counted
        otherwise. The signature is verified here, before pymavlink records the stream's
        timestamp (pymavlink 2.4.50 records it first: one forged packet would lock a stream out)."""
        if self.key is None:
            return True
        c = self.counters
        if not signed:
            if not (self.allow_unsigned_heartbeat and msgid == MSG_HEARTBEAT):
                c.reject("unsigned")
                return False
            return True
        h = hashlib.sha256(self.key)
        h.update(pkt[:-6])
        if h.digest()[:6] != pkt[-6:]:
            c.reject("bad_signature")
            return False
        return True

    def _accepted(self, pkt: bytes, seq: int, sysid: int, compid: int, signed: bool) -> None:
        self.last_signed = signed and self.key is not None
        # Sequence numbers count only on packets the application takes or finds merely old
        # (`commit`), and with a key only on signed ones (a spoofed unsigned HEARTBEAT or a
        # packet replayed from another link would otherwise interleave a foreign sequence).
        self._pending_seq = (sysid, compid, seq) if (self.key is None or signed) else None
        self.counters.received += 1
        if self.tlog is not None:
            self.tlog.write(pkt)

    def accept_fields(self, pkt: bytes, types: dict):
        """`accept` for the message types in ``types`` ({msgid: pymavlink message class}) without
        building a message object: (msgid, the payload's fields in wire order as one flat tuple,
        arrays spread out, as the class's ``unpacker`` gives them), or None (counted, as `accept`
        counts; another message id is rejected as ``unexpected_message``). The same checks as
        pymavlink's decode (checksum, signature and its replay window, through pymavlink's own
        ``check_signature``), at a fraction of the cost: building the object is most of it
        (an agent takes a sample of every neighbour at every step)."""
        c = self.counters
        seq, sysid, compid, msgid, signed = packet_ids(pkt)
        self._pending_seq = self._pending_sig = None
        if not self._authentic(pkt, msgid, signed):
            return None
        cls = types.get(msgid)
        if cls is None:
            c.reject("unexpected_message")
            return None
        if crc_ok(pkt) is not True:
            c.bad_packet()
            self.rx_errors["crc"] += 1
            return None
        if signed and self.key is not None and not self._fresh(pkt, sysid, compid):
            c.reject("replay")
            return None
        plen = pkt[1]
        size = cls.unpacker.size
        payload = bytes(pkt[HEADER_LEN:HEADER_LEN + plen])
        if plen < size:   # MAVLink 2 drops the payload's trailing zeros
            payload += bytes(size - plen)
        try:
            fields = cls.unpacker.unpack(payload[:size])
        except struct.error:
            c.bad_packet()
            return None
        self._accepted(pkt, seq, sysid, compid, signed)
        return msgid, fields

    def accepted(self, pkt, seq: int, sysid: int, compid: int) -> bool:
        """A packet (sequence ``seq`` from sysid:compid) whose framing, checksum and fields
        compiled code checked as `accept_fields` checks them: with a key its signature and
        replay window are checked here as `accept_fields` checks them (a refusal counted:
        False); then recorded as `accept_fields` records it, for `commit` (True)."""
        signed = bool(pkt[2] & IFLAG_SIGNED)
        self._pending_seq = self._pending_sig = None
        if not self._authentic(pkt, pkt[7] | (pkt[8] << 8) | (pkt[9] << 16), signed):
            return False
        if signed and self.key is not None and not self._fresh(pkt, sysid, compid):
            self.counters.reject("replay")
            return False
        self._accepted(pkt, seq, sysid, compid, signed)
        return True

    def took(self, sysid: int, compid: int, seqs) -> None:
        """Unsigned packets of (sysid, compid) with sequence numbers ``seqs`` were checked and
        accepted in full by the application without `accept_fields` (a compiled decoder,
        `bridge.swarm.sample_wire`, on a link without a key or a tlog): counted as
        `accept_fields` and `commit` count them, one after the other."""
        if self.key is not None or self.tlog is not None:
            raise Se3SyncError("Peer.took: only for a link without a key or a tlog")
        self._pending_seq = self._pending_sig = None
        self.last_signed = False
        self.counters.received += len(seqs)
        for seq in seqs:
            self._count_seq(sysid, compid, seq)

    def took_counted(self, n: int, dropped: int) -> None:
        """``n`` unsigned packets were checked and accepted in full by compiled code that also
        counted their sequence numbers in `sequence_array`'s array, finding ``dropped`` lost
        (`bridge.mavlink.state_wire.take_states`): what `took` records besides."""
        if self.key is not None or self.tlog is not None:
            raise Se3SyncError("Peer.took_counted: only for a link without a key or a tlog")
        self._pending_seq = self._pending_sig = None
        self.last_signed = False
        self.counters.received += n
        self.counters.dropped += dropped

    def take_signed(self, data: bytes, ends, sysid: int, compid: int) -> bool:
        """`took` for signed packets: the packets data[0:ends[0]], data[ends[0]:ends[1]], …
        (found and checked but for their signatures by a compiled decoder) are taken if each is
        signed with the key and newer than its stream's window as the windows stand after the
        ones before it, exactly as `accept_fields` and `commit` would take them one after the
        other; then counted and committed (True). Otherwise nothing changes (False) and the
        caller hands the packets to `accept_fields`, which counts the refusal."""
        if self.key is None or self.tlog is not None:
            raise Se3SyncError("Peer.take_signed: only for a link with a key and without a tlog")
        sig = self.mav.signing
        windows = sig.stream_timestamps
        own = sig.timestamp
        moved = {}
        seqs = []
        start = 0
        for end in ends:
            pkt = data[start:end]
            start = end
            h = hashlib.sha256(self.key)
            h.update(pkt[:-6])
            if h.digest()[:6] != pkt[-6:]:
                return False
            stream = (pkt[-13], sysid, compid)
            ts = int.from_bytes(pkt[-12:-6], "little")
            last = moved.get(stream, windows.get(stream))
            if last is not None:
                if ts <= last:
                    return False
            elif ts + NEW_STREAM_UNITS < own:
                return False
            moved[stream] = ts
            if ts > own:
                own = ts
            seqs.append(pkt[4])
        self._pending_seq = self._pending_sig = None
        self.last_signed = True
        self.counters.received += len(seqs)
        for seq in seqs:
            self._count_seq(sysid, compid, seq)
        windows.update(moved)
        sig.timestamp = own
        return True

    def accept(self, pkt: bytes):
        """A framed packet -> message, or None (counted: rejected by reason, or malformed)."""
        c = self.counters
        seq, sysid, compid, msgid, signed = packet_ids(pkt)
        self._pending_seq = self._pending_sig = None
        if not self._authentic(pkt, msgid, signed):
            return None
        if signed and self.key is not None and crc_ok(pkt) is True \
                and not self._fresh(pkt, sysid, compid):
            c.reject("replay")
            return None
        try:
            # decoded without pymavlink's signing check (ours is above), which would record
            # the stream's timestamp before the application has accepted the packet
            m = self._decoder.decode(bytearray(pkt))
        except Exception:  # noqa: BLE001 - untrusted input must never crash us
            c.bad_packet()
            self.rx_errors["decode"] += 1
            self._pending_sig = None
            return None
        if isinstance(m, mavlink2.MAVLink_unknown):
            c.reject("unknown_message")
            self._pending_sig = None
            return None
        self._accepted(pkt, seq, sysid, compid, signed)
        return m


def crc_ok(pkt: bytes) -> bool | None:
    """The X.25 checksum of a framed MAVLink 2 packet is right (None: unknown message id, no
    CRC_EXTRA to check with). The per-step messages' CRC_EXTRA from `bridge.mavlink.codec`'s
    table, the others' from pymavlink's."""
    msgid = pkt[7] | (pkt[8] << 8) | (pkt[9] << 16)
    extra = codec.CRC_EXTRA.get(msgid)
    if extra is None:
        entry = mavlink2.mavlink_map.get(msgid)
        if entry is None:
            return None
        extra = entry.crc_extra
    return codec.crc_matches(pkt, extra)


def is_loopback(host: str) -> bool:
    return host in LOOPBACK_HOSTS or host.startswith("127.")


def binds_non_loopback(endpoint: str) -> bool:
    """Does a socket for this endpoint accept datagrams from other machines? udpin binds HOST;
    udpout to a remote host binds 0.0.0.0 (see UdpSocket)."""
    _, (host, _) = parse_endpoint(endpoint)
    return not is_loopback(host)


def require_key_or_insecure(endpoints, key, insecure: bool,
                            what: str = "command the vehicles") -> None:
    """Refuses (Se3SyncError) a non-loopback socket without a signing key unless --insecure;
    ``what`` says what a stranger could then do."""
    if key is not None or insecure:
        return
    bad = [e for e in endpoints if binds_non_loopback(e)]
    if bad:
        raise Se3SyncError(f"{bad[0]} accepts datagrams from other machines and there is no "
                           f"signing key (--key): anyone on the network could {what}; "
                           "give --key, or --insecure to run unauthenticated")


DRAIN_BUDGET = 64   # datagrams per socket per pass; the caller's timer runs between passes


def receive_datagrams(sock, counters, on_packet, limit: int = DRAIN_BUDGET,
                      deadline: float | None = None, accept_from=None, fast=None) -> int:
    """Read pending datagrams on sock, split each into MAVLink 2 frames and hand each frame to
    on_packet(pkt, addr). Network input is untrusted: a datagram that does not frame, or whose
    frames break their handler, is counted once as malformed and dropped, never raised.

    How much is read: at most ``limit`` datagrams; with a ``deadline`` (time.monotonic()),
    batches of ``limit`` until the socket is empty or the deadline has passed (a drain by time,
    not by count: a flood then costs the caller a bounded time per pass, not its genuine data,
    which a count would leave behind the junk in the socket buffer). What the kernel drops
    beyond its buffer is the flood's loss (`UdpSocket.kernel_drops`).

    Cheap refusals before any parsing: a first byte that is not MAVLink 2's magic (``malformed``)
    and, with ``accept_from`` (a predicate of the sender's address), a sender it refuses
    (counted ``wrong_address``). ``fast(data, addr) -> bool``, if given, may take a datagram
    whole before it is framed (a compiled decoder of the common case, `bridge.swarm.sample_wire`):
    True means it did everything ``on_packet`` would have done with its frames, False hands the
    datagram on unchanged. Returns the number of datagrams read."""
    c = counters
    total = 0
    while True:
        batch = sock.recv_all(limit)
        nb = len(batch)
        total += nb
        if nb > c.drain_max:
            c.drain_max = nb
        for data, addr in batch:
            take_datagram(data, addr, c, on_packet, accept_from, fast)
        if nb < limit:
            return total
        if deadline is None or time.monotonic() >= deadline:
            c.drain_capped += 1
            return total


def take_datagram(data, addr, counters, on_packet, accept_from=None, fast=None) -> None:
    """One datagram read from a socket, as `receive_datagrams` takes each (counted, checked,
    split into frames, each frame to ``on_packet``); never raises."""
    c = counters
    c.datagrams += 1
    if not data or data[0] != MAGIC_V2:
        c.malformed += 1
        return
    if accept_from is not None and not accept_from(addr):
        c.reject("wrong_address")
        return
    if fast is not None and fast(data, addr):
        return
    try:
        pkts, err = split_datagram(data)
        if err is not None:
            c.malformed += 1
            return
        m0 = c.malformed
        for pkt in pkts:
            on_packet(pkt, addr)
        if c.malformed > m0 + 1:
            c.malformed = m0 + 1  # one bad datagram counts once
    except Exception:  # noqa: BLE001 - untrusted input never crashes us
        c.malformed += 1


# SO_ATTACH_REUSEPORT_CBPF (Linux 4.5; asm-generic's number, which Python's socket module does
# not name) with a one-instruction classic BPF program, "return k": a datagram that no
# connected member of a shared port claims goes to member k of the port's group (in the order
# they were bound while none has closed). `UdpSocket` steers to member 0, the catch-all, so
# that a peer's socket gets no stranger's datagram in the instant between its bind and its
# connect.
_SO_ATTACH_REUSEPORT_CBPF = getattr(socket, "SO_ATTACH_REUSEPORT_CBPF",
                                    51 if sys.platform.startswith("linux") else None)
# SO_TIMESTAMPNS (asm-generic's number, also its SCM_ message's): each datagram read with
# recvmsg carries the kernel's arrival time, which orders one sender's datagrams across the two
# sockets of a shared port that it reached around a peer socket's connect (`merge_backlog`)
_SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35 if sys.platform.startswith("linux") else None)


def steer_unclaimed(s: socket.socket, member: int = 0) -> bool:
    """Sends the datagrams of s's port group that no connected member claims to ``member``;
    False where the kernel has no such option (a peer's socket's ``backlog`` then keeps the
    senders apart on its own)."""
    import ctypes

    if _SO_ATTACH_REUSEPORT_CBPF is None:
        return False
    ret_k = struct.pack("=HBBI", 0x06, 0, 0, int(member))       # BPF_RET | BPF_K
    prog = ctypes.create_string_buffer(ret_k, len(ret_k))
    fprog = struct.pack("@HP", 1, ctypes.addressof(prog))     # struct sock_fprog {len, filter*}
    try:
        s.setsockopt(socket.SOL_SOCKET, _SO_ATTACH_REUSEPORT_CBPF, fprog)
        return True
    except OSError:
        return False


def _stamp_arrivals(s: socket.socket) -> bool:
    """Asks the kernel to keep each datagram's arrival time for s (SO_TIMESTAMPNS); False where
    it cannot."""
    if _SO_TIMESTAMPNS is None:
        return False
    try:
        s.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
        return True
    except OSError:
        return False


def parse_endpoint(ep: str):
    """'udpin:HOST:PORT' | 'udpout:HOST:PORT' | 'udp:HOST:PORT' (= udpin) -> (mode, (host, port))."""
    mode, host, port = ep.split(":")
    if mode == "udp":
        mode = "udpin"
    return mode, (host, int(port))


class UdpSocket:
    """A non-blocking UDP socket. ``udpin``: bound to HOST:PORT, replies go to whoever talked last
    (or to an address the caller gives); ``udpout``: sends to HOST:PORT from an ephemeral port,
    connected to it, so that the kernel hands it datagrams from HOST:PORT only (anyone else's
    are dropped by the kernel: a stranger cannot fill its buffer). ``connect_to`` (udpin): the
    same for one peer's address, on a port shared with ``reuse_port``.

    A port shared so has one catch-all (the first socket bound, without ``connect_to``) and its
    peers' connected sockets. Between its bind and its connect a peer's socket is an
    unconnected member of the port's group, and the kernel may hand it anyone's datagrams: its
    readers, which take every datagram on it to be the peer's (the compiled ones read no
    address), would then take another sender's datagram for the peer's. The catch-all steers
    to itself what no connected socket claims (`steer_unclaimed`), but Linux applies that only
    while no member is connected: once one is, every unclaimed datagram goes to the newest
    unconnected member, the catch-all gets none of them until the connect (measured on 6.18).
    So whatever reached the new socket before its connect is read at once with its true sender
    (``backlog``: `recv_all` returns it first; a reader that reads no addresses defers to
    `recv_all` while it is there). A sender's datagrams of that instant may then lie on both
    sockets, and its earlier ones on the catch-all: `merge_backlog` puts them back in the order
    they arrived (the kernel's arrival times), on the catch-all."""

    def __init__(self, endpoint: str, rcvbuf: int = 1 << 20, reuse_port: bool = False,
                 connect_to=None):
        self.endpoint = endpoint
        self.mode, addr = parse_endpoint(endpoint)
        self.stamped = False       # arrival times kept by the kernel (`merge_backlog`)
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, rcvbuf)
        except OSError:
            pass
        if self.mode == "udpin":
            # no SO_REUSEADDR: a port already in use is an error, not a silent split; only the
            # inter-agent link shares its port between its own sockets (SO_REUSEPORT, after
            # checking that the port is free: `AgentLink`)
            if reuse_port:
                s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
                self.stamped = _stamp_arrivals(s)
            try:
                s.bind(addr)
                if connect_to is not None:
                    s.connect(connect_to)
                elif reuse_port:
                    steer_unclaimed(s)
            except OSError:
                s.close()
                raise
            self.remote = None
            # the one address the kernel hands this socket datagrams from (as recvfrom gives it)
            self.connected_to = connect_to
        else:
            try:
                s.bind((addr[0] if addr[0] in ("127.0.0.1", "localhost") else "0.0.0.0", 0))
                s.connect(addr)
            except OSError:
                s.close()
                raise
            self.remote = addr
            self.connected_to = None    # (recvfrom may spell its address otherwise)
        s.setblocking(False)
        self.sock = s
        self.local = s.getsockname()
        self.backlog = []     # [(data, addr)] read before anything else (see the class's doc)
        self._backlog_ns = []  # …their arrival times (ns; None: unknown), `merge_backlog`'s
        if connect_to is not None:
            self._backlog_ns, self.backlog = self._read_stamped(4096)
            if self.stamped:
                # its arrival times served that once; its every read after is the hot path
                s.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 0)
                self.stamped = False

    def fileno(self) -> int:
        return self.sock.fileno()

    def send(self, data: bytes, addr=None) -> bool:
        addr = addr or self.remote
        if addr is None:
            return False
        for _ in range(2):
            try:
                self.sock.sendto(data, addr)
                return True
            except ConnectionRefusedError:
                # a connected socket reports an earlier ICMP "port unreachable" (the peer was
                # not listening yet) on the next call: this datagram was not sent, try again
                continue
            except OSError:
                return False
        return False

    def recv_all(self, limit: int = 4096):
        """Every datagram waiting now: [(data, addr)] (what came before a connect first)."""
        if self.backlog:
            out = self.take_backlog()
            return out + self._read(max(0, limit - len(out)))
        return self._read(limit)

    def merge_backlog(self, peer: "UdpSocket", limit: int = 4096) -> None:
        """The catch-all's part when its port's new ``peer`` socket has connected: what waits
        here now (at most ``limit`` datagrams) and what reached ``peer`` before its connect
        (its backlog, taken from it), merged in the order they arrived, kept behind this
        socket's backlog for `recv_all`. Without arrival times, what waits here comes first."""
        t_here, here = self._read_stamped(limit)
        t_peer, there = peer._backlog_ns, peer.take_backlog()
        peer._backlog_ns = []
        items = list(zip(t_here, here)) + list(zip(t_peer, there))
        if None not in t_here and None not in t_peer:
            items.sort(key=lambda x: x[0])      # stable: one socket's order kept on a tie
        self.backlog.extend(d for _, d in items)

    def _read_stamped(self, limit: int):
        """`_read` with each datagram's arrival time: ([ns or None], [(data, addr)])."""
        if not self.stamped:
            out = self._read(limit)
            return [None] * len(out), out
        ts, out = [], []
        recvmsg = self.sock.recvmsg
        space = socket.CMSG_SPACE(16)
        for _ in range(limit):
            try:
                data, anc, _, addr = recvmsg(65535, space)
            except BlockingIOError:
                break
            except OSError as exc:
                if exc.errno in (errno.ECONNREFUSED, errno.EAGAIN):
                    continue
                break
            t = None
            for level, kind, raw in anc:
                if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS and len(raw) >= 16:
                    sec, nsec = struct.unpack_from("qq", raw)
                    t = sec * 1_000_000_000 + nsec
            ts.append(t)
            out.append((data, addr))
        return ts, out

    def take_backlog(self) -> list:
        """What reached this socket before its connect, [(data, addr)], now taken from it."""
        out, self.backlog, self._backlog_ns = self.backlog, [], []
        return out

    def _read(self, limit: int):
        out = []
        recv = self.sock.recvfrom
        for _ in range(limit):
            try:
                out.append(recv(65535))
            except BlockingIOError:
                break
            except OSError as exc:  # ICMP port unreachable surfaces as ECONNREFUSED on Linux
                if exc.errno in (errno.ECONNREFUSED, errno.EAGAIN):
                    continue
                break
        return out

    def kernel_drops(self) -> int | None:
        """Datagrams the kernel dropped for this socket (its receive buffer was full: a flood,
        or a reader that fell behind), from /proc/net/udp; None where that is not available."""
        try:
            ino = os.fstat(self.sock.fileno()).st_ino
            with open("/proc/net/udp", encoding="ascii") as f:
                next(f)
                for line in f:
                    p = line.split()
                    if len(p) >= 13 and p[9] == str(ino):
                        return int(p[12])
        except (OSError, ValueError, StopIteration):
            return None
        return None

    def close(self) -> None:
        try:
            self.sock.close()
        except OSError:
            pass


_PORT_SLOT = 16          # ports are reserved in aligned slots of 16 (one lock file each)
_PORT_KEEP = 32          # reservations of the last 32 calls are held (the older are released)
_port_reservations: list = []


def _ephemeral_ports() -> tuple[int, int]:
    """The range the OS draws ports for sockets bound to port 0 from (Linux: from procfs;
    elsewhere Linux's default 32768..60999 and the IANA range 49152..65535, whichever is
    wider)."""
    try:
        with open("/proc/sys/net/ipv4/ip_local_port_range") as f:
            a, b = (int(x) for x in f.read().split())
        return a, b
    except (OSError, ValueError):
        return 32768, 65535


def _lock_slot(slot: int):
    """An exclusive, non-blocking lock on slot's file (an open fd), or None if another holder
    (another process, or an earlier call of this one) has it. Without fcntl: no locking."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        return -1
    import tempfile
    d = os.path.join(tempfile.gettempdir(), f"se3sync-ports-{os.getuid()}")
    os.makedirs(d, exist_ok=True)
    fd = os.open(os.path.join(d, f"{slot * _PORT_SLOT}.lock"), os.O_RDWR | os.O_CREAT, 0o600)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return fd
    except OSError:
        os.close(fd)
        return None


def free_base_port(n: int, lo: int = 20000, hi: int | None = None) -> int:
    """A base port p with p .. p+n-1 all free on 127.0.0.1 (UDP and TCP), for tests and
    benchmarks whose processes must be told their ports before they bind them (a scenario's
    ``bridge.base_port`` or ``network.base_port``: one port per vehicle or agent). Where the
    code under test can bind port 0 itself and report the port, use that instead.

    Safe against the races "bind to 0, close, reuse the number" has:
    - the block lies between ``lo`` and the OS's ephemeral range (`_ephemeral_ports`), so no
      socket bound to port 0 anywhere on the machine (a client, a udpout endpoint, a resolver)
      can be given one of its ports between this call and their use: ``hi`` defaults to the
      range's start (on a machine whose range starts below lo + 1000, to 65536, and this
      point does not hold there);
    - its ports are reserved for this process, by exclusive locks on files in the temporary
      directory (``se3sync-ports-UID/``, one per aligned slot of 16 ports) held until 32 more
      blocks have been handed out: no other caller of this function (a second test run, an
      earlier test of this one still starting its processes) is given them meanwhile;
    - every port of the block is checked bindable right now (UDP and TCP).
    What remains: a program that binds a fixed port in that range without asking."""
    n = max(1, int(n))
    eph_lo, _ = _ephemeral_ports()
    if hi is None:
        hi = eph_lo if eph_lo >= lo + 1000 else 65536
    slots = -(-n // _PORT_SLOT)
    first, last = -(-lo // _PORT_SLOT), hi // _PORT_SLOT - slots   # candidate start slots
    if last < first:
        raise RuntimeError(f"no room for {n} ports in {lo}..{hi - 1}")
    rng = random.Random(os.getpid() ^ time.monotonic_ns())
    for _ in range(400):
        s0 = rng.randint(first, last)
        p = s0 * _PORT_SLOT
        fds = []
        try:
            for s in range(s0, s0 + slots):
                fd = _lock_slot(s)
                if fd is None:
                    break
                fds.append(fd)
            else:
                if _all_bindable(p, n):
                    _port_reservations.append(fds)
                    fds = []
                    while len(_port_reservations) > _PORT_KEEP:
                        for fd in _port_reservations.pop(0):
                            if fd >= 0:
                                os.close(fd)
                    return p
        finally:
            for fd in fds:
                if fd >= 0:
                    os.close(fd)
    raise RuntimeError(f"no {n} free ports in {lo}..{hi - 1}")


def _all_bindable(p: int, n: int) -> bool:
    socks = []
    try:
        for i in range(n):
            for kind in (socket.SOCK_DGRAM, socket.SOCK_STREAM):
                s = socket.socket(socket.AF_INET, kind)
                socks.append(s)
                s.bind(("127.0.0.1", p + i))
        return True
    except OSError:
        return False
    finally:
        for s in socks:
            s.close()
