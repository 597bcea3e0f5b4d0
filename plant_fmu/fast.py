"""FleetFMU: the plant FMU loaded with fmpy, plus a low-overhead stepping path.

The fast path (``set_input`` / ``do_step`` / ``get_state`` / ``get_quat``) calls the FMU's
C functions directly through ctypes prototypes with plain-integer pointer arguments computed
once, on preallocated numpy buffers: no per-call allocation.
"""
from __future__ import annotations

import atexit
import ctypes
import shutil
import threading
import zipfile
from ctypes import c_double, c_int, c_size_t, c_void_p
from pathlib import Path
from typing import NamedTuple
from xml.etree import ElementTree

import numpy as np

from controller import layout as state_layout
from controller.errors import Se3SyncError
from controller.se3 import rot_to_quat

from . import build, layout

fmi2OK, fmi2Warning, fmi2Discard, fmi2Error, fmi2Fatal = 0, 1, 2, 3, 4
_STATUS = {0: "OK", 1: "Warning", 2: "Discard", 3: "Error", 4: "Fatal", 5: "Pending"}

# one extraction per FMU file per process: instances share the loaded library
_extract_lock = threading.Lock()
_extracted: dict[tuple[str, float], str] = {}


def _cleanup_extracted() -> None:
    for d in _extracted.values():
        shutil.rmtree(d, ignore_errors=True)


atexit.register(_cleanup_extracted)


class FMUError(Se3SyncError):
    """An FMI call returned fmi2Error or fmi2Fatal; the message includes what the FMU logged."""

    def __init__(self, function: str, status: int, messages: list[str]):
        self.function = function
        self.status = status
        self.messages = list(messages)
        super().__init__(f"{function} returned fmi2{_STATUS.get(status, status)}: {_one_line(self.messages)}")


_DETAIL_MAX = 400  # characters of FMU messages in an FMUError (all of them stay in .messages)


def _one_line(messages: list[str]) -> str:
    """The logged messages joined into one line of at most about _DETAIL_MAX characters, whole
    messages first to last, then "(+k more)"; a single overlong message is cut with "..."."""
    parts = [" ".join(m.split()) for m in messages]
    parts = [m for m in parts if m]
    if not parts:
        return "no message logged"
    detail, used = "", 0
    for m in parts:
        if detail and len(detail) + 2 + len(m) > _DETAIL_MAX:
            break
        detail = f"{detail}; {m}" if detail else (m if len(m) <= _DETAIL_MAX else m[:_DETAIL_MAX - 3] + "...")
        used += 1
    if used < len(parts):
        detail += f" (+{len(parts) - used} more)"
    return detail


def read_model_description(path, *args, **kwargs):
    """fmpy's read_model_description, fmpy imported on first use: what imports this module
    only to name its types (`cosim.fastloop`, an agent process that steps no FMU) does not pay
    for fmpy (20-30 ms of start-up)."""
    from fmpy import read_model_description as read

    return read(path, *args, **kwargs)


def _identity(fmu_path: Path, n: int) -> tuple[str, str]:
    """(guid, Co-Simulation modelIdentifier) of the FMU at fmu_path, checked to be a plant of n
    bodies. The plant for n bodies that `build` makes is recognised by its GUID (it hashes the C
    sources and n), read from the head of modelDescription.xml: fmpy's full read builds an
    object per variable (2.6 s for 1000 bodies, 51,000 variables) and the layout of our own FMU
    is plant_fmu/layout.py's. Any other FMU is read and validated by fmpy and must have 6·n
    inputs."""
    head = {}
    try:
        with zipfile.ZipFile(fmu_path) as z, z.open("modelDescription.xml") as f:
            for event, el in ElementTree.iterparse(f, events=("start",)):
                if el.tag == "fmiModelDescription":
                    head["guid"] = el.get("guid")
                elif el.tag == "CoSimulation":
                    head["id"] = el.get("modelIdentifier")
                elif el.tag == "ModelVariables":
                    break
    except (OSError, KeyError, zipfile.BadZipFile, ElementTree.ParseError):
        head = {}
    if head.get("guid") == build.guid(n) and head.get("id") == build.MODEL_IDENTIFIER:
        return head["guid"], head["id"]
    md = read_model_description(str(fmu_path))
    n_in = sum(1 for v in md.modelVariables if v.causality == "input")
    if n_in != 6 * n:
        raise Se3SyncError(f"{fmu_path} has {n_in // 6} bodies, expected {n}")
    if md.coSimulation is None:
        raise Se3SyncError(f"{fmu_path} has no Co-Simulation interface")
    return md.guid, md.coSimulation.modelIdentifier


