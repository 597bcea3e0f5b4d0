"""Building, validating and importing the plant FMU; its layout; the `se3sync fmu build` command."""
from __future__ import annotations

import os
import subprocess
import sys
import zipfile

import numpy as np
import pytest
from fmpy import extract, read_model_description, simulate_fmu
from fmpy.fmi2 import FMU2Slave
from fmpy.validation import validate_fmu

from plant_fmu import build, layout


@pytest.mark.parametrize("n", [1, 6])
def test_fmpy_validation_reports_no_problems(n):
    path = build.fmu_path(n)
    assert validate_fmu(str(path)) == []
    md = read_model_description(str(path))
    assert md.fmiVersion == "2.0" and md.coSimulation.modelIdentifier == build.MODEL_IDENTIFIER
    cs = md.coSimulation
    assert cs.canGetAndSetFMUstate and cs.canSerializeFMUstate and cs.canHandleVariableCommunicationStepSize
    assert cs.canNotUseMemoryManagementFunctions
    assert sum(v.causality == "input" for v in md.modelVariables) == 6 * n
    assert {u.name for u in md.unitDefinitions} >= {"kg", "kg.m2", "m", "m/s", "rad/s", "N", "N.m", "s"}
    with zipfile.ZipFile(path) as z:
        names = set(z.namelist())
    assert f"binaries/{build.platform_tag()}/{build.MODEL_IDENTIFIER}.so" in names
    assert {"sources/model.c", "sources/fmi2.c", "sources/model.h", "sources/config.h",
            "sources/fmi2Functions.h"} <= names


def test_layout_matches_model_description():
    n = 3
    md = read_model_description(build.fmu_path(n).as_posix())
    by_vr = {v.valueReference: v for v in md.modelVariables}
    assert len(by_vr) == len(md.modelVariables)  # unique value references
    for vr in by_vr:
        assert layout.variable_name(vr, n) == by_vr[vr].name
    state = [by_vr[int(vr)].name for vr in layout.vr_state(n)]
    assert state[:18] == ["body[1].p[1]", "body[1].p[2]", "body[1].p[3]"] + [
        f"body[1].R[{r},{c}]" for r in (1, 2, 3) for c in (1, 2, 3)] + [f"body[1].xi[{k}]" for k in range(1, 7)]
    assert state[18] == "body[2].p[1]" and layout.vr_state(n)[18] == 1100
    assert [by_vr[int(v)].name for v in layout.vr_quat(n)[:4]] == [f"body[1].q[{k}]" for k in range(1, 5)]
    assert all(by_vr[int(v)].causality == "input" for v in layout.vr_input(n))
    assert by_vr[int(layout.vr_inertia(n)[5])].name == "body[1].J[2,3]"
    assert [by_vr[int(v)].name for v in layout.VR_GRAVITY] == ["g[1]", "g[2]", "g[3]"]
    assert by_vr[layout.VR_H_INTERNAL].name == "h_internal" and by_vr[layout.VR_H_INTERNAL].start == "0.0001"
    for name, size in (("m", 1), ("J", 9), ("p0", 3), ("q0", 4), ("xi0", 6)):
        vrs = layout.vr_param(n, name)
        assert vrs.shape == (n * size,) and all(by_vr[int(v)].causality == "parameter" for v in vrs)
    with pytest.raises(ValueError):
        layout.variable_name(1025)
    with pytest.raises(ValueError):
        layout.variable_name(layout.body_base(n), n)


def test_fmpy_simulate_fmu_runs_it_alone():
    path = build.fmu_path(6)
    res = simulate_fmu(str(path), stop_time=1.0, output_interval=0.1,
                       start_values={"body[2].xi0[4]": 2.0, "body[2].xi0[6]": -0.5, "body[2].p0[1]": 1.0,
                                     "body[3].xi0[3]": 0.5})
    names = res.dtype.names
    assert names[0] == "time"
    assert {f"body[{i}].{v}" for i in range(1, 7) for v in ("p[1]", "R[3,3]", "xi[6]", "q[4]")} <= set(names)
    assert res["time"][-1] == pytest.approx(1.0)
    # body 2 moves with constant velocity (R = I, no rotation, no force)
    assert res["body[2].p[1]"][-1] == pytest.approx(3.0, abs=1e-12)
    assert res["body[2].p[3]"][-1] == pytest.approx(-0.5, abs=1e-12)
    # body 3 spins about z at 0.5 rad/s
    assert res["body[3].R[2,1]"][-1] == pytest.approx(np.sin(0.5), abs=1e-12)
    assert res["body[1].p[1]"][-1] == 0.0


