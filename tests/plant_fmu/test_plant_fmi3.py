"""The plant as an FMI 3.0 Co-Simulation FMU (c/fmi3.c over the same c/model.c as FMI 2.0).

Driven through fmpy's own FMU3Slave with a logger callback that records the messages; the
FMI 2.0 build of the same model is the reference (results must agree bit for bit).
"""
from __future__ import annotations

import ctypes
import math
import os
import shutil
import zipfile

import numpy as np
import pytest
from fmpy import extract, read_model_description, simulate_fmu
from fmpy.fmi1 import FMICallException
from fmpy.fmi2 import FMU2Slave
from fmpy.fmi3 import FMU3Slave, fmi3Error, fmi3Float64, fmi3ValueReference
from fmpy.validation import validate_fmu

from plant_fmu import build, layout

N = 2
B1, B2 = layout.body_base(0), layout.body_base(1)
VR_STATE = [int(v) for v in layout.vr_state(N)]
VR_U = [int(v) for v in layout.vr_input(N)]


@pytest.fixture(scope="module")
def fmu3():
    path = build.fmu_path(N, fmi_version=3)
    return read_model_description(str(path)), extract(str(path))


@pytest.fixture(scope="module")
def fmu2():
    path = build.fmu_path(N)
    return read_model_description(str(path)), extract(str(path))


class Plant3:
    """FMU3Slave + recorded log messages [(category, status, text)]."""

    def __init__(self, unzipped, token=None, name="p3"):
        md, d = unzipped
        self.messages = []
        self.slave = FMU3Slave(guid=token or md.guid, unzipDirectory=d, modelIdentifier=md.coSimulation.modelIdentifier,
                               instanceName=name)

    def log(self, env, status, category, message):
        self.messages.append((category.decode(), status, message.decode()))

    def instantiate(self, **kw):
        self.slave.instantiate(logMessage=self.log, **kw)
        return self

    def __enter__(self):
        return self.instantiate()

    def __exit__(self, *exc):
        self.slave.freeInstance()

    def expect_error(self, fn, *args, match: str):
        del self.messages[:]
        with pytest.raises(FMICallException) as exc:
            fn(*args)
        assert exc.value.status == fmi3Error
        text = " | ".join(m[2] for m in self.messages)
        assert match in text, (match, self.messages)
        assert any(m[1] == fmi3Error and m[0] == "logStatusError" for m in self.messages)
        return text


# an asymmetric, tumbling body 1 (principal moments 1, 2, 2.5 in a rotated frame, spinning near the
# unstable middle axis) and a body 2 in gravity; both with nonzero, time-varying wrenches
_Q = np.array([[0.36, 0.48, -0.8], [-0.8, 0.6, 0.0], [0.48, 0.64, 0.6]])
J1 = _Q @ np.diag([1.0, 2.0, 2.5]) @ _Q.T
_Q0 = np.array([0.9, 0.1, -0.3, 0.2]) / math.sqrt(0.95) * (1 + 1e-7)  # slightly off unit: normalised
PARAMS = {B1 + 40: 1.7, B2 + 40: 0.4, layout.VR_H_INTERNAL: 2.5e-3, 3: -9.81}
PARAMS.update({B1 + 41 + k: float(x) for k, x in enumerate(J1.ravel())})
PARAMS.update({B1 + 53 + k: float(x) for k, x in enumerate(_Q0)})
PARAMS.update({B1 + 57 + k: x for k, x in enumerate((0.05, 3.0, 0.1, 0.3, -0.2, 0.5))})
PARAMS.update({B2 + 57 + k: x for k, x in enumerate((1.0, -0.5, 0.25, 0.0, 1.0, 2.0))})
PARAMS.update({B2 + 50: 1.0, B2 + 52: -2.0})


def wrench(i: int) -> list[float]:
    t = 0.01 * i
    return [0.2 * math.sin(t), -0.1, 0.05 * math.cos(3 * t), 1.0, 0.3 * t, -0.2,
            0.0, 0.01, -0.02, 0.5 * math.cos(t), 0.0, 4.0]


def run3(plant: Plant3, steps: int, h: float = 0.01) -> np.ndarray:
    s = plant.slave
    s.setFloat64(list(PARAMS), list(PARAMS.values()))
    s.enterInitializationMode(startTime=0.0)
    s.exitInitializationMode()  # fmi3Warning (q0 normalised) is not an exception
    out = [s.getFloat64(VR_STATE)]
    t = 0.0
    for i in range(steps):
        s.setFloat64(VR_U, wrench(i))
        event, terminate, early, last = s.doStep(t, h)
        assert (event, terminate, early) == (False, False, False) and last == t + h
        t += h
        out.append(s.getFloat64(VR_STATE))
    assert s.getFloat64([0]) == [t]  # time, the independent variable
    return np.array(out)


