"""Multirotor airframes: rotor geometry presets that match the flight stacks' own frame definitions,
the allocation matrix they give, and the stack parameters that make a stack's mixer match it.

Body frame FRD; a rotor sits at azimuth φ (degrees from the nose, positive towards the right wing,
ArduPilot's convention) at ``arm_length``; its thrust axis is "up" (−z) tilted by ``tilt_deg`` about
the arm (+tilt for clockwise rotors, −tilt for counter-clockwise ones, as seen from above; a
negative ``tilt_deg`` reverses both); its drag torque is ``torque_coeff``·thrust against its spin.
Column k of A (w = A c, c the normalised thrusts):

    A[3:, k] = T n_k,     A[:3, k] = T (r_k × n_k − km_k n_k),     km_k = +torque_coeff (CCW), −torque_coeff (CW)

(PX4's moment model, ActuatorEffectivenessRotors: a CCW rotor yaws the body clockwise seen from
above, i.e. +z in FRD; its CA_ROTORn_KM is positive for CCW.)

Sources of the presets (read in the stacks' own repositories; facts only, no code):

* ArduPilot ``libraries/AP_Motors/AP_MotorsMatrix.cpp`` (master, 2026-04: ``setup_quad_matrix``,
  ``setup_hexa_matrix``): motor i's angle and yaw factor (CCW = +1, CW = −1), in motor order;
  ``AP_Motors_Class.h``: FRAME_CLASS QUAD = 1, HEXA = 2; FRAME_TYPE PLUS = 0, X = 1.
* PX4 ``src/lib/mixer/MultirotorMixer/geometries/hex_plus.toml`` and ``hex_x.toml`` (rotor positions
  and directions, the same order as ArduPilot's), ``ROMFS/px4fmu_common/init.d-posix/airframes/
  10015_gazebo-classic_iris`` (quad X: CA_ROTOR0..3 front-right KM +, back-left KM +, front-left
  KM −, back-right KM −, PWM_MAIN_FUNCn = 100 + n); control allocation parameters CA_ROTOR_COUNT,
  CA_ROTORn_PX/PY/PZ/AX/AY/AZ/KM/CT, CA_R_REV (``src/modules/control_allocator/module.yaml``);
  ``pwm_out_sim`` (``src/modules/simulation/pwm_out_sim/PWMSim.cpp``, ``module_sim.yaml``): a
  non-reversible motor's HIL output is (pwm − PWM_MAIN_MINn)/(PWM_MAIN_MAXn − PWM_MAIN_MINn).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from controller.errors import Se3SyncError

CW, CCW = False, True


@dataclass(frozen=True)
class Frame:
    azimuths: tuple          # degrees, rotor order = output order (the stacks' motor order)
    ccw: tuple               # spin of each rotor seen from above
    default_tilt: float      # degrees
    description: str
    source: str


FRAMES = {
    "hexa-tilted": Frame((0.0, 60.0, 120.0, 180.0, 240.0, 300.0), (CW, CCW, CW, CCW, CW, CCW), 30.0,
                         "fully actuated hexarotor, arms alternately tilted (se3sync's default)",
                         "se3sync (issue 14); rotor k at 60°·k"),
    "quad-x": Frame((45.0, -135.0, -45.0, 135.0), (CCW, CCW, CW, CW), 0.0,
                    "quadrotor X (ArduPilot QUAD/X, PX4 quadrotor x)",
                    "ArduPilot AP_MotorsMatrix.cpp setup_quad_matrix MOTOR_FRAME_TYPE_X; "
                    "PX4 init.d-posix/airframes/10015_gazebo-classic_iris"),
    "hexa-plus": Frame((0.0, 180.0, -120.0, 60.0, -60.0, 120.0), (CW, CCW, CW, CCW, CCW, CW), 0.0,
                       "hexarotor + (ArduPilot HEXA/PLUS, PX4 hexarotor +)",
                       "ArduPilot AP_MotorsMatrix.cpp setup_hexa_matrix MOTOR_FRAME_TYPE_PLUS; "
                       "PX4 MultirotorMixer/geometries/hex_plus.toml"),
    "hexa-x": Frame((90.0, -90.0, -30.0, 150.0, 30.0, -150.0), (CW, CCW, CW, CCW, CCW, CW), 0.0,
                    "hexarotor X (ArduPilot HEXA/X, PX4 hexarotor x)",
                    "ArduPilot AP_MotorsMatrix.cpp setup_hexa_matrix MOTOR_FRAME_TYPE_X; "
                    "PX4 MultirotorMixer/geometries/hex_x.toml"),
}
DEFAULT_FRAME = "hexa-tilted"
MAX_ROTORS = 6      # controls[0:6]: every preset fits

# ArduPilot's matrix frames a geometry can be matched against: (FRAME_CLASS, FRAME_TYPE) ->
# (name, [(angle°, yaw factor) per motor 1..n]) from AP_MotorsMatrix.cpp
ARDUPILOT_FRAMES = {
    (1, 0): ("QUAD/PLUS", ((90, 1), (-90, 1), (0, -1), (180, -1))),
    (1, 1): ("QUAD/X", ((45, 1), (-135, 1), (-45, -1), (135, -1))),
    (2, 0): ("HEXA/PLUS", ((0, -1), (180, 1), (-120, -1), (60, 1), (-60, 1), (120, -1))),
    (2, 1): ("HEXA/X", ((90, -1), (-90, 1), (-30, -1), (150, 1), (30, 1), (-150, -1))),
}
AP_MOTOR1_FUNCTION = 33     # SERVOn_FUNCTION of Motor1 (Motor m: 32 + m)
PX4_MOTOR1_FUNCTION = 101   # PWM_MAIN_FUNCn of Motor1 (Motor m: 100 + m)
# ArduPilot's motor output range (defaults written to the file): pwm = 1000 + 1000·(spin_min +
# (spin_max − spin_min)·thrust) for MOT_THST_EXPO = 0, i.e. affine in the stack's thrust demand
AP_SPIN_ARM, AP_SPIN_MIN, AP_SPIN_MAX = 0.10, 0.15, 0.95
# The hover throttles the stacks accept. ArduPilot: libraries/AP_Motors/AP_MotorsMulticopter.h
# (AP_MOTORS_THST_HOVER_MIN 0.125f, AP_MOTORS_THST_HOVER_MAX 0.6875f); AP_MotorsMulticopter.cpp's
# update_throttle_hover() constrains the learnt MOT_THST_HOVER to them, and get_throttle_hover()
# (the header) returns MOT_THST_HOVER constrained to them: a value outside is not used as written
# (the parameter's documented @Range, 0.2 0.8, is only advice to a ground station). PX4:
# src/modules/mc_pos_control/multicopter_position_control_params.yaml, MPC_THR_HOVER min 0.1,
# max 0.8 (mc_pos_control_params.c @min/@max in older releases).
AP_THST_HOVER_RANGE = (0.125, 0.6875)
PX4_THR_HOVER_RANGE = (0.1, 0.8)


def check_frame(key: str, name) -> str:
    if name not in FRAMES:
        raise Se3SyncError(f"{key}: unknown frame {name!r} (one of {', '.join(FRAMES)})")
    return name


@dataclass(frozen=True)
class Rotor:
    position: np.ndarray     # m, FRD
    axis: np.ndarray         # unit thrust direction, FRD
    km: float                # m: yaw moment per unit thrust along −axis (PX4's KM: + for CCW)


def rotors(spec) -> list:
    """The rotors of an AllocationSpec (frame, arm_length, tilt_deg, torque_coeff)."""
    fr = FRAMES[spec.frame]
    a = math.radians(spec.tilt_deg)
    out = []
    for phi_deg, ccw in zip(fr.azimuths, fr.ccw):
        phi = (phi_deg / 60.0) * math.pi / 3.0   # = k·π/3 for rotor k of the hexarotors, as before
        er = np.array([math.cos(phi), math.sin(phi), 0.0])
        up = np.array([0.0, 0.0, -1.0])
        t = (-a) if ccw else a          # +tilt for CW rotors, −tilt for CCW ones
        # Rodrigues: `up` rotated about er by t (er ⟂ up)
        n = math.cos(t) * up + math.sin(t) * np.cross(er, up)
        out.append(Rotor(spec.arm_length * er, n, spec.torque_coeff if ccw else -spec.torque_coeff))
    return out


def allocation_matrix(spec) -> np.ndarray:
    """6×6 A with w_frd = A c; columns past the frame's rotor count are zero."""
    A = np.zeros((6, MAX_ROTORS))
    for k, r in enumerate(rotors(spec)):
        A[3:, k] = spec.max_thrust * r.axis
        A[:3, k] = spec.max_thrust * (np.cross(r.position, r.axis) - r.km * r.axis)
    return A


