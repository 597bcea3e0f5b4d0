"""Delay margin of the zero-order-hold loop linearised at consensus, the delay modelled exactly.

Contract (the one the co-simulation's [network] delay and the per-vehicle agents implement):
at communication step n agent i uses its own state x_i(n) fresh and, for each neighbour j, the
data j published at step n − d: X_j(n−d), ξ_j(n−d) and θ_k(n−d) (after the jump stage) for the
edges k that j owns. Each agent evaluates its incident edges with its own fresh pose and the
delayed neighbour pose, flows the θ_k it owns (the positive end's) with that X̄_k, and uses the
delayed θ_k of the edges its neighbours own. A delay of D seconds is d = ⌈D/h − 1e-9⌉ steps.

Linearised, with s = (δ, ξ, θ) and the edge Jacobian J of `stability_sparse.edge_jacobian`:
    s(n+1) = Φ₀ s(n) + Φ_d s(n−d),
where Φ₀ holds the plant, the −k_ξξ term and each agent's fresh columns of J (the positive end:
its δ, ξ and θ_k; the negative end: its δ, ξ) and Φ_d the delayed ones. With d = 0, Φ₀ + Φ_d
is the loop of `stability`. The delayed data enter only through the wrench and θ's flow,
Φ_d = B C with C = [K_d; G_d], so the augmented state is z(n) = (s(n), w(n−1), …, w(n−d)) with
w = C s: 12N + M + d(6N + M) states instead of (d + 1)(12N + M). The rigid motion (all δ_i
equal) spans an invariant subspace with eigenvalue 1, projected out before taking ρ.
"""
from __future__ import annotations

import math
import time

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from controller.errors import Se3SyncError

from ..signals import interruptible
from ..threads import analysis as blas_policy
from .delay_count import determinant_on_tree, roots_outside
from .stability_sparse import Linearisation

# Dense eigvals costs O(m³) in the augmented size m (2 cores: 0.4 / 1.4 / 2.3 / 7 / 17 s at
# m = 733 / 1389 / 1983 / 2871 / 3759), so it is used up to about 2.5 s a probe. Above, the
# largest-modulus ARPACK search is unreliable: the dominant eigenvalues cluster near 1 (slow
# modes at a small step), and asked for the 6 largest it can return converged Ritz values that
# are not the largest (16-agent tree, d = 16: 0.998905 for LAPACK's 0.999821; with k = 12 and
# a 24-agent tree at d = 22 it returned 0.99990706 and missed a real mode at 0.99993175). The
# spectrum meets the unit circle in two places only, so two shift-invert searches are used
# instead (`_radius_near`, one sparse LU each): near z = 1, where the undelayed loop's slow
# modes sit, and near e^{jω} at the angle where `crossing_delay` saw the delay push roots out.
# Their larger modulus equalled LAPACK's radius at every probe compared (hil_6uav at d = 1, 5,
# 10, 16, 20, 24, 25, to 1e-10; random trees of 12, 16, 20, 24 and 50 agents at the margin and
# one past it, to the 8 digits `check` prints), in 0.03–0.6 s where dense took up to 2 min and
# ARPACK up to 2.5 min (100 agents, 16,000 states).
DENSE_MAX = 2000
ARPACK_K = 12
# `crossing_delay` takes every eigenvalue of T₁₂T₂₁ (m/2 square) at several hundred frequencies,
# O(m³) each: `check` took 32 s at 100 agents and 4 minutes at 210 (m = 1469). Above 1500
# (about 214 agents on a tree) `delay_margin` declines rather than search without the crossing
# angle: ARPACK's largest-modulus search then decides, and it can call an unstable delay stable
# (a 220-agent tree ran past 5 minutes on 2 cores with it).
CROSSING_MAX = 1500
# On a tree of at least this many agents the margin comes from exact counts of the roots outside
# the unit circle (`delay_count`) instead of the sweep and the radii: O(N) per frequency, and
# faster from here on (16-agent tree: 0.22 s against 0.60 s; 50 agents: 0.45 s against 5.9 s).
# Below, the sweep's radii at the margin and past it are kept for what they tell (how near the
# circle the loop is).
COUNT_FROM_AGENTS = 16
# The count's search (`_margin_by_count`) starts at this delay, in steps, and grows it by
# 1/COUNT_GROWTH (at least one step) while no root is outside.
COUNT_START = 8
COUNT_GROWTH = 5
# Halvings of a grid interval where the count of |μ| > 1 changes. 3 gave the same ⌊τ⌋ and ω
# (within 2 %, τ within 0.003) as 12 on hil_6uav and 32 seeded random trees of 8–100 agents, with
# 45–60 % of the eigenproblems (100 agents: 408 instead of 1049, 29 s instead of 79 s); 1 moved
# a 32-agent tree's guess from 21.68 to 22.59. The guess only starts the search: the radii at ⌊τ⌋
# and ⌊τ⌋ + 1 decide.
NARROW_DEPTH = 3

