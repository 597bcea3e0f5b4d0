"""Initial states S0 (N, 18) (`controller.layout`): the scenario's generators and the sweeps'
adversarial starts, written once.

* `paper_state`: the paper's construction, R_i(0) = R_a(∓π/2, v), p_i(0) = (I − R_i(0)) b/d, ξ = 0;
* `random_state`: Haar rotations, positions uniform in a box, velocities uniform in a 6-ball;
* `critical_pose` / `poses_from_relative`: relative poses on the undesired critical points
  X̄ = 𝒯(R_a(π, v), (I − R_a(π, v)) b/d), v an eigenvector of W, turned into absolute poses.
"""
from __future__ import annotations

import math

import numpy as np

from controller import layout, se3

__all__ = ["paper_state", "random_state", "critical_pose", "poses_from_relative",
           "state_from_poses"]


def state_from_poses(X, xi=None) -> np.ndarray:
    return layout.pack_state(X, xi)


def paper_state(N: int, v, weighting) -> np.ndarray:
    """R_i(0) = R_a(−π/2, v) for odd i and R_a(+π/2, v) for even i (1-based), p_i(0) =
    (I − R_i(0)) b/d, ξ(0) = 0 (the paper's Section SIMULATION)."""
    S0 = np.zeros((N, layout.S_WIDTH))
    c = weighting.b / weighting.d
    for i in range(N):
        ang = -math.pi / 2 if (i + 1) % 2 == 1 else math.pi / 2
        R = se3.R_a(ang, v)
        S0[i, layout.P] = c - R @ c
        S0[i, layout.R] = R.ravel()
    return S0


def random_state(rng, N: int, position_box: float, velocity_ball: float) -> np.ndarray:
    """R_i Haar-uniform, p_i uniform in [−box, box]³, ξ_i uniform in the 6-ball of radius
    ``velocity_ball`` (direction Gaussian-normalised, radius ∝ U^(1/6)), drawn in this order."""
    R = se3.random_rotation(rng, N)
    p = rng.uniform(-position_box, position_box, size=(N, 3))
    dirs = rng.standard_normal((N, 6))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    rad = velocity_ball * rng.uniform(0.0, 1.0, size=(N, 1)) ** (1.0 / 6.0)
    S0 = np.zeros((N, layout.S_WIDTH))
    S0[:, layout.P] = p
    S0[:, layout.R] = R.reshape(N, 9)
    S0[:, layout.XI] = dirs * rad
    return S0


def critical_pose(weighting, eigvec: int) -> np.ndarray:
    """X̄ = 𝒯(R_a(π, v), (I − R_a(π, v)) b/d), v the unit eigenvector ``eigvec`` (1..3,
    ascending eigenvalues) of W."""
    v = weighting.eig()[1][:, eigvec - 1]
    # R_a(π, v) = I + sin(π) v^× + 2 (v^×)² = 2vvᵀ − I, written without the rounding of sin(π)
    # ≈ 1.2e-16 (which the unstable critical point amplifies); se3.R_a(π, v) agrees to 1e-15.
    R = 2.0 * np.outer(v, v) - np.eye(3)
    return se3.T(R, (np.eye(3) - R) @ (weighting.b / weighting.d))


def poses_from_relative(graph, Xbar) -> np.ndarray:
    """Absolute poses (N, 4, 4) with X_1 = I and X̄_k = X_j⁻¹ X_i on every edge k = (i, j),
    walking the tree from agent 1."""
    N = graph.n
    X = [None] * N
    X[0] = np.eye(4)
    adj = {a: [] for a in range(N)}
    for k, (i, j) in enumerate(graph.edges):
        adj[int(i)].append((int(j), k, True))    # i known -> X_j = X_i X̄_k⁻¹
        adj[int(j)].append((int(i), k, False))   # j known -> X_i = X_j X̄_k
    stack = [0]
    while stack:
        a = stack.pop()
        for b, k, a_is_pos in adj[a]:
            if X[b] is None:
                X[b] = X[a] @ se3.inverse(Xbar[k]) if a_is_pos else X[a] @ Xbar[k]
                stack.append(b)
    return np.stack(X)
