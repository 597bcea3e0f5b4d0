"""The delayed network step: a law run per agent, each agent using its own state fresh and the
newest data received from each neighbour over the ``[network]`` links.

It lives next to `cosim.network`, which owns its semantics (the delay contract, the age rule, the
link schedules and statistics). The link bookkeeping is shared (`receive`, `fail_safe`, inlined
into each law's delayed step); what an agent computes from the data is the law's: here the
paper's (`delayed_network_step`, its per-edge mathematics from `controller.kernels`, so that with
every transit time 0 it is bit-identical to `controller.kernels.network_step`); another law
writes its own from the same two pieces (cosim/laws/decoupled.py) and hands it to
`cosim.network.NetworkController` through its ``delayed_step()`` capability.

Links: 2k carries the positive end a's (X_a, ξ_a, θ_k after the jump stage) to the negative end
b of edge k; 2k + 1 carries (X_b, ξ_b) to a. sched[r, l] is the transit time in steps of link l's
message of sample n (−1: lost). ring_S (L, N, 18) / ring_theta (L, M) hold the published samples
n − L + 1 .. n at slot s mod L; arrival[l, a mod L] is the newest sample arriving over link l at
step a (−1: none); held (2M,) is the newest sample received on each link (−1: none yet, recv_*
hold S0 and θ(0)), recv_S (2M, 18) / recv_theta (2M,) its data.

Age rule: on a link whose data is older than max_age steps the receiver's edge term is held at
its last value (term (2M, 6)) and an owned θ_k neither jumps nor flows; older than max_age + hold
the receiving agent fails safe (u_i = 0); failsafe (N, 4) holds per agent the flag this step and
the last, the steps and the entries in fail-safe. Fresh data rejoins. Statistics: age_hist
(2M, H) counts the used-data age (clipped to H − 1); counts (2M, 2): messages sent, lost.
"""
from __future__ import annotations

from controller.kernels import (P_KE, P_KX, P_KXI, Ad_inv_T, edge_update, gradient_core,
                                prepare, rel_pose_rows)
from controller.jit import jit
from controller.layout import S_XI

__all__ = ["delayed_network_step", "receive", "fail_safe", "age_of"]


@jit(inline=True)
def receive(S, n, sched, r, ring_S, arrival, held, recv_S, edges, max_age, hold, age_hist,
            counts, failsafe):
    """Step n's links: S published into the ring, this step's message of every link scheduled,
    the newest arrived sample of every link taken into recv_S, ages counted, and the agents whose
    data are older than max_age + hold marked for fail-safe."""
    N = S.shape[0]
    M = edges.shape[0]
    L = ring_S.shape[0]
    H = age_hist.shape[1]
    slot = n % L
    for i in range(N):
        for c in range(S.shape[1]):
            ring_S[slot, i, c] = S[i, c]
        failsafe[i, 1] = failsafe[i, 0]
        failsafe[i, 0] = 0
    # links: this step's message, then the newest arrived sample
    for l in range(2 * M):
        k = l // 2
        src = edges[k, 0] if l % 2 == 0 else edges[k, 1]
        dst = edges[k, 1] if l % 2 == 0 else edges[k, 0]
        t = sched[r, l]
        counts[l, 0] += 1
        if t < 0:
            counts[l, 1] += 1
        else:  # transit t ≤ L − 1 steps: slots of arrival steps n .. n + L − 1 are distinct
            a = (n + t) % L
            if n > arrival[l, a]:
                arrival[l, a] = n
        s = arrival[l, slot]  # the newest sample arriving at step n (−1: none)
        arrival[l, slot] = -1
        if s > held[l]:
            held[l] = s
            for c in range(S.shape[1]):
                recv_S[l, c] = ring_S[s % L, src, c]
        age = n - held[l] if held[l] >= 0 else n
        age_hist[l, min(max(age, 0), H - 1)] += 1
        if age > max_age + hold:
            failsafe[dst, 0] = 1


