"""Several agents in one process (bridge/swarm/host.py): how the host stops its agents. The
agents here are stand-ins for `run_agent` (the swarm itself, hosted, is in test_agents.py:
lockstep equals `run`, and SIGTERM finishes every output)."""
from __future__ import annotations

import os
import signal
import threading
import time

import pytest

from bridge.swarm.host import Host, run_agents
from cosim import signals

WAIT_S = 30.0   # a stand-in that is never told to stop gives up after this (the test then fails)


class _Master:
    def __init__(self):
        self.stopped = threading.Event()

    def request_stop(self):
        self.stopped.set()


def _stand_in(fail=(), registered=None):
    """A `run_agent` stand-in: registers a master, then runs until the master or the host's
    ``stop`` says stop (an agent of ``fail`` raises once every agent has registered)."""
    registered = registered if registered is not None else []

    def run_agent(agent_id, host, **kw):
        m = _Master()
        host.register(m)
        registered.append(agent_id)
        if agent_id in fail:
            while len(registered) < len(host.ids):
                time.sleep(0.001)
            raise RuntimeError(f"agent {agent_id} failed")
        told = m.stopped.wait(WAIT_S)
        return {"agent": agent_id, "interrupted": told, "host_stop": host.stop.is_set(), **kw}
    return run_agent


def test_an_agent_that_fails_stops_the_others_which_still_finish():
    out = run_agents(_stand_in(fail=(2,)), [1, 2, 3], lambda i: {"summary": f"agent_{i}.json"})
    assert list(out) == [1, 2, 3]
    assert isinstance(out[2], RuntimeError)
    for i in (1, 3):
        assert out[i] == {"agent": i, "interrupted": True, "host_stop": True,
                          "summary": f"agent_{i}.json"}


def test_an_agent_that_fails_before_the_host_first_looks_still_stops_the_others(monkeypatch):
    """The host's main thread descheduled between starting the agents and its first look at
    them, while one fails at once: it still stops the others (it waited for an agent to end,
    and the others waited for a stop: they ran until they ended on their own). The delay is
    made certain here: the host's first clear of its "an agent ended" event comes after the
    failing agent has set it."""
    import types

    from bridge.swarm import host as host_mod

    class LateLook(threading.Event):
        looked = False

        def clear(self):
            if not self.looked:
                self.looked = True
                assert self.wait(WAIT_S), "no agent ended"
            super().clear()

    monkeypatch.setattr(host_mod, "threading",
                        types.SimpleNamespace(**{**vars(threading), "Event": LateLook}))
    started = time.monotonic()
    out = run_agents(_stand_in(fail=(2,), registered=[]), [1, 2, 3], lambda i: {})
    assert isinstance(out[2], RuntimeError)
    assert all(out[i]["interrupted"] and out[i]["host_stop"] for i in (1, 3)), out
    assert time.monotonic() - started < WAIT_S


def test_a_signal_stops_every_agent_and_is_noted():
    registered = []

    def kill_when_running():
        t_end = time.monotonic() + WAIT_S
        while len(registered) < 3 and time.monotonic() < t_end:
            time.sleep(0.001)
        os.kill(os.getpid(), signal.SIGTERM)

    killer = threading.Thread(target=kill_when_running, daemon=True)
    killer.start()
    try:
        out = run_agents(_stand_in(registered=registered), [4, 5, 6], lambda i: {})
        assert signals.received() == "SIGTERM"
    finally:
        signals.reset()
        killer.join()
    assert all(out[i]["interrupted"] and out[i]["host_stop"] for i in (4, 5, 6)), out


def test_a_master_registered_after_the_stop_is_stopped_at_once():
    host = Host([1, 2])
    first = _Master()
    host.register(first)
    host.stop_all()
    late = _Master()
    host.register(late)
    assert first.stopped.is_set() and late.stopped.is_set() and host.stop.is_set()


