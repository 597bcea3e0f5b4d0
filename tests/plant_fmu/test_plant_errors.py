"""Bad input and illegal call sequences: fmi2Error + a logged message naming the culprit, no crash.

Driven through fmpy's own FMU2Slave with a logger callback that records the messages.
"""
from __future__ import annotations

import ctypes
import math

import numpy as np
import pytest
from fmpy import extract, read_model_description
from fmpy.fmi1 import FMICallException
from fmpy.fmi2 import (FMU2Slave, fmi2CallbackFunctions, fmi2CallbackLoggerTYPE, fmi2Error,
                       fmi2OK, fmi2Warning)

from plant_fmu import build, layout

N = 2
B2 = layout.body_base(1)  # body[2]


@pytest.fixture(scope="module")
def unzipped():
    path = build.fmu_path(N)
    md = read_model_description(str(path))
    return md, extract(str(path))


class Plant:
    """FMU2Slave + recorded log messages."""

    def __init__(self, unzipped, guid=None):
        md, d = unzipped
        self.messages = []

        def log(env, name, status, category, message):
            self.messages.append((category.decode(), status, message.decode()))

        self.cb = fmi2CallbackFunctions()
        self.cb.logger = fmi2CallbackLoggerTYPE(log)
        self.slave = FMU2Slave(guid=guid or md.guid, unzipDirectory=d, modelIdentifier=md.coSimulation.modelIdentifier,
                               instanceName="bad")

    def __enter__(self):
        self.slave.instantiate(callbacks=self.cb)
        return self

    def __exit__(self, *exc):
        self.slave.freeInstance()

    def init(self):
        self.slave.setupExperiment(startTime=0.0)
        self.slave.enterInitializationMode()
        return self.slave.exitInitializationMode()

    def expect_error(self, fn, *args, match: str):
        del self.messages[:]
        with pytest.raises(FMICallException) as exc:
            fn(*args)
        assert exc.value.status == fmi2Error
        text = " | ".join(m[2] for m in self.messages)
        assert match in text, (match, self.messages)
        assert any(m[1] == fmi2Error and m[0] == "logStatusError" for m in self.messages)
        return text


def set_params(p, values: dict):
    p.slave.setReal(list(values), list(values.values()))


BAD_PARAMETERS = [
    ("mass zero", {B2 + 40: 0.0}, "body[2].m"),
    ("mass negative", {B2 + 40: -1.0}, "body[2].m"),
    ("J not symmetric", {B2 + 42: 0.1, B2 + 44: 0.2}, "body[2].J is not symmetric"),
    ("J not positive definite", {B2 + 49: -1.0}, "body[2].J is not positive definite"),
    ("J singular", {B2 + 41: 0.0, B2 + 45: 1.0, B2 + 49: 1.0}, "body[2].J is not positive definite"),
    ("J breaks triangle inequality", {B2 + 41: 1.0, B2 + 45: 1.0, B2 + 49: 2.5}, "triangle inequality"),
    ("q0 zero", {B2 + 53: 0.0}, "body[2].q0"),
    ("q0 far from unit", {B2 + 53: 1.01}, "body[2].q0"),
    ("h_internal zero", {layout.VR_H_INTERNAL: 0.0}, "h_internal"),
    ("h_internal negative", {layout.VR_H_INTERNAL: -1e-4}, "h_internal"),
]


@pytest.mark.parametrize("case,values,match", BAD_PARAMETERS, ids=[c[0] for c in BAD_PARAMETERS])
def test_bad_parameters_refused_at_exit_initialization(unzipped, case, values, match):
    with Plant(unzipped) as p:
        set_params(p, values)
        p.slave.setupExperiment(startTime=0.0)
        p.slave.enterInitializationMode()
        p.expect_error(p.slave.exitInitializationMode, match=match)
        # nothing was lost: fix the parameters and carry on
        set_params(p, {layout.VR_H_INTERNAL: 1e-4, B2 + 40: 1.0, B2 + 53: 1.0,
                       **{B2 + 41 + k: float(k in (0, 4, 8)) for k in range(9)}})
        assert p.slave.exitInitializationMode() == fmi2OK
        p.slave.doStep(0.0, 0.01)


def test_triangle_inequality_boundary_is_accepted(unzipped):
    """A thin plate (J3 = J1 + J2 exactly) is physical."""
    with Plant(unzipped) as p:
        set_params(p, {B2 + 41: 1.0, B2 + 45: 2.0, B2 + 49: 3.0})
        assert p.init() == fmi2OK


def test_every_problem_is_reported(unzipped):
    with Plant(unzipped) as p:
        set_params(p, {layout.body_base(0) + 40: -2.0, B2 + 53: 0.0})
        p.slave.enterInitializationMode()
        text = p.expect_error(p.slave.exitInitializationMode, match="body[1].m")
        assert "body[2].q0" in text


