"""libc's recv and send for kernels (bridge/mavlink/udp_io.py), both ways they are built: numba
intrinsics (what the JIT and the ahead-of-time module call) and ctypes (what the kernels call
when numba runs them as Python, NUMBA_DISABLE_JIT=1). Each against Python's own socket calls
on real sockets: the bytes, the lengths, and the empty socket's EAGAIN."""
from __future__ import annotations

import socket
import time

import numpy as np
import pytest

from bridge.mavlink import udp_io


def _pair():
    a = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    b = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    a.bind(("127.0.0.1", 0))
    b.bind(("127.0.0.1", 0))
    a.connect(b.getsockname())
    b.connect(a.getsockname())
    a.setblocking(False)
    b.setblocking(False)
    return a, b


def _compiled():
    from controller.jit import numba_module

    njit = numba_module().njit
    recv, send, errno = udp_io._intrinsics(numba_module())

    @njit
    def c_recv(fd, buf, n, flags):
        r = recv(fd, buf, n, flags)
        return r, (errno() if r < 0 else 0)

    @njit
    def c_send(fd, buf, n, flags):
        r = send(fd, buf, n, flags)
        return r, (errno() if r < 0 else 0)

    return c_recv, c_send


def _ctypes():
    recv, send, errno = udp_io._ctypes_calls()

    def c_recv(fd, buf, n, flags):
        r = recv(fd, buf, n, flags)
        return r, (errno() if r < 0 else 0)

    def c_send(fd, buf, n, flags):
        r = send(fd, buf, n, flags)
        return r, (errno() if r < 0 else 0)

    return c_recv, c_send


def _recv_within(c_recv, fd, buf, n, seconds=5.0):
    """c_recv until a datagram comes (a loaded machine may deliver it late), or (−1, errno)."""
    end = time.monotonic() + seconds
    while True:
        got = c_recv(fd, buf, n, udp_io.MSG_DONTWAIT)
        if got[0] >= 0 or time.monotonic() > end:
            return got
        time.sleep(0.001)


@pytest.mark.parametrize("build", [_compiled, _ctypes])
def test_recv_and_send_are_the_sockets(build):
    c_recv, c_send = build()
    a, b = _pair()
    try:
        buf = np.zeros(2048, np.uint8)
        # empty: −1 and EAGAIN, as Python's BlockingIOError
        r, e = c_recv(b.fileno(), buf, buf.shape[0], udp_io.MSG_DONTWAIT)
        assert r == -1 and e in (udp_io.EAGAIN, udp_io.EWOULDBLOCK)
        rng = np.random.default_rng(1)
        for size in (1, 12, 300, 1500):
            data = rng.integers(0, 256, size, dtype=np.uint8)
            # ours out, Python's in
            out = data.copy()
            assert c_send(a.fileno(), out, size, udp_io.MSG_DONTWAIT) == (size, 0)
            b.settimeout(5.0)
            assert b.recv(65535) == data.tobytes()
            b.setblocking(False)
            # Python's out, ours in (what the buffer held beyond it untouched)
            a.send(data.tobytes()[::-1])
            buf[:] = 7
            got = _recv_within(c_recv, b.fileno(), buf, buf.shape[0])
            assert got == (size, 0)
            assert buf[:size].tobytes() == data.tobytes()[::-1] and (buf[size:] == 7).all()
            # a shorter buffer takes the datagram's head only, as recv(n) does
            a.send(data.tobytes())
            got = _recv_within(c_recv, b.fileno(), buf, 1)
            assert got == (1, 0) and buf[0] == data[0]
    finally:
        a.close()
        b.close()
