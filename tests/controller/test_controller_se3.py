"""SE(3) toolkit: the paper's identities, group axioms and exp/log, on random inputs."""
import numpy as np
import pytest
from scipy.linalg import expm, logm

from controller import se3

rng = np.random.default_rng(20261121)


def test_random_rotations_are_rotations():
    R = se3.random_rotation(rng, 500)
    assert np.allclose(R @ np.swapaxes(R, -1, -2), np.eye(3), atol=1e-14)
    assert np.allclose(np.linalg.det(R), 1.0, atol=1e-14)


def test_hat_vee_and_skew():
    xi = rng.standard_normal((50, 6))
    y, z = rng.standard_normal((2, 50, 3))
    assert np.allclose(se3.vee(se3.hat(xi)), xi)
    assert np.allclose(np.einsum("nij,nj->ni", se3.skew(y), z), np.cross(y, z))


def test_identa_inner_product():
    """⟨⟨𝔸, x^⟩⟩ = 2 xᵀ ψ̄(𝔸) for any 4×4 𝔸."""
    AA = rng.standard_normal((200, 4, 4))
    x = rng.standard_normal((200, 6))
    lhs = np.einsum("nij,nij->n", AA, se3.hat(x))
    rhs = 2 * np.einsum("ni,ni->n", x, se3.psi_bar(AA))
    assert np.allclose(lhs, rhs, rtol=1e-13, atol=1e-12)


def test_psi_definition():
    A = rng.standard_normal((100, 3, 3))
    y = rng.standard_normal((100, 3))
    assert np.allclose(np.einsum("nij,nij->n", A, se3.skew(y)), 2 * np.einsum("ni,ni->n", y, se3.psi(A)))


def test_identb():
    """ψ̄(Xᵀ(I − X)𝔸) = −ψ̄((I − X⁻¹)𝔸)."""
    X = se3.random_pose(rng, 200, scale=3.0)
    AA = rng.standard_normal((200, 4, 4))
    I = np.eye(4)
    lhs = se3.psi_bar(np.swapaxes(X, -1, -2) @ (I - X) @ AA)
    rhs = -se3.psi_bar((I - se3.inverse(X)) @ AA)
    assert np.allclose(lhs, rhs, atol=1e-11)


def test_props():
    X = se3.random_pose(rng, 200, scale=3.0)
    x = rng.standard_normal((200, 6))
    # (propa) Ad_{X⁻¹} = Ad_X⁻¹
    assert np.allclose(se3.Ad(se3.inverse(X)), np.linalg.inv(se3.Ad(X)), atol=1e-11)
    # (propb) X x^ X⁻¹ = (Ad_X x)^, and Ad(X)ξ against (X ξ^ X⁻¹)^∨
    lhs = X @ se3.hat(x) @ se3.inverse(X)
    assert np.allclose(lhs, se3.hat(np.einsum("nij,nj->ni", se3.Ad(X), x)), atol=1e-11)
    assert np.allclose(se3.vee(lhs), np.einsum("nij,nj->ni", se3.Ad(X), x), atol=1e-11)
    # (propc) ad_x x = 0
    assert np.allclose(np.einsum("nij,nj->ni", se3.ad(x), x), 0, atol=1e-13)
    # ad is the derivative of Ad at the identity: Ad_{exp(s y^)} x ≈ x + s ad_y x
    y = rng.standard_normal((200, 6))
    s = 1e-6
    fd = (np.einsum("nij,nj->ni", se3.Ad(se3.exp_se3(s * y)), x)
          - np.einsum("nij,nj->ni", se3.Ad(se3.exp_se3(-s * y)), x)) / (2 * s)
    assert np.allclose(fd, np.einsum("nij,nj->ni", se3.ad(y), x), atol=1e-7)
    # Ad is a group homomorphism
    Y = se3.random_pose(rng, 200)
    assert np.allclose(se3.Ad(X @ Y), se3.Ad(X) @ se3.Ad(Y), atol=1e-11)


def test_Ad_inv_T_closed_form():
    X = se3.random_pose(rng, 100, scale=3.0)
    assert np.allclose(se3.Ad_inv_T(X), np.swapaxes(np.linalg.inv(se3.Ad(X)), -1, -2), atol=1e-11)


def test_group_axioms_and_inverse():
    X, Y, Z = (se3.random_pose(rng, 100, scale=2.0) for _ in range(3))
    assert np.allclose((X @ Y) @ Z, X @ (Y @ Z), atol=1e-12)
    assert np.allclose(X @ se3.inverse(X), np.eye(4), atol=1e-13)
    assert np.allclose(se3.inverse(X), np.linalg.inv(X), atol=1e-12)
    assert np.allclose(se3.inverse(X @ Y), se3.inverse(Y) @ se3.inverse(X), atol=1e-12)


