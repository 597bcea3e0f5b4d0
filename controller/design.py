"""The weighting matrix 𝔸 (`AA_def`) and the synergy parameters P_𝔸 of Lemma 2 (`eqn:P_A`).

Defaults, used for whatever the caller leaves out (documented in docs/reference/scenario.md
``[synergy]`` and docs/theory.md):
- γ = ½ · 4Δ*/π², half its bound;
- Θ = (θ*, −θ*), θ* ∈ (0, π] maximising 2 sin²(θ/2)Δ* − γθ²/2, i.e. the exact gap for one
  magnitude; the two signs let the jump pick the better side;
- δ = ½ · Lemma 2's bound (4Δ*/π² − γ)θ_M²/2, which is also below the exact gap.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np

from .errors import DesignError, WeightingError

__all__ = ["WeightingMatrix", "SynergyDesign", "DesignWarning", "design_synergy", "Delta",
           "delta_min", "detect_case"]


class DesignWarning(UserWarning):
    """A parameter was accepted, but only on a weaker footing than the Lemma states."""


def _fmt(x):
    return np.array2string(np.asarray(x, float), precision=6, separator=", ",
                           suppress_small=False, max_line_width=10_000)


@dataclass(frozen=True)
class WeightingMatrix:
    """𝔸 = [[A, b], [bᵀ, d]] with W = A − bbᵀ/d ⪰ 0 and W̄ = ½(tr(W)I − W) ≻ 0."""

    AA: np.ndarray

    def __post_init__(self):
        AA = np.array(self.AA, dtype=float)
        if AA.shape != (4, 4):
            raise WeightingError(f"weighting matrix 𝔸 must be 4×4, got shape {AA.shape}")
        if not np.all(np.isfinite(AA)):
            raise WeightingError(f"weighting matrix 𝔸 has non-finite entries: {_fmt(AA)}")
        asym = np.abs(AA - AA.T)
        if asym.max() > 1e-9 * max(1.0, np.abs(AA).max()):
            r, c = np.unravel_index(np.argmax(asym), asym.shape)
            raise WeightingError(
                f"weighting matrix 𝔸 is not symmetric: 𝔸[{r + 1},{c + 1}] = {AA[r, c]:.6g} but "
                f"𝔸[{c + 1},{r + 1}] = {AA[c, r]:.6g}")
        AA = 0.5 * AA + 0.5 * AA.T     # (½(𝔸 + 𝔸ᵀ) overflowed for entries near the float maximum)
        d = AA[3, 3]
        if not d > 0:
            raise WeightingError(f"weighting matrix: d must be > 0, got d = {d:.6g}")
        A, b = AA[:3, :3], AA[:3, 3]
        W = A - np.outer(b, b) / d
        lam = np.linalg.eigvalsh(W)
        scale = max(1.0, abs(lam[-1]))
        if lam[0] < -1e-12 * scale:
            raise WeightingError(
                f"W = A − bbᵀ/d is not positive semi-definite: eigenvalues {_fmt(lam)}")
        Wbar = 0.5 * (np.trace(W) * np.eye(3) - W)
        lam_bar = np.linalg.eigvalsh(Wbar)
        if lam_bar[0] <= 1e-12 * scale:
            raise WeightingError(
                f"W̄ = (tr(W)I − W)/2 is not positive definite: eigenvalues {_fmt(lam_bar)}")
        object.__setattr__(self, "AA", AA)

    @classmethod
    def from_blocks(cls, A, b, d) -> "WeightingMatrix":
        A = np.asarray(A, float)
        b = np.asarray(b, float).ravel()
        if A.shape != (3, 3):
            raise WeightingError(f"weighting matrix: A must be 3×3, got shape {A.shape}")
        if b.shape != (3,):
            raise WeightingError(f"weighting matrix: b must have 3 entries, got {b.size}")
        AA = np.zeros((4, 4))
        AA[:3, :3] = A
        AA[:3, 3] = b
        AA[3, :3] = b
        AA[3, 3] = float(d)
        return cls(AA)

    @property
    def A(self):
        return self.AA[:3, :3]

    @property
    def b(self):
        return self.AA[:3, 3]

    @property
    def d(self) -> float:
        return float(self.AA[3, 3])

    @property
    def W(self):
        return self.A - np.outer(self.b, self.b) / self.d

    @property
    def W_bar(self):
        W = self.W
        return 0.5 * (np.trace(W) * np.eye(3) - W)

    def eig(self):
        """Eigenvalues of W ascending and unit eigenvectors as columns, each with its
        largest-magnitude component positive (a deterministic sign)."""
        lam, V = np.linalg.eigh(self.W)
        for k in range(3):
            if V[np.argmax(np.abs(V[:, k])), k] < 0:
                V[:, k] = -V[:, k]
        return lam, V


def Delta(W, v, u):
    """Δ(v, u) = uᵀ(tr(W)I − W − 2vᵀWv(I − vvᵀ))u (Lemma 2). Broadcasts over v and u."""
    W = np.asarray(W, float)
    v = np.asarray(v, float)
    u = np.asarray(u, float)
    vWv = np.einsum("...i,ij,...j->...", v, W, v)
    uWu = np.einsum("...i,ij,...j->...", u, W, u)
    uu = np.einsum("...i,...i->...", u, u)
    uv = np.einsum("...i,...i->...", u, v)
    return np.trace(W) * uu - uWu - 2 * vWv * (uu - uv * uv)


def _eigenspaces(lam, V, tol):
    """Group eigenvalues that agree within tol·λ₃ into eigenspaces (lists of columns)."""
    scale = max(abs(lam[-1]), 1e-300)
    groups = [[0]]
    for k in (1, 2):
        if lam[k] - lam[groups[-1][-1]] <= tol * scale:
            groups[-1].append(k)
        else:
            groups.append([k])
    return [(float(np.mean(lam[g])), V[:, g]) for g in groups]


def delta_min(W, u, tol=1e-8):
    """min over unit eigenvectors v of W of Δ(v, u).

    A repeated eigenvalue λ has a whole eigenplane (or sphere) of unit eigenvectors. On it
    Δ(v, u) = uᵀ(tr(W)I − W)u − 2λ(‖u‖² − (uᵀv)²), smallest where v ⟂ u, so the plane's
    minimum is uᵀ(tr(W)I − W)u − 2λ‖u‖²; on a sphere (W = λI) it is the same expression.
    """
    W = np.asarray(W, float)
    lam, V = np.linalg.eigh(W)
    u = np.asarray(u, float)
    best = np.inf
    base = np.trace(W) * (u @ u) - u @ W @ u
    for lam_k, basis in _eigenspaces(lam, V, tol):
        if basis.shape[1] == 1:
            val = float(Delta(W, basis[:, 0], u))
        else:
            val = float(base - 2 * lam_k * (u @ u))
        best = min(best, val)
    return best


def detect_case(lam, tol=1e-8):
    """Lemma 2's case (1, 2 or 3) from the ascending eigenvalues of W."""
    l1, l2, l3 = lam
    if l2 - l1 <= tol * max(abs(l3), 1e-300):
        return 1
    if l3 - l1 > 0 and l2 >= l1 * l3 / (l3 - l1):
        return 2
    return 3