def rotor_count(spec) -> int:
    return len(FRAMES[spec.frame].azimuths)


def hover_fraction(spec, mass: float, g: float) -> float:
    """Thrust fraction c of every rotor that holds the weight level: m g / Σ_k (vertical thrust at c = 1)."""
    lift = -float(allocation_matrix(spec)[5].sum())
    if not lift > 0:
        raise Se3SyncError(f"frame {spec.frame!r}: the rotors give no upward thrust")
    return mass * g / lift


# ------------------------------------------------------------------ ArduPilot
def _angle(position) -> float:
    return math.degrees(math.atan2(position[1], position[0]))


def _same_angle(a: float, b: float) -> bool:
    return abs((a - b + 180.0) % 360.0 - 180.0) < 1e-6


def ardupilot_match(spec):
    """(FRAME_CLASS, FRAME_TYPE, name, [motor number of output k]) of the ArduPilot matrix frame whose
    motors sit where our rotors sit and yaw the body the same way (the sign of A's yaw row: with a
    large tilt, the thrust's sideways part yaws against the rotor drag). Raises Se3SyncError if none."""
    A = allocation_matrix(spec)
    rs = rotors(spec)
    yaw = [float(np.sign(A[2, k])) for k in range(len(rs))]
    for (cls, typ), (name, motors) in ARDUPILOT_FRAMES.items():
        if len(motors) != len(rs):
            continue
        order = []
        for k, r in enumerate(rs):
            m = [i for i, (ang, yf) in enumerate(motors) if _same_angle(ang, _angle(r.position)) and yf == yaw[k]]
            if len(m) != 1:
                break
            order.append(m[0] + 1)
        if len(order) == len(rs) and len(set(order)) == len(rs):
            return cls, typ, name, order
    fr = FRAMES[spec.frame]
    drag = spec.torque_coeff
    if spec.tilt_deg != 0:
        lever = spec.arm_length * math.sin(math.radians(abs(spec.tilt_deg)))
        turn = " reverses" if spec.tilt_deg > 0 and lever > drag else ""
        if turn:
            raise Se3SyncError(
                f"--write-params: frame {spec.frame!r} with tilt_deg = {spec.tilt_deg:g}: the tilted thrust's yaw "
                f"moment ({lever:.3g} m per N) outweighs the rotor drag ({drag:.3g} m per N) and reverses every "
                f"rotor's yaw, which no ArduPilot matrix frame has (its mixer would yaw the wrong way); use "
                f"tilt_deg = {-spec.tilt_deg:g} (tilted the other way, the two add) or a tilt under "
                f"{math.degrees(math.asin(min(1.0, drag / spec.arm_length))):.3g}°, or PX4 (any geometry)")
    raise Se3SyncError(f"--write-params: no ArduPilot matrix frame has rotors at {list(fr.azimuths)}° "
                       f"spinning {['CCW' if c else 'CW' for c in fr.ccw]}")


