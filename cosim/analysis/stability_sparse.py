"""Sampled-data stability at scale: the linearised ZOH loop built per edge and per agent.

The loop linearised at consensus (X_i = exp(δ_i^), θ = 0, ξ = 0) is the one of `stability`,
assembled without ever forming a dense (12N + M)² matrix:

* Controller: at first order each edge k = (i, j) contributes a function of
  (δ_i, δ_j, ξ_i, ξ_j, θ_k) only, and at consensus every edge sits at the same point
  (X̄_k = I, θ_k = 0) with the same parameters. So one 13 × 25 edge Jacobian, from central
  finite differences of the law's own step on a two-agent graph (`cosim.analysis.linear`),
  gives every block of K and G; the −k_ξ ξ_i term is linear and exact.
* Plant: δ̇_i = ξ_i, 𝕀_i ξ̇_i = u_i is nilpotent, so its zero-order hold is closed form per agent:
  A_d = [[I, hI], [0, I]], B_d = [[h²/2 𝕀_i⁻¹], [h 𝕀_i⁻¹]].

Two ways to get the spectral radius (`method` in the result):

* "modal" (every agent has the same 𝕀, and the edge Jacobian has the incidence structure
  u = −(L⊗K_δ)δ − (L⊗K_e)ξ − (B⊗K_θ)θ, θ̇ = (Bᵀ⊗g_δ)δ + (Bᵀ⊗g_ξ)ξ + g_θθ, checked numerically):
  with the SVD B = U Σ Vᵀ of the incidence matrix, δ̃ = (Uᵀ⊗I)δ, ξ̃ = (Uᵀ⊗I)ξ, θ̃ = Vᵀθ
  decouple the loop exactly into one 13 × 13 block per nonzero Laplacian eigenvalue s = σ²
  plus the common mode (six eigenvalues at exactly 1, the rigid motion, and the damping
  I − h𝕀⁻¹k_ξ of the mean velocity). The Laplacian eigenvalues of the tree come from Sylvester
  inertia counts (an O(N) LDLᵀ elimination from the leaves) and bisection, in O(N) memory.
  Exact up to the bisection tolerance (1e-13 relative), with no eigensolver convergence to trust.
* "sparse" (heterogeneous agents): the sparse Φ, the rigid subspace projected out, and the
  eigenvalues of largest modulus from ARPACK (dense `eigvals` below `DENSE_MAX` states).
"""
from __future__ import annotations

import numpy as np

from controller.errors import Se3SyncError
from controller.jit import numba_module

from ..signals import interruptible
from .linear import edge_jacobian, law_of

# the inertia counts are compiled, like the kernels (numba as the kernels load it, on-disk cache)
numba = numba_module()

__all__ = ["modal_blocks", "laplacian_eigenvalues", "sparse_loop", "spectral_radius_fast",
           "analyse_fast", "Linearisation", "DENSE_MAX"]

DENSE_MAX = 3000          # below this many states a dense eigvals is faster than ARPACK
STRUCT_TOL = 1e-7         # relative tolerance of the incidence-structure check


def modal_blocks(J):
    """(K_δ, K_e, K_θ, g_δ, g_ξ, g_θ) if J has the incidence structure, else None."""
    Kd, Ke, Kt = -J[0:6, 0:6], -J[0:6, 12:18], -J[0:6, 24]
    gd, gx, gt = J[12, 0:6], J[12, 12:18], J[12, 24]
    expect = np.zeros_like(J)
    expect[0:6, 0:6], expect[0:6, 6:12] = -Kd, Kd
    expect[6:12, 0:6], expect[6:12, 6:12] = Kd, -Kd
    expect[0:6, 12:18], expect[0:6, 18:24] = -Ke, Ke
    expect[6:12, 12:18], expect[6:12, 18:24] = Ke, -Ke
    expect[0:6, 24], expect[6:12, 24] = -Kt, Kt
    expect[12, 0:6], expect[12, 6:12] = gd, -gd
    expect[12, 12:18], expect[12, 18:24] = gx, -gx
    expect[12, 24] = gt
    if np.abs(J - expect).max() > STRUCT_TOL * max(1.0, np.abs(J).max()):
        return None
    return Kd, Ke, Kt, gd, gx, gt


