"""Weighting matrix refusals and Lemma 2 (`eqn:P_A`), checked against direct computation."""
import math
import warnings

import numpy as np
import pytest

import controller as C
from controller import potential, se3
from controller.design import Delta, lemma2_u_c1

from _paper import A, b, d, random_weighting

rng = np.random.default_rng(7)


def paper_weighting():
    return C.WeightingMatrix.from_blocks(A, b, d)


# ---------------------------------------------------------------- weighting matrix refusals
def test_refuses_non_symmetric():
    AA = paper_weighting().AA.copy()
    AA[0, 3] += 1.0
    with pytest.raises(C.WeightingError, match=r"not symmetric: 𝔸\[1,4\]"):
        C.WeightingMatrix(AA)


@pytest.mark.parametrize("dval", [0.0, -2.0])
def test_refuses_non_positive_d(dval):
    with pytest.raises(C.WeightingError, match=f"d must be > 0, got d = {dval:g}"):
        C.WeightingMatrix.from_blocks(A, b, dval)


def test_refuses_W_not_psd():
    with pytest.raises(C.WeightingError, match=r"not positive semi-definite: eigenvalues \[-"):
        C.WeightingMatrix.from_blocks(np.diag([1.0, 2.0, 3.0]), [2.0, 0, 0], 1.0)


def test_refuses_W_bar_not_pd():
    # W = diag(0, 0, 1): PSD, but W̄ has eigenvalue (0 + 0)/2 = 0.
    with pytest.raises(C.WeightingError, match="W̄ .* is not positive definite"):
        C.WeightingMatrix.from_blocks(np.diag([0.0, 0.0, 1.0]), [0, 0, 0], 1.0)


def test_W_and_W_bar_share_eigenvectors():
    wm = paper_weighting()
    lam, V = wm.eig()
    assert np.allclose(wm.W @ V, V * lam)
    # W̄ v = ½(tr W − λ) v for each eigenvector v of W
    assert np.allclose(wm.W_bar @ V, V * (0.5 * (lam.sum() - lam)))


# ---------------------------------------------------------------- Lemma 2 on random W
def _min_over_eigvecs_direct(W, u, case, lam_exact):
    """min Δ(v, u) over unit eigenvectors of W, by brute force: the isolated eigenvectors, and
    in case 1 a 3600-point sweep of the eigenplane refined by golden-section search."""
    lam, V = np.linalg.eigh(W)
    if case != 1:
        return min(float(Delta(W, V[:, k], u)) for k in range(3))
    e1, e2 = V[:, 0], V[:, 1]
    phi = np.linspace(0, np.pi, 3601)
    vals = Delta(W, np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2, u)
    k = int(np.argmin(vals))
    lo, hi = phi[max(k - 1, 0)], phi[min(k + 1, 3600)]
    g = (math.sqrt(5) - 1) / 2
    f = lambda p: float(Delta(W, math.cos(p) * e1 + math.sin(p) * e2, u))  # noqa: E731
    for _ in range(100):
        a, c = hi - g * (hi - lo), lo + g * (hi - lo)
        if f(a) < f(c):
            hi = c
        else:
            lo = a
    return min(f(0.5 * (lo + hi)), float(Delta(W, V[:, 2], u)))


@pytest.mark.parametrize("case", [1, 2, 3])
def test_lemma2_delta_star_is_min_over_eigenvectors(case):
    """≥ 1000 random W in all (≥ 340 per case): the Lemma's Δ*_W is the true minimum."""
    n = 0
    for _ in range(345):
        AA, bb, dd, lam = random_weighting(rng, case)
        wm = C.WeightingMatrix.from_blocks(AA, bb, dd)
        lam_w, V = wm.eig()
        assert C.detect_case(lam_w) == case
        u, dstar = lemma2_u_c1(lam_w, V, case, alpha_signs=rng.choice([-1, 1], 3))
        assert abs(np.linalg.norm(u) - 1) < 1e-14
        direct = _min_over_eigvecs_direct(wm.W, u, case, lam)
        assert direct == pytest.approx(dstar, rel=1e-8, abs=1e-10)
        assert dstar > 0
        n += 1
    assert n == 345


def test_case_boundaries():
    assert C.detect_case((1.0, 1.0, 3.0)) == 1
    assert C.detect_case((1.0, 1.5, 3.0)) == 2     # τ = 1·3/2 = 1.5 → λ₂ ≥ τ
    assert C.detect_case((1.0, 1.49, 3.0)) == 3
    assert C.detect_case((1.0, 1.0 + 1e-12, 3.0)) == 1  # within the tolerance for λ₁ = λ₂


