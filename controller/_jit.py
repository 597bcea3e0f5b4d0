"""The one switch between compiled and plain-Python execution of the kernels.

Kernels are written as scalar loops so that numba compiles them to tight machine code; with
NUMBA_DISABLE_JIT=1 numba hands back the plain functions and the same source runs as Python,
which is how the tests check that both give the same numbers.
"""
import numba


def jit(fn=None, *, inline=False):
    # cache=True writes the machine code next to the source, so a second process starts
    # without recompiling. fastmath stays off: the plain-Python run must agree to rounding.
    # inline="always" is for the small per-edge helpers: a compiled call that passes arrays
    # increments and decrements each array's reference count (atomic operations), which cost
    # more than the helper's arithmetic; inlining at numba's IR level removes them.
    def wrap(f):
        if inline:
            return numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")(f)
        return numba.njit(cache=True, nogil=True, error_model="numpy")(f)

    return wrap(fn) if fn is not None else wrap