@jit(inline=True)
def age_of(n, held, l):
    """The age in steps of the data link l delivers at step n."""
    return n - held[l] if held[l] >= 0 else n


@jit(inline=True)
def fail_safe(u, failsafe):
    """Zero wrench for the agents marked by `receive`; counts their steps and entries."""
    for i in range(u.shape[0]):
        if failsafe[i, 0]:
            failsafe[i, 2] += 1
            if not failsafe[i, 1]:
                failsafe[i, 3] += 1
            for a in range(6):
                u[i, a] = 0.0


@jit
def delayed_network_step(S, n, sched, r, ring_S, ring_theta, arrival, held, recv_S, recv_theta,
                         term, max_age, hold, theta, edges, P, h, hybrid, u, mu, jumped,
                         theta_prev, theta_jump, age_hist, counts, failsafe):
    """`ex_controller` per agent at communication step n when neighbour data travels over
    delayed, lossy links (the delay contract of `cosim.network`; the arrays as in the module
    docstring).

    Each agent accumulates −k_ξ ξ_i, then its edges' terms in ascending edge order, with the
    products of `network_step`: with every transit time 0 the two are bit-identical. An owned
    θ_k on data older than max_age neither jumps nor flows. Returns the number of jumps.
    """
    N = S.shape[0]
    M = edges.shape[0]
    L = ring_S.shape[0]
    kX = P[P_KX]
    kxi = P[P_KXI]
    ke = P[P_KE]
    slot = n % L
    receive(S, n, sched, r, ring_S, arrival, held, recv_S, edges, max_age, hold, age_hist,
            counts, failsafe)
    for i in range(N):
        for a in range(6):
            u[i, a] = -kxi * S[i, S_XI + a]
    n_jumps = 0
    for k in range(M):
        i = edges[k, 0]
        j = edges[k, 1]
        lp = 2 * k      # i → j
        ln = 2 * k + 1  # j → i
        # positive end i (owner of θ_k): X̄_k = X_j(s)⁻¹ X_i(n)
        theta_prev[k] = theta[k]
        age_n = age_of(n, held, ln)
        if age_n > max_age:
            mu[k] = 0.0
            jumped[k] = False
            theta_jump[k] = theta[k]
        else:
            Rb, pb = rel_pose_rows(S, i, recv_S, ln)
            g, gn, th_next, th_jump, mu_k, jumped_k = edge_update(Rb, pb, theta[k], hybrid, P, h)
            mu[k] = mu_k
            jumped[k] = jumped_k
            theta_jump[k] = th_jump
            theta[k] = th_next
            if jumped_k:
                n_jumps += 1
            for a in range(6):
                dxi = S[i, S_XI + a] - recv_S[ln, S_XI + a]
                term[ln, a] = -kX * g[a] - ke * dxi
        ring_theta[slot, k] = theta_jump[k]
        for a in range(6):
            u[i, a] += term[ln, a]
        # negative end j: X̄_k = X_j(n)⁻¹ X_i(s), θ_k(s) as published by i
        if held[lp] >= 0 and held[lp] > n - L:  # its slot still holds that sample's θ_k
            recv_theta[lp] = ring_theta[held[lp] % L, k]
        age_p = age_of(n, held, lp)
        if age_p <= max_age:
            Rb, pb = rel_pose_rows(recv_S, lp, S, j)
            Ra, Rg = prepare(Rb, recv_theta[lp], P)
            g, grad_theta = gradient_core(Rb, pb, recv_theta[lp], P, Ra, Rg)
            gn = Ad_inv_T(Rb, pb, g)
            for a in range(6):
                dxi = recv_S[lp, S_XI + a] - S[j, S_XI + a]
                term[lp, a] = kX * gn[a] + ke * dxi
        for a in range(6):
            u[j, a] += term[lp, a]
    fail_safe(u, failsafe)
    return n_jumps
