"""libc's ``recv`` and ``send`` for compiled code: a kernel reads and writes UDP sockets itself
(issue 31).

Why: an agent reads a datagram per neighbour per step and then asks each socket once more,
to learn that it is empty. From Python each of those is a socket method call that builds a
bytes object and an address tuple, and the empty answer raises and catches BlockingIOError:
about 1 µs of Python around each system call. A kernel that calls libc directly reads every
neighbour's socket into one preallocated buffer and decodes what it read in the same call
(`bridge.swarm.sample_wire.drain_samples`); `send_all` sends a frame that compiled code wrote
(an agent's sample to its neighbours, its command to its vehicle) on connected sockets.

The three functions are numba intrinsics: LLVM declares the C symbols and the call resolves
against the process's libc, in numba's JIT and in the ahead-of-time module alike (the module's
shared object leaves them undefined, and the dynamic loader binds them when it is imported).
Where numba runs kernels as Python (``NUMBA_DISABLE_JIT=1``) the same calls go through ctypes.
A process on the ahead-of-time kernels never builds them (that would import numba): its module
holds the compiled callers already.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import errno as _errno
import os

from controller import jit as _jit

__all__ = ["recv", "send", "errno", "send_all", "MSG_DONTWAIT", "EAGAIN", "EWOULDBLOCK",
           "ECONNREFUSED", "EINTR"]

MSG_DONTWAIT = 0x40
EAGAIN = _errno.EAGAIN
EWOULDBLOCK = _errno.EWOULDBLOCK
ECONNREFUSED = _errno.ECONNREFUSED
EINTR = _errno.EINTR


def _unavailable(*_a):
    raise RuntimeError("bridge.mavlink.udp_io: this process runs the ahead-of-time kernels, whose "
                       "module calls libc itself")


def _ctypes_calls():
    """recv, send and errno through ctypes: the kernels run as Python."""
    libc = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)
    c_recv, c_send = libc.recv, libc.send
    for f in (c_recv, c_send):
        f.restype = ctypes.c_ssize_t
        f.argtypes = (ctypes.c_int, ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int)

    def recv(fd, buf, n, flags):
        return c_recv(int(fd), buf.ctypes.data, int(n), int(flags))

    def send(fd, buf, n, flags):
        return c_send(int(fd), buf.ctypes.data, int(n), int(flags))

    def errno():
        return ctypes.get_errno()

    return recv, send, errno


def _intrinsics(numba):
    from llvmlite import ir
    from numba import types
    from numba.core import cgutils
    from numba.extending import intrinsic

    i8p = ir.IntType(8).as_pointer()
    i32, i64 = ir.IntType(32), ir.IntType(64)
    # ssize_t f(int fd, void *buf, size_t n, int flags): recv(2) and send(2) on LP64
    io_fnty = ir.FunctionType(i64, [i32, i8p, i64, i32])

    def io_call(symbol):
        def call(typingctx, fd, buf, n, flags):
            if not (isinstance(buf, types.Array) and buf.dtype == types.uint8 and buf.ndim == 1
                    and buf.layout == "C"):
                return None
            sig = types.int64(fd, buf, n, flags)

            def codegen(context, builder, signature, args):
                fd_v, buf_v, n_v, flags_v = args
                ary = context.make_array(signature.args[1])(context, builder, value=buf_v)
                fn = cgutils.get_or_insert_function(builder.module, io_fnty, symbol)
                return builder.call(fn, [
                    context.cast(builder, fd_v, signature.args[0], types.int32),
                    builder.bitcast(ary.data, i8p),
                    context.cast(builder, n_v, signature.args[2], types.int64),
                    context.cast(builder, flags_v, signature.args[3], types.int32)])
            return sig, codegen
        call.__name__ = symbol
        return intrinsic(call)

    @intrinsic
    def errno(typingctx):
        def codegen(context, builder, signature, args):
            fn = cgutils.get_or_insert_function(builder.module,
                                                ir.FunctionType(i32.as_pointer(), []),
                                                "__errno_location")
            return builder.sext(builder.load(builder.call(fn, [])), i64)
        return types.int64(), codegen

    return io_call("recv"), io_call("send"), errno


def _make():
    if _jit.aot_module() is not None:
        return _unavailable, _unavailable, _unavailable
    if os.environ.get("NUMBA_DISABLE_JIT", "0") not in ("", "0"):
        return _ctypes_calls()
    return _intrinsics(_jit.numba_module())


recv, send, errno = _make()


@_jit.jit(error_model="python")
def send_all(fds, buf, n, ok):
    """buf[:n] sent on each connected socket of ``fds`` with libc's send, as
    `bridge.mavlink.link.UdpSocket.send` sends (once more after an ICMP error the socket
    reported, never waiting): ok[q] = 1 if socket q took it, else 0. Returns how many took it."""
    sent = 0
    for q in range(fds.shape[0]):
        ok[q] = 0
        for _ in range(2):
            r = send(fds[q], buf, n, MSG_DONTWAIT)
            if r >= 0:
                ok[q] = 1
                sent += 1
                break
            e = errno()
            if e != ECONNREFUSED and e != EINTR:
                break
    return sent
