"""A struct-level MAVLink 2 codec for the messages of the per-step path (issue 31).

pymavlink builds a Python object per message, packs its header with a second object and runs
its checksum through a third; an agent sends and receives a handful of messages at every step
(250 Hz), so that is most of what an agent costs besides the law. This module does the same
work as plain `struct` layouts fixed at import: one `Message` per message of the common dialect
the links use (what the bridge and the agents send and take per step, and the few they handle
at 1 Hz), framed exactly as pymavlink's ``MAVLink_message._pack`` frames them (MAVLink 2 header,
the payload's trailing zeros dropped, the X.25 checksum with the message's CRC_EXTRA, and with a
key the 13-byte signature: link id, 48-bit timestamp, the first 6 bytes of
SHA-256(key + header + payload + checksum + link id + timestamp)), and decoded as pymavlink's
``MAVLink.decode`` decodes them (a short payload zero-extended, a longer one cut to the layout).
`tests/bridge/test_mavlink_codec.py` checks both byte for byte against pymavlink, signed and unsigned.

It imports neither pymavlink nor numpy. The state a frame needs (sequence number, system and
component id, signing: key, link id, own timestamp) is read from and written to a pymavlink-like
object, ``mav`` (``seq``, ``srcSystem``, ``srcComponent``, ``signing.sign_outgoing``,
``signing.secret_key``, ``signing.link_id``, ``signing.timestamp``): `bridge.mavlink.link.Peer`'s
own ``MAVLink`` object, so a link that sends through this codec and through pymavlink keeps one
sequence and one signing timestamp, and `bridge.mavlink.signing_state` persists it as before.

Use:
    ``ODOMETRY.encoded(*fields)`` -> an `Outgoing` message (its fields in wire order, arrays
    spread, char arrays as bytes), which `Peer.pack` packs like a pymavlink message;
    ``frame(mav, ODOMETRY, payload)`` -> the packet's bytes;
    ``decode(pkt)`` -> (Message, fields in wire order), or `CodecError` for what pymavlink
    refuses; ``Message.unpacker`` is a ``struct.Struct`` as pymavlink's classes have one, so
    `Peer.accept_fields` takes these layouts as it takes pymavlink's classes.
"""
from __future__ import annotations

import hashlib
import struct
import time

try:
    from fastcrc.crc16 import mcrf4xx as _mcrf4xx
except ImportError:  # pragma: no cover - fastcrc is a dependency of the mavlink extra
    _mcrf4xx = None

__all__ = ["Message", "Outgoing", "Received", "CodecError", "MESSAGES", "BY_ID", "CRC_EXTRA", "frame", "decode",
           "crc_x25", "crc_matches", "signature", "sign_frame", "setup_signing", "HEADER_LEN",
           "SIG_LEN", "MAGIC_V2"]

MAGIC_V2 = 0xFD
HEADER_LEN = 10
SIG_LEN = 13
IFLAG_SIGNED = 0x01
_TS_MASK = (1 << 48) - 1


def _crc_slow(data, crc: int = 0xFFFF) -> int:
    for b in bytes(data):
        tmp = b ^ (crc & 0xFF)
        tmp = (tmp ^ (tmp << 4)) & 0xFF
        crc = (crc >> 8) ^ (tmp << 8) ^ (tmp << 3) ^ (tmp >> 4)
    return crc


def crc_x25(data, crc: int = 0xFFFF) -> int:
    """MAVLink's X.25 (CRC-16/MCRF4XX) checksum of ``data``, continuing from ``crc``."""
    if _mcrf4xx is None:  # pragma: no cover
        return _crc_slow(data, crc)
    return _mcrf4xx(data, crc)


class CodecError(ValueError):
    """A packet pymavlink would refuse: ``reason`` is "magic", "length", "crc", "signature"
    or "unknown" (a message id this codec has no layout for)."""

    def __init__(self, reason: str, detail: str = ""):
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason


class Message:
    """One message's wire layout. ``fields``: (name, struct type, count) in wire order (the
    common dialect's order: by type size, extensions last); a char array is one ``Ns`` field.
    ``extensions``: how many of the last fields are MAVLink 2 extensions (they take no part in
    CRC_EXTRA, which is given)."""

    __slots__ = ("name", "id", "crc_extra", "fields", "unpacker", "size", "n_values", "_tail",
                 "_id_bytes", "extensions")

    def __init__(self, name: str, msg_id: int, crc_extra: int, fields, extensions: int = 0):
        self.name = name
        self.id = int(msg_id)
        self.crc_extra = int(crc_extra)
        self.fields = tuple((n, t, int(c)) for n, t, c in fields)
        self.extensions = int(extensions)
        fmt = "<" + "".join((f"{c}{t}" if c > 1 else t) for _, t, c in self.fields)
        self.unpacker = struct.Struct(fmt)
        self.size = self.unpacker.size
        self.n_values = sum(1 if t == "s" else c for _, t, c in self.fields)
        self._tail = bytes((self.crc_extra,))
        self._id_bytes = bytes((self.id & 0xFF, (self.id >> 8) & 0xFF, self.id >> 16))

    def __repr__(self) -> str:
        return f"<MAVLink 2 layout {self.name} #{self.id}>"

    @property
    def format(self) -> str:
        return self.unpacker.format

    def payload(self, *values) -> bytes:
        """The full payload of the fields in wire order (arrays spread, char arrays as bytes)."""
        return self.unpacker.pack(*values)

    def encoded(self, *values) -> "Outgoing":
        """An outgoing message of these fields (wire order), for `Peer.pack`."""
        return Outgoing(self, self.unpacker.pack(*values))

    def unpack(self, payload) -> tuple:
        """The fields (wire order, flat) of a received payload: zero-extended to the layout's
        size when MAVLink 2 dropped trailing zeros, cut to it when longer (newer extensions)."""
        n = len(payload)
        size = self.size
        if n < size:
            payload = bytes(payload) + bytes(size - n)
        elif n > size:
            payload = payload[:size]
        return self.unpacker.unpack(payload)

    def as_dict(self, values) -> dict:
        """{field name: value} of flat wire-order values: arrays as lists, char arrays as bytes
        without their trailing NULs (pymavlink's ``_<name>_raw``)."""
        out = {}
        i = 0
        for name, t, c in self.fields:
            if t == "s":
                out[name] = values[i].rstrip(b"\x00")
                i += 1
            elif c > 1:
                out[name] = list(values[i:i + c])
                i += c
            else:
                out[name] = values[i]
                i += 1
        return out


class Outgoing:
    """A message to send: its layout and full payload. ``pack(mav)`` frames it with ``mav``'s
    sequence number, ids and signing as a pymavlink message's ``pack(mav)`` does (and, as
    pymavlink, leaves ``mav.seq`` to the caller: `Peer.pack` counts it)."""

    __slots__ = ("msg", "payload")

    def __init__(self, msg: Message, payload: bytes):
        self.msg = msg
        self.payload = payload

    def pack(self, mav, force_mavlink1: bool = False) -> bytes:
        if force_mavlink1:
            raise ValueError("bridge.mavlink.codec frames MAVLink 2 only")
        return frame(mav, self.msg, self.payload)

    def get_type(self) -> str:
        return self.msg.name

    def get_msgId(self) -> int:
        return self.msg.id


class Received:
    """A received message of a numeric layout (no char arrays) decoded by the layout, as the
    handlers of pymavlink's messages read it: its fields as attributes (arrays as lists), and
    ``get_msgId``, ``get_type``, ``get_msgbuf`` (the packet), ``get_srcSystem``,
    ``get_srcComponent`` (its header's). Built from `Peer.accept_fields`' values: the same
    numbers as pymavlink's decode (tests/bridge/test_mavlink_codec.py), without its objects."""

    def __init__(self, msg: Message, values, pkt):
        self.__dict__.update(msg.as_dict(values))
        self._msg = msg
        self._pkt = pkt

    def get_msgId(self) -> int:
        return self._msg.id

    def get_type(self) -> str:
        return self._msg.name

    def get_msgbuf(self):
        return self._pkt

    def get_srcSystem(self) -> int:
        return self._pkt[5]

    def get_srcComponent(self) -> int:
        return self._pkt[6]


EPOCH_2015 = 1420070400   # signing timestamps count 10 µs from 2015-01-01 00:00 UTC


def setup_signing(mav, key: bytes, *, link_id: int = 0, allow_unsigned_callback=None,
                  initial_timestamp: int | None = None) -> None:
    """pymavlink's ``mavutil.mavfile.setup_signing`` for one MAVLink object (sign outgoing with
    ``key`` on ``link_id``, own timestamp = now), without importing mavutil (11 MB and a
    quarter of a second of serial-port and log-reader modules an agent never uses)."""
    sg = mav.signing
    sg.secret_key = key
    sg.sign_outgoing = True
    sg.allow_unsigned_callback = allow_unsigned_callback
    sg.link_id = link_id
    if initial_timestamp is None:
        now = max(time.time(), EPOCH_2015)
        initial_timestamp = int((now - EPOCH_2015) * 100 * 1000)
    sg.timestamp = initial_timestamp


def signature(key: bytes, signed_part) -> bytes:
    """The 6 signature bytes of a packet whose bytes up to and including its timestamp are
    ``signed_part``."""
    return hashlib.sha256(key + bytes(signed_part)).digest()[:6]