# ---- Laplacian eigenvalues of a tree -----------------------------------------------------


def _tree_order(N, edges, root=0):
    """(order, parent): a BFS order from root and each agent's parent (−1 at the root)."""
    src = np.concatenate([edges[:, 0], edges[:, 1]])
    dst = np.concatenate([edges[:, 1], edges[:, 0]])
    by = np.lexsort((dst, src))                    # neighbours of each agent, ascending
    indices = dst[by]
    indptr = np.concatenate([[0], np.cumsum(np.bincount(src, minlength=N))])
    order = np.empty(N, dtype=np.int64)
    parent = np.full(N, -1, dtype=np.int64)
    seen = np.zeros(N, dtype=bool)
    order[0], seen[root], head, tail = root, True, 0, 1
    while head < tail:
        v = order[head]
        head += 1
        for w in indices[indptr[v]:indptr[v + 1]]:
            if not seen[w]:
                seen[w] = True
                parent[w] = v
                order[tail] = w
                tail += 1
    return order, parent


@numba.njit(cache=True, nogil=True)
def _count_below(x, order, parent, deg, a):
    """Number of eigenvalues of L = D − Adj below x (Sylvester's inertia of L − xI, eliminated
    from the leaves up: a tree's LDLᵀ has no fill; a zero pivot is nudged as bisection does)."""
    N = order.shape[0]
    for v in range(N):
        a[v] = deg[v] - x
    count = 0
    for t in range(N - 1, -1, -1):
        v = order[t]
        av = a[v]
        if av == 0.0:
            av = -1e-300
        if av < 0.0:
            count += 1
        p = parent[v]
        if p >= 0:
            a[p] -= 1.0 / av
    return count


@numba.njit(cache=True, nogil=True)
def _bisect_all(order, parent, deg, hi, tol, out):
    N = order.shape[0]
    a = np.empty(N)
    # stack of (lo, hi, count(lo), count(hi))
    slo = np.empty(4 * 64 + N)
    shi = np.empty(4 * 64 + N)
    sclo = np.empty(4 * 64 + N, dtype=np.int64)
    schi = np.empty(4 * 64 + N, dtype=np.int64)
    top = 0
    slo[0] = -1e-3
    shi[0] = hi
    sclo[0] = 0
    schi[0] = N
    top = 1
    while top > 0:
        top -= 1
        lo = slo[top]
        h = shi[top]
        clo = sclo[top]
        chi = schi[top]
        if chi == clo:
            continue
        if h - lo <= tol:
            for k in range(clo, chi):
                out[k] = 0.5 * (lo + h)
            continue
        mid = 0.5 * (lo + h)
        cm = _count_below(mid, order, parent, deg, a)
        slo[top] = lo
        shi[top] = mid
        sclo[top] = clo
        schi[top] = cm
        top += 1
        slo[top] = mid
        shi[top] = h
        sclo[top] = cm
        schi[top] = chi
        top += 1


_LAP_CACHE: dict = {}


def laplacian_eigenvalues(N, edges, rel_tol: float = 1e-13) -> np.ndarray:
    """All N eigenvalues of the tree's Laplacian, ascending (the first is 0). The last graph's
    spectrum is kept: `check` linearises the same graph several times (step, rate, gains)."""
    edges = np.asarray(edges, dtype=np.int64)
    key = (N, rel_tol, edges.tobytes())
    if key in _LAP_CACHE:
        return _LAP_CACHE[key].copy()
    lam = _laplacian_eigenvalues(N, edges, rel_tol)
    _LAP_CACHE.clear()
    _LAP_CACHE[key] = lam
    return lam.copy()


