"""What the machine did while a real-time test ran, for the tests that step at a wall-clock
rate (the swarm, the bridge through a relay): a test of this kind must not fail on load alone.

`CpuShare` measures, over a block of a test, the CPU time the whole machine spent busy
(/proc/stat: user, nice, system, irq, softirq and steal time of every core) and the CPU time
of the test's own processes (this process and its waited-for children, `getrusage`): the
difference is the CPU other work took meanwhile ("other", in cores).

`skip_if_deadline_missed` skips a test, before its assertions, when the run itself recorded
that it missed its deadline (the fraction of control steps that started after their deadline,
as the MAVLink plant counts them: ``late_steps``) above ``LATE_MAX`` while other work took
at least ``OTHER_MIN`` cores: the skip names both numbers. On a machine without other work
the assertions always run, so a test still fails when the code itself cannot keep the rate.
SE3SYNC_LOAD_SKIP=0 in the environment turns the skip off (the assertions always run). See
docs/testing.md.
"""
from __future__ import annotations

import os
import resource
import time

import pytest

LATE_MAX = 0.02    # fraction of a process's control steps that may start after their deadline
OTHER_MIN = 0.25   # cores of other work that make the machine "busy" for these tests


def _busy_seconds():
    """CPU seconds the machine has spent busy since boot (every core), or None (no procfs)."""
    try:
        with open("/proc/stat") as f:
            v = [int(x) for x in f.readline().split()[1:9]]
    except (OSError, ValueError):
        return None
    user, nice, system, _idle, _iowait, irq, softirq, steal = v
    return (user + nice + system + irq + softirq + steal) / os.sysconf("SC_CLK_TCK")


def _own_seconds() -> float:
    s, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return s.ru_utime + s.ru_stime + c.ru_utime + c.ru_stime


class CpuShare:
    """``with CpuShare() as cpu: ...``; then cpu.wall (s), cpu.busy, cpu.own and cpu.other
    (cores: average over the block; busy and other are None without /proc/stat). Children
    count as own once they have been waited for, so wait for them inside the block."""

    def __enter__(self):
        self._t, self._busy, self._own = time.monotonic(), _busy_seconds(), _own_seconds()
        return self

    def __exit__(self, *exc):
        self.wall = max(1e-9, time.monotonic() - self._t)
        self.own = (_own_seconds() - self._own) / self.wall
        busy = _busy_seconds()
        self.busy = None if busy is None or self._busy is None else (busy - self._busy) / self.wall
        self.other = None if self.busy is None else max(0.0, self.busy - self.own)
        return False

    def __str__(self):
        if self.other is None:
            return f"{self.wall:.1f} s, this test {self.own:.2f} cores"
        return (f"{self.wall:.1f} s: other work {self.other:.2f} of {os.cpu_count()} cores, "
                f"this test {self.own:.2f}")


def skip_if_deadline_missed(cpu: CpuShare, late: dict, what: str) -> None:
    """``late``: {process name: (late steps, steps)}. Skips when the largest late fraction
    exceeds LATE_MAX and other work took at least OTHER_MIN cores (see the module)."""
    name, (n_late, n) = max(late.items(), key=lambda kv: kv[1][0] / max(1, kv[1][1]))
    frac = n_late / max(1, n)
    print(f"\n{what}: {cpu}; late steps: "
          + ", ".join(f"{k} {a}/{b} ({a / max(1, b):.1%})" for k, (a, b) in late.items()))
    if os.environ.get("SE3SYNC_LOAD_SKIP", "1") == "0":
        return
    if frac > LATE_MAX and cpu.other is not None and cpu.other >= OTHER_MIN:
        pytest.skip(f"{what}: the machine could not keep the real-time deadline: {frac:.1%} of "
                    f"the control steps of {name} started late (limit {LATE_MAX:.0%}) while "
                    f"other work took {cpu.other:.2f} of {os.cpu_count()} cores (limit "
                    f"{OTHER_MIN})")
