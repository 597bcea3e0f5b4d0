"""A vehicle's state datagram checked and decoded by compiled code (issue 31): the common case
of `bridge.mavlink.plant`'s receive path, at the cost of its bytes.

`scan_odometry` takes one datagram that is exactly what a vehicle streams at every step, one
ODOMETRY (signed as the link is) in the frames `bridge.mavlink.state.StateTracker` takes without a rotation,
and makes every check the tracker makes before its time checks (framing, checksum with
CRC_EXTRA, frame ids, finite values, a unit quaternion). It returns the wire row or says "not
this case", and the plant then hands the datagram to its reference path (`Peer.accept_fields`,
`StateTracker.on_odometry`), so every refusal has one implementation; a decision that rounding
could tip (the quaternion's norm near the tolerance) is left to the reference path. The values
are the float32 fields widened to float64, what `struct.unpack` gives the reference path.

`recv_state` reads the vehicle's connected socket with libc's recv and scans what it read, in
one call: no bytes object, address tuple or exception per read. `pack_command` is the way back:
the step's SET_ACTUATOR_CONTROL_TARGET framed as `bridge.mavlink.codec.frame` frames it (the
same bytes; a signature is the caller's to write, `codec.sign_frame`), into a preallocated
buffer that `bridge.mavlink.udp_io.send_all` sends. `command_row` is a one-vehicle agent's whole
command in one call: the wrench mapped to controls (`bridge.mavlink.transport.Transport.controls_row`'s
operations), framed and sent.
"""
from __future__ import annotations

import numpy as np

from controller.jit import jit
from controller.layout import S_R

from . import codec
from .sequence import seq_step
from .state import C_MIN, C_OFFSET, C_START, FUTURE_US, OFFSET_WINDOW_S, QUAT_TOL
from .udp_io import (EAGAIN, ECONNREFUSED, EINTR, EWOULDBLOCK, MSG_DONTWAIT, errno, recv,
                     send_all)

__all__ = ["scan_odometry", "recv_state", "take_states", "wire_to_state_ned", "pack_command",
           "command_row", "QUAT_MARGIN", "ODOMETRY_SIZE", "COMMAND_BYTES", "TAKE_STOP",
           "TAKE_FULL", "TAKE_SCANNED", "TAKE_OTHER", "T_ITER", "T_READS", "T_TAKEN",
           "T_DROPPED", "TAKE_SLOTS"]

MAGIC = 0xFD
SIG_LEN = 13
ID_ODOMETRY = codec.ODOMETRY.id
EXTRA_ODOMETRY = codec.ODOMETRY.crc_extra
ODOMETRY_SIZE = 233                   # the payload with its extensions (wire order, see codec)
FRAME_LOCAL_NED = 1
FRAME_LOCAL_FRD = 20
FRAME_BODY_FRD = 12
ID_COMMAND = codec.SET_ACTUATOR_CONTROL_TARGET.id
EXTRA_COMMAND = codec.SET_ACTUATOR_CONTROL_TARGET.crc_extra
COMMAND_SIZE = 43                     # time_usec, controls[8], group_mlx, target system, component
COMMAND_BYTES = 12 + COMMAND_SIZE + SIG_LEN     # pack_command's most
# the norm test is left to the reference path this close to the tolerance (a double's rounding
# of the sum of squares is ~1e-16; this margin is far beyond it and costs no genuine sample)
QUAT_MARGIN = 1e-9


@jit(error_model="python", inline=True)
def row_to_state(w, i, S, o):
    """S[o:o + 18] = [p, R(q) row-major, ξ] of the wire row w[i:i + 13] in a NED world:
    `bridge.mavlink.transport.wire_row_to_state`'s operations in its order (`quat_to_rot_row`),
    so its bits."""
    qw, qx, qy, qz = w[i + 3], w[i + 4], w[i + 5], w[i + 6]
    nq = np.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    qw, qx, qy, qz = qw / nq, qx / nq, qy / nq, qz / nq
    for k in range(3):
        S[o + k] = w[i + k]
    S[o + 3] = 1 - 2 * (qy * qy + qz * qz)
    S[o + 4] = 2 * (qx * qy - qw * qz)
    S[o + 5] = 2 * (qx * qz + qw * qy)
    S[o + 6] = 2 * (qx * qy + qw * qz)
    S[o + 7] = 1 - 2 * (qx * qx + qz * qz)
    S[o + 8] = 2 * (qy * qz - qw * qx)
    S[o + 9] = 2 * (qx * qz - qw * qy)
    S[o + 10] = 2 * (qy * qz + qw * qx)
    S[o + 11] = 1 - 2 * (qx * qx + qy * qy)
    for k in range(6):
        S[o + 12 + k] = w[i + 7 + k]


