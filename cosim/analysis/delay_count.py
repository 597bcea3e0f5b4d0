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
an interval is halved while any factor turns by more than `TURN` there. `InputDeterminant` does
so in the delayed inputs' coordinates, compiled (1.1 ms per frequency at 1000 agents, 10 ms at
10,000, 2 cores); `TreeDeterminant`, on the whole state in numpy (40 ms at 1000), is kept for a
Φ₀ with an eigenvalue on the circle. 200–500 frequencies per delay up to the margin."""
from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import scipy.sparse as sp

from controller.jit import numba_module

from .stability_sparse import _tree_order

numba = numba_module()     # as the kernels load it (on-disk cache writes that may fail)

# Largest phase step of one pivot block between neighbouring frequencies; above it the interval
# is halved. With 0.5 the counts equalled dense eigvals on every case compared (12-agent tree at
# d = 22, 23, 24, 30: 0, 2, 6, 6) and did not change with 0.25 and twice the grid (1000 agents).
TURN = 0.5
GRID = 40                   # log-spaced frequencies to start from, 1e-9 … π
RIGID = 6                   # the rigid motion's roots at z = 1
RADIAL = 1e-7              # the step off the circle for the phase's rate
# Intervals decided (and midpoints evaluated) per call: enough for the cores, and the phases
# kept (N each) stay few — the ones a pending interval still needs.
BATCH = 32


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

    fixed_half_turns = 0            # every factor of det M is sampled

    def log_dets(self, zs, d: int) -> np.ndarray:
        """(len(zs), N): log det of every agent's pivot block at each z (their sum is
        log det M(z) mod 2πj)."""
        return np.array([self._log_dets(complex(z), d) for z in np.atleast_1d(zs)])

    def _log_dets(self, z: complex, d: int) -> np.ndarray:
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


# ---- the input-space elimination, compiled ------------------------------------------------
#
# Why numba and a hand-written LU: the pivot blocks are 6–16 square, where LAPACK's per-call
# overhead and numpy's batching (every block padded to the largest, np.add.at for the parents)
# cost more than the arithmetic. At 1000 agents one frequency takes 1.9 ms on one core here,
# against 40 ms for `TreeDeterminant`'s batched numpy on the whole state.


@numba.njit(cache=True, nogil=True, error_model="numpy",
            fastmath={"reassoc", "contract", "arcp", "nsz"})
def _lu(A, n, piv):
    """In-place LU with partial pivoting of A[:n, :n]; log det A (complex, phase mod 2π)."""
    det = 1.0 + 0.0j                        # logs only when needed: a complex log costs ~25 flops
    ld = 0.0 + 0.0j
    flips = 0
    for k in range(n):
        p, big = k, abs(A[k, k])
        for i in range(k + 1, n):
            a = abs(A[i, k])
            if a > big:
                p, big = i, a
        piv[k] = p
        if p != k:
            flips += 1
            for j in range(n):
                A[k, j], A[p, j] = A[p, j], A[k, j]
        akk = A[k, k]
        det *= akk
        if not 1e-100 < abs(det) < 1e100:   # a hub's many pivots would overflow the product
            ld += np.log(det)
            det = 1.0 + 0.0j
        inv = 1.0 / akk
        for i in range(k + 1, n):
            f = A[i, k] * inv
            A[i, k] = f
            for j in range(k + 1, n):
                A[i, j] -= f * A[k, j]
    return ld + np.log(-det if flips % 2 else det)


@numba.njit(cache=True, nogil=True, error_model="numpy",
            fastmath={"reassoc", "contract", "arcp", "nsz"})
def _lu_solve(A, n, piv, X, m):
    """X[:n, :m] ← A⁻¹ X for A factored by `_lu`."""
    for k in range(n):
        p = piv[k]
        if p != k:
            for j in range(m):
                X[k, j], X[p, j] = X[p, j], X[k, j]
    for k in range(n):
        for i in range(k + 1, n):
            f = A[i, k]
            for j in range(m):
                X[i, j] -= f * X[k, j]
    for k in range(n - 1, -1, -1):
        inv = 1.0 / A[k, k]
        for j in range(m):
            X[k, j] *= inv
        for i in range(k):
            f = A[i, k]
            for j in range(m):
                X[i, j] -= f * X[k, j]


@numba.njit(cache=True, nogil=True, error_model="numpy",
            fastmath={"reassoc", "contract", "arcp", "nsz"})
def _input_log_dets(zs, lams, Pt, Bt, tb, tr, Ce, e_type, e_rows, t_off, r, s_off, diag_e,
                    order, parent, up_e, down_e, out):
    """out[k, i] = log det of agent i's pivot block of I − λ_k T(z_k), T = C (zI − Φ₀)⁻¹ B,
    eliminated along ``order`` (children before parents, the root last)."""
    nt, bmax, rmax = Bt.shape
    ne = e_type.size
    N = r.size
    Y = np.empty((nt, bmax, rmax), dtype=np.complex128)
    Tf = np.zeros(t_off[ne], dtype=np.complex128)     # flat: a hub's block is not everyone's
    Sf = np.empty(s_off[N], dtype=np.complex128)
    A = np.empty((bmax, bmax), dtype=np.complex128)
    X = np.empty((rmax, rmax), dtype=np.complex128)
    piv = np.empty(max(bmax, rmax), dtype=np.int64)
    for k in range(zs.size):
        z, lam = zs[k], lams[k]
        lam2 = lam * lam
        for t in range(nt):                 # Y_t = (zI − Φ₀_t)⁻¹ B_t, one per kind of agent
            b, m = tb[t], tr[t]
            for i in range(b):
                for j in range(b):
                    A[i, j] = -Pt[t, i, j]
                A[i, i] += z
                for j in range(m):
                    Y[t, i, j] = Bt[t, i, j]
            _lu(A, b, piv)
            _lu_solve(A, b, piv, Y[t], m)
        for e in range(ne):                 # T_ij = C_ij Y_j, one per kind of coupling
            t = e_type[e]
            b, m = tb[t], tr[t]
            Te = Tf[t_off[e]:t_off[e + 1]].reshape((e_rows[e], m))
            Te[:, :] = 0.0
            for i in range(e_rows[e]):
                for q in range(b):
                    f = Ce[e, i, q]
                    if f != 0.0:            # C reads a few of an agent's states per input
                        for j in range(m):
                            Te[i, j] += f * Y[t, q, j]
        for i in range(N):
            ri, e = r[i], diag_e[i]
            Si = Sf[s_off[i]:s_off[i + 1]].reshape((ri, ri))
            if e >= 0:
                Te = Tf[t_off[e]:t_off[e + 1]].reshape((ri, ri))
                for a in range(ri):
                    for c in range(ri):
                        Si[a, c] = -lam * Te[a, c]
            else:
                Si[:, :] = 0.0
            for a in range(ri):
                Si[a, a] += 1.0
        for s in range(N - 1):
            c = order[s]
            p = parent[c]
            rc, rp = r[c], r[p]
            Sc = Sf[s_off[c]:s_off[c + 1]].reshape((rc, rc))
            out[k, c] = _lu(Sc, rc, piv)
            Tu = Tf[t_off[up_e[c]]:t_off[up_e[c] + 1]].reshape((rc, rp))
            Td = Tf[t_off[down_e[c]]:t_off[down_e[c] + 1]].reshape((rp, rc))
            for a in range(rc):
                for q in range(rp):
                    X[a, q] = Tu[a, q]
            _lu_solve(Sc, rc, piv, X, rp)      # S_c⁻¹ T_cp
            Sp = Sf[s_off[p]:s_off[p + 1]].reshape((rp, rp))
            for a in range(rp):               # S_p −= λ² T_pc S_c⁻¹ T_cp
                for q in range(rc):
                    f = lam2 * Td[a, q]
                    for w in range(rp):
                        Sp[a, w] -= f * X[q, w]
        root = order[N - 1]
        out[k, root] = _lu(Sf[s_off[root]:s_off[root + 1]].reshape((r[root], r[root])),
                           r[root], piv)


class PoleOnCircle(ValueError):
    """Φ₀ has an eigenvalue on the unit circle: T(z) has a pole there."""


class InputDeterminant:
    """det M(z) = det(zI − Φ₀) · det(I − z^{−d} T(z)) with T = C (zI − Φ₀)⁻¹ B, the second factor
    eliminated leaves-first along the tree in the delayed inputs' coordinates.

    Why this factorisation: an agent's delayed inputs (its wrench, 6, and the θ flows of the
    edges it owns) are half its states (its δ, ξ and owned θ), so the pivot blocks are half as
    large (6–7 on the random trees against 12–13), and T(z) between two agents depends on z
    only through (zI − Φ₀_j)⁻¹ B_j, the same for every agent of a kind (degree, owned edges,
    inertia): it is solved once per kind and frequency. The first factor needs no sampling at
    all: det(zI − Φ₀) is a real polynomial with no root on the circle (checked), so its phase
    grows by exactly π per eigenvalue of Φ₀ inside the circle over 0 < ω ≤ π (conjugate
    symmetry halves the full turn); `fixed_half_turns` is that count. Construction raises
    ValueError where Φ₀ has an eigenvalue on the circle (T would have a pole there) or the
    blocks do not follow the tree; `TreeDeterminant` then counts on the whole state."""

    def __init__(self, lin, Phi0, B, C, root: int = 0):
        N, E = lin.N, np.asarray(lin.edges, dtype=np.int64)
        if E.shape[0] != N - 1:
            raise ValueError("InputDeterminant: the agents' graph is not a tree")
        M = E.shape[0] if Phi0.shape[0] > 12 * N else 0
        owner = E[:M, 0]
        pos = np.zeros(M, dtype=np.int64)          # an owned θ's place among its owner's
        if M:
            by = np.lexsort((np.arange(M), owner))
            pos[by] = np.arange(M) - np.searchsorted(owner[by], owner[by])
        nown = np.bincount(owner, minlength=N)
        a6, l6 = np.repeat(np.arange(N), 6), np.tile(np.arange(6), N)
        st_agent = np.concatenate([a6, a6, owner])
        st_local = np.concatenate([l6, 6 + l6, 12 + pos])
        sl_agent, sl_local = np.concatenate([a6, owner]), np.concatenate([l6, 6 + pos])
        b, r = 12 + nown, 6 + nown
        bmax, rmax = int(b.max()), int(r.max())
        order, parent = _tree_order(N, E, root)
        if np.count_nonzero(parent < 0) != 1:
            raise ValueError("InputDeterminant: the agents' graph is not connected")

        def blocks(X, ra, rl, ca, cl):
            X = sp.coo_matrix(X)
            keep = X.data != 0.0
            return ra[X.row[keep]], rl[X.row[keep]], ca[X.col[keep]], cl[X.col[keep]], \
                X.data[keep]

        Pblk, Bblk = np.zeros((N, bmax, bmax)), np.zeros((N, bmax, rmax))
        for X, out, ca, cl in ((Phi0, Pblk, st_agent, st_local), (B, Bblk, sl_agent, sl_local)):
            i, li, j, lj, v = blocks(X, st_agent, st_local, ca, cl)
            if np.any(i != j):
                raise ValueError("InputDeterminant: Φ₀ or B couples two agents")
            out[i, li, lj] = v
        i, li, j, lj, v = blocks(C, sl_agent, sl_local, st_agent, st_local)
        Cs = np.zeros((3, N, rmax, bmax))           # i reads i; child reads parent; parent child
        kind = np.full(i.size, -1)
        kind[j == i] = 0
        kind[j == parent[i]] = 1
        kind[(kind < 0) & (parent[j] == i)] = 2
        if np.any(kind < 0):
            raise ValueError("InputDeterminant: a delayed input reads an agent that is not a "
                             "neighbour")
        at = np.where(kind == 2, j, i)              # both couplings of an edge kept at its child
        Cs[kind, at, li, lj] = v

        key = np.concatenate([Pblk.reshape(N, -1), Bblk.reshape(N, -1), b[:, None]], axis=1)
        first, atype = np.unique(key, axis=0, return_index=True, return_inverse=True)[1:]
        atype = atype.ravel()
        self.Pt, self.Bt = Pblk[first], np.ascontiguousarray(Bblk[first])
        self.tb, self.tr = b[first], r[first]
        ev = [np.linalg.eigvals(P[:k, :k]) for P, k in zip(self.Pt, self.tb)]
        gap = min(float(np.abs(np.abs(e) - 1.0).min()) for e in ev)
        if gap < 1e-9:
            raise PoleOnCircle("InputDeterminant: Φ₀ has an eigenvalue on the unit circle")
        per_type = np.bincount(atype, minlength=len(first))
        self.fixed_half_turns = int(sum(c * int((np.abs(e) < 1.0).sum())
                                        for c, e in zip(per_type, ev)))

        kids = np.flatnonzero(parent >= 0)
        diag = np.flatnonzero(np.abs(Cs[0]).reshape(N, -1).max(axis=1) > 0)
        # every coupling block with the kind of the agent it reads and its row count
        blk = np.concatenate([Cs[0][diag], Cs[1][kids], Cs[2][kids]])
        coltype = np.concatenate([atype[diag], atype[parent[kids]], atype[kids]])
        rows = np.concatenate([r[diag], r[kids], r[parent[kids]]])
        ekey = np.concatenate([blk.reshape(blk.shape[0], -1), coltype[:, None],
                               rows[:, None]], axis=1)
        efirst, etype = np.unique(ekey, axis=0, return_index=True, return_inverse=True)[1:]
        etype = etype.ravel()
        self.Ce = np.ascontiguousarray(blk[efirst])
        self.e_type, self.e_rows = coltype[efirst], rows[efirst]
        self.t_off = np.concatenate([[0], np.cumsum(self.e_rows * self.tr[self.e_type])])
        nd, nk = diag.size, kids.size
        self.diag_e = np.full(N, -1)
        self.diag_e[diag] = etype[:nd]
        self.up_e = np.full(N, -1)
        self.up_e[kids] = etype[nd:nd + nk]
        self.down_e = np.full(N, -1)
        self.down_e[kids] = etype[nd + nk:]
        self.r = r
        self.s_off = np.concatenate([[0], np.cumsum(r * r)])
        self.order = np.ascontiguousarray(order[::-1])     # children before parents
        self.parent = parent
        self.N = N

    def log_dets(self, zs, d: int) -> np.ndarray:
        """(len(zs), N): log det of every agent's pivot block of I − z^{−d} T(z) at each z;
        the frequencies are shared among the cores (the kernel releases the GIL)."""
        zs = np.atleast_1d(np.asarray(zs, dtype=complex))
        out = np.empty((zs.size, self.N), dtype=complex)
        args = (self.Pt, self.Bt, self.tb, self.tr, self.Ce, self.e_type, self.e_rows,
                self.t_off, self.r, self.s_off, self.diag_e, self.order, self.parent,
                self.up_e, self.down_e)
        parts = np.array_split(np.arange(zs.size), min(_WORKERS, zs.size))

        def run(ix):
            o = np.empty((ix.size, self.N), dtype=complex)
            _input_log_dets(zs[ix], zs[ix] ** (-d), *args, o)
            out[ix] = o

        if len(parts) == 1:
            run(parts[0])
        else:
            for f in [_pool().submit(run, ix) for ix in parts]:
                f.result()
        return out


_WORKERS = max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
               else (os.cpu_count() or 1))
_POOLS: list = []


def _pool() -> ThreadPoolExecutor:
    if not _POOLS:
        _POOLS.append(ThreadPoolExecutor(_WORKERS, thread_name_prefix="se3sync-count"))
    return _POOLS[0]


def determinant_on_tree(lin, Phi0, B, C, root: int = 0):
    """`InputDeterminant`, or `TreeDeterminant` where Φ₀ has an eigenvalue on the circle."""
    try:
        return InputDeterminant(lin, Phi0, B, C, root)
    except PoleOnCircle:
        return TreeDeterminant(lin, Phi0, B, C, root)


def roots_outside(tdet, n: int, d: int, grid: int = GRID, turn: float = TURN):
    """(roots of the augmented loop with delay d outside the unit circle, frequencies used).

    ``tdet`` is an `InputDeterminant` or a `TreeDeterminant`. The phase of each pivot block is
    followed from ω = 1e-9 (z = 1 is the rigid motion's root) to π. Each block's determinant is
    analytic in z, so its phase turns at the rate ∂arg/∂ω = ∂log|·|/∂r on the circle
    (Cauchy–Riemann), taken from a second elimination at radius 1 + `RADIAL`. An interval is
    halved while some block turns by more than ``turn`` across it, or would at the rate seen at
    either end: the phase alone cannot tell a block that turned by 2π from one that stood still
    (a 24-agent tree at d = 22 was miscounted by 2 so). The intervals are taken `BATCH` at a
    time from the low end, their midpoints evaluated in one call (shared among the cores); each
    decision is the interval's own, so the frequencies are those of halving one interval after
    another, and only the phases of pending intervals' ends are kept.
    The sum of the phase changes is a whole number of half turns up to rounding; a count
    further than 0.25 from a whole number is refused (ValueError), not rounded."""
    def at(ws):
        z = np.exp(1j * np.asarray(ws))
        f = tdet.log_dets(np.concatenate([z, (1.0 + RADIAL) * z]), d)
        k = z.size
        return f[:k].imag, np.abs(f[k:].real - f[:k].real).max(axis=1) / RADIAL

    ws = np.geomspace(1e-9, math.pi, grid)
    ph, rt = at(ws)
    known = {w: (ph[i], rt[i]) for i, w in enumerate(ws)}
    refs = {w: 2 for w in ws}
    refs[ws[0]] = refs[ws[-1]] = 1
    used, total = grid, 0.0
    stack = list(zip(ws[:-1], ws[1:]))[::-1]
    while stack:
        batch, stack = stack[-BATCH:], stack[:-BATCH]
        a, c = np.array(batch).T
        pa = np.array([known[x][0] for x in a])
        pc = np.array([known[x][0] for x in c])
        rate = np.maximum([known[x][1] for x in a], [known[x][1] for x in c])
        step = (pc - pa + math.pi) % (2 * math.pi) - math.pi
        fast = np.maximum(np.abs(step).max(axis=1), (c - a) * rate)
        split = (fast > turn) & (c - a > 1e-12 * c)
        total += step[~split].sum()
        for x in np.concatenate([a[~split], c[~split]]):     # drop phases no one needs
            refs[x] -= 1
            if not refs[x]:
                del known[x], refs[x]
        mids = 0.5 * (a[split] + c[split])
        if mids.size:
            ph, rt = at(mids)
            known.update((w, (ph[i], rt[i])) for i, w in enumerate(mids))
            refs.update((w, 2) for w in mids)
            used += mids.size
        for lo, m, hi in zip(a[split][::-1], mids[::-1], c[split][::-1]):
            stack += [(m, hi), (lo, m)]
    out = n - RIGID / 2 - (tdet.fixed_half_turns + total / math.pi)
    if not math.isfinite(out):
        raise ValueError(f"argument principle at d = {d}: a pivot block is singular on the "
                         f"unit circle (a root on it)")
    k = int(round(out))
    if abs(out - k) > 0.25:
        raise ValueError(f"argument principle at d = {d}: {out:.3f} roots outside, not a whole "
                         f"number")
    return k, used
