"""ROS 2 CDR messages for the MCAP log (``se3sync run --log-encoding cdr``).

The JSON log spends most of a 1000-agent run formatting and compressing text (1.3 MB a
record). In CDR a number is its 8 bytes, and a message of a run has the same shape at every
record: only its numbers and time stamps change. So each message kind is serialised once, by
mcap-ros2-support's encoder with a marked value in every place that varies (`compile_layout`),
and each record writes its numbers into the marked places of a buffer that holds those bytes
(`Layout.fill`, a compiled loop). `decode` reads a message with a function generated for its
type (`cdr_decode`); `decode_reference` is mcap-ros2-support's decoder, which tests hold it to.

Schemas are ROS 2 ``.msg`` files (``ros2_schemas/``): Foxglove's ``foxglove_msgs`` as published,
the ``geometry_msgs`` and ``builtin_interfaces`` types they use, and ``se3sync_msgs`` for our own
channels. ROS 2 field names are lower case, so ``mu_U``, ``U``, ``V`` and ``kX_U`` are written
``mu_u``, ``u``, ``v`` and ``kx_u``, and a time's ``nsec`` is ``nanosec``; `decode` gives back the
JSON log's names, so readers see one vocabulary.
"""
from __future__ import annotations

import struct
from functools import lru_cache
from pathlib import Path

import numpy as np

from controller import jit

from .cdr_decode import decoder, parse_msg

__all__ = ["SCHEMA", "schema_text", "compile_layout", "Layout", "decode", "decode_reference",
           "MODE"]

_DIR = Path(__file__).with_name("ros2_schemas")
_SEP = "=" * 80

# channel -> ROS 2 type of its messages
SCHEMA = {"/tf": "foxglove_msgs/msg/FrameTransforms", "/edges": "se3sync_msgs/msg/Edges",
          "/agents": "se3sync_msgs/msg/Agents", "/lyapunov": "se3sync_msgs/msg/Lyapunov",
          "/scene": "foxglove_msgs/msg/SceneUpdate", "trail": "foxglove_msgs/msg/PosesInFrame"}

_PRIMITIVE = {"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16",
              "int32", "uint32", "int64", "uint64", "string", "wstring"}

# an edge's mode string as the uint32 its 4 bytes make (see Layout.fill)
MODE = {m: int.from_bytes(m.encode(), "little") for m in ("flow", "jump")}


def _deps(pkg: str, text: str) -> list[str]:
    """The message types a .msg text uses, as pkg/Name, in order of first use."""
    out = []
    for line in text.splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        typ = line.split()[0].split("[", 1)[0].split("<", 1)[0]
        if typ in _PRIMITIVE:  # constants and defaults are of primitive types too
            continue
        full = typ if "/" in typ else f"{pkg}/{typ}"
        if full not in out:
            out.append(full)
    return out


@lru_cache(maxsize=None)
def schema_text(name: str) -> str:
    """The concatenated ROS 2 message definition of ``pkg/msg/Name`` (the format rosbag2 and
    Foxglove read): its .msg text, then each type it uses, depth first, after a line of 80 '='
    and ``MSG: pkg/Name``."""
    pkg, _, msg = name.split("/")
    order, seen = [], set()

    def visit(full):
        p, m = full.split("/")
        text = (_DIR / p / f"{m}.msg").read_text()
        for d in _deps(p, text):
            if d not in seen:
                seen.add(d)
                order.append(d)
                visit(d)
        return text

    parts = [visit(f"{pkg}/{msg}")]
    for d in order:
        p, m = d.split("/")
        parts.append(f"{_SEP}\nMSG: {d}\n{(_DIR / p / f'{m}.msg').read_text()}")
    return "\n".join(parts)


@lru_cache(maxsize=None)
def _codec(name: str):
    # the functions mcap_ros2's own Writer and DecoderFactory build their codecs with
    from mcap_ros2._dynamic import generate_dynamic, serialize_dynamic

    text = schema_text(name)
    return serialize_dynamic(name, text)[name], generate_dynamic(name, text)[name]


# Markers. A float place k holds the float64 whose bits are _F_MARK << 32 | k (finite, ~1e8);
# a time place j (sec or nanosec) the uint32 _T_MARK << 16 | j; a mode place j the 4-character
# string 0x7F + j in three base-64 digits from '0'. CDR aligns a float64 to 8 and a uint32 or a
# string's length to 4 counting from the end of the 4-byte header, so the markers are looked for
# at those offsets only, where no marker of one kind can be read as one of another.
_F_MARK, _T_MARK = 0x41A5A5A5, 0x25A5


