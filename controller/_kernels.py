"""Per-edge mathematics of the hybrid law as scalar loops (compiled by numba, or plain Python).

This is the single implementation of U, μ_U, ψ̄_∇, ∇_θU, the jump map and the control law.
The network view, the per-agent view and the public functions in `potential` all call it.

State layout: `controller.layout` (S[i] = [p, R row-major, ξ], the plant FMU's output block).
Parameter vector P (see `pack`): the weighting matrix, the synergy design and the gains,
with W R_a(θ_j)ᵀ precomputed for every θ_j ∈ Θ so that a candidate costs nine products.

The per-edge pieces pass 3×3 matrices as 9-tuples (row-major) and vectors as tuples: inlined
into the network loop, LLVM keeps them in registers, where small scratch arrays would make
every intermediate a store and a reload (measured: 87 → see benchmarks/bench_controller.py).
The array-taking functions (`edge_U`, `edge_mu`, `edge_gradient`, ...) wrap the same cores
for the per-agent view and `potential`, so both views run identical arithmetic.
"""
from __future__ import annotations

import math

import numpy as np

from .jit import jit

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

from .layout import S_P, S_R, S_WIDTH, S_XI  # noqa: F401 (the kernels index S with these)


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
    for j, th in enumerate(Theta):
        Ra = np.array(rot_axis_angle(th, u_c1[0], u_c1[1], u_c1[2])).reshape(3, 3)
        P[P_THETA + m + 9 * j:P_THETA + m + 9 * (j + 1)] = (W @ Ra.T).ravel()
        P[P_THETA + 10 * m + j] = 0.5 * gamma * th * th
    return P


@jit(inline=True)
def rot_axis_angle(theta, u0, u1, u2):
    """ℛ_a(θ, u) = I + sinθ u^× + (1 − cosθ)(u^×)², (u^×)² = uuᵀ − I for unit u; a 9-tuple."""
    sh = math.sin(0.5 * theta)
    ch = math.cos(0.5 * theta)
    s = 2.0 * sh * ch
    c1 = 2.0 * sh * sh  # 1 − cosθ without cancellation
    return (1.0 + c1 * (u0 * u0 - 1.0), -s * u2 + c1 * u0 * u1, s * u1 + c1 * u0 * u2,
            s * u2 + c1 * u1 * u0, 1.0 + c1 * (u1 * u1 - 1.0), -s * u0 + c1 * u1 * u2,
            -s * u1 + c1 * u2 * u0, s * u0 + c1 * u2 * u1, 1.0 + c1 * (u2 * u2 - 1.0))


@jit(inline=True)
def rel_pose_rows(A, i, B, j):
    """X̄ = X_j⁻¹ X_i with X_i from row i of A and X_j from row j of B: `rel_pose` with the two
    poses taken from different arrays (the same products, so equal data gives equal bits)."""
    a0 = B[j, 3]
    a1 = B[j, 4]
    a2 = B[j, 5]
    a3 = B[j, 6]
    a4 = B[j, 7]
    a5 = B[j, 8]
    a6 = B[j, 9]
    a7 = B[j, 10]
    a8 = B[j, 11]
    b0 = A[i, 3]
    b1 = A[i, 4]
    b2 = A[i, 5]
    b3 = A[i, 6]
    b4 = A[i, 7]
    b5 = A[i, 8]
    b6 = A[i, 9]
    b7 = A[i, 10]
    b8 = A[i, 11]
    d0 = A[i, 0] - B[j, 0]
    d1 = A[i, 1] - B[j, 1]
    d2 = A[i, 2] - B[j, 2]
    R = (a0 * b0 + a3 * b3 + a6 * b6, a0 * b1 + a3 * b4 + a6 * b7, a0 * b2 + a3 * b5 + a6 * b8,
         a1 * b0 + a4 * b3 + a7 * b6, a1 * b1 + a4 * b4 + a7 * b7, a1 * b2 + a4 * b5 + a7 * b8,
         a2 * b0 + a5 * b3 + a8 * b6, a2 * b1 + a5 * b4 + a8 * b7, a2 * b2 + a5 * b5 + a8 * b8)
    p = (a0 * d0 + a3 * d1 + a6 * d2, a1 * d0 + a4 * d1 + a7 * d2, a2 * d0 + a5 * d1 + a8 * d2)
    return R, p


