"""numba's on-disk cache that cannot be written (controller/jit.py): the kernel still runs."""
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

KERNEL = '''
from controller.jit import jit

@jit
def twice(x):
    return 2.0 * x
'''


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="RLIMIT_FSIZE as Linux has it")
def test_a_cache_that_cannot_be_written_leaves_the_kernel_running(tmp_path):
    """A process limited to 64-byte files (a full disk, as far as the cache is concerned)
    compiles a cached kernel into an empty cache directory: the call answers, exit 0, and no
    temporary file of numba's is left. (It raised numba's OSError out of the call.)"""
    import resource
    import signal

    (tmp_path / "k.py").write_text(KERNEL)
    cache = tmp_path / "cache"

    def limited():
        resource.setrlimit(resource.RLIMIT_FSIZE, (64, 64))
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)

    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache), "PYTHONDONTWRITEBYTECODE": "1",
           "PYTHONPATH": os.pathsep.join([str(tmp_path), str(ROOT)])}
    env.pop("NUMBA_DISABLE_JIT", None)
    r = subprocess.run([sys.executable, "-c", "import k; print(k.twice(21.0))"], cwd=tmp_path,
                       env=env, preexec_fn=limited, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and r.stdout.strip() == "42.0", r.stderr
    assert not [p for p in cache.rglob("*") if ".tmp." in p.name]


CALLEE = '''
from controller.jit import jit

STEP = {step}


@jit(inline=True)
def bump(x):
    return x + STEP
'''

CALLER = '''
from controller.jit import jit
from pkg.callee import bump


@jit
def twice_bumped(x):
    return 2.0 * bump(x)
'''

RUN = '''
import sys
from controller import jit
jit._ROOT = sys.argv[1]
jit._PACKAGES = ("pkg",)
jit.KERNEL_SOURCES = ("pkg/__init__.py", "pkg/callee.py", "pkg/caller.py")
from pkg.caller import twice_bumped
print(twice_bumped(1.0))
'''


def _project(tmp_path, script: str):
    """A package ``pkg`` (callee.py, caller.py) taken for ours by `controller.jit`, with numba's
    cache in tmp_path/cache: (a call of ``script`` in a fresh process, its printed number;
    a function that writes callee.py with STEP)."""
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "caller.py").write_text(CALLER)
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache"),
           "PYTHONDONTWRITEBYTECODE": "1",
           "PYTHONPATH": os.pathsep.join([str(tmp_path), str(ROOT)])}
    env.pop("NUMBA_DISABLE_JIT", None)

    def answer():
        r = subprocess.run([sys.executable, "-c", script, str(tmp_path)], cwd=tmp_path,
                           env=env, capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, r.stderr
        return float(r.stdout)

    def set_step(step: float) -> None:
        (pkg / "callee.py").write_text(CALLEE.format(step=step))

    return answer, set_step


def test_an_edit_of_what_a_kernel_inlines_compiles_it_again(tmp_path):
    """A cached kernel (`twice_bumped`, in caller.py) inlines a function and reads a constant
    of another file (callee.py). After that file is edited the next process runs the new code,
    not the cached machine code: numba's own stamp is the caller's file only (this answered
    4.0 again after STEP went from 1 to 2, as agent_step answered the old law after an edit of
    controller/_kernels.py)."""
    answer, set_step = _project(tmp_path, RUN)
    set_step(1.0)
    assert answer() == 4.0
    assert list((tmp_path / "cache").rglob("*.nbi"))      # cached: the next process loads it
    assert answer() == 4.0
    set_step(2.0)
    assert answer() == 6.0


def test_the_stamp_covers_every_source_a_kernel_depends_on():
    """`controller.jit.KERNEL_SOURCES` holds every module that defines a compiled kernel (jit,
    njit) and every module of ours that those import from, transitively (their constants and
    inlined functions are in the machine code)."""
    import ast

    from controller.jit import KERNEL_SOURCES

    pkgs = ("controller", "cosim", "bridge", "plant_fmu")

    def module_file(mod):
        p = ROOT.joinpath(*mod.split("."))
        for f in (p.with_suffix(".py"), p / "__init__.py"):
            if f.is_file():
                return f.relative_to(ROOT).as_posix()
        return None

    def imported(rel):
        path = ROOT / rel
        package = rel[:-3].split("/")[:-1]       # (an __init__'s package is its folder)
        out = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package[:len(package) - node.level + 1]
                    mod = ".".join(base + ([node.module] if node.module else []))
                else:
                    mod = node.module or ""
                if mod.split(".")[0] not in pkgs:
                    continue
                out.add(mod)
                out.update(f"{mod}.{a.name}" for a in node.names)
            elif isinstance(node, ast.Import):
                out.update(a.name for a in node.names if a.name.split(".")[0] in pkgs)
        return {f for f in map(module_file, out) if f is not None}

    kernels = set()
    for pkg in pkgs:
        for f in (ROOT / pkg).rglob("*.py"):
            text = f.read_text()
            if "@jit" in text or "njit(" in text or "@njit" in text:
                kernels.add(f.relative_to(ROOT).as_posix())
    assert "controller/_kernels.py" in kernels and "bridge/swarm/tick.py" in kernels
    seen, todo = set(), sorted(kernels)
    while todo:
        rel = todo.pop()
        if rel not in seen:
            seen.add(rel)
            todo.extend(imported(rel))
    assert not seen - set(KERNEL_SOURCES), sorted(seen - set(KERNEL_SOURCES))


USER_LAW = '''
from numba import njit
from pkg.callee import bump


@njit(cache=True)
def users_step(x):
    return 3.0 * bump(x)
'''

RUN_USER = RUN.replace("from pkg.caller import twice_bumped\nprint(twice_bumped(1.0))",
                       "from pkg.caller import twice_bumped\nimport userlaw\n"
                       "print(userlaw.users_step(1.0))")


def test_a_users_kernel_that_calls_ours_is_compiled_again_after_ours_change(tmp_path):
    """A law of the user's own, outside our packages, compiled with numba's njit and calling
    one of our kernels (the compiled seam of docs/architecture.md): after our file changes, its
    next process runs the new code too."""
    (tmp_path / "userlaw.py").write_text(USER_LAW)
    answer, set_step = _project(tmp_path, RUN_USER)
    set_step(1.0)
    assert answer() == 6.0
    assert answer() == 6.0
    set_step(2.0)
    assert answer() == 9.0
