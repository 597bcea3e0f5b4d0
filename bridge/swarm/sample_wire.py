"""A neighbour's sample datagram checked and decoded by compiled code (issue 31): the receive
path's common case at the cost of its bytes.

`scan_sample` takes one datagram that is exactly what an honest neighbour j sends once per
step, ODOMETRY then (if j owns edges) one DEBUG_FLOAT_ARRAY "theta", signed or not as the link
is, and makes every check `bridge.swarm.agent_link` makes of it but the signature's: framing,
system and component, message ids, checksums with CRC_EXTRA, frame ids, finite values, a unit
quaternion, a whole-step stamp not past the receiver's limit, the θ name, array id and values,
and both stamps equal. It returns the sample's step and its values (the wire row in
`agent_link`'s order, then θ), or −1 for anything else, which the link then hands to its
reference path (`AgentLink._on_packet`). So every refusal and every rare case (reordered,
duplicated, split across datagrams, a quaternion near the tolerance) has one implementation,
and this one only ever says "the reference path would take this sample whole"; signatures and
replay windows stay with `bridge.mavlink.link.Peer`, which checks them on the packets found
here. The values are the float32 fields widened to float64, exactly what `struct.unpack` gives
the reference path; nothing is computed from them here except the decisions, and a decision
that rounding could tip (the quaternion's norm near the tolerance) is left to the reference
path.
"""
from __future__ import annotations

import numpy as np

from bridge.mavlink import codec
from bridge.mavlink.state import QUAT_TOL
from controller.jit import jit

__all__ = ["scan_sample", "SCAN_WIDTH", "ODOMETRY_SIZE", "THETA_SIZE"]

MAGIC = 0xFD
COMPONENT = 191                       # agent_link.AGENT_COMPONENT (MAV_COMP_ID_ONBOARD_COMPUTER)
ID_ODOMETRY = codec.ODOMETRY.id
ID_THETA = codec.DEBUG_FLOAT_ARRAY.id
EXTRA_ODOMETRY = codec.ODOMETRY.crc_extra
EXTRA_THETA = codec.DEBUG_FLOAT_ARRAY.crc_extra
ODOMETRY_SIZE = 233                   # the payload with its extensions (wire order, see codec)
THETA_SIZE = 252
FRAME_LOCAL_NED = 1
FRAME_BODY_FRD = 12
SIG_LEN = 13
THETA_NAME = np.frombuffer(b"theta\0", np.uint8).copy()
SCAN_WIDTH = 13 + 58                  # wire row, then at most one chunk of θ
# the norm test is left to the reference path this close to the tolerance (a double's rounding
# of the sum of squares is ~1e-16; this margin is far beyond it and costs no genuine sample)
QUAT_MARGIN = 1e-9


@jit(error_model="python")
def _crc(buf, start, end, extra):
    """MAVLink's X.25 (MCRF4XX) checksum of buf[start:end] followed by CRC_EXTRA."""
    crc = 0xFFFF
    for i in range(start, end + 1):
        b = buf[i] if i < end else extra
        tmp = (b ^ (crc & 0xFF)) & 0xFF
        tmp = (tmp ^ (tmp << 4)) & 0xFF
        crc = ((crc >> 8) ^ (tmp << 8) ^ (tmp << 3) ^ (tmp >> 4)) & 0xFFFF
    return crc


@jit(error_model="python")
def _packet(buf, i, n, signed, sysid, msgid, extra, size, payload):
    """The packet at buf[i:]: signed if ``signed`` else not (its signature is the caller's to
    verify), from (sysid, COMPONENT), id msgid, checksum right, its payload (zero-extended to
    ``size``) copied to ``payload``. Returns its end, or −1."""
    if n - i < 12 or buf[i] != MAGIC or buf[i + 2] != signed:
        return -1
    plen = np.int64(buf[i + 1])
    end = i + 12 + plen + SIG_LEN * signed
    if end > n or plen > size:
        return -1
    if buf[i + 5] != sysid or buf[i + 6] != COMPONENT:
        return -1
    if (np.int64(buf[i + 7]) | (np.int64(buf[i + 8]) << 8) | (np.int64(buf[i + 9]) << 16)) != msgid:
        return -1
    c = i + 10 + plen
    if _crc(buf, i + 1, c, extra) != (np.int64(buf[c]) | (np.int64(buf[c + 1]) << 8)):
        return -1
    for k in range(plen):
        payload[k] = buf[i + 10 + k]
    for k in range(plen, size):
        payload[k] = 0
    return end


@jit(error_model="python")
def _u64(p, o):
    v = np.uint64(0)
    for k in range(7, -1, -1):
        v = (v << np.uint64(8)) | np.uint64(p[o + k])
    return v


@jit(error_model="python")
def scan_sample(buf, n, signed, sysid, n_theta, h_us, limit, scratch, out, seqs):
    """Step s of the sample in datagram buf[:n] from neighbour ``sysid`` (owning ``n_theta`` ≤ 58
    edges), or −1 (see the module docstring). ``signed`` (0 or 1): the link's packets carry
    signatures, which the caller verifies (`bridge.mavlink.link.Peer.take_signed`). On success
    out[0:13] holds the wire row (x y z, q w x y z, body rates, body velocity),
    out[13:13 + n_theta] θ, seqs[0:2] the packets' sequence numbers and seqs[2:4] their ends.
    ``limit``: the newest step the receiver takes; ``scratch``: ≥ 252 bytes."""
    odo = scratch[0:ODOMETRY_SIZE]
    e = _packet(buf, 0, n, signed, sysid, ID_ODOMETRY, EXTRA_ODOMETRY, ODOMETRY_SIZE, odo)
    if e < 0:
        return -1
    seqs[0] = buf[4]
    seqs[2] = e
    if odo[228] != FRAME_LOCAL_NED or odo[229] != FRAME_BODY_FRD:
        return -1
    f = odo[8:60].view(np.float32)          # x y z, q[4], vx vy vz, rates
    for k in range(3):
        out[k] = f[k]
    for k in range(4):
        out[3 + k] = f[3 + k]
    for k in range(3):
        out[7 + k] = f[10 + k]               # body rates
        out[10 + k] = f[7 + k]               # body velocity
    for k in range(13):
        if not np.isfinite(out[k]):
            return -1
    nq = np.sqrt(out[3] * out[3] + out[4] * out[4] + out[5] * out[5] + out[6] * out[6])
    if abs(nq - 1.0) > QUAT_TOL - QUAT_MARGIN:
        return -1
    t = _u64(odo, 0)
    if t > np.uint64(1 << 62):
        return -1
    t = np.int64(t)
    if t % h_us != 0:
        return -1
    s = t // h_us
    if s > limit:
        return -1
    if n_theta == 0:
        return s if e == n else -1
    th = scratch[0:THETA_SIZE]
    e2 = _packet(buf, e, n, signed, sysid, ID_THETA, EXTRA_THETA, THETA_SIZE, th)
    if e2 != n:
        return -1
    seqs[1] = buf[e + 4]
    seqs[3] = e2
    if np.int64(_u64(th, 0)) != t or (np.int64(th[8]) | (np.int64(th[9]) << 8)) != sysid:
        return -1
    for k in range(6):
        if th[10 + k] != THETA_NAME[k]:
            return -1
    d = th[20:20 + 4 * n_theta].view(np.float32)
    for k in range(n_theta):
        if not np.isfinite(d[k]):
            return -1
        out[13 + k] = d[k]
    return s

