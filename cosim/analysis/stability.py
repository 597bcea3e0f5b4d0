"""Sampled-data stability of the zero-order-hold loop, linearised at consensus.

State x = [δ_1..δ_N (6 each), ξ_1..ξ_N (6 each), θ_1..θ_M], X_i = exp(δ_i^), θ = 0, ξ = 0.
Plant (the ad term is quadratic and drops): δ̇ = ξ, 𝕀 ξ̇ = u, discretised exactly under ZOH
with scipy.linalg.expm of [[A, B], [0, 0]]·h. Controller at a communication point: u_n = K x_n
and θ_{n+1} = θ_n + h·G x_n, where K and G (the linearised −k_θ∇_θU) come from central finite
differences of the very kernel the co-simulation runs (`controller.kernels.network_step`).
The rigid motion of the whole group leaves exactly six eigenvalues at 1; they are removed
(checked to lie within 1e-6 of 1) and the spectral radius of the rest decides stability.
"""
from __future__ import annotations

import numpy as np

from controller import LawParameters, se3
from controller.layout import pack_state
from controller.kernels import network_step

from ..controllers import make_controller
from .stability_sparse import analyse_fast, largest_stable_step

__all__ = ["linearise", "closed_loop", "spectral_radius", "max_stable_step", "analyse"]

RIGID_TOL = 1e-6


def _S_of(x, N):
    d = x[:6 * N].reshape(N, 6)
    xi = x[6 * N:12 * N].reshape(N, 6)
    X = se3.exp_se3(d)
    return pack_state(X, xi)


def linearise(scenario, hybrid: bool = True, eps: float = 1e-6):
    """(K (6N × n_x), G (M × n_x)) with n_x = 12N + M (θ included only if hybrid)."""
    sc = scenario
    N, M = sc.graph.n, sc.graph.M
    # δ = ∞: no jump may fire while linearising (at consensus μ_U < 0 < δ anyway)
    P = LawParameters.of(sc.weighting, sc.design, sc.gains, delta=np.inf).P
    edges = np.ascontiguousarray(sc.graph.edges)
    Mt = M if hybrid else 0
    nx = 12 * N + Mt
    u = np.zeros((N, 6))
    mu = np.zeros(M)
    jumped = np.zeros(M, dtype=np.bool_)
    tp = np.zeros(M)
    tj = np.zeros(M)

    def f(x):
        S = _S_of(x, N)
        th = np.zeros(M)
        if hybrid:
            th[:] = x[12 * N:]
        network_step(S, th, edges, P, 1.0, hybrid, u, mu, jumped, tp, tj)
        # with h = 1 the flow gives θ⁺ − θ = −k_θ∇_θU
        return np.concatenate([u.ravel(), (th - x[12 * N:]) if hybrid else np.zeros(0)])

    Kx = np.zeros((6 * N, nx))
    G = np.zeros((Mt, nx))
    for c in range(nx):
        e = np.zeros(nx)
        e[c] = eps
        col = (f(e) - f(-e)) / (2 * eps)
        Kx[:, c] = col[:6 * N]
        G[:, c] = col[6 * N:]
    return Kx, G


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


def spectral_radius(scenario, h: float, Kx=None, G=None, hybrid: bool = True) -> float:
    if Kx is None:
        Kx, G = linearise(scenario, hybrid)
    lam = np.linalg.eigvals(closed_loop(scenario, h, Kx, G))
    order = np.argsort(np.abs(lam - 1.0))
    rigid, rest = lam[order[:6]], lam[order[6:]]
    worst = float(np.abs(rigid - 1.0).max())
    if worst > RIGID_TOL:
        raise RuntimeError(f"linearisation: the six rigid-motion eigenvalues are not at 1 "
                           f"(largest distance {worst:.3g})")
    return float(np.abs(rest).max()) if rest.size else 0.0


def max_stable_step(scenario, Kx=None, G=None, hybrid: bool = True, rel_tol: float = 0.01,
                    h_start: float = 1e-4) -> float:
    """The largest h with spectral radius < 1, by bracketing and bisection (1 % relative)."""
    if Kx is None:
        Kx, G = linearise(scenario, hybrid)

    return largest_stable_step(lambda h: spectral_radius(scenario, h, Kx, G) < 1.0, h_start,
                               rel_tol)


def analyse(scenario, h: float | None = None, hybrid: bool = True, bisect: bool = True,
            law: str | None = None) -> dict:
    """{"step", "spectral_radius", "stable", "max_stable_step", "method"} for the scenario's h
    (or h). ``law``: a registered law name (`cosim.controllers.LAWS`); it decides ``hybrid``
    (whether θ is a state of the loop). Computed without dense matrices by `stability_sparse`
    (exact modal decoupling when the agents are identical, else a sparse eigensolver); the
    dense functions above are the reference it is tested against."""
    if law is not None:
        hybrid = make_controller(law, scenario).hybrid
    return analyse_fast(scenario, h, hybrid, bisect)