__all__ = ["delayed_loop", "delayed_parts", "augmented", "delay_radius", "delay_margin",
           "crossing_delay", "LoopTransfer", "steps_of_delay"]


def steps_of_delay(D: float, h: float) -> int:
    """d = ⌈D/h − 1e-9⌉: the number of whole steps a delay of D seconds spans."""
    return max(0, int(math.ceil(D / h - 1e-9)))


def delayed_loop(lin: Linearisation, h: float):
    """(Φ₀, Φ_d), sparse CSR, each (12N + M)² (θ only if hybrid)."""
    Phi0, Bf, Cd = delayed_parts(lin, h)
    return Phi0, (Bf @ Cd).tocsr()


def delayed_parts(lin: Linearisation, h: float, fresh_wrench: bool = False):
    """(Φ₀, B, C) with Φ_d = B C: the delayed data enter only through the wrench and θ's flow,
    C = [K_d; G_d] ((6N + M) × n), B = blkdiag(B_d, h I). ``fresh_wrench``: also K₀ (6N × n),
    the wrench's gain on the fresh data (Φ₀'s wrench rows are B_d K₀ plus the plant's)."""
    N, M, J, E = lin.N, lin.M, lin.J, lin.edges
    Mt = M if lin.hybrid else 0
    n6, n = 6 * N, 12 * N + Mt
    p, q = E[:, 0], E[:, 1]
    # column offsets of J: δp, δq, ξp, ξq (6 each), θ; and where they sit in s
    col_of = {0: 6 * p, 6: 6 * q, 12: n6 + 6 * p, 18: n6 + 6 * q}
    fresh_for = {0: (0, 12), 6: (6, 18)}          # u_p sees its own δ, ξ fresh; u_q likewise
    parts = {True: ([], [], []), False: ([], [], [])}

    def add(fresh, r, c, v):
        parts[fresh][0].append(r)
        parts[fresh][1].append(c)
        parts[fresh][2].append(v)

    rr, cc = np.divmod(np.arange(36), 6)
    for r_off, who in ((0, p), (6, q)):
        for c_off, col0 in col_of.items():
            blk = J[r_off:r_off + 6, c_off:c_off + 6].ravel()
            add(c_off in fresh_for[r_off], (6 * who[:, None] + rr).ravel(),
                (col0[:, None] + cc).ravel(), np.tile(blk, M))
        if Mt:   # the owner (positive end) uses θ_k fresh, the negative end the delayed copy
            add(r_off == 0, (6 * who[:, None] + np.arange(6)).ravel(),
                np.repeat(12 * N + np.arange(M), 6), np.tile(J[r_off:r_off + 6, 24], M))
    add(True, np.arange(n6), n6 + np.arange(n6), np.full(n6, -lin.k_xi))
    Kx = {f: sp.csr_matrix((np.concatenate(v), (np.concatenate(r), np.concatenate(c))),
                           shape=(n6, n)) for f, (r, c, v) in parts.items()}
    h2 = 0.5 * h * h
    Binv = sp.block_diag(list(lin.I6inv), format="csr")
    Bd = sp.vstack([h2 * Binv, h * Binv]).tocsr()
    Ad = sp.identity(12 * N, format="csr") + sp.csr_matrix(
        (np.full(n6, h), (np.arange(n6), n6 + np.arange(n6))), shape=(12 * N, 12 * N))
    top0 = Bd @ Kx[True] + sp.hstack([Ad, sp.csr_matrix((12 * N, Mt))])
    extra = (Kx[True],) if fresh_wrench else ()
    if not Mt:
        return (top0.tocsr(), Bd, Kx[False], *extra)
    # θ_k(n+1) = θ_k(n) + h G(x_p(n), x_q(n−d), θ_k(n)): the owner's fresh δp, ξp, θ
    g = J[12]
    r = np.repeat(np.arange(M), 12)
    cf = np.concatenate([6 * p[:, None] + np.arange(6), n6 + 6 * p[:, None] + np.arange(6)],
                        axis=1).ravel()
    cd = np.concatenate([6 * q[:, None] + np.arange(6), n6 + 6 * q[:, None] + np.arange(6)],
                        axis=1).ravel()
    vf = np.tile(h * np.concatenate([g[0:6], g[12:18]]), M)
    vd = np.tile(np.concatenate([g[6:12], g[18:24]]), M)
    th = 12 * N + np.arange(M)
    G0 = sp.csr_matrix((np.concatenate([vf, np.full(M, 1.0 + h * g[24])]),
                        (np.concatenate([r, np.arange(M)]), np.concatenate([cf, th]))),
                       shape=(M, n))
    Gd = sp.csr_matrix((vd, (r, cd)), shape=(M, n))
    B = sp.block_diag([Bd, h * sp.identity(M)], format="csr")
    C = sp.vstack([Kx[False], Gd]).tocsr()
    return (sp.vstack([top0, G0]).tocsr(), B, C, *extra)


