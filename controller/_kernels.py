"""Per-edge mathematics of the hybrid law as scalar loops (compiled by numba, or plain Python).

This is the single implementation of U, μ_U, ψ̄_∇, ∇_θU, the jump map and the control law.
The network view, the per-agent view and the public functions in `potential` all call it.

State layout, one row per agent, matching the plant FMU's output block:
    S[i] = [p (3), R row-major (9), ξ = [ω; v] (6)]            (N, 18)
Parameter vector P (see `pack`): the weighting matrix, the synergy design and the gains,
with W R_a(θ_j)ᵀ precomputed for every θ_j ∈ Θ so that a candidate costs nine products.
"""
from __future__ import annotations

import math

import numpy as np

from ._jit import jit

P_A = 0        # A, 9 values row-major
P_B = 9        # b, 3
P_D = 12       # d
P_W = 13       # W = A − bbᵀ/d, 9
P_UC1 = 22     # u_c1, 3
P_UC2 = 25     # u_c2, 3
P_GAMMA = 28
P_DELTA = 29
P_TRW = 30
P_KX = 31
P_KXI = 32
P_KE = 33
P_KTH = 34
P_C = 35       # c = b/d, 3 (so that no edge divides)
P_M = 38       # m = |Θ|
P_THETA = 39   # Θ (m), then K_j = W R_a(θ_j)ᵀ (9 m), then γθ_j²/2 (m)

S_P = 0
S_R = 3
S_XI = 12
S_WIDTH = 18


def pack(A, b, d, u_c1, u_c2, gamma, delta, Theta, k_X, k_xi, k_e, k_theta):
    """Build the parameter vector P read by every kernel."""
    A = np.asarray(A, float)
    b = np.asarray(b, float)
    W = A - np.outer(b, b) / d
    Theta = np.asarray(Theta, float).ravel()
    m = Theta.size
    P = np.zeros(P_THETA + 11 * m)
    P[P_A:P_A + 9] = A.ravel()
    P[P_B:P_B + 3] = b
    P[P_D] = d
    P[P_W:P_W + 9] = W.ravel()
    P[P_UC1:P_UC1 + 3] = u_c1
    P[P_UC2:P_UC2 + 3] = u_c2
    P[P_GAMMA] = gamma
    P[P_DELTA] = delta
    P[P_TRW] = np.trace(W)
    P[P_KX], P[P_KXI], P[P_KE], P[P_KTH] = k_X, k_xi, k_e, k_theta
    P[P_C:P_C + 3] = b / d
    P[P_M] = m
    P[P_THETA:P_THETA + m] = Theta
    Ra = np.empty((3, 3))
    for j, th in enumerate(Theta):
        rot_axis_angle(th, u_c1[0], u_c1[1], u_c1[2], Ra)
        P[P_THETA + m + 9 * j:P_THETA + m + 9 * (j + 1)] = (W @ Ra.T).ravel()
        P[P_THETA + 10 * m + j] = 0.5 * gamma * th * th
    return P


@jit(inline=True)
def rot_axis_angle(theta, u0, u1, u2, Ra):
    """ℛ_a(θ, u) = I + sinθ u^× + (1 − cosθ)(u^×)² into Ra; (u^×)² = uuᵀ − I for unit u."""
    sh = math.sin(0.5 * theta)
    ch = math.cos(0.5 * theta)
    s = 2.0 * sh * ch
    c1 = 2.0 * sh * sh  # 1 − cosθ without cancellation
    Ra[0, 0] = 1.0 + c1 * (u0 * u0 - 1.0)
    Ra[0, 1] = -s * u2 + c1 * u0 * u1
    Ra[0, 2] = s * u1 + c1 * u0 * u2
    Ra[1, 0] = s * u2 + c1 * u1 * u0
    Ra[1, 1] = 1.0 + c1 * (u1 * u1 - 1.0)
    Ra[1, 2] = -s * u0 + c1 * u1 * u2
    Ra[2, 0] = -s * u1 + c1 * u2 * u0
    Ra[2, 1] = s * u0 + c1 * u2 * u1
    Ra[2, 2] = 1.0 + c1 * (u2 * u2 - 1.0)


@jit(inline=True)
def rel_pose(S, i, j, Rb, pb):
    """X̄ = X_j⁻¹ X_i: R̄ = R_jᵀ R_i, p̄ = R_jᵀ (p_i − p_j)."""
    for a in range(3):
        for c in range(3):
            acc = 0.0
            for e in range(3):
                acc += S[j, S_R + 3 * e + a] * S[i, S_R + 3 * e + c]
            Rb[a, c] = acc
    for a in range(3):
        acc = 0.0
        for e in range(3):
            acc += S[j, S_R + 3 * e + a] * (S[i, S_P + e] - S[j, S_P + e])
        pb[a] = acc


