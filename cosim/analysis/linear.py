"""A law's loop linearised at consensus, from the law's own step: what `check` needs of any law.

The analysis (`stability`, `stability_sparse`, `delay_margin`, `convergence_rate`) needs three
things of a law, all taken here by central finite differences of the law's ``step_state`` at
consensus (X_i = exp(δ_i^), ξ_i = 0, θ = 0), so that a law registered in `cosim.registry.LAWS`
is analysed exactly as it runs, with nothing declared for it:

* ``k_xi``: its own-velocity gain. The wrench of a lone agent must be u_i = −k_ξ ξ_i (checked on
  ξ = e_c and 2e_c, and on a rotated, displaced pose with ξ = 0), which is what decouples the
  loop by graph modes and what makes the rigid motion of the group a mode at 1;
* the edge Jacobian J (13 × 25) of one edge k = (i, j) on two agents, the own-velocity terms
  removed: rows u_i (6), u_j (6), θ̇_k (1); columns δ_i, δ_j, ξ_i, ξ_j (6 each), θ_k. A law
  whose wrench is a sum over its edges of terms in (X̄_k, ξ_i, ξ_j, θ_k), as the paper's is,
  is described by it on any tree (every edge sits at the same point at consensus);
* whether it has a θ-like state (its ``edge_state``): θ_k is then a state of the loop, flowing
  as θ_k(n+1) = θ_k(n) + h·θ̇_k (the step is evaluated with h = 1 to read θ̇_k = θ⁺ − θ).

No jump may fire at consensus (μ_U < 0 < δ there); one that did is an error. `loop_jacobian` is
the same on the whole graph, the dense reference (`stability.linearise`).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from controller import Gains, se3
from controller.errors import Se3SyncError
from controller.layout import pack_state

from ..controllers import make_controller
from ..scenario import restrict

__all__ = ["law_of", "edge_jacobian", "loop_jacobian", "own_velocity_gain", "GAINS"]

GAINS = ("k_X", "k_xi", "k_e", "k_theta")


def law_of(law) -> str:
    """A registered law's name; True / False stand for "hybrid" / "gradient" (θ a state or not,
    the analysis' former switch)."""
    if isinstance(law, (bool, np.bool_)):
        return "hybrid" if law else "gradient"
    return str(law)


def _with_gains(scenario, gains):
    if gains is None:
        return scenario
    return dataclasses.replace(scenario, gains=Gains(**{k: float(getattr(gains, k))
                                                         for k in GAINS}))


class _Stepper:
    """The law built on a scenario, as a function of the loop's state x = (δ, ξ, θ)."""

    def __init__(self, scenario, law: str):
        self.law = make_controller(law, scenario)
        self.name = law
        self.N, self.M = scenario.graph.n, scenario.graph.M
        self.state = getattr(self.law, "edge_state", None)

    def __call__(self, x):
        N = self.N
        S = pack_state(se3.exp_se3(x[:6 * N].reshape(N, 6)), x[6 * N:12 * N].reshape(N, 6))
        es = self.state
        if es is not None:
            es.theta[:] = x[12 * N:]
        u, events = self.law.step_state(S, 1.0)
        if events:
            raise Se3SyncError(f"check: the law {self.name!r} jumped while being linearised at "
                               f"consensus")
        if es is None:
            return u.ravel().copy()
        # with h = 1 the flow gives θ⁺ − θ = θ̇
        return np.concatenate([u.ravel(), es.theta - x[12 * N:]])


def own_velocity_gain(scenario, law="hybrid", gains=None) -> float:
    """k_ξ of u_i = −k_ξ ξ_i, the wrench of a lone agent (see the module docstring)."""
    sc = _with_gains(scenario, gains)
    name = law_of(law)
    f = _Stepper(restrict(sc, [1])[0], name)
    x = np.zeros(12)
    K = np.zeros((6, 6))
    for c in range(6):
        x[6 + c] = 1.0
        K[:, c] = -f(x)
        x[6 + c] = 2.0
        twice = -f(x)
        x[6 + c] = 0.0
        if not np.allclose(twice, 2.0 * K[:, c], rtol=1e-12, atol=0.0):
            K[0, 0] = np.nan
    k = K[0, 0]
    x[:6] = [0.3, -0.2, 0.5, 1.0, -2.0, 0.5]       # a rotated, displaced lone agent at rest
    if not (np.isfinite(k) and np.array_equal(K, k * np.eye(6)) and not np.any(f(x))):
        raise Se3SyncError(f"check: the law {name!r} does not act on a lone agent as "
                           f"u_i = -k_xi xi_i, which the linearised analysis needs")
    return float(k)


def edge_jacobian(scenario, law="hybrid", gains=None, eps: float = 1e-6):
    """(J (13 × 25), k_xi, has_state): the edge Jacobian of the law on the scenario's first edge
    (its two agents, `cosim.scenario.restrict`), own-velocity terms removed; the θ row and
    column are zero when the law has no θ-like state."""
    sc = _with_gains(scenario, gains)
    name = law_of(law)
    k_xi = own_velocity_gain(sc, name)
    if sc.graph.M == 0:
        raise Se3SyncError("check: the graph has no edge to linearise")
    f = _Stepper(restrict(sc, sc.graph.edge_list[0])[0], name)
    has_state = f.state is not None
    J = np.zeros((13, 25))
    for c in range(25 if has_state else 24):
        e = np.zeros(25 if has_state else 24)
        e[c] = eps
        col = (f(e) - f(-e)) / (2 * eps)
        J[:col.size, c] = col
    J[0:6, 12:18] += k_xi * np.eye(6)
    J[6:12, 18:24] += k_xi * np.eye(6)
    return J, k_xi, has_state


def loop_jacobian(scenario, law="hybrid", eps: float = 1e-6):
    """(K (6N × n_x), G (M' × n_x)) on the whole graph, n_x = 12N + M' with M' = M if the law
    has a θ-like state, else 0: u = K x and θ̇ = G x at first order."""
    f = _Stepper(scenario, law_of(law))
    N, M = f.N, f.M
    Mt = M if f.state is not None else 0
    nx = 12 * N + Mt
    Kx = np.zeros((6 * N, nx))
    G = np.zeros((Mt, nx))
    for c in range(nx):
        e = np.zeros(nx)
        e[c] = eps
        col = (f(e) - f(-e)) / (2 * eps)
        Kx[:, c] = col[:6 * N]
        G[:, c] = col[6 * N:]
    return Kx, G
