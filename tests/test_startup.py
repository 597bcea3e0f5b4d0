"""Start-up: what `controller.jit` keeps numba from importing, and that numba still does
everything it did (BLAS, its config file, extension entry points). Each case runs in a fresh
process, since each is about what a process imports."""
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "scenarios" / "paper_6uav.toml"


def _run(code, cwd=None, extra_path=None, timeout=300):
    env = dict(os.environ, NUMBA_DISABLE_JIT="0")
    env.pop("NUMBA_BOUNDSCHECK", None)
    path = [str(ROOT)] + ([str(extra_path)] if extra_path else [])
    env["PYTHONPATH"] = os.pathsep.join(path + [env.get("PYTHONPATH", "")])
    r = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True,
                       text=True, timeout=timeout, env=env, cwd=cwd)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout.strip().splitlines()[-1])


def _numba_extensions_installed():
    from importlib.metadata import entry_points
    return bool(list(entry_points(group="numba_extensions")))


def _yaml_installed():
    import importlib.util
    return importlib.util.find_spec("yaml") is not None


_BLAS_SCRIPT = r"""
import sys
import numpy as np
import controller as C
from controller import se3
g = C.Graph(3, [(1, 2), (2, 3)])
q = se3.rot_to_quat(np.eye(3))                  # a compiled kernel: numba's registries load
before = "scipy.linalg" in sys.modules
import numba
@numba.njit
def gemv(a, x):
    return np.dot(a, x)
a = np.arange(12.0).reshape(3, 4)
x = np.arange(4.0)
equal = np.array_equal(gemv(a, x), a @ x)
print(before, "scipy.linalg" in sys.modules, equal, q.tolist())
"""


def test_numba_loads_without_importing_scipy_linalg_and_blas_still_works():
    """`controller.jit` steps over numba's import-time BLAS probe (the start-up's 0.11 s):
    the first compiled call leaves scipy.linalg unimported, and a kernel that does call BLAS
    still compiles (numba's own probe is back in place) and agrees with numpy."""
    r = subprocess.run([sys.executable, "-c", _BLAS_SCRIPT], capture_output=True, text=True,
                       timeout=300, env=dict(os.environ, NUMBA_DISABLE_JIT="0"))
    assert r.returncode == 0, r.stderr
    before, after, equal, q = r.stdout.split(maxsplit=3)
    assert (before, after, equal) == ("False", "True", "True")
    assert json.loads(q) == [1.0, 0.0, 0.0, 0.0]


def test_numba_is_imported_without_scipy_yaml_or_the_entry_point_scan(tmp_path):
    """After the first compiled call: scipy and yaml are not imported, nor importlib.metadata
    when no installed package declares a numba extension; all three import normally afterwards,
    and numba's config still knows yaml is there."""
    out = _run("""
        import json, sys
        import numpy as np
        from controller import se3
        q = se3.rot_to_quat(np.eye(3))
        seen = {m: m in sys.modules for m in ("scipy", "yaml", "importlib.metadata")}
        import scipy.linalg, importlib.metadata
        from numba.core import config
        ok = bool(np.allclose(scipy.linalg.expm(np.zeros((2, 2))), np.eye(2)))
        print(json.dumps([seen, ok, config._HAVE_YAML, hasattr(importlib.metadata, "version"),
                          q.tolist()]))
    """, cwd=tmp_path)
    seen, ok, have_yaml, md, q = out
    assert seen["scipy"] is False and seen["yaml"] is False
    if not _numba_extensions_installed():
        assert seen["importlib.metadata"] is False
    assert ok and md and q == [1.0, 0.0, 0.0, 0.0]
    assert have_yaml is _yaml_installed()


