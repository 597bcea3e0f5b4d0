"""The struct-level MAVLink 2 codec (bridge/mavlink/codec.py, issue 31) against pymavlink, the
reference it replaces on the per-step path: for every message it has a layout for, random fields
(edge values included: NaN, ±inf, −0, the integer limits, trailing zeros that MAVLink 2 drops)
frame to pymavlink's bytes, signed and unsigned, with the same sequence number, ids, link id and
signing timestamp; everything pymavlink decodes (random payload bytes of every length too)
decodes to the same values, floats bit for bit; what pymavlink refuses (checksum, signature,
length, magic) the codec refuses. Then the users: every output profile's command, the
inter-agent sample and `Peer.accept_fields` give the bytes and fields they gave with pymavlink."""
from __future__ import annotations

import math
import os
import random
import struct

import pytest

os.environ.setdefault("MAVLINK20", "1")

from pymavlink import mavutil  # noqa: E402

from bridge.mavlink import codec  # noqa: E402
from bridge.mavlink import output as out  # noqa: E402
from bridge.mavlink.link import Counters, Peer, crc_ok, mavlink2  # noqa: E402

M = mavlink2
KEY = bytes(range(7, 39))
INT_RANGES = {"B": (0, 255), "b": (-128, 127), "H": (0, 0xFFFF), "h": (-0x8000, 0x7FFF),
              "I": (0, 0xFFFFFFFF), "i": (-0x80000000, 0x7FFFFFFF), "Q": (0, (1 << 64) - 1)}
FLOAT_EDGES = (math.nan, math.inf, -math.inf, 0.0, -0.0, 3.4028234663852886e38, 1e-45, -1.5)


def _pym_class(msg):
    return M.mavlink_map[msg.id]


def _mav(sysid=7, compid=191, seq=0, key=None, link_id=0, ts=0):
    """A pymavlink MAVLink object in a given state (what both encoders read and move)."""
    mav = M.MAVLink(None, srcSystem=sysid, srcComponent=compid)
    mav.seq = seq

    class _H:
        pass

    h = _H()
    h.mav = mav
    if key is not None:
        mavutil.mavfile.setup_signing(h, key, sign_outgoing=True, link_id=link_id,
                                      initial_timestamp=ts)
    return mav


def _value(rng: random.Random, t: str, count: int):
    if t == "s":
        n = rng.randint(0, count)
        return bytes(rng.randint(1, 127) for _ in range(n))
    if t == "f":
        x = rng.choice(FLOAT_EDGES) if rng.random() < 0.3 else rng.uniform(-1e6, 1e6)
        return x
    lo, hi = INT_RANGES[t]
    r = rng.random()
    return lo if r < 0.15 else hi if r < 0.3 else rng.randint(lo, hi)


def _fields(rng: random.Random, msg, zero_tail: bool):
    """Random values by field name (arrays as lists); with zero_tail a random number of the
    last wire fields are zero (MAVLink 2 drops them from the payload)."""
    vals = {}
    for name, t, c in msg.fields:
        vals[name] = _value(rng, t, c) if t == "s" or c == 1 else [_value(rng, t, 1) for _ in range(c)]
    if zero_tail:
        k = rng.randint(1, len(msg.fields))
        for name, t, c in msg.fields[-k:]:
            z = b"" if t == "s" else 0.0 if t == "f" else 0
            vals[name] = z if (t == "s" or c == 1) else [z] * c
    return vals


def _flat(msg, vals) -> list:
    flat = []
    for name, t, c in msg.fields:
        v = vals[name]
        if t != "s" and c > 1:
            flat.extend(v)
        else:
            flat.append(v)
    return flat


