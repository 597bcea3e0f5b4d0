"""The closed loop as an FMI system: the controller FMU (pythonfmu) passes `fmpy validate`; the
SSP archive validates against the SSP 1.0 schemas; running it in FMPy (`fmpy.ssp`) and in
libcosim (libcosimpy) equals `se3sync run` of the same scenario with
``simulation.actuation_delay = 1``, the one-step actuation delay those fixed-step (Jacobi)
masters add: the same jumps (step and edge) and the 1 s samples within 1e-9 relative, for the
hybrid law and for the gradient law."""
import json
import os
import zipfile
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pythonfmu")
pytest.importorskip("libcosimpy")

from cosim.cli import main  # noqa: E402
from cosim.fmi.masters import run_fmpy, run_libcosim, samples, ssp_parameters  # noqa: E402
from cosim.fmi.ssp import CONTROLLER, PLANT, SSD_NAME, write_ssp  # noqa: E402
from cosim.scenario import load_scenario  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
HIL = ROOT / "scenarios" / "hil_6uav.toml"


DURATION = "simulation.duration=3"


@pytest.fixture(scope="module")
def scenario_file(tmp_path_factory):
    """hil_6uav (h = 4 ms) from a random start whose edges jump at t = 0 and later (the start
    test_agents uses for a mid-run jump)."""
    text = HIL.read_text().replace('generator = "paper"\naxis = [0.2997, 0.8380, 0.4560]',
                                   'generator = "random"\nseed = 6\nvelocity_ball = 0.5')
    path = tmp_path_factory.mktemp("fmi") / "hil_random6.toml"
    path.write_text(text)
    return path


@pytest.fixture(scope="module")
def scenario(scenario_file):
    """The scenario, 3 s."""
    return load_scenario(scenario_file, [DURATION])


@pytest.fixture(scope="module")
def system(scenario, tmp_path_factory):
    out = tmp_path_factory.mktemp("ssp") / "system.ssp"
    write_ssp(scenario, out)
    return out


def _run(scenario_file, tmp_path_factory, *extra):
    """The summary of `se3sync run SCENARIO --set simulation.duration=3 EXTRA…`."""
    out = tmp_path_factory.mktemp("run") / "s.json"
    argv = ["run", str(scenario_file), "--set", DURATION, *extra, "--summary", str(out)]
    assert main(argv) == 0
    return json.loads(out.read_text())


@pytest.fixture(scope="module")
def reference(scenario_file, tmp_path_factory):
    """`se3sync run` with the wrench applied one step late: what a Jacobi master runs."""
    s = _run(scenario_file, tmp_path_factory, "--set", "simulation.actuation_delay=1")
    assert s["actuation_delay_steps"] == 1
    return s


@pytest.fixture(scope="module")
def plain(scenario_file, tmp_path_factory):
    """`se3sync run` of the scenario, as it is."""
    return _run(scenario_file, tmp_path_factory)


def _schema_dir():
    import fmpy

    return Path(fmpy.__file__).parent / "ssp" / "schema"


def test_ssd_and_ssv_files_validate_against_the_ssp_schema(system, scenario):
    from lxml import etree

    sd = _schema_dir()
    with zipfile.ZipFile(system) as z:
        names = set(z.namelist())
        assert names == {SSD_NAME, "resources/plant.fmu", "resources/controller.fmu",
                         "resources/plant.ssv", "resources/controller.ssv"}
        for name, xsd in ((SSD_NAME, "SystemStructureDescription.xsd"),
                          ("resources/plant.ssv", "SystemStructureParameterValues.xsd"),
                          ("resources/controller.ssv", "SystemStructureParameterValues.xsd")):
            schema = etree.XMLSchema(etree.parse(str(sd / xsd)))
            doc = etree.fromstring(z.read(name))
            assert schema.validate(doc), (name, str(schema.error_log))
        # a document the schema must refuse: the check itself can fail
        bad = z.read(SSD_NAME).replace(b'kind="input"', b'kind="sideways"', 1)
        schema = etree.XMLSchema(etree.parse(str(sd / "SystemStructureDescription.xsd")))
        assert not schema.validate(etree.fromstring(bad))


def test_every_connection_joins_an_output_to_an_input_of_the_fmus(system, scenario, tmp_path):
    """Each connector is a variable of its FMU with that causality, and every parameter bound
    is a parameter of its FMU."""
    from fmpy import read_model_description
    from xml.etree import ElementTree as ET
    from cosim.fmi.ssp import NS

    with zipfile.ZipFile(system) as z:
        z.extractall(tmp_path)
        root = ET.fromstring(z.read(SSD_NAME))
    mds = {c: {v.name: v for v in read_model_description(
        str(tmp_path / "resources" / f"{c}.fmu")).modelVariables} for c in (PLANT, CONTROLLER)}
    for comp in root.iter(f"{{{NS['ssd']}}}Component"):
        vars_ = mds[comp.get("name")]
        for c in comp.iter(f"{{{NS['ssd']}}}Connector"):
            assert vars_[c.get("name")].causality == c.get("kind"), c.get("name")
    conns = list(root.iter(f"{{{NS['ssd']}}}Connection"))
    assert len(conns) == 24 * scenario.graph.n
    for c in conns:
        assert mds[c.get("startElement")][c.get("startConnector")].causality == "output"
        assert mds[c.get("endElement")][c.get("endConnector")].causality == "input"
    ps = ssp_parameters(system).parameters
    assert len(ps) > 200
    for p in ps:
        comp, name = p.name.split(".", 1)
        assert mds[comp][name].causality == "parameter", p.name


