"""The distributed hybrid feedback (`ex_controller`) in two views, and the gradient baseline.

Sampled-data semantics at a communication point of length h:
    1. every edge k in its jump set 𝒥_k (μ_U ≥ δ) jumps, θ_k⁺ = argmin_{θ'∈Θ} U(X̄_k, θ');
    2. the wrench u_i is computed with the post-jump θ;
    3. θ_k flows over h: θ_k ← θ_k − h k_θ ∇_θU(X̄_k, θ_k) (forward Euler, held X̄_k).
Agent i owns θ_k for k ∈ 𝓜_i⁺.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from . import _agent_kernels as AK
from . import _kernels as K
from .design import SynergyDesign, WeightingMatrix
from .errors import Se3SyncError
from .graph import Graph
from .layout import XI, pack_state
from .params import LawParameters

__all__ = ["Gains", "JumpEvent", "HybridController", "GradientController", "AgentStepper",
           "pack_state", "V_bar", "jump_bound"]


@dataclass(frozen=True)
class Gains:
    """k_X, k_ξ, k_e, k_θ of `hybridcontroller`, all > 0."""

    k_X: float
    k_xi: float
    k_e: float
    k_theta: float = 1.0

    def __post_init__(self):
        for name in ("k_X", "k_xi", "k_e", "k_theta"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float, np.floating)) and math.isfinite(v) and v > 0):
                raise Se3SyncError(f"gains: {name} must be a finite number > 0, got {v!r}")


class JumpEvent(NamedTuple):
    """θ_k jumped at a communication point: edge k (from 1), θ⁻, θ⁺, and μ_U(X̄_k, θ⁻)."""

    edge: int
    theta_before: float
    theta_after: float
    mu: float


class HybridController:
    """The network view: one call computes every agent's wrench at a communication point.

    State: θ (M,). `step_state(S, h)` is the fast path (S as the plant FMU returns it);
    `step(X, xi, h)` accepts poses (N, 4, 4). Both return (u, events), u (N, 6) being a buffer
    that the next call overwrites. After a step, per edge: `theta` (after the flow), `mu`
    (μ_U at the communication point, before any jump), `jumped`, `theta_prev` (θ on entry)
    and `theta_jump` (θ after the jump stage, before the flow).
    """

    name = "hybrid"
    hybrid = True

    def __init__(self, graph: Graph, weighting: WeightingMatrix, design: SynergyDesign | None,
                 gains: Gains, theta0=None):
        if self.hybrid and design is None:
            raise Se3SyncError("the hybrid controller needs a synergy design")
        self.graph = graph
        self.weighting = weighting
        self.design = design
        self.gains = gains
        self.params = LawParameters.of(weighting, design, gains)
        self.P = self.params.P
        self.edges = np.ascontiguousarray(graph.edges)
        M = graph.M
        self.theta = np.zeros(M)
        self.reset(theta0)
        self.u = np.zeros((graph.n, 6))
        self.mu = np.zeros(M)
        self.jumped = np.zeros(M, dtype=np.bool_)
        self.theta_prev = np.zeros(M)
        self.theta_jump = np.zeros(M)

    def write_wrench_into(self, buf):
        """Compute future wrenches straight into buf (N, 6), e.g. a plant's input buffer,
        so that applying them costs no copy."""
        if not (isinstance(buf, np.ndarray) and buf.shape == (self.graph.n, 6)
                and buf.dtype == np.float64 and buf.flags.c_contiguous and buf.flags.writeable):
            raise Se3SyncError(f"wrench buffer must be a writable C-contiguous float64 array of "
                               f"shape ({self.graph.n}, 6)")
        self.u = buf

    def reset(self, theta0=None):
        M = self.graph.M
        if theta0 is None or not self.hybrid:
            self.theta[:] = 0.0
        else:
            t = np.asarray(theta0, float).ravel()
            if t.shape != (M,) or not np.all(np.isfinite(t)):
                raise Se3SyncError(f"theta0 must hold {M} finite values, got {t.tolist()}")
            self.theta[:] = t

    def step_state(self, S, h: float):
        n = K.network_step(S, self.theta, self.edges, self.P, float(h), self.hybrid,
                           self.u, self.mu, self.jumped, self.theta_prev, self.theta_jump)
        if n == 0:
            return self.u, ()
        return self.u, tuple(
            JumpEvent(int(k) + 1, float(self.theta_prev[k]), float(self.theta_jump[k]),
                      float(self.mu[k]))
            for k in np.flatnonzero(self.jumped))

    def step(self, X, xi, h: float):
        return self.step_state(pack_state(X, xi), h)

    def U_edges(self, S, theta=None) -> np.ndarray:
        """U(X̄_k, θ_k) for every edge (θ defaults to the current state)."""
        out = np.empty(self.graph.M)
        th = self.theta if theta is None else np.asarray(theta, float)
        K.network_U(np.asarray(S, float), th, self.edges, self.P, out)
        return out

    def V_bar(self, S, inertia, theta=None) -> float:
        """V̄ = k_X Σ_k U(X̄_k, θ_k) + Σ_i ξ_iᵀ 𝕀_i ξ_i (`V_def`); inertia (N, 6, 6) or (6, 6)."""
        return _V_bar(self.params, self.edges, np.asarray(S, float),
                      self.theta if theta is None else np.asarray(theta, float), inertia)


class GradientController(HybridController):
    """The gradient-only baseline: θ ≡ 0 and no jumps (smooth, hence at best almost global)."""

    name = "gradient"
    hybrid = False

    def __init__(self, graph: Graph, weighting: WeightingMatrix, gains: Gains,
                 design: SynergyDesign | None = None, theta0=None):
        if theta0 is not None and np.any(np.asarray(theta0, float) != 0):
            raise Se3SyncError("the gradient baseline has θ ≡ 0: theta0 must be zero or omitted")
        super().__init__(graph, weighting, None, gains)


def _V_bar(params: LawParameters, edges, S, theta, inertia) -> float:
    U = np.empty(edges.shape[0])
    K.network_U(S, theta, edges, params.P, U)
    xi = S[:, XI]
    I = np.broadcast_to(np.asarray(inertia, float), (S.shape[0], 6, 6))
    return float(params.k_X * U.sum() + np.einsum("ni,nij,nj->", xi, I, xi))


def V_bar(graph: Graph, weighting: WeightingMatrix, design: SynergyDesign | None, gains: Gains,
          S, theta, inertia) -> float:
    """V̄ = k_X Σ_k U(X̄_k, θ_k) + Σ_i ξ_iᵀ 𝕀_i ξ_i (`V_def`); inertia (N, 6, 6) or (6, 6).
    With ``design=None`` (the gradient baseline) θ ≡ 0."""
    S = np.asarray(S, float)
    th = np.zeros(graph.M) if design is None else np.asarray(theta, float)
    return _V_bar(LawParameters.of(weighting, design, gains),
                  np.ascontiguousarray(graph.edges), S, th, inertia)


def jump_bound(V0: float, k_X: float, delta: float) -> int:
    """⌈V̄(0)/(k_X δ)⌉, Theorem 1's bound on the number of jumps."""
    q = V0 / (k_X * delta)
    if not math.isfinite(q):
        raise Se3SyncError(f"the jump bound V̄(0)/(k_X δ) = {V0:.6g}/({k_X:.6g}·{delta:.6g}) is "
                           "not finite: the initial state or the gains are out of range")
    return int(math.ceil(q))


