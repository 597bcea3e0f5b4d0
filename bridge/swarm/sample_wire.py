"""A neighbour's sample datagram checked and decoded, and the agent's own encoded, by compiled
code (issue 31): the link's common case at the cost of its bytes.

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

`pack_sample` is the send side's mirror: what `agent_link.encode_sample` and `Peer.pack` make of
one sample (ODOMETRY and θ, the quaternion by `controller.kernels.quat_of`, the payloads'
trailing zeros dropped, the checksums), written into a preallocated buffer in one call; a signed
link's signatures are then filled by `bridge.mavlink.codec.sign_frame` (SHA-256 stays with
hashlib). tests/bridge/test_sample_wire.py checks its datagrams against the reference path's,
byte for byte, signed and unsigned. `publish_sample` is an unsigned link's whole publish in one
call: the owned θ gathered from the step's θ, `pack_sample`, the datagram sent to every neighbour.
"""
from __future__ import annotations

import numpy as np

from bridge.mavlink import codec
from bridge.mavlink.state import QUAT_TOL
from bridge.mavlink.state_wire import QUAT_MARGIN, _crc, _seq_step, _u64, row_to_state
from controller.jit import jit
from controller.kernels import FRESH, quat_of
from controller.layout import S_OMEGA, S_P, S_R, S_V

from bridge.mavlink.udp_io import ECONNREFUSED, EINTR, MSG_DONTWAIT, errno, recv, send_all

__all__ = ["scan_sample", "pack_sample", "publish_sample", "held_rows", "drain_samples", "age_rules", "AGE_BINS", "SCAN_WIDTH",
           "SCAN_STATE",
           "ODOMETRY_SIZE", "THETA_SIZE", "PACK_BYTES", "D_DATAGRAMS", "D_RECEIVED", "D_DROPPED",
           "D_LEN", "D_BATCH", "D_WIDTH"]

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
SCAN_STATE = 13 + 58                  # scan_sample's out: wire row, at most one chunk of θ,
SCAN_WIDTH = SCAN_STATE + 18          # then the state row in NED
PACK_BYTES = 2 * (12 + SIG_LEN) + ODOMETRY_SIZE + THETA_SIZE   # pack_sample's most
ESTIMATOR_NAIVE = 1                   # MAV_ESTIMATOR_TYPE_NAIVE
QUALITY = 100


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
def scan_sample(buf, n, signed, sysid, n_theta, h_us, limit, scratch, out, seqs):
    """Step s of the sample in datagram buf[:n] from neighbour ``sysid`` (owning ``n_theta`` ≤ 58
    edges), or −1 (see the module docstring). ``signed`` (0 or 1): the link's packets carry
    signatures, which the caller verifies (`bridge.mavlink.link.Peer.take_signed`). On success
    out[0:13] holds the wire row (x y z, q w x y z, body rates, body velocity),
    out[13:13 + n_theta] θ, out[SCAN_STATE:SCAN_STATE + 18] the state row of a NED world
    (`bridge.mavlink.transport.wire_row_to_state`'s operations in its order: the same bits),
    seqs[0:2] the packets' sequence numbers and seqs[2:4] their ends. ``limit``: the newest
    step the receiver takes; ``scratch``: ≥ 252 bytes."""
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
    row_to_state(out, 0, out, SCAN_STATE)
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


# drain_samples' totals: datagrams and packets taken, sequence gaps (losses), the length of the
# datagram handed back and how many its socket had given in this batch, the most datagrams read
# from one socket in one batch, the step of a signed sample handed back for its signatures
D_DATAGRAMS, D_RECEIVED, D_DROPPED, D_LEN, D_K, D_BATCH, D_STEP = range(7)
D_WIDTH = 7


