"""The per-agent view's arithmetic (`ex_controller` for agent i only), compiled once for its two
callers: `AgentStepper` (dicts in, one edge per call) and the agent process's step
(`agent_step`: every edge of the neighbourhood in one call over preallocated arrays).

Both evaluate every float through the cores below (and the network view's `prepare`, `mu_core`,
`gradient_core`, `Ad_inv_T`, `rel_pose_rows`), so the two paths agree bit for bit on any CPU:
the kernels are compiled without fastmath, and LLVM neither reorders nor fuses (FMA) floating-point
operations without it, whatever the caller they are inlined into.

Edge k = (a, b), a its positive end: its part of u_a is −k_X ψ̄_∇(X̄_k, θ_k) − k_e(ξ_a − ξ_b),
its part of u_b is k_X Ad⁻ᵀ_{X̄_k} ψ̄_∇(X̄_k, θ_k) + k_e(ξ_a − ξ_b) (`hybridcontroller`, B̄ of
`Bt_def`).
"""
from __future__ import annotations

import numpy as np

from .jit import jit
from ._kernels import (P_DELTA, P_KE, P_KTH, P_KX, P_KXI, P_THETA, Ad_inv_T, _t3, _t9,
                       gradient_core, mu_core, prepare, rel_pose_rows)
from .layout import S_XI

FRESH = 0   # agent_step's mode of a neighbour (the age rule's verdict); any other value: stale


@jit(inline=True)
def term_core(Rb, pb, theta, xi_a, xi_b, positive, P):
    """(edge k's part of u at its positive end (``positive``) or its negative end, as a 6-tuple,
    ∇_θU(X̄_k, θ_k)); R̄ a row-major 9-tuple, p̄ a 3-tuple, ξ_a and ξ_b of the positive and the
    negative end as 6-tuples."""
    Ra, Rg = prepare(Rb, theta, P)
    g, grad_theta = gradient_core(Rb, pb, theta, P, Ra, Rg)
    kX = P[P_KX]
    ke = P[P_KE]
    d0 = xi_a[0] - xi_b[0]
    d1 = xi_a[1] - xi_b[1]
    d2 = xi_a[2] - xi_b[2]
    d3 = xi_a[3] - xi_b[3]
    d4 = xi_a[4] - xi_b[4]
    d5 = xi_a[5] - xi_b[5]
    if positive:
        t = (-kX * g[0] - ke * d0, -kX * g[1] - ke * d1, -kX * g[2] - ke * d2,
             -kX * g[3] - ke * d3, -kX * g[4] - ke * d4, -kX * g[5] - ke * d5)
    else:
        gn = Ad_inv_T(Rb, pb, g)
        t = (kX * gn[0] + ke * d0, kX * gn[1] + ke * d1, kX * gn[2] + ke * d2,
             kX * gn[3] + ke * d3, kX * gn[4] + ke * d4, kX * gn[5] + ke * d5)
    return t, grad_theta


@jit(inline=True)
def flow_core(theta, grad_theta, P, h):
    """θ − h k_θ ∇_θU: the flow of θ over h (forward Euler, held X̄)."""
    return theta - h * P[P_KTH] * grad_theta


@jit(inline=True)
def wrench_core(xi, T, P):
    """u_i = −k_ξ ξ_i + Σ_r T[r], the rows summed in order (ascending k), as a 6-tuple."""
    kxi = P[P_KXI]
    u0 = -kxi * xi[0]
    u1 = -kxi * xi[1]
    u2 = -kxi * xi[2]
    u3 = -kxi * xi[3]
    u4 = -kxi * xi[4]
    u5 = -kxi * xi[5]
    for r in range(T.shape[0]):
        u0 += T[r, 0]
        u1 += T[r, 1]
        u2 += T[r, 2]
        u3 += T[r, 3]
        u4 += T[r, 4]
        u5 += T[r, 5]
    return u0, u1, u2, u3, u4, u5


@jit(inline=True)
def _t6(v):
    return v[0], v[1], v[2], v[3], v[4], v[5]


@jit(inline=True)
def _xi_row(S, i):
    return (S[i, S_XI], S[i, S_XI + 1], S[i, S_XI + 2], S[i, S_XI + 3], S[i, S_XI + 4],
            S[i, S_XI + 5])


# ---- array-taking entry points of `AgentStepper` (one edge per call)