def ardupilot_params(spec, mass: float, g: float) -> list:
    """[(name, value, comment)] for ArduPilot (a .parm file for --defaults)."""
    cls, typ, name, order = ardupilot_match(spec)
    c_h = hover_fraction(spec, mass, g)
    hover = round((c_h - AP_SPIN_MIN) / (AP_SPIN_MAX - AP_SPIN_MIN), 6)
    _check_hover("MOT_THST_HOVER", hover, AP_THST_HOVER_RANGE, "ArduPilot (AP_MotorsMulticopter.h)", c_h, spec, mass)
    A = allocation_matrix(spec)
    ratio = float(np.abs(A[2, :len(order)]).mean()) / (spec.max_thrust * spec.torque_coeff) if spec.torque_coeff else 0
    out = [("FRAME_CLASS", cls, f"{name} (ArduPilot AP_MotorsMatrix.cpp) matched to se3sync frame {spec.frame}"),
           ("FRAME_TYPE", typ, "" if spec.tilt_deg == 0 else
            f"tilt {spec.tilt_deg:g} deg: each rotor yaws the body {ratio:.3g} x as much as its drag torque alone "
            "(the stack's yaw loop sees that much more authority)")]
    for k, m in enumerate(order):
        out.append((f"SERVO{k + 1}_FUNCTION", AP_MOTOR1_FUNCTION + m - 1, f"output {k + 1} = Motor{m} "
                    f"(rotor {k + 1} at {_angle(rotors(spec)[k].position):g}°)"))
    out += [("MOT_PWM_TYPE", 0, "normal PWM"),
            ("MOT_PWM_MIN", 1000, "se3sync reads thrust = (pwm - 1000)/1000 of max_thrust"),
            ("MOT_PWM_MAX", 2000, ""),
            ("MOT_SPIN_ARM", AP_SPIN_ARM, "ArduPilot's defaults, written so that MOT_THST_HOVER below holds"),
            ("MOT_SPIN_MIN", AP_SPIN_MIN, ""),
            ("MOT_SPIN_MAX", AP_SPIN_MAX, ""),
            ("MOT_THST_EXPO", 0.0, "se3sync's thrust is linear in the output"),
            ("MOT_THST_HOVER", hover, f"{mass:g} kg: each rotor at {c_h:.4g} of {spec.max_thrust:g} N")]
    return out


