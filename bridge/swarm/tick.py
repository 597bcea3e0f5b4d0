"""An agent step's compiled part in one call over one workspace (issue 31): the age rule of every
neighbour, the law (`agent_step`, both stages) and the publish of the agent's sample.

Why one workspace: a compiled call converts each array argument it is given (the array's
object, its dimensions, a reference-counted handle made and freed), and on a step woken from a
sleep none of that is in the cache. Measured here: a call of 20 one-element arrays took
13.2 µs against 5.2 µs for 2 arrays when the caches had been flushed (1.26 against 0.29 µs
warm); a hosted 6x250 swarm whose agents made two more calls of 10 arrays each per step spent
14 % more CPU (`benchmarks/bench_agents.py --against`, 6 pairs). The step's three calls took 36
arrays; `agent_tick` takes 3. `Workspace` moves the arrays those calls use into three buffers
(int64, float64, bytes) and gives their owners views of them, so every other reader (the
drain, the log, the summaries, the reference paths) reads and writes the same memory;
`agent_tick` carves the same views from the buffers with the table at the head of the int64
one. Nothing is computed differently: the three kernels are called as before, in the order
`AgentNode._step_compiled` calls them (tests/bridge/test_tick.py compares the two paths bit for
bit, fail-safe, hold and the age rule's rare cases included).
"""
from __future__ import annotations

import numpy as np

from controller.jit import jit
from controller.kernels import agent_step

from .sample_wire import age_rules, publish_sample

__all__ = ["Workspace", "agent_tick", "TICK_SLOTS", "T_AGAIN", "T_CHANGED", "T_FAILSAFE",
           "T_HOLD", "O_JUMPS", "O_FRAMES"]

# the slots, in the kernel's order: (name, buffer) with buffer 0 int64, 1 float64, 2 bytes
TICK_SLOTS = (
    # the age rule (`sample_wire.age_rules`)
    ("held_step", 0), ("ages", 0), ("verdict", 0), ("mode", 0), ("hist", 0), ("held", 1),
    ("rx", 1), ("rx_q", 0), ("rx_r", 0), ("rx_c", 0), ("last_verdict", 0),
    # the law (`agent_step`)
    ("S", 1), ("ea", 0), ("eb", 0), ("owned", 2), ("nbr", 0), ("P", 1), ("theta", 1),
    ("theta_prev", 1), ("theta_jump", 1), ("mu", 1), ("jumped", 2), ("term", 1), ("rel", 1),
    ("u", 1),
    # the publish (`sample_wire.publish_sample`)
    ("pbuf", 2), ("own_r", 0), ("pth", 1), ("pf32", 2), ("ends", 0), ("sfds", 0), ("sok", 0),
    ("pst", 0),
    # what the call returns besides its flags (`O_*`)
    ("out", 0),
)
_SLOT = {name: i for i, (name, _) in enumerate(TICK_SLOTS)}
(HELD_STEP, AGES, VERDICT, MODE, HIST, HELD, RX, RX_Q, RX_R, RX_C, LAST_VERDICT, S_, EA, EB,
 OWNED, NBR, P_, THETA, THETA_PREV, THETA_JUMP, MU, JUMPED, TERM, REL, U, PBUF, OWN_R, PTH,
 PF32, ENDS, SFDS, SOK, PST, OUT) = range(len(TICK_SLOTS))
_TWO_D = {"hist", "held", "S", "term", "rel", "u"}
_BYTES = {"owned": np.bool_, "jumped": np.bool_, "pbuf": np.uint8, "pf32": np.float32}
HEAD = 3 * len(TICK_SLOTS)     # the table: slot s at (element offset, rows, columns) 3s … 3s + 2
# agent_tick's flags
T_AGAIN, T_CHANGED, T_FAILSAFE, T_HOLD = 1, 2, 4, 8
O_JUMPS, O_FRAMES = 0, 1       # out[…]: the jumps, the sample's frames (−1: beyond float32)
_ALIGN = 8                     # bytes: every slot starts on a multiple (the float32 views)