@jit(inline=True)
def mat_mul3(X, Y, out):
    """out = X Y for 3×3 arrays."""
    for a in range(3):
        x0 = X[a, 0]
        x1 = X[a, 1]
        x2 = X[a, 2]
        out[a, 0] = x0 * Y[0, 0] + x1 * Y[1, 0] + x2 * Y[2, 0]
        out[a, 1] = x0 * Y[0, 1] + x1 * Y[1, 1] + x2 * Y[2, 1]
        out[a, 2] = x0 * Y[0, 2] + x1 * Y[1, 2] + x2 * Y[2, 2]


@jit(inline=True)
def prepare(Rb, theta, P, Ra, Rg):
    """R_a = ℛ_a(θ, u_c1) and R_g = R̄ R_a, the rotation of Γ = X̄ 𝒯_uc(θ): shared by μ_U,
    U and the gradients so that each edge evaluates sin and cos once."""
    rot_axis_angle(theta, P[P_UC1], P[P_UC1 + 1], P[P_UC1 + 2], Ra)
    mat_mul3(Rb, Ra, Rg)


@jit(inline=True)
def _trace_W(P, Rg):
    """tr(W R_g) (W symmetric)."""
    acc = 0.0
    for a in range(3):
        for c in range(3):
            acc += P[P_W + 3 * a + c] * Rg[a, c]
    return acc


@jit(inline=True)
def U_core(Rb, pb, theta, P, Rg):
    """U(X̄, θ) by `U_explicit`: tr(W(I − R̄ℛ_a)) + γθ²/2 + d/2‖p̄ − (I − R̄)b/d‖²."""
    e2 = 0.0
    for a in range(3):
        ea = pb[a] - P[P_C + a] + Rb[a, 0] * P[P_C] + Rb[a, 1] * P[P_C + 1] + Rb[a, 2] * P[P_C + 2]
        e2 += ea * ea
    return P[P_TRW] - _trace_W(P, Rg) + 0.5 * P[P_GAMMA] * theta * theta + 0.5 * P[P_D] * e2


@jit(inline=True)
def mu_core(Rb, theta, P, Rg):
    """(μ_U, j*) with μ_U = U(X̄, θ) − min_{θ'∈Θ} U(X̄, θ') (`mu_U_def`) and j* the index of
    the minimiser in Θ (`eqn: gtheta`).

    Terms of U that do not depend on θ cancel in μ_U and are left out. Ties go to the first
    element of Θ: a later candidate must be lower by more than rounding to win.
    """
    s_cur = -_trace_W(P, Rg) + 0.5 * P[P_GAMMA] * theta * theta
    m = int(P[P_M])
    best = 0.0
    jstar = 0
    for j in range(m):
        off = P_THETA + m + 9 * j
        acc = 0.0
        for a in range(3):
            for c in range(3):
                acc += Rb[a, c] * P[off + 3 * a + c]
        s_j = -acc + P[P_THETA + 10 * m + j]
        if j == 0 or s_j < best - 1e-12 * (1.0 + abs(best)):
            best = s_j
            jstar = j
    return s_cur - best, jstar