class FmiCalls(NamedTuple):
    """What compiled code needs to drive one FleetFMU instance without Python (a numba-friendly
    record: `FleetFMU.fmi_calls`): ``calls`` the addresses of fmi2GetReal, fmi2SetReal and
    fmi2DoStep (int64 (3,), in `CALL_NAMES` order), ``component`` the fmi2Component, the value
    references of the state rows and of the inputs (uint32), and the instance's state (n, 18)
    and input (n, 6) buffers. The addresses are valid while the instance is open."""

    calls: np.ndarray
    component: int
    vr_state: np.ndarray
    vr_input: np.ndarray
    state: np.ndarray
    inputs: np.ndarray


CALL_NAMES = ("fmi2GetReal", "fmi2SetReal", "fmi2DoStep")


def _as_array(x, shape, name) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    try:
        return np.broadcast_to(a, shape).astype(np.float64, copy=True)
    except ValueError:
        raise Se3SyncError(f"{name} must have shape {shape}, got {a.shape}") from None


class FleetFMU:
    """N rigid bodies in one instance of the plant FMU.

    Typical use::

        with FleetFMU(6) as fleet:
            fleet.set_parameters(mass=m, J=J, p0=p0, R0=R0, xi0=xi0)
            fleet.initialize()
            for k in range(steps):
                fleet.set_input(u)            # (6, 6) body wrenches
                fleet.do_step(k * h, h)
                X = fleet.get_state()         # (6, 18) [p, R row-major, xi] (buffer reused)
    """

    def __init__(self, n_bodies: int, fmu_path=None, instance_name: str = "plant", logger=None):
        self.n = n = int(n_bodies)
        if fmu_path is None:
            fmu_path = build.fmu_path(n)
        self.fmu_path = Path(fmu_path)
        self.messages: list[tuple[str, int, str]] = []
        self._user_logger = logger
        self._closed = True
        self._slave = None
        from fmpy import extract
        from fmpy.fmi2 import FMU2Slave, fmi2CallbackFunctions, fmi2CallbackLoggerTYPE

        guid, model_identifier = _identity(self.fmu_path, n)
        key = (str(self.fmu_path.resolve()), self.fmu_path.stat().st_mtime)
        with _extract_lock:
            unzipdir = _extracted.get(key)
            if unzipdir is None:
                unzipdir = _extracted[key] = extract(str(self.fmu_path))

        def _log(env, name, status, category, message):
            cat = category.decode("utf-8", "replace") if category else ""
            text = message.decode("utf-8", "replace") if message else ""
            self.messages.append((cat, int(status), text))
            if self._user_logger is not None:
                try:
                    self._user_logger(cat, int(status), text)
                except Exception:  # never let a Python exception cross the C boundary
                    pass

        self._logger_cb = fmi2CallbackLoggerTYPE(_log)
        self._callbacks = fmi2CallbackFunctions()
        self._callbacks.logger = self._logger_cb
        slave = FMU2Slave(guid=guid, unzipDirectory=unzipdir,
                          modelIdentifier=model_identifier, instanceName=instance_name)
        self._mark = len(self.messages)
        try:
            slave.instantiate(callbacks=self._callbacks)
        except Exception:
            raise FMUError("fmi2Instantiate", fmi2Error, [m[2] for m in self.messages]) from None
        self._slave = slave
        self._closed = False
        comp = slave.component

        def raw(name, *argtypes, keep_gil=False):
            addr = ctypes.cast(getattr(slave.dll, name), c_void_p).value
            proto = ctypes.PYFUNCTYPE if keep_gil else ctypes.CFUNCTYPE
            f = proto(c_int, *argtypes)(addr)
            if not argtypes:
                f.argtypes = None  # arguments are passed as ready-made ctypes objects (fastest)
            return f

        # get/set are short: keep the GIL (PYFUNCTYPE) and pass prebuilt ctypes objects;
        # doStep releases the GIL so that other threads can run during long steps
        self._SetReal = raw("fmi2SetReal", keep_gil=True)
        self._GetReal = raw("fmi2GetReal", keep_gil=True)
        self._DoStep = raw("fmi2DoStep", c_void_p, c_double, c_double, c_int)
        self._GetFMUstate = raw("fmi2GetFMUstate", c_void_p, c_void_p)
        self._SetFMUstate = raw("fmi2SetFMUstate", c_void_p, c_void_p)
        self._FreeFMUstate = raw("fmi2FreeFMUstate", c_void_p, c_void_p)
        self._c = c_void_p(comp)

        # preallocated buffers and their raw addresses
        self._vr_state = np.ascontiguousarray(layout.vr_state(n))
        self._vr_quat = np.ascontiguousarray(layout.vr_quat(n))
        self._vr_input = np.ascontiguousarray(layout.vr_input(n))
        self._vr_contact = np.ascontiguousarray(layout.vr_contact(n))
        self._state = np.zeros((n, layout.N_STATE))
        self._quat = np.zeros((n, 4))
        self._u = np.zeros((n, 6))
        self._n_state, self._n_quat, self._n_input = (c_size_t(n * layout.N_STATE), c_size_t(n * 4),
                                                      c_size_t(n * 6))
        self._p_vr_state = c_void_p(self._vr_state.ctypes.data)
        self._p_vr_quat = c_void_p(self._vr_quat.ctypes.data)
        self._p_vr_input = c_void_p(self._vr_input.ctypes.data)
        self._p_state = c_void_p(self._state.ctypes.data)
        self._p_quat = c_void_p(self._quat.ctypes.data)
        self._p_u = c_void_p(self._u.ctypes.data)

    # ------------------------------------------------------------------ helpers
    def raise_status(self, function: str, status: int):
        """Raises the FMUError of a call that returned ``status`` (≥ fmi2Error) outside this
        object (compiled code driving `fmi_calls`), with what the FMU logged since."""
        self._fail(function, int(status))

    def _fail(self, function: str, status: int):
        msgs = [m[2] for m in self.messages[self._mark:] if m[1] >= fmi2Warning] or [m[2] for m in self.messages[-3:]]
        self._mark = len(self.messages)
        raise FMUError(function, status, msgs)

    def _check_open(self):
        if self._closed:
            raise Se3SyncError("the FMU instance is closed")

    def _call(self, function: str, f, *args):
        self._check_open()
        self._mark = len(self.messages)
        try:
            status = f(*args)
        except Exception as exc:  # fmpy raises FMICallException for status > warning
            status = getattr(exc, "status", fmi2Error)
        if status >= fmi2Error:
            self._fail(function, status)
        return status

    def set_real(self, vrs, values) -> None:
        """Sets Real variables by value reference (any phase; checked by the FMU)."""
        self._check_open()
        vr = np.ascontiguousarray(vrs, dtype=np.uint32).reshape(-1)
        val = np.ascontiguousarray(values, dtype=np.float64).reshape(-1)
        if vr.size != val.size:
            raise Se3SyncError(f"{vr.size} value references but {val.size} values")
        self._mark = len(self.messages)
        st = self._SetReal(self._c, c_void_p(vr.ctypes.data), c_size_t(vr.size), c_void_p(val.ctypes.data))
        if st >= fmi2Error:
            self._fail("fmi2SetReal", st)

    def get_real(self, vrs) -> np.ndarray:
        self._check_open()
        vr = np.ascontiguousarray(vrs, dtype=np.uint32).reshape(-1)
        out = np.empty(vr.size)
        self._mark = len(self.messages)
        st = self._GetReal(self._c, c_void_p(vr.ctypes.data), c_size_t(vr.size), c_void_p(out.ctypes.data))
        if st >= fmi2Error:
            self._fail("fmi2GetReal", st)
        return out

    # ------------------------------------------------------------------ setup
    def set_parameters(self, mass=None, J=None, p0=None, R0=None, q0=None, xi0=None, gravity=None,
                       h_internal=None, ground=None, ground_height=None, drag_linear=None,
                       drag_angular=None) -> None:
        """Sets the parameters (before ``initialize``); None leaves the FMU's default
        (m = 1, J = I, p0 = 0, q0 = identity, xi0 = 0, g = 0, h_internal = 1e-4; no ground, no drag).
        ``ground`` (bool), ``ground_height`` (m along −g), ``drag_linear`` (N·s/m) and ``drag_angular``
        (N·m·s/rad) are the optional plant terms (docs/reference/plant-fmu.md "Ground and drag")."""
        n = self.n
        vrs, vals = [], []
        if mass is not None:
            vrs.append(layout.vr_mass(n)); vals.append(_as_array(mass, (n,), "mass").reshape(-1))
        if J is not None:
            vrs.append(layout.vr_inertia(n)); vals.append(_as_array(J, (n, 3, 3), "J").reshape(-1))
        if p0 is not None:
            vrs.append(layout.vr_p0(n)); vals.append(_as_array(p0, (n, 3), "p0").reshape(-1))
        if R0 is not None and q0 is not None:
            raise Se3SyncError("give either R0 or q0, not both")
        if R0 is not None:
            R = _as_array(R0, (n, 3, 3), "R0")
            err = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2))
            det = np.linalg.det(R)
            bad = np.flatnonzero((err > 1e-6) | (det <= 0) | ~np.isfinite(err))
            if bad.size:
                i = int(bad[0])
                raise Se3SyncError(f"R0 of body {i + 1} is not a rotation matrix (|R^T R - I| = {err[i]:.3g}, "
                                   f"det = {det[i]:.6g})")
            q0 = rot_to_quat(R)
        if q0 is not None:
            vrs.append(layout.vr_q0(n)); vals.append(_as_array(q0, (n, 4), "q0").reshape(-1))
        if xi0 is not None:
            vrs.append(layout.vr_xi0(n)); vals.append(_as_array(xi0, (n, 6), "xi0").reshape(-1))
        if gravity is not None:
            vrs.append(layout.VR_GRAVITY); vals.append(_as_array(gravity, (3,), "gravity"))
        if h_internal is not None:
            vrs.append(np.array([layout.VR_H_INTERNAL], dtype=np.uint32)); vals.append(np.array([float(h_internal)]))
        for vr, value in ((layout.VR_GROUND, None if ground is None else float(bool(ground))),
                          (layout.VR_GROUND_HEIGHT, ground_height), (layout.VR_DRAG_LINEAR, drag_linear),
                          (layout.VR_DRAG_ANGULAR, drag_angular)):
            if value is not None:
                vrs.append(np.array([vr], dtype=np.uint32)); vals.append(np.array([float(value)]))
        if vrs:
            self.set_real(np.concatenate(vrs), np.concatenate(vals))

    def set_initial_state(self, S0, **parameters) -> None:
        """Sets the initial state from rows S0 (n, 18) laid out as `controller.layout` (p, R,
        ξ), plus any other parameters of `set_parameters` (mass, J, gravity, h_internal)."""
        S0 = _as_array(S0, (self.n, state_layout.S_WIDTH), "S0")
        self.set_parameters(p0=state_layout.positions(S0), R0=state_layout.rotations(S0),
                            xi0=state_layout.velocities(S0), **parameters)

    def initialize(self, t0: float = 0.0) -> None:
        """setupExperiment(t0) + enter/exit initialization mode (parameters are validated here)."""
        self._check_open()
        s = self._slave
        self._call("fmi2SetupExperiment", s.setupExperiment, None, float(t0))
        self._call("fmi2EnterInitializationMode", s.enterInitializationMode)
        self._call("fmi2ExitInitializationMode", s.exitInitializationMode)

    # ------------------------------------------------------------------ fast path
    @property
    def u(self) -> np.ndarray:
        """The preallocated (n, 6) input buffer: write into it and call ``set_input()`` to skip a copy."""
        return self._u

    def set_input(self, u: np.ndarray | None = None) -> None:
        """u: (n, 6) body wrenches [tau; f] (copied into the preallocated input buffer);
        None sends the buffer ``self.u`` as it is."""
        if u is not None and u is not self._u:
            np.copyto(self._u, u)
        st = self._SetReal(self._c, self._p_vr_input, self._n_input, self._p_u)
        if st >= fmi2Error:
            self._fail("fmi2SetReal", st)

    def do_step(self, t: float, h: float) -> None:
        st = self._DoStep(self._c, t, h, 1)
        if st >= fmi2Error:
            self._fail("fmi2DoStep", st)

    def get_state(self) -> np.ndarray:
        """(n, 18) [p, R row-major, xi] -- a view of a buffer that the next call overwrites."""
        st = self._GetReal(self._c, self._p_vr_state, self._n_state, self._p_state)
        if st >= fmi2Error:
            self._fail("fmi2GetReal", st)
        return self._state

    def get_contact(self) -> np.ndarray:
        """(n,) bool: which bodies rest on the ground (always False without a ground)."""
        return self.get_real(self._vr_contact) != 0.0
    def fmi_calls(self) -> FmiCalls:
        """The raw interface of this open instance for compiled code (`FmiCalls`)."""
        self._check_open()
        calls = np.array([ctypes.cast(getattr(self._slave.dll, name), c_void_p).value
                          for name in CALL_NAMES], dtype=np.int64)
        return FmiCalls(calls, int(self._c.value), self._vr_state, self._vr_input, self._state,
                        self._u)

    def get_quat(self) -> np.ndarray:
        """(n, 4) unit quaternions (w first, w >= 0) -- a view of a reused buffer."""
        st = self._GetReal(self._c, self._p_vr_quat, self._n_quat, self._p_quat)
        if st >= fmi2Error:
            self._fail("fmi2GetReal", st)
        return self._quat

    # ------------------------------------------------------------------ FMU state
    def get_fmu_state(self) -> c_void_p:
        state = c_void_p()
        self._call("fmi2GetFMUstate", self._GetFMUstate, self._c, ctypes.addressof(state))
        return state

    def set_fmu_state(self, state: c_void_p) -> None:
        self._call("fmi2SetFMUstate", self._SetFMUstate, self._c, state)

    def free_fmu_state(self, state: c_void_p) -> None:
        if state is not None and state.value:
            self._call("fmi2FreeFMUstate", self._FreeFMUstate, self._c, ctypes.addressof(state))

    def serialize_fmu_state(self, state: c_void_p) -> bytes:
        self._check_open()
        self._mark = len(self.messages)
        try:
            return self._slave.serializeFMUstate(state)
        except Exception as exc:
            self._fail("fmi2SerializeFMUstate", getattr(exc, "status", fmi2Error))

    def deserialize_fmu_state(self, data: bytes) -> c_void_p:
        self._check_open()
        self._mark = len(self.messages)
        try:
            return self._slave.deSerializeFMUstate(bytes(data))
        except Exception as exc:
            self._fail("fmi2DeSerializeFMUstate", getattr(exc, "status", fmi2Error))

    # ------------------------------------------------------------------ life cycle
    def reset(self) -> None:
        self._check_open()
        self._call("fmi2Reset", self._slave.reset)

    def terminate(self) -> None:
        self._check_open()
        self._call("fmi2Terminate", self._slave.terminate)

    def close(self) -> None:
        """Frees the instance (and unloads the library); safe to call more than once."""
        if self._closed:
            return
        self._closed = True

        def closed(*args):
            raise Se3SyncError("the FMU instance is closed")

        # the fast path must never reach the freed instance
        self._SetReal = self._GetReal = self._DoStep = closed
        self._GetFMUstate = self._SetFMUstate = self._FreeFMUstate = closed
        try:
            self._slave.freeInstance()
        finally:
            self._slave = None

    def __enter__(self) -> "FleetFMU":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass
