"""The one switch between compiled and plain-Python execution of the kernels.

Kernels are written as scalar loops so that numba compiles them to tight machine code; with
NUMBA_DISABLE_JIT=1 numba hands back the plain functions and the same source runs as Python,
which is how the tests check that both give the same numbers.

numba is imported at the first `jit` (a kernel module's import), not with this module. A process
that has called `use_aot` before any kernel module was imported never imports it: `jit` hands
back the ahead-of-time module's compiled function of that kernel (`bridge.swarm.aot`: the agent
process's kernels, built once by numba's AOT compiler), or the plain function for a kernel that
module does not hold (set-up arithmetic, run once).
"""
import os
import sys


def _import_numba():
    """Import numba without three imports that buy nothing here (together ~40 ms of a 0.5 s
    start-up).

    - `numba/__init__` imports scipy only to refuse a scipy older than 1.0; our install pins a
      newer one (13 ms). scipy is hidden (numba catches the ImportError) for that one import.
    - `numba.core.config` imports yaml only to read a `.numba_config.yaml` in the working
      directory (13 ms). With no such file, yaml is hidden the same way, and numba's config
      then gets a lazy yaml, so a config file written later is still read.
    - `numba.core.entrypoints` imports importlib.metadata (14 ms) and, at the first compile,
      lists every installed distribution (5 ms) to run the `numba_extensions` hooks. When no
      distribution on sys.path declares one (`_no_numba_extensions`), numba gets a lazy
      importlib.metadata and is told that the (empty) set of hooks has run.
    Each module imports normally afterwards.
    """
    if "numba" in sys.modules:
        return sys.modules["numba"]
    hide = [m for m in ("scipy", "yaml") if m not in sys.modules]
    if os.path.isfile(".numba_config.yaml") and "yaml" in hide:
        hide.remove("yaml")
    import importlib
    lazy_md = None
    if _no_numba_extensions() and "importlib.metadata" not in sys.modules:
        # `from importlib import metadata` takes the package's attribute when it has one; the
        # real import (by anyone, later) replaces it
        lazy_md = importlib.metadata = _Lazy("importlib.metadata")
    for m in hide:
        sys.modules[m] = None
    try:
        import numba
    finally:
        for m in hide:
            if sys.modules.get(m, 0) is None:
                del sys.modules[m]
        if lazy_md is not None and importlib.__dict__.get("metadata") is lazy_md:
            del importlib.metadata
    if lazy_md is not None:
        entrypoints = sys.modules.get("numba.core.entrypoints")
        if entrypoints is not None and hasattr(entrypoints, "_already_initialized"):
            entrypoints._already_initialized = True
    config = sys.modules.get("numba.core.config")
    if "yaml" in hide and config is not None and not getattr(config, "_HAVE_YAML", True):
        import importlib.util
        if importlib.util.find_spec("yaml") is not None:
            config.yaml = _Lazy("yaml")
            config._HAVE_YAML = True
    return numba


def _no_numba_extensions() -> bool:
    """True when no distribution importlib.metadata would find declares a `numba_extensions`
    entry point: it finds them through PathFinder, in the `*.dist-info` and `*.egg-info`
    folders of sys.path's directories. Anything else on the path (a zip, an egg, another
    finder that lists distributions) answers False, and numba looks for itself."""
    import importlib.machinery
    if any(hasattr(f, "find_distributions") and f is not importlib.machinery.PathFinder
           for f in sys.meta_path):
        return False
    for entry in sys.path:
        entry = entry or "."
        if not os.path.isdir(entry):
            if os.path.exists(entry):
                return False
            continue
        try:
            names = os.listdir(entry)
        except OSError:
            return False
        for name in names:
            if name.endswith((".dist-info", ".egg-info")):
                ep = os.path.join(entry, name, "entry_points.txt")
                try:
                    with open(ep, "rb") as f:
                        if b"numba_extensions" in f.read():
                            return False
                except FileNotFoundError:
                    pass
                except OSError:
                    return False
            elif name.endswith(".egg"):
                return False
    return True