def _laplacian_eigenvalues(N, edges, rel_tol):
    deg = np.bincount(edges.ravel(), minlength=N).astype(float)
    if N <= 400:   # LAPACK is exact and instant here
        L = np.diag(deg)
        L[edges[:, 0], edges[:, 1]] = L[edges[:, 1], edges[:, 0]] = -1.0
        return np.linalg.eigvalsh(L)
    if deg.max() <= 2:   # a path: tridiagonal in path order, LAPACK's stemr does it in O(N²)
        import scipy.linalg
        order, _ = _tree_order(N, edges, root=int(np.argmin(deg)))
        return scipy.linalg.eigvalsh_tridiagonal(deg[order], -np.ones(N - 1))
    order, parent = _tree_order(N, edges)
    hi = 2.0 * deg.max() + 1.0          # Gershgorin
    out = np.empty(N)
    _bisect_all(order, parent, deg, hi, rel_tol * hi, out)
    return np.sort(out)


# ---- the modal path --------------------------------------------------------------------


def _plant_zoh(h, I6inv):
    """(A_d, B_d) of δ̇ = ξ, 𝕀ξ̇ = u under zero-order hold over h (closed form: nilpotent)."""
    Ad = np.eye(12)
    Ad[:6, 6:] = h * np.eye(6)
    Bd = np.vstack([0.5 * h * h * I6inv, h * I6inv])
    return Ad, Bd


def modal_matrices(s, h, blocks, I6inv, k_xi, hybrid=True):
    """Φ_s (len(s), 13, 13) (12 × 12 without θ) for Laplacian eigenvalues s > 0."""
    Kd, Ke, Kt, gd, gx, gt = blocks
    s = np.asarray(s, float)
    sig = np.sqrt(s)
    n = 13 if hybrid else 12
    Ad, Bd = _plant_zoh(h, I6inv)
    Ku = np.zeros((s.size, 6, n))
    Ku[:, :, 0:6] = -s[:, None, None] * Kd
    Ku[:, :, 6:12] = -k_xi * np.eye(6) - s[:, None, None] * Ke
    if hybrid:
        Ku[:, :, 12] = -sig[:, None] * Kt
    Phi = np.zeros((s.size, n, n))
    Phi[:, :12, :] = np.einsum("ab,nbc->nac", Bd, Ku)
    Phi[:, :12, :12] += Ad
    if hybrid:
        Phi[:, 12, 0:6] = h * sig[:, None] * gd
        Phi[:, 12, 6:12] = h * sig[:, None] * gx
        Phi[:, 12, 12] = 1.0 + h * gt
    return Phi


def common_mode_eigenvalues(h, I6inv, k_xi):
    """The mean velocity's six eigenvalues (δ̃ of the common mode gives the six rigid 1's)."""
    return np.linalg.eigvals(np.eye(6) - h * k_xi * I6inv)