def _pym_pack(msg, vals, mav) -> bytes:
    """pymavlink's bytes for these values: its message class built with its own constructor
    (SET_ATTITUDE_TARGET: plus the thrust_body extension, as `output.AttitudeTargetMessage`
    appends it)."""
    cls = _pym_class(msg)
    args = [vals[n] for n in cls.fieldnames]
    m = cls(*args)
    if msg is codec.SET_ATTITUDE_TARGET:
        base = m.unpacker.pack(*_flat(msg, vals)[:-3])
        return m._pack(mav, m.crc_extra, base + struct.pack("<3f", *vals["thrust_body"]))
    return m.pack(mav)


def _bits(x):
    if isinstance(x, float):
        return struct.pack("<d", x)
    if isinstance(x, list):
        return [_bits(v) for v in x]
    return x


# ------------------------------------------------------------------------------ layouts
@pytest.mark.parametrize("msg", codec.MESSAGES, ids=lambda m: m.name)
def test_every_layout_is_pymavlinks(msg):
    cls = _pym_class(msg)
    assert (msg.id, msg.crc_extra, msg.name) == (cls.id, cls.crc_extra, cls.msgname)
    names = [n for n, _, _ in msg.fields]
    if msg is codec.SET_ATTITUDE_TARGET:   # + thrust_body, newer than pymavlink's common.xml
        assert names == cls.ordered_fieldnames + ["thrust_body"]
        assert msg.format == cls.unpacker.format + "3f"
    else:
        assert names == cls.ordered_fieldnames
        assert msg.format == cls.unpacker.format
    assert msg.size == cls.unpacker.size + (12 if msg is codec.SET_ATTITUDE_TARGET else 0)
    assert codec.BY_ID[msg.id] is msg and codec.CRC_EXTRA[msg.id] == cls.crc_extra


# ------------------------------------------------------------------------------ encoding
@pytest.mark.parametrize("signed", [False, True], ids=["unsigned", "signed"])
@pytest.mark.parametrize("msg", codec.MESSAGES, ids=lambda m: m.name)
def test_random_fields_frame_to_pymavlinks_bytes(msg, signed):
    rng = random.Random(f"{msg.name}{signed}")
    truncated = 0
    for trial in range(300):
        vals = _fields(rng, msg, zero_tail=trial % 3 == 0 or trial == 1)
        if trial == 1:   # every field zero: the payload keeps one byte
            vals = _fields(rng, msg, zero_tail=False)
            for name, t, c in msg.fields:
                vals[name] = b"" if t == "s" else ([0] * c if c > 1 else 0)
        state = dict(sysid=rng.randint(0, 255), compid=rng.randint(0, 255), seq=rng.randint(0, 255),
                     key=KEY if signed else None, link_id=rng.randint(0, 255),
                     ts=rng.choice([0, 1, (1 << 48) - 1, rng.randint(0, 1 << 47)]))
        a, b = _mav(**state), _mav(**state)
        ref = _pym_pack(msg, vals, a)
        got = msg.encoded(*_flat(msg, vals)).pack(b)
        assert got == ref, (msg.name, vals)
        assert (b.seq, b.signing.timestamp) == (a.seq, a.signing.timestamp)
        truncated += ref[1] < msg.size
        if trial == 1:
            assert ref[1] == 1
        # and frame() with the payload alone gives the same
        assert codec.frame(_mav(**state), msg, msg.payload(*_flat(msg, vals))) == ref
    assert truncated > 50     # the zero-tail cases did exercise MAVLink 2's truncation


def test_outgoing_messages_quack_like_pymavlinks_for_peer_pack():
    """`Peer.pack` packs an Outgoing as a pymavlink message: sequence numbers count on, signing
    timestamps move by one per packet, one stream for both kinds of message."""
    p, q = Peer(3, 191, Counters(), key=KEY, link_id=9), Peer(3, 191, Counters(), key=KEY, link_id=9)
    q.mav.signing.timestamp = p.mav.signing.timestamp
    for i in range(300):
        hb = (i, 18, 8, 0, 4, 3)
        a = p.pack(p.mav.heartbeat_encode(18, 8, 0, i, 4, 3)) if i % 2 else \
            p.pack(codec.HEARTBEAT.encoded(*hb))
        b = q.pack(codec.HEARTBEAT.encoded(*hb))
        assert a == b
    assert p.mav.seq == q.mav.seq == 300 % 256
    o = codec.ODOMETRY.encoded(*([0] * codec.ODOMETRY.n_values))
    assert o.get_type() == "ODOMETRY" and o.get_msgId() == 331
    with pytest.raises(ValueError):
        o.pack(p.mav, force_mavlink1=True)