class _Lazy:
    """Stands for a module that is imported on its first attribute access."""

    def __init__(self, name: str):
        self._name = name

    def __getattr__(self, attr):
        import importlib
        return getattr(importlib.import_module(self._name), attr)


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


def _cache_writes_may_fail() -> None:
    """A compiled kernel whose on-disk cache cannot be written (a full disk, a size limit, a
    read-only tree) runs from memory: numba raises the OSError out of the call that compiled it
    (a command on a full disk ended in numba's traceback, not its one-line error about the output
    it could not write). numba already removes its half-written file; the next process compiles
    again. (numba forgives only Windows' sharing errors here, `_guard_against_spurious_io_errors`.)"""
    try:
        from numba.core import caching
        save = caching.Cache.save_overload
    except (ImportError, AttributeError):      # another numba layout: as it is
        return
    if getattr(save, "_se3sync", False):
        return

    def save_overload(self, sig, data):
        try:
            save(self, sig, data)
        except OSError:
            pass
    save_overload._se3sync = True
    caching.Cache.save_overload = save_overload


# every source a compiled kernel's machine code can depend on: the modules that define kernels
# (jit, njit) and, transitively, every module of ours they import from (their constants and the
# functions they inline). tests/controller/test_jit_cache.py checks that it covers that closure.
KERNEL_SOURCES = (
    "controller/__init__.py", "controller/_agent_kernels.py", "controller/_kernels.py",
    "controller/errors.py", "controller/jit.py", "controller/kernels.py", "controller/layout.py",
    "controller/se3.py",
    "cosim/__init__.py", "cosim/analysis/delay_count.py", "cosim/analysis/linear.py",
    "cosim/analysis/stability_sparse.py", "cosim/controllers.py", "cosim/fastloop.py",
    "cosim/initial.py", "cosim/laws/decoupled.py", "cosim/log/cdr.py", "cosim/log/cdr_decode.py",
    "cosim/network_step.py", "cosim/plugins.py", "cosim/registry.py", "cosim/scenario.py",
    "cosim/signals.py",
    "bridge/mavlink/__init__.py", "bridge/mavlink/airframes.py", "bridge/mavlink/codec.py",
    "bridge/mavlink/config.py", "bridge/mavlink/frames.py", "bridge/mavlink/link.py",
    "bridge/mavlink/mapping.py", "bridge/mavlink/output.py", "bridge/mavlink/sequence.py",
    "bridge/mavlink/state.py", "bridge/mavlink/state_wire.py", "bridge/mavlink/transport.py",
    "bridge/mavlink/udp_io.py", "bridge/swarm/sample_wire.py", "bridge/swarm/tick.py",
    "plant_fmu/__init__.py", "plant_fmu/build.py", "plant_fmu/fast.py", "plant_fmu/layout.py",
)
_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
_PACKAGES = ("controller", "cosim", "bridge", "plant_fmu")    # whose kernels get the stamp
_STAMP = []     # the sources' digest, once computed


def sources_stamp(root: str = _ROOT, sources=KERNEL_SOURCES) -> bytes:
    """SHA-256 of `KERNEL_SOURCES` (each path and its bytes; a missing one as missing)."""
    import hashlib
    h = hashlib.sha256()
    for rel in sources:
        h.update(rel.encode() + b"\0")
        try:
            with open(os.path.join(root, rel), "rb") as f:
                h.update(f.read())
        except OSError:
            h.update(b"\0missing")
        h.update(b"\0")
    return h.digest()


_DEPENDS: dict = {}     # source file -> whether its kernels may inline ours


def _of_ours(v) -> bool:
    """``v`` (a module, or what a module imported: a function, a kernel, a class) is ours."""
    try:
        name = v.__name__ if isinstance(v, type(sys)) else getattr(v, "__module__", "")
        return isinstance(name, str) and name.partition(".")[0] in _PACKAGES
    except Exception:       # noqa: BLE001 - an object whose attributes raise: not ours
        return False