def run2(unzipped, steps: int, h: float = 0.01) -> np.ndarray:
    md, d = unzipped
    s = FMU2Slave(guid=md.guid, unzipDirectory=d, modelIdentifier=md.coSimulation.modelIdentifier, instanceName="p2")
    s.instantiate()
    try:
        s.setReal(list(PARAMS), list(PARAMS.values()))
        s.setupExperiment(startTime=0.0)
        s.enterInitializationMode()
        s.exitInitializationMode()
        out = [s.getReal(VR_STATE)]
        t = 0.0
        for i in range(steps):
            s.setReal(VR_U, wrench(i))
            s.doStep(t, h)
            t += h
            out.append(s.getReal(VR_STATE))
        return np.array(out)
    finally:
        s.freeInstance()


# ------------------------------------------------------------------ model description, build, import


@pytest.mark.parametrize("n", [1, 6])
def test_fmpy_validation_reports_no_problems(n):
    path = build.fmu_path(n, fmi_version=3)
    assert validate_fmu(str(path)) == []
    md = read_model_description(str(path))
    assert md.fmiVersion == "3.0" and md.guid == build.guid(n, 3) != build.guid(n)
    cs = md.coSimulation
    assert cs.modelIdentifier == build.MODEL_IDENTIFIER
    assert cs.canGetAndSetFMUstate and cs.canSerializeFMUstate and cs.canHandleVariableCommunicationStepSize
    # same variables, value references, causalities, variabilities, start values and units as FMI 2.0
    md2 = read_model_description(str(build.fmu_path(n)))
    key = lambda v: (v.name, v.valueReference, v.causality, v.variability, v.start, v.unit)  # noqa: E731
    assert [key(v) for v in md.modelVariables[1:]] == [key(v) for v in md2.modelVariables]
    assert all(v.type == "Float64" for v in md.modelVariables)
    time = md.modelVariables[0]
    assert (time.name, time.valueReference, time.causality) == ("time", 0, "independent")
    assert {o.variable.valueReference for o in md.outputs} == {
        v.valueReference for v in md2.modelVariables if v.causality == "output"}
    with zipfile.ZipFile(path) as z:
        names = set(z.namelist())
    assert f"binaries/{build.platform_tuple()}/{build.MODEL_IDENTIFIER}.so" in names
    assert {"sources/model.c", "sources/fmi3.c", "sources/model.h", "sources/config.h",
            "sources/fmi3Functions.h", "sources/buildDescription.xml"} <= names
    assert not any("fmi2" in f for f in names)
    assert md.buildConfigurations[0].sourceFileSets[0].sourceFiles == ["model.c", "fmi3.c"]


def test_fmi_version_is_part_of_the_cache_key():
    assert build.fmu_path(N, fmi_version=3) != build.fmu_path(N)
    assert build.fmu_path(N, 3) == build.fmu_path(N, fmi_version=3)
    for bad in (1, 4, "3", True):
        with pytest.raises(build.BuildError, match="FMI version"):
            build.fmu_path(N, fmi_version=bad)


def test_fmpy_simulate_fmu_runs_it_and_matches_fmi2():
    kw = dict(stop_time=0.5, output_interval=0.05,
              start_values={"body[2].xi0[4]": 2.0, "body[2].xi0[2]": 1.5, "body[3].xi0[3]": 0.5, "g[3]": -9.81,
                            "body[4].J[1,1]": 0.5})
    res3 = simulate_fmu(str(build.fmu_path(6, fmi_version=3)), **kw)
    res2 = simulate_fmu(str(build.fmu_path(6)), **kw)
    assert res3["time"][-1] == pytest.approx(0.5)
    assert {f"body[{i}].{v}" for i in range(1, 7) for v in ("p[1]", "R[3,3]", "xi[6]", "q[4]")} <= set(res3.dtype.names)
    assert res3["body[3].R[2,1]"][-1] == pytest.approx(np.sin(0.25), abs=1e-12)
    for name in res2.dtype.names:
        assert np.array_equal(res3[name], res2[name]), name
    assert res3["body[2].p[3]"][-1] != 0.0


def test_trajectory_is_bit_identical_to_fmi2(fmu3, fmu2):
    with Plant3(fmu3) as p:
        x3 = run3(p, 150)
        assert any(m[1] == 1 and "body[1].q0" in m[2] for m in p.messages)  # the normalisation warning
    x2 = run2(fmu2, 150)
    assert x3.shape == (151, 18 * N)
    assert x3.tobytes() == x2.tobytes()
    # it really tumbles (omega changes a lot) and body 2 moves
    assert np.ptp(x3[:, 12:15], axis=0).max() > 1.0
    assert np.abs(x3[-1, 18:21] - x3[0, 18:21]).max() > 1.0


