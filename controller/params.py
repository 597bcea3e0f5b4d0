"""`LawParameters`: the one place where the law's parameters become the vector every kernel reads.

The weighting matrix 𝔸 (`AA_def`), the synergy design P_A (`eqn:P_A`) and the gains k_X, k_ξ,
k_e, k_θ (`hybridcontroller`) are packed once into ``P``; the network view, the per-agent view,
`potential`, V̄, the master's metrics and the stability analysis all take a LawParameters.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import _kernels as K
from .design import SynergyDesign, WeightingMatrix

__all__ = ["LawParameters"]


@dataclass(frozen=True, eq=False)
class LawParameters:
    """``LawParameters.of(weighting, design, gains)``; ``design=None`` is the gradient baseline
    (θ ≡ 0: u_c and Θ never enter). ``P`` is the packed vector."""

    weighting: WeightingMatrix
    design: SynergyDesign | None
    gains: object
    k_X: float
    k_xi: float
    k_e: float
    k_theta: float
    delta: float
    P: np.ndarray

    @classmethod
    def of(cls, weighting: WeightingMatrix, design: SynergyDesign | None, gains,
           *, delta: float | None = None) -> "LawParameters":
        """``delta`` overrides the design's δ (``math.inf``: no jump can fire, as when the loop
        is linearised at consensus)."""
        if design is None:
            u1, u2, gamma, d, Theta = np.zeros(3), np.zeros(3), 0.0, math.inf, (0.0,)
        else:
            u1, u2 = design.u_c1, design.u_c2
            gamma, d, Theta = design.gamma, design.delta, design.Theta
        if delta is not None:
            d = float(delta)
        P = K.pack(weighting.A, weighting.b, weighting.d, u1, u2, gamma, d, Theta,
                   gains.k_X, gains.k_xi, gains.k_e, gains.k_theta)
        return cls(weighting, design, gains, float(gains.k_X), float(gains.k_xi), float(gains.k_e),
                   float(gains.k_theta), float(d), P)

    def with_delta(self, delta: float) -> "LawParameters":
        return LawParameters.of(self.weighting, self.design, self.gains, delta=delta)
