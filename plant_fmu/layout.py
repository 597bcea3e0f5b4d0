"""Value-reference layout of the se3sync plant FMU (a fixed contract, mirrored by c/model.h).

Body ``i`` (1-based; ``b = i - 1``) occupies the value references from
``base = 1000 + 100 * b``:

==============  ===================  ==========================================
offset          variable             meaning
==============  ===================  ==========================================
0..2            ``body[i].p[k]``     position, world frame (output)
3..11           ``body[i].R[r,c]``   rotation matrix, row-major (output)
12..17          ``body[i].xi[k]``    body velocity [w; v] (output)
18..21          ``body[i].q[k]``     quaternion, w first, w >= 0 (output)
22              ``body[i].contact``  1 while resting on the ground, else 0 (output)
30..35          ``body[i].u[k]``     body wrench [tau; f] (input)
40              ``body[i].m``        mass (parameter)
41..49          ``body[i].J[r,c]``   inertia, row-major (parameter)
50..52          ``body[i].p0[k]``    initial position (parameter)
53..56          ``body[i].q0[k]``    initial quaternion, w first (parameter)
57..62          ``body[i].xi0[k]``   initial body velocity (parameter)
==============  ===================  ==========================================

Globals: ``g[1..3]`` at 1..3 (gravity, world frame), ``h_internal`` at 4, and the optional plant
terms (all 0 = off by default): ``ground`` at 5 (1 = a ground plane), ``ground_height`` at 6,
``drag_linear`` at 7, ``drag_angular`` at 8.
"""
from __future__ import annotations

import numpy as np

from controller.layout import S_P, S_R, S_WIDTH, S_XI

BODY_BASE = 1000
BODY_STRIDE = 100
MAX_BODIES = 100_000

# p, R, xi: the block the controller consumes, laid out as controller.layout defines it
OFF_P, OFF_R, OFF_XI, N_STATE = S_P, S_R, S_XI, S_WIDTH
OFF_Q = 18
OFF_CONTACT = 22
OFF_U = 30
OFF_M, OFF_J, OFF_P0, OFF_Q0, OFF_XI0 = 40, 41, 50, 53, 57

VR_GRAVITY = np.array([1, 2, 3], dtype=np.uint32)
VR_GRAVITY.flags.writeable = False
VR_H_INTERNAL = 4
VR_GROUND, VR_GROUND_HEIGHT, VR_DRAG_LINEAR, VR_DRAG_ANGULAR = 5, 6, 7, 8
# (name, value reference, unit, description) of the optional plant terms (docs/reference/plant-fmu.md
# "Ground and drag")
TERMS = (
    ("ground", VR_GROUND, "", "1: a ground plane perpendicular to g (sticking contact, no bounce), 0: none"),
    ("ground_height", VR_GROUND_HEIGHT, "m", "height of the ground plane along up = -g/|g|"),
    ("drag_linear", VR_DRAG_LINEAR, "N.s/m", "linear drag on the body velocity: f = -drag_linear v"),
    ("drag_angular", VR_DRAG_ANGULAR, "N.m.s/rad", "linear drag on the angular rate: tau = -drag_angular omega"),
)

_PARAM_BLOCKS = {"m": (OFF_M, 1), "J": (OFF_J, 9), "p0": (OFF_P0, 3), "q0": (OFF_Q0, 4), "xi0": (OFF_XI0, 6)}


def _check_n(n: int) -> int:
    n = int(n)
    if not 1 <= n <= MAX_BODIES:
        raise ValueError(f"number of bodies must be in 1..{MAX_BODIES}, got {n}")
    return n


def body_base(b: int) -> int:
    """First value reference of body ``b`` (0-based)."""
    return BODY_BASE + BODY_STRIDE * int(b)


def _block(n: int, offset: int, size: int) -> np.ndarray:
    n = _check_n(n)
    bases = BODY_BASE + BODY_STRIDE * np.arange(n, dtype=np.uint32)
    return (bases[:, None] + np.arange(offset, offset + size, dtype=np.uint32)[None, :]).reshape(-1)


def vr_state(n: int) -> np.ndarray:
    """(n*18,) uint32: [p(3), R(9, row-major), xi(6)] of every body, body after body."""
    return _block(n, OFF_P, N_STATE)


def vr_quat(n: int) -> np.ndarray:
    """(n*4,) uint32: quaternion outputs (w first) of every body."""
    return _block(n, OFF_Q, 4)


def vr_contact(n: int) -> np.ndarray:
    """(n,) uint32: the contact output (1 resting on the ground, 0 not) of every body."""
    return _block(n, OFF_CONTACT, 1)


def vr_input(n: int) -> np.ndarray:
    """(n*6,) uint32: the input wrench [tau; f] of every body."""
    return _block(n, OFF_U, 6)


def vr_param(n: int, name: str) -> np.ndarray:
    """Value references of the parameter block ``name`` (m, J, p0, q0, xi0) of every body."""
    try:
        offset, size = _PARAM_BLOCKS[name]
    except KeyError:
        raise ValueError(f"unknown body parameter {name!r}; expected one of {sorted(_PARAM_BLOCKS)}") from None
    return _block(n, offset, size)


def vr_mass(n: int) -> np.ndarray:
    return vr_param(n, "m")


def vr_inertia(n: int) -> np.ndarray:
    return vr_param(n, "J")


