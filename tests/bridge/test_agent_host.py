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