def test_slightly_off_quaternion_is_normalised_with_a_warning(unzipped):
    with Plant(unzipped) as p:
        q = np.array([1.0, 0.2, -0.1, 0.3])
        q *= (1 + 5e-4) / np.linalg.norm(q)
        set_params(p, {B2 + 53 + k: q[k] for k in range(4)})
        assert p.init() == fmi2Warning
        assert any("body[2].q0" in m[2] and "normalised" in m[2] and m[1] == fmi2Warning for m in p.messages)
        out = np.array(p.slave.getReal([B2 + 18 + k for k in range(4)]))
        assert abs(np.linalg.norm(out) - 1) < 1e-15
        assert np.allclose(out, q / np.linalg.norm(q), atol=1e-15)


NON_FINITE = [
    (layout.body_base(1) + 40, "body[2].m"),
    (B2 + 42, "body[2].J[1,2]"),
    (B2 + 52, "body[2].p0[3]"),
    (B2 + 55, "body[2].q0[3]"),
    (B2 + 62, "body[2].xi0[6]"),
    (2, "g[2]"),
    (layout.VR_H_INTERNAL, "h_internal"),
]


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize("vr,name", NON_FINITE, ids=[c[1] for c in NON_FINITE])
def test_non_finite_parameters_refused_at_set_time(unzipped, vr, name, value):
    with Plant(unzipped) as p:
        p.expect_error(p.slave.setReal, [vr], [value], match=name)
        assert p.init() == fmi2OK  # the refused value was not stored


def test_non_finite_input_refused_at_set_time(unzipped):
    with Plant(unzipped) as p:
        p.init()
        vr = B2 + 33  # body[2].u[4]
        p.expect_error(p.slave.setReal, [B2 + 30, vr], [1.0, math.nan], match="body[2].u[4]")
        assert p.slave.getReal([B2 + 30]) == [0.0]  # nothing of the refused call was stored
        p.slave.doStep(0.0, 0.01)


def test_bad_communication_steps(unzipped):
    with Plant(unzipped) as p:
        p.init()
        for h in (0.0, -0.01, math.nan, math.inf):
            p.expect_error(p.slave.doStep, 0.0, h, match="communicationStepSize")
        p.slave.doStep(0.0, 0.01)


def test_overflowing_state_fails_the_step_without_crashing(unzipped):
    with Plant(unzipped) as p:
        p.init()
        p.slave.setReal([B2 + 33], [1e308])
        p.expect_error(p.slave.doStep, 0.0, 1.0, match="no longer finite")
        p.expect_error(p.slave.doStep, 1.0, 1.0, match="illegal call")  # step failed: no more steps
        p.slave.terminate()


def test_unknown_value_references(unzipped):
    with Plant(unzipped) as p:
        p.expect_error(p.slave.setReal, [9], [1.0], match="unknown value reference 9")
        p.init()
        bad = layout.body_base(N)  # first VR past the last body
        p.expect_error(p.slave.getReal, [1000, bad], match=f"unknown value reference {bad}")
        p.expect_error(p.slave.getReal, [1025], match="unknown value reference 1025")
        p.expect_error(p.slave.setReal, [1000], [1.0], match="body[1].p[1]")  # outputs are not settable


def test_parameters_fixed_after_initialization(unzipped):
    with Plant(unzipped) as p:
        p.init()
        p.expect_error(p.slave.setReal, [B2 + 40], [2.0], match="body[2].m")
        p.expect_error(p.slave.setReal, [3], [1.0], match="g[3]")
        assert p.slave.getReal([B2 + 40]) == [1.0]
        p.slave.setReal([B2 + 30], [1.0])  # inputs are fine


def test_no_integer_boolean_string_variables(unzipped):
    with Plant(unzipped) as p:
        p.init()
        s = p.slave
        for fn, args in ((s.getInteger, ([1],)), (s.getBoolean, ([1],)), (s.getString, ([1],)),
                         (s.setInteger, ([1], [1])), (s.setBoolean, ([1], [True])), (s.setString, ([1], ["x"]))):
            p.expect_error(fn, *args, match="unknown value reference 1")
        for fn in (s.getInteger, s.getBoolean, s.getString):
            assert fn([]) == []
        assert s.fmi2SetInteger(s.component, None, 0, None) == fmi2OK


def test_guid_mismatch_is_refused(unzipped):
    p = Plant(unzipped, guid="{00000000-1111-2222-3333-444444444444}")
    with pytest.raises(Exception, match="instantiate"):
        p.slave.instantiate(callbacks=p.cb)
    assert any("GUID" in m[2] and m[1] == fmi2Error for m in p.messages)
    p.slave.freeLibrary()