def vr_p0(n: int) -> np.ndarray:
    return vr_param(n, "p0")


def vr_q0(n: int) -> np.ndarray:
    return vr_param(n, "q0")


def vr_xi0(n: int) -> np.ndarray:
    return vr_param(n, "xi0")


# (offset, size, short name, kind, units per component, description)
_BODY_VARS = (
    (OFF_P, 3, "p", "output", ("m",) * 3, "position of the body in the world frame"),
    (OFF_R, 9, "R", "output", ("",) * 9, "rotation matrix body->world, row-major"),
    (OFF_XI, 6, "xi", "output", ("rad/s",) * 3 + ("m/s",) * 3, "body-frame velocity [omega; v]"),
    (OFF_Q, 4, "q", "output", ("",) * 4, "unit quaternion of R (w first, w >= 0)"),
    (OFF_CONTACT, 1, "contact", "output", ("",), "1 while resting on the ground plane, else 0"),
    (OFF_U, 6, "u", "input", ("N.m",) * 3 + ("N",) * 3, "body-frame wrench [torque; force]"),
    (OFF_M, 1, "m", "parameter", ("kg",), "mass"),
    (OFF_J, 9, "J", "parameter", ("kg.m2",) * 9, "inertia about the centre of mass, body frame, row-major"),
    (OFF_P0, 3, "p0", "parameter", ("m",) * 3, "initial position"),
    (OFF_Q0, 4, "q0", "parameter", ("",) * 4, "initial orientation quaternion (w first)"),
    (OFF_XI0, 6, "xi0", "parameter", ("rad/s",) * 3 + ("m/s",) * 3, "initial body-frame velocity [omega; v]"),
)

_COMPONENT_NAMES = {
    "p": ("x", "y", "z"),
    "p0": ("x", "y", "z"),
    "q": ("w", "x", "y", "z"),
    "q0": ("w", "x", "y", "z"),
    "xi": ("omega_x", "omega_y", "omega_z", "v_x", "v_y", "v_z"),
    "xi0": ("omega_x", "omega_y", "omega_z", "v_x", "v_y", "v_z"),
    "u": ("tau_x", "tau_y", "tau_z", "f_x", "f_y", "f_z"),
}


def _default_start(short: str, k: int) -> float:
    if short == "m":
        return 1.0
    if short == "J":
        return 1.0 if k in (0, 4, 8) else 0.0
    if short == "q0":
        return 1.0 if k == 0 else 0.0
    return 0.0


def _suffix(short: str, size: int, k: int) -> str:
    if size == 1:
        return ""
    if size == 9:
        return f"[{k // 3 + 1},{k % 3 + 1}]"
    return f"[{k + 1}]"


def variables(n: int):
    """Yields one dict per scalar variable (name, vr, causality, variability, initial, unit,
    description, start) in modelDescription order: globals, then body after body."""
    n = _check_n(n)
    for k, axis in enumerate("xyz"):
        yield dict(name=f"g[{k + 1}]", vr=int(VR_GRAVITY[k]), causality="parameter", variability="fixed",
                   initial="exact", unit="m/s2", start=0.0,
                   description=f"gravity, world frame, {axis} component (every body)")
    yield dict(name="h_internal", vr=VR_H_INTERNAL, causality="parameter", variability="fixed", initial="exact",
               unit="s", start=1e-4, description="fixed internal integration step (RKMK4 on SE(3))")
    for name, vr, unit, desc in TERMS:
        yield dict(name=name, vr=vr, causality="parameter", variability="fixed", initial="exact", unit=unit,
                   start=0.0, description=desc)
    for b in range(n):
        base = body_base(b)
        for offset, size, short, kind, units, desc in _BODY_VARS:
            for k in range(size):
                comp = _COMPONENT_NAMES.get(short)
                d = desc if size == 1 else (
                    f"{desc}, {comp[k]}" if comp else f"{desc}, element ({k // 3 + 1},{k % 3 + 1})")
                v = dict(name=f"body[{b + 1}].{short}{_suffix(short, size, k)}", vr=base + offset + k,
                         causality=kind, unit=units[k], description=f"body {b + 1}: {d}")
                if kind == "output":
                    v.update(variability="discrete" if short == "contact" else "continuous", initial="calculated",
                             start=None)
                elif kind == "input":
                    v.update(variability="continuous", initial=None, start=0.0)
                else:
                    v.update(variability="fixed", initial="exact", start=_default_start(short, k))
                yield v


def variable_name(vr: int, n_bodies: int | None = None) -> str:
    """Structured name of value reference ``vr`` (e.g. ``body[2].u[4]``); ValueError if unknown
    (or if it belongs to a body beyond ``n_bodies`` when that is given)."""
    vr = int(vr)
    if 1 <= vr <= 3:
        return f"g[{vr}]"
    if vr == VR_H_INTERNAL:
        return "h_internal"
    for name, tvr, _unit, _desc in TERMS:
        if vr == tvr:
            return name
    if vr >= BODY_BASE:
        b, off = divmod(vr - BODY_BASE, BODY_STRIDE)
        if b < MAX_BODIES and (n_bodies is None or b < n_bodies):
            for offset, size, short, _kind, _units, _desc in _BODY_VARS:
                if offset <= off < offset + size:
                    return f"body[{b + 1}].{short}{_suffix(short, size, off - offset)}"
    raise ValueError(f"unknown value reference {vr}")
