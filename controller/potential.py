"""U, μ_U, ψ̄_∇ and ∇_θU as functions of (X̄, θ), broadcasting over leading axes.

They call the per-edge kernels, so these are the numbers the control law uses.
"""
from __future__ import annotations

import numpy as np

from . import _kernels as K
from . import se3
from .design import SynergyDesign, WeightingMatrix
from .law import Gains
from .params import LawParameters

__all__ = ["T_uc", "Gamma", "U", "mu_U", "grad_theta_U", "psi_bar_nabla", "jump_map", "params"]


def params(weighting: WeightingMatrix, design: SynergyDesign, k_X=1.0, k_xi=1.0, k_e=1.0,
           k_theta=1.0) -> np.ndarray:
    """The packed parameter vector of `LawParameters` for these gains (unit gains by default:
    U, μ_U and the gradients do not depend on them)."""
    return LawParameters.of(weighting, design, Gains(k_X, k_xi, k_e, k_theta)).P


def T_uc(design: SynergyDesign, weighting: WeightingMatrix, theta):
    """𝒯_uc(θ) = exp(θ u_c^) = 𝒯(ℛ_a(θ, u_c1), (I − ℛ_a(θ, u_c1)) b/d) in closed form."""
    Ra = se3.R_a(theta, design.u_c1)
    c = weighting.b / weighting.d
    return se3.T(Ra, c - np.einsum("...ij,j->...i", Ra, c))


def Gamma(design, weighting, Xbar, theta):
    """Γ_𝔸(X̄, θ) = X̄ exp(θ u_c^) (`Gamma_def`)."""
    return np.asarray(Xbar, float) @ T_uc(design, weighting, theta)


def _loop(fn, Xbar, theta, out_shape):
    Xbar = np.asarray(Xbar, float)
    theta = np.asarray(theta, float)
    shape = np.broadcast_shapes(Xbar.shape[:-2], theta.shape)
    Xb = np.broadcast_to(Xbar, shape + (4, 4)).reshape(-1, 4, 4)
    th = np.broadcast_to(theta, shape).ravel()
    out = np.empty((Xb.shape[0],) + out_shape)
    for n in range(Xb.shape[0]):
        Rb = np.ascontiguousarray(Xb[n, :3, :3])
        pb = np.ascontiguousarray(Xb[n, :3, 3])
        out[n] = fn(Rb, pb, float(th[n]))
    return out.reshape(shape + out_shape)


def U(weighting, design, Xbar, theta):
    """U(X̄, θ) (`U_explicit`)."""
    P = params(weighting, design)
    return _loop(lambda R, p, t: K.edge_U(R, p, t, P), Xbar, theta, ())


def mu_U(weighting, design, Xbar, theta):
    """μ_U(X̄, θ) = U(X̄, θ) − min_{θ'∈Θ} U(X̄, θ') (`mu_U_def`)."""
    P = params(weighting, design)
    return _loop(lambda R, p, t: K.edge_mu(R, p, t, P)[0], Xbar, theta, ())


def jump_map(weighting, design, Xbar):
    """g(X̄) = argmin_{θ'∈Θ} U(X̄, θ') (`eqn: gtheta`), ties to the first element of Θ."""
    P = params(weighting, design)
    Theta = np.asarray(design.Theta)
    return _loop(lambda R, p, t: Theta[K.edge_mu(R, p, 0.0, P)[1]], Xbar, 0.0, ())


def grad_theta_U(weighting, design, Xbar, theta):
    """∇_θU(X̄, θ) (`st_c`)."""
    P = params(weighting, design)
    g = np.empty(6)
    return _loop(lambda R, p, t: K.edge_gradient(R, p, t, P, g), Xbar, theta, ())


def psi_bar_nabla(weighting, design, Xbar, theta):
    """ψ̄_∇(X̄, θ) = ψ̄(X̄⁻¹∇_X̄ U) (`st_b`), shape (..., 6)."""
    P = params(weighting, design)
    g = np.empty(6)

    def f(R, p, t):
        K.edge_gradient(R, p, t, P, g)
        return g.copy()

    return _loop(f, Xbar, theta, (6,))