class AgentStepper:
    """The per-agent view: agent i computes u_i from what it can know.

    It is handed its own edges only ({k: (positive, negative)}), and at each communication
    point the relative poses X̄_k of those edges, its own ξ_i, its neighbours' ξ_j and the θ_k
    of the edges its neighbours own (as published after their jumps). It owns θ_k, k ∈ 𝓜_i⁺.
    Call `jump` on every agent, exchange `theta_owned`, then `wrench`, then `flow`; or `step`.
    """

    def __init__(self, agent: int, local_edges: dict, weighting: WeightingMatrix,
                 design: SynergyDesign | None, gains: Gains, theta0: dict | None = None):
        self.agent = int(agent)
        self.hybrid = design is not None
        self.local_edges = {int(k): (int(a), int(b)) for k, (a, b) in sorted(local_edges.items())}
        for k, (a, b) in self.local_edges.items():
            if self.agent not in (a, b):
                raise Se3SyncError(f"agent {self.agent}: edge {k} = ({a}, {b}) is not one of its edges")
        self.owned = [k for k, (a, _) in self.local_edges.items() if a == self.agent]
        self.params = LawParameters.of(weighting, design, gains)
        self.P = self.params.P
        self.theta = {k: float((theta0 or {}).get(k, 0.0)) if self.hybrid else 0.0 for k in self.owned}

    @property
    def theta_owned(self) -> dict:
        return dict(self.theta)

    @staticmethod
    def _split(Xk):
        """X̄_k as a 4×4 pose, or already split as (R̄ (3, 3), p̄ (3,)) (`kernels.relative_pose`)."""
        if isinstance(Xk, tuple):
            return Xk
        Xk = np.asarray(Xk, float)
        return np.ascontiguousarray(Xk[:3, :3]), np.ascontiguousarray(Xk[:3, 3])

    def jump(self, rel: dict, edges=None) -> tuple:
        """Phase 1: jump every owned edge in its jump set. rel: {k: X̄_k (4, 4)}. ``edges``: only
        these owned edges (an edge whose neighbour data are too old neither jumps nor flows).
        ``last_mu`` keeps μ_U(X̄_k, θ_k) before the jump of each edge looked at."""
        self.last_mu = {}
        if not self.hybrid:
            return ()
        events = []
        for k in (self.owned if edges is None else [k for k in self.owned if k in edges]):
            Rb, pb = self._split(rel[k])
            mu, jstar = K.edge_mu(Rb, pb, self.theta[k], self.P)
            self.last_mu[k] = float(mu)
            if mu >= self.P[K.P_DELTA]:
                before = self.theta[k]
                self.theta[k] = float(self.P[K.P_THETA + jstar])
                events.append(JumpEvent(k, before, self.theta[k], float(mu)))
        return tuple(events)

    def terms(self, rel: dict, xi_i, xi_nbrs: dict, theta_nbrs: dict, edges=None) -> dict:
        """Edge k's part of u_i, {k: (6,)}, for k in ``edges`` (default all of 𝓜_i):
        −k_X ψ̄_∇(X̄_k, θ_k) − k_e(ξ_i − ξ_j) at the positive end, k_X Ad⁻ᵀ_{X̄_k} ψ̄_∇ + k_e(ξ_j − ξ_i)
        at the negative end, θ_k being the neighbour's (``theta_nbrs``) for k ∈ 𝓜_i⁻
        (`kernels.edge_term`, the agent process's compiled step's arithmetic)."""
        P = self.P
        xi_i = np.asarray(xi_i, float)
        out = {}
        for k, (a, b) in self.local_edges.items():
            if edges is not None and k not in edges:
                continue
            Rb, pb = self._split(rel[k])
            t = np.empty(6)
            if a == self.agent:
                AK.edge_term(Rb, pb, self.theta[k], xi_i, np.asarray(xi_nbrs[b], float), True,
                             P, t)
            else:
                th = float(theta_nbrs[k]) if self.hybrid else 0.0
                AK.edge_term(Rb, pb, th, np.asarray(xi_nbrs[a], float), xi_i, False, P, t)
            out[k] = t
        return out

    def wrench_of(self, xi_i, terms: dict) -> np.ndarray:
        """u_i = −k_ξ ξ_i + Σ_k term_k, summed in ascending k (the network view's order;
        `kernels.wrench_sum`)."""
        T = np.array([terms[k] for k in sorted(terms)], dtype=float).reshape(-1, 6)
        u = np.empty(6)
        AK.wrench_sum(np.asarray(xi_i, float), T, self.P, u)
        return u

    def wrench(self, rel: dict, xi_i, xi_nbrs: dict, theta_nbrs: dict) -> np.ndarray:
        """Phase 2: u_i from X̄_k (k ∈ 𝓜_i), ξ_i, {j: ξ_j} and {k: θ_k} for k ∈ 𝓜_i⁻."""
        return self.wrench_of(xi_i, self.terms(rel, xi_i, xi_nbrs, theta_nbrs))

    def flow(self, rel: dict, h: float, edges=None):
        """Phase 3: θ_k ← θ_k − h k_θ ∇_θU for every owned edge (or those in ``edges``)."""
        if not self.hybrid:
            return
        for k in (self.owned if edges is None else [k for k in self.owned if k in edges]):
            Rb, pb = self._split(rel[k])
            self.theta[k] = float(AK.edge_flow(Rb, pb, self.theta[k], self.P, float(h)))

    def step(self, rel, xi_i, xi_nbrs, theta_nbrs, h):
        events = self.jump(rel)
        u = self.wrench(rel, xi_i, xi_nbrs, theta_nbrs)
        self.flow(rel, h)
        return u, events