def test_illegal_call_sequences(unzipped):
    with Plant(unzipped) as p:
        s = p.slave
        p.expect_error(s.doStep, 0.0, 0.01, match="fmi2DoStep: illegal call in state 'instantiated'")
        p.expect_error(s.exitInitializationMode, match="fmi2ExitInitializationMode: illegal call")
        p.expect_error(s.terminate, match="fmi2Terminate: illegal call")
        s.setupExperiment(startTime=0.0)
        s.enterInitializationMode()
        p.expect_error(s.doStep, 0.0, 0.01, match="fmi2DoStep: illegal call in state 'initialization mode'")
        p.expect_error(s.setupExperiment, None, 0.0, match="fmi2SetupExperiment: illegal call")
        s.exitInitializationMode()
        p.expect_error(s.enterInitializationMode, match="fmi2EnterInitializationMode: illegal call")
        s.doStep(0.0, 0.01)
        p.expect_error(s.cancelStep, match="fmi2CancelStep")
        s.terminate()
        p.expect_error(s.doStep, 0.01, 0.01, match="fmi2DoStep: illegal call in state 'terminated'")
        p.expect_error(s.setReal, [B2 + 30], [1.0], match="fmi2SetReal: illegal call in state 'terminated'")
        p.expect_error(s.terminate, match="fmi2Terminate: illegal call")
        p.expect_error(s.exitInitializationMode, match="illegal call in state 'terminated'")
        s.reset()  # allowed: back to a usable instance
        p.init()
        s.doStep(0.0, 0.01)


def test_unsupported_capabilities(unzipped):
    with Plant(unzipped) as p:
        s = p.slave
        p.init()
        p.expect_error(s.getDirectionalDerivative, [1000], [B2 + 30], [1.0], match="not supported")
        p.expect_error(s.setRealInputDerivatives, [B2 + 30], [1], [1.0], match="not supported")
        p.expect_error(s.getRealOutputDerivatives, [1000], [1], match="not supported")
        with pytest.raises(FMICallException) as exc:
            s.fmi2GetStatus(s.component, 0, ctypes.byref(ctypes.c_int()))
        assert exc.value.status == 2  # fmi2Discard: only defined after fmi2Pending
        s.doStep(0.0, 0.25)
        t = ctypes.c_double()
        assert s.fmi2GetRealStatus(s.component, 2, ctypes.byref(t)) == fmi2OK and t.value == 0.25
        flag = ctypes.c_int(7)
        assert s.fmi2GetBooleanStatus(s.component, 3, ctypes.byref(flag)) == fmi2OK and flag.value == 0


def test_null_instance_is_guarded(unzipped):
    with Plant(unzipped) as p:
        lib = p.slave.dll
        vr = (ctypes.c_uint * 1)(1000)
        val = (ctypes.c_double * 1)()
        for name, args in (("fmi2DoStep", (None, ctypes.c_double(0.0), ctypes.c_double(0.1), 1)),
                           ("fmi2GetReal", (None, vr, ctypes.c_size_t(1), val)),
                           ("fmi2SetReal", (None, vr, ctypes.c_size_t(1), val)),
                           ("fmi2ExitInitializationMode", (None,)),
                           ("fmi2Terminate", (None,)), ("fmi2Reset", (None,)),
                           ("fmi2GetFMUstate", (None, None)), ("fmi2CancelStep", (None,))):
            f = ctypes.CFUNCTYPE(ctypes.c_int, *[ctypes.c_void_p] * 0)(ctypes.cast(getattr(lib, name),
                                                                                     ctypes.c_void_p).value)
            f.argtypes = None
            assert f(*args) == fmi2Error, name
        lib.fmi2FreeInstance.argtypes = [ctypes.c_void_p]
        lib.fmi2FreeInstance(None)


def test_fleet_fmu_raises_with_the_logged_messages():
    from controller.errors import Se3SyncError
    from plant_fmu.fast import FleetFMU, FMUError

    seen = []
    f = FleetFMU(N, logger=lambda cat, status, text: seen.append(text))
    with pytest.raises(Se3SyncError, match="R0 of body 2 is not a rotation"):
        f.set_parameters(R0=[np.eye(3), 2 * np.eye(3)])
    with pytest.raises(FMUError, match=r"body\[1\]\.m = nan is not finite"):
        f.set_parameters(mass=[math.nan, 1.0])
    f.set_parameters(mass=[-1.0, 1.0])
    with pytest.raises(FMUError, match=r"fmi2ExitInitializationMode.*body\[1\]\.m = -1 must be > 0") as exc:
        f.initialize()
    assert exc.value.status == fmi2Error and any("body[1].m" in m for m in exc.value.messages)
    assert any("body[1].m" in text for text in seen)
    assert ("logStatusError", fmi2Error, "body[1].m = -1 must be > 0") in f.messages
    with pytest.raises(FMUError, match="illegal call"):
        f.do_step(0.0, 0.1)
    f.close()
    f.close()  # idempotent
    for call in (f.reset, lambda: f.do_step(0.0, 0.1), f.get_state, lambda: f.set_input(np.zeros((N, 6)))):
        with pytest.raises(Se3SyncError, match="closed"):
            call()
