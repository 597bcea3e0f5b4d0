"""Frame conventions at the MAVLink boundary, with exact (sign-permutation) conversions.

MAVLink speaks NED (world) and FRD (body). A scenario's world frame is either

* ``"ned"``: identical to MAVLink's (world NED, body FRD): every conversion is the identity;
* ``"enu"``: world ENU (x east, y north, z up), body FLU (x forward, y left, z up).

ENU -> NED is ``P_W = [[0,1,0],[1,0,0],[0,0,-1]]`` and FLU -> FRD is ``P_B = diag(1,-1,-1)``;
both are proper rotations whose entries are 0 and ±1, so applying them only permutes and negates
numbers: the conversions are exact in floating point and lockstep runs stay bit-faithful.

    p_ned = P_W p_enu,   R_ned_frd = P_W R_enu_flu P_B,   ξ_frd = P_B ξ_flu,   u_frd = P_B u_flu.

The quaternion helpers below spell out every operation in a fixed order (no BLAS, no reductions
whose order could depend on the batch size), so the vehicle (one body at a time) and the
reference co-simulation (all bodies at once) round identically.
"""
from __future__ import annotations

import numpy as np

from controller import layout
from controller.se3 import quat_to_rot as _q2r
from controller.se3 import quat_to_rot_row
from controller.se3 import rot_to_quat as _r2q

P_W = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
P_B = np.diag([1.0, -1.0, -1.0])

WORLD_FRAMES = ("ned", "enu")


def quat_to_rot(q: np.ndarray) -> np.ndarray:
    """(n,4) quaternions (w, x, y, z), normalised here, -> (n,9) row-major rotation matrices
    (`controller.se3.quat_to_rot`; one row through its scalar form, the same bits)."""
    q = np.asarray(q, dtype=np.float64)
    if q.shape[0] == 1:   # one vehicle or one neighbour per call
        return np.array([quat_to_rot_row(*q[0].tolist())])
    return _q2r(q).reshape(q.shape[0], 9)


def quat_norm_error(q: np.ndarray) -> np.ndarray:
    """| ‖q‖ − 1 | per row."""
    q = np.asarray(q, dtype=np.float64)
    return np.abs(np.sqrt(q[:, 0] * q[:, 0] + q[:, 1] * q[:, 1] + q[:, 2] * q[:, 2]
                          + q[:, 3] * q[:, 3]) - 1.0)


def rot_to_quat(R9: np.ndarray) -> np.ndarray:
    """(n,9) row-major rotation matrices -> (n,4) unit quaternions (w first, w >= 0)."""
    R9 = np.asarray(R9, dtype=np.float64)
    return _r2q(R9.reshape(-1, 3, 3))


# ---------------------------------------------------------------- scenario <-> MAVLink frames
def world_to_ned_p(p: np.ndarray, world: str) -> np.ndarray:
    """(n,3) positions (or world-frame vectors) from the scenario world to NED."""
    p = np.asarray(p, dtype=np.float64)
    if world == "ned":
        return p.copy()
    return np.stack([p[:, 1], p[:, 0], -p[:, 2]], axis=1)


def ned_to_world_p(p: np.ndarray, world: str) -> np.ndarray:
    p = np.asarray(p, dtype=np.float64)
    if world == "ned":
        return p.copy()
    return np.stack([p[:, 1], p[:, 0], -p[:, 2]], axis=1)  # P_W is its own inverse


def body_to_frd(v: np.ndarray, world: str) -> np.ndarray:
    """(n,3k) body vectors (ξ, u: groups of 3) from the scenario body frame to FRD."""
    v = np.asarray(v, dtype=np.float64)
    if world == "ned":
        return v.copy()
    out = v.copy()
    for g in range(v.shape[1] // 3):
        out[:, 3 * g + 1] = -v[:, 3 * g + 1]
        out[:, 3 * g + 2] = -v[:, 3 * g + 2]
    return out


frd_to_body = body_to_frd  # P_B is its own inverse


def rot_world_to_ned(R9: np.ndarray, world: str) -> np.ndarray:
    """(n,9) R (scenario body -> scenario world) to R_ned_frd = P_W R P_B (exact)."""
    R9 = np.asarray(R9, dtype=np.float64)
    if world == "ned":
        return R9.copy()
    R = R9.reshape(-1, 3, 3)
    # P_W R: rows (r1, r0, -r2); then · P_B: columns (c0, -c1, -c2)
    M = np.stack([R[:, 1], R[:, 0], -R[:, 2]], axis=1)
    M[:, :, 1] = -M[:, :, 1]
    M[:, :, 2] = -M[:, :, 2]
    return M.reshape(-1, 9)


rot_ned_to_world = rot_world_to_ned  # P_W and P_B are involutions


def state_world_to_ned(S: np.ndarray, world: str) -> np.ndarray:
    """(n,18) [p, R, ξ] in the scenario frames -> NED/FRD (exact)."""
    S = np.asarray(S, dtype=np.float64)
    out = np.empty_like(S)
    out[:, layout.P] = world_to_ned_p(S[:, layout.P], world)
    out[:, layout.R] = rot_world_to_ned(S[:, layout.R], world)
    out[:, layout.XI] = body_to_frd(S[:, layout.XI], world)
    return out


state_ned_to_world = state_world_to_ned  # involution