def frame(mav, msg: Message, payload: bytes) -> bytes:
    """pymavlink's ``MAVLink_message._pack`` (and ``sign_packet``) for a full payload in wire
    order: header, payload without its trailing zeros (at least one byte), checksum, and the
    signature when ``mav.signing.sign_outgoing`` (the own timestamp then moves on by one)."""
    plen = len(payload)
    if payload[plen - 1] == 0:
        p = payload.rstrip(b"\x00")
        if not p:
            p = payload[:1]
        payload = p
        plen = len(p)
    sg = mav.signing
    signed = sg.sign_outgoing
    body = bytes((MAGIC_V2, plen, IFLAG_SIGNED if signed else 0, 0, mav.seq & 0xFF,
                  mav.srcSystem, mav.srcComponent)) + msg._id_bytes + payload
    crc = _mcrf4xx(msg._tail, _mcrf4xx(body[1:])) if _mcrf4xx is not None else \
        _crc_slow(msg._tail, _crc_slow(body[1:]))
    body += crc.to_bytes(2, "little")
    if not signed:
        return body
    ts = sg.timestamp
    body += bytes((sg.link_id & 0xFF,)) + (ts & _TS_MASK).to_bytes(6, "little")
    sg.timestamp = ts + 1
    return body + hashlib.sha256(sg.secret_key + body).digest()[:6]


def sign_frame(mav, buf, start: int, end: int) -> None:
    """Signs, in place, a frame that ends in SIG_LEN bytes left for it, buf[start:end] (a
    writable buffer: bytearray, numpy uint8): link id, own timestamp and signature as `frame`
    writes them (the own timestamp then moves on by one)."""
    sg = mav.signing
    ts = sg.timestamp
    m = memoryview(buf)
    s = end - SIG_LEN
    m[s:s + 7] = bytes((sg.link_id & 0xFF,)) + (ts & _TS_MASK).to_bytes(6, "little")
    sg.timestamp = ts + 1
    m[end - 6:end] = hashlib.sha256(sg.secret_key + m[start:end - 6].tobytes()).digest()[:6]


_EXTRA_BYTE = [bytes((i,)) for i in range(256)]


def crc_matches(pkt, crc_extra: int) -> bool:
    """The checksum of a framed MAVLink 2 packet (signed or not) is right for ``crc_extra``."""
    end = HEADER_LEN + pkt[1]
    if _mcrf4xx is None:  # pragma: no cover
        crc = _crc_slow(_EXTRA_BYTE[crc_extra], _crc_slow(pkt[1:end]))
    else:
        crc = _mcrf4xx(_EXTRA_BYTE[crc_extra], _mcrf4xx(pkt[1:end]))
    return crc == (pkt[end] | (pkt[end + 1] << 8))


def decode(pkt, messages: dict | None = None, key: bytes | None = None):
    """A framed MAVLink 2 packet -> (Message, its fields in wire order), checked as pymavlink's
    ``decode`` checks it: the magic byte, the length (header + payload + checksum [+ signature]
    = the packet), the checksum, and with ``key`` the signature (HMAC only: replay windows are
    the link's, `bridge.mavlink.link.Peer`). ``messages``: {id: Message}, default every layout
    here. Raises `CodecError`."""
    n = len(pkt)
    if n < HEADER_LEN + 2 or pkt[0] != MAGIC_V2:
        raise CodecError("magic" if n and pkt[0] != MAGIC_V2 else "length")
    plen = pkt[1]
    signed = pkt[2] & IFLAG_SIGNED
    if n != HEADER_LEN + plen + 2 + (SIG_LEN if signed else 0):
        raise CodecError("length", f"{n} bytes for a payload of {plen}")
    msgid = pkt[7] | (pkt[8] << 8) | (pkt[9] << 16)
    msg = (BY_ID if messages is None else messages).get(msgid)
    if msg is None:
        raise CodecError("unknown", f"message id {msgid}")
    if not crc_matches(pkt, msg.crc_extra):
        raise CodecError("crc", msg.name)
    if key is not None:
        if not signed or signature(key, memoryview(pkt)[:n - 6]) != bytes(pkt[n - 6:]):
            raise CodecError("signature", msg.name)
    return msg, msg.unpack(memoryview(pkt)[HEADER_LEN:HEADER_LEN + plen])


# ------------------------------------------------------------------------------ the layouts
# From the common dialect (common.xml), fields in wire order; tests/bridge/test_mavlink_codec.py checks
# each against pymavlink's class (id, CRC_EXTRA, struct format, field order).
HEARTBEAT = Message("HEARTBEAT", 0, 50, (
    ("custom_mode", "I", 1), ("type", "B", 1), ("autopilot", "B", 1), ("base_mode", "B", 1),
    ("system_status", "B", 1), ("mavlink_version", "B", 1)))
