"""`se3sync check` idle and with the cores busy: the BLAS threads se3sync chooses
(`cosim/threads.py`) against the BLAS library's default (``SE3SYNC_BLAS_THREADS=0``, what se3sync
did before choosing them).

    python benchmarks/bench_check_load.py [--runs 3] [--load-jobs 2] [--scenario S.toml]
    python benchmarks/bench_check_load.py --eig 300 1100 2000    (also dense eigvals by size)
    python benchmarks/bench_check_load.py --idle-by-priority      (root: "idle" on a shared machine)

Each `check` is a process of its own: its wall time, its CPU time (user + system of the child)
and the cores other work took meanwhile (the machine's busy time from /proc/stat less the
check's own CPU time), so that "idle" can be judged on a shared machine. The cases are
interleaved run by run, first on the machine as found, then with ``--load-jobs`` more
`yes > /dev/null` processes (as tests/under_load.sh starts them) at the benchmark's own
niceness, killed afterwards.

--idle-by-priority (root): the first state's runs are made at real-time priority (SCHED_FIFO 1,
`chrt -f 1`; every thread of the process), so that the other processes of a shared machine
cannot take the cores from them: the machine as the benchmark sees it is idle (the "other work"
column shows it), whatever else runs. The busy state stays at normal priority.

--eig N …: `numpy.linalg.eigvals` of a random N × N matrix (the delay margin's dense
eigenproblems reach 2000 rows) on 1 and on 2 BLAS threads (threadpoolctl), in this process,
in the same two states: what decides `cosim.threads.analysis_threads`.
"""
from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "benchmarks"))
import _markdown  # noqa: E402


def busy_seconds() -> float:
    with open("/proc/stat") as f:
        v = [int(x) for x in f.readline().split()[1:]]
    return (v[0] + v[1] + v[2] + v[5] + v[6] + v[7]) / os.sysconf("SC_CLK_TCK")


class Load:
    """``n`` `yes > /dev/null` processes while the block runs."""

    def __init__(self, n: int):
        self.n, self.procs = n, []

    def __enter__(self):
        self.procs = [subprocess.Popen(["yes"], stdout=subprocess.DEVNULL) for _ in range(self.n)]
        time.sleep(0.5)
        return self

    def __exit__(self, *exc):
        for p in self.procs:
            p.kill()
        for p in self.procs:
            p.wait()


def realtime(on: bool) -> None:
    """Every thread of this process at SCHED_FIFO 1 (on) or back to SCHED_OTHER."""
    policy, prio = (os.SCHED_FIFO, 1) if on else (os.SCHED_OTHER, 0)
    for tid in os.listdir("/proc/self/task"):
        try:
            os.sched_setscheduler(int(tid), policy, os.sched_param(prio))
        except ProcessLookupError:
            pass


def check_once(scenario: str, env: dict, rt: bool = False) -> tuple:
    """(wall s, CPU s, cores other work took) of one `se3sync check` (rt: at SCHED_FIFO 1)."""
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    b0 = busy_seconds()
    t0 = time.perf_counter()
    p = subprocess.run([*(["chrt", "-f", "1"] if rt else []), sys.executable, "-m", "cosim.cli",
                        "check", scenario], cwd=ROOT, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    b1 = busy_seconds()
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if p.returncode != 0:
        raise SystemExit(f"check failed: {p.stderr.strip()}")
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    return wall, cpu, max(0.0, (b1 - b0 - cpu) / wall)


def states(load_jobs, rt=False):
    """(label, yes jobs, real-time priority): the machine as found (the "other work" column says
    how idle it was) or made idle by priority, then busier."""
    return (("idle (SCHED_FIFO)" if rt else "no added load", 0, rt),
            (f"+ {load_jobs} × yes", load_jobs, False))


CASES = {"chosen (1 thread)": {}, "library default": {"SE3SYNC_BLAS_THREADS": "0"}}


def bench_check(scenario, runs, load_jobs, rt=False):
    base = {k: v for k, v in os.environ.items()
            if k not in ("SE3SYNC_BLAS_THREADS", "OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS",
                         "MKL_NUM_THREADS")}
    base["PYTHONPATH"] = ROOT + os.pathsep + base.get("PYTHONPATH", "")
    check_once(scenario, base)   # warm: numba's and Python's on-disk caches
    rows = []
    for state, jobs, prio in states(load_jobs, rt):
        res = {c: [] for c in CASES}
        with Load(jobs):
            for r in range(runs):
                for case, env in CASES.items():
                    w, c, o = check_once(scenario, {**base, **env}, prio)
                    res[case].append((w, c, o))
                    print(f"{state:18s} {case:18s} run {r + 1}: wall {w:6.2f} s, CPU {c:6.2f} s, "
                          f"other work {o:4.2f} cores", flush=True)
        for case, xs in res.items():
            rows.append([state, case, f"{statistics.median(x[0] for x in xs):.2f}",
                         " / ".join(f"{x[0]:.2f}" for x in xs),
                         f"{statistics.median(x[1] for x in xs):.2f}",
                         f"{statistics.median(x[2] for x in xs):.2f}"])
    return rows


def bench_eig(sizes, load_jobs, rt=False):
    import numpy as np
    import scipy.linalg  # noqa: F401 - both BLAS libraries loaded, as in `check`
    from threadpoolctl import threadpool_limits

    rng = np.random.default_rng(0)
    rows = []
    for state, jobs, prio in states(load_jobs, rt):
        with Load(jobs):
            for n in sizes:
                A = rng.standard_normal((n, n))
                t = {1: [], 2: []}
                for _ in range(3):
                    for th in (1, 2):
                        with threadpool_limits(limits=th, user_api="blas"):
                            realtime(prio)   # after the limit: its threads exist now
                            try:
                                t0 = time.perf_counter()
                                np.linalg.eigvals(A)
                                t[th].append(time.perf_counter() - t0)
                            finally:
                                realtime(False)
                m1, m2 = statistics.median(t[1]), statistics.median(t[2])
                print(f"{state:18s} eigvals {n:5d}: 1 thread {m1:.3f} s, 2 threads {m2:.3f} s",
                      flush=True)
                rows.append([state, n, f"{m1:.3f}", f"{m2:.3f}", f"{m1 / m2:.2f}"])
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", default="scenarios/hil_6uav.toml")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--load-jobs", type=int, default=2)
    ap.add_argument("--eig", type=int, nargs="*", default=[])
    ap.add_argument("--idle-by-priority", action="store_true")
    _markdown.add_option(ap)
    args = ap.parse_args()
    with _markdown.Report(args.markdown) as rep:
        rows = bench_check(args.scenario, args.runs, args.load_jobs, args.idle_by_priority)
        rep.table(["machine", "BLAS threads", "wall, median (s)", "wall, each run (s)",
                   "CPU, median (s)", "other work (cores)"], rows,
                  caption=f"se3sync check {args.scenario}, {args.runs} runs per case")
        if args.eig:
            rep.table(["machine", "N", "1 thread (s)", "2 threads (s)", "1 thread / 2 threads"],
                      bench_eig(args.eig, args.load_jobs, args.idle_by_priority),
                      caption="numpy.linalg.eigvals of a random N × N matrix, median of 3")


if __name__ == "__main__":
    main()
