"""The agent process's kernels compiled ahead of time (issue 31): an agent runs without numba.

numba and LLVM were two thirds of an agent process's memory: importing numba maps 67 MB, and
its first compiled call (even from the on-disk cache) builds numba's runtime helpers with LLVM,
28 MB more of LLVM's pages: 154 MB in all, of which the agent's own work is ~50. The agent calls
a handful of kernels (`EXPORTS`); numba's ahead-of-time compiler (`numba.pycc`) compiles those
same functions, with what they call inlined as in the JIT, into one extension module that needs
numpy and nothing of numba's. Its code is for the architecture's generic CPU; the kernels are
compiled without fastmath, so LLVM neither reorders nor fuses floating-point operations for
either target and the two agree bit for bit (tests/bridge/test_agent_aot.py checks every
kernel on random inputs, and lockstep swarms either way).

The module is built once per source (`key`: the kernels' sources, numba's, numpy's and Python's
versions) by a child process (`python -m bridge.swarm.aot`, which dies with the process that
started it), under a lock so that a swarm's agents starting together build it once, into the
directory of numba's cache (`cache_dir`); it appears there whole or not at all. A
process calls `use` before it imports any kernel: from then on `controller.jit.jit` hands out
the module's functions (`controller.jit.use_aot`). Where the module cannot be built (no C
compiler), `use` says why and the process stays on numba's JIT.
"""
from __future__ import annotations

import fcntl
import hashlib
import importlib
import importlib.machinery
import importlib.util
import os
import shutil
import subprocess
import sys
import sysconfig
import tempfile
import time
import warnings
from pathlib import Path

from controller import jit
from cosim import signals

__all__ = ["EXPORTS", "key", "cache_dir", "module_path", "ensure", "load", "use", "AotError"]

ROOT = Path(__file__).resolve().parents[2]
BUILD_TIMEOUT_S = 600.0

# name -> ("module" or "module:function", numba signature): the kernels an agent process calls
# (its compiled step, the neighbour samples' decoder and encoder, the metrics of its samples, the
# quaternions, the reference view's one-edge pieces, the CDR log's scatter). The hot ones take
# the exact layouts their callers pass.
EXPORTS = {
    "agent_step": ("controller._agent_kernels",
                   "i8(f8[:, ::1], i8[::1], i8[::1], b1[::1], i8[::1], i8[::1], b1, f8[::1], "
                   "f8, i8, b1, f8[::1], f8[::1], f8[::1], f8[::1], f8[::1], b1[::1], f8[:, ::1],"
                   " f8[:, ::1], f8[:, ::1])"),
    "scan_sample": ("bridge.swarm.sample_wire",
                    "i8(Array(uint8, 1, 'C', readonly=True), i8, i8, i8, i8, i8, i8, u1[::1], "
                    "f8[::1], i8[::1])"),
    "drain_samples": ("bridge.swarm.sample_wire",
                      "i8(i8, i8, i8[::1], i8[::1], i8[::1], i8, i8, i8, i8, f8, u1[::1], u1[::1], "
                      "f8[::1], i8[::1], i8[::1], f8[:, ::1], f8[::1], i8[:, ::1], i8[::1], "
                      "i8[::1])"),
    "scan_odometry": ("bridge.mavlink.state_wire",
                      "i8(Array(uint8, 1, 'C', readonly=True), i8, i8, u1[::1], f8[::1], "
                      "i8[::1])"),
    "recv_state": ("bridge.mavlink.state_wire",
                   "i8(i8, u1[::1], i8, u1[::1], f8[::1], i8[::1])"),
    "take_states": ("bridge.mavlink.state_wire",
                    "i8(i8, u1[::1], u1[::1], f8[::1], i8[::1], i8, i8, i8, f8, f8, f8[::1], "
                    "u8[::1], i8[::1], f8[::1], i8[::1])"),
    "wire_to_state_ned": ("bridge.mavlink.state_wire", "void(f8[:, ::1], f8[:, ::1])"),
    "age_rules": ("bridge.swarm.sample_wire",
                  "i8(i8, i8[::1], i8, i8, i8, i8[::1], i8[::1], i8[::1], i8[:, ::1], "
                  "f8[:, ::1], f8[::1], i8[::1], i8[::1], i8[::1])"),
    "send_all": ("bridge.mavlink.udp_io", "i8(i8[::1], u1[::1], i8, i8[::1])"),
    "pack_command": ("bridge.mavlink.state_wire",
                     "i8(u1[::1], i8, f8, f8, f8, f8, f8, f8, i8, i8, i8, i8, i8, i8, i8, f4[::1])"),
    "command_row": ("bridge.mavlink.state_wire",
                    "i8(f8[::1], f8[:, ::1], f8[::1], b1, b1, f8, f8[::1], f8[:, ::1], i8, i8, i8, "
                    "i8, i8, i8, i8, u1[::1], f4[::1], i8[::1], i8[::1], i8[::1])"),
    "pack_sample": ("bridge.swarm.sample_wire",
                    "i8(u1[::1], i8, f8[::1], b1, f8[::1], i8, i8, i8, i8, f4[::1], i8[::1])"),
    "publish_sample": ("bridge.swarm.sample_wire",
                       "i8(u1[::1], i8, f8[:, ::1], f8[::1], i8[::1], f8[::1], i8, i8, f4[::1], "
                       "i8[::1], i8[::1], i8[::1], i8[::1])"),
    "held_rows": ("bridge.swarm.sample_wire", "void(f8[:, ::1], f8[:, ::1], i8[::1], f8[:, ::1])"),
    "agent_tick": ("bridge.swarm.tick",
                   "i8(i8, i8[::1], f8[::1], u1[::1], b1, f8, i8, i8, i8, i8, i8, i8)"),
    "rot_to_quat_rows": ("controller._kernels", "void(f8[:, ::1], f8[:, ::1])"),
    "network_U": ("controller._kernels",
                  "void(f8[:, ::1], f8[::1], i8[:, ::1], f8[::1], f8[::1])"),
    "metrics": ("controller._kernels",
                "UniTuple(f8, 2)(f8[:, ::1], i8[:, ::1], f8[::1], f8, f8[::1], f8[:, :, ::1], "
                "f8[::1], f8[::1], f8[:, ::1])"),
    "relative_pose": ("controller._kernels", "void(f8[:, :], i8, f8[:, :], i8, f8[:, :], f8[:])"),
    "edge_term": ("controller._agent_kernels",
                  "f8(f8[:, :], f8[:], f8, f8[:], f8[:], b1, f8[::1], f8[:])"),
    "edge_flow": ("controller._agent_kernels", "f8(f8[:, :], f8[:], f8, f8[::1], f8)"),
    "wrench_sum": ("controller._agent_kernels", "void(f8[:], f8[:, :], f8[::1], f8[:])"),
    # the CDR log's scatter (`cosim.log.cdr`: `--log-encoding cdr`)
    "cdr_scatter": ("cosim.log.cdr:_scatter_py",
                    "void(f8[:, ::1], u4[:, ::1], i8, i8[::1], f8[:, ::1], i8[::1], i8[::1], "
                    "i8[::1], i8[::1], u4[:, ::1])"),
}