def lemma2_u_c1(lam, V, case, alpha_signs=(1, 1, 1)):
    """(u_c1, Δ*_W) from the three cases of Lemma 2.

    The Lemma fixes |α_i| only: Δ(v, u) depends on α_i², so every sign pattern is as good.
    alpha_signs picks one, relative to eigenvectors whose largest component is positive;
    the result is then signed so that its own largest component is positive.
    """
    l1, l2, l3 = lam
    if case == 1:
        a2 = np.array([l2 / (2 * l3), l2 / (2 * l3), 1 - l2 / l3])
        dstar = l1 * (1 - l2 / l3)
    elif case == 2:
        a2 = np.array([0.0, l2 / (l2 + l3), l3 / (l2 + l3)])
        dstar = l1
    else:
        s = 2 * (l1 * l2 + l1 * l3 + l2 * l3)
        prod_others = np.array([l2 * l3, l1 * l3, l1 * l2])
        a2 = 1 - 4 * prod_others / s
        dstar = 4 * l1 * l2 * l3 / s
    alpha = np.sqrt(np.clip(a2, 0.0, None)) * np.sign(np.asarray(alpha_signs, float))
    u = V @ alpha
    u = u / np.linalg.norm(u)
    if u[np.argmax(np.abs(u))] < 0:
        u = -u
    return u, float(dstar)