def test_agents_that_all_finish_are_not_stopped():
    def run_agent(agent_id, host, **kw):
        host.register(_Master())
        return {"agent": agent_id}

    out = run_agents(run_agent, [3, 1], lambda i: {})
    assert out == {3: {"agent": 3}, 1: {"agent": 1}} and list(out) == [3, 1]


def test_stop_all_may_be_reentered_as_a_signal_handler_would():
    """SIGINT or SIGTERM runs `stop_all` in the main thread, which may be inside `stop_all`
    already (an agent failed a moment before): the second call must not wait for the first."""
    host = Host([1])

    class _Reenters(_Master):
        def request_stop(self):
            super().request_stop()
            if len(calls) < 2:
                calls.append(True)
                host.stop_all()

    calls = []
    m = _Reenters()
    host.register(m)
    t = threading.Thread(target=host.stop_all, daemon=True)
    t.start()
    t.join(WAIT_S)
    assert not t.is_alive() and m.stopped.is_set() and len(calls) == 2


# ---------------------------------------------------------------------------- the stepping thread
class _Paced:
    """A plant paced by the host: its loop's step k (k ≥ 1) is due at t0 + k·h."""

    def __init__(self, t0, h):
        self.t0, self.h, self.k = t0, h, 0
        self.due = None
        self.resumes = 0

    def advance(self):
        self.k += 1
        self.due = self.t0 + self.k * self.h

    def resume(self):
        self.resumes += 1


def _loop(plant, name, n, log, fail_at=None):
    """A stand-in for `Master.steps`: n steps, each noted (name, k, time, thread)."""
    for k in range(n):
        log.append((name, k, time.monotonic(), threading.get_ident()))
        if k == fail_at:
            raise RuntimeError(f"{name} failed at step {k}")
        plant.advance()
        yield
    return {"name": name, "steps": n}


def _drive_all(host, loops):
    """Drives each (name, plant, steps) from a thread of its own, as the agents' threads do;
    returns {name: (summary, cpu) or the exception} and the drivers' thread ids."""
    out, idents = {}, set()

    def driver(name, plant, steps):
        idents.add(threading.get_ident())
        try:
            out[name] = host.drive(steps, plant)
        except Exception as exc:  # noqa: BLE001 - compared below
            out[name] = exc

    ts = [threading.Thread(target=driver, args=x, daemon=True) for x in loops]
    for t in ts:
        t.start()
    for t in ts:
        t.join(WAIT_S)
    assert not any(t.is_alive() for t in ts)
    host.close()
    return out, idents


def test_one_thread_steps_every_loop_none_before_its_deadline():
    from bridge.swarm.host import DUE_SLACK_S

    host = Host([1, 2, 3])
    h, n, log = 0.005, 30, []
    t0 = time.monotonic() + 0.02
    plants = {f"a{i}": _Paced(t0 + i * 1e-6, h) for i in range(3)}   # one timeline, read apart
    out, drivers = _drive_all(host, [(k, p, _loop(p, k, n, log)) for k, p in plants.items()])
    for name, p in plants.items():
        summary, cpu = out[name]
        assert summary == {"name": name, "steps": n} and cpu >= 0.0
        assert p.resumes == n + 1    # before each step, and before the end
    stepper = {e[3] for e in log}
    assert len(stepper) == 1 and not stepper & drivers        # one thread, none of the drivers'
    assert len(log) == 3 * n
    for name, k, t, _ in log:
        if k:
            assert t >= plants[name].t0 + k * h - DUE_SLACK_S, (name, k)
    # closed with no loop left: the stepping thread ends
    t_end = time.monotonic() + WAIT_S
    while any(t.ident in stepper for t in threading.enumerate()) and time.monotonic() < t_end:
        time.sleep(0.001)
    assert not any(t.ident in stepper for t in threading.enumerate())