# what the module is compiled from: every source its kernels read (constants included), the
# same list that keeps numba's on-disk caches honest (`controller.jit.KERNEL_SOURCES`), and this
SOURCES = (*jit.KERNEL_SOURCES, "bridge/swarm/aot.py")


class AotError(Exception):
    """The ahead-of-time module cannot be had here; the message says why, on one line."""


def key() -> str:
    """16 hex digits naming one build: the sources, the exports and the tools' versions."""
    from importlib.metadata import version

    h = hashlib.sha256(jit.sources_stamp(str(ROOT), SOURCES))
    for dist in ("numba", "numpy", "pymavlink"):
        try:
            h.update(f"{dist}={version(dist)}\0".encode())
        except Exception:       # not installed as a distribution: the build will say so
            h.update(f"{dist}=?\0".encode())
    h.update(f"{sys.version}\0{sysconfig.get_platform()}\0".encode())
    return h.hexdigest()[:16]


def cache_dir() -> Path:
    """Where builds live: beside numba's cache (``NUMBA_CACHE_DIR``/se3sync_aot when it is
    set), else this package's ``__pycache__``, else ``~/.cache/se3sync/aot``."""
    env = os.environ.get("NUMBA_CACHE_DIR")
    if env:
        return Path(env) / "se3sync_aot"
    here = Path(__file__).resolve().parent / "__pycache__"
    try:
        here.mkdir(exist_ok=True)
        if os.access(here, os.W_OK):
            return here
    except OSError:
        pass
    return Path.home() / ".cache" / "se3sync" / "aot"


def _name(k: str) -> str:
    return f"agent_kernels_{k}"


def module_path(k: str | None = None) -> Path:
    k = k or key()
    return cache_dir() / (_name(k) + sysconfig.get_config_var("EXT_SUFFIX"))