def test_controller_fmu_passes_fmpy_validate(tmp_path, capsys):
    from fmpy.validation import validate_fmu

    out = tmp_path / "law.fmu"
    assert main(["fmu", "build", "--controller", str(HIL), "-o", str(out)]) == 0
    assert "wrote" in capsys.readouterr().out
    assert validate_fmu(str(out)) == []
    # alone in fmpy, with its default experiment: the scenario's edges all jump at t = 0
    from fmpy import simulate_fmu

    r = simulate_fmu(str(out), stop_time=0.008, output=["n_jumps", "theta[1]"])
    assert list(r["n_jumps"]) == [0, 5, 5] and r["theta[1]"][0] == 0.0


def test_a_bad_parameter_is_an_fmi_error(tmp_path):
    """k_X ≤ 0 is refused in exitInitializationMode, as fmi2Error (FMPy raises)."""
    from fmpy import simulate_fmu
    from fmpy.fmi1 import FMICallException

    out = tmp_path / "law.fmu"
    assert main(["fmu", "build", "--controller", str(HIL), "-o", str(out)]) == 0
    with pytest.raises(FMICallException):
        simulate_fmu(str(out), stop_time=0.008, start_values={"k_X": -1.0})


def _close(a, b, rel=1e-9):
    for x, y in zip(a, b):
        assert x["t"] == y["t"]
        for k in ("rot_err", "pos_err", "xi_max", "V"):
            assert abs(x[k] - y[k]) <= rel * max(abs(y[k]), 1e-300), (x["t"], k, x[k], y[k])
        np.testing.assert_allclose(x["theta"], y["theta"], rtol=rel, atol=1e-300)


def _jumps(summary, h):
    return [(round(j["t"] / h), j["edge"]) for j in summary["jumps"]]


@pytest.mark.parametrize("master", ["fmpy", "libcosim"])
def test_system_in_a_master_equals_run_with_one_step_of_actuation_delay(system, scenario,
                                                                        reference, plain,
                                                                        master):
    h, steps = scenario.step, scenario.n_steps()
    run = (run_fmpy if master == "fmpy" else run_libcosim)(system, steps, h)
    ref_jumps = _jumps(reference, h)
    assert any(s > 0 for s, _ in ref_jumps) and any(s == 0 for s, _ in ref_jumps)
    assert run.jumps == ref_jumps
    # the delay moves no jump of this run: the same steps and edges as plain `se3sync run`
    assert run.jumps == _jumps(plain, h)
    got = samples(scenario, run)
    assert [s["t"] for s in got] == [0.0, 1.0, 2.0]
    _close(got, reference["samples"][:3])
    # ... but not plain `run`'s samples: the delay is what differs (docs/fmi-system.md)
    d = abs(got[1]["pos_err"] - plain["samples"][1]["pos_err"]) / plain["samples"][1]["pos_err"]
    assert d > 1e-4, d


@pytest.fixture(scope="module")
def gradient_system(scenario, tmp_path_factory):
    out = tmp_path_factory.mktemp("ssp_gradient") / "system.ssp"
    write_ssp(scenario, out, law="gradient")
    return out


@pytest.mark.parametrize("master", ["fmpy", "libcosim"])
def test_gradient_law_system_equals_run_with_one_step_of_actuation_delay(
        gradient_system, scenario, scenario_file, tmp_path_factory, master):
    """The gradient baseline's FMU (`--law gradient`: θ ≡ 0, no jump) in the SSP against
    `se3sync run --controller gradient` with the same delay."""
    h, steps = scenario.step, scenario.n_steps()
    ref = _run(scenario_file, tmp_path_factory, "--controller", "gradient", "--set",
               "simulation.actuation_delay=1")
    run = (run_fmpy if master == "fmpy" else run_libcosim)(gradient_system, steps, h)
    assert run.jumps == _jumps(ref, h) == []
    assert not run.theta.any()
    got = samples(scenario, run)
    assert [s["t"] for s in got] == [0.0, 1.0, 2.0]
    _close(got, ref["samples"][:3])


def test_ssp_command_errors_are_one_line(tmp_path, capsys):
    assert main(["ssp", str(HIL), "-o", str(tmp_path / "x.zip")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--output" in err
    assert main(["ssp", str(HIL), "-o", str(tmp_path / "x.ssp"), "--set", "gains.k_X=0"]) == 2
    assert "gains.k_X" in capsys.readouterr().err
    assert os.listdir(tmp_path) == []
