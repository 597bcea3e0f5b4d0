"""Decoupled SO(3) × R³ pose synchronisation: the design the paper contrasts itself with.

The seed paper (Lin, Wang, Su, Tayebi; its introduction) names "the decoupled control framework
on SO(3) × R³" of `schlanbusch2011synchronization` and `nair2007stable` (S. Nair and N. E.
Leonard, *Stable synchronization of rigid body networks*, Networks and Heterogeneous Media 2(4),
2007, doi:10.3934/nhm.2007.2.597): the rigid-body dynamics are split into rotational and
translational parts and each gets its own feedback, energy shaping with a coupling potential of
the neighbours' relative orientation and another of their relative position, plus damping
("disregard[ing] the intrinsic geometric coupling" of SE(3), in the paper's words). What is
implemented here is that design for the paper's plant and graph, stated exactly (from the
references we could read the abstracts, not their equations: the law below is ours, in their
framework):

For an edge k = (i, j) (i its positive end), X̄_k = X_j⁻¹X_i = (R̄, p̄), so that R̄ = R_jᵀR_i and
‖p̄‖ = ‖p_i − p_j‖, the potential is the sum of a rotational and a translational one,

    U_dec(X̄) = tr(A(I − R̄)) + (d/2)‖p̄‖²                                          (1)

with A and d of the scenario's weighting 𝔸 = [[A, b], [bᵀ, d]]: it is the paper's U
(`U_explicit`) at θ = 0 with the coupling b removed, the one term that ties rotation and
translation together. Agent i applies, in its body frame (u = [τ; f], ξ = [ω; v]),

    u_i = −k_ξ ξ_i + Σ_{k∈𝓜_i⁺} t⁺_k + Σ_{k∈𝓜_i⁻} t⁻_k                              (2)
    t⁺_k = −k_X [ψ(A R̄); (d/2) R̄ᵀp̄] − k_e [ω_i − R̄ᵀω_j; v_i − R̄ᵀv_j]             (3)
    t⁻_k = +k_X [ψ(R̄ A); (d/2) p̄]    − k_e [ω_j − R̄ω_i;  v_j − R̄v_i]               (4)

ψ(M) = ½(M − Mᵀ)^∨ (`psiA_def`). The k_X terms are −k_X/2 times the gradient of (1) in each
agent's body frame (the attitude consensus torque and, rotated into the body frame, the
world-frame spring k_X d/2 (p_i − p_j)); the k_e terms damp the relative angular and linear
velocities, each expressed in the agent's own frame (R̄ᵀ maps frame j to frame i), as an
inertial-frame design does, where the paper uses ξ_i − ξ_j. At consensus (R̄ = I, p̄ = 0) the
linearised loop is the gradient baseline's for b = 0. Smooth and time-invariant, the law is at
best almost globally stable: with R̄ = R_a(π, v), v an eigenvector of A, and p̄ = 0 on every
edge, every term vanishes (an undesired equilibrium).

Gains: the scenario's k_X, k_ξ, k_e (k_θ unused; there is no θ). The law declares a compiled
network step (`decoupled_step`, `law_step` for `DecoupledStep`), a per-agent view
(`DecoupledAgent`), its step on delayed data for ``[network]`` (`delayed_decoupled_step`, on
the link bookkeeping of `cosim.network_step`), all three from the one per-edge function
`edge_terms`, and no θ-like state; `check` linearises it from its own step.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from controller.errors import Se3SyncError
from controller.kernels import rel_pose_rows
from controller.layout import S_XI

from ..controllers import DelayedLaw, compiled_law_step
from ..network_step import age_of, fail_safe, receive

__all__ = ["make", "DecoupledLaw", "DecoupledAgent", "DecoupledStep", "decoupled_step",
           "delayed_decoupled_step", "pack"]

# the parameter vector Q
Q_A = 0      # A, 9 values row-major
Q_HD = 9     # d/2
Q_KX = 10
Q_KXI = 11
Q_KE = 12
Q_SIZE = 13


def pack(A, d, k_X, k_xi, k_e) -> np.ndarray:
    """Q, the parameter vector the kernels read."""
    Q = np.zeros(Q_SIZE)
    Q[Q_A:Q_A + 9] = np.asarray(A, float).ravel()
    Q[Q_HD] = 0.5 * float(d)
    Q[Q_KX], Q[Q_KXI], Q[Q_KE] = k_X, k_xi, k_e
    return Q


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def edge_terms(Rb, pb, xi_a, xi_b, Q):
    """(t⁺, t⁻) of (3) and (4) as 6-tuples for R̄ (row-major 9-tuple), p̄ (3-tuple) and the
    velocities of the positive end a and the negative end b (6-tuples)."""
    A0 = Q[Q_A]
    A1 = Q[Q_A + 1]
    A2 = Q[Q_A + 2]
    A3 = Q[Q_A + 3]
    A4 = Q[Q_A + 4]
    A5 = Q[Q_A + 5]
    A6 = Q[Q_A + 6]
    A7 = Q[Q_A + 7]
    A8 = Q[Q_A + 8]
    hd = Q[Q_HD]
    kX = Q[Q_KX]
    ke = Q[Q_KE]
    # ψ(A R̄): M[r, s] = Σ_e A[r, e] R̄[e, s]
    m21 = A6 * Rb[1] + A7 * Rb[4] + A8 * Rb[7]
    m12 = A3 * Rb[2] + A4 * Rb[5] + A5 * Rb[8]
    m02 = A0 * Rb[2] + A1 * Rb[5] + A2 * Rb[8]
    m20 = A6 * Rb[0] + A7 * Rb[3] + A8 * Rb[6]
    m10 = A3 * Rb[0] + A4 * Rb[3] + A5 * Rb[6]
    m01 = A0 * Rb[1] + A1 * Rb[4] + A2 * Rb[7]
    # ψ(R̄ A): N[r, s] = Σ_e R̄[r, e] A[e, s]
    n21 = Rb[6] * A1 + Rb[7] * A4 + Rb[8] * A7
    n12 = Rb[3] * A2 + Rb[4] * A5 + Rb[5] * A8
    n02 = Rb[0] * A2 + Rb[1] * A5 + Rb[2] * A8
    n20 = Rb[6] * A0 + Rb[7] * A3 + Rb[8] * A6
    n10 = Rb[3] * A0 + Rb[4] * A3 + Rb[5] * A6
    n01 = Rb[0] * A1 + Rb[1] * A4 + Rb[2] * A7
    # R̄ᵀ p̄
    q0 = Rb[0] * pb[0] + Rb[3] * pb[1] + Rb[6] * pb[2]
    q1 = Rb[1] * pb[0] + Rb[4] * pb[1] + Rb[7] * pb[2]
    q2 = Rb[2] * pb[0] + Rb[5] * pb[1] + Rb[8] * pb[2]
    # the other end's velocities in each end's frame: R̄ᵀξ_b (ω and v) and R̄ξ_a
    wb0 = Rb[0] * xi_b[0] + Rb[3] * xi_b[1] + Rb[6] * xi_b[2]
    wb1 = Rb[1] * xi_b[0] + Rb[4] * xi_b[1] + Rb[7] * xi_b[2]
    wb2 = Rb[2] * xi_b[0] + Rb[5] * xi_b[1] + Rb[8] * xi_b[2]
    vb0 = Rb[0] * xi_b[3] + Rb[3] * xi_b[4] + Rb[6] * xi_b[5]
    vb1 = Rb[1] * xi_b[3] + Rb[4] * xi_b[4] + Rb[7] * xi_b[5]
    vb2 = Rb[2] * xi_b[3] + Rb[5] * xi_b[4] + Rb[8] * xi_b[5]
    wa0 = Rb[0] * xi_a[0] + Rb[1] * xi_a[1] + Rb[2] * xi_a[2]
    wa1 = Rb[3] * xi_a[0] + Rb[4] * xi_a[1] + Rb[5] * xi_a[2]
    wa2 = Rb[6] * xi_a[0] + Rb[7] * xi_a[1] + Rb[8] * xi_a[2]
    va0 = Rb[0] * xi_a[3] + Rb[1] * xi_a[4] + Rb[2] * xi_a[5]
    va1 = Rb[3] * xi_a[3] + Rb[4] * xi_a[4] + Rb[5] * xi_a[5]
    va2 = Rb[6] * xi_a[3] + Rb[7] * xi_a[4] + Rb[8] * xi_a[5]
    tp = (-kX * (0.5 * (m21 - m12)) - ke * (xi_a[0] - wb0),
          -kX * (0.5 * (m02 - m20)) - ke * (xi_a[1] - wb1),
          -kX * (0.5 * (m10 - m01)) - ke * (xi_a[2] - wb2),
          -kX * (hd * q0) - ke * (xi_a[3] - vb0),
          -kX * (hd * q1) - ke * (xi_a[4] - vb1),
          -kX * (hd * q2) - ke * (xi_a[5] - vb2))
    tn = (kX * (0.5 * (n21 - n12)) - ke * (xi_b[0] - wa0),
          kX * (0.5 * (n02 - n20)) - ke * (xi_b[1] - wa1),
          kX * (0.5 * (n10 - n01)) - ke * (xi_b[2] - wa2),
          kX * (hd * pb[0]) - ke * (xi_b[3] - va0),
          kX * (hd * pb[1]) - ke * (xi_b[4] - va1),
          kX * (hd * pb[2]) - ke * (xi_b[5] - va2))
    return tp, tn


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _xi(S, i):
    return (S[i, S_XI], S[i, S_XI + 1], S[i, S_XI + 2], S[i, S_XI + 3], S[i, S_XI + 4],
            S[i, S_XI + 5])


@njit(cache=True, nogil=True, error_model="numpy")
def decoupled_step(S, edges, Q, u):
    """(2) for every agent into u (N, 6) at state S (N, 18): −k_ξ ξ_i, then the edges' terms in
    ascending edge order (the per-agent view's order). Returns 0 (no jumps)."""
    kxi = Q[Q_KXI]
    for i in range(S.shape[0]):
        for a in range(6):
            u[i, a] = -kxi * S[i, S_XI + a]
    for k in range(edges.shape[0]):
        i = edges[k, 0]
        j = edges[k, 1]
        Rb, pb = rel_pose_rows(S, i, S, j)
        tp, tn = edge_terms(Rb, pb, _xi(S, i), _xi(S, j), Q)
        for a in range(6):
            u[i, a] += tp[a]
            u[j, a] += tn[a]
    return 0


@njit(cache=True, nogil=True, error_model="numpy")
def edge_terms_into(Rb, pb, xi_a, xi_b, Q, tp, tn):
    """`edge_terms` for arrays (R̄ (3, 3), p̄ (3,), ξ_a, ξ_b (6,)) into tp, tn (6,)."""
    R = (Rb[0, 0], Rb[0, 1], Rb[0, 2], Rb[1, 0], Rb[1, 1], Rb[1, 2], Rb[2, 0], Rb[2, 1],
         Rb[2, 2])
    a, b = edge_terms(R, (pb[0], pb[1], pb[2]),
                      (xi_a[0], xi_a[1], xi_a[2], xi_a[3], xi_a[4], xi_a[5]),
                      (xi_b[0], xi_b[1], xi_b[2], xi_b[3], xi_b[4], xi_b[5]), Q)
    for c in range(6):
        tp[c] = a[c]
        tn[c] = b[c]


@njit(cache=True, nogil=True, error_model="numpy")
def delayed_decoupled_step(S, n, sched, r, ring_S, arrival, held, recv_S, term, max_age, hold,
                           edges, Q, u, age_hist, counts, failsafe):
    """(2) per agent at step n on the data its neighbours' messages delivered over the
    ``[network]`` links (`cosim.network_step`: the links, the age rule, the fail-safe): each end
    of edge k evaluates its term from its own fresh row and the newest row received from the
    other end; a term on data older than max_age steps is held. With every transit time 0 the
    rows received are this step's: bit-identical to `decoupled_step`. Returns 0."""
    receive(S, n, sched, r, ring_S, arrival, held, recv_S, edges, max_age, hold, age_hist,
            counts, failsafe)
    kxi = Q[Q_KXI]
    for i in range(S.shape[0]):
        for a in range(6):
            u[i, a] = -kxi * S[i, S_XI + a]
    for k in range(edges.shape[0]):
        i = edges[k, 0]
        j = edges[k, 1]
        lp = 2 * k      # i → j
        ln = 2 * k + 1  # j → i
        if age_of(n, held, ln) <= max_age:     # positive end i: X̄_k = X_j(s)⁻¹ X_i(n)
            Rb, pb = rel_pose_rows(S, i, recv_S, ln)
            tp, tn = edge_terms(Rb, pb, _xi(S, i), _xi(recv_S, ln), Q)
            for a in range(6):
                term[ln, a] = tp[a]
        for a in range(6):
            u[i, a] += term[ln, a]
        if age_of(n, held, lp) <= max_age:     # negative end j: X̄_k = X_j(n)⁻¹ X_i(s)
            Rb, pb = rel_pose_rows(recv_S, lp, S, j)
            tp, tn = edge_terms(Rb, pb, _xi(recv_S, lp), _xi(S, j), Q)
            for a in range(6):
                term[lp, a] = tn[a]
        for a in range(6):
            u[j, a] += term[lp, a]
    fail_safe(u, failsafe)
    return 0


class DecoupledStep(NamedTuple):
    """The compiled step's record (`cosim.controllers.law_step`)."""

    edges: np.ndarray
    Q: np.ndarray
    u: np.ndarray


@compiled_law_step(DecoupledStep)
@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _step(a, S, h):
    return decoupled_step(S, a.edges, a.Q, a.u)


class DecoupledLaw:
    """The network view: every agent's wrench (2) at a communication point."""

    name = "decoupled"
    edge_state = None      # no θ-like state

    def __init__(self, graph, weighting, gains):
        self.graph = graph
        self.Q = pack(weighting.A, weighting.d, gains.k_X, gains.k_xi, gains.k_e)
        self.edges = np.ascontiguousarray(graph.edges, dtype=np.int64)
        self.u = np.zeros((graph.n, 6))

    def write_wrench_into(self, buf):
        """Compute future wrenches straight into buf (N, 6), e.g. a plant's input buffer."""
        if not (isinstance(buf, np.ndarray) and buf.shape == (self.graph.n, 6)
                and buf.dtype == np.float64 and buf.flags.c_contiguous and buf.flags.writeable):
            raise Se3SyncError(f"wrench buffer must be a writable C-contiguous float64 array of "
                               f"shape ({self.graph.n}, 6)")
        self.u = buf

    def reset(self, theta0=None) -> None:
        if theta0 is not None and np.any(np.asarray(theta0, float) != 0):
            raise Se3SyncError("the decoupled law has no θ: theta0 must be zero or omitted")

    def step_state(self, S, h: float):
        decoupled_step(S, self.edges, self.Q, self.u)
        return self.u, ()

    def compiled_step(self) -> DecoupledStep:
        return DecoupledStep(self.edges, self.Q, self.u)

    def agent_view(self, i: int) -> "DecoupledAgent":
        return DecoupledAgent(i, self.graph.local_edges(int(i)), self.Q)

    def delayed_step(self) -> DelayedLaw:
        edges, Q, u = self.edges, self.Q, self.u

        def step(S, n, sched, r, ring_S, ring_theta, arrival, held, recv_S, recv_theta, term,
                 max_age, hold, h, age_hist, counts, failsafe):
            return delayed_decoupled_step(S, n, sched, r, ring_S, arrival, held, recv_S, term,
                                          max_age, hold, edges, Q, u, age_hist, counts, failsafe)

        return DelayedLaw(step, None, u)


class DecoupledAgent:
    """Agent i's view: its wrench (2) from X̄_k of its edges, its ξ_i and its neighbours' ξ_j
    (the `controller.AgentStepper` interface, with nothing to jump or flow: θ ≡ 0)."""

    hybrid = False

    def __init__(self, agent: int, local_edges: dict, Q):
        self.agent = int(agent)
        self.local_edges = {int(k): (int(a), int(b)) for k, (a, b) in sorted(local_edges.items())}
        self.Q = Q
        self.owned = [k for k, (a, _) in self.local_edges.items() if a == self.agent]
        # no θ: what an agent publishes for its owned edges (the link carries one per edge) is 0
        self.theta = {k: 0.0 for k in self.owned}
        self.last_mu = {}
        self._tp = np.empty(6)
        self._tn = np.empty(6)

    @property
    def theta_owned(self) -> dict:
        return dict(self.theta)

    def jump(self, rel: dict, edges=None) -> tuple:
        self.last_mu = {}
        return ()

    def flow(self, rel: dict, h: float, edges=None) -> None:
        pass

    def terms(self, rel: dict, xi_i, xi_nbrs: dict, theta_nbrs: dict, edges=None) -> dict:
        """Edge k's part of u_i, {k: (6,)}, for k in ``edges`` (default all of 𝓜_i): t⁺_k at
        the positive end, t⁻_k at the negative; rel[k] = (R̄ (3, 3), p̄ (3,)) or X̄_k (4, 4)."""
        xi_i = np.asarray(xi_i, float)
        out = {}
        for k, (a, b) in self.local_edges.items():
            if edges is not None and k not in edges:
                continue
            Xk = rel[k]
            if isinstance(Xk, tuple):
                Rb, pb = Xk
            else:
                Xk = np.asarray(Xk, float)
                Rb, pb = np.ascontiguousarray(Xk[:3, :3]), np.ascontiguousarray(Xk[:3, 3])
            mine = a == self.agent
            xa = xi_i if mine else np.asarray(xi_nbrs[a], float)
            xb = np.asarray(xi_nbrs[b], float) if mine else xi_i
            edge_terms_into(Rb, pb, xa, xb, self.Q, self._tp, self._tn)
            out[k] = (self._tp if mine else self._tn).copy()
        return out

    def wrench_of(self, xi_i, terms: dict) -> np.ndarray:
        """u_i = −k_ξ ξ_i + Σ_k term_k, summed in ascending k (the network view's order)."""
        u = -self.Q[Q_KXI] * np.asarray(xi_i, float)
        for k in sorted(terms):
            u = u + terms[k]
        return u

    def wrench(self, rel: dict, xi_i, xi_nbrs: dict, theta_nbrs: dict) -> np.ndarray:
        return self.wrench_of(xi_i, self.terms(rel, xi_i, xi_nbrs, theta_nbrs))

    def step(self, rel, xi_i, xi_nbrs, theta_nbrs, h):
        return self.wrench(rel, xi_i, xi_nbrs, theta_nbrs), ()


def make(scenario) -> DecoupledLaw:
    """The decoupled law with the scenario's weighting (A, d) and gains (k_X, k_ξ, k_e)."""
    return DecoupledLaw(scenario.graph, scenario.weighting, scenario.gains)
