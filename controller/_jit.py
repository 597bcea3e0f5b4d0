"""The one switch between compiled and plain-Python execution of the kernels.

Kernels are written as scalar loops so that numba compiles them to tight machine code; with
NUMBA_DISABLE_JIT=1 numba hands back the plain functions and the same source runs as Python,
which is how the tests check that both give the same numbers.
"""
import numba


def _load_numba_without_blas_probe():
    """Load numba's array registry (numba.np.arraymath) without its BLAS probe.

    numba loads that module at the first compiled call of every process, and at import it
    calls `numba.np.linalg.ensure_blas`, which imports scipy.linalg only to learn that BLAS
    exists: 0.11 s of a 0.6 s start-up here (scipy.linalg pulls in scipy's array-API layer,
    which loads numpy.f2py and numpy.testing). No kernel of ours calls BLAS, and scipy is a
    dependency, so the probe's answer is known. The probe is stepped over for that one import
    and put back: a kernel that does use BLAS still runs `ensure_blas` when it compiles, and
    numba's compiled BLAS wrappers import scipy's cython_blas themselves when they run.
    """
    import sys
    if "numba.np.arraymath" in sys.modules:
        return
    try:
        import numba.np.linalg as linalg
        probe = linalg.ensure_blas
    except (ImportError, AttributeError):      # another numba layout: let it probe
        return
    linalg.ensure_blas = lambda: None
    try:
        import numba.np.arraymath  # noqa: F401
    finally:
        linalg.ensure_blas = probe


_load_numba_without_blas_probe()


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