def _gap(Theta, Delta_min, gamma):
    """max over θ' ∈ Θ of [2 sin²(θ'/2) Δ − γθ'²/2]."""
    Theta = np.asarray(Theta, float)
    return float(np.max(2 * np.sin(Theta / 2) ** 2 * Delta_min - 0.5 * gamma * Theta ** 2))


def _best_theta(Delta_star, gamma):
    """θ* ∈ (0, π] maximising 2 sin²(θ/2)Δ* − γθ²/2 (a grid, then Newton on the derivative
    Δ* sinθ − γθ)."""
    grid = np.linspace(1e-3, np.pi, 4001)
    vals = 2 * np.sin(grid / 2) ** 2 * Delta_star - 0.5 * gamma * grid ** 2
    t = grid[np.argmax(vals)]
    for _ in range(50):
        f = Delta_star * math.sin(t) - gamma * t
        fp = Delta_star * math.cos(t) - gamma
        if fp >= 0:
            break
        step = f / fp
        t_new = min(max(t - step, 1e-6), math.pi)
        if abs(t_new - t) < 1e-15:
            t = t_new
            break
        t = t_new
    return float(t)


@dataclass(frozen=True)
class SynergyDesign:
    """P_𝔸 = {Θ, u_c1, u_c2, γ, δ} with the quantities Lemma 2 computes on the way."""

    case: int
    eigvals: tuple
    u_c1: np.ndarray
    u_c2: np.ndarray
    Theta: tuple
    gamma: float
    delta: float
    delta_star: float
    gamma_bound: float
    delta_bound: float
    exact_gap: float
    warnings: tuple = field(default=())

    @property
    def u_c(self):
        return np.concatenate([self.u_c1, self.u_c2])

    @property
    def theta_M(self) -> float:
        return float(np.max(np.abs(self.Theta)))

    def as_dict(self) -> dict:
        return {
            "case": self.case,
            "eigenvalues_W": [float(x) for x in self.eigvals],
            "u_c1": [float(x) for x in self.u_c1],
            "u_c2": [float(x) for x in self.u_c2],
            "Theta": [float(x) for x in self.Theta],
            "delta_star": self.delta_star,
            "gamma": self.gamma,
            "delta": self.delta,
            "gamma_bound": self.gamma_bound,
            "delta_bound": self.delta_bound,
            "exact_gap": self.exact_gap,
            "warnings": list(self.warnings),
        }


