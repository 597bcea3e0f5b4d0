"""Several agents of a swarm in one process (`se3sync agent --id 1,2,3`, `swarm
--agents-per-process K`): one thread per agent, each the whole of `run_agent` (its own vehicle
link, neighbour link, master loop, log and summary), sharing one interpreter.

Why: on a machine that simulates many vehicles, an agent process costs what its interpreter,
numpy and numba's JIT cost (about 150 MB resident, most of it the same in every process) and a
wake-up of its own every step. Hosted together, K agents hold those once, and the agents of a
process wake at the same deadline back to back. Nothing the agents compute changes: each thread
talks to its vehicle and its neighbours over its own sockets and the same wire as a process of
its own would, and a lockstep swarm hosted this way equals `se3sync run` as one process per
agent does. A companion computer runs one agent: hosting is for simulation machines.

Stopping: the main thread catches SIGINT and SIGTERM and asks every agent to stop
(`Master.request_stop` for a running master loop; an agent still connecting, waiting for the
start or waiting in lockstep sees the signal itself through `cosim.signals`). An agent that
fails stops the others (`Host.stop`: each finishes its log and summary as "interrupted"); its
neighbours in other processes would fail safe anyway, and `swarm` stops the swarm.
"""
from __future__ import annotations

import threading

from cosim import signals

__all__ = ["Host", "run_agents"]

JOIN_POLL_S = 0.05


class Host:
    """What the agents of one process share (`run_agent`'s ``host``): their ids, the ``stop``
    event and their master loops (`register`), which `stop_all` asks to stop."""

    def __init__(self, ids):
        self.ids = tuple(int(i) for i in ids)
        self.stop = threading.Event()
        # passed between the agents' vehicle plants (`MavlinkPlant.step_lock`): one step at a
        # time (see `run_agent`)
        self.step_lock = threading.Lock()
        self._masters = []
        # re-entrant: the main thread's signal handler may call stop_all while it is in stop_all
        self._lock = threading.RLock()

    def register(self, master) -> None:
        with self._lock:
            self._masters.append(master)
            if self.stop.is_set():
                master.request_stop()

    def stop_all(self) -> None:
        with self._lock:
            self.stop.set()
            for m in self._masters:
                m.request_stop()


class _Agent(threading.Thread):
    def __init__(self, run_agent, agent_id: int, kwargs: dict):
        super().__init__(name=f"agent {agent_id}", daemon=True)
        self.run_agent = run_agent
        self.agent_id = agent_id
        self.kwargs = kwargs
        self.result = None

    def run(self):
        try:
            self.result = self.run_agent(agent_id=self.agent_id, **self.kwargs)
        except BaseException as exc:  # noqa: BLE001 - handed to the main thread
            self.result = exc


def run_agents(run_agent, ids, kwargs_for) -> dict:
    """Runs ``run_agent(agent_id=i, host=…, **kwargs_for(i))`` for every i of ``ids``, each in
    its own thread, and waits for all of them; returns {i: its summary or the exception it
    raised}, in the order of ``ids``. The first agent to fail (an exception other than
    KeyboardInterrupt) stops the others, and so does a signal. The caller sets the process's
    BLAS threads (`cosim.threads.limit_process`): `run_agent` leaves them to the host."""
    host = Host(ids)
    threads = [_Agent(run_agent, i, {**kwargs_for(i), "host": host}) for i in host.ids]
    with signals.catching(host.stop_all):
        for t in threads:
            t.start()
        while True:
            alive = [t for t in threads if t.is_alive()]
            if not alive:
                break
            alive[0].join(JOIN_POLL_S)
            if not host.stop.is_set() and any(
                    isinstance(t.result, BaseException) and not isinstance(t.result, KeyboardInterrupt)
                    for t in threads if not t.is_alive()):
                host.stop_all()
    return {t.agent_id: t.result for t in threads}
