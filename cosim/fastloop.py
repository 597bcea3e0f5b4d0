"""The compiled block loop of the master: plant FMU + network controller without Python per step.

Between two returns to Python (at most a block of steps), one numba function runs, per step n,
exactly what the reference loop in `master.py` does through Python:

    fmi2GetReal(S) ; law_step(law, S, h) → u ; fmi2SetReal(u) ; fmi2DoStep(k·h, h) ; k += 1

calling the FMU's C functions through the raw addresses that fmpy loaded (the FMU stays a real
FMU) and the law's compiled step directly. What the reference loop does at its ticks is gathered
into preallocated arrays instead: the raw rows and metrics of every log record, every jump with
its exact step, the state of a 1 s summary sample. Python then encodes those outside the loop,
on a writer thread, while the next block runs with the GIL released.

What the loop needs it gets through public, typed records: the plant's `cosim.plants.CompiledPlant`
(the FMU's calls and buffers, and the plant's clock k, which the loop advances in place: the
plant owns its time), the law's compiled record (`cosim.controllers.law_step` is specialised for
its type) and `cosim.controllers.EdgeState`, the master's metric buffers (`Metrics`), and the
buffers the block fills (`LogRecords`, `Jumps`, `Samples`). The addresses are arguments, never
globals, so `cache=True` machine code holds no process-specific pointer.
"""
from __future__ import annotations

import hashlib
import inspect
import os
import queue
import sys
import threading
import time
from types import FunctionType
from typing import NamedTuple

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic

from controller import layout
from controller.errors import Se3SyncError
from controller.kernels import metrics, network_U
from plant_fmu.fast import CALL_NAMES

from . import signals
from .signals import MAX_BLOCK
from .controllers import law_step


__all__ = ["compiled_pair", "run_compiled", "Metrics", "LogRecords", "Jumps", "Samples"]

# which FMI call failed (returned by the block as out[O_CALL]), in `CALL_NAMES` order
CALL_GET, CALL_SET, CALL_STEP = 0, 1, 2
# slots of the block's int64 result vector
O_N, O_REC, O_JMP, O_STATUS, O_CALL, O_SAMPLED = range(6)
FMI2_ERROR = 3
JUMP_CAPACITY = 4096  # jumps a block can hold (at least M: one step's worth)
TARGET_BLOCK_S = 0.1  # a block is cut shorter when MAX_BLOCK steps would take longer (Ctrl-C)
# with a log, the first block is this short and the blocks double from there: the writer
# thread encodes a block's records while the next block steps, so one long first block would
# leave it idle until then (a 1000-agent run's whole first second)
FIRST_LOGGED_BLOCK = 16
# ... and they grow only while shorter than this: the records of the last block are encoded
# after the loop has stopped, so a long one is a tail of logging the loop waits for (a
# 1000-agent run at h = 1 ms reached 256-step, 56 ms blocks, and its last quarter second of
# records was encoded after the last step)
TARGET_LOGGED_BLOCK_S = 0.01
QUEUE_BYTES = 128 << 20  # record arrays that may wait for the log writer
# Python's GIL switch interval while a logged run steps: a block that ends waits for the GIL
# the encoder thread holds, by default up to 5 ms (paper scenario: a 1000-step block is 1.3 ms,
# so the loop would mostly wait; logging share 39 % of the wall time at 5 ms, 7 % at 0.1 ms)
LOGGED_SWITCH_S = 1e-4


@intrinsic
def _fmi2_xreal(typingctx, fn, comp, vr, nvr, val):
    """fmi2Status f(fmi2Component, const fmi2ValueReference[], size_t, fmi2Real[]) at address
    fn: fmi2SetReal and fmi2GetReal share this signature."""
    sig = types.int32(fn, comp, vr, nvr, val)

    def codegen(context, builder, signature, args):
        f, c, r, n, v = args
        i8p = ir.IntType(8).as_pointer()
        i64 = ir.IntType(64)
        fnty = ir.FunctionType(ir.IntType(32), [i8p, i8p, i64, i8p])
        fp = builder.inttoptr(f, fnty.as_pointer())
        return builder.call(fp, [builder.inttoptr(c, i8p), builder.inttoptr(r, i8p),
                                 builder.zext(n, i64) if n.type.width < 64 else n,
                                 builder.inttoptr(v, i8p)])

    return sig, codegen