def augmented(Phi0, B, C, d: int):
    """The loop on z = (s(n), w(n−1), …, w(n−d)) with w = C s the delayed data actually used:
    s(n+1) = Φ₀s(n) + B w(n−d), w(n) = C s(n). Its nonzero eigenvalues are those of the
    companion matrix on (s(n), …, s(n−d)), with (6N + M) instead of 12N + M states per step."""
    if d == 0:
        return (Phi0 + B @ C).tocsr()
    m = C.shape[0]
    blocks = [[None] * (d + 1) for _ in range(d + 1)]
    blocks[0][0] = Phi0
    blocks[0][d] = B
    blocks[1][0] = C
    for k in range(2, d + 1):
        blocks[k][k - 1] = sp.identity(m, format="csr")
    for k in range(1, d + 1):                     # keep every block row's shape defined
        if blocks[k][k] is None:
            blocks[k][k] = sp.csr_matrix((m, m))
    return sp.bmat(blocks, format="csr")


def _rigid_basis_aug(N, C, d):
    """Orthonormal basis of the rigid motion in z: s = common δ, every w slot = C s."""
    n = C.shape[1]
    S = np.zeros((n, 6))
    for a in range(6):
        S[a:6 * N:6, a] = 1.0
    Z = np.vstack([S] + [C @ S] * d)
    return np.linalg.qr(Z)[0]


def delay_radius(lin: Linearisation, h: float, d: int, loop=None, near: float | None = None):
    """Spectral radius of the delayed loop without the rigid motion's six eigenvalues 1.

    Up to `DENSE_MAX` states: LAPACK on the whole matrix. Above, with ``near`` = ω (the angle
    where `crossing_delay` saw a root leave the circle): the larger modulus of the eigenvalues
    nearest z = 1 (the undelayed loop's slow modes) and nearest e^{jω} (the roots the delay
    pushes out), by shift-invert (`_radius_near`); without it, ARPACK's largest-modulus
    search, which can miss the largest on this clustered spectrum."""
    Phi0, B, C = loop if loop is not None else delayed_parts(lin, h)
    A = augmented(Phi0, B, C, d)
    Q = _rigid_basis_aug(lin.N, C, d)
    if np.abs(A @ Q - Q).max() > 1e-9:
        raise RuntimeError("delayed linearisation: the rigid motion is not invariant")
    m = A.shape[0]
    if m <= DENSE_MAX:
        D = A.toarray()
        D -= (D @ Q) @ Q.T
        D -= Q @ (Q.T @ D)
        return float(np.abs(interruptible(np.linalg.eigvals, D)).max())
    if near is not None:
        loop = (Phi0, B, C)
        return max(_radius_near(loop, 0.0, d), _radius_near(loop, near, d))

    def mv(x):
        x = np.asarray(x).ravel()
        x = x - Q @ (Q.T @ x)
        y = A @ x
        return y - Q @ (Q.T @ y)

    op = sla.LinearOperator((m, m), matvec=mv, dtype=float)
    try:
        lam = sla.eigs(op, k=min(ARPACK_K, m - 2), which="LM", tol=1e-12, ncv=min(80, m - 1),
                       maxiter=20000, return_eigenvectors=False)
    except sla.ArpackNoConvergence as exc:
        raise Se3SyncError(f"delay margin: ARPACK did not converge at d = {d} ({exc})") from None
    return float(np.abs(lam).max())


