"""Suite-wide setup: the same verdicts however the suite was started (docs/testing.md)."""
import signal


def pytest_configure(config):
    # A suite started in the background of a non-interactive shell (`python -m pytest &` in a
    # script, a CI step's background job) inherits SIGINT ignored, and so would every process
    # a test starts: the tests of Ctrl-C (cosim.signals.interruptible, SIGINT during a
    # command's start-up) would then see their signal vanish. Python's own handler is restored.
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