def _depends_on_ours(path: str) -> bool:
    """A file of our packages, or a module that imports from them (a law of the user's own
    whose step calls our kernels: `docs/architecture.md`, the compiled seam). Other packages'
    files keep numba's stamp: their caches are not ours to invalidate."""
    hit = _DEPENDS.get(path)
    if hit is None:
        hit = path.startswith(tuple(os.path.join(_ROOT, p) + os.sep for p in _PACKAGES))
        if not hit:
            for m in list(sys.modules.values()):
                f = getattr(m, "__file__", None)
                if f and os.path.abspath(f) == path:
                    hit = any(_of_ours(v) for v in list(vars(m).values()))
                    break
        _DEPENDS[path] = hit
    return hit


def _cache_stamps_cover_every_source() -> None:
    """A kernel's on-disk cache is valid for the sources it was compiled from, all of them.

    numba keeps a function's machine code with the digest of the function's own file only, but
    the code also holds what the function inlines from other files and the constants it reads
    there: editing `controller/_kernels.py` (the paper's geometry) left `agent_step` (in
    `_agent_kernels.py`) running the old law from the cache, silently, until the cache was
    cleared by hand. For a function in one of our files, or in a module that imports from them
    (a law of the user's own), the stamp numba compares is now that file's digest and
    `sources_stamp`'s together: an edit of any of `KERNEL_SOURCES` compiles those kernels again
    (a few seconds at the next run), never runs old machine code. Functions of other packages
    keep numba's stamp."""
    try:
        from numba.core import caching
        mixin = caching._SourceFileBackedLocatorMixin
        own = mixin.get_source_stamp
    except (ImportError, AttributeError):      # another numba layout: as it is
        return
    if getattr(own, "_se3sync", False):
        return

    def get_source_stamp(self):
        st = own(self)
        if not _depends_on_ours(os.path.abspath(str(getattr(self, "_py_file", "")))):
            return st
        if not _STAMP:
            _STAMP.append(sources_stamp(_ROOT, KERNEL_SOURCES))
        return (st, _STAMP[0])
    get_source_stamp._se3sync = True
    mixin.get_source_stamp = get_source_stamp


_NUMBA = []     # numba, once imported here
_AOT = []       # the ahead-of-time module and its names, once `use_aot` chose it


def numba_module():
    """numba, imported (once) as `_import_numba` and `_load_numba_without_blas_probe` do."""
    if not _NUMBA:
        if _AOT:
            raise RuntimeError("this process runs the ahead-of-time kernels: numba is not "
                               "to be imported (controller.jit.use_aot)")
        numba = _import_numba()
        _load_numba_without_blas_probe()
        _cache_writes_may_fail()
        _cache_stamps_cover_every_source()
        _NUMBA.append(numba)
    return _NUMBA[0]


def use_aot(module, names: dict) -> None:
    """From now on `jit` hands back ``module``'s function for each kernel that ``names`` maps
    ("module.function" of its source -> the name the module exports it as), the plain function
    for any other, and never imports numba. Only before any kernel was compiled here: a process
    is one or the other."""
    if _NUMBA:
        raise RuntimeError("use_aot: numba's kernels are already loaded in this process")
    _AOT[:] = [module, dict(names)]


def aot_module():
    """The module `use_aot` chose, or None (numba compiles the kernels)."""
    return _AOT[0] if _AOT else None


def jit(fn=None, *, inline=False, error_model="numpy"):
    # cache=True writes the machine code next to the source, so a second process starts
    # without recompiling. fastmath stays off: the plain-Python run must agree to rounding.
    # inline="always" is for the small per-edge helpers: a compiled call that passes arrays
    # increments and decrements each array's reference count (atomic operations), which cost
    # more than the helper's arithmetic; inlining at numba's IR level removes them.
    def wrap(f):
        if _AOT:
            name = _AOT[1].get(f"{f.__module__}.{f.__qualname__}")
            return f if name is None else getattr(_AOT[0], name)
        options = dict(cache=True, nogil=True, error_model=error_model)
        if inline:
            options["inline"] = "always"
        return numba_module().njit(**options)(f)

    return wrap(fn) if fn is not None else wrap