def _critical_points(wm, n_plane=16):
    """Undesired critical points (`def:Upsilon_V`): R̄ = R_a(π, v), p̄ = (I − R̄)b/d, for every
    eigenvector v of W, sampling eigenplanes of repeated eigenvalues."""
    lam, V = np.linalg.eigh(wm.W)
    vs = [V[:, k] for k in range(3)]
    if lam[1] - lam[0] <= 1e-8 * lam[2]:
        for phi in np.linspace(0, np.pi, n_plane, endpoint=False):
            vs.append(np.cos(phi) * V[:, 0] + np.sin(phi) * V[:, 1])
    out = []
    for v in vs:
        R = se3.R_a(np.pi, v)
        out.append(se3.T(R, (np.eye(3) - R) @ wm.b / wm.d))
    return np.array(out)


def test_critical_points_are_critical():
    """ψ̄_∇ vanishes at the undesired critical points (θ = 0), so they are equilibria."""
    for case in (1, 2, 3):
        for _ in range(20):
            wm = C.WeightingMatrix.from_blocks(*random_weighting(rng, case)[:3])
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                des = C.design_synergy(wm)
            Xc = _critical_points(wm)
            g = potential.psi_bar_nabla(wm, des, Xc, 0.0)
            assert np.abs(g).max() < 1e-9 * max(1.0, np.abs(wm.AA).max())


@pytest.mark.parametrize("case", [1, 2, 3])
def test_mu_exceeds_delta_at_every_undesired_critical_point(case):
    for _ in range(60):
        wm = C.WeightingMatrix.from_blocks(*random_weighting(rng, case)[:3])
        des = C.design_synergy(wm)  # defaults: no warning expected
        assert des.warnings == ()
        mu = potential.mu_U(wm, des, _critical_points(wm), 0.0)
        assert np.all(mu > des.delta)
        # and the exact gap is the smallest μ_U over the critical set (Appendix A)
        assert mu.min() >= des.exact_gap - 1e-9
        assert des.delta < des.delta_bound < des.exact_gap + 1e-12


def test_one_jump_lowers_U_by_at_least_delta():
    wm = paper_weighting()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        des = C.design_synergy(wm, Theta=[0.3 * np.pi, -0.3 * np.pi, 0.6 * np.pi], gamma=0.33, delta=0.02)
    Xb = se3.random_pose(rng, 4000, scale=2.0)
    th = rng.uniform(-2, 2, 4000)
    mu = potential.mu_U(wm, des, Xb, th)
    jump = mu >= des.delta
    assert jump.sum() > 100
    th_plus = potential.jump_map(wm, des, Xb[jump])
    U_before = potential.U(wm, des, Xb[jump], th[jump])
    U_after = potential.U(wm, des, Xb[jump], th_plus)
    assert np.all(U_before - U_after >= des.delta - 1e-12)
    # the jump lands on the argmin over Θ: no element of Θ does better
    for t in des.Theta:
        assert np.all(U_after <= potential.U(wm, des, Xb[jump], t) + 1e-12)


# ---------------------------------------------------------------- the paper's 𝔸
def test_paper_weighting_numbers():
    wm = paper_weighting()
    with pytest.warns(C.DesignWarning, match="above Lemma 2's bound"):
        des = C.design_synergy(wm, Theta=[0.3 * np.pi], gamma=0.33, delta=0.02, alpha_signs=(1, -1, 1))
    assert des.case == 2
    assert np.allclose(des.eigvals, [0.892, 4.568, 18.341], atol=1e-3)
    assert des.delta_star == pytest.approx(des.eigvals[0])          # case 2: Δ* = λ₁
    assert np.allclose(des.u_c1, [0.1063, 0.9936, 0.0381], atol=1e-4)
    assert np.allclose(des.u_c2, -np.cross(des.u_c1, b) / d, atol=1e-14)
    assert np.allclose(des.u_c2, [-3.06, 0.20, 3.32], atol=5e-3)   # as the paper prints it
    assert des.gamma_bound == pytest.approx(4 * des.delta_star / np.pi**2)
    assert des.gamma_bound == pytest.approx(0.362, abs=1e-3)
    assert des.delta_bound == pytest.approx(0.0140, abs=1e-4)
    assert des.delta_bound < 0.02 < des.exact_gap
    assert des.exact_gap == pytest.approx(
        2 * np.sin(0.15 * np.pi) ** 2 * des.delta_star - 0.33 * (0.3 * np.pi) ** 2 / 2)
    assert len(des.warnings) == 1