def test_fmu_state_replays_a_step_bitwise(fmu3):
    with Plant3(fmu3) as p:
        s = p.slave
        run3(p, 5)
        t = 0.05
        state = s.getFMUState()
        s.setFloat64(VR_U, wrench(7))
        s.doStep(t, 0.03)
        after = s.getFloat64(VR_STATE + [0])
        s.setFloat64(VR_U, wrench(9))
        s.doStep(t + 0.03, 0.01)
        s.setFMUState(state)
        assert s.getFloat64([0]) == [t]
        s.setFloat64(VR_U, wrench(7))
        s.doStep(t, 0.03)
        assert np.array(s.getFloat64(VR_STATE + [0])).tobytes() == np.array(after).tobytes()
        # serialized form: round trip into a new FMU state
        blob = s.serializeFMUState(state)
        state2 = s.deserializeFMUState(blob)
        s.setFMUState(state2)
        s.setFloat64(VR_U, wrench(7))
        s.doStep(t, 0.03)
        assert np.array(s.getFloat64(VR_STATE + [0])).tobytes() == np.array(after).tobytes()
        p.expect_error(s.deserializeFMUState, blob[:-8], match="does not match the expected")
        s.freeFMUState(state)
        s.freeFMUState(state2)


# ------------------------------------------------------------------ bad input and illegal calls


def test_bad_mass_is_refused_at_exit_initialization_and_can_be_fixed(fmu3):
    with Plant3(fmu3) as p:
        s = p.slave
        s.setFloat64([B2 + 40], [0.0])
        s.enterInitializationMode()
        text = p.expect_error(s.exitInitializationMode, match="body[2].m")
        assert "still in initialization mode" in text
        s.setFloat64([B2 + 40], [-2.0])
        p.expect_error(s.exitInitializationMode, match="body[2].m")
        s.setFloat64([B2 + 40], [2.0])
        s.exitInitializationMode()
        s.doStep(0.0, 0.01)


def test_non_finite_input_is_refused_and_changes_nothing(fmu3):
    with Plant3(fmu3) as p:
        s = p.slave
        s.enterInitializationMode()
        s.exitInitializationMode()
        s.setFloat64(VR_U, [1.0] * 6 * N)
        for bad in (math.nan, math.inf, -math.inf):
            p.expect_error(s.setFloat64, [B2 + 30, B2 + 33], [5.0, bad], match="body[2].u[4]")
        assert s.getFloat64([B2 + 30, B2 + 33]) == [1.0, 1.0]  # nothing of the refused call stored
        p.expect_error(s.setFloat64, [B1 + 40], [2.0], match="body[1].m (value reference 1040) is a fixed parameter")
        p.expect_error(s.setFloat64, [B1 + 0], [2.0], match="body[1].p[1] (value reference 1000) is an output")
        p.expect_error(s.setFloat64, [0], [1.0], match="time (value reference 0) is the independent variable")
        p.expect_error(s.getFloat64, [B1 + 25], match="unknown value reference 1025")
        s.doStep(0.0, 0.01)


def test_nvalues_must_equal_nvaluereferences(fmu3):
    with Plant3(fmu3) as p:
        s = p.slave
        vr = (fmi3ValueReference * 2)(B1, B1 + 1)
        buf = (fmi3Float64 * 3)()
        p.expect_error(s.fmi3GetFloat64, s.component, vr, 2, buf, 3, match="nValues = 3 must equal nValueReferences = 2")
        p.expect_error(s.fmi3SetFloat64, s.component, vr, 2, buf, 1, match="nValues = 1")


def test_wrong_token_gives_null_and_a_message(fmu3):
    p = Plant3(fmu3, token="{00000000-dead-beef-0000-000000000000}")
    with pytest.raises(Exception, match="Failed to instantiate"):
        p.instantiate()
    assert any(m[1] == fmi3Error and "instantiationToken mismatch" in m[2] and "dead-beef" in m[2]
               for m in p.messages), p.messages
    p.slave.freeLibrary()
    p = Plant3(fmu3)
    with pytest.raises(Exception, match="Failed to instantiate"):
        p.instantiate(eventModeUsed=True)
    assert any("eventModeUsed" in m[2] for m in p.messages)
    p.slave.freeLibrary()
    with Plant3(fmu3) as ok:  # the process survives and a good instance still works
        ok.slave.enterInitializationMode()
        ok.slave.exitInitializationMode()