def _check_hover(key: str, value: float, rng: tuple, stack: str, c_h: float, spec, mass: float) -> None:
    """Refuse a hover throttle the stack would not use as written (one line naming key and value)."""
    lo, hi = rng
    if not lo <= value <= hi:
        raise Se3SyncError(f"--write-params: {key} = {value:.4g} is outside the {lo:g}..{hi:g} that {stack} accepts "
                           f"(hovering {mass:g} kg takes {c_h:.3g} of each rotor's {spec.max_thrust:g} N): change "
                           "allocation.max_thrust or the mass")


# ------------------------------------------------------------------ PX4
def px4_params(spec, mass: float, g: float) -> list:
    """[(name, value, comment)] for PX4 (``param set-default`` lines for an airframe file)."""
    rs = rotors(spec)
    c_h = hover_fraction(spec, mass, g)
    _check_hover("MPC_THR_HOVER", round(c_h, 6), PX4_THR_HOVER_RANGE, "PX4 (mc_pos_control)", c_h, spec, mass)
    out = [("CA_AIRFRAME", 0, "multirotor"),
           ("CA_ROTOR_COUNT", len(rs), f"{spec.frame}: {FRAMES[spec.frame].source}")]
    for k, r in enumerate(rs):
        for ax, v in zip("XYZ", r.position):
            out.append((f"CA_ROTOR{k}_P{ax}", _num(v), ""))
        for ax, v in zip("XYZ", r.axis):
            out.append((f"CA_ROTOR{k}_A{ax}", _num(v), ""))
        out.append((f"CA_ROTOR{k}_KM", _num(r.km), "CCW" if r.km > 0 else "CW"))
        out.append((f"CA_ROTOR{k}_CT", _num(spec.max_thrust), "N at full output (linear: THR_MDL_FAC 0)"))
    out.append(("CA_R_REV", (1 << len(rs)) - 1 if spec.reversible else 0, "reversible rotors"))
    out.append(("THR_MDL_FAC", 0.0, "se3sync's thrust is linear in the output"))
    for k in range(len(rs)):
        out += [(f"PWM_MAIN_FUNC{k + 1}", PX4_MOTOR1_FUNCTION + k, f"output {k + 1} = Motor{k + 1}"),
                (f"PWM_MAIN_MIN{k + 1}", 1000, ""), (f"PWM_MAIN_MAX{k + 1}", 2000, "")]
    out.append(("MPC_THR_HOVER", round(c_h, 6), f"{mass:g} kg"))
    return out