ATTITUDE_QUATERNION = Message("ATTITUDE_QUATERNION", 31, 246, (
    ("time_boot_ms", "I", 1), ("q1", "f", 1), ("q2", "f", 1), ("q3", "f", 1), ("q4", "f", 1),
    ("rollspeed", "f", 1), ("pitchspeed", "f", 1), ("yawspeed", "f", 1),
    ("repr_offset_q", "f", 4)), extensions=1)
LOCAL_POSITION_NED = Message("LOCAL_POSITION_NED", 32, 185, (
    ("time_boot_ms", "I", 1), ("x", "f", 1), ("y", "f", 1), ("z", "f", 1), ("vx", "f", 1),
    ("vy", "f", 1), ("vz", "f", 1)))
MANUAL_CONTROL = Message("MANUAL_CONTROL", 69, 243, (
    ("x", "h", 1), ("y", "h", 1), ("z", "h", 1), ("r", "h", 1), ("buttons", "H", 1),
    ("target", "B", 1), ("buttons2", "H", 1), ("enabled_extensions", "B", 1), ("s", "h", 1),
    ("t", "h", 1), ("aux1", "h", 1), ("aux2", "h", 1), ("aux3", "h", 1), ("aux4", "h", 1),
    ("aux5", "h", 1), ("aux6", "h", 1)), extensions=10)
COMMAND_LONG = Message("COMMAND_LONG", 76, 152, (
    ("param1", "f", 1), ("param2", "f", 1), ("param3", "f", 1), ("param4", "f", 1),
    ("param5", "f", 1), ("param6", "f", 1), ("param7", "f", 1), ("command", "H", 1),
    ("target_system", "B", 1), ("target_component", "B", 1), ("confirmation", "B", 1)))
COMMAND_ACK = Message("COMMAND_ACK", 77, 143, (
    ("command", "H", 1), ("result", "B", 1), ("progress", "B", 1), ("result_param2", "i", 1),
    ("target_system", "B", 1), ("target_component", "B", 1)), extensions=4)
# with the ``thrust_body`` extension (float[3] after type_mask), which pymavlink's bundled
# common.xml lacks (bridge.mavlink.output.AttitudeTargetMessage); CRC_EXTRA is unchanged
SET_ATTITUDE_TARGET = Message("SET_ATTITUDE_TARGET", 82, 49, (
    ("time_boot_ms", "I", 1), ("q", "f", 4), ("body_roll_rate", "f", 1),
    ("body_pitch_rate", "f", 1), ("body_yaw_rate", "f", 1), ("thrust", "f", 1),
    ("target_system", "B", 1), ("target_component", "B", 1), ("type_mask", "B", 1),
    ("thrust_body", "f", 3)), extensions=1)
SET_ACTUATOR_CONTROL_TARGET = Message("SET_ACTUATOR_CONTROL_TARGET", 139, 168, (
    ("time_usec", "Q", 1), ("controls", "f", 8), ("group_mlx", "B", 1),
    ("target_system", "B", 1), ("target_component", "B", 1)))
STATUSTEXT = Message("STATUSTEXT", 253, 83, (
    ("severity", "B", 1), ("text", "s", 50), ("id", "H", 1), ("chunk_seq", "B", 1)),
    extensions=2)
ODOMETRY = Message("ODOMETRY", 331, 91, (
    ("time_usec", "Q", 1), ("x", "f", 1), ("y", "f", 1), ("z", "f", 1), ("q", "f", 4),
    ("vx", "f", 1), ("vy", "f", 1), ("vz", "f", 1), ("rollspeed", "f", 1),
    ("pitchspeed", "f", 1), ("yawspeed", "f", 1), ("pose_covariance", "f", 21),
    ("velocity_covariance", "f", 21), ("frame_id", "B", 1), ("child_frame_id", "B", 1),
    ("reset_counter", "B", 1), ("estimator_type", "B", 1), ("quality", "b", 1)), extensions=3)
DEBUG_FLOAT_ARRAY = Message("DEBUG_FLOAT_ARRAY", 350, 232, (
    ("time_usec", "Q", 1), ("array_id", "H", 1), ("name", "s", 10), ("data", "f", 58)),
    extensions=1)

MESSAGES = (HEARTBEAT, ATTITUDE_QUATERNION, LOCAL_POSITION_NED, MANUAL_CONTROL, COMMAND_LONG,
            COMMAND_ACK, SET_ATTITUDE_TARGET, SET_ACTUATOR_CONTROL_TARGET, STATUSTEXT, ODOMETRY,
            DEBUG_FLOAT_ARRAY)
BY_ID = {m.id: m for m in MESSAGES}
CRC_EXTRA = {m.id: m.crc_extra for m in MESSAGES}
