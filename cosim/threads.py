"""How many threads BLAS gets: the one place se3sync chooses it (docs/performance.md#blas-threads).

NumPy and SciPy each load their own OpenBLAS, which by default starts one thread per core for
every call large enough and keeps them spinning between calls. On the matrices se3sync gives it
(the analysis's dense eigenproblems of at most a few thousand rows, the 3 × 3 and 6 × 6
products of a step) the threads gain little when the machine is idle and cost several times the
work when other jobs share the cores: `se3sync check scenarios/hil_6uav.toml` takes 2.4–2.5 s
idle either way, but with other jobs on the two cores 53 s on the library's default threads
(17 s of CPU: the threads spin) against 17 s on one (2.7 s of CPU, as idle; medians of 3,
benchmarks/bench_check_load.py). So the count is chosen here, per job:

* **analysis** (`check`, the checks before `run`, `swarm` and `connect`, `run`'s delay guard):
  `analysis_threads` (one, at every size), applied by `analysis` around `stability.analyse`,
  `delay_margin.delay_margin` and `convergence_rate.convergence`;
* **sweep samples** (`run_chunk`, in a Dask worker process or in-process):
  `SWEEP_WORKER_THREADS` per worker process, the cores being shared by the workers;
* **agent processes** (`se3sync agent`, `swarm`'s children): `AGENT_THREADS`, set for the whole
  process (`limit_process`).

``SE3SYNC_BLAS_THREADS=N`` overrides every choice: N ≥ 1 threads, or 0 to leave the BLAS
libraries' own default (OpenBLAS: ``OPENBLAS_NUM_THREADS`` or ``OMP_NUM_THREADS``, else one
thread per core), which is what se3sync did before choosing.

A choice covers the BLAS libraries already loaded (threadpoolctl) and those loaded while it holds
(``OPENBLAS_NUM_THREADS``, ``OMP_NUM_THREADS`` and ``MKL_NUM_THREADS`` are set meanwhile and
restored after; a library loaded then keeps that count as its default). The user's own
``OPENBLAS_NUM_THREADS`` and the like still set the count outside these jobs and with
``SE3SYNC_BLAS_THREADS=0``.
"""
from __future__ import annotations

import functools
import os
import threading
from contextlib import contextmanager

from threadpoolctl import threadpool_info, threadpool_limits

from controller.errors import Se3SyncError

__all__ = ["ENV", "ANALYSIS_THREADS", "SWEEP_WORKER_THREADS",
           "AGENT_THREADS", "override", "chosen", "analysis_threads", "blas_threads",
           "analysis", "limit_process", "blas_info"]

ENV = "SE3SYNC_BLAS_THREADS"
# The loader's variables: read by a BLAS library when it is loaded
LOAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")

# One at every size. Measured on 2 cores (benchmarks/bench_check_load.py): with the cores to
# itself, a dense eigvals on 2 threads is as fast as on one up to 1100 rows and 1.5× faster at
# 2000 (the largest the delay margin solves densely); with two other jobs on the cores it is 4
# to 9 times slower at every size. A rule by size would buy 1.5× on an idle machine at the risk
# of 6× on a shared one: SE3SYNC_BLAS_THREADS=2 buys it where the cores are known to be free.
ANALYSIS_THREADS = 1
SWEEP_WORKER_THREADS = 1
AGENT_THREADS = 1


def override() -> int | None:
    """``SE3SYNC_BLAS_THREADS`` as a count (0: the library's default), or None when unset.
    Se3SyncError (one line) for anything else than an integer >= 0."""
    raw = os.environ.get(ENV)
    if raw is None or raw.strip() == "":
        return None
    try:
        n = int(raw.strip())
    except ValueError:
        n = -1
    if n < 0:
        raise Se3SyncError(f"{ENV}: must be an integer >= 0 (0: the BLAS library's default), "
                           f"got {raw!r}")
    return n


def chosen(n: int | None) -> int | None:
    """The count to apply for a job whose policy says ``n`` (None: the library's default),
    after the override."""
    o = override()
    if o is not None:
        return None if o == 0 else o
    return n


def analysis_threads(states: int) -> int | None:
    """The analysis's BLAS threads for a loop of ``states`` states (12N + M): `ANALYSIS_THREADS`
    whatever the size (why: at its definition). None would leave the library's default."""
    return ANALYSIS_THREADS


@contextmanager
def blas_threads(n: int | None):
    """``n`` BLAS threads while the block runs (None: leave them), restored after."""
    if n is None:
        yield
        return
    saved = {var: os.environ.get(var) for var in LOAD_VARS}
    os.environ.update({var: str(n) for var in LOAD_VARS})
    try:
        with threadpool_limits(limits=int(n), user_api="blas"):
            yield
    finally:
        for var, old in saved.items():
            if old is None:
                os.environ.pop(var, None)
            else:
                os.environ[var] = old


def analysis(fn):
    """Decorator of an analysis entry point ``fn(scenario, ...)``: its BLAS threads are
    `analysis_threads` of the scenario's loop (12N + M states), after the override. Nested
    entry points keep the outer choice."""
    @functools.wraps(fn)
    def wrapper(scenario, *args, **kwargs):
        if getattr(_depth, "n", 0):
            return fn(scenario, *args, **kwargs)
        states = 12 * scenario.graph.n + scenario.graph.M
        _depth.n = 1
        try:
            with blas_threads(chosen(analysis_threads(states))):
                return fn(scenario, *args, **kwargs)
        finally:
            _depth.n = 0
    return wrapper


_depth = threading.local()


def limit_process(n: int | None) -> None:
    """For a process that does one job (an agent): ``n`` BLAS threads (after the override) from
    now on, for the libraries loaded and those loaded later."""
    n = chosen(n)
    if n is None:
        return
    os.environ.update({var: str(n) for var in LOAD_VARS})
    threadpool_limits(limits=int(n), user_api="blas")


def blas_info() -> list:
    """[(library file name, threads)] of every BLAS library loaded (what the policy's tests
    and `check --json` readers look at)."""
    return [(os.path.basename(d["filepath"]), int(d["num_threads"]))
            for d in threadpool_info() if d.get("user_api") == "blas"]
