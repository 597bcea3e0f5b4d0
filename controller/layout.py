"""The state row shared by the controller, the plant FMU and the logs: one row per agent.

    S[i] = [p (3), R row-major (9), ξ = [ω; v] (6)]        S has shape (N, 18)

p is the position in the world frame, R the rotation body → world, ξ the body-frame velocity
(`eqn:kinematic`). The plant FMU returns exactly this block (`plant_fmu.layout` builds its value
references from these offsets), and every kernel reads it, so the layout is defined here once.
"""
from __future__ import annotations

import numpy as np

__all__ = ["S_P", "S_R", "S_XI", "S_OMEGA", "S_V", "S_WIDTH", "P", "R", "XI", "OMEGA", "V",
           "positions", "rotations", "velocities", "pack_state", "poses"]

S_P = 0        # p, 3 values
S_R = 3        # R, 9 values, row-major
S_XI = 12      # ξ = [ω; v], 6 values
S_OMEGA = 12
S_V = 15
S_WIDTH = 18

P = slice(S_P, S_P + 3)
R = slice(S_R, S_R + 9)
XI = slice(S_XI, S_XI + 6)
OMEGA = slice(S_OMEGA, S_OMEGA + 3)
V = slice(S_V, S_V + 3)


def positions(S) -> np.ndarray:
    """(..., 3) positions (a view)."""
    return S[..., P]


def rotations(S) -> np.ndarray:
    """(..., 3, 3) rotation matrices (a view when S is contiguous)."""
    S = np.asarray(S)
    return S[..., R].reshape(S.shape[:-1] + (3, 3))


def velocities(S) -> np.ndarray:
    """(..., 6) body velocities ξ = [ω; v] (a view)."""
    return S[..., XI]


def pack_state(X, xi=None) -> np.ndarray:
    """S (N, 18) from poses X (N, 4, 4) and velocities ξ (N, 6) (zeros if None)."""
    X = np.asarray(X, float)
    N = X.shape[0]
    S = np.zeros((N, S_WIDTH))
    S[:, P] = X[:, :3, 3]
    S[:, R] = X[:, :3, :3].reshape(N, 9)
    if xi is not None:
        S[:, XI] = np.asarray(xi, float)
    return S


def poses(S) -> np.ndarray:
    """(N, 4, 4) homogeneous poses of the rows of S."""
    S = np.asarray(S, float)
    X = np.zeros(S.shape[:-1] + (4, 4))
    X[..., :3, :3] = rotations(S)
    X[..., :3, 3] = positions(S)
    X[..., 3, 3] = 1.0
    return X