@jit(inline=True)
def gradient_core(Rb, pb, theta, P, Ra, Rg, g):
    """ψ̄_∇(X̄, θ) (`st_b`) into g (6,); returns ∇_θU(X̄, θ) (`st_c`).

    With Γ = X̄ 𝒯_uc(θ) = 𝒯(R_g, p_g), c = b/d and q = R_gᵀp_g = R_aᵀ(c + R̄ᵀp̄) − c:
        ψ̄((I − Γ⁻¹)𝔸) = [−ψ(R_gᵀA) + ½ b×q ;  ½(b − R_gᵀb + d q)]  =: [a; w]
        ψ̄_∇ = Ad⁻ᵀ_{𝒯_uc(θ)} [a; w] = [R_a a + p_T × (R_a w); R_a w],  p_T = (I − R_a)c
        ∇_θU = γθ + 2 (u_c1·a + u_c2·w)
    """
    d = P[P_D]
    b0 = P[P_B]
    b1 = P[P_B + 1]
    b2 = P[P_B + 2]
    c0 = P[P_C]
    c1 = P[P_C + 1]
    c2 = P[P_C + 2]
    # y = c + R̄ᵀ p̄
    y0 = c0 + Rb[0, 0] * pb[0] + Rb[1, 0] * pb[1] + Rb[2, 0] * pb[2]
    y1 = c1 + Rb[0, 1] * pb[0] + Rb[1, 1] * pb[1] + Rb[2, 1] * pb[2]
    y2 = c2 + Rb[0, 2] * pb[0] + Rb[1, 2] * pb[1] + Rb[2, 2] * pb[2]
    # q = R_aᵀ y − c
    q0 = Ra[0, 0] * y0 + Ra[1, 0] * y1 + Ra[2, 0] * y2 - c0
    q1 = Ra[0, 1] * y0 + Ra[1, 1] * y1 + Ra[2, 1] * y2 - c1
    q2 = Ra[0, 2] * y0 + Ra[1, 2] * y1 + Ra[2, 2] * y2 - c2
    A00 = P[P_A]
    A01 = P[P_A + 1]
    A02 = P[P_A + 2]
    A11 = P[P_A + 4]
    A12 = P[P_A + 5]
    A22 = P[P_A + 8]
    # M = R_gᵀ A, M[r, s] = Σ_e R_g[e, r] A[e, s]; ψ(M) needs six entries
    M21 = Rg[0, 2] * A01 + Rg[1, 2] * A11 + Rg[2, 2] * A12
    M12 = Rg[0, 1] * A02 + Rg[1, 1] * A12 + Rg[2, 1] * A22
    M02 = Rg[0, 0] * A02 + Rg[1, 0] * A12 + Rg[2, 0] * A22
    M20 = Rg[0, 2] * A00 + Rg[1, 2] * A01 + Rg[2, 2] * A02
    M10 = Rg[0, 1] * A00 + Rg[1, 1] * A01 + Rg[2, 1] * A02
    M01 = Rg[0, 0] * A01 + Rg[1, 0] * A11 + Rg[2, 0] * A12
    a0 = -0.5 * (M21 - M12) + 0.5 * (b1 * q2 - b2 * q1)
    a1 = -0.5 * (M02 - M20) + 0.5 * (b2 * q0 - b0 * q2)
    a2 = -0.5 * (M10 - M01) + 0.5 * (b0 * q1 - b1 * q0)
    # R_gᵀ b
    r0 = Rg[0, 0] * b0 + Rg[1, 0] * b1 + Rg[2, 0] * b2
    r1 = Rg[0, 1] * b0 + Rg[1, 1] * b1 + Rg[2, 1] * b2
    r2 = Rg[0, 2] * b0 + Rg[1, 2] * b1 + Rg[2, 2] * b2
    w0 = 0.5 * (b0 - r0 + d * q0)
    w1 = 0.5 * (b1 - r1 + d * q1)
    w2 = 0.5 * (b2 - r2 + d * q2)
    # R_a w and R_a a
    rw0 = Ra[0, 0] * w0 + Ra[0, 1] * w1 + Ra[0, 2] * w2
    rw1 = Ra[1, 0] * w0 + Ra[1, 1] * w1 + Ra[1, 2] * w2
    rw2 = Ra[2, 0] * w0 + Ra[2, 1] * w1 + Ra[2, 2] * w2
    ra0 = Ra[0, 0] * a0 + Ra[0, 1] * a1 + Ra[0, 2] * a2
    ra1 = Ra[1, 0] * a0 + Ra[1, 1] * a1 + Ra[1, 2] * a2
    ra2 = Ra[2, 0] * a0 + Ra[2, 1] * a1 + Ra[2, 2] * a2
    # p_T = c − R_a c
    pt0 = c0 - (Ra[0, 0] * c0 + Ra[0, 1] * c1 + Ra[0, 2] * c2)
    pt1 = c1 - (Ra[1, 0] * c0 + Ra[1, 1] * c1 + Ra[1, 2] * c2)
    pt2 = c2 - (Ra[2, 0] * c0 + Ra[2, 1] * c1 + Ra[2, 2] * c2)
    g[0] = ra0 + pt1 * rw2 - pt2 * rw1
    g[1] = ra1 + pt2 * rw0 - pt0 * rw2
    g[2] = ra2 + pt0 * rw1 - pt1 * rw0
    g[3] = rw0
    g[4] = rw1
    g[5] = rw2
    return P[P_GAMMA] * theta + 2.0 * (
        P[P_UC1] * a0 + P[P_UC1 + 1] * a1 + P[P_UC1 + 2] * a2
        + P[P_UC2] * w0 + P[P_UC2 + 1] * w1 + P[P_UC2 + 2] * w2
    )


@jit
def edge_U(Rb, pb, theta, P, Ra, Rg):
    prepare(Rb, theta, P, Ra, Rg)
    return U_core(Rb, pb, theta, P, Rg)


@jit
def edge_mu(Rb, pb, theta, P, Ra, Rg):
    prepare(Rb, theta, P, Ra, Rg)
    return mu_core(Rb, theta, P, Rg)


@jit
def edge_gradient(Rb, pb, theta, P, Ra, Rg, g):
    prepare(Rb, theta, P, Ra, Rg)
    return gradient_core(Rb, pb, theta, P, Ra, Rg, g)