def test_setup_signing_is_mavutils():
    allow = (lambda mav, msgid: msgid == 0)   # noqa: E731
    for ts in (None, 0, 12345):
        a, b = _mav(), M.MAVLink(None, srcSystem=7, srcComponent=191)

        class _H:
            mav = a

        mavutil.mavfile.setup_signing(_H(), KEY, sign_outgoing=True, allow_unsigned_callback=allow,
                                      link_id=5, initial_timestamp=ts)
        codec.setup_signing(b, KEY, link_id=5, allow_unsigned_callback=allow, initial_timestamp=ts)
        sa, sb = a.signing, b.signing
        assert (sa.secret_key, sa.sign_outgoing, sa.allow_unsigned_callback, sa.link_id) == \
            (sb.secret_key, sb.sign_outgoing, sb.allow_unsigned_callback, sb.link_id)
        assert abs(sa.timestamp - sb.timestamp) <= (0 if ts is not None else 100_000)  # ≤ 1 s
    import subprocess
    import sys
    # the link (and so an agent) no longer loads mavutil
    code = "import bridge.mavlink.link, sys; print('pymavlink.mavutil' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


# ------------------------------------------------------------------------------ decoding
def _pym_decode(pkt: bytes, key=None):
    rx = _mav(sysid=1, compid=1, key=key)
    if key is not None:
        rx.signing.timestamp = 0
    return rx.decode(bytearray(pkt))


def _pym_values(msg, m) -> dict:
    cls = _pym_class(msg)
    out_ = {}
    for name, t, c in msg.fields:
        if name not in cls.ordered_fieldnames:
            continue
        v = getattr(m, f"_{name}_raw") if t == "s" else getattr(m, name)
        out_[name] = list(v) if isinstance(v, (list, tuple)) else v
    return out_


@pytest.mark.parametrize("signed", [False, True], ids=["unsigned", "signed"])
@pytest.mark.parametrize("msg", codec.MESSAGES, ids=lambda m: m.name)
def test_decodes_what_pymavlink_decodes_bit_for_bit(msg, signed):
    rng = random.Random(f"dec{msg.name}{signed}")
    key = KEY if signed else None
    for trial in range(300):
        mav = _mav(sysid=rng.randint(1, 255), compid=rng.randint(0, 255), seq=rng.randint(0, 255),
                   key=key, link_id=rng.randint(0, 255), ts=rng.randint(1, 1 << 40))
        if trial % 2:
            # random payload bytes of every length (any float bit pattern, signalling NaNs,
            # a payload longer than pymavlink's layout), framed by the codec
            n = rng.randint(1, min(255, msg.size + 8))
            payload = bytes(rng.getrandbits(8) for _ in range(n))
            pkt = codec.frame(mav, msg, payload)
        else:
            pkt = _pym_pack(msg, _fields(rng, msg, zero_tail=trial % 4 == 0), mav)
        m = _pym_decode(pkt, key)
        assert m.get_msgId() == msg.id
        got_msg, flat = codec.decode(pkt, key=key)
        assert got_msg is msg and len(flat) == msg.n_values
        got = msg.as_dict(flat)
        want = _pym_values(msg, m)
        for name, v in want.items():
            assert _bits(got[name]) == _bits(v), (msg.name, name, got[name], v)
        if msg is codec.SET_ATTITUDE_TARGET:   # the extension, as the vehicle reads it
            assert _bits(list(got["thrust_body"])) == _bits(list(out.thrust_body_of(m)))