def _mode_marker(j: int) -> str:
    return "\x7f" + "".join(chr(0x30 + (j >> s & 63)) for s in (12, 6, 0))


def _scatter_py(a, w, R, f8, v, sec, nsec, t, mode, modes):
    """Rows 0..R-1 of a layout's buffer (``a`` float64, ``w`` its uint32 view): the numbers,
    time stamps and modes into their places. Compiled (`_scatter`) and without the GIL: the
    log's writer thread fills while the loop steps."""
    for r in range(R):
        for k in range(f8.size):
            a[r, f8[k]] = v[r, k]
        s = t[r] // 1_000_000_000
        ns = t[r] - s * 1_000_000_000
        for k in range(sec.size):
            w[r, sec[k]] = s
        for k in range(nsec.size):
            w[r, nsec[k]] = ns
        for k in range(mode.size):
            w[r, mode[k]] = modes[r, k]


_compiled = []


def _scatter(*args):
    if not _compiled:
        # an agent process runs it from its ahead-of-time kernels (`bridge.swarm.aot`), without
        # numba; elsewhere numba is loaded here, not when the module is: reading a log
        # (`se3sync plot`) or writing a JSON one does not need it
        aot = jit.aot_module()
        f = getattr(aot, "cdr_scatter", None) if aot is not None else None
        if f is None:
            f = jit.numba_module().njit(cache=True, nogil=True)(_scatter_py)
        _compiled.append(f)
    _compiled[0](*args)


class Layout:
    """The bytes of one message with the places of its numbers (byte offsets, in the order the
    builder asked for them): ``f8`` float64 places, ``sec`` / ``nsec`` the time stamps', ``mode``
    the 4-byte edge modes'."""

    def __init__(self, data: bytes, f8, sec, nsec, mode):
        self.tpl = np.frombuffer(data, np.uint8)
        self.size = len(data)
        # a message is kept at byte 4 of a float64 row: its float64 places (offsets 4 mod 8)
        # and its uint32 ones are then aligned
        self._w = (self.size + 4 + 7) // 8
        self.f8 = 1 + (np.asarray(f8, np.int64) - 4) // 8
        self.sec = 1 + np.asarray(sec, np.int64) // 4
        self.nsec = 1 + np.asarray(nsec, np.int64) // 4
        self.mode = 1 + np.asarray(mode, np.int64) // 4
        self._buf = np.empty((0, self._w))
        self._none = np.zeros((0, 0), np.uint32)

    def fill(self, values, t_ns, modes=None) -> np.ndarray:
        """R messages as the rows of a (R, size) uint8 array: ``values`` (R, K) float64 in the
        builder's order (K = len(f8); shape (K,) for one message), ``t_ns`` R time stamps (or
        one), ``modes`` (R, len(mode)) uint32 (`MODE` values). The rows are a view of the
        layout's own buffer, valid until its next fill: the constant bytes are written once,
        and a fill writes only the places."""
        v = np.ascontiguousarray(values, np.float64).reshape(-1, len(self.f8))
        R = v.shape[0]
        if R > len(self._buf):
            self._buf = np.empty((max(R, 2 * len(self._buf)), self._w))
            self._buf.view(np.uint8)[:, 4:4 + self.size] = self.tpl
        t = np.ascontiguousarray(np.broadcast_to(np.asarray(t_ns, np.int64).reshape(-1), (R,)))
        m = (self._none if not len(self.mode)
             else np.ascontiguousarray(modes, np.uint32).reshape(R, -1))
        buf = self._buf
        _scatter(buf, buf.view(np.uint32), R, self.f8, v, self.sec, self.nsec, t, self.mode, m)
        return buf.view(np.uint8)[:R, 4:4 + self.size]