def _num(v: float) -> float:
    v = float(round(v, 9))
    return 0.0 if v == 0 else v      # no "-0.0" in the file


# ------------------------------------------------------------------ files
STACKS = ("ardupilot", "px4")


def params_text(stack: str, spec, mass: float, g: float, header: str = "") -> str:
    """The parameter file: ArduPilot ``NAME VALUE`` lines (a .parm for SITL's --defaults), PX4
    ``param set-default NAME VALUE`` lines (for an airframe file); ``#`` comments."""
    rows = ardupilot_params(spec, mass, g) if stack == "ardupilot" else px4_params(spec, mass, g)
    lines = [f"# {line}" for line in header.splitlines()]
    for name, value, comment in rows:
        v = repr(float(value)) if isinstance(value, float) else str(int(value))
        body = f"{name} {v}" if stack == "ardupilot" else f"param set-default {name} {v}"
        lines.append(body + (f"  # {comment}" if comment else ""))
    return "\n".join(lines) + "\n"


def parse_params(text: str) -> dict:
    """NAME -> value from either format (comments, ``param set``/``set-default`` prefixes, ``,`` or
    whitespace separators)."""
    out = {}
    for n, line in enumerate(text.splitlines(), start=1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.replace(",", " ").split()
        if parts[:2] in (["param", "set-default"], ["param", "set"]):
            parts = parts[2:]
        if len(parts) != 2:
            raise Se3SyncError(f"parameter file line {n}: expected NAME VALUE, got {line!r}")
        try:
            out[parts[0]] = float(parts[1])
        except ValueError:
            raise Se3SyncError(f"parameter file line {n}: {parts[1]!r} is not a number") from None
    return out


def geometry_from_params(stack: str, params: dict) -> list:
    """[(angle° of output k's rotor, yaw sign +1 CCW / −1 CW)] that a stack configured with these
    parameters drives on outputs 1..n (ArduPilot: its frame's motor table through SERVOn_FUNCTION;
    PX4: CA_ROTORk on the output whose PWM_MAIN_FUNC is Motor k+1)."""
    out = []
    if stack == "ardupilot":
        key = (int(params["FRAME_CLASS"]), int(params["FRAME_TYPE"]))
        if key not in ARDUPILOT_FRAMES:
            raise Se3SyncError(f"FRAME_CLASS/FRAME_TYPE {key} is not one of {sorted(ARDUPILOT_FRAMES)}")
        motors = ARDUPILOT_FRAMES[key][1]
        for k in range(len(motors)):
            m = int(params[f"SERVO{k + 1}_FUNCTION"]) - AP_MOTOR1_FUNCTION
            ang, yf = motors[m]
            out.append((float(ang), float(yf)))
        return out
    n = int(params["CA_ROTOR_COUNT"])
    for k in range(n):
        m = int(params[f"PWM_MAIN_FUNC{k + 1}"]) - PX4_MOTOR1_FUNCTION
        out.append((_angle((params[f"CA_ROTOR{m}_PX"], params[f"CA_ROTOR{m}_PY"])),
                    float(np.sign(params[f"CA_ROTOR{m}_KM"]))))
    return out


def px4_matrix_from_params(params: dict) -> np.ndarray:
    """The allocation matrix PX4's effectiveness model builds from CA_ROTOR* (output order)."""
    n = int(params["CA_ROTOR_COUNT"])
    A = np.zeros((6, MAX_ROTORS))
    for k in range(n):
        m = int(params[f"PWM_MAIN_FUNC{k + 1}"]) - PX4_MOTOR1_FUNCTION
        p = np.array([params[f"CA_ROTOR{m}_P{a}"] for a in "XYZ"])
        ax = np.array([params[f"CA_ROTOR{m}_A{a}"] for a in "XYZ"])
        ct, km = params[f"CA_ROTOR{m}_CT"], params[f"CA_ROTOR{m}_KM"]
        A[3:, k] = ct * ax
        A[:3, k] = ct * (np.cross(p, ax) - km * ax)
    return A