def test_sources_compile_standalone(tmp_path):
    """The sources/ folder alone (as `fmpy compile` would use it) builds a working binary."""
    path = build.build_fmu(2, tmp_path / "two.fmu")
    d = tmp_path / "x"
    with zipfile.ZipFile(path) as z:
        z.extractall(d)
    md = read_model_description(str(path))
    lib = d / "binaries" / build.platform_tag() / f"{build.MODEL_IDENTIFIER}.so"
    lib.unlink()
    cc = build.find_compiler()
    src = d / "sources"
    sources = md.buildConfigurations[0].sourceFileSets[0].sourceFiles  # from <SourceFiles>
    assert sources == ["model.c", "fmi2.c"]
    subprocess.run(cc + ["-shared", "-fPIC", "-O1", "-o", str(lib)] + [str(src / f) for f in sources] + ["-lm"],
                   check=True, capture_output=True)
    s = FMU2Slave(guid=md.guid, unzipDirectory=str(d), modelIdentifier=build.MODEL_IDENTIFIER, instanceName="x")
    s.instantiate()
    s.setupExperiment(startTime=0.0)
    s.enterInitializationMode()
    s.exitInitializationMode()
    s.doStep(0.0, 0.1)
    assert s.getReal([layout.body_base(1)]) == [0.0]
    s.terminate()
    s.freeInstance()


def test_cache_is_keyed_and_reused(tmp_path, monkeypatch):
    monkeypatch.setenv("SE3SYNC_CACHE", str(tmp_path / "cache"))
    build._memo.clear()
    p = build.fmu_path(2)
    assert p.parent == tmp_path / "cache" and p.exists()
    mtime = p.stat().st_mtime_ns
    build._memo.clear()
    assert build.fmu_path(2) == p and p.stat().st_mtime_ns == mtime  # not rebuilt
    assert build.fmu_path(3) != p
    assert sorted(f.name.endswith(".fmu") for f in p.parent.iterdir()) == [True, True]
    build._memo.clear()


def test_concurrent_builds_are_atomic(tmp_path):
    env = dict(os.environ, SE3SYNC_CACHE=str(tmp_path))
    code = "from plant_fmu.build import fmu_path; import zipfile; zipfile.ZipFile(fmu_path(4)).testzip()"
    procs = [subprocess.Popen([sys.executable, "-c", code], env=env, stderr=subprocess.PIPE, text=True)
             for _ in range(3)]
    for p in procs:
        _, err = p.communicate(timeout=300)
        assert p.returncode == 0, err
    files = list(tmp_path.iterdir())
    assert len(files) == 1 and validate_fmu(str(files[0])) == []


def test_missing_compiler_is_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.setenv("CC", "/nonexistent/cc")
    with pytest.raises(build.BuildError, match="C compiler"):
        build.build_fmu(1, tmp_path / "x.fmu")
    monkeypatch.delenv("CC")
    monkeypatch.setenv("PATH", str(tmp_path))
    with pytest.raises(build.BuildError, match="no C compiler was found.*install"):
        build.find_compiler()
    assert list(tmp_path.iterdir()) == []


def test_cli_build(tmp_path, capsys):
    from cosim.cli import main

    out = tmp_path / "x.fmu"
    assert main(["fmu", "build", "--bodies", "2", "-o", str(out)]) == 0
    assert validate_fmu(str(out)) == []
    md = read_model_description(str(out))
    assert sum(v.causality == "input" for v in md.modelVariables) == 12
    assert sorted(os.listdir(tmp_path)) == ["x.fmu"]
    d = extract(str(out))
    assert os.path.exists(os.path.join(d, "sources", "config.h"))


@pytest.mark.parametrize("n", ["0", "-3", "100001"])
def test_cli_bad_n(tmp_path, capsys, n):
    from cosim.cli import main

    out = tmp_path / "x.fmu"
    assert main(["fmu", "build", "--bodies", n, "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--bodies" in err[0]
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_cli_unwritable_output_and_failed_compile(tmp_path, capsys, monkeypatch):
    from cosim.cli import main

    assert main(["fmu", "build", "--bodies", "1", "-o", str(tmp_path / "nodir" / "x.fmu")]) == 2
    assert "--output" in capsys.readouterr().err
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        if not os.access(ro, os.W_OK):  # (root can write anyway)
            assert main(["fmu", "build", "--bodies", "1", "-o", str(ro / "x.fmu")]) == 2
            assert list(ro.iterdir()) == []
    finally:
        ro.chmod(0o700)
    monkeypatch.setenv("CC", "false")  # a "compiler" that always fails
    out = tmp_path / "y.fmu"
    assert main(["fmu", "build", "--bodies", "1", "-o", str(out)]) == 2
    assert "compiling the plant FMU failed" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ro"]


def test_cli_help_is_true(capsys):
    from cosim.cli import main

    with pytest.raises(SystemExit):
        main(["fmu", "build", "--help"])
    out = capsys.readouterr().out
    assert "--bodies" in out and "C compiler" in out
