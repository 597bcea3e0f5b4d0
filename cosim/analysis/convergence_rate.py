"""Local convergence rate of the sampled loop linearised at consensus, θ included.

The slowest mode is the eigenvalue λ* of largest modulus once the rigid motion's six 1's are
removed; its decay rate is r = −ln|λ*|/h (1/s), and a relative-pose error e decays like
e·exp(−r t) once the faster modes have died out. So reaching the sweep's tolerances
(rot_tol = pos_tol = 1e-2) from an error e₀ takes about ln(e₀/1e-2)/r. This is a local
prediction: from far away the jumps and the nonlinear flow come first.

Which gain limits it: ∂r/∂ln k for k_X, k_ξ, k_e, k_θ by central differences (k → k e^{±ε}),
the gains the law's linearisation does not depend on left out (k_θ without a θ-like state),
and the slowest mode's eigenvector split into its pose (δ), velocity (ξ) and θ parts (fractions
of its squared norm; in the modal coordinates of `stability_sparse` the split is the same as in
the original ones, as U ⊗ I and V are orthogonal).
"""
from __future__ import annotations

import math
import types

import numpy as np

from controller import layout

from ..signals import interruptible
from ..threads import analysis as blas_policy
from .linear import GAINS, law_of
from .stability_sparse import (
    DENSE_MAX,
    Linearisation,
    _rigid_basis,
    common_mode_eigenvalues,
    modal_matrices,
    sparse_loop,
)

__all__ = ["slowest_mode", "convergence", "initial_error", "ROT_TOL", "POS_TOL"]

ROT_TOL = 1e-2
POS_TOL = 1e-2


def initial_error(scenario) -> float:
    """max over edges of ‖I − R̄_k‖_F and ‖p̄_k‖ at the scenario's initial condition."""
    S = scenario.S0
    E = np.asarray(scenario.graph.edges)
    if E.size == 0:
        return 0.0
    R = layout.rotations(S)
    p = layout.positions(S)
    i, j = E[:, 0], E[:, 1]
    Rb = np.einsum("kea,kec->kac", R[j], R[i])                 # R_jᵀ R_i
    pb = np.einsum("kea,ke->ka", R[j], p[i] - p[j])            # R_jᵀ (p_i − p_j)
    rot = np.linalg.norm(np.eye(3) - Rb, axis=(1, 2))
    return float(max(rot.max(), np.linalg.norm(pb, axis=1).max()))


def slowest_mode(lin: Linearisation, h: float) -> dict:
    """{"lambda", "rate", "fractions" (pose, velocity, theta), "graph_eigenvalue"}."""
    if lin.method == "modal":
        Phi = modal_matrices(lin.s, h, lin.blocks, lin.I6inv[0], lin.k_xi, lin.hybrid)
        lam = np.linalg.eigvals(Phi)
        com = common_mode_eigenvalues(h, lin.I6inv[0], lin.k_xi)
        l_idx = np.unravel_index(np.argmax(np.abs(lam)), lam.shape) if lam.size else None
        if l_idx is None or np.abs(com).max() > np.abs(lam[l_idx]):
            c = com[np.argmax(np.abs(com))]
            return {"lambda": complex(c), "rate": -math.log(abs(c)) / h,
                    "fractions": {"pose": 0.0, "velocity": 1.0, "theta": 0.0},
                    "graph_eigenvalue": 0.0}
        w, V = np.linalg.eig(Phi[l_idx[0]])
        m = int(np.argmin(np.abs(w - lam[l_idx])))
        v = np.abs(V[:, m]) ** 2
        lam_star = complex(w[m])
        s = float(lin.s[l_idx[0]])
    else:
        n = 12 * lin.N + (lin.M if lin.hybrid else 0)
        Phi = sparse_loop(lin, h)
        Q = _rigid_basis(lin.N, n)
        if n <= DENSE_MAX:
            A = Phi.toarray()
            A -= (A @ Q) @ Q.T
            A -= Q @ (Q.T @ A)
            w, V = interruptible(np.linalg.eig, A)
            m = int(np.argmax(np.abs(w)))
        else:
            import scipy.sparse.linalg as sla

            def mv(x):
                x = np.asarray(x).ravel()
                x = x - Q @ (Q.T @ x)
                y = Phi @ x
                return y - Q @ (Q.T @ y)
            op = sla.LinearOperator((n, n), matvec=mv, dtype=float)
            w, V = sla.eigs(op, k=6, which="LM", tol=1e-13, ncv=60, maxiter=20000)
            m = int(np.argmax(np.abs(w)))
        lam_star = complex(w[m])
        x = np.abs(V[:, m]) ** 2
        N6 = 6 * lin.N
        v = np.concatenate([[x[:N6].sum()] * 1, [x[N6:2 * N6].sum()], [x[2 * N6:].sum()]])
        v = np.concatenate([np.full(6, v[0] / 6), np.full(6, v[1] / 6), v[2:3]])
        s = float("nan")
    tot = v.sum()
    fr = {"pose": float(v[0:6].sum() / tot), "velocity": float(v[6:12].sum() / tot),
          "theta": float(v[12:].sum() / tot)}
    return {"lambda": lam_star, "rate": -math.log(abs(lam_star)) / h, "fractions": fr,
            "graph_eigenvalue": s}


@blas_policy
def convergence(scenario, h: float | None = None, law="hybrid", e0: float | None = None,
                eps: float = 0.05, lin: Linearisation | None = None) -> dict:
    """The slowest decay rate, the time to the sweep's tolerances from e0 (default: the
    scenario's initial error), ∂rate/∂ln(gain) and the slowest mode's composition; ``law``: a
    registered law name (True / False: hybrid / gradient)."""
    h = float(scenario.step if h is None else h)
    law = law_of(law)
    lin = lin or Linearisation(scenario, law)
    mode = slowest_mode(lin, h)
    rate = mode["rate"]
    e0 = initial_error(scenario) if e0 is None else float(e0)
    tol = min(ROT_TOL, POS_TOL)
    if rate <= 0:
        t_conv = float("inf")
    else:
        t_conv = max(0.0, math.log(max(e0, tol) / tol) / rate)
    sens = {}
    g = scenario.gains
    for name in GAINS:
        r = []
        for sgn in (1.0, -1.0):
            vals = {k: float(getattr(g, k)) for k in GAINS}
            vals[name] *= math.exp(sgn * eps)
            li = Linearisation(scenario, law, gains=types.SimpleNamespace(**vals),
                               force_sparse=lin.method != "modal",
                               laplacian=getattr(lin, "laplacian", None))
            if sgn > 0 and li.k_xi == lin.k_xi and np.array_equal(li.J, lin.J):
                break       # a gain the law's loop does not depend on (k_θ without θ)
            r.append(slowest_mode(li, h)["rate"])
        if len(r) == 2:
            sens[name] = (r[0] - r[1]) / (2 * eps)
    limiting = max(sens, key=lambda k: abs(sens[k])) if sens else None
    return {"rate": rate, "time_constant": (1.0 / rate) if rate > 0 else float("inf"),
            "lambda_slowest": [mode["lambda"].real, mode["lambda"].imag],
            "slowest_mode": mode["fractions"], "graph_eigenvalue": mode["graph_eigenvalue"],
            "from_error": e0, "tolerance": tol, "time_to_tolerance": t_conv,
            "sensitivity": sens, "limiting_gain": limiting}