def compile_layout(name: str, build) -> Layout:
    """Serialises ``build(f, t, mode)`` (the message as a dict: ``f()`` for each varying
    float64 in the order `Layout.fill` takes them, ``t()`` for each time stamp ({"sec",
    "nanosec"}), ``mode()`` for each edge mode) and finds the places of its markers."""
    n = {"f": 0, "t": 0, "m": 0}
    t_kind = []

    def f():
        k = n["f"]
        n["f"] += 1
        return struct.unpack("<d", struct.pack("<Q", _F_MARK << 32 | k))[0]

    def t():
        j = n["t"]
        n["t"] += 2
        t_kind.extend(("sec", "nsec"))
        return {"sec": _T_MARK << 16 | j, "nanosec": _T_MARK << 16 | (j + 1)}

    def mode():
        j = n["m"]
        n["m"] += 1
        return _mode_marker(j)

    msg = build(f, t, mode)
    if max(n.values()) >= 1 << 16:
        raise ValueError(f"{name}: more than 65536 places of one kind")
    enc, _ = _codec(name)
    data = enc(msg)
    b = np.frombuffer(data, np.uint8)
    w8 = b[4:4 + 8 * ((len(b) - 4) // 8)].view("<u8")
    (i8,) = np.nonzero((w8 >> np.uint64(32)) == _F_MARK)
    k8 = (w8[i8] & np.uint64(0xFFFFFFFF)).astype(np.int64)
    w4 = b[:4 * (len(b) // 4)].view("<u4")
    (i4,) = np.nonzero((w4 >> np.uint32(16)) == _T_MARK)
    k4 = (w4[i4] & np.uint32(0xFFFF)).astype(np.int64)
    by = w4.view(np.uint8).reshape(-1, 4)
    digits = (by[:, 1:] >= 0x30) & (by[:, 1:] < 0x70)
    (im,) = np.nonzero((by[:, 0] == 0x7F) & digits.all(axis=1))
    km = ((by[im, 1].astype(np.int64) - 0x30) << 12 | (by[im, 2].astype(np.int64) - 0x30) << 6
          | (by[im, 3].astype(np.int64) - 0x30))
    for what, keys, count in (("float", k8, n["f"]), ("time", k4, n["t"]), ("mode", km, n["m"])):
        if len(keys) != count or (count and not np.array_equal(np.sort(keys), np.arange(count))):
            raise ValueError(f"{name}: found {len(keys)} {what} places of {count}")
    f8 = np.empty(n["f"], np.int64)
    f8[k8] = 4 + 8 * i8
    t4 = np.empty(n["t"], np.int64)
    t4[k4] = 4 * i4
    md = np.empty(n["m"], np.int64)
    md[km] = 4 * im
    kinds = np.array(t_kind)
    return Layout(data, f8, t4[kinds == "sec"], t4[kinds == "nsec"], md)


# names a CDR message gives back in the JSON log's vocabulary, by ROS 2 type
_RENAME = {"builtin_interfaces/Time": {"nanosec": "nsec"},
           "builtin_interfaces/Duration": {"nanosec": "nsec"},
           "se3sync_msgs/Edge": {"mu_u": "mu_U", "u": "U"},
           "se3sync_msgs/Lyapunov": {"v": "V", "kx_u": "kX_U"}}


def _plain(x):
    slots = getattr(type(x), "__slots__", None)
    if slots is not None and hasattr(x, "_type"):
        ren = _RENAME.get(x._type.replace("/msg/", "/"), {})
        return {ren.get(k, k): _plain(getattr(x, k)) for k in slots}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, (bytes, bytearray)):
        return list(x)
    return x


@lru_cache(maxsize=None)
def _decoder(name: str):
    defs = {}

    def visit(full):
        if full not in defs:
            p, m = full.split("/")
            defs[full] = parse_msg(p, (_DIR / p / f"{m}.msg").read_text())
            for _, base, _, _ in defs[full]:
                if "/" in base:
                    visit(base)

    pkg, _, msg = name.split("/")
    visit(f"{pkg}/{msg}")
    return decoder(name, defs, _RENAME)


def decode(name: str, data: bytes) -> dict:
    """A CDR message of ROS 2 type ``name`` as the dict the JSON log would give (names as
    there, times as {"sec", "nsec"}), by the decoder generated for its type (`cdr_decode`).
    Raises ValueError or struct.error on a message that is not whole."""
    return _decoder(name)(data)


def decode_reference(name: str, data: bytes) -> dict:
    """The same dict by mcap-ros2-support's own decoder (19 s against 3 s on a 1000-agent
    log's second); the tests hold `decode` to it."""
    return _plain(_codec(name)[1](data))
