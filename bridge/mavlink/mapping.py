"""Wrench <-> actuator controls, per vehicle, batched over the fleet.

Both directions are written as element-wise numpy operations in a fixed order (no BLAS, no
reductions), so that mapping one vehicle at a time (the loopback vehicle) and the whole fleet at
once (the reference co-simulation, `bridge.mavlink.transport`) round identically, bit for bit.

Wrenches here are in the vehicle's FRD body frame, [τ; f] (N·m, N).

* ``direct``: controls = clip((w + w_ff) ./ max_wrench, −1, 1), order (τx, τy, τz, fx, fy, fz).
* ``allocation``: a multirotor, w = A c with c the rotor thrusts normalised by the maximum
  thrust; the rotor geometry is a preset of `bridge.mavlink.airframes` (``allocation.frame``). The default
  airframe is a hexarotor with alternately tilted arms (rotor k at azimuth 60°·k, its thrust axis,
  nominally −z (up), tilted by ±tilt about the arm, spin and tilt signs alternating): A is 6×6 and
  invertible, so the pseudo-inverse is the inverse and there is no null space: a zero wrench means
  zero thrust. The stacks' standard frames (quad-x, hexa-plus, hexa-x; ``tilt_deg = 0``) are not
  fully actuated: A⁺ gives the least-squares wrench (no sideways force); they are there for the
  flight stacks' simulator interfaces, which only decode (controls -> wrench). Unidirectional rotors (c ∈ [0, 1])
  therefore cannot produce every wrench from rest; they work around a positive *baseline*, the
  feed-forward gravity compensation (``gravity_compensation = true``), for which
  c_b = A⁺ w_ff > 0 in hover. The commanded part is scaled by the largest s ∈ [0, 1] with
  c_b + s·A⁺w inside the rotor range, which keeps the commanded wrench's direction; if c_b itself
  is outside the range (no baseline, or an attitude the airframe cannot hold), c_b + A⁺w is
  clipped. Gravity-free scenarios need reversible ("3D") rotors, c ∈ [−1, 1]
  (``allocation.reversible = true``); otherwise they saturate. Every step at which some
  vehicle saturates is counted.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .airframes import allocation_matrix

DIRECT, ALLOCATION = "direct", "allocation"
MAPPINGS = (DIRECT, ALLOCATION)


@dataclass(frozen=True)
class AllocationSpec:
    arm_length: float = 0.25      # m
    tilt_deg: float = 30.0        # alternating tilt of the thrust axes about the arms
    max_thrust: float = 15.0      # N per rotor
    torque_coeff: float = 0.016   # m: rotor drag torque = torque_coeff · thrust
    reversible: bool = False      # thrust range [-1, 1] instead of [0, 1]
    frame: str = "hexa-tilted"    # rotor geometry preset (bridge.mavlink.airframes.FRAMES)


@dataclass(frozen=True)
class MappingSpec:
    kind: str = DIRECT
    max_wrench: tuple = (1.0, 1.0, 1.0, 10.0, 10.0, 10.0)
    allocation: AllocationSpec = field(default_factory=AllocationSpec)


def hexarotor_matrix(spec: AllocationSpec) -> np.ndarray:
    """6×6 A with w_frd = A c, c the normalised thrusts of the rotors (`bridge.mavlink.airframes`; columns
    past the frame's rotor count are zero)."""
    return allocation_matrix(spec)


def _matvec(M: np.ndarray, x: np.ndarray) -> np.ndarray:
    """(n,6,6) · (n,6) with the sum over j in a fixed order."""
    out = M[:, :, 0] * x[:, 0:1]
    for j in range(1, x.shape[1]):
        out = out + M[:, :, j] * x[:, j:j + 1]
    return out


class FleetMapping:
    """The mappings of N vehicles (each ``direct`` or ``allocation``)."""

    def __init__(self, specs):
        specs = list(specs)
        self.specs = specs
        n = self.n = len(specs)
        self.kind = np.array([s.kind for s in specs])
        self.direct = np.flatnonzero(self.kind == DIRECT)
        self.alloc = np.flatnonzero(self.kind == ALLOCATION)
        self.max_wrench = np.ones((n, 6))
        self.A = np.zeros((n, 6, 6))
        self.Ainv = np.zeros((n, 6, 6))
        self.lo = np.zeros((n, 1))
        for i, s in enumerate(specs):
            if s.kind == DIRECT:
                self.max_wrench[i] = np.asarray(s.max_wrench, float)
                self.lo[i] = -1.0
            else:
                A = hexarotor_matrix(s.allocation)
                self.A[i] = A
                self.Ainv[i] = np.linalg.pinv(A)
                self.lo[i] = -1.0 if s.allocation.reversible else 0.0
        self.saturations = 0          # control steps at which at least one vehicle saturated
        self.saturated_vehicles = np.zeros(n, dtype=np.int64)
        # one vehicle with the direct mapping (an agent's): `encode_row` in plain floats
        self.one_direct = n == 1 and self.direct.size == 1
        self._mw = self.max_wrench[0].tolist()
        self.last_saturated = np.zeros(n, dtype=bool)   # per vehicle: the last encode saturated

    def subset(self, idx) -> "FleetMapping":
        return FleetMapping([self.specs[i] for i in np.atleast_1d(idx)])

    # ------------------------------------------------------------------ wrench -> controls
    def encode(self, w: np.ndarray, base: np.ndarray | None = None) -> np.ndarray:
        """(n,6) commanded FRD wrenches (+ baseline/feed-forward wrenches) -> (n,6) controls.

        Updates the saturation counters."""
        w = np.asarray(w, dtype=np.float64)
        c = np.zeros((self.n, 6))
        sat = np.zeros(self.n, dtype=bool)
        if self.direct.size:
            d = self.direct
            tot = w[d] if base is None else w[d] + base[d]
            x = tot / self.max_wrench[d]
            sat[d] = np.any(np.abs(x) > 1.0, axis=1)
            c[d] = np.clip(x, -1.0, 1.0)
        if self.alloc.size:
            a = self.alloc
            Ai = self.Ainv[a]
            lo = self.lo[a]
            cw = _matvec(Ai, w[a])
            cb = np.zeros_like(cw) if base is None else _matvec(Ai, base[a])
            feasible = np.all((cb >= lo) & (cb <= 1.0), axis=1)
            # largest s in [0, 1] with lo <= cb + s cw <= 1, component-wise
            with np.errstate(divide="ignore", invalid="ignore"):
                up = np.where(cw > 0, (1.0 - cb) / cw, np.inf)
                dn = np.where(cw < 0, (lo - cb) / cw, np.inf)
            s = np.minimum(1.0, np.minimum(up.min(axis=1), dn.min(axis=1)))
            s = np.where(feasible, np.maximum(s, 0.0), 1.0)
            ca = cb + s[:, None] * cw
            sat[a] = (s < 1.0) | ~feasible | np.any((ca < lo) | (ca > 1.0), axis=1)
            c[a] = np.clip(ca, lo, 1.0)
        if sat.any():
            self.saturations += 1
            self.saturated_vehicles += sat
        self.last_saturated = sat
        return c

    def encode_row(self, w: list, base: list | None = None) -> list:
        """`encode` for one vehicle with the ``direct`` mapping (``one_direct``), the wrench and
        baseline as lists of 6 floats: the same operations on the same floats (so the same
        bits), without numpy's per-call cost on a one-row array. Updates the counters."""
        mw = self._mw
        c = [0.0] * 6
        sat = False
        for i in range(6):
            x = (w[i] if base is None else w[i] + base[i]) / mw[i]
            if abs(x) > 1.0:
                sat = True
            # np.clip: NaN stays NaN
            c[i] = -1.0 if x < -1.0 else 1.0 if x > 1.0 else x
        if sat:
            self.saturations += 1
            self.saturated_vehicles[0] += 1
        if self.last_saturated[0] != sat:     # (a new array each step cost more than the rest)
            self.last_saturated = np.array([sat])
        return c

    # ------------------------------------------------------------------ controls -> wrench
    def decode_row(self, c: list) -> list:
        """`decode` for one vehicle with the ``direct`` mapping (``one_direct``), the controls a
        list of 6 floats: the same products (so the same bits), without numpy's per-call cost
        (a vehicle's every command)."""
        mw = self._mw
        return [c[i] * mw[i] for i in range(6)]

    def decode(self, c: np.ndarray) -> np.ndarray:
        """(n,6) controls -> (n,6) FRD wrenches (the loopback vehicle's actuators)."""
        c = np.asarray(c, dtype=np.float64)
        w = np.zeros((self.n, 6))
        if self.direct.size:
            d = self.direct
            w[d] = c[d] * self.max_wrench[d]
        if self.alloc.size:
            a = self.alloc
            w[a] = _matvec(self.A[a], c[a])
        return w
