"""The closed loop as an SSP 1.0 system (`se3sync ssp SCENARIO -o system.ssp`).

The archive holds:

- ``SystemStructure.ssd``: the system (two components, their connectors, the connections and a
  default experiment with the communication step as OSP's ``FixedStepAlgorithm`` annotation,
  which libcosim reads);
- ``resources/plant.fmu``: the plant FMU for the scenario's N bodies (`plant_fmu.build`);
- ``resources/controller.fmu``: the law (`cosim.fmi.law_fmu`, pythonfmu);
- ``resources/plant.ssv`` and ``resources/controller.ssv``: every parameter of each component
  (masses, inertias, initial state, gravity, internal step; gains, weighting matrix, synergy
  design, θ(0)), bound to its component by a ParameterBinding. Numbers are written as their
  shortest round-trip text, so every master reads the scenario's floats exactly.

Connections: plant ``body[i].p[k]``, ``body[i].R[r,c]``, ``body[i].xi[k]`` → controller inputs
of the same names; controller ``body[i].u[k]`` → plant inputs. The controller's θ, μ_U and jump
outputs are declared as connectors too, so a master records them.

Written by hand (ElementTree): the SSD is small, and the test validates it and the SSV files
against the SSP 1.0 XML schemas that FMPy ships (`fmpy/ssp/schema`, BSD 2-clause, Modelica
Association Project "SSP"); se3sync ships no schema.
"""
from __future__ import annotations

import tempfile
import zipfile
from pathlib import Path
from xml.etree import ElementTree as ET

import numpy as np

from controller import __version__
from controller import layout
from controller.se3 import rot_to_quat
from plant_fmu import build as plant_build

from ..files import atomic_path
from .law_fmu import build_law_fmu, law_spec, plant_start_state

__all__ = ["NS", "SSD_NAME", "write_ssp", "plant_parameters", "controller_parameters",
           "state_connectors", "controller_outputs"]

NS = {"ssd": "http://ssp-standard.org/SSP1/SystemStructureDescription",
      "ssc": "http://ssp-standard.org/SSP1/SystemStructureCommon",
      "ssv": "http://ssp-standard.org/SSP1/SystemStructureParameterValues",
      "osp": "http://opensimulationplatform.com/SSP/OSPAnnotations"}
SSD_NAME = "SystemStructure.ssd"
PLANT, CONTROLLER = "plant", "controller"

for _p, _u in NS.items():
    ET.register_namespace(_p, _u)


def _q(tag: str) -> str:
    p, _, name = tag.partition(":")
    return f"{{{NS[p]}}}{name}"


def _num(x) -> str:
    """A float as its shortest round-trip text (xs:double accepts it; INF/NaN never occur)."""
    return repr(float(x))


def state_connectors(n: int) -> list:
    """The names of the state the plant outputs and the controller reads, body after body."""
    out = []
    for i in range(1, n + 1):
        out += [f"body[{i}].p[{k}]" for k in range(1, 4)]
        out += [f"body[{i}].R[{r},{c}]" for r in range(1, 4) for c in range(1, 4)]
        out += [f"body[{i}].xi[{k}]" for k in range(1, 7)]
    return out


def wrench_connectors(n: int) -> list:
    return [f"body[{i}].u[{k}]" for i in range(1, n + 1) for k in range(1, 7)]


def controller_outputs(m: int) -> list:
    """(name, type) of the controller's outputs beside the wrench."""
    return ([(f"theta[{k}]", "Real") for k in range(1, m + 1)]
            + [(f"mu_U[{k}]", "Real") for k in range(1, m + 1)]
            + [(f"jumped[{k}]", "Boolean") for k in range(1, m + 1)]
            + [(f"jumps[{k}]", "Integer") for k in range(1, m + 1)]
            + [("n_jumps", "Integer")])


def plant_parameters(scenario) -> list:
    """(name, type, value) of every plant FMU parameter, as `FmuPlant` sets them."""
    sc = scenario
    S0 = np.asarray(sc.S0, float)
    q0 = rot_to_quat(S0[:, layout.R].reshape(-1, 3, 3))   # w, x, y, z: what FleetFMU sets
    out = [(f"g[{k + 1}]", "Real", float(sc.gravity[k])) for k in range(3)]
    out.append(("h_internal", "Real", float(sc.internal_step)))
    for i in range(sc.graph.n):
        b = f"body[{i + 1}]"
        out.append((f"{b}.m", "Real", float(sc.masses[i])))
        out += [(f"{b}.J[{r + 1},{c + 1}]", "Real", float(sc.inertias[i][r, c]))
                for r in range(3) for c in range(3)]
        out += [(f"{b}.p0[{k + 1}]", "Real", float(S0[i, layout.P][k])) for k in range(3)]
        out += [(f"{b}.q0[{k + 1}]", "Real", float(q0[i, k])) for k in range(4)]
        out += [(f"{b}.xi0[{k + 1}]", "Real", float(S0[i, layout.XI][k])) for k in range(6)]
    return out