def test_exp_matches_matrix_exponential():
    xi = rng.standard_normal((100, 6)) * 2
    ref = np.array([expm(se3.hat(x)) for x in xi])
    assert np.allclose(se3.exp_se3(xi), ref, atol=1e-12)
    w = rng.standard_normal((100, 3)) * 2
    assert np.allclose(se3.exp_so3(w), np.array([expm(se3.skew(x)) for x in w]), atol=1e-12)


@pytest.mark.parametrize("scale", [1e-14, 1e-9, 1e-6, 1e-4, 1e-3, 2e-3, 1e-2, 0.099, 0.101, 0.5, 2.0])
def test_exp_log_round_trip_all_scales(scale):
    """log(exp(ξ)) = ξ across every series switch: ω to 1e-12 of its norm, v to 1e-12 of ‖ξ‖."""
    xi = rng.standard_normal((200, 6))
    xi[:, :3] *= scale / np.linalg.norm(xi[:, :3], axis=1, keepdims=True)
    back = se3.log_se3(se3.exp_se3(xi))
    err_w = np.linalg.norm(back[:, :3] - xi[:, :3], axis=1)
    err_v = np.linalg.norm(back[:, 3:] - xi[:, 3:], axis=1)
    assert np.all(err_w <= 1e-12 * scale)
    assert np.all(err_v <= 1e-12 * np.linalg.norm(xi, axis=1))
    w = xi[:, :3]
    assert np.all(np.linalg.norm(se3.log_so3(se3.exp_so3(w)) - w, axis=1) <= 1e-12 * scale)


def test_small_angle_series_against_long_series():
    """The short series branches agree with 12-term Taylor sums in extended precision."""
    from math import factorial

    def series(t, first):  # Σ_k (−1)^k t^{2k} / (first + 2k)!
        t = np.longdouble(t)
        return sum((-1) ** k * t ** (2 * k) / np.longdouble(factorial(first + 2 * k)) for k in range(12))

    for t in [1e-8, 1e-5, 3e-4, 9.9e-4, 1.1e-3, 0.02, 0.0999, 0.1001, 0.3]:
        A, B, C = se3._coeffs(np.array(t))
        assert abs(float(A) / float(series(t, 1)) - 1) < 1e-15  # sin t / t
        assert abs(float(B) / float(series(t, 2)) - 1) < 1e-15  # (1 − cos t)/t²
        assert abs(float(C) / float(series(t, 3)) - 1) < 1e-12  # (t − sin t)/t³


@pytest.mark.parametrize("gap", [0.0, 1e-12, 1e-8, 1e-5, 1e-3, 5e-3])
def test_log_near_pi(gap):
    u = rng.standard_normal((100, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    theta = np.pi - gap
    R = se3.R_a(np.full(100, theta), u)
    w = se3.log_so3(R)
    assert np.allclose(np.linalg.norm(w, axis=1), theta, atol=1e-9)
    assert np.allclose(se3.exp_so3(w), R, atol=1e-12)


def test_log_matches_scipy_logm():
    X = se3.random_pose(rng, 30, scale=2.0)
    for Xk, xi in zip(X, se3.log_se3(X)):
        assert np.allclose(se3.hat(xi), logm(Xk).real, atol=1e-9)


def test_R_a_is_exp():
    th = rng.uniform(-np.pi, np.pi, 100)
    u = rng.standard_normal((100, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    assert np.allclose(se3.R_a(th, u), se3.exp_so3(th[:, None] * u), atol=1e-13)


def test_quaternion_round_trip():
    R = se3.random_rotation(rng, 300)
    q = se3.rot_to_quat(R)
    assert np.all(q[:, 0] >= 0)
    assert np.allclose(np.linalg.norm(q, axis=1), 1)
    assert np.allclose(se3.quat_to_rot(q), R, atol=1e-14)
    # a half turn has w = 0 and the four branches of Shepperd's method must all be exact
    for axis in np.eye(3):
        Rpi = se3.R_a(np.pi, axis)
        assert np.allclose(se3.quat_to_rot(se3.rot_to_quat(Rpi)), Rpi, atol=1e-15)


def test_broadcasting_over_batch_axes():
    X = se3.random_pose(rng, (4, 5))
    xi = rng.standard_normal((4, 5, 6))
    assert se3.exp_se3(xi).shape == (4, 5, 4, 4)
    assert se3.log_se3(X).shape == (4, 5, 6)
    assert se3.Ad(X).shape == (4, 5, 6, 6)
    flat = se3.Ad(X.reshape(-1, 4, 4)).reshape(4, 5, 6, 6)
    assert np.array_equal(se3.Ad(X), flat)
