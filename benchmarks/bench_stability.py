"""Stability analysis at scale: `se3sync check` on chains and random trees, time and peak memory.

    python benchmarks/bench_stability.py [--sizes 1000 10000] [--dense-n 60]
    python benchmarks/bench_stability.py --delay 6 12 16     (only the delay-margin search)
    python benchmarks/bench_stability.py --crossing 12 24 50 (only `crossing_delay`)

Each `check` runs in its own process under /usr/bin/time -v (wall time, maximum resident set
size). Then the new analysis is compared with the dense one (`cosim.stability.linearise`,
`closed_loop`, `eigvals`) on a random tree of --dense-n agents and on a heterogeneous one, at
three steps, and the dense run's time is given as a ratio to the new one (same process).

--delay N …: the delay margin of hil_6uav (N = 6) or a seeded N-agent random tree, searched from
`crossing_delay`'s guess and by doubling (``guess=False``) in the same process: the delays tried,
the wall time of each search and their ratio; the margins must be equal and the radii
equal to 1e-9 (above 2000 states the two use different eigensolvers).

--shift-invert N …: one shift-invert search of the delayed loop (`_radius_near`, near e^{jω} with
ω = 0.03 rad/step, where these trees' roots cross, at d = 20) with `_shift_inverse`'s LU of the
(12N + M)-square M(σ) against an LU of the whole augmented A − σI (the code before it): times,
their ratio and the two radii.

--crossing N …: `crossing_delay` on a seeded N-agent random tree with T's eigenvalues in ±μ
pairs (ν = μ² of T₁₂T₂₁, half the size) against those of T itself (``paired=False``), and one
T(e^{jω}) assembled per agent block (`LoopTransfer.matrix`) against a dense n × n solve: times,
their ratios and the two guesses τ.
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
sys.path.insert(0, os.path.join(ROOT, "benchmarks"))
import _markdown  # noqa: E402


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


def delay_search(N):
    from cosim.analysis.delay_margin import delay_margin
    from cosim.analysis.stability_cases import tree_scenario_text
    from cosim.analysis.stability_sparse import Linearisation
    from cosim.scenario import load_scenario, parse_scenario

    sc = (load_scenario(os.path.join(ROOT, "scenarios", "hil_6uav.toml")) if N == 6 else
          parse_scenario(tree_scenario_text(N, "random", 0), "tree", "tree.toml"))
    lin = Linearisation(sc, True, force_sparse=True)
    res = {}
    for guess in (True, False):
        tried = []
        t0 = time.perf_counter()
        out = delay_margin(sc, lin=lin, guess=guess, count=False,
                           progress=lambda d, r, s: tried.append(d))
        res[guess] = (time.perf_counter() - t0, tried, out)
    (tg, dg, og), (td, dd, od) = res[True], res[False]
    # above DENSE_MAX the two searches use different solvers (shift-invert at the guess's
    # crossing angle, ARPACK's largest-modulus search without it): radii agree to rounding
    dr = max(abs(og[k] - od[k]) for k in ("rho_at_margin", "rho_beyond"))
    same = og["delay_margin_steps"] == od["delay_margin_steps"] and dr < 1e-9
    return (f"delay N = {N}: margin {og['delay_margin_steps']} steps; guess {tg:.1f} s (tried "
            f"{dg}), doubling {td:.1f} s (tried {dd}); ratio {tg / td:.2f}; "
            f"{'same' if same else 'DIFFERENT'} margin, radii within {dr:.1e}")


def count_search(N):
    """The margin from counts of the roots outside the circle against the sweep and the radii
    (the sweep only up to 100 agents: it grows as N³), on the seeded random tree."""
    import resource

    from cosim.analysis.delay_margin import delay_margin
    from cosim.analysis.stability_cases import tree_scenario_text
    from cosim.analysis.stability_sparse import Linearisation
    from cosim.scenario import load_scenario, parse_scenario

    sc = (load_scenario(os.path.join(ROOT, "scenarios", "hil_6uav.toml")) if N == 6 else
          parse_scenario(tree_scenario_text(N, "random", 0), "tree", "tree.toml"))
    t0 = time.perf_counter()
    lin = Linearisation(sc, True, force_sparse=True)
    tl = time.perf_counter() - t0
    tried = []
    t0 = time.perf_counter()
    out = delay_margin(sc, lin=lin, count=True,
                       progress=lambda d, r, s, outside=None: tried.append(f"{d}:{outside}"))
    tc = time.perf_counter() - t0
    line = (f"count N = {N}: margin {out['delay_margin_steps']} steps in {tc:.2f} s (+{tl:.2f} s "
            f"linearising; counts d:outside {' '.join(tried)}); peak RSS "
            f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")
    if N <= 100:
        t0 = time.perf_counter()
        ref = delay_margin(sc, lin=lin, count=False)
        ts = time.perf_counter() - t0
        same = ref["delay_margin_steps"] == out["delay_margin_steps"]
        line += (f"; sweep and radii {ts:.2f} s, ratio {tc / ts:.2f}, "
                 f"{'same' if same else 'DIFFERENT'} margin")
    return line


def _tree_loop(N):
    """(Φ₀, B, C) of the delayed loop of the seeded N-agent random tree (seed 0)."""
    from cosim.analysis import delay_margin as dm
    from cosim.analysis.stability_cases import tree_scenario_text
    from cosim.analysis.stability_sparse import Linearisation
    from cosim.scenario import parse_scenario

    sc = parse_scenario(tree_scenario_text(N, "random", 0), "tree", "tree.toml")
    return dm.delayed_parts(Linearisation(sc, True, force_sparse=True), sc.step)


def shift_invert(N):
    import numpy as np
    import scipy.sparse as sp
    import scipy.sparse.linalg as sla

    from cosim.analysis import delay_margin as dm

    loop = _tree_loop(N)
    d, w, k = 20, 0.03, dm.ARPACK_K
    sigma = complex(np.exp(1j * w))

    def whole():            # the LU of the whole augmented matrix, as before _shift_inverse
        A = dm.augmented(*loop, d)
        lu = sla.splu((A - sigma * sp.identity(A.shape[0], format="csc")).tocsc().astype(complex))
        op = sla.LinearOperator(A.shape, matvec=lambda x: lu.solve(np.asarray(x, dtype=complex)),
                                dtype=complex)
        theta = sla.eigs(op, k=k, which="LM", tol=1e-12, ncv=4 * k, maxiter=20000,
                         return_eigenvectors=False)
        lam = sigma + 1.0 / theta
        return float(np.abs(lam[np.abs(lam - 1.0) > 1e-8]).max())

    out = {}
    for name, f in (("small", lambda: dm._radius_near(loop, w, d)), ("whole", whole)):
        t0 = time.perf_counter()
        out[name] = (f(), time.perf_counter() - t0)
    (rs, ts), (rw, tw) = out["small"], out["whole"]
    return (f"shift-invert N = {N} ({loop[0].shape[0] + d * loop[2].shape[0]} states at d = {d}): "
            f"LU of M(sigma) {ts:.2f} s, LU of A - sigma I {tw:.2f} s, ratio {ts / tw:.2f}; "
            f"radii {rs:.10f} and {rw:.10f}")


def crossing(N):
    import numpy as np

    from cosim.analysis import delay_margin as dm

    loop = _tree_loop(N)
    out = {}
    for paired in (True, False):
        t0 = time.perf_counter()
        out[paired] = (dm.crossing_delay(*loop, paired=paired), time.perf_counter() - t0)
    (cp, tp), (cf, tf) = out[True], out[False]
    P0, B, C = (x.toarray() for x in loop)
    blocks = dm.LoopTransfer(*loop)
    w, reps = 0.03, 20
    t0 = time.perf_counter()
    for _ in range(reps):
        blocks.matrix(w)
    t_block = (time.perf_counter() - t0) / reps
    t0 = time.perf_counter()
    for _ in range(reps):
        C @ np.linalg.solve(np.exp(1j * w) * np.eye(P0.shape[0]) - P0, B)
    t_dense = (time.perf_counter() - t0) / reps
    return (f"crossing N = {N} (m = {C.shape[0]}): paired {tp:.2f} s (tau {cp[0]:.4f}), "
            f"full T {tf:.2f} s (tau {cf[0]:.4f}); ratio {tp / tf:.2f}. One T(e^jw): per block "
            f"{1e3 * t_block:.2f} ms, dense solve {1e3 * t_dense:.2f} ms; ratio "
            f"{t_block / t_dense:.2f}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000])
    ap.add_argument("--dense-n", type=int, default=60)
    ap.add_argument("--delay", type=int, nargs="+", metavar="N",
                    help="only compare the delay-margin searches on these agent counts")
    ap.add_argument("--crossing", type=int, nargs="+", metavar="N",
                    help="only compare crossing_delay's eigenvalue routes on these agent counts")
    ap.add_argument("--shift-invert", type=int, nargs="+", metavar="N", dest="shift_invert",
                    help="only compare the two LUs of a shift-invert search on these agent counts")
    ap.add_argument("--count", type=int, nargs="+", metavar="N",
                    help="only time the delay margin from counts of the roots outside the unit "
                         "circle on these agent counts (6: hil_6uav), against the sweep and the "
                         "radii up to 100 agents")
    _markdown.add_option(ap)
    a = ap.parse_args()
    with _markdown.Report(a.markdown):
        bench(a, ap)


def bench(a, ap):
    for option, job in (("crossing", crossing), ("delay", delay_search),
                        ("shift_invert", shift_invert), ("count", count_search)):
        counts = getattr(a, option)
        if counts:
            bad = [N for N in counts if N < 2]
            if bad:
                ap.error(f"--{option.replace('_', '-')}: agent counts must be >= 2, "
                         f"got {bad[0]}")
            for N in counts:
                print(job(N), flush=True)
            return
    with tempfile.TemporaryDirectory() as tmp:
        for N in a.sizes:
            for kind in ("chain", "random"):
                print(check_cost(N, kind, tmp), flush=True)
    for line in agreement(a.dense_n):
        print(line, flush=True)


if __name__ == "__main__":
    main()