@intrinsic
def _fmi2_do_step(typingctx, fn, comp, t, h):
    """fmi2DoStep(c, t, h, noSetFMUStatePriorToCurrentPoint = fmi2True) at address fn."""
    sig = types.int32(fn, comp, t, h)

    def codegen(context, builder, signature, args):
        f, c, tt, hh = args
        i8p = ir.IntType(8).as_pointer()
        i32 = ir.IntType(32)
        fnty = ir.FunctionType(i32, [i8p, ir.DoubleType(), ir.DoubleType(), i32])
        fp = builder.inttoptr(f, fnty.as_pointer())
        return builder.call(fp, [builder.inttoptr(c, i8p), tt, hh, ir.Constant(i32, 1)])

    return sig, codegen


class Metrics(NamedTuple):
    """The master's metric parameters and buffers (`cosim.master.NetworkMetrics`)."""

    edges: np.ndarray
    P: np.ndarray
    kX: float
    masses: np.ndarray
    J: np.ndarray
    rot: np.ndarray
    pos: np.ndarray
    U: np.ndarray
    quat: np.ndarray

    @classmethod
    def of(cls, m) -> "Metrics":
        return cls(m.edges, m.P, m.kX, m.masses, m.J, m.rot, m.pos, m.U, m.quat)


class LogRecords(NamedTuple):
    """The block's log records: the step of each, the raw rows and the metrics."""

    step: np.ndarray
    S: np.ndarray
    u: np.ndarray
    theta: np.ndarray
    mu: np.ndarray
    jumped: np.ndarray
    rot: np.ndarray
    pos: np.ndarray
    U: np.ndarray
    quat: np.ndarray
    V: np.ndarray

    @classmethod
    def empty(cls, cap, N, M) -> "LogRecords":
        return cls(np.empty(cap, np.int64), np.empty((cap, N, layout.S_WIDTH)),
                   np.empty((cap, N, 6)), np.empty((cap, M)), np.empty((cap, M)),
                   np.empty((cap, M), np.bool_), np.empty((cap, M)), np.empty((cap, M)),
                   np.empty((cap, M)), np.empty((cap, N, 4)), np.empty(cap))

    @property
    def cap(self) -> int:
        return self.step.shape[0]


class Jumps(NamedTuple):
    """The block's jumps: step, edge (from 1), θ before and after, μ."""

    step: np.ndarray
    edge: np.ndarray
    before: np.ndarray
    after: np.ndarray
    mu: np.ndarray

    @classmethod
    def empty(cls, cap) -> "Jumps":
        return cls(np.empty(cap, np.int64), np.empty(cap, np.int64), np.empty(cap),
                   np.empty(cap), np.empty(cap))


class Samples(NamedTuple):
    """The block's summary samples (step, S and θ after the jump stage) and u(0)."""

    step: np.ndarray
    S: np.ndarray
    theta: np.ndarray
    u0: np.ndarray