class Workspace:
    """The arrays of ``slots`` ((name, owner, attribute) or (name, None, array): a constant
    copied in) moved into the three buffers of `TICK_SLOTS`' kinds, in its order: each owner's
    attribute is then a view of its buffer, with the values it had. `intact` says whether every
    owner still holds its view (an array assigned anew would leave the kernel reading the old
    memory)."""

    def __init__(self, slots):
        slots = list(slots)
        names = [s[0] for s in slots]
        if names != [n for n, _ in TICK_SLOTS]:
            raise ValueError(f"Workspace: slots {names} are not TICK_SLOTS' {list(_SLOT)}")
        arrays = [getattr(o, a) if o is not None else a for _, o, a in slots]
        size = [HEAD, 0, 0]
        place = []
        for (name, kind), a in zip(TICK_SLOTS, arrays):
            a = np.asarray(a)
            if a.ndim > 2 or not a.flags.c_contiguous or (kind == 2) != (a.dtype.itemsize != 8) \
                    or (kind < 2 and a.dtype != (np.int64, np.float64)[kind]):
                raise ValueError(f"Workspace: slot {name}: {a.dtype} {a.shape} does not fit")
            off = size[kind]
            if kind == 2:
                off = -(-off // _ALIGN) * _ALIGN
            place.append((kind, off, a))
            size[kind] = off + (a.nbytes if kind == 2 else a.size)
        self.I = np.zeros(size[0], np.int64)
        self.F = np.zeros(max(size[1], 1), np.float64)
        self.B = np.zeros(max(size[2], 1), np.uint8)
        bufs = (self.I, self.F, self.B)
        self._held = []
        for s, ((kind, off, a), (_, owner, attr)) in enumerate(zip(place, slots)):
            shape = a.shape if a.ndim == 2 else (a.size, 1)
            self.I[3 * s:3 * s + 3] = (off, *shape)
            n = a.nbytes if kind == 2 else a.size
            v = bufs[kind][off:off + n]
            if kind == 2:
                v = v.view(a.dtype)
            v = v.reshape(a.shape)
            v[...] = a
            if owner is not None:
                setattr(owner, attr, v)
                self._held.append((owner, attr, v))

    @staticmethod
    def views(I, F, B) -> dict:
        """{slot name: its view} of the buffers (I, F, B) of a workspace or of a copy, as
        `agent_tick` carves them."""
        out = {}
        for s, (name, kind) in enumerate(TICK_SLOTS):
            o, r, c = (int(x) for x in I[3 * s:3 * s + 3])
            if kind < 2:
                v = (I, F)[kind][o:o + r * c]
            else:
                dt = np.dtype(_BYTES[name])
                v = B[o:o + r * c * dt.itemsize].view(dt)
            out[name] = v.reshape(r, c) if name in _TWO_D else v
        return out

    def detached(self) -> tuple:
        """Copies of the buffers (I, F, B) with no socket to send on (−1): a call that
        changes nothing of the agent's and sends nothing (the warm-up's)."""
        I, F, B = self.I.copy(), self.F.copy(), self.B.copy()
        o, m = int(I[3 * SFDS]), int(I[3 * SFDS + 1])
        I[o:o + m] = -1
        return I, F, B

    def intact(self) -> bool:
        """Every owner still holds the view it was given."""
        return all(getattr(o, a) is v for o, a, v in self._held)


@jit(inline=True)
def _i1(I, s):
    o = I[3 * s]
    return I[o:o + I[3 * s + 1]]


@jit(inline=True)
def _i2(I, s):
    o, r, c = I[3 * s], I[3 * s + 1], I[3 * s + 2]
    return I[o:o + r * c].reshape((r, c))


@jit(inline=True)
def _f1(I, F, s):
    o = I[3 * s]
    return F[o:o + I[3 * s + 1]]


@jit(inline=True)
def _f2(I, F, s):
    o, r, c = I[3 * s], I[3 * s + 1], I[3 * s + 2]
    return F[o:o + r * c].reshape((r, c))


@jit(inline=True)
def _b1(I, B, s):
    o = I[3 * s]
    return B[o:o + I[3 * s + 1]].view(np.bool_)


@jit(inline=True)
def _u1(I, B, s):
    o = I[3 * s]
    return B[o:o + I[3 * s + 1]]


@jit(inline=True)
def _f4(I, B, s):
    o = I[3 * s]
    return B[o:o + 4 * I[3 * s + 1]].view(np.float32)


@jit(error_model="numpy")
def agent_tick(n, I, F, B, hybrid, h, max_age, hold, future, t_us, sysid, seq):
    """Step n of `AgentNode._step_compiled`'s compiled part over the workspace (I, F, B): the
    age rule (`age_rules`; ``max_age`` < 0: none), then, unless it leaves a neighbour to the
    caller (`T_AGAIN`: nothing more is done), the law's both stages in fail-safe if a verdict is
    fail-safe (`agent_step`) and the sample sent (`publish_sample`, stamped ``t_us``, from
    ``sysid`` with sequence numbers from ``seq``). Returns the flags: `T_CHANGED` a verdict
    differs from the last step's (kept in the workspace, ``last_verdict``), `T_FAILSAFE`, `T_HOLD`; out[O_JUMPS]
    and out[O_FRAMES] as those kernels return them."""
    held_step = _i1(I, HELD_STEP)
    verdict = _i1(I, VERDICT)
    mode = _i1(I, MODE)
    rx = _f1(I, F, RX)
    out = _i1(I, OUT)
    again = age_rules(n, held_step, max_age, hold, future, _i1(I, AGES), verdict, mode,
                      _i2(I, HIST), _f2(I, F, HELD), rx, _i1(I, RX_Q), _i1(I, RX_R),
                      _i1(I, RX_C))
    if again:
        return T_AGAIN
    flags = 0
    last = _i1(I, LAST_VERDICT)
    for q in range(verdict.shape[0]):
        v = verdict[q]
        if v != last[q]:
            flags |= T_CHANGED
            last[q] = v
        if v == 2:
            flags |= T_FAILSAFE
        elif v == 1:
            flags |= T_HOLD
    S = _f2(I, F, S_)
    theta_jump = _f1(I, F, THETA_JUMP)
    out[O_JUMPS] = agent_step(S, _i1(I, EA), _i1(I, EB), _b1(I, B, OWNED), _i1(I, NBR), mode,
                              hybrid, _f1(I, F, P_), h, 3, (flags & T_FAILSAFE) != 0,
                              _f1(I, F, THETA), rx, _f1(I, F, THETA_PREV), theta_jump,
                              _f1(I, F, MU), _b1(I, B, JUMPED), _f2(I, F, TERM),
                              _f2(I, F, REL), _f2(I, F, U))
    out[O_FRAMES] = publish_sample(_u1(I, B, PBUF), t_us, S, theta_jump, _i1(I, OWN_R),
                                   _f1(I, F, PTH), sysid, seq, _f4(I, B, PF32), _i1(I, ENDS),
                                   _i1(I, SFDS), _i1(I, SOK), _i1(I, PST))
    return flags