def _shift_inverse(Phi0, B, C, d: int, sigma: complex):
    """(A − σI)⁻¹ for the augmented A of `augmented`, as a LinearOperator, from one sparse LU of
    the n × n matrix M(σ) = Φ₀ − σI + σ^{−d} B C instead of the (n + d·m)-square A − σI.

    Why: the shift registers only pass w along, so with r_1 = y_1/σ, r_k = (r_{k−1} + y_k)/σ,
    (A − σI) z = y gives w_k = σ^{−k} C s − r_k, and the first block row leaves
    M(σ) s = y_0 + B r_d. The LU is d + 1 times smaller, and so is its fill (1000-agent tree,
    d = 20: 13,000 states instead of 153,000)."""
    n, m = Phi0.shape[0], C.shape[0]
    M = Phi0.tocsc() - sigma * sp.identity(n, format="csc") + sigma ** (-d) * (B @ C).tocsc()
    lu = sla.splu(M.astype(complex).tocsc())
    powers = sigma ** -np.arange(1, d + 1)

    def solve(y):                   # d = 0 needs no case of its own: no delay line, r = 0
        y = np.asarray(y, dtype=complex).ravel()
        Y = y[n:].reshape(d, m)
        R = np.empty_like(Y)
        r = np.zeros(m, dtype=complex)
        for k in range(d):
            r = (r + Y[k]) / sigma
            R[k] = r
        s = lu.solve(y[:n] + B @ r)
        W = np.outer(powers, C @ s) - R
        return np.concatenate([s, W.ravel()])

    return sla.LinearOperator((n + d * m, n + d * m), matvec=solve, dtype=complex)


def _radius_near(loop, w: float, d: int, k: int = ARPACK_K) -> float:
    """Largest modulus among the k eigenvalues of the augmented loop nearest σ (ARPACK on the
    shift-inverted (A − σI)⁻¹, `_shift_inverse`), the rigid motion's eigenvalues 1 left out:
    σ = e^{jω} for ω > 0; for ω = 0, σ = 1 + 1e-3, since A − I is singular (the rigid motion),
    and k + 6. Shift-invert converges fastest on the eigenvalues nearest σ, which is where a
    root that leaves the unit circle at angle ω sits while d is near the margin."""
    sigma = complex(np.exp(1j * w)) if w > 0 else 1.0 + 1e-3
    k = k if w > 0 else k + 6
    op = _shift_inverse(*loop, d, sigma)
    m = op.shape[0]
    try:
        theta = sla.eigs(op, k=min(k, m - 2), which="LM", tol=1e-12, ncv=min(4 * k, m - 1),
                         maxiter=20000, return_eigenvectors=False)
    except sla.ArpackNoConvergence as exc:
        raise Se3SyncError(f"delay margin: shift-invert ARPACK did not converge at d = {d} "
                           f"({exc})") from None
    lam = sigma + 1.0 / theta
    lam = lam[np.abs(lam - 1.0) > 1e-8]
    return float(np.abs(lam).max()) if lam.size else 0.0


def _probe(lo: int, hi: int, r_lo: float, r_hi: float, secant: bool) -> int:
    """The next d to try inside the bracket lo < d < hi (ρ(lo) < 1 ≤ ρ(hi)): where the secant
    through the two ends crosses 1, rounded up (ρ(d) bends upwards, so the secant's crossing
    lies at or below the true one), or the midpoint. Either way the bracket shrinks, and with
    one crossing the margin found is the same; the secant needs fewer of the large-d
    eigenproblems (hil_6uav: 22, 24, 25 after the bracket 16–32 instead of 24, 28, 26, 25)."""
    if secant and r_hi > r_lo:
        mid = int(math.ceil(lo + (1.0 - r_lo) * (hi - lo) / (r_hi - r_lo) - 1e-9))
    else:
        mid = (lo + hi) // 2
    return min(max(mid, lo + 1), hi - 1)