@jit
def relative_pose(A, i, B, j, R, p):
    """X̄ = X_j⁻¹ X_i into R (3, 3) and p (3,), X_i from row i of A and X_j from row j of B
    (the products of `rel_pose_rows`, so the per-agent view sees the network step's X̄)."""
    Rt, pt = rel_pose_rows(A, i, B, j)
    for a in range(3):
        p[a] = pt[a]
        for b in range(3):
            R[a, b] = Rt[3 * a + b]


@jit(inline=True)
def rel_pose(S, i, j):
    """X̄ = X_j⁻¹ X_i: (R̄ = R_jᵀ R_i as a 9-tuple, p̄ = R_jᵀ (p_i − p_j) as a 3-tuple)."""
    return rel_pose_rows(S, i, S, j)


@jit(inline=True)
def mul3(X, Y):
    """X Y for 3×3 matrices as row-major 9-tuples."""
    return (X[0] * Y[0] + X[1] * Y[3] + X[2] * Y[6], X[0] * Y[1] + X[1] * Y[4] + X[2] * Y[7],
            X[0] * Y[2] + X[1] * Y[5] + X[2] * Y[8],
            X[3] * Y[0] + X[4] * Y[3] + X[5] * Y[6], X[3] * Y[1] + X[4] * Y[4] + X[5] * Y[7],
            X[3] * Y[2] + X[4] * Y[5] + X[5] * Y[8],
            X[6] * Y[0] + X[7] * Y[3] + X[8] * Y[6], X[6] * Y[1] + X[7] * Y[4] + X[8] * Y[7],
            X[6] * Y[2] + X[7] * Y[5] + X[8] * Y[8])


@jit(inline=True)
def prepare(Rb, theta, P):
    """(R_a, R_g) = (ℛ_a(θ, u_c1), R̄ R_a), R_g being the rotation of Γ = X̄ 𝒯_uc(θ)."""
    Ra = rot_axis_angle(theta, P[P_UC1], P[P_UC1 + 1], P[P_UC1 + 2])
    return Ra, mul3(Rb, Ra)


@jit(inline=True)
def _trace_W(P, Rg):
    """tr(W R_g) (W symmetric)."""
    return (P[P_W] * Rg[0] + P[P_W + 1] * Rg[1] + P[P_W + 2] * Rg[2]
            + P[P_W + 3] * Rg[3] + P[P_W + 4] * Rg[4] + P[P_W + 5] * Rg[5]
            + P[P_W + 6] * Rg[6] + P[P_W + 7] * Rg[7] + P[P_W + 8] * Rg[8])


@jit(inline=True)
def U_core(Rb, pb, theta, P, Rg):
    """U(X̄, θ) by `U_explicit`: tr(W(I − R̄ℛ_a)) + γθ²/2 + d/2‖p̄ − (I − R̄)b/d‖²."""
    c0 = P[P_C]
    c1 = P[P_C + 1]
    c2 = P[P_C + 2]
    e0 = pb[0] - c0 + Rb[0] * c0 + Rb[1] * c1 + Rb[2] * c2
    e1 = pb[1] - c1 + Rb[3] * c0 + Rb[4] * c1 + Rb[5] * c2
    e2 = pb[2] - c2 + Rb[6] * c0 + Rb[7] * c1 + Rb[8] * c2
    return (P[P_TRW] - _trace_W(P, Rg) + 0.5 * P[P_GAMMA] * theta * theta
            + 0.5 * P[P_D] * (e0 * e0 + e1 * e1 + e2 * e2))


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
        o = P_THETA + m + 9 * j
        acc = (Rb[0] * P[o] + Rb[1] * P[o + 1] + Rb[2] * P[o + 2] + Rb[3] * P[o + 3]
               + Rb[4] * P[o + 4] + Rb[5] * P[o + 5] + Rb[6] * P[o + 6] + Rb[7] * P[o + 7]
               + Rb[8] * P[o + 8])
        s_j = -acc + P[P_THETA + 10 * m + j]
        if j == 0 or s_j < best - 1e-12 * (1.0 + abs(best)):
            best = s_j
            jstar = j
    return s_cur - best, jstar


