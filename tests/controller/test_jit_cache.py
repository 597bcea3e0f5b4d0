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
