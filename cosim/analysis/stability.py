"""Sampled-data stability of the zero-order-hold loop, linearised at consensus.

State x = [δ_1..δ_N (6 each), ξ_1..ξ_N (6 each), θ_1..θ_M], X_i = exp(δ_i^), θ = 0, ξ = 0 (θ only
for a law with a θ-like state). Plant (the ad term is quadratic and drops): δ̇ = ξ, 𝕀 ξ̇ = u,
discretised exactly under ZOH with scipy.linalg.expm of [[A, B], [0, 0]]·h. Controller at a
communication point: u_n = K x_n and θ_{n+1} = θ_n + h·G x_n, where K and G come from central
finite differences of the law's own step, the very code the co-simulation runs
(`cosim.analysis.linear`). The rigid motion of the whole group leaves exactly six eigenvalues at
1; they are removed (checked to lie within 1e-6 of 1) and the spectral radius of the rest decides
stability. These dense functions are the reference `stability_sparse` is tested against.
"""
from __future__ import annotations

import numpy as np

from ..threads import analysis as blas_policy
from .linear import law_of, loop_jacobian
from .stability_sparse import analyse_fast, largest_stable_step

__all__ = ["linearise", "closed_loop", "spectral_radius", "max_stable_step", "analyse"]

RIGID_TOL = 1e-6


def linearise(scenario, law="hybrid", eps: float = 1e-6):
    """(K (6N × n_x), G (M × n_x)) with n_x = 12N + M (θ included only if the law has a θ-like
    state); ``law``: a registered law name (True / False: hybrid / gradient)."""
    return loop_jacobian(scenario, law_of(law), eps)


def closed_loop(scenario, h: float, Kx, G) -> np.ndarray:
    sc = scenario
    N = sc.graph.n
    Mt = G.shape[0]
    n6 = 6 * N
    A = np.zeros((12 * N, 12 * N))
    A[:n6, n6:] = np.eye(n6)
    B = np.zeros((12 * N, n6))
    I6 = sc.inertia6
    for i in range(N):
        B[n6 + 6 * i:n6 + 6 * i + 6, 6 * i:6 * i + 6] = np.linalg.inv(I6[i])
    aug = np.zeros((12 * N + n6, 12 * N + n6))
    aug[:12 * N, :12 * N] = A
    aug[:12 * N, 12 * N:] = B
    import scipy.linalg            # the dense reference only; `analyse` does not come here
    E = scipy.linalg.expm(aug * h)
    Ad, Bd = E[:12 * N, :12 * N], E[:12 * N, 12 * N:]
    nx = 12 * N + Mt
    Phi = np.zeros((nx, nx))
    Phi[:12 * N, :] = Bd @ Kx
    Phi[:12 * N, :12 * N] += Ad
    if Mt:
        Phi[12 * N:, :] = h * G
        Phi[12 * N:, 12 * N:] += np.eye(Mt)
    return Phi


def spectral_radius(scenario, h: float, Kx=None, G=None, law="hybrid") -> float:
    if Kx is None:
        Kx, G = linearise(scenario, law)
    lam = np.linalg.eigvals(closed_loop(scenario, h, Kx, G))
    order = np.argsort(np.abs(lam - 1.0))
    rigid, rest = lam[order[:6]], lam[order[6:]]
    worst = float(np.abs(rigid - 1.0).max())
    if worst > RIGID_TOL:
        raise RuntimeError(f"linearisation: the six rigid-motion eigenvalues are not at 1 "
                           f"(largest distance {worst:.3g})")
    return float(np.abs(rest).max()) if rest.size else 0.0


def max_stable_step(scenario, Kx=None, G=None, law="hybrid", rel_tol: float = 0.01,
                    h_start: float = 1e-4) -> float:
    """The largest h with spectral radius < 1, by bracketing and bisection (1 % relative)."""
    if Kx is None:
        Kx, G = linearise(scenario, law)

    return largest_stable_step(lambda h: spectral_radius(scenario, h, Kx, G) < 1.0, h_start,
                               rel_tol)


@blas_policy
def analyse(scenario, h: float | None = None, law="hybrid", bisect: bool = True) -> dict:
    """{"step", "spectral_radius", "stable", "max_stable_step", "method"} for the scenario's h
    (or h), the loop of ``law`` (a registered law name, `cosim.registry.LAWS`; True / False:
    hybrid / gradient). Computed without dense matrices by `stability_sparse` (exact modal
    decoupling when the agents are identical, else a sparse eigensolver); the dense functions
    above are the reference it is tested against."""
    return analyse_fast(scenario, h, law_of(law), bisect)