@njit(cache=True, nogil=True, error_model="numpy")
def run_block(plant, law, es, mx, rec, jmp, smp, h, n0, n1, dec, rec0, spl, out):
    """Steps n0 … n1−1 (stopping early before a step whose jumps might not fit the buffers).

    plant: a `CompiledPlant` (doStep runs from k·h, k = its clock, advanced after each completed
    doStep; with d = len(held) > 0 the FMU is sent held[k % d], the wrench of step k − d, and
    the law's wrench is kept there: `cosim.plants.DelayedActuation`); law: the law's compiled
    record (`law_step`), which computes the wrench into the plant's input buffer; es: its
    `EdgeState`. A step n ≥ rec0 with dec > 0 and n % dec == 0 stores a log record in rec
    (`LogRecords`, metrics from mx, `Metrics`); n % spl == 0 stores a summary sample in smp (`Samples`: S and θ after the jump stage; at n = 0 also u, for u(0)), as many
    as the block crosses; jmp (`Jumps`) the jumps. out receives the steps done (completed
    doSteps), records, jumps (those of a failing step included, as the Python loop has them),
    the first FMI status ≥ fmi2Error (else 0), the failing call and whether a sample was taken.

    Every record but ``law`` comes as a plain tuple of its fields (`_plain`): numba types a
    plain tuple at a call in half the time of a NamedTuple (the block's call costs about what
    49 separate arguments did); ``law`` keeps its class, which selects its `law_step`.
    """
    (fn, comp, vr_state, vr_input, S, u), clock, held = plant
    n_held = held.shape[0]
    theta_prev, theta_jump, mu, jumped = es[1], es[2], es[3], es[4]
    edges, Pm, kX, masses, J, rot, pos, U, quat = mx
    jmp_step, jmp_edge, jmp_before, jmp_after, jmp_mu = jmp
    smp_step, smp_S, smp_theta, smp_u = smp
    rec_step, rec_S, rec_u, rec_theta, rec_mu, rec_jumped, rec_rot, rec_pos, rec_U, rec_quat, \
        rec_V = rec
    M = edges.shape[0]
    n_st = S.size
    n_in = u.size
    p_S = S.ctypes.data
    p_u = u.ctypes.data
    p_vs = vr_state.ctypes.data
    p_vi = vr_input.ctypes.data
    nrec = 0
    njmp = 0
    out[O_STATUS] = 0
    out[O_SAMPLED] = 0
    n = n0
    while n < n1:
        if njmp + M > jmp_step.shape[0]:
            break  # the jump buffers might overflow: hand them to Python first
        st = _fmi2_xreal(fn[0], comp, p_vs, n_st, p_S)
        if st >= FMI2_ERROR:
            out[O_STATUS] = st
            out[O_CALL] = CALL_GET
            break
        nj = law_step(law, S, h)
        if nj > 0:
            for k in range(M):
                if jumped[k]:
                    jmp_step[njmp] = n
                    jmp_edge[njmp] = k + 1
                    jmp_before[njmp] = theta_prev[k]
                    jmp_after[njmp] = theta_jump[k]
                    jmp_mu[njmp] = mu[k]
                    njmp += 1
        if n % spl == 0:
            ns = out[O_SAMPLED]
            smp_step[ns] = n
            smp_S[ns] = S
            smp_theta[ns] = theta_jump
            if n == 0:
                smp_u[:, :] = u
            out[O_SAMPLED] = ns + 1
        if n >= rec0 and dec > 0 and n % dec == 0:
            network_U(S, theta_jump, edges, Pm, U)
            V, ximax = metrics(S, edges, U, kX, masses, J, rot, pos, quat)
            rec_step[nrec] = n
            rec_S[nrec] = S
            rec_u[nrec] = u
            rec_theta[nrec] = theta_jump
            rec_mu[nrec] = mu
            rec_jumped[nrec] = jumped
            rec_rot[nrec] = rot
            rec_pos[nrec] = pos
            rec_U[nrec] = U
            rec_quat[nrec] = quat
            rec_V[nrec] = V
            nrec += 1
        k = clock[0]
        if n_held > 0:   # an actuation delay: send the wrench of step k − d, keep this one
            hk = held[k % n_held]
            for i in range(u.shape[0]):
                for a in range(u.shape[1]):
                    x = hk[i, a]
                    hk[i, a] = u[i, a]
                    u[i, a] = x
        st = _fmi2_xreal(fn[1], comp, p_vi, n_in, p_u)
        if st >= FMI2_ERROR:
            out[O_STATUS] = st
            out[O_CALL] = CALL_SET
            break
        st = _fmi2_do_step(fn[2], comp, k * h, h)
        if st >= FMI2_ERROR:
            out[O_STATUS] = st
            out[O_CALL] = CALL_STEP
            break
        clock[0] = k + 1
        n += 1
    out[O_N] = n
    out[O_REC] = nrec
    out[O_JMP] = njmp