class Linearisation:
    """Everything h-independent: the edge Jacobian of the law (a registered name; True / False:
    hybrid / gradient), its own-velocity gain k_xi, whether θ is a state of the loop
    (``hybrid``), and the Laplacian spectrum if modal. ``gains`` replaces the scenario's."""

    def __init__(self, scenario, law="hybrid", gains=None, force_sparse=False, laplacian=None):
        sc = scenario
        self.scenario = sc
        self.law = law_of(law)
        self.gains = gains
        self.N, self.M = sc.graph.n, sc.graph.M
        self.edges = np.ascontiguousarray(sc.graph.edges, dtype=np.int64)
        self.J, self.k_xi, self.hybrid = edge_jacobian(sc, self.law, gains)
        I6 = sc.inertia6
        self.I6inv = np.linalg.inv(I6)
        same = bool(np.all(np.abs(I6 - I6[0]) <= 1e-12 * np.abs(I6[0]).max()))
        self.blocks = modal_blocks(self.J) if same and not force_sparse else None
        self.method = "modal" if self.blocks is not None else "sparse"
        if self.method == "modal":
            lam = laplacian_eigenvalues(self.N, self.edges) if laplacian is None else laplacian
            self.laplacian = lam
            self.s = lam[1:]           # λ_1 = 0 is the common mode
            if self.s.size and self.s[0] <= 1e-12 * max(1.0, lam[-1]):
                raise RuntimeError("graph Laplacian: a second zero eigenvalue (not connected)")

    # -- spectral radius
    def mode_eigenvalues(self, h):
        """(eigenvalues (N−1, n_b), the common mode's six) for the modal path."""
        Phi = modal_matrices(self.s, h, self.blocks, self.I6inv[0], self.k_xi, self.hybrid)
        return np.linalg.eigvals(Phi), common_mode_eigenvalues(h, self.I6inv[0], self.k_xi)

    def spectral_radius(self, h):
        if self.method == "modal":
            lam, com = self.mode_eigenvalues(h)
            r = np.abs(lam).max() if lam.size else 0.0
            return float(max(r, np.abs(com).max()))
        return _sparse_radius(sparse_loop(self, h), self)


def sparse_loop(lin, h, Kfresh=True):
    """Φ (sparse CSR, (12N + M)²): the whole linearised ZOH loop, as `stability.closed_loop`."""
    import scipy.sparse as sp      # only heterogeneous agents need it: 0.1 s off `run`'s start
    N, M, J, E = lin.N, lin.M, lin.J, lin.edges
    Mt = M if lin.hybrid else 0
    n6 = 6 * N
    # controller Jacobian Kx (6N × n): u rows, and G (Mt × n): θ rows
    ip, jn = E[:, 0], E[:, 1]
    Kr, Kc, Kv = [], [], []
    for r_off, who in ((0, ip), (6, jn)):
        for c_off, col0 in ((0, 6 * ip), (6, 6 * jn), (12, n6 + 6 * ip), (18, n6 + 6 * jn)):
            blk = J[r_off:r_off + 6, c_off:c_off + 6]
            rr, cc = np.meshgrid(np.arange(6), np.arange(6), indexing="ij")
            Kr.append((6 * who[:, None] + rr.ravel()).ravel())
            Kc.append((col0[:, None] + cc.ravel()).ravel())
            Kv.append(np.tile(blk.ravel(), M))
        if Mt:
            Kr.append((6 * who[:, None] + np.arange(6)).ravel())
            Kc.append(np.repeat(12 * N + np.arange(M), 6))
            Kv.append(np.tile(J[r_off:r_off + 6, 24], M))
    Kr.append(np.arange(n6))
    Kc.append(n6 + np.arange(n6))
    Kv.append(np.full(n6, -lin.k_xi))
    nx = 12 * N + Mt
    Kx = sp.csr_matrix((np.concatenate(Kv), (np.concatenate(Kr), np.concatenate(Kc))),
                       shape=(n6, nx))
    # per-agent ZOH: B_d = blkdiag over agents
    h2 = 0.5 * h * h
    Binv = sp.block_diag(list(lin.I6inv), format="csr")
    Bd = sp.vstack([h2 * Binv, h * Binv]).tocsr()
    Ad = sp.identity(12 * N, format="csr") + sp.csr_matrix(
        (np.full(n6, h), (np.arange(n6), n6 + np.arange(n6))), shape=(12 * N, 12 * N))
    top = Bd @ Kx
    top = top + sp.hstack([Ad, sp.csr_matrix((12 * N, Mt))])
    if not Mt:
        return top.tocsr()
    gr = np.repeat(np.arange(M), 25)
    gc = np.concatenate([6 * ip[:, None] + np.arange(6), 6 * jn[:, None] + np.arange(6),
                         n6 + 6 * ip[:, None] + np.arange(6), n6 + 6 * jn[:, None] + np.arange(6),
                         12 * N + np.arange(M)[:, None]], axis=1).ravel()
    gv = np.tile(h * J[12, :], M)
    Gm = sp.csr_matrix((gv, (gr, gc)), shape=(M, nx)) + sp.csr_matrix(
        (np.ones(M), (np.arange(M), 12 * N + np.arange(M))), shape=(M, nx))
    return sp.vstack([top, Gm]).tocsr()