@jit(error_model="python")
def wire_to_state_ned(wire, S):
    """`bridge.mavlink.transport.wire_to_state` of (n, 13) wire rows in a NED world into S
    (n, 18), row by row as `wire_row_to_state`: the same bits."""
    for r in range(wire.shape[0]):
        row_to_state(wire[r], 0, S[r], 0)


@jit(error_model="python")
def _crc(buf, start, end, extra):
    """MAVLink's X.25 (MCRF4XX) checksum of buf[start:end] followed by CRC_EXTRA."""
    crc = 0xFFFF
    for i in range(start, end + 1):
        b = np.int64(buf[i]) if i < end else extra    # (as Python: no uint8 arithmetic)
        tmp = (b ^ (crc & 0xFF)) & 0xFF
        tmp = (tmp ^ (tmp << 4)) & 0xFF
        crc = ((crc >> 8) ^ (tmp << 8) ^ (tmp << 3) ^ (tmp >> 4)) & 0xFFFF
    return crc


@jit(error_model="python")
def _u64(p, o):
    v = np.uint64(0)
    for k in range(7, -1, -1):
        v = (v << np.uint64(8)) | np.uint64(p[o + k])
    return v


@jit(error_model="python")
def scan_odometry(buf, n, signed, scratch, out, meta):
    """A vehicle's state datagram, the common case of `bridge.mavlink.plant`'s receive path:
    exactly one ODOMETRY (any system and component), signed if ``signed`` (1) else not (its
    signature and replay window are the caller's to check), checksum right, frame_id
    MAV_FRAME_LOCAL_NED or _FRD, child_frame_id MAV_FRAME_BODY_FRD, finite values and a unit
    quaternion (the decisions `bridge.mavlink.state.StateTracker.on_odometry` makes before its
    time checks). Returns 1 with out[0:13] its wire row (x y z, q w x y z, body rates, body
    velocity: the float32 fields widened) and meta = (sequence, system, component, time_usec,
    frame_id), or 0 for anything else (the reference path's). ``scratch``: ≥ 233 bytes."""
    if n < 12 or buf[0] != MAGIC or buf[2] != signed:
        return 0
    plen = np.int64(buf[1])
    if n != 12 + plen + SIG_LEN * signed or plen > ODOMETRY_SIZE:
        return 0
    if (np.int64(buf[7]) | (np.int64(buf[8]) << 8) | (np.int64(buf[9]) << 16)) != ID_ODOMETRY:
        return 0
    c = 10 + plen
    if _crc(buf, 1, c, EXTRA_ODOMETRY) != (np.int64(buf[c]) | (np.int64(buf[c + 1]) << 8)):
        return 0
    odo = scratch[0:ODOMETRY_SIZE]
    for k in range(plen):
        odo[k] = buf[10 + k]
    for k in range(plen, ODOMETRY_SIZE):
        odo[k] = 0
    if (odo[228] != FRAME_LOCAL_NED and odo[228] != FRAME_LOCAL_FRD) or odo[229] != FRAME_BODY_FRD:
        return 0
    f = odo[8:60].view(np.float32)
    for k in range(7):
        out[k] = f[k]
    for k in range(3):
        out[7 + k] = f[10 + k]               # body rates
        out[10 + k] = f[7 + k]               # body velocity
    for k in range(13):
        if not np.isfinite(out[k]):
            return 0
    nq = np.sqrt(out[3] * out[3] + out[4] * out[4] + out[5] * out[5] + out[6] * out[6])
    if abs(nq - 1.0) > QUAT_TOL - QUAT_MARGIN:
        return 0
    t = _u64(odo, 0)
    if t > np.uint64(1 << 62):
        return 0
    meta[0] = buf[4]
    meta[1] = buf[5]
    meta[2] = buf[6]
    meta[3] = np.int64(t)
    meta[4] = odo[228]
    return 1