@njit(cache=True, nogil=True, error_model="numpy")
def sample_metrics(smp, nsmp, mx, out):
    """out[q] = (V̄, max|ξ|, max rot_err, max pos_err) of the block's summary sample q: what
    `NetworkMetrics.sample` computes, the same kernels in the same order (max propagates NaN as
    numpy's does), in one call instead of a few Python-level calls per sample. smp, mx: the
    plain tuples of `Samples` and `Metrics`."""
    smp_S, smp_theta = smp[1], smp[2]
    edges, P, kX, masses, J, rot, pos, U, quat = mx
    M = edges.shape[0]
    for q in range(nsmp):
        network_U(smp_S[q], smp_theta[q], edges, P, U)
        V, ximax = metrics(smp_S[q], edges, U, kX, masses, J, rot, pos, quat)
        r = rot[0] if M else 0.0
        p = pos[0] if M else 0.0
        for k in range(1, M):
            if r == r and (rot[k] > r or rot[k] != rot[k]):
                r = rot[k]
            if p == p and (pos[k] > p or pos[k] != pos[k]):
                p = pos[k]
        out[q, 0] = V
        out[q, 1] = ximax
        out[q, 2] = r
        out[q, 3] = p


_BLOCKS: dict = {}


def _block_loop(law):
    """`run_block` compiled for the type of the law's record, with an on-disk cache of its own.

    numba keeps one cache index per function, every compiled signature in it, and unpickles all
    of them to load any one; a law's record class is in its signature, so with one run_block
    for every law, loading the paper's loop would import every other law's module first (about
    10 ms each per process). A copy of run_block per record type (the same code, a qualname
    naming the type) keeps the indexes apart. numba checks a cached function against its own
    source file only, not against the functions it inlines: the qualname also carries the stamp
    of the file defining the record (where a law's compiled step lives), so that editing a law
    recompiles its loop instead of running the old machine code."""
    kind = type(law)
    loop = _BLOCKS.get(kind)
    if loop is None:
        py = getattr(run_block, "py_func", None)
        if py is None:            # NUMBA_DISABLE_JIT=1: plain Python
            return run_block
        try:
            st = os.stat(inspect.getfile(kind))
            stamp = hashlib.sha1(f"{st.st_mtime_ns} {st.st_size}".encode()).hexdigest()[:10]
        except (OSError, TypeError):
            stamp = "0"
        f = FunctionType(py.__code__, py.__globals__, py.__name__, py.__defaults__)
        f.__qualname__ = (f"run_block_{kind.__module__}_{kind.__qualname__}".replace(".", "_")
                          + f"_{stamp}")
        f.__doc__ = py.__doc__
        loop = _BLOCKS[kind] = njit(cache=True, nogil=True, error_model="numpy")(f)
    return loop


def _plain(record) -> tuple:
    """A record as the plain tuple of its fields, nested records too (see `run_block`)."""
    return tuple(_plain(x) if isinstance(x, tuple) else x for x in record)


def compiled_pair(plant, controller):
    """(the plant's `CompiledPlant`, the law's compiled record) when the pair can run the
    compiled loop, else None: a plant with ``compiled_plant()`` (the FMU plant: one FMI 2.0
    instance for all bodies) and a law with ``compiled_step()`` whose wrench buffer is the
    plant's input buffer (`cosim.master.Master` arranges that through ``write_wrench_into``).
    A plant with ``stats`` runs in Python: its statistics are read at the sample ticks."""
    cp = getattr(plant, "compiled_plant", None)
    cs = getattr(controller, "compiled_step", None)
    if cp is None or cs is None or getattr(plant, "stats", None) is not None:
        return None
    p, law = cp(), cs()
    if p is None or law is None:
        return None
    u = getattr(law, "u", None)
    if u is not p.fmi.inputs or p.fmi.state.shape[0] != u.shape[0]:
        return None
    return p, law