def _rigid_basis(N, n):
    """Orthonormal basis of the rigid motion (δ_i = c for all i), (n × 6)."""
    Q = np.zeros((n, 6))
    for a in range(6):
        Q[a:6 * N:6, a] = 1.0 / np.sqrt(N)
    return Q


def _sparse_radius(Phi, lin, k=6):
    """ρ of Φ with the rigid subspace projected out: Q spans ΦQ = Q, so in the basis [Q, Q⊥]
    Φ is block triangular and (I − QQᵀ)Φ(I − QQᵀ) has the remaining eigenvalues (plus six 0)."""
    import scipy.sparse.linalg as sla
    n = Phi.shape[0]
    Q = _rigid_basis(lin.N, n)
    if np.abs(Phi @ Q - Q).max() > 1e-9:
        raise RuntimeError("linearisation: the rigid motion is not invariant under the loop")
    if n <= DENSE_MAX:
        A = Phi.toarray()
        A -= (A @ Q) @ Q.T
        A -= Q @ (Q.T @ A)
        return float(np.abs(interruptible(np.linalg.eigvals, A)).max())

    def mv(x):
        x = np.asarray(x).ravel()
        x = x - Q @ (Q.T @ x)
        y = Phi @ x
        return y - Q @ (Q.T @ y)

    op = sla.LinearOperator((n, n), matvec=mv, dtype=float)
    try:
        lam = sla.eigs(op, k=k, which="LM", tol=1e-13, ncv=max(4 * k, 60), maxiter=20000,
                       return_eigenvectors=False)
    except sla.ArpackNoConvergence as exc:
        raise Se3SyncError(f"stability: ARPACK did not converge on the {n}-state loop of "
                           f"heterogeneous agents ({exc})") from None
    return float(np.abs(lam).max())


def largest_stable_step(stable, h_start: float, rel_tol: float = 0.01) -> float:
    """The largest h with ``stable(h)``, by bracketing from h_start (doubling or halving) and
    bisection to ``rel_tol``; inf above 1000 s, 0 below 1e-12 s."""
    lo = hi = None
    h = h_start
    if stable(h):
        lo = h
        while hi is None:
            h *= 2
            if h > 1e3:
                return float("inf")
            if stable(h):
                lo = h
            else:
                hi = h
    else:
        hi = h
        while lo is None:
            h /= 2
            if h < 1e-12:
                return 0.0
            if stable(h):
                lo = h
            else:
                hi = h
    while hi - lo > rel_tol * lo:
        mid = 0.5 * (lo + hi)
        if stable(mid):
            lo = mid
        else:
            hi = mid
    return float(lo)


def max_stable_step(lin, h_start, rel_tol=0.01):
    """The largest h with ρ < 1 (`largest_stable_step` on this linearisation)."""
    return largest_stable_step(lambda h: lin.spectral_radius(h) < 1.0, h_start, rel_tol)


def spectral_radius_fast(scenario, h=None, law="hybrid"):
    lin = Linearisation(scenario, law)
    return lin.spectral_radius(float(scenario.step if h is None else h))


def analyse_fast(scenario, h=None, law="hybrid", bisect=True, lin=None) -> dict:
    """`stability.analyse` without dense matrices; adds "method"."""
    h = float(scenario.step if h is None else h)
    lin = lin or Linearisation(scenario, law)
    rho = lin.spectral_radius(h)
    out = {"step": h, "spectral_radius": rho, "stable": bool(rho < 1.0), "method": lin.method}
    if bisect:
        out["max_stable_step"] = max_stable_step(lin, h)
    return out