@jit(error_model="python")
def recv_state(fd, buf, signed, scratch, out, meta):
    """One datagram read from the connected socket ``fd`` into buf with libc's recv, then
    `scan_odometry`: 1 (its case: ``out``, meta[0:5] as it fills them), 2 (any other datagram,
    for the reference path), both with the datagram's length in meta[5]; 0 when the socket is
    empty; −2 for an ICMP error the socket reported (no datagram: read on, as
    `bridge.mavlink.link.UdpSocket.recv_all` does); −1 for any other error (stop reading)."""
    while True:
        r = recv(fd, buf, buf.shape[0], MSG_DONTWAIT)
        if r >= 0:
            break
        e = errno()
        if e == EINTR:
            continue
        if e == ECONNREFUSED:
            return -2
        return 0 if e == EAGAIN or e == EWOULDBLOCK else -1
    meta[5] = r
    return 1 if scan_odometry(buf, r, signed, scratch, out, meta) else 2

# `take_states`: what ended the call …
TAKE_STOP, TAKE_FULL, TAKE_SCANNED, TAKE_OTHER = 0, 1, 2, 3
# … and its counts (int64): reads of the batch (as `recv_state`'s loop in the plant counts
# them), datagrams of the batch, states taken and sequence gaps counted since the caller last
# took them over
T_ITER, T_READS, T_TAKEN, T_DROPPED = range(4)
TAKE_SLOTS = 4


# the link's rule, compiled into the readers that count sequence numbers themselves (an edit of
# sequence.py compiles them again: `controller.jit.KERNEL_SOURCES`)
_seq_step = jit(seq_step, inline=True)


@jit(error_model="python")
def take_states(fd, buf, scratch, out, meta, sysid, compid, limit, now, stale_us, clock, stamp,
                seqs, wire, tot):
    """A real-time vehicle's states read from its connected socket ``fd`` and taken whole, the
    common case of `bridge.mavlink.plant`'s receive path: `recv_state` (unsigned), then, for an
    ODOMETRY from (``sysid``, ``compid``) that `bridge.mavlink.state.StateTracker` would take
    (its time checks on ``clock`` and ``stamp``, the tracker's own arrays, at wall time ``now``;
    ``stale_us``: its stale_after·1e6), what the tracker and the link record: the wire row into
    ``wire``, the clock and stamp moved, the sequence number counted in ``seqs[0]`` (the peer's
    `sequence_array`'s state) as `Peer.commit` counts it, tot[T_TAKEN] and tot[T_DROPPED]
    added to. Anything else the reference path decides, with every refusal: the call returns
    TAKE_SCANNED (a scanned ODOMETRY in buf, ``out`` and ``meta`` as `recv_state` leaves them)
    or TAKE_OTHER (any other datagram) with nothing of it recorded, TAKE_STOP when the socket
    is empty (or failed), TAKE_FULL after ``limit`` reads of the batch (tot[T_ITER])."""
    while tot[T_ITER] < limit:
        r = recv_state(fd, buf, 0, scratch, out, meta)
        if r == 0 or r == -1:
            return TAKE_STOP
        tot[T_ITER] += 1
        if r == -2:
            continue
        tot[T_READS] += 1
        if r == 2:
            return TAKE_OTHER
        if meta[1] != sysid or meta[2] != compid:
            return TAKE_SCANNED
        t = meta[3]
        # `StateTracker._time_ok` (real time) on copies, kept only if the state is taken
        off = clock[C_OFFSET]
        low = clock[C_MIN]
        start = clock[C_START]
        if np.isnan(start) or now - start >= OFFSET_WINDOW_S:
            off = low if not np.isnan(start) and now - start < 2 * OFFSET_WINDOW_S else np.nan
            low = np.nan
            start = now
        d = now * 1e6 - np.float64(t)
        if not np.isnan(off) and d < off - FUTURE_US:
            return TAKE_SCANNED
        if np.uint64(t) <= stamp[0]:
            return TAKE_SCANNED           # a repeat, out of order, or a reboot's
        if np.isnan(off) or d < off:
            off = d
        elif d - off > stale_us:
            return TAKE_SCANNED
        if np.isnan(low) or d < low:
            low = d
        clock[C_OFFSET] = off
        clock[C_MIN] = low
        clock[C_START] = start
        stamp[0] = np.uint64(t)
        for k in range(13):
            wire[k] = out[k]
        st, lost = _seq_step(seqs[0], meta[0])
        seqs[0] = st
        tot[T_DROPPED] += lost
        tot[T_TAKEN] += 1
    return TAKE_FULL


