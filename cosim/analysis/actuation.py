"""Stability of the loop whose plant applies each wrench d_a steps late (`simulation.actuation_delay`).

What it models: `cosim.plants.DelayedActuation`, the loop a Jacobi FMI master runs with d_a = 1
(docs/fmi-system.md): over [t_n, t_{n+1}] the plant applies u(n − d_a), while θ's flow is the
controller's own and is not delayed. With the [network] delay d of `delay_margin` as well
(neighbour data d steps old), linearised at consensus, with the parts of
`delay_margin.delayed_parts` (Φ₀ = P + B_u K₀, Φ_d = B C, C = [K_d; G_d]):

    s(n+1) = P s(n) + B_u u(n − d_a) + B_θ G_d s(n − d),    u(n) = K₀ s(n) + K_d s(n − d)

where B_u = B's wrench columns (the ZOH plant's input) and B_θ = B's θ columns (h I). The state
is z = (s(n), w(n−1), …, w(n−d), u(n−1), …, u(n−d_a)) with w = C s: 12N + M + d(6N + M) +
6N·d_a states. With d_a = 0 it is `delay_margin.augmented`. The rigid motion's six eigenvalues
1 are projected out before the spectral radius is taken, as there.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..signals import interruptible
from ..threads import analysis as blas_policy
from .delay_margin import DENSE_MAX, augmented, delayed_parts
from .stability_sparse import Linearisation, largest_stable_step

__all__ = ["actuated_loop", "actuation_radius", "actuation_check", "states"]


def actuated_loop(lin: Linearisation, h: float, d: int, d_a: int):
    """(A, Q): the loop on z (sparse CSR) and an orthonormal basis Q of its rigid motion."""
    Phi0, B, C, K0 = delayed_parts(lin, h, fresh_wrench=True)
    N = lin.N
    n6 = 6 * N
    n, m = Phi0.shape[0], C.shape[0]
    S = np.zeros((n, 6))                  # the rigid motion: every δ_i the same
    for a in range(6):
        S[a:n6:6, a] = 1.0
    if d_a == 0:
        A = augmented(Phi0, B, C, d)
        Q = np.vstack([S] + [C @ S] * d)
        return A, np.linalg.qr(Q)[0]
    Bu, Bth = B[:, :n6], B[:, n6:]
    Kd, Gd = C[:n6], C[n6:]
    P = (Phi0 - Bu @ K0).tocsr()
    # slots: 0 = s, 1..d = w(n−1..n−d), d+1..d+d_a = u(n−1..n−d_a)
    k = 1 + d + d_a
    blocks = [[None] * k for _ in range(k)]
    size = [n] + [m] * d + [n6] * d_a
    blocks[0][0] = P
    blocks[0][d + d_a] = Bu                      # u(n − d_a) drives the plant
    if d == 0:
        if Bth.shape[1]:
            blocks[0][0] = (P + Bth @ Gd).tocsr()   # θ's flow with everyone's data fresh
        blocks[1][0] = (K0 + Kd).tocsr()        # u(n), into the slot u(n−1) at n+1
    else:
        if Bth.shape[1]:
            blocks[0][d] = sp.hstack([sp.csr_matrix((n, n6)), Bth]).tocsr()   # G_d s(n−d)
        blocks[1][0] = C
        for j in range(2, d + 1):
            blocks[j][j - 1] = sp.identity(m, format="csr")
        # u(n) = K₀ s(n) + K_d s(n − d), K_d s(n − d) being the wrench rows of w(n − d)
        blocks[d + 1][0] = K0
        blocks[d + 1][d] = sp.hstack([sp.identity(n6), sp.csr_matrix((n6, m - n6))]).tocsr()
    for j in range(d + 2, k):
        blocks[j][j - 1] = sp.identity(n6, format="csr")
    for j in range(k):                            # every block row's and column's shape defined
        if blocks[j][j] is None:
            blocks[j][j] = sp.csr_matrix((size[j], size[j]))
    A = sp.bmat(blocks, format="csr")
    U = (K0 + Kd) @ S                             # the wrench at a rigid displacement
    Q = np.vstack([S] + [C @ S] * d + [U] * d_a)
    return A, np.linalg.qr(Q)[0]


def actuation_radius(lin: Linearisation, h: float, d: int, d_a: int) -> float:
    """Spectral radius of the loop with d steps of network delay and d_a of actuation delay,
    without the rigid motion's six eigenvalues 1 (LAPACK on the whole matrix: up to
    `DENSE_MAX` states)."""
    A, Q = actuated_loop(lin, h, d, d_a)
    if np.abs(A @ Q - Q).max() > 1e-9:
        raise RuntimeError("actuation delay: the rigid motion is not invariant")
    D = A.toarray()
    D -= (D @ Q) @ Q.T
    D -= Q @ (Q.T @ D)
    return float(np.abs(interruptible(np.linalg.eigvals, D)).max())


def states(lin: Linearisation, d: int, d_a: int) -> int:
    """The size of z."""
    n6 = 6 * lin.N
    m = n6 + (lin.M if lin.hybrid else 0)
    return 12 * lin.N + (lin.M if lin.hybrid else 0) + d * m + d_a * n6


@blas_policy
def actuation_check(scenario, law="hybrid", bisect: bool = True) -> dict | None:
    """The scenario's loop with its ``simulation.actuation_delay`` d_a and its [network]
    table's worst-case delay d (steps): {"actuation_delay_steps", "network_delay_steps",
    "spectral_radius", "stable", "max_stable_step", "method"}; None when d_a = 0.
    "max_stable_step" (``bisect``) is the largest h stable with d_a steps of actuation delay,
    found without network delay only (None with one: its steps change with h). Above
    `DENSE_MAX` states "method" says so and the radius is None."""
    d_a = int(getattr(scenario, "actuation_delay", 0))
    if d_a <= 0:
        return None
    net = scenario.tables.get("network")
    h = float(scenario.step)
    lin = Linearisation(scenario, law, force_sparse=True)
    d = net.worst_delay(scenario.graph, h)[0] if net is not None else 0
    out = {"actuation_delay_steps": d_a, "network_delay_steps": d, "spectral_radius": None,
           "stable": None, "max_stable_step": None}
    size = states(lin, d, d_a)
    if size > DENSE_MAX:
        out["method"] = (f"not computed: {size} states > {DENSE_MAX} (the loop with the delays, "
                         "dense)")
        return out
    rho = actuation_radius(lin, h, d, d_a)
    out.update(spectral_radius=rho, stable=bool(rho < 1.0),
               method=f"dense, {size} states (the loop with its delayed wrenches)")
    if bisect and d == 0:
        out["max_stable_step"] = largest_stable_step(
            lambda hh: actuation_radius(lin, hh, 0, d_a) < 1.0, h, 0.01)
    return out