class LoopTransfer:
    """T(e^{jω}) = C (e^{jω}I − Φ₀)⁻¹ B, m × m, and the eigenvalues that `crossing_delay` needs.

    Φ₀ is block-diagonal, a block per agent (its δ, ξ and the θ_k it owns; finer where its
    gains leave parts uncoupled): every coupling between agents is delayed, so it sits in B C.
    T is therefore assembled from one small solve per block, batched over blocks of equal
    shape, instead of one dense n × n solve (24 agents: 0.4 ms against 8 ms per frequency).

    The agents' graph is a tree, so it is bipartite. T(z) maps a slot (a delayed input of agent
    i) only to slots of i's neighbours, which lie on the other side; with Σ = ±1 by side,
    Σ T Σ = −T, and the eigenvalues of T come in pairs ±μ. With the slots ordered by side,
    T = [[0, T₁₂], [T₂₁, 0]], and ν = μ² are the eigenvalues of T₁₂ T₂₁, half the size (an
    eigenproblem costs an eighth). Where the blocks do not split into two sides (not a tree),
    the eigenvalues of T itself are used."""

    def __init__(self, Phi0, B, C):
        from scipy.sparse.csgraph import connected_components

        P0, Bc, Cc = Phi0.tocsr(copy=True), B.tocsr(copy=True), C.tocsc(copy=True)
        for X in (P0, Bc, Cc):      # the blocks come from the pattern: stored zeros are not in it
            X.eliminate_zeros()
        self.m, self.n = C.shape
        # blocks of Φ₀ (an agent's block may split, e.g. a rotation axis its gains do not couple),
        # merged where one delayed input enters several (𝕀⁻¹ coupling what Φ₀ does not)
        absB = abs(Bc)
        nb, lab = connected_components(abs(P0) + abs(P0.T) + absB @ absB.T, directed=False)
        inj = np.full(self.m, -1)           # the block each delayed slot enters
        groups, reads = {}, []
        for b in range(nb):
            idx = np.flatnonzero(lab == b)
            Bb = Bc[idx]
            cols = np.unique(Bb.indices)    # disjoint across blocks, by the merge above
            inj[cols] = b
            Cb = Cc[:, idx]
            rows = np.unique(Cb.indices)
            reads.append(rows)
            key = (idx.size, rows.size, cols.size)
            g = groups.setdefault(key, ([], [], [], [], []))
            g[0].append(P0[idx][:, idx].toarray())
            g[1].append(Bb[:, cols].toarray())
            g[2].append(Cb[rows].toarray())
            g[3].append(rows)
            g[4].append(cols)
        self.groups = [tuple(np.array(x) for x in g) for g in groups.values()]
        self.side = self._sides(nb, inj, reads)

    @staticmethod
    def _sides(nb, inj, reads):
        """Side (0/1) of every slot, by the side of the block it enters; None if the blocks'
        coupling graph (block b reads the slots `reads[b]`, which enter `inj`) is not bipartite."""
        nbr = [set(inj[r].tolist()) - {b} for b, r in enumerate(reads)]
        adj = [set() for _ in range(nb)]
        for b, s in enumerate(nbr):
            for c in s:
                adj[b].add(c)
                adj[c].add(b)
        colour = np.full(nb, -1)
        for root in range(nb):
            if colour[root] >= 0:
                continue
            colour[root], stack = 0, [root]
            while stack:
                b = stack.pop()
                for c in adj[b]:
                    if colour[c] < 0:
                        colour[c] = 1 - colour[b]
                        stack.append(c)
                    elif colour[c] == colour[b]:
                        return None
        if np.any(inj < 0):
            return None
        for b, r in enumerate(reads):        # a block's own slots never read it
            if np.any(colour[inj[r]] == colour[b]):
                return None
        return colour[inj]

    def matrix(self, w: float) -> np.ndarray:
        z = np.exp(1j * w)
        T = np.zeros((self.m, self.m), dtype=complex)
        for P, Bb, Cb, rows, cols in self.groups:
            G = np.linalg.solve(z * np.eye(P.shape[1]) - P, Bb)
            T[rows[:, :, None], cols[:, None, :]] = Cb @ G
        return T

    def eigenvalues(self, w: float):
        """(λ, p): with p = 2, λ are the eigenvalues ν = μ² of T₁₂ T₂₁; with p = 1, the μ of T."""
        T = self.matrix(w)
        if self.side is None:
            return np.linalg.eigvals(T), 1
        a, b = np.flatnonzero(self.side == 0), np.flatnonzero(self.side == 1)
        if a.size > b.size:
            a, b = b, a
        return np.linalg.eigvals(T[np.ix_(a, b)] @ T[np.ix_(b, a)]), 2