def test_paper_printed_u_c1_is_normalised_with_warning():
    wm = paper_weighting()
    with pytest.warns(C.DesignWarning) as rec:
        des = C.design_synergy(wm, Theta=[0.3 * np.pi], gamma=0.33, delta=0.02, u_c1=[0.11, 0.99, 0.04])
    msgs = [str(r.message) for r in rec]
    assert any("norm 0.99" in m and "normalised" in m for m in msgs)
    assert np.linalg.norm(des.u_c1) == pytest.approx(1.0, abs=1e-15)
    lam, V = np.linalg.eigh(wm.W)
    assert des.delta_star == pytest.approx(min(Delta(wm.W, V[:, k], des.u_c1) for k in range(3)))
    assert des.delta_star == pytest.approx(0.83, abs=0.01)


def test_refuses_gamma_at_or_above_bound():
    wm = paper_weighting()
    bound = 4 * 0.8922711347365843 / np.pi**2
    for g in (bound, bound * 1.01):
        with pytest.raises(C.DesignError, match="gamma = .* is at or above its bound 4Δ\\*/π²"):
            C.design_synergy(wm, gamma=g, alpha_signs=(1, -1, 1))
    with pytest.raises(C.DesignError, match="gamma must be > 0"):
        C.design_synergy(wm, gamma=0.0)


def test_refuses_delta_at_or_above_exact_gap():
    wm = paper_weighting()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ok = C.design_synergy(wm, Theta=[0.3 * np.pi], gamma=0.33, delta=0.02)
    for dl in (ok.exact_gap, ok.exact_gap * 1.5):
        with pytest.raises(C.DesignError, match="delta = .* at or above the exact gap"):
            C.design_synergy(wm, Theta=[0.3 * np.pi], gamma=0.33, delta=dl)
    with pytest.raises(C.DesignError, match="delta must be > 0"):
        C.design_synergy(wm, delta=-1.0)


def test_refuses_bad_Theta_and_u_c1():
    wm = paper_weighting()
    for th in ([0.0], [4.0], [], [float("nan")]):
        with pytest.raises(C.DesignError, match="Theta"):
            C.design_synergy(wm, Theta=th)
    with pytest.raises(C.DesignError, match="u_c1 must be a non-zero"):
        C.design_synergy(wm, u_c1=[0, 0, 0])
    with pytest.raises(C.DesignError, match="alpha_signs"):
        C.design_synergy(wm, alpha_signs=(1, 0, 1))


def test_refuses_repeated_largest_eigenvalue():
    """λ₂ = λ₃: the eigenplane holds v ⟂ u_c1 with Δ ≤ 0 for any u_c1, so no design exists."""
    with pytest.raises(C.DesignError, match="Δ\\*_W .* is not positive"):
        C.design_synergy(C.WeightingMatrix.from_blocks(np.diag([1.0, 3.0, 3.0]), [0, 0, 0], 1.0))
    with pytest.raises(C.DesignError, match="not positive"):
        C.design_synergy(C.WeightingMatrix.from_blocks(np.eye(3) * 2.0, [0, 0, 0], 1.0))


def test_defaults_are_admissible_and_documented_values():
    wm = paper_weighting()
    des = C.design_synergy(wm)
    assert des.gamma == pytest.approx(0.5 * des.gamma_bound)
    t = des.Theta[0]
    assert des.Theta == (t, -t)
    # θ* maximises 2 sin²(θ/2)Δ* − γθ²/2 on (0, π]: its derivative Δ* sinθ − γθ vanishes there
    assert des.delta_star * np.sin(t) - des.gamma * t == pytest.approx(0.0, abs=1e-12)
    grid = np.linspace(1e-3, np.pi, 20001)
    f = 2 * np.sin(grid / 2) ** 2 * des.delta_star - des.gamma * grid**2 / 2
    assert f.max() <= 2 * np.sin(t / 2) ** 2 * des.delta_star - des.gamma * t**2 / 2 + 1e-12
    assert des.delta == pytest.approx(0.5 * des.delta_bound)
    assert des.warnings == ()
