"""SE(3) toolkit in the paper's vocabulary.

Every function broadcasts over leading batch axes: a vector argument has shape (..., 3) or
(..., 6), a matrix argument (..., 3, 3), (..., 4, 4) or (..., 6, 6). Orientation is a rotation
matrix throughout; quaternions live only at the boundaries (FMU, MAVLink, Foxglove).

Small-angle and near-π branches use series expansions, so exp/log are accurate to ~1e-12 near
the identity and recover the axis near a half turn.
"""
from __future__ import annotations

import math

import numpy as np

from . import _kernels as K

__all__ = [
    "skew", "unskew", "hat", "vee", "psi", "psi_bar", "Ad", "ad", "Ad_inv_T",
    "exp_so3", "log_so3", "exp_se3", "log_se3", "R_a", "T", "inverse", "split",
    "random_rotation", "random_pose", "quat_to_rot", "quat_to_rot_row", "rot_to_quat",
]

# Below this angle the trigonometric coefficients are evaluated by their Taylor series:
# the truncation error at the switch is below 1e-16 and the closed form would lose digits.
_SMALL = 1e-3


def skew(y):
    """y^× with y×z = y^× z."""
    y = np.asarray(y, dtype=float)
    out = np.zeros(y.shape[:-1] + (3, 3))
    out[..., 0, 1] = -y[..., 2]
    out[..., 0, 2] = y[..., 1]
    out[..., 1, 0] = y[..., 2]
    out[..., 1, 2] = -y[..., 0]
    out[..., 2, 0] = -y[..., 1]
    out[..., 2, 1] = y[..., 0]
    return out


def unskew(S):
    """Inverse of `skew` on so(3) (reads the lower triangle)."""
    S = np.asarray(S, dtype=float)
    return np.stack([S[..., 2, 1], S[..., 0, 2], S[..., 1, 0]], axis=-1)


def hat(xi):
    """ξ^ ∈ se(3) for ξ = [ω; v] (`xi_def`)."""
    xi = np.asarray(xi, dtype=float)
    out = np.zeros(xi.shape[:-1] + (4, 4))
    out[..., :3, :3] = skew(xi[..., :3])
    out[..., :3, 3] = xi[..., 3:]
    return out


def vee(X):
    """Inverse of `hat`."""
    X = np.asarray(X, dtype=float)
    return np.concatenate([unskew(X[..., :3, :3]), X[..., :3, 3]], axis=-1)


def psi(A):
    """ψ(A) = ½[a32 − a23, a13 − a31, a21 − a12] (so that ⟨⟨A, y^×⟩⟩ = 2yᵀψ(A))."""
    A = np.asarray(A, dtype=float)
    return 0.5 * np.stack(
        [A[..., 2, 1] - A[..., 1, 2], A[..., 0, 2] - A[..., 2, 0], A[..., 1, 0] - A[..., 0, 1]],
        axis=-1,
    )


def psi_bar(AA):
    """ψ̄(𝔸) = [ψ(A); ½b] for 𝔸 = [[A, b], [cᵀ, d]] (`psiA_def`)."""
    AA = np.asarray(AA, dtype=float)
    return np.concatenate([psi(AA[..., :3, :3]), 0.5 * AA[..., :3, 3]], axis=-1)


def split(X):
    """(R, p) of a pose X = 𝒯(R, p)."""
    X = np.asarray(X, dtype=float)
    return X[..., :3, :3], X[..., :3, 3]


def T(R, p):
    """𝒯(R, p) = [[R, p], [0, 1]]."""
    R = np.asarray(R, dtype=float)
    p = np.asarray(p, dtype=float)
    shape = np.broadcast_shapes(R.shape[:-2], p.shape[:-1])
    out = np.zeros(shape + (4, 4))
    out[..., :3, :3] = R
    out[..., :3, 3] = p
    out[..., 3, 3] = 1.0
    return out


def inverse(X):
    """X⁻¹ = 𝒯(Rᵀ, −Rᵀp), the closed form (assumes RᵀR = I)."""
    R, p = split(X)
    Rt = np.swapaxes(R, -1, -2)
    return T(Rt, -np.einsum("...ij,...j->...i", Rt, p))