class _Writer:
    """Encodes the blocks' log items on a thread, in order (the logger is used by it alone)."""

    def __init__(self, logger, block_bytes):
        self.logger = logger
        # blocks waiting for the encoder hold their record arrays: bound them in bytes
        self.q = queue.Queue(maxsize=int(min(64, max(2, QUEUE_BYTES // max(1, block_bytes)))))
        self.error = None
        self.t = threading.Thread(target=self._loop, name="se3sync-log", daemon=True)
        self.t.start()

    def _loop(self):
        while True:
            item = self.q.get()
            if item is None:
                return
            if self.error is not None:
                continue
            try:
                item()
            except BaseException as exc:  # surfaced by the master at the next block
                self.error = exc

    def put(self, fn):
        if self.error is not None:
            raise self.error
        self.q.put(fn)

    def close(self):
        self.q.put(None)
        self.t.join()
        if self.error is not None:
            raise self.error


def run_compiled(master, plant, law, n_steps, bar, spl, dec, budget=None):
    """The compiled counterpart of the loop in `Master.run`, on the records of `compiled_pair`;
    returns (n, interrupted, timed_out).

    Same per-step semantics, ticks and events as the reference loop: jumps are recorded with
    their exact step, log records at n % dec == 0, summary samples at n % spl == 0. Between
    blocks of at most MAX_BLOCK steps (cut shorter when they would take more than
    TARGET_BLOCK_S): Ctrl-C / SIGTERM / `Master.request_stop` (`Master.stop_requested`) and the
    wall-clock budget, counted from the end of the first block as in the reference loop.
    """
    h = master.h
    N, M = master.N, master.M
    logger = master.logger
    logging = logger is not None
    es = _plain(master.edge_state)
    mx = _plain(Metrics.of(master.metrics))
    cplant = _plain(plant)
    loop = _block_loop(law)
    jcap = max(M, JUMP_CAPACITY)
    # summary samples: as many as the longest block crosses (blocks do not stop at them, so
    # a sweep sampling every few steps still runs up to MAX_BLOCK steps per compiled call)
    scap = MAX_BLOCK // spl + 2
    smp = Samples(np.zeros(scap, np.int64), np.zeros((scap, N, layout.S_WIDTH)),
                  np.zeros((scap, M)), np.zeros((N, 6)))
    smp_t = _plain(smp)
    out = np.zeros(6, dtype=np.int64)
    writer = None
    if logging:
        writer = _Writer(logger, 8 * (N * 28 + 5 * M) * ((MAX_BLOCK - 1) // dec + 1))
    block = FIRST_LOGGED_BLOCK if logging else MAX_BLOCK
    target = TARGET_LOGGED_BLOCK_S if logging else TARGET_BLOCK_S
    # a logger may ask for blocks of its own length (the live view alone: a block per frame)
    target = getattr(logger, "block_seconds", None) or target
    # ... and say, before each block, whether it wants a record from it at all (the live view
    # alone, `LiveTee.frame_wanted`: only when a frame is due, and then only the block's last
    # record; the records of the other blocks would be taken to be thrown away)
    wanted = getattr(logger, "frame_wanted", None) if logging else None
    n = 0
    interrupted = timed_out = False
    deadline = None
    pending = None
    # record buffers the writer has encoded, for the next blocks: fresh ones cost the loop a
    # page fault per 4 KiB written (a 1000-agent record is 0.26 MB)
    free = []
    # a signal only asks the master to stop while blocks run (they are short): Python would run
    # a raising handler between blocks only, where a KeyboardInterrupt would lose the step count
    catcher = signals.catching(master.request_stop).__enter__()
    switch = sys.getswitchinterval()
    if logging:
        sys.setswitchinterval(min(switch, LOGGED_SWITCH_S))
    jb = Jumps.empty(jcap)   # read out (copied) by _hand_over after each block: one for all
    jb_t = tuple(jb)
    try:
        while n < n_steps and not master.stop_requested:
            nxt = min(n_steps, n + block)
            rec0 = n
            if wanted is not None:   # no record unless a frame is due; then the last one only
                rec0 = max(n, (nxt - 1) // dec * dec) if wanted() else nxt
            cap = (nxt - rec0 - 1) // dec + 1 if logging and nxt > rec0 else 0
            rec = None
            while free and rec is None:
                r = free.pop()
                rec = r if r.cap >= cap else None
            if rec is None:
                rec = LogRecords.empty(cap, N, M)
            t0 = time.perf_counter()
            loop(cplant, law, es, mx, tuple(rec), jb_t, smp_t, h, n, nxt, dec, rec0, spl, out)
            now = time.perf_counter()
            dt = now - t0
            n0, n = n, int(out[O_N])
            if n > n0 and dt > target * 1.5:
                block = max(1, int((n - n0) * target / dt))
            elif block < MAX_BLOCK and dt < target / 2:
                block = min(MAX_BLOCK, 2 * block)
            _hand_over(master, writer, rec, int(out[O_REC]), jb, int(out[O_JMP]), h,
                       int(out[O_SAMPLED]), smp, mx, free)
            if out[O_STATUS]:
                pending = (CALL_NAMES[int(out[O_CALL])], int(out[O_STATUS]))
                break
            if master.diverged is not None:   # a sample of this block showed it (guards)
                break
            if bar is not None:
                bar.update(n - bar.n)
            if master.stop_requested:
                interrupted = n < n_steps
                break
            if budget is not None:
                if deadline is None:
                    deadline = now + float(budget)
                elif now > deadline and n < n_steps:
                    timed_out = True
                    break
            if writer is not None and writer.error is not None:
                raise writer.error
    finally:
        catcher.__exit__()
        sys.setswitchinterval(switch)
        if writer is not None:
            writer.close()
    if pending is not None:
        try:
            master.plant.raise_fmi_status(*pending)
        except Se3SyncError as exc:
            # a non-finite state or wrench (the plant's input buffer): the run diverged
            if not master.plant_failed(n, plant.fmi.inputs, exc):
                raise
    return n, interrupted, timed_out


def _hand_over(master, writer, rec, nrec, jb, njmp, h, nsmp, smp, mx, free=None):
    """The block's events, in step order: the summary samples (main thread, they fill
    master.add_sample, which checks them for divergence), jumps (master.add_jump now, the log on
    the writer) and log records."""
    if nsmp:
        m = master.metrics
        out = np.empty((nsmp, 4))
        sample_metrics(_plain(smp), nsmp, mx, out)
        steps = smp.step[:nsmp].tolist()
        if steps[0] == 0:
            master.u0 = smp.u0.copy()
        for q, (V, ximax, r, p) in enumerate(out.tolist()):
            master.add_sample(m.record(steps[q] * h, r, p, ximax, smp.theta[q], V))
    jstep, jedge, jbefore, jafter, jmu = (a[:njmp].tolist() for a in jb)
    for s, e, b, a, m in zip(jstep, jedge, jbefore, jafter, jmu):
        master.add_jump({"t": s * h, "edge": e, "theta_before": b, "theta_after": a, "mu": m})
    if writer is None or (njmp == 0 and nrec == 0):
        if free is not None:   # nothing to write from them: the next block may fill them
            free.append(rec)
        return
    kX = master.metrics.kX
    # a logger called in the loop's own thread (the live view alone) must not hand the GIL
    # over: the loop would wait for it, up to the switch interval, to go on
    inline = getattr(writer.logger, "inline", False)
    sleep = time.sleep

    def write():
        lg = writer.logger
        jump = getattr(lg, "jump_fast", lg.jump)
        block = getattr(lg, "record_block", None)
        steps = rec.step[:nrec].tolist()
        inf = float("inf")
        i = r = 0
        while r < nrec:
            while i < njmp and jstep[i] <= steps[r]:  # a step's jumps come before its record
                t = jstep[i] * h
                jump(round(t * 1e9), t, jedge[i], jbefore[i], jafter[i], jmu[i])
                i += 1
            nxt_jump = jstep[i] if i < njmp else inf
            rb = r + 1  # records r … rb−1 have no jump between them: encoded together
            while rb < nrec and steps[rb] < nxt_jump:
                rb += 1
            sl = slice(r, rb)
            k = rb - r
            args = ([round(st * h * 1e9) for st in steps[sl]], rec.S[sl], rec.u[sl],
                    rec.theta[sl], rec.mu[sl], rec.jumped[sl], rec.rot[sl],
                    rec.pos[sl], rec.U[sl], rec.quat[sl], rec.V[sl].tolist(),
                    [float(kX * x.sum()) for x in rec.U[sl]])
            if block is not None:
                block(*args)
            else:
                for q in range(k):
                    lg.record(*(a[q] for a in args))
            r = rb
            # hand the GIL over: a block that ends waits for it, by default up to the 5 ms
            # switch interval, which would serialise the loop behind the encoder
            if not inline:
                sleep(0)
        while i < njmp:
            t = jstep[i] * h
            jump(round(t * 1e9), t, jedge[i], jbefore[i], jafter[i], jmu[i])
            i += 1
        if free is not None:   # encoded: the loop may fill these buffers again
            free.append(rec)

    if inline:
        write()   # a logger that asks to be called here (the live view alone: cheap, see
        # cosim/log/live.py): no hand-over to the writer thread for every block
    else:
        writer.put(write)
