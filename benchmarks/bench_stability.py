"""Stability analysis at scale: `se3sync check` on chains and random trees, time and peak memory.

    python benchmarks/bench_stability.py [--sizes 1000 10000] [--dense-n 60]

Each `check` runs in its own process under /usr/bin/time -v (wall time, maximum resident set
size). Then the new analysis is compared with the dense one (`cosim.stability.linearise`,
`closed_loop`, `eigvals`) on a random tree of --dense-n agents and on a heterogeneous one, at
three steps, and the dense run's time is given as a ratio to the new one (same process).
"""
from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)


def check_cost(N, kind, tmp):
    from cosim.analysis.stability_cases import tree_scenario_text
    path = os.path.join(tmp, f"{kind}_{N}.toml")
    with open(path, "w") as f:
        f.write(tree_scenario_text(N, kind, seed=3))
    exe = os.path.join(os.path.dirname(sys.executable), "se3sync")
    p = subprocess.run(["/usr/bin/time", "-v", exe, "check", path], capture_output=True, text=True)
    if p.returncode != 0:
        return f"{kind:6s} N={N:6d}: FAILED {p.stderr.strip().splitlines()[-1]}"
    wall = re.search(r"Elapsed \(wall clock\) time.*: (\S+)", p.stderr).group(1)
    rss = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", p.stderr).group(1))
    rho = re.search(r"spectral_radius (\S+)", p.stdout).group(1)
    mss = re.search(r"max_stable_step (\S+ s)", p.stdout).group(1)
    rate = re.search(r"slowest_rate\s+(\S+)", p.stdout).group(1)
    return (f"{kind:6s} N={N:6d}: check {wall} wall, peak RSS {rss / 1024:.0f} MiB; "
            f"rho {rho}, max_stable_step {mss}, slowest rate {rate} /s")


def agreement(N):
    import numpy as np

    from cosim.analysis import stability as dense
    from cosim.analysis import stability_sparse as F
    from cosim.scenario import parse_scenario
    from cosim.analysis.stability_cases import tree_scenario_text
    out = []
    for hetero in (False, True):
        masses = np.random.default_rng(1).uniform(1, 4, N) if hetero else None
        sc = parse_scenario(tree_scenario_text(N, "random", 2, masses), "t", "t.toml")
        t = time.perf_counter()
        Kx, G = dense.linearise(sc)
        rd = [dense.spectral_radius(sc, h, Kx, G) for h in (0.004, 0.012, 0.03)]
        td = time.perf_counter() - t
        t = time.perf_counter()
        lin = F.Linearisation(sc)
        rn = [lin.spectral_radius(h) for h in (0.004, 0.012, 0.03)]
        tn = time.perf_counter() - t
        err = max(abs(a - b) for a, b in zip(rd, rn))
        out.append(f"random tree N={N} {'heterogeneous' if hetero else 'identical'} agents "
                   f"({lin.method}): max |rho_new - rho_dense| = {err:.2e} over h = 4, 12, 30 ms; "
                   f"dense/new time = {td / tn:.0f}x")
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000])
    ap.add_argument("--dense-n", type=int, default=60)
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        for N in a.sizes:
            for kind in ("chain", "random"):
                print(check_cost(N, kind, tmp), flush=True)
    for line in agreement(a.dense_n):
        print(line, flush=True)


if __name__ == "__main__":
    main()
