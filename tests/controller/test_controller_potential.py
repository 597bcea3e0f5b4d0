"""U, T_uc, Γ, μ_U, ψ̄_∇ and ∇_θU against their definitions and finite differences."""
import warnings

import numpy as np
import pytest
from scipy.linalg import expm

import controller as C
from controller import potential, se3

from _paper import A, b, d, random_weighting

rng = np.random.default_rng(11)


def designs():
    """A non-diagonal 𝔸 (the paper's) and a diagonal one (b = 0, A diagonal)."""
    out = []
    wm = C.WeightingMatrix.from_blocks(A, b, d)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out.append(("paper", wm, C.design_synergy(wm, Theta=[0.3 * np.pi, -0.5 * np.pi], gamma=0.33, delta=0.02)))
    wd = C.WeightingMatrix.from_blocks(np.diag([1.0, 2.5, 4.0]), [0, 0, 0], 2.0)
    out.append(("diagonal", wd, C.design_synergy(wd)))
    wr = C.WeightingMatrix.from_blocks(*random_weighting(rng, 3)[:3])
    out.append(("random", wr, C.design_synergy(wr)))
    return out


DESIGNS = designs()
IDS = [n for n, _, _ in DESIGNS]


def U_def(wm, des, Xbar, theta):
    """`U_def` straight from its matrix definition, with scipy's expm for exp(θ u_c^)."""
    G = Xbar @ expm(theta * se3.hat(des.u_c))
    I = np.eye(4)
    return 0.5 * np.trace((I - G) @ wm.AA @ (I - G).T) + 0.5 * des.gamma * theta**2


@pytest.mark.parametrize("name,wm,des", DESIGNS, ids=IDS)
def test_T_uc_closed_form_is_exponential(name, wm, des):
    for th in rng.uniform(-4, 4, 20):
        assert np.allclose(potential.T_uc(des, wm, th), expm(th * se3.hat(des.u_c)), atol=1e-12)


@pytest.mark.parametrize("name,wm,des", DESIGNS, ids=IDS)
def test_U_explicit_equals_definition(name, wm, des):
    Xb = se3.random_pose(rng, 200, scale=2.0)
    th = rng.uniform(-3, 3, 200)
    got = potential.U(wm, des, Xb, th)
    ref = np.array([U_def(wm, des, X, t) for X, t in zip(Xb, th)])
    assert np.allclose(got, ref, rtol=1e-12, atol=1e-11)
    assert np.all(got > 0)
    assert potential.U(wm, des, np.eye(4), 0.0) == pytest.approx(0.0, abs=1e-14)


@pytest.mark.parametrize("name,wm,des", DESIGNS, ids=IDS)
def test_psi_bar_nabla_against_finite_differences(name, wm, des):
    """d/ds U(X̄ exp(s ξ^), θ)|₀ = 2 ξᵀ ψ̄_∇(X̄, θ) (`U_derivative` with `identa`)."""
    s = 1e-5
    for _ in range(60):
        Xb = se3.random_pose(rng, (), scale=2.0)
        th = rng.uniform(-3, 3)
        xi = rng.standard_normal(6)
        fd = (U_def(wm, des, Xb @ expm(s * se3.hat(xi)), th)
              - U_def(wm, des, Xb @ expm(-s * se3.hat(xi)), th)) / (2 * s)
        g = potential.psi_bar_nabla(wm, des, Xb, th)
        assert 2 * xi @ g == pytest.approx(fd, rel=1e-7, abs=1e-7)


@pytest.mark.parametrize("name,wm,des", DESIGNS, ids=IDS)
def test_grad_theta_against_finite_differences(name, wm, des):
    s = 1e-6
    for _ in range(60):
        Xb = se3.random_pose(rng, (), scale=2.0)
        th = rng.uniform(-3, 3)
        nu = rng.standard_normal()
        fd = (U_def(wm, des, Xb, th + s * nu) - U_def(wm, des, Xb, th - s * nu)) / (2 * s)
        assert nu * potential.grad_theta_U(wm, des, Xb, th) == pytest.approx(fd, rel=1e-7, abs=1e-7)


@pytest.mark.parametrize("name,wm,des", DESIGNS, ids=IDS)
def test_psi_bar_nabla_matches_st_b_matrix_form(name, wm, des):
    """`st_b`: ψ̄_∇ = Ad⁻ᵀ_{𝒯_uc(θ)} ψ̄((I − Γ⁻¹)𝔸), evaluated with 4×4 and 6×6 matrices."""
    Xb = se3.random_pose(rng, 50, scale=2.0)
    th = rng.uniform(-3, 3, 50)
    for X, t, g in zip(Xb, th, potential.psi_bar_nabla(wm, des, Xb, th)):
        Tu = expm(t * se3.hat(des.u_c))
        G = X @ Tu
        ref = np.linalg.inv(se3.Ad(Tu)).T @ se3.psi_bar((np.eye(4) - np.linalg.inv(G)) @ wm.AA)
        assert np.allclose(g, ref, atol=1e-10)
        # `st_c`
        gt = potential.grad_theta_U(wm, des, X, t)
        assert gt == pytest.approx(des.gamma * t + 2 * des.u_c @ se3.psi_bar((np.eye(4) - np.linalg.inv(G)) @ wm.AA))


@pytest.mark.parametrize("name,wm,des", DESIGNS, ids=IDS)
def test_mu_U_and_jump_map(name, wm, des):
    Xb = se3.random_pose(rng, 100, scale=2.0)
    th = rng.uniform(-3, 3, 100)
    U_theta = np.stack([potential.U(wm, des, Xb, t) for t in des.Theta], axis=-1)
    mu = potential.mu_U(wm, des, Xb, th)
    assert np.allclose(mu, potential.U(wm, des, Xb, th) - U_theta.min(axis=-1), atol=1e-11)
    assert np.allclose(potential.jump_map(wm, des, Xb), np.asarray(des.Theta)[U_theta.argmin(axis=-1)])


def test_jump_map_ties_go_to_first_element_of_Theta():
    """At an undesired critical point U(X̄, θ) = U(X̄, −θ): the first listed element wins."""
    wm = C.WeightingMatrix.from_blocks(A, b, d)
    lam, V = np.linalg.eigh(wm.W)
    R = se3.R_a(np.pi, V[:, 2])
    Xc = se3.T(R, (np.eye(3) - R) @ b / d)
    for Theta in ([0.3 * np.pi, -0.3 * np.pi], [-0.3 * np.pi, 0.3 * np.pi]):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            des = C.design_synergy(wm, Theta=Theta, gamma=0.33, delta=0.02)
        u_pair = potential.U(wm, des, Xc, np.array(Theta))
        assert abs(u_pair[0] - u_pair[1]) < 1e-12
        assert potential.jump_map(wm, des, Xc) == Theta[0]


def test_U_is_invariant_only_through_its_terms():
    """Changing θ leaves the position term of `U_explicit` unchanged (the paper's key remark)."""
    wm, des = DESIGNS[0][1], DESIGNS[0][2]
    Xb = se3.random_pose(rng, (), scale=2.0)
    R, p = Xb[:3, :3], Xb[:3, 3]
    pos_term = 0.5 * wm.d * np.sum((p - (np.eye(3) - R) @ wm.b / wm.d) ** 2)
    for t in (-1.0, 0.2, 2.5):
        rot_term = np.trace(wm.W @ (np.eye(3) - R @ se3.R_a(t, des.u_c1)))
        assert potential.U(wm, des, Xb, t) == pytest.approx(rot_term + 0.5 * des.gamma * t * t + pos_term)