def ensure(timeout: float = BUILD_TIMEOUT_S, progress=None) -> Path:
    """The built module's path, building it first (in a child process) when there is none.
    Concurrent callers wait for one build (a lock file). Raises `AotError` with the reason when
    it cannot be built; the reason is kept beside it, so the next caller does not try again
    until a source or a tool changes."""
    k = key()
    path = module_path(k)
    if path.exists():
        return path
    d = path.parent
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise AotError(f"cannot make {str(d)!r}: {exc.strerror}") from None
    failed = d / f"{_name(k)}.failed"
    deadline = time.monotonic() + timeout
    with open(d / f"{_name(k)}.lock", "a+") as lock:
        while True:
            try:
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() > deadline:
                    raise AotError(f"waited {timeout:g} s for another process's build") from None
                time.sleep(0.05)
        try:
            if path.exists():
                return path
            if failed.exists():
                raise AotError(failed.read_text().strip() or "an earlier build failed")
            if progress is not None:
                progress("compiling the agent's kernels ahead of time (once per source)")
            _build(k, path, failed, deadline)
            return path
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def _build(k: str, path: Path, failed: Path, deadline: float) -> None:
    with tempfile.TemporaryDirectory(dir=path.parent, prefix=".build-") as tmp:
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join([str(ROOT)] + [p for p in
                                             env.get("PYTHONPATH", "").split(os.pathsep) if p])
        env.pop("NUMBA_DISABLE_JIT", None)
        try:
            r = subprocess.run([sys.executable, "-m", "bridge.swarm.aot", tmp, _name(k)],
                               capture_output=True, text=True, env=env, cwd=tmp,
                               timeout=max(1.0, deadline - time.monotonic()),
                               preexec_fn=signals.die_with(os.getpid()))
        except subprocess.TimeoutExpired:
            raise AotError("the build ran past its time") from None
        built = Path(tmp) / path.name
        if r.returncode != 0 or not built.exists():
            lines = [ln for ln in (r.stderr or r.stdout or "").splitlines() if ln.strip()]
            reason = f"the build failed: {lines[-1].strip() if lines else f'exit {r.returncode}'}"
            failed.write_text(reason[:500] + "\n")
            raise AotError(reason)
        os.replace(built, path)     # whole or not at all: a reader never sees half a module
    _prune(path)


def _prune(keep: Path, age_s: float = 86400.0) -> None:
    """Builds of other sources (an edited kernel, another numba) left a day ago or more, and
    the build directories of builds killed an hour ago or more (a process killed while it
    built: its builder died with it, `cosim.signals.die_with`)."""
    now = time.time()
    for old in keep.parent.glob("agent_kernels_*"):
        if old.name.split(".")[0] == keep.name.split(".")[0]:
            continue
        try:
            if now - old.stat().st_mtime > age_s:
                old.unlink()
        except OSError:
            pass
    for old in keep.parent.glob(".build-*"):
        try:
            if now - old.stat().st_mtime > 3600.0:
                shutil.rmtree(old, ignore_errors=True)
        except OSError:
            pass


def load(path: Path | None = None):
    """The built module (import it once; a later call returns the same module)."""
    path = Path(path) if path is not None else module_path()
    name = path.name.split(".")[0]
    if name in sys.modules:
        return sys.modules[name]
    loader = importlib.machinery.ExtensionFileLoader(name, str(path))
    spec = importlib.util.spec_from_file_location(name, str(path), loader=loader)
    module = importlib.util.module_from_spec(spec)
    loader.exec_module(module)
    sys.modules[name] = module
    return module


def use(progress=None) -> str:
    """Make this process run the kernels from the ahead-of-time module (building it when
    needed). Returns "aot", or "jit: <why>" when the process stays on numba's JIT (the module
    cannot be built, or a kernel was already loaded)."""
    if jit.aot_module() is not None:
        return "aot"
    if "controller._kernels" in sys.modules:
        return "jit: the kernels were loaded before the choice"
    if os.environ.get("NUMBA_DISABLE_JIT", "0") not in ("", "0"):
        return "jit: NUMBA_DISABLE_JIT is set (the kernels run as Python)"
    try:
        module = load(ensure(progress=progress))
    except (AotError, ImportError, OSError) as exc:
        return f"jit: {exc}"
    jit.use_aot(module, source_names())
    return "aot"


def source_names() -> dict:
    """{"module.function" of each export's source: its name in the module} (`jit.use_aot`)."""
    out = {}
    for export, (target, _) in EXPORTS.items():
        mod, _, attr = target.partition(":")
        out[f"{mod}.{attr or export}"] = export
    return out


def _compile(out_dir: str, name: str) -> None:
    """The child process's work: compile `EXPORTS` into ``out_dir``/``name``."""
    jit.numba_module()      # numba as the JIT imports it
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")     # numba.pycc's pending-deprecation notice
        from numba.pycc import CC
    cc = CC(name)
    cc.output_dir = out_dir
    cc.verbose = False
    for export, (target, sig) in EXPORTS.items():
        mod, _, attr = target.partition(":")
        f = getattr(importlib.import_module(mod), attr or export)
        cc.export(export, sig)(getattr(f, "py_func", f))
    cc.compile()


if __name__ == "__main__":
    if len(sys.argv) != 3:
        print("usage: python -m bridge.swarm.aot OUT_DIR NAME", file=sys.stderr)
        sys.exit(2)
    try:
        _compile(sys.argv[1], sys.argv[2])
    except Exception as exc:    # one line for the parent's reason (AotError)
        first = next((ln for ln in str(exc).splitlines() if ln.strip()), "")
        print(f"{type(exc).__name__}: {first}", file=sys.stderr)
        sys.exit(1)
