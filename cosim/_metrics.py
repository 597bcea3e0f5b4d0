"""Compiled helpers for the slow path of the master (log records and samples).

One call computes, for every edge, ‖I − R̄_k‖_F and ‖p̄_k‖, for every agent the quaternion of
R_i in Foxglove's (x, y, z, w) order, and returns V̄ (U comes from the controller's public
kernel `network_U`, so the per-edge kernel signatures may change freely).
"""
from __future__ import annotations

import math

import numpy as np

from controller._jit import jit


@jit
def metrics(S, edges, U, kX, masses, J, rot_err, pos_err, quat):
    """Fills rot_err, pos_err (M,) and quat (N, 4: x, y, z, w) ; returns (V̄, max|ξ|) with
    V̄ = k_X ΣU + Σ ξᵀ𝕀ξ from U (M,) (computed before by `controller._kernels.network_U`)."""
    N = S.shape[0]
    M = edges.shape[0]
    Rb = np.empty((3, 3))
    pb = np.empty(3)
    usum = 0.0
    for k in range(M):
        i = edges[k, 0]
        j = edges[k, 1]
        # X̄ = X_j⁻¹ X_i: R̄ = R_jᵀ R_i, p̄ = R_jᵀ (p_i − p_j)
        for a in range(3):
            for c in range(3):
                acc = 0.0
                for e in range(3):
                    acc += S[j, 3 + 3 * e + a] * S[i, 3 + 3 * e + c]
                Rb[a, c] = acc
            acc = 0.0
            for e in range(3):
                acc += S[j, 3 + 3 * e + a] * (S[i, e] - S[j, e])
            pb[a] = acc
        acc = 0.0
        for a in range(3):
            for c in range(3):
                x = (1.0 if a == c else 0.0) - Rb[a, c]
                acc += x * x
        rot_err[k] = math.sqrt(acc)
        pos_err[k] = math.sqrt(pb[0] * pb[0] + pb[1] * pb[1] + pb[2] * pb[2])
        usum += U[k]
    kin = 0.0
    ximax = 0.0
    for i in range(N):
        for a in range(6):
            v = abs(S[i, 12 + a])
            if v > ximax:
                ximax = v
        for a in range(3):
            for c in range(3):
                kin += S[i, 12 + a] * J[i, a, c] * S[i, 12 + c]
        for a in range(3):
            kin += masses[i] * S[i, 15 + a] * S[i, 15 + a]
        # quaternion (Shepperd), R row-major at S[i, 3:12]
        r00 = S[i, 3]; r01 = S[i, 4]; r02 = S[i, 5]
        r10 = S[i, 6]; r11 = S[i, 7]; r12 = S[i, 8]
        r20 = S[i, 9]; r21 = S[i, 10]; r22 = S[i, 11]
        tr = r00 + r11 + r22
        if tr >= r00 and tr >= r11 and tr >= r22:
            w = 0.5 * math.sqrt(max(1.0 + tr, 0.0)); s = 0.25 / w
            x = (r21 - r12) * s; y = (r02 - r20) * s; z = (r10 - r01) * s
        elif r00 >= r11 and r00 >= r22:
            x = 0.5 * math.sqrt(max(1.0 + r00 - r11 - r22, 0.0)); s = 0.25 / x
            w = (r21 - r12) * s; y = (r01 + r10) * s; z = (r02 + r20) * s
        elif r11 >= r22:
            y = 0.5 * math.sqrt(max(1.0 - r00 + r11 - r22, 0.0)); s = 0.25 / y
            w = (r02 - r20) * s; x = (r01 + r10) * s; z = (r12 + r21) * s
        else:
            z = 0.5 * math.sqrt(max(1.0 - r00 - r11 + r22, 0.0)); s = 0.25 / z
            w = (r10 - r01) * s; x = (r02 + r20) * s; y = (r12 + r21) * s
        if w < 0.0:
            w = -w; x = -x; y = -y; z = -z
        quat[i, 0] = x
        quat[i, 1] = y
        quat[i, 2] = z
        quat[i, 3] = w
    return kX * usum + kin, ximax
