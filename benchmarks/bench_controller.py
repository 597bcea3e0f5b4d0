"""One network step of the hybrid law: compiled kernel vs a batched-numpy formulation.

    python benchmarks/bench_controller.py

Cases: the paper's graph (6 agents, 5 edges) and random trees of 100 and 1000 agents. Also
measures the start-up cost of the compiled kernel: first compile (empty numba cache) against a
second process that loads it from the cache. Timings are medians of repeated runs in one
process, so the ratios are comparable; absolute numbers move with the machine's load.
"""
from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
import warnings

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "tests"))

import _markdown  # noqa: E402
import controller as C  # noqa: E402
from controller import se3  # noqa: E402
from _paper import A, EDGES, GAINS, b, d  # noqa: E402


def random_tree(rng, n):
    perm = rng.permutation(n) + 1
    return [(int(perm[k]), int(perm[rng.integers(0, k)])) for k in range(1, n)]


class BatchedNumpyLaw:
    """The same law written as whole-array numpy operations over edges (for comparison)."""

    def __init__(self, g, wm, des, gains):
        self.g, self.wm, self.des, self.k = g, wm, des, gains
        self.pos, self.neg = g.edges[:, 0], g.edges[:, 1]
        self.c = wm.b / wm.d
        self.theta = np.zeros(g.M)

    def step(self, S, h):
        R = S[:, 3:12].reshape(-1, 3, 3)
        p = S[:, :3]
        xi = S[:, 12:]
        Rj = np.swapaxes(R[self.neg], 1, 2)
        Rb = Rj @ R[self.pos]
        pb = np.einsum("kij,kj->ki", Rj, p[self.pos] - p[self.neg])
        Ra = se3.R_a(self.theta, self.des.u_c1)
        Rg = Rb @ Ra
        RgT = np.swapaxes(Rg, 1, 2)
        y = self.c + np.einsum("kji,kj->ki", Rb, pb)
        q = np.einsum("kji,kj->ki", Ra, y) - self.c
        a = -se3.psi(RgT @ self.wm.A) + 0.5 * np.cross(self.wm.b, q)
        w = 0.5 * (self.wm.b - RgT @ self.wm.b + self.wm.d * q)
        rw = np.einsum("kij,kj->ki", Ra, w)
        pt = self.c - Ra @ self.c
        g = np.concatenate([np.einsum("kij,kj->ki", Ra, a) + np.cross(pt, rw), rw], axis=1)
        gth = self.des.gamma * self.theta + 2 * (a @ self.des.u_c1 + w @ self.des.u_c2)
        rv = np.einsum("kij,kj->ki", Rb, g[:, 3:])
        gn = np.concatenate([np.einsum("kij,kj->ki", Rb, g[:, :3]) + np.cross(pb, rv), rv], axis=1)
        dxi = xi[self.pos] - xi[self.neg]
        u = -self.k.k_xi * xi
        np.add.at(u, self.pos, -self.k.k_X * g - self.k.k_e * dxi)
        np.add.at(u, self.neg, self.k.k_X * gn + self.k.k_e * dxi)
        self.theta = self.theta - h * self.k.k_theta * gth
        return u


def timeit(fn, min_time=0.3):
    fn()
    n = 1
    while True:
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        dt = time.perf_counter() - t0
        if dt > min_time:
            break
        n *= 4
    reps = []
    for _ in range(5):
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        reps.append((time.perf_counter() - t0) / n)
    return float(np.median(reps))


def startup():
    code = ("import time; t=time.perf_counter(); import numpy as np, warnings; warnings.simplefilter('ignore');"
            "import controller as C; from controller import _kernels as K;"
            "S=np.zeros((2,18)); S[:,3]=S[:,7]=S[:,11]=1;"
            "P=K.pack(np.eye(3)*2,np.zeros(3),1.0,np.array([1.,0,0]),np.zeros(3),0.1,0.01,[1.0],1,1,1,1);"
            "K.network_step(S,np.zeros(1),np.array([[0,1]]),P,1e-3,True,np.zeros((2,6)),np.zeros(1),"
            "np.zeros(1,dtype=np.bool_),np.zeros(1),np.zeros(1)); print(time.perf_counter()-t)")
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        first = float(subprocess.check_output([sys.executable, "-c", code], env=env))
        second = float(subprocess.check_output([sys.executable, "-c", code], env=env))
    return first, second


def main():
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    _markdown.add_option(ap)
    args = ap.parse_args()
    with _markdown.Report(args.markdown) as rep:
        bench(rep)


def bench(rep):
    warnings.simplefilter("ignore")
    rows = []
    rng = np.random.default_rng(0)
    wm = C.WeightingMatrix.from_blocks(A, b, d)
    des = C.design_synergy(wm, Theta=[0.3 * np.pi], gamma=0.33, delta=0.02, alpha_signs=(1, -1, 1))
    gains = C.Gains(**GAINS)
    print(f"{'case':>22} {'edges':>6} {'numba step':>12} {'per edge':>10} {'numpy step':>12} {'ratio':>7}")
    for name, n, edges in [("paper graph", 6, EDGES), ("random tree 100", 100, None),
                           ("random tree 1000", 1000, None)]:
        g = C.Graph(n, edges or random_tree(rng, n))
        X = se3.random_pose(rng, n, scale=2.0)
        S = C.pack_state(X, 0.1 * rng.standard_normal((n, 6)))
        # θ chosen on the jump map so no edge jumps while timing: the steady flowing case
        ctl = C.HybridController(g, wm, des, gains, theta0=np.full(g.M, 0.3 * np.pi))
        ctl.P[C.law.K.P_DELTA] = np.inf
        t_nb = timeit(lambda: ctl.step_state(S, 0.0))
        npl = BatchedNumpyLaw(g, wm, des, gains)
        npl.theta[:] = 0.3 * np.pi
        t_np = timeit(lambda: npl.step(S, 0.0))
        ctl.theta[:] = npl.theta
        assert np.allclose(ctl.step_state(S, 0.0)[0], npl.step(S, 0.0), atol=1e-9)
        print(f"{name:>22} {g.M:>6} {t_nb * 1e6:>10.2f}µs {t_nb / g.M * 1e9:>8.1f}ns "
              f"{t_np * 1e6:>10.1f}µs {t_np / t_nb:>6.1f}×")
        rows.append((name, g.M, f"{t_nb * 1e6:.2f}", f"{t_nb / g.M * 1e9:.1f}",
                     f"{t_np * 1e6:.1f}", f"{t_np / t_nb:.1f}×"))
    first, second = startup()
    print(f"start-up incl. import: first compile {first:.2f} s, from the on-disk cache {second:.2f} s")
    rep.table(["case", "edges", "compiled step (µs)", "per edge (ns)", "batched numpy step (µs)",
               "numpy / compiled"], rows)
    rep.note(f"Start-up of a process that imports the controller and takes one network step: "
             f"{first:.2f} s with the first compile (empty numba cache), {second:.2f} s from the "
             f"on-disk cache. Medians of repeated runs in one process.")


if __name__ == "__main__":
    main()