def test_illegal_call_sequences(fmu3):
    with Plant3(fmu3) as p:
        s = p.slave
        p.expect_error(s.doStep, 0.0, 0.01, match="fmi3DoStep: illegal call in state 'instantiated'")
        p.expect_error(s.exitInitializationMode, match="illegal call in state 'instantiated'")
        p.expect_error(s.terminate, match="fmi3Terminate: illegal call")
        s.enterInitializationMode()
        p.expect_error(s.doStep, 0.0, 0.01, match="illegal call in state 'initialization mode'")
        p.expect_error(s.enterInitializationMode, match="illegal call in state 'initialization mode'")
        s.exitInitializationMode()
        p.expect_error(s.doStep, 0.0, 0.0, match="communicationStepSize")
        p.expect_error(s.doStep, 0.0, math.nan, match="communicationStepSize")
        s.doStep(0.0, 0.01)
        s.terminate()
        p.expect_error(s.doStep, 0.01, 0.01, match="illegal call in state 'terminated'")
        p.expect_error(s.setFloat64, [B1 + 30], [1.0], match="illegal call in state 'terminated'")
        assert s.getFloat64([0]) == [0.01]
        s.reset()
        assert s.getFloat64([0, B1 + 40]) == [0.0, 1.0]
        s.enterInitializationMode()
        s.exitInitializationMode()


def test_only_float64_and_unsupported_parts_of_the_api(fmu3):
    with Plant3(fmu3) as p:
        s = p.slave
        assert s.getVersion() == "3.0"
        assert s.getInt32([]) == [] and s.getBoolean([]) == []
        p.expect_error(s.getInt32, [B1], match="fmi3GetInt32: unknown value reference 1000")
        p.expect_error(s.setBoolean, [B1 + 30], [True], match="fmi3SetBoolean: unknown value reference 1030")
        p.expect_error(s.getFloat32, [B1], match="only Float64")
        p.expect_error(s.enterEventMode, match="fmi3EnterEventMode: not supported")
        p.expect_error(s.enterStepMode, match="fmi3EnterStepMode: not supported")
        p.expect_error(s.enterConfigurationMode, match="not supported")
        p.expect_error(s.getDirectionalDerivative, [B1], [B1 + 30], [1.0], match="not supported")
        p.expect_error(s.getAdjointDerivative, [B1], [B1 + 30], [1.0], match="not supported")
        p.expect_error(s.getOutputDerivatives, [B1], [1], match="not supported")
        p.expect_error(s.fmi3SetTime, s.component, 1.0, match="Co-Simulation only")
        p.expect_error(s.fmi3GetNumberOfContinuousStates, s.component, ctypes.byref(ctypes.c_size_t()),
                       match="Co-Simulation only")
        p.expect_error(s.fmi3ActivateModelPartition, s.component, 0, 0.0, match="not supported")
        s.enterInitializationMode()
        s.exitInitializationMode()
        s.doStep(0.0, 0.01)  # still works after all the refused calls


# ------------------------------------------------------------------ rebuilding, command line


@pytest.mark.skipif(shutil.which("cmake") is None, reason="fmpy builds from buildDescription.xml with cmake")
def test_fmpy_rebuilds_the_binary_from_build_description(tmp_path):
    from fmpy.build import build_platform_binary

    path = build.build_fmu(1, tmp_path / "one.fmu", fmi_version=3)
    d = tmp_path / "x"
    with zipfile.ZipFile(path) as z:
        z.extractall(d)
    lib = d / "binaries" / build.platform_tuple() / f"{build.MODEL_IDENTIFIER}.so"
    lib.unlink()
    (tmp_path / "b").mkdir()
    build_platform_binary(d.resolve(), build_dir=tmp_path / "b")
    assert lib.exists()
    md = read_model_description(str(path))
    with Plant3((md, str(d))) as p:
        p.slave.enterInitializationMode()
        p.slave.exitInitializationMode()
        p.slave.doStep(0.0, 0.1)


def test_cli_build_fmi3(tmp_path, capsys):
    from cosim.cli import main

    out = tmp_path / "x.fmu"
    assert main(["fmu", "build", "--bodies", "2", "-o", str(out), "--fmi", "3"]) == 0
    assert "FMI 3.0" in capsys.readouterr().out
    md = read_model_description(str(out))
    assert md.fmiVersion == "3.0"
    assert sorted(os.listdir(tmp_path)) == ["x.fmu"]
    with pytest.raises(SystemExit):
        main(["fmu", "build", "--help"])
    assert "--fmi" in capsys.readouterr().out