def test_refuses_what_pymavlink_refuses():
    rng = random.Random(5)
    for msg in codec.MESSAGES:
        for signed in (False, True):
            key = KEY if signed else None
            mav = _mav(sysid=4, compid=191, key=key, link_id=3, ts=1000)
            pkt = _pym_pack(msg, _fields(rng, msg, zero_tail=False), mav)
            codec.decode(pkt, key=key)   # the genuine packet passes
            bad = []
            # a payload or checksum byte flipped
            for i in (HEADER := codec.HEADER_LEN, HEADER + pkt[1] - 1, HEADER + pkt[1] + 1):
                b = bytearray(pkt)
                b[i] ^= 0x5A
                bad.append(("crc", bytes(b)))
            bad.append(("length", pkt[:-1]))                       # truncated
            bad.append(("length", pkt + b"\x00"))                  # trailing junk
            bad.append(("magic", b"\xfe" + pkt[1:]))               # not MAVLink 2
            if signed:
                b = bytearray(pkt)
                b[-1] ^= 1                                         # the signature
                bad.append(("signature", bytes(b)))
                b = bytearray(pkt)
                b[-8] ^= 1                                         # the signed timestamp
                bad.append(("signature", bytes(b)))
            for reason, b in bad:
                with pytest.raises(Exception):
                    _pym_decode(b, key)
                with pytest.raises(codec.CodecError) as e:
                    codec.decode(b, key=key)
                assert e.value.reason == reason, (msg.name, reason, e.value)
    # an unsigned packet where a key is required; an id the codec has no layout for
    pkt = _pym_pack(codec.HEARTBEAT, _fields(rng, codec.HEARTBEAT, False), _mav())
    with pytest.raises(codec.CodecError, match="signature"):
        codec.decode(pkt, key=KEY)
    pkt = _mav().param_request_read_encode(1, 1, b"X", 0).pack(_mav())
    assert isinstance(_pym_decode(pkt), M.MAVLink_unknown) is False   # pymavlink knows it...
    with pytest.raises(codec.CodecError, match="unknown"):
        codec.decode(pkt)                                               # ...the codec does not
    assert crc_ok(pkt) is True           # the link's checksum still covers every message


def test_crc_ok_of_the_link_uses_the_codecs_table_and_agrees_with_pymavlink():
    rng = random.Random(9)
    for msg in codec.MESSAGES:
        pkt = bytearray(_pym_pack(msg, _fields(rng, msg, zero_tail=False), _mav()))
        assert crc_ok(pkt) is True and codec.crc_matches(pkt, msg.crc_extra)
        pkt[codec.HEADER_LEN] ^= 1
        assert crc_ok(pkt) is False and not codec.crc_matches(pkt, msg.crc_extra)
    assert crc_ok(bytes([0xFD, 0, 0, 0, 0, 1, 1, 0xFF, 0xFF, 0xFF, 0, 0])) is None
    assert codec.crc_x25(b"123456789") == 0x6F91 == codec._crc_slow(b"123456789")


# ------------------------------------------------------------------------------ the users
def _reference_command(prof, mav, c, *, target, k, wire):
    """What each output profile sent through pymavlink (lockstep stamps)."""
    if isinstance(prof, out.ActuatorControlTarget):
        return mav.set_actuator_control_target_encode(k * prof.h_us, prof.group_mlx, target, 1,
                                                      [c[0], c[1], c[2], c[3], c[4], c[5], 0.0, 0.0])
    if isinstance(prof, out.DoSetActuator):
        return mav.command_long_encode(target, 1, M.MAV_CMD_DO_SET_ACTUATOR, k & 0xFF, c[0], c[1],
                                       c[2], c[3], c[4], c[5], float(prof.actuator_index_offset))
    if isinstance(prof, out.ArduSubManualControl):
        x, y, z, r, s, t = out.manual_control_axes(c)
        return mav.manual_control_encode(target, x, y, z, r, 0, 0, out.MANUAL_EXTENSIONS, s, t)
    q_d, tb = prof.att.encode(c, wire)
    return out.AttitudeTargetMessage((k * prof.h_ms) & 0xFFFFFFFF, target, 1, out.PX4_TYPE_MASK,
                                     list(q_d), list(tb))


