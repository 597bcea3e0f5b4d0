"""Loopback helpers for the tests that count what one read takes: a datagram sent on loopback
is queued on its receiver by the kernel's softirq, which a busy machine may defer (ksoftirqd),
so a test that asserts what one poll reads first waits until all of it is queued, not a fixed
sleep.

`wait_queued` watches the receiving socket's memory (SO_MEMINFO: the bytes its queue holds,
each datagram counted at its buffer's true size, the same for equal payloads) until it holds
the datagrams sent to it.
"""
from __future__ import annotations

import select
import socket
import struct
import time

SO_MEMINFO = getattr(socket, "SO_MEMINFO", 55)   # Linux


def queued_bytes(sock) -> int:
    """The bytes a socket's receive queue holds now (SK_MEMINFO_RMEM_ALLOC)."""
    return struct.unpack("9I", sock.getsockopt(socket.SOL_SOCKET, SO_MEMINFO, 36))[0]


_TRUESIZE: dict[int, int] = {}


def datagram_truesize(size: int) -> int:
    """What one datagram of ``size`` bytes costs a loopback receiver's queue (measured once)."""
    if size in _TRUESIZE:
        return _TRUESIZE[size]
    r = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    t = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        r.bind(("127.0.0.1", 0))
        t.sendto(bytes(size), r.getsockname())
        select.select([r], [], [], 10.0)
        _TRUESIZE[size] = queued_bytes(r)
        return _TRUESIZE[size]
    finally:
        r.close()
        t.close()


def wait_queued(sock, sizes, size: int | None = None, timeout: float = 10.0) -> None:
    """Returns once ``sock`` (nothing read from it since it last was empty) holds datagrams of
    the payload ``sizes`` (a list; or ``sizes`` datagrams of ``size`` bytes); fails after
    ``timeout`` s naming what it holds."""
    if size is not None:
        sizes = [size] * sizes
    want = sum(datagram_truesize(n) for n in sizes)
    end = time.monotonic() + timeout
    while (got := queued_bytes(sock)) < want:
        assert time.monotonic() < end, f"{got} of {want} bytes queued after {timeout} s"
        time.sleep(0.001)