def test_a_loop_that_fails_raises_in_its_driver_and_the_others_go_on():
    host = Host([1, 2])
    t0, h, log = time.monotonic(), 0.002, []
    a, b = _Paced(t0, h), _Paced(t0, h)
    out, _ = _drive_all(host, [("a", a, _loop(a, "a", 20, log, fail_at=5)),
                               ("b", b, _loop(b, "b", 20, log))])
    assert isinstance(out["a"], RuntimeError) and "step 5" in str(out["a"])
    assert out["b"][0] == {"name": "b", "steps": 20}


def test_a_loop_that_joins_later_starts_at_once():
    """Step 0 of a loop that joins while the stepper waits a long deadline runs at once: every
    step of the loop that joined is in the log before that deadline (the times the steps
    recorded, not a stopwatch around the call)."""
    host = Host([1, 2])
    log = []
    slow = _Paced(time.monotonic(), 2.0)           # one step; the loop ends at its deadline, 2 s
    started = threading.Event()

    def drive_slow():
        started.set()
        host.drive(_loop(slow, "slow", 1, log), slow)

    t = threading.Thread(target=drive_slow, daemon=True)
    t.start()
    started.wait(WAIT_S)
    while not log:
        time.sleep(0.001)
    quick = _Paced(time.monotonic(), 0.001)
    summary, _ = host.drive(_loop(quick, "quick", 3, log), quick)
    t.join(WAIT_S)
    host.close()
    assert not t.is_alive() and summary["steps"] == 3
    steps = [(name, k) for name, k, _, _ in log]
    assert steps == [("slow", 0), ("quick", 0), ("quick", 1), ("quick", 2)], steps
    assert all(when < slow.due for name, _, when, _ in log if name == "quick"), (log, slow.due)


def test_master_steps_yields_once_per_step_and_ends_as_run():
    """`Master.steps` driven by hand: one yield per step, and the summary and final state of
    `Master.run` (the Python reference loop, which `run` now drives the same way)."""
    import numpy as np

    from cosim.master import Master
    from cosim.plants import FmuPlant
    from cosim.scenario import load_scenario
    from pathlib import Path

    sc = load_scenario(Path(__file__).resolve().parents[2] / "scenarios" / "paper_6uav.toml",
                       ["simulation.duration=0.3"])
    out = []
    for by_hand in (False, True):
        plant = FmuPlant.from_scenario(sc)
        try:
            m = Master(sc, plant, "hybrid", None)
            m.use_compiled = False
            if by_hand:
                gen, yields = m.steps(sc.n_steps()), 0
                try:
                    while True:
                        next(gen)
                        yields += 1
                except StopIteration as end:
                    s = end.value
                assert yields == sc.n_steps() == s["steps"]
            else:
                s = m.run(sc.n_steps())
            out.append((s, plant.read().copy()))
        finally:
            plant.close()
    (s0, S0), (s1, S1) = out
    assert np.array_equal(S0, S1)
    timing = ("wall_time_s", "realtime_factor", "us_per_step")
    assert {k: v for k, v in s0.items() if k not in timing} == \
        {k: v for k, v in s1.items() if k not in timing}


def test_a_plant_that_fails_after_its_wait_fails_inside_the_loop():
    """`resume` raising is thrown into the loop at its last step, as a plant that waits for
    itself raises from `advance`: the loop's own handlers see it (here it records it and ends)."""
    host = Host([1])

    class _Breaks(_Paced):
        def resume(self):
            super().resume()
            if self.resumes == 4:
                raise OSError("link gone")

    p, seen = _Breaks(time.monotonic(), 0.001), []

    def loop():
        try:
            for _ in range(10):
                p.advance()
                yield
        except OSError as exc:
            seen.append((p.k, str(exc)))
            return {"failed_at": p.k}

    summary, _ = host.drive(loop(), p)
    host.close()
    assert summary == {"failed_at": 3} and seen == [(3, "link gone")]