@pytest.mark.skipif(not _yaml_installed(), reason="numba reads its config file with yaml")
def test_numba_config_file_is_still_read(tmp_path):
    """A `.numba_config.yaml` in the working directory is read at import, as numba reads it;
    one written after the import is read by numba's `reload_config` through the lazy yaml."""
    (tmp_path / "at_import").mkdir()
    (tmp_path / "at_import" / ".numba_config.yaml").write_text("boundscheck: 1\n")
    assert _run("""
        import json
        import controller.jit
        controller.jit.numba_module()   # numba is imported at the first kernel
        from numba.core import config
        print(json.dumps(config.BOUNDSCHECK))
    """, cwd=tmp_path / "at_import") == 1
    (tmp_path / "later").mkdir()
    assert _run("""
        import json, sys
        import controller.jit
        controller.jit.numba_module()   # numba is imported at the first kernel
        from numba.core import config
        before = (config.BOUNDSCHECK, "yaml" in sys.modules)
        open(".numba_config.yaml", "w").write("boundscheck: 1\\n")
        config.reload_config()
        print(json.dumps([before, config.BOUNDSCHECK]))
    """, cwd=tmp_path / "later") == [[None, False], 1]


def test_a_numba_extension_entry_point_still_runs(tmp_path):
    """A distribution on sys.path that declares a `numba_extensions` `init` entry point: the
    start-up scan sees it, numba imports importlib.metadata and runs the hook at the first
    compile. Without it the scan answers as importlib.metadata does."""
    site = tmp_path / "site"
    dist = site / "numbaext_probe-1.0.dist-info"
    dist.mkdir(parents=True)
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: numbaext-probe\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text("[numba_extensions]\ninit = numbaext_probe:init\n")
    (site / "numbaext_probe.py").write_text("CALLS = []\n\ndef init():\n    CALLS.append(1)\n")
    code = """
        import json, sys
        import numpy as np
        from controller import jit as _jit, se3
        scan = _jit._no_numba_extensions()
        from importlib.metadata import entry_points
        truth = not list(entry_points(group="numba_extensions"))
        se3.rot_to_quat(np.eye(3))
        probe = sys.modules.get("numbaext_probe")
        print(json.dumps([scan, truth, None if probe is None else probe.CALLS]))
    """
    scan, truth, calls = _run(code, cwd=tmp_path, extra_path=site)
    assert (scan, truth, calls) == (False, False, [1])
    scan, truth, _ = _run(code, cwd=tmp_path)
    assert scan == truth


def test_run_does_not_import_scipy_for_identical_agents(tmp_path):
    """`se3sync run` on the paper scenario (identical agents: the modal analysis, the compiled
    loop, the log) never imports scipy: 0.2 s of its start-up. The sparse analysis of
    heterogeneous agents and `check` import it when they need it."""
    out = _run(f"""
        import json, sys
        from cosim.cli import main
        rc = main(["run", {str(PAPER)!r}, "--duration", "0.01",
                   "--log", {str(tmp_path / "a.mcap")!r}])
        print(json.dumps([rc, sorted(m for m in sys.modules if m.split(".")[0] == "scipy")]))
    """, cwd=tmp_path)
    assert out == [0, []]
    assert (tmp_path / "a.mcap").stat().st_size > 0


def test_an_agent_process_does_not_import_fmpy(tmp_path):
    """Issue 31: an agent process steps no FMU, and `import bridge.swarm.agent` (through
    cosim.master → cosim.fastloop → plant_fmu.fast) leaves fmpy unimported (20-30 ms and 2 MB of
    every agent's start-up); plant_fmu.fast imports it when a FleetFMU is made, which still
    works."""
    out = _run("""
        import json, sys
        import bridge.swarm.agent
        before = "fmpy" in sys.modules
        from plant_fmu.fast import FleetFMU
        with FleetFMU(1) as f:
            f.initialize()
            f.do_step(0.0, 0.001)
            ok = f.get_state().shape == (1, 18)
        print(json.dumps([before, "fmpy" in sys.modules, ok]))
    """, cwd=tmp_path)
    assert out == [False, True, True]