@jit(inline=True)
def gradient_core(Rb, pb, theta, P, Ra, Rg):
    """(ψ̄_∇(X̄, θ) (`st_b`) as a 6-tuple, ∇_θU(X̄, θ) (`st_c`)).

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
    y0 = c0 + Rb[0] * pb[0] + Rb[3] * pb[1] + Rb[6] * pb[2]
    y1 = c1 + Rb[1] * pb[0] + Rb[4] * pb[1] + Rb[7] * pb[2]
    y2 = c2 + Rb[2] * pb[0] + Rb[5] * pb[1] + Rb[8] * pb[2]
    # q = R_aᵀ y − c
    q0 = Ra[0] * y0 + Ra[3] * y1 + Ra[6] * y2 - c0
    q1 = Ra[1] * y0 + Ra[4] * y1 + Ra[7] * y2 - c1
    q2 = Ra[2] * y0 + Ra[5] * y1 + Ra[8] * y2 - c2
    A00 = P[P_A]
    A01 = P[P_A + 1]
    A02 = P[P_A + 2]
    A11 = P[P_A + 4]
    A12 = P[P_A + 5]
    A22 = P[P_A + 8]
    # M = R_gᵀ A, M[r, s] = Σ_e R_g[e, r] A[e, s]; ψ(M) needs six entries
    M21 = Rg[2] * A01 + Rg[5] * A11 + Rg[8] * A12
    M12 = Rg[1] * A02 + Rg[4] * A12 + Rg[7] * A22
    M02 = Rg[0] * A02 + Rg[3] * A12 + Rg[6] * A22
    M20 = Rg[2] * A00 + Rg[5] * A01 + Rg[8] * A02
    M10 = Rg[1] * A00 + Rg[4] * A01 + Rg[7] * A02
    M01 = Rg[0] * A01 + Rg[3] * A11 + Rg[6] * A12
    a0 = -0.5 * (M21 - M12) + 0.5 * (b1 * q2 - b2 * q1)
    a1 = -0.5 * (M02 - M20) + 0.5 * (b2 * q0 - b0 * q2)
    a2 = -0.5 * (M10 - M01) + 0.5 * (b0 * q1 - b1 * q0)
    # R_gᵀ b
    r0 = Rg[0] * b0 + Rg[3] * b1 + Rg[6] * b2
    r1 = Rg[1] * b0 + Rg[4] * b1 + Rg[7] * b2
    r2 = Rg[2] * b0 + Rg[5] * b1 + Rg[8] * b2
    w0 = 0.5 * (b0 - r0 + d * q0)
    w1 = 0.5 * (b1 - r1 + d * q1)
    w2 = 0.5 * (b2 - r2 + d * q2)
    # R_a w and R_a a
    rw0 = Ra[0] * w0 + Ra[1] * w1 + Ra[2] * w2
    rw1 = Ra[3] * w0 + Ra[4] * w1 + Ra[5] * w2
    rw2 = Ra[6] * w0 + Ra[7] * w1 + Ra[8] * w2
    ra0 = Ra[0] * a0 + Ra[1] * a1 + Ra[2] * a2
    ra1 = Ra[3] * a0 + Ra[4] * a1 + Ra[5] * a2
    ra2 = Ra[6] * a0 + Ra[7] * a1 + Ra[8] * a2
    # p_T = c − R_a c
    pt0 = c0 - (Ra[0] * c0 + Ra[1] * c1 + Ra[2] * c2)
    pt1 = c1 - (Ra[3] * c0 + Ra[4] * c1 + Ra[5] * c2)
    pt2 = c2 - (Ra[6] * c0 + Ra[7] * c1 + Ra[8] * c2)
    g = (ra0 + pt1 * rw2 - pt2 * rw1, ra1 + pt2 * rw0 - pt0 * rw2, ra2 + pt0 * rw1 - pt1 * rw0,
         rw0, rw1, rw2)
    grad_theta = P[P_GAMMA] * theta + 2.0 * (
        P[P_UC1] * a0 + P[P_UC1 + 1] * a1 + P[P_UC1 + 2] * a2
        + P[P_UC2] * w0 + P[P_UC2 + 1] * w1 + P[P_UC2 + 2] * w2
    )
    return g, grad_theta


@jit(inline=True)
def Ad_inv_T(Rb, pb, g):
    """Ad⁻ᵀ_{X̄} g = [R̄ g_ω + p̄ × (R̄ g_v); R̄ g_v], so that B̄_jk g = −Ad⁻ᵀ_{X̄} g (`Bt_def`)."""
    rv0 = Rb[0] * g[3] + Rb[1] * g[4] + Rb[2] * g[5]
    rv1 = Rb[3] * g[3] + Rb[4] * g[4] + Rb[5] * g[5]
    rv2 = Rb[6] * g[3] + Rb[7] * g[4] + Rb[8] * g[5]
    return (Rb[0] * g[0] + Rb[1] * g[1] + Rb[2] * g[2] + pb[1] * rv2 - pb[2] * rv1,
            Rb[3] * g[0] + Rb[4] * g[1] + Rb[5] * g[2] + pb[2] * rv0 - pb[0] * rv2,
            Rb[6] * g[0] + Rb[7] * g[1] + Rb[8] * g[2] + pb[0] * rv1 - pb[1] * rv0,
            rv0, rv1, rv2)


@jit(inline=True)
def edge_update(Rb, pb, theta, hybrid, P, h):
    """One edge at a communication point: jump if in 𝒥_k, gradient, then flow of θ over h.

    Returns (g, gn, θ⁺ after the flow, θ after the jump, μ_U before the jump, jumped): g is
    ψ̄_∇ (the positive end's term, B̄_ik = I) and gn is Ad⁻ᵀ_{X̄}ψ̄_∇ (the negative end's term
    with its sign flipped).
    """
    Ra, Rg = prepare(Rb, theta, P)
    mu = 0.0
    jumped = False
    if hybrid:
        mu, jstar = mu_core(Rb, theta, P, Rg)
        if mu >= P[P_DELTA]:
            theta = P[P_THETA + jstar]
            jumped = True
            Ra, Rg = prepare(Rb, theta, P)
    g, grad_theta = gradient_core(Rb, pb, theta, P, Ra, Rg)
    gn = Ad_inv_T(Rb, pb, g)
    theta_next = theta - h * P[P_KTH] * grad_theta if hybrid else theta
    return g, gn, theta_next, theta, mu, jumped


@jit(inline=True)
def _t9(M):
    return (M[0, 0], M[0, 1], M[0, 2], M[1, 0], M[1, 1], M[1, 2], M[2, 0], M[2, 1], M[2, 2])


@jit(inline=True)
def _t3(v):
    return (v[0], v[1], v[2])


# ---- array-taking entry points (per-agent view, `potential`): the same cores as the network


@jit
def edge_U(Rb, pb, theta, P):
    """U(X̄, θ) for R̄ (3, 3), p̄ (3,)."""
    R = _t9(Rb)
    Ra, Rg = prepare(R, theta, P)
    return U_core(R, _t3(pb), theta, P, Rg)


@jit
def edge_mu(Rb, pb, theta, P):
    """(μ_U, j*) for R̄ (3, 3), p̄ (3,)."""
    R = _t9(Rb)
    Ra, Rg = prepare(R, theta, P)
    return mu_core(R, theta, P, Rg)


@jit
def edge_gradient(Rb, pb, theta, P, g):
    """ψ̄_∇ into g (6,); returns ∇_θU."""
    R = _t9(Rb)
    Ra, Rg = prepare(R, theta, P)
    gt, grad_theta = gradient_core(R, _t3(pb), theta, P, Ra, Rg)
    for a in range(6):
        g[a] = gt[a]
    return grad_theta


@jit
def Ad_inv_T_apply(Rb, pb, g, out):
    """out = Ad⁻ᵀ_{X̄} g for R̄ (3, 3), p̄ (3,)."""
    gt = (g[0], g[1], g[2], g[3], g[4], g[5])
    o = Ad_inv_T(_t9(Rb), _t3(pb), gt)
    for a in range(6):
        out[a] = o[a]


@jit
def network_step(S, theta, edges, P, h, hybrid, u, mu, jumped, theta_prev, theta_jump):
    """`ex_controller` for every agent at one communication point.

    theta (M,) is updated in place (jumps, then flow over h); u (N, 6) receives the wrench;
    mu (μ_U before any jump), jumped, theta_prev (θ on entry) and theta_jump (θ after the jump
    stage) describe each edge. Returns the number of jumps. Each agent accumulates −k_ξ ξ_i,
    then its edges' terms in ascending edge order, the same order as the per-agent view, so
    the two agree to rounding.
    """
    N = S.shape[0]
    M = edges.shape[0]
    kX = P[P_KX]
    kxi = P[P_KXI]
    ke = P[P_KE]
    for i in range(N):
        for a in range(6):
            u[i, a] = -kxi * S[i, S_XI + a]
    n_jumps = 0
    for k in range(M):
        i = edges[k, 0]
        j = edges[k, 1]
        Rb, pb = rel_pose(S, i, j)
        g, gn, th_next, th_jump, mu_k, jumped_k = edge_update(Rb, pb, theta[k], hybrid, P, h)
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
    for k in range(edges.shape[0]):
        Rb, pb = rel_pose(S, edges[k, 0], edges[k, 1])
        Ra, Rg = prepare(Rb, theta[k], P)
        out[k] = U_core(Rb, pb, theta[k], P, Rg)


@jit(inline=True)
def quat_of(r00, r01, r02, r10, r11, r12, r20, r21, r22):
    """Unit quaternion (w, x, y, z), w ≥ 0, of a rotation matrix by Shepperd's method: of the
    four algebraically equal forms, the one with the largest pivot (ties to the first)."""
    tr = r00 + r11 + r22
    if tr >= r00 and tr >= r11 and tr >= r22:
        w = 0.5 * math.sqrt(max(1.0 + tr, 0.0))
        s = 0.25 / w
        x = (r21 - r12) * s
        y = (r02 - r20) * s
        z = (r10 - r01) * s
    elif r00 >= r11 and r00 >= r22:
        x = 0.5 * math.sqrt(max(1.0 + r00 - r11 - r22, 0.0))
        s = 0.25 / x
        w = (r21 - r12) * s
        y = (r01 + r10) * s
        z = (r02 + r20) * s
    elif r11 >= r22:
        y = 0.5 * math.sqrt(max(1.0 - r00 + r11 - r22, 0.0))
        s = 0.25 / y
        w = (r02 - r20) * s
        x = (r01 + r10) * s
        z = (r12 + r21) * s
    else:
        z = 0.5 * math.sqrt(max(1.0 - r00 - r11 + r22, 0.0))
        s = 0.25 / z
        w = (r10 - r01) * s
        x = (r02 + r20) * s
        y = (r12 + r21) * s
    if w < 0.0:
        return -w, -x, -y, -z
    return w, x, y, z


@jit
def rot_to_quat_rows(R9, out):
    """out[n] = (w, x, y, z) of the row-major rotation matrix R9[n] (n, 9)."""
    for n in range(R9.shape[0]):
        q = quat_of(R9[n, 0], R9[n, 1], R9[n, 2], R9[n, 3], R9[n, 4], R9[n, 5],
                    R9[n, 6], R9[n, 7], R9[n, 8])
        for a in range(4):
            out[n, a] = q[a]


@jit
def metrics(S, edges, U, kX, masses, J, rot_err, pos_err, quat):
    """Fills rot_err, pos_err (M,) and quat (N, 4: x, y, z, w, Foxglove's order); returns
    (V̄, max|ξ|) with V̄ = k_X ΣU + Σ ξᵀ𝕀ξ (`V_def`) from U (M,) computed by `network_U`."""
    N = S.shape[0]
    M = edges.shape[0]
    usum = 0.0
    for k in range(M):
        Rb, pb = rel_pose(S, edges[k, 0], edges[k, 1])
        acc = 0.0
        for a in range(3):
            for c in range(3):
                x = (1.0 if a == c else 0.0) - Rb[3 * a + c]
                acc += x * x
        rot_err[k] = math.sqrt(acc)
        pos_err[k] = math.sqrt(pb[0] * pb[0] + pb[1] * pb[1] + pb[2] * pb[2])
        usum += U[k]
    kin = 0.0
    ximax = 0.0
    for i in range(N):
        for a in range(6):
            v = abs(S[i, S_XI + a])
            if v > ximax:
                ximax = v
        for a in range(3):
            for c in range(3):
                kin += S[i, S_XI + a] * J[i, a, c] * S[i, S_XI + c]
        for a in range(3):
            kin += masses[i] * S[i, S_XI + 3 + a] * S[i, S_XI + 3 + a]
        w, x, y, z = quat_of(S[i, S_R], S[i, S_R + 1], S[i, S_R + 2], S[i, S_R + 3],
                             S[i, S_R + 4], S[i, S_R + 5], S[i, S_R + 6], S[i, S_R + 7],
                             S[i, S_R + 8])
        quat[i, 0] = x
        quat[i, 1] = y
        quat[i, 2] = z
        quat[i, 3] = w
    return kX * usum + kin, ximax
