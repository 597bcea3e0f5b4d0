"""The one switch between compiled and plain-Python execution of the kernels.

Kernels are written as scalar loops so that numba compiles them to tight machine code; with
NUMBA_DISABLE_JIT=1 numba hands back the plain functions and the same source runs as Python,
which is how the tests check that both give the same numbers.
"""
import numba


def jit(fn):
    # cache=True writes the machine code next to the source, so a second process starts
    # without recompiling. fastmath stays off: the plain-Python run must agree to rounding.
    return numba.njit(cache=True, nogil=True)(fn)