@pytest.mark.parametrize("signed", [False, True], ids=["unsigned", "signed"])
@pytest.mark.parametrize("name", out.PROFILES)
def test_every_output_profile_sends_pymavlinks_bytes(name, signed):
    import numpy as np
    rng = np.random.default_rng(3)
    prof = out.profile(name, h=0.004, J=np.diag([0.043, 0.041, 0.082]),
                       max_wrench=(50.0, 50.0, 50.0, 20.0, 20.0, 20.0), group_mlx=2,
                       actuator_index_offset=1)
    key = KEY if signed else None
    a, b = _mav(sysid=255, key=key, link_id=4, ts=77), _mav(sysid=255, key=key, link_id=4, ts=77)
    for k in range(200):
        c = rng.uniform(-1, 1, 6)
        if k % 5 == 0:
            c[rng.integers(0, 6, 3)] = 0.0      # zero controls: truncation
        if k == 1:
            c[:] = 0.0
        q = rng.normal(size=4)
        wire = np.concatenate([rng.normal(size=3), q / np.linalg.norm(q), rng.normal(size=6)])
        wire = wire.astype(np.float32).astype(float)
        ref = _reference_command(prof, a, c, target=k % 7 + 1, k=k, wire=wire).pack(a)
        got = prof.message(b, c, target=k % 7 + 1, k=k, lockstep=True, wire=wire).pack(b)
        assert got == ref, (name, k)
        a.seq = b.seq = (a.seq + 1) & 0xFF