def Ad(X):
    """Ad_X = [[R, 0], [p^× R, R]] (`Ad_def`)."""
    R, p = split(X)
    out = np.zeros(R.shape[:-2] + (6, 6))
    out[..., :3, :3] = R
    out[..., 3:, 3:] = R
    out[..., 3:, :3] = skew(p) @ R
    return out


def Ad_inv_T(X):
    """Ad_X^{-T} = [[R, p^× R], [0, R]], formed without inverting a 6×6 matrix."""
    R, p = split(X)
    out = np.zeros(R.shape[:-2] + (6, 6))
    out[..., :3, :3] = R
    out[..., 3:, 3:] = R
    out[..., :3, 3:] = skew(p) @ R
    return out


def ad(xi):
    """ad_ξ = [[ω^×, 0], [v^×, ω^×]] (`ad_def`)."""
    xi = np.asarray(xi, dtype=float)
    out = np.zeros(xi.shape[:-1] + (6, 6))
    W = skew(xi[..., :3])
    out[..., :3, :3] = W
    out[..., 3:, 3:] = W
    out[..., 3:, :3] = skew(xi[..., 3:])
    return out


def _coeffs(theta):
    """A = sinθ/θ, B = (1−cosθ)/θ², C = (θ−sinθ)/θ³.

    B is formed as 2 sin²(θ/2)/θ², which has no cancellation. C's closed form loses ~6ε/θ²
    relative, so below θ = 0.1 it is its Taylor series (truncation < 1e-20 there).
    """
    t = np.asarray(theta, dtype=float)
    t2 = t * t
    tiny = np.abs(t) < _SMALL
    safe = np.where(tiny, 1.0, t)
    A = np.where(tiny, 1 - t2 / 6 + t2 * t2 / 120, np.sin(safe) / safe)
    sh = np.sin(0.5 * safe) / safe
    B = np.where(tiny, 0.5 - t2 / 24 + t2 * t2 / 720, 2 * sh * sh)
    small = np.abs(t) < 0.1
    safe_c = np.where(small, 1.0, t)
    C_series = 1 / 6 - t2 * (1 / 120 - t2 * (1 / 5040 - t2 * (1 / 362880 - t2 * (
        1 / 39916800 - t2 / 6227020800))))
    C = np.where(small, C_series, (safe_c - np.sin(safe_c)) / safe_c**3)
    return A, B, C


def exp_so3(w):
    """exp(ω^×) by Rodrigues' formula."""
    w = np.asarray(w, dtype=float)
    theta = np.linalg.norm(w, axis=-1)
    A, B, _ = _coeffs(theta)
    W = skew(w)
    return np.eye(3) + A[..., None, None] * W + B[..., None, None] * (W @ W)


def R_a(theta, u):
    """ℛ_a(θ, u) = I + sinθ u^× + (1 − cosθ)(u^×)², u a unit axis."""
    theta = np.asarray(theta, dtype=float)
    U = skew(u)
    s = np.sin(theta)[..., None, None]
    c = (1.0 - np.cos(theta))[..., None, None]
    return np.eye(3) + s * U + c * (U @ U)


def log_so3(R):
    """ω with exp(ω^×) = R and ‖ω‖ ≤ π.

    θ comes from atan2(‖ψ(R)‖, (tr R − 1)/2), which keeps full relative precision for small
    angles (arccos does not). Near π the axis is read from the symmetric part of R.
    """
    R = np.asarray(R, dtype=float)
    s_vec = psi(R)  # = sinθ · u
    s = np.linalg.norm(s_vec, axis=-1)
    c = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    theta = np.arctan2(s, c)
    A, _, _ = _coeffs(theta)
    w_generic = s_vec / np.where(A == 0, 1.0, A)[..., None]
    # Near π, sinθ → 0 and ψ(R) carries no direction: use uuᵀ = (R + Rᵀ − 2c I) / (2(1 − c)).
    near_pi = (np.pi - theta) < 1e-2
    if np.any(near_pi):
        S = 0.5 * (R + np.swapaxes(R, -1, -2)) - c[..., None, None] * np.eye(3)
        S = S / np.where(near_pi, 1.0 - c, 1.0)[..., None, None]  # ≈ uuᵀ
        diag = np.diagonal(S, axis1=-2, axis2=-1)
        k = np.argmax(diag, axis=-1)
        col = np.take_along_axis(S, k[..., None, None].repeat(3, axis=-1), axis=-2)[..., 0, :]
        u = col / np.linalg.norm(col, axis=-1, keepdims=True)
        sign = np.where(np.einsum("...i,...i->...", u, s_vec) < 0, -1.0, 1.0)
        w_pi = (sign * theta)[..., None] * u
        w_generic = np.where(near_pi[..., None], w_pi, w_generic)
    return w_generic


