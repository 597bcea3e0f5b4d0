"""Roots of the delayed loop outside the unit circle, counted by the argument principle, for
agents on a tree: the delay margin without the O(m³) frequency sweep.

With M(z) = zI − Φ₀ − z^{−d} B C (`delay_margin.delayed_parts`), the augmented loop's
characteristic polynomial is z^{d·m} det M(z); six of its roots are the rigid motion's z = 1.
Along the upper half of the unit circle its phase grows by π per root inside, so

    roots outside = n − 3 − Δ arg det M(e^{jω}) / π,   ω from 0⁺ to π,

(n = 12N + M states; the 3 is the rigid roots' half turn, 6 × π/2, which the count leaves out).

Why not one determinant: the delay puts d·m roots in rings just inside the circle, and the phase
of det M swings by tens of turns between them (100-agent tree, d = 20: 80π over
0.004 < ω < 0.02), so sampling it aliases by whole turns (a 400-point grid miscounted by 14).
Eliminating the agents' blocks leaves-first along the tree factors det M into one pivot block
per agent; each factor's phase moves only near its own roots, so each is unwrapped on its own and
an interval is halved while any factor turns by more than `TURN` there. The elimination costs
O(N) per frequency, and 400–750 frequencies did at 12–1000 agents."""
from __future__ import annotations

import math

import numpy as np

# Largest phase step of one pivot block between neighbouring frequencies; above it the interval
# is halved. With 0.5 the counts equalled dense eigvals on every case compared (12-agent tree at
# d = 22, 23, 24, 30: 0, 2, 6, 6) and did not change with 0.25 and twice the grid (1000 agents).
TURN = 0.5
GRID = 40                   # log-spaced frequencies to start from, 1e-9 … π
RIGID = 6                   # the rigid motion's roots at z = 1
RADIAL = 1e-7              # the step off the circle for the phase's rate


class TreeDeterminant:
    """The log-determinants of the pivot blocks of M(z) eliminated leaves-first along the tree.

    Agent i's block holds its δ, ξ and the θ_k of the edges it owns; Φ₀ does not couple agents,
    B C couples only neighbours, so on a tree the Schur complement of a child's block updates
    only its parent's. Blocks are padded to one size with an identity (the determinant does not
    change) so that every level of the tree is one batched LAPACK call."""

    def __init__(self, lin, Phi0, B, C, root: int = 0):
        N, E = lin.N, lin.edges
        if E.shape[0] != N - 1:
            raise ValueError("TreeDeterminant: the agents' graph is not a tree")
        n6, th = 6 * N, 12 * N
        own = [[] for _ in range(N)]
        nbr = [[] for _ in range(N)]
        for k, (p, q) in enumerate(E):
            if Phi0.shape[0] > th:
                own[p].append(th + k)
            nbr[p].append(q)
            nbr[q].append(p)
        idx = [np.r_[6 * i:6 * i + 6, n6 + 6 * i:n6 + 6 * i + 6, own[i]].astype(int)
               for i in range(N)]
        b = max(x.size for x in idx)
        parent = np.full(N, -1)
        depth = np.zeros(N, dtype=int)
        order, seen = [root], np.zeros(N, dtype=bool)
        seen[root] = True
        for u in order:
            for v in nbr[u]:
                if not seen[v]:
                    seen[v], parent[v], depth[v] = True, u, depth[u] + 1
                    order.append(v)
        if not seen.all():
            raise ValueError("TreeDeterminant: the agents' graph is not connected")
        P, BC = Phi0.tocsr(), (B @ C).tocsr()

        def block(X, r, c):
            out = np.zeros((b, b))
            out[:idx[r].size, :idx[c].size] = X[idx[r]][:, idx[c]].toarray()
            return out

        self.N, self.b, self.root = N, b, root
        self.active = np.zeros((N, b, b))           # zI on a block's own states only
        self.pad = np.zeros((N, b, b))              # and 1 on its padding
        for i in range(N):
            s = idx[i].size
            self.active[i, :s, :s] = np.eye(s)
            self.pad[i, s:, s:] = np.eye(b - s)
        self.Phi0 = np.array([block(P, i, i) for i in range(N)])
        self.BCii = np.array([block(BC, i, i) for i in range(N)])
        self.parent = parent
        kids = np.flatnonzero(parent >= 0)
        self.up = np.array([block(BC, c, parent[c]) for c in kids])     # child's rows
        self.down = np.array([block(BC, parent[c], c) for c in kids])   # parent's rows
        row = np.full(N, -1)
        row[kids] = np.arange(kids.size)
        self.levels = [(lev, row[lev]) for lev in
                       (kids[depth[kids] == L] for L in range(depth.max(), 0, -1))]

    def log_dets(self, z: complex, d: int) -> np.ndarray:
        """log det of every agent's pivot block at z (their sum is log det M(z) mod 2πj)."""
        lam = z ** (-d)
        Mb = z * self.active - self.Phi0 - lam * self.BCii + self.pad
        out = np.empty(self.N, dtype=complex)
        for lev, r in self.levels:
            Pc = Mb[lev]
            X = np.linalg.solve(Pc, self.up[r])
            out[lev] = np.log(np.linalg.det(Pc))
            np.add.at(Mb, self.parent[lev], -(lam * lam) * (self.down[r] @ X))
        out[self.root] = np.log(np.linalg.det(Mb[self.root]))
        return out


def roots_outside(tdet: TreeDeterminant, n: int, d: int, grid: int = GRID, turn: float = TURN):
    """(roots of the augmented loop with delay d outside the unit circle, frequencies used).

    The phase of each pivot block is followed from ω = 1e-9 (z = 1 is the rigid motion's root)
    to π. Each block's determinant is analytic in z, so its phase turns at the rate
    ∂arg/∂ω = ∂log|·|/∂r on the circle (Cauchy–Riemann), taken from a second elimination at
    radius 1 + `RADIAL`. An interval is halved while some block turns by more than ``turn``
    across it, or would at the rate seen at either end: the phase alone cannot tell a block that
    turned by 2π from one that stood still (a 24-agent tree at d = 22 was miscounted by 2 so).
    The sum of the phase changes is a whole number of half turns up to rounding; a count further
    than 0.25 from a whole number is refused (ValueError), not rounded."""
    def at(w):      # milliseconds each: Ctrl-C is taken between them, no `interruptible`
        z = complex(np.exp(1j * w))
        f = tdet.log_dets(z, d)
        return f.imag, (tdet.log_dets((1.0 + RADIAL) * z, d).real - f.real) / RADIAL

    ws = np.geomspace(1e-9, math.pi, grid)
    ph = {w: at(w) for w in ws}
    total, stack = 0.0, [(ws[i], ws[i + 1]) for i in range(grid - 2, -1, -1)]
    while stack:
        a, c = stack.pop()
        (pa, ra), (pc, rc) = ph[a], ph[c]
        step = (pc - pa + math.pi) % (2 * math.pi) - math.pi
        fast = max(np.abs(step).max(), (c - a) * max(np.abs(ra).max(), np.abs(rc).max()))
        if fast > turn and c - a > 1e-12 * c:
            m = 0.5 * (a + c)
            ph[m] = at(m)
            stack += [(m, c), (a, m)]
            continue
        total += step.sum()
    out = n - RIGID / 2 - total / math.pi
    k = int(round(out))
    if abs(out - k) > 0.25:
        raise ValueError(f"argument principle at d = {d}: {out:.3f} roots outside, not a whole "
                         f"number")
    return k, len(ph)
