"""Losses from a sender's MAVLink sequence numbers, exactly, where packets come late or twice.

A sender numbers its packets modulo 256. A gap in the numbers is counted as that many packets
lost; a number that comes late (reordered on the way, or read after newer ones) fills a gap
counted before, and is taken off the count; a number that comes twice counts once. The last
``SEQ_WINDOW`` numbers before the newest are remembered for that. A number further back than
that (up to 127 behind: modulo 256, anything further is ahead) is left out: a packet that
late, or a sender that started again, cannot be told apart from one number, and moving the
newest back to it would count the way forward again as lost (a sample resent 45 packets late
made 45). A sender that starts again is counted on once its numbers are within reach again.

The state of one sender is one int64 (kept in a dict by `bridge.mavlink.link.Peer`, in an
array by the compiled readers, `bridge.mavlink.state_wire` and `bridge.swarm.sample_wire`):
−1 before its first packet, else ``last | seen << 8``: the newest number, and a bit for each of
the SEQ_WINDOW numbers before it (bit i: number last − 1 − i), set where the number came or
was never counted lost. This module is plain Python: `state_wire` compiles `seq_step` into its
readers (and the ahead-of-time module, `bridge.swarm.aot`), the link calls it as it is.
"""
from __future__ import annotations

SEQ_WINDOW = 32                       # late numbers recognised, behind the newest
_ALL = (1 << SEQ_WINDOW) - 1


def seq_step(state: int, seq: int):
    """(the state after a packet numbered ``seq``, the packets it finds lost: the gap before
    it, or −1 for a late one that fills a gap counted before, else 0)."""
    if state < 0:
        return seq | (_ALL << 8), 0
    last = state & 0xFF
    seen = state >> 8
    gap = (seq - last - 1) & 0xFF
    if gap < 128:                     # ahead: the numbers between are lost (for now)
        d = gap + 1
        if d > SEQ_WINDOW:
            seen = 0
        else:
            seen = ((seen & (_ALL >> d)) << d) | (1 << (d - 1))
        return seq | (seen << 8), gap
    back = (last - seq) & 0xFF        # behind the newest by this many
    if back == 0:
        return state, 0               # the newest, again
    if back <= SEQ_WINDOW:
        bit = 1 << (back - 1)
        if seen & bit:
            return state, 0           # came already (or was never counted lost)
        return state | (bit << 8), -1
    return state, 0                   # far behind: left out (see the module's doc)


def seq_last(state: int):
    """The newest sequence number a state holds (None: none yet)."""
    return None if state < 0 else state & 0xFF