@jit(error_model="python")
def drain_samples(q0, k0, fds, sysids, n_thetas, h_us, limit, signed, batch, now, buf, scratch,
                  out, seqs, held_step, held, held_t, counts, last_seq, totals):
    """Reads the neighbours' sockets fds[q0:] (connected: the kernel hands socket q neighbour
    q's datagrams only) with libc's recv, each until it is empty or ``batch`` datagrams were
    read (k0 of socket q0's already), and takes every datagram that `scan_sample` takes whole
    (``n_thetas[q]`` ≥ 0 edges owned; −1: none) and that is newer than held_step[q], as
    `AgentLink._take_sample` takes it: the sample into held_step[q], held[q] (scan_sample's
    ``out``) and held_t[q] = ``now``, counts[q] += (packets, 1), its packets' sequence numbers
    through last_seq[q] (the peer's sequence states) as `Peer._count_seq` counts them, and the `D_*` totals.
    Returns −1 once every socket is empty; 3q when the datagram in buf[:totals[D_LEN]] (from
    neighbour q, the totals[D_K]-th of its batch) is for the reference path; 3q + 1 when
    socket q gave ``batch`` datagrams (the caller's deadline decides whether to read on);
    ``signed`` (1): 3q + 2 when that datagram would be taken but for its signatures, which the
    caller verifies (scan_sample's ``out`` and ``seqs`` filled, the step in totals[D_STEP]):
    nothing of it is taken here."""
    m = fds.shape[0]
    cap = buf.shape[0]
    for q in range(q0, m):
        k = k0 if q == q0 else 0
        while k < batch:
            r = recv(fds[q], buf, cap, MSG_DONTWAIT)
            if r < 0:
                e = errno()
                if e == EINTR:
                    continue
                if e == ECONNREFUSED:     # an ICMP error reported on the connected socket
                    k += 1
                    continue
                break                     # empty (EAGAIN), or an error Python's read stops at
            k += 1
            if k > totals[D_BATCH]:
                totals[D_BATCH] = k
            nt = n_thetas[q]
            s = -1
            if nt >= 0:
                s = scan_sample(buf, r, signed, sysids[q], nt, h_us, limit, scratch, out, seqs)
            if s < 0 or (held_step[q] >= 0 and s <= held_step[q]) or signed:
                totals[D_LEN] = r
                totals[D_K] = k
                totals[D_STEP] = s
                return 3 * q + (2 if s >= 0 and signed and
                                (held_step[q] < 0 or s > held_step[q]) else 0)
            npk = 2 if nt > 0 else 1
            for p in range(npk):
                st, lost = _seq_step(last_seq[q], seqs[p])
                last_seq[q] = st
                totals[D_DROPPED] += lost
            totals[D_DATAGRAMS] += 1
            totals[D_RECEIVED] += npk
            counts[q, 0] += npk
            counts[q, 1] += 1
            held_step[q] = s
            held_t[q] = now
            for i in range(out.shape[0]):
                held[q, i] = out[i]
        if k >= batch:
            return 3 * q + 1
    return -1

# age_rules' histogram of the ages used, per neighbour: ages 0 … AGE_BINS − 2 (older ones are
# recorded by the caller, who knows them exactly)
AGE_BINS = 4096


@jit(error_model="python")
def age_rules(n, held_step, max_age, hold, future, ages, verdict, mode, hist, held, rx, rx_q,
              rx_r, rx_c):
    """`AgentLink.age_rule` of every neighbour q at step n over the drain's arrays: its age
    (ages[q] = n − held_step[q]; 0 before its first sample, when the rule counts from step 0),
    recorded in hist[q] as `age_steps` records it; its verdict (0 fresh, 1 hold, 2 fail-safe;
    ``max_age`` < 0: none) and `agent_step`'s mode[q] (`FRESH` or stale); then the held θ of
    each received edge, rx[rx_r[i]] = held[rx_q[i], rx_c[i]], where q holds a sample. Returns 1
    when the caller must look again (an age past the histogram, or a sample stamped more than
    ``future`` steps after n: `AgentLink._verdict` decides those), else 0."""
    again = 0
    for q in range(held_step.shape[0]):
        s = held_step[q]
        if s < 0:
            age = n
            ages[q] = 0
        else:
            age = n - s
            ages[q] = age
            a = age if age > 0 else 0
            if a >= AGE_BINS - 1 or age < -future:
                again = 1
            else:
                hist[q, a] += 1
        if max_age < 0 or age <= max_age:
            v = 0
        elif age <= max_age + hold:
            v = 1
        else:
            v = 2
        verdict[q] = v
        mode[q] = FRESH if v == 0 else FRESH + 1
    for i in range(rx_q.shape[0]):
        q = rx_q[i]
        if held_step[q] >= 0:
            rx[rx_r[i]] = held[q, rx_c[i]]
    return again


@jit(error_model="python")
def _frame(buf, o, plen_full, signed, seq, sysid, msgid, extra):
    """Frames the payload at buf[o + 10:o + 10 + plen_full] in place: its trailing zeros dropped
    (one byte kept), the header before it and the checksum after it, SIG_LEN bytes left for the
    signature when ``signed``. Returns the frame's end."""
    plen = plen_full
    while plen > 1 and buf[o + 10 + plen - 1] == 0:
        plen -= 1
    buf[o] = MAGIC
    buf[o + 1] = plen
    buf[o + 2] = signed
    buf[o + 3] = 0
    buf[o + 4] = seq & 0xFF
    buf[o + 5] = sysid
    buf[o + 6] = COMPONENT
    buf[o + 7] = msgid & 0xFF
    buf[o + 8] = (msgid >> 8) & 0xFF
    buf[o + 9] = (msgid >> 16) & 0xFF
    c = o + 10 + plen
    crc = _crc(buf, o + 1, c, extra)
    buf[c] = crc & 0xFF
    buf[c + 1] = crc >> 8
    return c + 2 + SIG_LEN * signed


@jit(error_model="python")
def _put_u64(buf, o, v):
    for k in range(8):
        buf[o + k] = (v >> (8 * k)) & 0xFF


