"""Suite-wide setup: the same verdicts however the suite was started (docs/testing.md)."""
import signal
import sys
from pathlib import Path

# The tests are grouped by package (tests/controller, tests/plant_fmu, tests/cosim, tests/bridge)
# without __init__ files, and a few reuse another group's helpers by module name (the swarm
# comparison of tests/bridge/test_agents.py, the live view's client of tests/cosim/test_live.py):
# every group's directory is importable, as tests/ itself is (this file's directory).
_HERE = Path(__file__).resolve().parent
for _group in ("controller", "plant_fmu", "cosim", "bridge"):
    if str(_HERE / _group) not in sys.path:
        sys.path.append(str(_HERE / _group))


def pytest_configure(config):
    # A suite started in the background of a non-interactive shell (`python -m pytest &` in a
    # script, a CI step's background job) inherits SIGINT ignored, and so would every process
    # a test starts: the tests of Ctrl-C (cosim.signals.interruptible, SIGINT during a
    # command's start-up) would then see their signal vanish. Python's own handler is restored.
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