def _V(w):
    """Left Jacobian V(ω) = I + B ω^× + C (ω^×)² used by exp on SE(3)."""
    theta = np.linalg.norm(w, axis=-1)
    _, B, C = _coeffs(theta)
    W = skew(w)
    return np.eye(3) + B[..., None, None] * W + C[..., None, None] * (W @ W)


def exp_se3(xi):
    """exp(ξ^) = 𝒯(exp(ω^×), V(ω) v)."""
    xi = np.asarray(xi, dtype=float)
    w, v = xi[..., :3], xi[..., 3:]
    return T(exp_so3(w), np.einsum("...ij,...j->...i", _V(w), v))


def log_se3(X):
    """ξ with exp(ξ^) = X, rotation angle ≤ π."""
    R, p = split(X)
    w = log_so3(R)
    theta = np.linalg.norm(w, axis=-1)
    A, B, _ = _coeffs(theta)
    # V⁻¹ = I − ½ω^× + D (ω^×)², D = (1 − A/(2B))/θ² with series 1/12 + θ²/720 + θ⁴/30240.
    # Below 0.1 rad the closed form cancels (1 − A/2B ≈ θ²/12): use the series of
    # (1 − (θ/2)cot(θ/2))/θ², whose next term is below 1e-20 there.
    t2 = theta * theta
    small = theta < 0.1
    D_series = 1 / 12 + t2 * (1 / 720 + t2 * (1 / 30240 + t2 * (1 / 1209600 + t2 / 47900160)))
    D = np.where(small, D_series,
                 (1 - A / (2 * np.where(B == 0, 1.0, B))) / np.where(small, 1.0, t2))
    W = skew(w)
    Vinv = np.eye(3) - 0.5 * W + D[..., None, None] * (W @ W)
    return np.concatenate([w, np.einsum("...ij,...j->...i", Vinv, p)], axis=-1)


def random_rotation(rng, size=()):
    """Haar-uniform rotations from normalised quaternions (every axis a unit vector)."""
    shape = (size,) if isinstance(size, (int, np.integer)) else tuple(size)
    q = rng.standard_normal(shape + (4,))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return quat_to_rot(q)


def random_pose(rng, size=(), scale=1.0):
    R = random_rotation(rng, size)
    p = scale * rng.standard_normal(R.shape[:-2] + (3,))
    return T(R, p)


def quat_to_rot(q):
    """Rotation matrix of a unit quaternion (w, x, y, z); the quaternion is normalised first."""
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    out = np.empty(q.shape[:-1] + (3, 3))
    out[..., 0, 0] = 1 - 2 * (y * y + z * z)
    out[..., 0, 1] = 2 * (x * y - w * z)
    out[..., 0, 2] = 2 * (x * z + w * y)
    out[..., 1, 0] = 2 * (x * y + w * z)
    out[..., 1, 1] = 1 - 2 * (x * x + z * z)
    out[..., 1, 2] = 2 * (y * z - w * x)
    out[..., 2, 0] = 2 * (x * z - w * y)
    out[..., 2, 1] = 2 * (y * z + w * x)
    out[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return out


def quat_to_rot_row(w, x, y, z) -> list:
    """`quat_to_rot` of one quaternion as a row-major list of 9 Python floats, the same operations
    in the same order, so the same bits. For per-packet paths: numpy costs ~2 µs per operation on
    a one-element array."""
    n = math.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    return [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]


def rot_to_quat(R):
    """Unit quaternion (w, x, y, z), w ≥ 0, of a rotation matrix (Shepperd's method).

    One implementation for the whole project (`controller.kernels.rot_to_quat_rows`): the plant's
    initial orientation, the logs and the MAVLink boundary all convert with it."""
    R = np.asarray(R, dtype=float)
    flat = np.ascontiguousarray(R.reshape(-1, 9))
    out = np.empty((flat.shape[0], 4))
    K.rot_to_quat_rows(flat, out)
    return out.reshape(R.shape[:-2] + (4,))
