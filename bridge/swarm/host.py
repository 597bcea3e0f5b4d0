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

Stepping (real time): one thread of the process steps every agent's master loop (`Master.steps`,
driven by `Host.drive`). It waits for the earliest deadline, then runs each agent whose step is
due, one after the other. Why not each thread its own steps: a thread woken from a wait costs
far more than the step itself on a virtual machine (cold caches, a context switch at each hand
over of the interpreter); with one thread, a process of K agents wakes once per period and its
agents' steps run back to back while its caches are warm. The agents' own threads connect,
wait for the start, and write their logs and summaries. Lockstep runs keep each agent's loop in
its own thread: there each step waits for the vehicle and the neighbours, not for a clock.

Stopping: the main thread catches SIGINT and SIGTERM and asks every agent to stop
(`Master.request_stop` for a running master loop; an agent still connecting, waiting for the
start or waiting in lockstep sees the signal itself through `cosim.signals`). An agent that
fails stops the others (`Host.stop`: each finishes its log and summary as "interrupted"); its
neighbours in other processes would fail safe anyway, and `swarm` stops the swarm.
"""
from __future__ import annotations

import threading
import time

from cosim import signals

__all__ = ["Host", "run_agents"]

# the agents of a process follow one timeline, but each reads it from the clocks on its own:
# their deadlines differ by microseconds, and a step due this soon runs with the others rather
# than after a wait of its own
DUE_SLACK_S = 1e-4


class _Run:
    """One master loop on the stepping thread: its steps, its plant, when its next step is due,
    the stepping thread's CPU spent on it, and how it ended."""

    def __init__(self, steps, plant, due):
        self.steps = steps
        self.plant = plant
        self.due = float("-inf") if due is None else float(due)
        self.cpu_s = 0.0
        self.value = None
        self.exc = None
        self.done = threading.Event()

    def step(self, c0: float) -> tuple:
        """One step, begun at the stepping thread's CPU time ``c0``: (False once the loop has
        ended, ``value`` or ``exc`` set; the thread's CPU time after it). One clock reading per
        step: the next step begins where this one ended (each reading is a system call)."""
        try:
            try:
                self.plant.resume()
            except BaseException as exc:  # noqa: BLE001 - thrown in
                # the loop waits at its last `advance`: it takes this as that advance's error,
                # as it would from a plant that waits for itself
                self.steps.throw(exc)
            else:
                next(self.steps)
            self.due = self.plant.due
            ok = True
        except StopIteration as end:
            self.value = end.value
            ok = False
        except BaseException as exc:  # noqa: BLE001 - handed to the agent's thread
            self.exc = exc
            ok = False
        c1 = time.thread_time()
        self.cpu_s += c1 - c0
        return ok, c1


class Host:
    """What the agents of one process share (`run_agent`'s ``host``): their ids, the ``stop``
    event and their master loops (`register`), which `stop_all` asks to stop."""

    def __init__(self, ids):
        self.ids = tuple(int(i) for i in ids)
        self.stop = threading.Event()
        self._masters = []
        self._runs = []
        self._cv = threading.Condition()
        self._stepper = None
        self._closing = False
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

    def drive(self, steps, plant, due: float | None = None) -> tuple:
        """Runs a master loop (``steps``: `Master.steps`, over ``plant``, a real-time
        `MavlinkPlant` with ``paced_by_host`` set) on the process's stepping thread and waits for
        it to end; returns (its summary, the stepping thread's CPU seconds spent on it) or
        raises what the loop raised. Its first step runs at ``due`` (time.monotonic()), or at
        once; every step after the plant's `resume`."""
        run = _Run(steps, plant, due)
        with self._cv:
            if self._closing:
                raise RuntimeError("Host.drive: the host is closed")
            self._runs.append(run)
            if self._stepper is None:
                self._stepper = threading.Thread(target=self._step_all, name="stepper",
                                                 daemon=True)
                self._stepper.start()
            self._cv.notify()
        run.done.wait()
        if run.exc is not None:
            raise run.exc
        return run.value, run.cpu_s

    def close(self) -> None:
        """Ends the stepping thread (once no loop is left)."""
        with self._cv:
            self._closing = True
            self._cv.notify()

    def _step_all(self) -> None:
        while True:
            with self._cv:
                while not self._runs:
                    if self._closing:
                        return
                    self._cv.wait()
                runs = list(self._runs)
                wait = min(r.due for r in runs) - time.monotonic()
                if wait > DUE_SLACK_S:
                    # a loop that joins meanwhile (due at once) wakes it early
                    self._cv.wait(wait)
                    continue
            now = time.monotonic() + DUE_SLACK_S
            ended = []
            c = time.thread_time()
            for r in runs:
                if r.due <= now:
                    ok, c = r.step(c)
                    if not ok:
                        ended.append(r)
            if ended:
                with self._cv:
                    for r in ended:
                        self._runs.remove(r)
                for r in ended:
                    r.done.set()


class _Agent(threading.Thread):
    def __init__(self, run_agent, agent_id: int, kwargs: dict, ended: threading.Event):
        super().__init__(name=f"agent {agent_id}", daemon=True)
        self.run_agent = run_agent
        self.agent_id = agent_id
        self.kwargs = kwargs
        self.result = None
        self.finished = False     # set before ``ended`` (is_alive() still holds for a moment)
        self.ended = ended

    def run(self):
        try:
            self.result = self.run_agent(agent_id=self.agent_id, **self.kwargs)
        except BaseException as exc:  # noqa: BLE001 - handed to the main thread
            self.result = exc
        finally:
            self.finished = True
            self.ended.set()


def run_agents(run_agent, ids, kwargs_for) -> dict:
    """Runs ``run_agent(agent_id=i, host=…, **kwargs_for(i))`` for every i of ``ids``, each in
    its own thread, and waits for all of them; returns {i: its summary or the exception it
    raised}, in the order of ``ids``. The first agent to fail (an exception other than
    KeyboardInterrupt) stops the others, and so does a signal. The caller sets the process's
    BLAS threads (`cosim.threads.limit_process`): `run_agent` leaves them to the host."""
    host = Host(ids)
    # the main thread sleeps until an agent ends (a signal's handler still runs at once): a
    # timed join would wake it, and take the interpreter from the stepping thread, many times
    # a second
    ended = threading.Event()
    threads = [_Agent(run_agent, i, {**kwargs_for(i), "host": host}, ended) for i in host.ids]
    try:
        with signals.catching(host.stop_all):
            for t in threads:
                t.start()
            while True:
                # cleared before the threads are looked at: one that ends after this wakes the
                # wait below, one that ended before (even before the first look: an agent that
                # fails at once) is seen now
                ended.clear()
                if not host.stop.is_set() and any(
                        isinstance(t.result, BaseException) and not isinstance(t.result, KeyboardInterrupt)
                        for t in threads if t.finished):
                    host.stop_all()
                if all(t.finished for t in threads):
                    break
                ended.wait()
            for t in threads:
                t.join()
    finally:
        host.close()
    return {t.agent_id: t.result for t in threads}