@jit(error_model="python")
def _put_f32(buf, o, f32, m):
    """f32[:m] as little-endian bytes at buf[o:]."""
    b = f32[:m].view(np.uint8)
    for k in range(4 * m):
        buf[o + k] = b[k]


@jit(error_model="numpy")
def pack_sample(buf, t_us, S, pose, theta, n_theta, sysid, seq, signed, f32, ends):
    """The datagram of one sample as `bridge.swarm.agent_link.encode_sample` and `Peer.pack`
    make it, byte for byte, into buf (≥ PACK_BYTES): ODOMETRY of the NED row S (18,) if
    ``pose``, then one DEBUG_FLOAT_ARRAY "theta" of theta[:n_theta] (0 < n_theta ≤ 58; none if
    0), sequence numbers from ``seq`` on, from (sysid, COMPONENT). ``signed`` (0 or 1): each
    frame ends in SIG_LEN bytes that the caller fills (`bridge.mavlink.codec.sign_frame`).
    ends[k]: the end of frame k. Returns the number of frames, or −1 when a value does not fit
    a float32 (the caller's reference path then raises as `struct.pack` does). ``f32``: ≥ 58
    float32 of scratch."""
    nf = 0
    o = 0
    if pose:
        w, x, y, z = quat_of(S[S_R], S[S_R + 1], S[S_R + 2], S[S_R + 3], S[S_R + 4],
                             S[S_R + 5], S[S_R + 6], S[S_R + 7], S[S_R + 8])
        vals = (S[S_P], S[S_P + 1], S[S_P + 2], w, x, y, z, S[S_V], S[S_V + 1], S[S_V + 2],
                S[S_OMEGA], S[S_OMEGA + 1], S[S_OMEGA + 2])
        for k in range(13):
            f32[k] = vals[k]
            if np.isinf(f32[k]) and not np.isinf(vals[k]):
                return -1
        for k in range(13, 55):                 # covariances unknown: NaN, then zeros
            f32[k] = np.nan if k == 13 or k == 34 else 0.0
        p = o + 10
        _put_u64(buf, p, t_us)
        _put_f32(buf, p + 8, f32, 55)
        buf[p + 228] = FRAME_LOCAL_NED
        buf[p + 229] = FRAME_BODY_FRD
        buf[p + 230] = 0
        buf[p + 231] = ESTIMATOR_NAIVE
        buf[p + 232] = QUALITY
        o = _frame(buf, o, ODOMETRY_SIZE, signed, seq, sysid, ID_ODOMETRY, EXTRA_ODOMETRY)
        ends[nf] = o
        nf += 1
    if n_theta > 0:
        for k in range(58):
            if k < n_theta:
                f32[k] = theta[k]
                if np.isinf(f32[k]) and not np.isinf(theta[k]):
                    return -1
            else:
                f32[k] = np.nan
        p = o + 10
        _put_u64(buf, p, t_us)
        buf[p + 8] = sysid & 0xFF
        buf[p + 9] = (sysid >> 8) & 0xFF
        for k in range(10):
            buf[p + 10 + k] = THETA_NAME[k] if k < 6 else 0
        _put_f32(buf, p + 20, f32, 58)
        o = _frame(buf, o, THETA_SIZE, signed, seq + nf, sysid, ID_THETA, EXTRA_THETA)
        ends[nf] = o
        nf += 1
    return nf


@jit(error_model="numpy")
def publish_sample(buf, t_us, S, theta, rows, th, sysid, seq, f32, ends, fds, ok, st):
    """An unsigned link's sample in one call: th[i] = theta[rows[i]] (the owned θ after the jump
    stage, in the link's order), `pack_sample` of the NED row S[0] and th into buf, then the
    datagram sent on each neighbour's connected socket (fds; `bridge.mavlink.udp_io.send_all`,
    ok as it sets it). st[0]: the sockets that took it. Returns `pack_sample`'s frame count
    (nothing sent when it is −1: a value beyond float32)."""
    m = rows.shape[0]
    for i in range(m):
        th[i] = theta[rows[i]]
    nf = pack_sample(buf, t_us, S[0], True, th, m, sysid, seq, 0, f32, ends)
    st[0] = 0
    if nf > 0:
        st[0] = send_all(fds, buf, ends[nf - 1], ok)
    return nf


@jit(error_model="python")
def held_rows(S, own, held_step, held):
    """The neighbourhood's state for a step: S[0] = own[0] (the vehicle's row), and for every
    neighbour q holding a sample (held_step[q] ≥ 0) S[q + 1] = its state row in ``held`` (the
    drain's rows, `SCAN_STATE` on); the rows of the others stay as they are."""
    W = S.shape[1]
    for c in range(W):
        S[0, c] = own[0, c]
    for q in range(held_step.shape[0]):
        if held_step[q] >= 0:
            for c in range(W):
                S[q + 1, c] = held[q, SCAN_STATE + c]