def test_the_inter_agent_sample_is_pymavlinks():
    import numpy as np

    from bridge.mavlink import frames
    from bridge.swarm.agent_link import NAN21, THETA_PER_MESSAGE, encode_sample, theta_name
    from controller import layout
    from controller.kernels import rot_to_quat_rows

    def reference(mav, n, h_us, S_row, theta, world):   # the pymavlink encoder it replaced
        t = n * h_us
        msgs = []
        if S_row is not None:
            S = np.asarray(S_row, float).reshape(1, layout.S_WIDTH)
            if world != "ned":
                S = frames.state_world_to_ned(S, world)
            q = np.empty((1, 4))
            rot_to_quat_rows(np.ascontiguousarray(S[:, layout.R]), q)
            q = q[0].tolist()
            p, w, v = S[0, layout.P].tolist(), S[0, layout.OMEGA].tolist(), S[0, layout.V].tolist()
            msgs.append(mav.odometry_encode(t, M.MAV_FRAME_LOCAL_NED, M.MAV_FRAME_BODY_FRD, p[0], p[1],
                                            p[2], q, v[0], v[1], v[2], w[0], w[1], w[2], NAN21,
                                            NAN21, 0, M.MAV_ESTIMATOR_TYPE_NAIVE, 100))
        theta = [float(x) for x in (theta or ())]
        for c0 in range(0, len(theta), THETA_PER_MESSAGE):
            ch = theta[c0:c0 + THETA_PER_MESSAGE]
            msgs.append(mav.debug_float_array_encode(
                t, theta_name(c0 // THETA_PER_MESSAGE).encode(), mav.srcSystem,
                ch + [math.nan] * (THETA_PER_MESSAGE - len(ch))))
        return msgs

    rng = np.random.default_rng(4)
    for signed in (False, True):
        key = KEY if signed else None
        pa = Peer(5, 191, Counters(), key=key, link_id=0)
        pb = Peer(5, 191, Counters(), key=key, link_id=0)
        pb.mav.signing.timestamp = pa.mav.signing.timestamp
        for trial in range(100):
            S = np.zeros(layout.S_WIDTH)
            S[layout.P] = rng.normal(size=3) * 10
            qq = rng.normal(size=4)
            qq /= np.linalg.norm(qq)
            S[layout.R] = frames.quat_to_rot(qq[None, :])[0]
            S[layout.XI] = rng.normal(size=6)
            if trial % 7 == 0:
                S[layout.XI] = 0.0
            theta = list(rng.normal(size=int(rng.integers(0, 130))))
            world = "enu" if trial % 2 else "ned"
            row = None if trial % 5 == 4 else S
            th = None if trial % 6 == 5 else theta
            ref = [pa.pack(m) for m in reference(pa.mav, trial, 4000, row, th, world)]
            got = [pb.pack(m) for m in encode_sample(pb.mav, trial, 4000, row, th, world)]
            assert got == ref, trial


def test_peer_accept_fields_takes_the_codecs_layouts_as_pymavlinks_classes():
    from bridge.mavlink.signing_state import wall_timestamp
    rng = random.Random(11)
    for msg in (codec.ODOMETRY, codec.DEBUG_FLOAT_ARRAY, codec.SET_ACTUATOR_CONTROL_TARGET):
        for key in (None, KEY):
            tx = _mav(sysid=2, compid=191, key=key, link_id=0, ts=wall_timestamp())
            for _ in range(50):
                pkt = _pym_pack(msg, _fields(rng, msg, zero_tail=rng.random() < 0.5), tx)
                tx.seq = (tx.seq + 1) & 0xFF
                ra, rb = Peer(1, 191, Counters(), key=key), Peer(1, 191, Counters(), key=key)
                fa = ra.accept_fields(pkt, {msg.id: _pym_class(msg)})
                fb = rb.accept_fields(pkt, {msg.id: msg})
                assert fa is not None and fb is not None
                assert _bits(list(fa[1])) == _bits(list(fb[1][:len(fa[1])]))


@pytest.mark.parametrize("msg", [codec.SET_ACTUATOR_CONTROL_TARGET, codec.SET_ATTITUDE_TARGET,
                                 codec.MANUAL_CONTROL])
def test_a_received_command_reads_as_pymavlinks_message(msg):
    """`codec.Received` (what the loopback vehicle makes of a per-step command) against
    pymavlink's decoded message: every field pymavlink has, bit for bit (floats) or equal, and
    the message's id, type, bytes and sender."""
    rng = random.Random(msg.id)
    for _ in range(100):
        tx = _mav(sysid=rng.randint(1, 255), compid=rng.randint(0, 255), seq=rng.randint(0, 255))
        pkt = _pym_pack(msg, _fields(rng, msg, zero_tail=rng.random() < 0.5), tx)
        want = M.MAVLink(None).decode(bytearray(pkt))
        got = Peer(1, 191, Counters()).accept_fields(pkt, {msg.id: msg})
        r = codec.Received(msg, got[1], pkt)
        for name in want.get_fieldnames():
            a, b = getattr(want, name), getattr(r, name)
            if isinstance(a, (list, tuple)):
                assert _bits(list(a)) == _bits(list(b)), name
            else:
                assert _bits([a]) == _bits([b]), name
        assert (r.get_msgId(), r.get_type(), bytes(r.get_msgbuf())) == \
            (want.get_msgId(), want.get_type(), bytes(want.get_msgbuf()))
        assert (r.get_srcSystem(), r.get_srcComponent()) == \
            (want.get_srcSystem(), want.get_srcComponent())
        if msg is codec.SET_ATTITUDE_TARGET:
            assert _bits(list(out.thrust_body_of(r))) == _bits(list(out.thrust_body_of(want)))