@jit(error_model="python")
def pack_command(buf, t_us, c0, c1, c2, c3, c4, c5, group_mlx, target_system, target_component,
                 seq, sysid, compid, signed, f32):
    """SET_ACTUATOR_CONTROL_TARGET (time_usec ``t_us``, controls c0..c5 then two zeros) framed
    into buf (≥ COMMAND_BYTES) as `bridge.mavlink.codec.frame` frames the payload that
    `codec.SET_ACTUATOR_CONTROL_TARGET.encoded` packs, byte for byte: sequence ``seq``, from
    (sysid, compid); ``signed`` (0 or 1): SIG_LEN bytes left at the end for the caller's
    signature. Returns the frame's length, or −1 when a control does not fit a float32 (the
    reference path then raises as `struct.pack` does). ``f32``: ≥ 8 float32 of scratch."""
    vals = (np.float64(c0), np.float64(c1), np.float64(c2), np.float64(c3), np.float64(c4),
            np.float64(c5), 0.0, 0.0)
    for k in range(8):
        f32[k] = vals[k]
        if np.isinf(f32[k]) and not np.isinf(vals[k]):
            return -1
    t = np.uint64(t_us)
    for k in range(8):
        buf[10 + k] = (t >> np.uint64(8 * k)) & np.uint64(0xFF)
    b = f32[0:8].view(np.uint8)
    for k in range(32):
        buf[18 + k] = b[k]
    buf[50] = group_mlx & 0xFF
    buf[51] = target_system & 0xFF
    buf[52] = target_component & 0xFF
    plen = np.int64(COMMAND_SIZE)
    while plen > 1 and buf[10 + plen - 1] == 0:    # MAVLink 2 drops the trailing zeros
        plen -= 1
    buf[0] = MAGIC
    buf[1] = plen
    buf[2] = signed
    buf[3] = 0
    buf[4] = seq & 0xFF
    buf[5] = sysid & 0xFF
    buf[6] = compid & 0xFF
    buf[7] = ID_COMMAND & 0xFF
    buf[8] = (ID_COMMAND >> 8) & 0xFF
    buf[9] = (ID_COMMAND >> 16) & 0xFF
    e = 10 + plen
    crc = _crc(buf, 1, e, EXTRA_COMMAND)
    buf[e] = crc & 0xFF
    buf[e + 1] = crc >> 8
    return e + 2 + SIG_LEN * signed


@jit(error_model="python")
def command_row(u, S, mw, enu, gc, mass, g, c_out, t_us, group_mlx, target_system,
                target_component, seq, sysid, compid, buf, f32, fds, ok, st):
    """One vehicle's command with the direct mapping, in one call: `Transport.controls_row` of
    the wrench u (6,) at state S[0] (the same operations on the same floats in the same order:
    the same bits) into c_out[0], then `pack_command` of those controls (unsigned) into buf, then
    the frame sent on fds[0] when that is a socket (≥ 0; `send_all`, ok[0] as it sets it).
    ``enu``: the world is not NED (FRD flips y and z of each triple); ``gc``: the baseline that
    cancels gravity g on mass ``mass`` is added; mw: the mapping's max wrench per axis. st[0] = 1
    if a value of u was not finite (taken as 0), st[1] = 1 if a control saturated, st[2] the
    sockets that took the frame. Returns `pack_command`'s length, or −1 (a control beyond
    float32: nothing sent, the reference path then raises as `struct.pack` does)."""
    nan = 0
    for i in range(6):
        x = u[i]
        if not np.isfinite(x):
            nan = 1
            x = 0.0
        c_out[0, i] = x
    if enu:     # body_to_frd: P_B on each group of 3
        c_out[0, 1] = -c_out[0, 1]
        c_out[0, 2] = -c_out[0, 2]
        c_out[0, 4] = -c_out[0, 4]
        c_out[0, 5] = -c_out[0, 5]
    sat = 0
    for i in range(6):
        if gc:
            if i < 3:
                b = -0.0 if enu and i > 0 else 0.0
            else:
                j = i - 3
                b = -mass * (S[0, S_R + j] * g[0] + S[0, S_R + 3 + j] * g[1]
                             + S[0, S_R + 6 + j] * g[2])
                if enu and j > 0:
                    b = -b
            x = (c_out[0, i] + b) / mw[i]
        else:
            x = c_out[0, i] / mw[i]
        if abs(x) > 1.0:
            sat = 1
        c_out[0, i] = -1.0 if x < -1.0 else 1.0 if x > 1.0 else x
    st[0] = nan
    st[1] = sat
    st[2] = 0
    n = pack_command(buf, t_us, c_out[0, 0], c_out[0, 1], c_out[0, 2], c_out[0, 3], c_out[0, 4],
                     c_out[0, 5], group_mlx, target_system, target_component, seq, sysid, compid,
                     0, f32)
    if n > 0 and fds[0] >= 0:
        st[2] = send_all(fds, buf, n, ok)
    return n