@jit
def edge_term(Rb, pb, theta, xi_a, xi_b, positive, P, out):
    """Edge k's part of u at its positive (``positive``) or negative end into out (6,), for R̄
    (3, 3), p̄ (3,) and ξ_a, ξ_b (6,) of the positive and the negative end; returns ∇_θU."""
    t, grad_theta = term_core(_t9(Rb), _t3(pb), theta, _t6(xi_a), _t6(xi_b), positive, P)
    for c in range(6):
        out[c] = t[c]
    return grad_theta


@jit
def edge_flow(Rb, pb, theta, P, h):
    """θ_k after the flow over h at X̄_k = (R̄ (3, 3), p̄ (3,))."""
    R = _t9(Rb)
    Ra, Rg = prepare(R, theta, P)
    g, grad_theta = gradient_core(R, _t3(pb), theta, P, Ra, Rg)
    return flow_core(theta, grad_theta, P, h)


@jit
def wrench_sum(xi, T, P, out):
    """out (6,) = −k_ξ ξ_i + Σ_r T[r] for ξ_i (6,) and the edges' terms T (E, 6), ascending k."""
    u = wrench_core(_t6(xi), T, P)
    for c in range(6):
        out[c] = u[c]


# ---- the agent process's step (bridge.swarm.agent), every edge of its neighbourhood at once


@jit
def agent_step(S, ea, eb, owned, nbr, mode, hybrid, P, h, stages, failsafe, theta, theta_rx,
               theta_prev, theta_jump, mu, jumped, term, rel, u):
    """Agent i's law at one communication point over its neighbourhood's E edges (rows r in
    ascending k); returns the number of jumps.

    S (n, 18): row 0 agent i, the other rows its neighbours as received. Edge r joins rows ea[r]
    (positive end) and eb[r]; owned[r]: θ_r is agent i's (ea[r] = 0); nbr[r]: the neighbour of
    the edge, whose age-rule verdict is mode[nbr[r]] (`FRESH`, or stale: the edge's term is held
    in term[r], an owned θ neither jumps nor flows). theta (E,): the owned θ on entry, the
    neighbourhood's θ after the flow on return; theta_rx: θ of the edges the neighbours own, as
    received (θ ≡ 0 in the law when not ``hybrid``). ``stages`` 1: X̄ of the fresh edges (into
    rel (E, 12): R̄ row-major, p̄) and the jump stage; 2: the terms, u (row 0: u_i, zero when
    ``failsafe``; other rows 0) and the flow; 3: both (lockstep publishes θ in between).
    theta_prev, theta_jump, mu (NaN: not looked at), jumped: as `network_step` writes them.
    """
    E = ea.shape[0]
    n_jumps = 0
    if stages & 1:
        for r in range(E):
            th = theta[r]
            theta_prev[r] = th
            mu[r] = np.nan
            jumped[r] = False
            if mode[nbr[r]] == FRESH:
                Rb, pb = rel_pose_rows(S, ea[r], S, eb[r])
                for c in range(9):
                    rel[r, c] = Rb[c]
                for c in range(3):
                    rel[r, 9 + c] = pb[c]
                if owned[r] and hybrid:
                    Ra, Rg = prepare(Rb, th, P)
                    m, jstar = mu_core(Rb, th, P, Rg)
                    mu[r] = m
                    if m >= P[P_DELTA]:
                        th = P[P_THETA + jstar]
                        jumped[r] = True
                        n_jumps += 1
            theta_jump[r] = th
    if stages & 2:
        xi_i = _xi_row(S, 0)
        for r in range(E):
            own = owned[r]
            if own:
                th = theta_jump[r]
            else:
                th = theta_rx[r]
                theta_jump[r] = th
            theta[r] = th
            if mode[nbr[r]] == FRESH:
                Rb = (rel[r, 0], rel[r, 1], rel[r, 2], rel[r, 3], rel[r, 4], rel[r, 5],
                      rel[r, 6], rel[r, 7], rel[r, 8])
                pb = (rel[r, 9], rel[r, 10], rel[r, 11])
                if own:
                    t, grad_theta = term_core(Rb, pb, th, xi_i, _xi_row(S, eb[r]), True, P)
                    if hybrid:
                        theta[r] = flow_core(th, grad_theta, P, h)
                else:
                    t, grad_theta = term_core(Rb, pb, th if hybrid else 0.0, _xi_row(S, ea[r]),
                                              xi_i, False, P)
                for c in range(6):
                    term[r, c] = t[c]
        for i in range(u.shape[0]):
            for c in range(6):
                u[i, c] = 0.0
        if not failsafe:
            w = wrench_core(xi_i, term, P)
            for c in range(6):
                u[0, c] = w[c]
    return n_jumps
