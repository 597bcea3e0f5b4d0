"""The closed loop as an FMI system: the controller FMU (pythonfmu) passes `fmpy validate`; the
SSP archive validates against the SSP 1.0 schemas; running it in FMPy (`fmpy.ssp`) and in
libcosim (libcosimpy) reproduces the se3sync master's run of the same scenario with the
one-step actuation delay those fixed-step (Jacobi) masters add: the same jumps (step and edge)
and the 1 s samples within 1e-9 relative."""
import os
import zipfile
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pythonfmu")
pytest.importorskip("libcosimpy")

from cosim.cli import main  # noqa: E402
from cosim.fmi.masters import (DelayedActuation, run_fmpy, run_libcosim, samples,  # noqa: E402
                               ssp_parameters)
from cosim.fmi.ssp import CONTROLLER, PLANT, SSD_NAME, write_ssp  # noqa: E402
from cosim.plants import FmuPlant  # noqa: E402
from cosim.run import run_scenario  # noqa: E402
from cosim.scenario import load_scenario  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
HIL = ROOT / "scenarios" / "hil_6uav.toml"


@pytest.fixture(scope="module")
def scenario(tmp_path_factory):
    """hil_6uav (h = 4 ms) from a random start whose edges jump at t = 0 and later (the start
    test_agents uses for a mid-run jump), 3 s."""
    text = HIL.read_text().replace('generator = "paper"\naxis = [0.2997, 0.8380, 0.4560]',
                                   'generator = "random"\nseed = 6\nvelocity_ball = 0.5')
    d = tmp_path_factory.mktemp("fmi")
    path = d / "hil_random6.toml"
    path.write_text(text)
    return load_scenario(path, ["simulation.duration=3"])


@pytest.fixture(scope="module")
def system(scenario, tmp_path_factory):
    out = tmp_path_factory.mktemp("ssp") / "system.ssp"
    write_ssp(scenario, out)
    return out


@pytest.fixture(scope="module")
def reference(scenario):
    """The se3sync master with the wrench applied one step late (`DelayedActuation`)."""
    plant = DelayedActuation(FmuPlant.from_scenario(scenario))
    try:
        return run_scenario(scenario, plant=plant)
    finally:
        plant.close()


@pytest.fixture(scope="module")
def plain(scenario):
    """`se3sync run` of the scenario, as it is."""
    return run_scenario(scenario)


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


@pytest.mark.parametrize("master", ["fmpy", "libcosim"])
def test_system_in_a_master_equals_the_run_with_actuation_delay(system, scenario, reference,
                                                                plain, master):
    h, steps = scenario.step, scenario.n_steps()
    run = (run_fmpy if master == "fmpy" else run_libcosim)(system, steps, h)
    ref_jumps = [(round(j["t"] / h), j["edge"]) for j in reference["jumps"]]
    assert any(s > 0 for s, _ in ref_jumps) and any(s == 0 for s, _ in ref_jumps)
    assert run.jumps == ref_jumps
    # the delay moves no jump of this run: the same steps and edges as `se3sync run`
    assert run.jumps == [(round(j["t"] / h), j["edge"]) for j in plain["jumps"]]
    got = samples(scenario, run)
    assert [s["t"] for s in got] == [0.0, 1.0, 2.0]
    _close(got, reference["samples"][:3])


def test_delayed_actuation_is_the_wrench_of_the_step_before(scenario):
    """DelayedActuation, checked by hand: 40 steps of the plant FMU driven with u(t_{n−1})
    computed by the law on the state at t_{n−1} (u ≡ 0 first) give the reference's state."""
    from cosim.master import Master
    from cosim.controllers import make_controller

    n = 40
    plant = DelayedActuation(FmuPlant.from_scenario(scenario))
    m = Master(scenario, plant, "hybrid")
    m.run(n)
    S_ref = plant.read().copy()
    plant.close()
    p = FmuPlant.from_scenario(scenario)
    law = make_controller("hybrid", scenario)
    prev = np.zeros((scenario.graph.n, 6))
    for _ in range(n):
        u, _ = law.step_state(p.read().copy(), scenario.step)
        p.apply(prev)
        prev = u.copy()
        p.advance(scenario.step)
    S = p.read().copy()
    p.close()
    assert np.array_equal(S, S_ref)


def test_ssp_command_errors_are_one_line(tmp_path, capsys):
    assert main(["ssp", str(HIL), "-o", str(tmp_path / "x.zip")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--output" in err
    assert main(["ssp", str(HIL), "-o", str(tmp_path / "x.ssp"), "--set", "gains.k_X=0"]) == 2
    assert "gains.k_X" in capsys.readouterr().err
    assert os.listdir(tmp_path) == []