def controller_parameters(spec: dict) -> list:
    """(name, type, value) of every controller FMU parameter, from its `law_spec`."""
    d = spec["defaults"]
    out = [(k, "Real", float(d[k])) for k in ("k_X", "k_xi", "k_e", "k_theta")]
    out += [(f"A[{r + 1},{c + 1}]", "Real", float(d["A"][r][c])) for r in range(3)
            for c in range(3)]
    out += [(f"b[{k + 1}]", "Real", float(d["b"][k])) for k in range(3)]
    out.append(("d", "Real", float(d["d"])))
    out += [(f"u_c1[{k + 1}]", "Real", float(d["u_c1"][k])) for k in range(3)]
    out += [(f"u_c2[{k + 1}]", "Real", float(d["u_c2"][k])) for k in range(3)]
    out += [(f"Theta[{j + 1}]", "Real", float(x)) for j, x in enumerate(d["Theta"])]
    out += [("gamma", "Real", float(d["gamma"])), ("delta", "Real", float(d["delta"])),
            ("hybrid", "Boolean", bool(d["hybrid"]))]
    out += [(f"theta0[{k + 1}]", "Real", float(x)) for k, x in enumerate(d["theta0"])]
    S0 = np.asarray(d["S0"], float)
    for i in range(spec["n"]):
        b = f"body[{i + 1}]"
        out += [(f"{b}.p0[{k + 1}]", "Real", float(S0[i, k])) for k in range(3)]
        out += [(f"{b}.R0[{r + 1},{c + 1}]", "Real", float(S0[i, 3 + 3 * r + c]))
                for r in range(3) for c in range(3)]
        out += [(f"{b}.xi0[{k + 1}]", "Real", float(S0[i, 12 + k])) for k in range(6)]
    return out


def ssv_xml(name: str, params) -> bytes:
    root = ET.Element(_q("ssv:ParameterSet"), {"version": "1.0", "name": name})
    ps = ET.SubElement(root, _q("ssv:Parameters"))
    for pname, typ, value in params:
        p = ET.SubElement(ps, _q("ssv:Parameter"), {"name": pname})
        v = ("true" if value else "false") if typ == "Boolean" else (
            str(int(value)) if typ == "Integer" else _num(value))
        ET.SubElement(p, _q(f"ssv:{typ}"), {"value": v})
    return ET.tostring(root, encoding="UTF-8", xml_declaration=True)


def _connector(parent, name, kind, typ="Real"):
    c = ET.SubElement(parent, _q("ssd:Connector"), {"name": name, "kind": kind})
    ET.SubElement(c, _q(f"ssc:{typ}"))


def ssd_xml(scenario, law: str, duration: float) -> bytes:
    sc = scenario
    n, m = sc.graph.n, sc.graph.M
    root = ET.Element(_q("ssd:SystemStructureDescription"),
                      {"name": sc.name, "version": "1.0",
                       "generationTool": f"se3sync {__version__}"})
    system = ET.SubElement(root, _q("ssd:System"), {
        "name": sc.name,
        "description": f"se3sync: {n} rigid bodies on SE(3) (plant) in closed loop with the "
                       f"{law} law (controller), communication step {sc.step!r} s"})
    elements = ET.SubElement(system, _q("ssd:Elements"))
    states, wrenches = state_connectors(n), wrench_connectors(n)
    for name, src, ins, outs in ((PLANT, "resources/plant.fmu", wrenches, states),
                                 (CONTROLLER, "resources/controller.fmu", states, wrenches)):
        comp = ET.SubElement(elements, _q("ssd:Component"),
                             {"name": name, "source": src,
                              "type": "application/x-fmu-sharedlibrary"})
        conns = ET.SubElement(comp, _q("ssd:Connectors"))
        for c in ins:
            _connector(conns, c, "input")
        for c in outs:
            _connector(conns, c, "output")
        if name == CONTROLLER:
            for c, typ in controller_outputs(m):
                _connector(conns, c, "output", typ)
        pb = ET.SubElement(comp, _q("ssd:ParameterBindings"))
        ET.SubElement(pb, _q("ssd:ParameterBinding"),
                      {"source": f"resources/{name}.ssv",
                       "type": "application/x-ssp-parameter-set"})
    connections = ET.SubElement(system, _q("ssd:Connections"))
    for c in states:
        ET.SubElement(connections, _q("ssd:Connection"),
                      {"startElement": PLANT, "startConnector": c,
                       "endElement": CONTROLLER, "endConnector": c})
    for c in wrenches:
        ET.SubElement(connections, _q("ssd:Connection"),
                      {"startElement": CONTROLLER, "startConnector": c,
                       "endElement": PLANT, "endConnector": c})
    ex = ET.SubElement(root, _q("ssd:DefaultExperiment"),
                       {"startTime": "0.0", "stopTime": _num(duration)})
    ann = ET.SubElement(ET.SubElement(ex, _q("ssd:Annotations")), _q("ssc:Annotation"),
                        {"type": "com.opensimulationplatform"})
    ET.SubElement(ET.SubElement(ann, _q("osp:Algorithm")), _q("osp:FixedStepAlgorithm"),
                  {"baseStepSize": _num(sc.step)})
    ET.indent(root)
    return ET.tostring(root, encoding="UTF-8", xml_declaration=True)


def write_ssp(scenario, out, law: str = "hybrid", duration: float | None = None) -> Path:
    """Writes the SSP archive of ``scenario`` with the ``law`` controller to ``out``
    (atomically). ``duration``: the default experiment's stop time (default the scenario's)."""
    sc = scenario
    duration = float(sc.duration if duration is None else duration)
    S0 = plant_start_state(sc)
    spec = law_spec(sc, law, S0)
    out = Path(out)
    with tempfile.TemporaryDirectory(prefix="se3sync-ssp-") as d:
        d = Path(d)
        plant = plant_build.build_fmu(sc.graph.n, d / "plant.fmu", fmi_version=2)
        ctrl = build_law_fmu(sc, d / "controller.fmu", law, S0)
        with atomic_path(out) as tmp:
            with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as z:
                z.writestr(SSD_NAME, ssd_xml(sc, law, duration))
                z.write(plant, "resources/plant.fmu")
                z.write(ctrl, "resources/controller.fmu")
                z.writestr("resources/plant.ssv", ssv_xml(PLANT, plant_parameters(sc)))
                z.writestr("resources/controller.ssv",
                           ssv_xml(CONTROLLER, controller_parameters(spec)))
    return out