def crossing_delay(Phi0, B, C, n_omega: int = 200, depth: int = NARROW_DEPTH,
                   paired: bool = True, sweep=None):
    """A guess of the margin from the loop transfer T(z) = C (zI − Φ₀)⁻¹ B (m × m): a root of the
    loop with delay τ sits on the unit circle at z = e^{jω} exactly when T(e^{jω}) has an
    eigenvalue μ with |μ| = 1 and arg μ = ωτ (mod 2π).

    On a log-spaced grid of ω the number of eigenvalues with |μ| > 1 is counted; where it
    changes between two points, bisection (at most ``depth`` halvings, recursing into both
    halves when both change) narrows each change until the eigenvalues that cross |μ| = 1 match
    their nearest neighbours at the other end unambiguously, as many as the count changed by;
    there the crossing is interpolated. On a tree the eigenvalues come in pairs ±μ
    (`LoopTransfer`), and the count and the matching run on ν = μ²; of a pair the one with the
    smaller angle crosses first, arg μ mod π = (arg ν mod 2π)/2 (``paired=False``: the
    eigenvalues of T itself, the reference the benchmark compares with).
    ``sweep(k, g, n_omega)``, if given, is called after each eigenproblem: k of them so far, g
    grid points done (the bisections follow the grid).
    Returns (τ, ω) of the crossing with the smallest τ = (arg μ mod 2π)/ω, in steps and
    rad/step; None if no eigenvalue reaches |μ| = 1 on 1e-3 ≤ ω ≤ π, or if the loop is too
    large for dense eigenvalues (m > `CROSSING_MAX`).

    Only a guess: a crossing and its return between two grid points cancel in the count, so
    `delay_margin` verifies ⌊τ⌋ and ⌊τ⌋ + 1 with the exact eigenproblems and searches on from
    there if they do not bracket the margin. Why a guess: the search's probes cost (n + d·m)³
    each, and growing d by doubling overshoots the margin by up to 2× (hil_6uav: 32 for a
    margin of 24, a third of the time). Why counts, not eigenvalues followed across the grid:
    the grid's 4 % steps are too coarse to match eigenvalues reliably where they move fast, and
    matching put the crossing a step past the margin on a 6-agent tree (34.04 for 33; counted:
    33.82) and missed the one that sets it on a 24-agent tree (23.48 for 22; counted: 22.70)."""
    m = C.shape[0]
    if m > CROSSING_MAX:
        return None
    tf = LoopTransfer(Phi0, B, C)
    if not paired:
        tf.side = None
    cache = {}
    done = 0                                    # grid points counted

    def eig(w):
        if w not in cache:
            cache[w] = tf.eigenvalues(w)[0]
            if sweep is not None:
                sweep(len(cache), done, n_omega)
        return cache[w]

    power = 1 if tf.side is None else 2         # eig() returns μ, or ν = μ² on a tree

    def count(w):
        return int((np.abs(eig(w)) > 1.0).sum())

    best = (math.inf, None)

    def narrow(wa, wb, ca, cb, level):
        nonlocal best
        ma, mb = eig(wa), eig(wb)
        dist = np.abs(ma[:, None] - mb[None, :])
        near = np.argsort(dist, axis=1)[:, :2]
        nb = mb[near[:, 0]]
        ra, rb = np.abs(ma), np.abs(nb)
        cross = np.nonzero((ra - 1.0) * (rb - 1.0) <= 0.0)[0]
        rows = np.arange(ma.size)
        d1, d2 = dist[rows, near[:, 0]], dist[rows, near[:, 1]]
        # stop halving once every crossing eigenvalue's match is unambiguous (its nearest
        # neighbour at the other end 5× closer than the next) and the count agrees
        sure = cross.size == abs(cb - ca) and bool(np.all(d1[cross] < 0.2 * d2[cross]))
        if level == 0 or sure:
            for k in cross:
                t = (1.0 - ra[k]) / (rb[k] - ra[k]) if rb[k] != ra[k] else 0.5
                wc = wa + t * (wb - wa)
                ph = np.angle(ma[k]) + t * np.angle(nb[k] / ma[k])
                best = min(best, ((ph % (2 * math.pi)) / (power * wc), wc))
            return
        wm = 0.5 * (wa + wb)
        cm = count(wm)
        if cm != ca:
            narrow(wa, wm, ca, cm, level - 1)
        if cm != cb:
            narrow(wm, wb, cm, cb, level - 1)

    grid = np.geomspace(1e-3, math.pi, n_omega)
    counts = []
    for w in grid:
        counts.append(count(w))
        done += 1
    for k in range(n_omega - 1):
        if counts[k] != counts[k + 1]:
            narrow(grid[k], grid[k + 1], counts[k], counts[k + 1], depth)
    return best if math.isfinite(best[0]) else None