def design_synergy(weighting: WeightingMatrix, Theta=None, gamma=None, delta=None, u_c1=None,
                   alpha_signs=(1, 1, 1), case_tol: float = 1e-8) -> SynergyDesign:
    """Lemma 2: detect the case, design or check u_c1, and check or choose Θ, γ, δ.

    alpha_signs (three ±1) chooses among the equally valid sign patterns of u_c1 = Σ α_i v_i;
    the paper's printed u_c1 for its own 𝔸 is the pattern (1, −1, 1).

    Refuses (DesignError) γ ∉ (0, 4Δ*/π²), Θ with an element outside 0 < |θ| ≤ π, and δ ∉
    (0, exact gap). Warns (DesignWarning, also kept in `.warnings`) when u_c1 was not unit and
    when δ is above the Lemma's conservative bound but below the exact gap.
    """
    notes = []
    lam, V = weighting.eig()
    case = detect_case(lam, case_tol)
    W = weighting.W
    signs = np.asarray(alpha_signs, float).ravel()
    if signs.shape != (3,) or not np.all(np.abs(signs) == 1):
        raise DesignError(f"alpha_signs must be three values of +1 or -1, got {_fmt(signs)}", "alpha_signs")
    if u_c1 is None:
        u, dstar = lemma2_u_c1(lam, V, case, signs)
    else:
        u = np.asarray(u_c1, float).ravel()
        if u.shape != (3,) or not np.all(np.isfinite(u)):
            raise DesignError(f"u_c1 must be 3 finite numbers, got {_fmt(u)}", "u_c1")
        n = np.linalg.norm(u)
        if n == 0:
            raise DesignError("u_c1 must be a non-zero vector, got (0, 0, 0)", "u_c1")
        if abs(n - 1) > 1e-9:
            notes.append(f"u_c1 = {_fmt(u)} has norm {n:.6g}; normalised to {_fmt(u / n)}")
        u = u / n
        dstar = delta_min(W, u, case_tol)
    # The Lemma's closed forms assume the eigenvectors are isolated (or, in case 1, the
    # eigenplane of λ₁ = λ₂). If λ₂ = λ₃ the eigenplane of λ₃ holds a v ⟂ u_c1 with
    # Δ(v, u_c1) = λ₁ − λ₃ < 0 for every choice, so the minimum is checked directly.
    dmin = delta_min(W, u, case_tol)
    if not (dstar > 1e-12 * max(1.0, lam[-1]) and dmin > 1e-12 * max(1.0, lam[-1])):
        raise DesignError(
            f"Δ*_W = min over eigenvectors v of W of Δ(v, u_c1) = {min(dstar, dmin):.6g} is not "
            f"positive (eigenvalues of W {_fmt(lam)}, u_c1 {_fmt(u)}): no jump can leave every "
            "undesired critical point; W needs three distinct eigenvalues or λ₁ = λ₂ < λ₃",
            "W" if u_c1 is None else "u_c1")
    u_c2 = -np.cross(u, weighting.b) / weighting.d
    gamma_bound = 4 * dstar / math.pi ** 2

    if gamma is None:
        gamma = 0.5 * gamma_bound
    gamma = float(gamma)
    if not (math.isfinite(gamma) and gamma > 0):
        raise DesignError(f"gamma must be > 0, got {gamma:.6g}", "gamma")
    if gamma >= gamma_bound:
        raise DesignError(
            f"gamma = {gamma:.6g} is at or above its bound 4Δ*/π² = {gamma_bound:.6g} "
            f"(Δ* = {dstar:.6g})", "gamma")

    if Theta is None:
        t = _best_theta(dstar, gamma)
        Theta = (t, -t)
    Theta = tuple(float(x) for x in np.atleast_1d(np.asarray(Theta, float)).ravel())
    if len(Theta) == 0:
        raise DesignError("Theta must hold at least one angle", "Theta")
    for x in Theta:
        if not (math.isfinite(x) and 0 < abs(x) <= math.pi + 1e-12):
            raise DesignError(f"Theta must hold angles with 0 < |θ| ≤ π, got θ = {x:.6g}", "Theta")
    theta_M = max(abs(x) for x in Theta)
    delta_bound = (gamma_bound - gamma) * theta_M ** 2 / 2
    exact_gap = _gap(Theta, dmin, gamma)
    if exact_gap <= 0:
        raise DesignError(
            f"the exact gap min_v max_θ'∈Θ [2 sin²(θ'/2)Δ(v, u_c1) − γθ'²/2] = {exact_gap:.6g} "
            f"is not positive for Theta = {_fmt(Theta)}, gamma = {gamma:.6g}", "Theta")

    if delta is None:
        delta = 0.5 * delta_bound if delta_bound > 0 else 0.5 * exact_gap
    delta = float(delta)
    if not (math.isfinite(delta) and delta > 0):
        raise DesignError(f"delta must be > 0, got {delta:.6g}", "delta")
    if delta >= exact_gap:
        raise DesignError(
            f"delta = {delta:.6g} is at or above the exact gap {exact_gap:.6g} "
            "(min over eigenvectors v of W of max over θ' ∈ Theta of "
            "2 sin²(θ'/2)Δ(v, u_c1) − γθ'²/2)", "delta")
    if delta >= delta_bound:
        notes.append(
            f"delta = {delta:.6g} is above Lemma 2's bound (4Δ*/π² − γ)θ_M²/2 = "
            f"{delta_bound:.6g} but below the exact gap {exact_gap:.6g}: accepted, because "
            "μ_U > δ holds at every undesired critical point")
    for msg in notes:
        warnings.warn(msg, DesignWarning, stacklevel=2)
    return SynergyDesign(case=case, eigvals=tuple(float(x) for x in lam), u_c1=u, u_c2=u_c2,
                         Theta=Theta, gamma=gamma, delta=delta, delta_star=float(dstar),
                         gamma_bound=gamma_bound, delta_bound=float(delta_bound),
                         exact_gap=exact_gap, warnings=tuple(notes))