@jit(inline=True)
def Ad_inv_T_apply(Rb, pb, g, out):
    """out = Ad⁻ᵀ_{X̄} g = [R̄ g_ω + p̄ × (R̄ g_v); R̄ g_v], so that B̄_jk g = −out (`Bt_def`)."""
    rv0 = Rb[0, 0] * g[3] + Rb[0, 1] * g[4] + Rb[0, 2] * g[5]
    rv1 = Rb[1, 0] * g[3] + Rb[1, 1] * g[4] + Rb[1, 2] * g[5]
    rv2 = Rb[2, 0] * g[3] + Rb[2, 1] * g[4] + Rb[2, 2] * g[5]
    out[0] = Rb[0, 0] * g[0] + Rb[0, 1] * g[1] + Rb[0, 2] * g[2] + pb[1] * rv2 - pb[2] * rv1
    out[1] = Rb[1, 0] * g[0] + Rb[1, 1] * g[1] + Rb[1, 2] * g[2] + pb[2] * rv0 - pb[0] * rv2
    out[2] = Rb[2, 0] * g[0] + Rb[2, 1] * g[1] + Rb[2, 2] * g[2] + pb[0] * rv1 - pb[1] * rv0
    out[3] = rv0
    out[4] = rv1
    out[5] = rv2


@jit(inline=True)
def edge_update(Rb, pb, theta, hybrid, P, h, Ra, Rg, g, gn):
    """One edge at a communication point: jump if in 𝒥_k, gradient, then flow of θ over h.

    Returns (θ⁺ after the flow, θ after the jump, μ_U before the jump, jumped). g receives
    ψ̄_∇ (the positive end's term, B̄_ik = I) and gn receives Ad⁻ᵀ_{X̄}ψ̄_∇ (the negative end's
    term with its sign flipped). Used by both the network and the per-agent views.
    """
    prepare(Rb, theta, P, Ra, Rg)
    mu = 0.0
    jumped = False
    if hybrid:
        mu, jstar = mu_core(Rb, theta, P, Rg)
        if mu >= P[P_DELTA]:
            theta = P[P_THETA + jstar]
            jumped = True
            prepare(Rb, theta, P, Ra, Rg)
    grad_theta = gradient_core(Rb, pb, theta, P, Ra, Rg, g)
    Ad_inv_T_apply(Rb, pb, g, gn)
    theta_next = theta - h * P[P_KTH] * grad_theta if hybrid else theta
    return theta_next, theta, mu, jumped


@jit
def network_step(S, theta, edges, P, h, hybrid, u, mu, jumped, theta_prev, theta_jump):
    """`ex_controller` for every agent at one communication point.

    theta (M,) is updated in place (jumps, then flow over h); u (N, 6) receives the wrench;
    mu (μ_U before any jump), jumped, theta_prev (θ on entry) and theta_jump (θ after the jump
    stage) describe each edge. Returns the number of
    jumps. Each agent accumulates −k_ξ ξ_i, then its edges' terms in ascending edge order, the
    same order as the per-agent view, so the two agree to rounding.
    """
    N = S.shape[0]
    M = edges.shape[0]
    kX = P[P_KX]
    kxi = P[P_KXI]
    ke = P[P_KE]
    for i in range(N):
        for a in range(6):
            u[i, a] = -kxi * S[i, S_XI + a]
    Rb = np.empty((3, 3))
    pb = np.empty(3)
    Ra = np.empty((3, 3))
    Rg = np.empty((3, 3))
    g = np.empty(6)
    gn = np.empty(6)
    n_jumps = 0
    for k in range(M):
        i = edges[k, 0]
        j = edges[k, 1]
        rel_pose(S, i, j, Rb, pb)
        th_next, th_jump, mu_k, jumped_k = edge_update(Rb, pb, theta[k], hybrid, P, h, Ra, Rg, g, gn)
        mu[k] = mu_k
        jumped[k] = jumped_k
        theta_prev[k] = theta[k]
        theta_jump[k] = th_jump
        theta[k] = th_next
        if jumped_k:
            n_jumps += 1
        for a in range(6):
            dxi = S[i, S_XI + a] - S[j, S_XI + a]
            u[i, a] += -kX * g[a] - ke * dxi
            u[j, a] += kX * gn[a] + ke * dxi
    return n_jumps


@jit
def network_U(S, theta, edges, P, out):
    """U(X̄_k, θ_k) for every edge into out (M,)."""
    Rb = np.empty((3, 3))
    pb = np.empty(3)
    Ra = np.empty((3, 3))
    Rg = np.empty((3, 3))
    for k in range(edges.shape[0]):
        rel_pose(S, edges[k, 0], edges[k, 1], Rb, pb)
        out[k] = edge_U(Rb, pb, theta[k], P, Ra, Rg)