@blas_policy
def delay_margin(scenario, h: float | None = None, law="hybrid", d_cap: int = 1024,
                 lin: Linearisation | None = None, secant: bool = True, guess: bool = True,
                 progress=None, sweep=None, count: bool | None = None) -> dict:
    """The largest d with ρ(d) < 1 and ρ(d + 1) ≥ 1 for the loop of ``law`` (a registered law
    name; True / False: hybrid / gradient), found by growing d from 0 until the loop
    is unstable and then narrowing the last bracket (`_probe`: by the secant, or by bisection
    with ``secant=False``). With ``guess=True`` the search starts from `crossing_delay`'s τ:
    ⌊τ⌋ and ⌊τ⌋ + 1 first, then on from the bracket they leave. This assumes that ρ(d) crosses
    1 once, which is what we observed: ρ(d) increases with d on every case we scanned d by d.
    ``progress(d, ρ, seconds)``, if given, is called after each eigenproblem, and ``sweep``
    is handed to `crossing_delay`. ``count`` (default: trees of `COUNT_FROM_AGENTS` agents or
    more, or above `CROSSING_MAX` delayed inputs) searches on exact counts of the roots outside the unit circle instead
    (`_margin_by_count`; ``progress(d, None, seconds, outside=k)``); ``count=False`` keeps the
    sweep and the radii.

    Returns {"delay_margin_steps", "delay_margin_s", "rho_at_margin", "rho_beyond",
    "delay_method"}; steps = −1 when the loop is unstable even without delay, and None when
    every d ≤ d_cap is stable (then ``"stable_up_to_steps"`` is the largest d tried), or (with
    ``guess``) when the loop has more than `CROSSING_MAX` delayed inputs."""
    h = float(scenario.step if h is None else h)
    if scenario.graph.M == 0:
        return {"delay_margin_steps": None, "delay_margin_s": None, "rho_at_margin": None,
                "rho_beyond": None, "delay_method": "no edges: no neighbour data to delay"}
    lin = lin or Linearisation(scenario, law, force_sparse=True)
    loop = delayed_parts(lin, h)
    rho = {}

    def r(d):
        if d not in rho:
            t0 = time.perf_counter()
            rho[d] = delay_radius(lin, h, d, loop, near)
            if progress is not None:
                progress(d, rho[d], time.perf_counter() - t0)
        return rho[d]

    n = (loop[0].shape[0], loop[2].shape[0])
    tree = lin.edges.shape[0] == lin.N - 1
    if count is None:
        count = tree and (n[1] > CROSSING_MAX or lin.N >= COUNT_FROM_AGENTS)
    if count:                       # scenarios' graphs are acyclic (Assumption 1), so trees
        return _margin_by_count(lin, loop, h, d_cap, progress)
    if guess and n[1] > CROSSING_MAX:
        return {"delay_margin_steps": None, "delay_margin_s": None, "rho_at_margin": None,
                "rho_beyond": None,
                "delay_method": f"not computed: {n[1]} delayed inputs, more than the "
                                f"{CROSSING_MAX} the frequency sweep takes (its eigenproblems "
                                f"grow as the cube)" + ("" if tree else "; the roots outside the "
                                "circle are counted instead only on a tree")}
    near = None                     # the crossing angle, once `crossing_delay` has one
    if r(0) >= 1.0:
        return {"delay_margin_steps": -1, "delay_margin_s": None, "rho_at_margin": None,
                "rho_beyond": r(0), "delay_method": _method(n, 0)}
    lo, hi = 0, 1
    cross = crossing_delay(*loop, sweep=sweep) if guess else None
    guessed = cross is not None and cross[0] < d_cap
    near = cross[1] if cross is not None else None
    if guessed:
        d0 = max(1, int(math.floor(cross[0])))
        lo, hi = (0, d0) if r(d0) >= 1.0 else (d0, d0 + 1)
    step = max(1, lo // 8)          # above a stable guess grow gently, from 0 by doubling
    while r(hi) < 1.0:
        lo, hi = hi, (hi + 2 * step if guessed else 2 * hi)
        step *= 2
        if hi > d_cap:
            return {"delay_margin_steps": None, "delay_margin_s": None, "rho_at_margin": r(lo),
                    "rho_beyond": None, "stable_up_to_steps": lo,
                    "delay_method": f"stable for every delay up to {lo} steps ({lo * h:g} s) "
                                    f"tried; " + _method(n, lo, lo, near)}
    while hi - lo > 1:
        mid = _probe(lo, hi, r(lo), r(hi), secant)
        if r(mid) < 1.0:
            lo = mid
        else:
            hi = mid
    how = _method(n, lo, hi, near)
    if guessed:
        how += (f"; search started from the frequency-sweep guess τ = {cross[0]:.2f} steps "
                f"(ω = {cross[1]:.4g} rad/step), {len(rho)} eigenproblems")
    return {"delay_margin_steps": lo, "delay_margin_s": lo * h, "rho_at_margin": r(lo),
            "rho_beyond": r(hi), "delay_method": how}


def _margin_by_count(lin, loop, h, d_cap, progress):
    """The margin from exact counts of the roots outside the unit circle (`delay_count`): the
    largest d with none (one crossing assumed, as the radius search does).

    The search starts at `COUNT_START` and grows d by a fifth (at least 1) while no root is
    outside, or halves it while some are; then it bisects the bracket down to 4 delays and
    steps up from its stable end. Why so cautious: a count past the margin costs more the
    further past it is, as more roots sit near the circle (1000-agent tree, margin 18:
    0.5–1.0 s at d ≤ 18, 1.2 s at 19, 2.4 s at 22, 3.5 s at 32; 10,000 agents: 5–8 s at
    d ≤ 16, 28 s at 20, 72 s at 24), so a few more counts below the margin are cheaper than one
    far past it, which doubling (up to 2× past) and bisection make."""
    tdet = determinant_on_tree(lin, *loop)
    n = loop[0].shape[0]
    found, freqs = {}, [0]

    def k(d):
        if d not in found:
            t0 = time.perf_counter()
            try:
                found[d], f = roots_outside(tdet, n, d)
            except ValueError as exc:           # a count that is not a whole number
                raise Se3SyncError(f"delay margin: {exc}") from None
            freqs[0] += f
            if progress is not None:
                progress(d, None, time.perf_counter() - t0, outside=found[d])
        return found[d]

    def report(**kw):
        return {"delay_margin_steps": None, "delay_margin_s": None, "rho_at_margin": None,
                "rho_beyond": None, **kw,
                "delay_method": kw.get("delay_method", "") + (
                    f"roots outside the unit circle counted by the argument principle, the "
                    f"determinant factored along the tree ({len(found)} delays, {freqs[0]} "
                    f"frequencies)")}

    lo = hi = min(COUNT_START, d_cap)
    if k(lo) == 0:
        while k(hi) == 0:
            if hi >= d_cap:
                return report(stable_up_to_steps=hi,
                              delay_method=f"stable for every delay up to {hi} steps "
                                           f"({hi * h:g} s) tried; ")
            lo, hi = hi, min(d_cap, hi + max(1, hi // COUNT_GROWTH))
    else:
        while k(lo) > 0:
            if lo == 0:
                return report(delay_margin_steps=-1, outside_at_margin=None,
                              outside_beyond=found[0])
            lo, hi = lo // 2, lo
    while hi - lo > 1:              # bisect down to 4, then step up from the stable end
        mid = (lo + hi) // 2 if hi - lo > 4 else lo + 1
        if k(mid) == 0:
            lo = mid
        else:
            hi = mid
    return report(delay_margin_steps=lo, delay_margin_s=lo * h, outside_at_margin=0,
                  outside_beyond=found[hi])


def _method(n, lo, hi=None, near=None):
    """How the radii at d = lo and d = hi were computed; both named when they differ."""
    def how(d):
        if n[0] + d * n[1] <= DENSE_MAX:
            return "dense eigvals"
        if near is None:
            return "ARPACK (largest modulus; on this clustered spectrum it can miss the largest)"
        return (f"shift-invert ARPACK near z = 1 and near the crossing angle ω = {near:.4g} "
                f"rad/step")

    hi = lo if hi is None else hi
    solver = how(hi) if how(lo) == how(hi) else f"d = {lo}: {how(lo)}; d = {hi}: {how(hi)}"
    return (f"augmented state (the {n[0]}-state loop and d past copies of the {n[1]} delayed "
            f"inputs), linearised at consensus, rigid motion projected out, {solver}")
