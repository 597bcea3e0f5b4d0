"""Running `system.ssp` in two FMI masters, and the se3sync run they reproduce.

Both FMPy's `fmpy.ssp.simulate_ssp` and libcosim's fixed-step algorithm step every FMU from the
values of the previous communication point and exchange outputs afterwards (a Jacobi scheme).
The controller FMU samples the state at t_n in its step [t_n, t_n + h] and outputs u(t_n), so
the plant applies u(t_n) over the next step: the loop these masters run is `se3sync run` with one
communication step of actuation delay (u ≡ 0 on the first step), i.e. `se3sync run` with
``simulation.actuation_delay = 1`` (`cosim.plants.DelayedActuation`), the run the masters are
held to (docs/fmi-system.md).

`run_fmpy` and `run_libcosim` return a `SystemRun`: the plant state at every communication point,
θ after the jump stage and every jump (step, edge), read from the FMUs' own outputs.
"""
from __future__ import annotations

import os
import tempfile
import zipfile
from dataclasses import dataclass
from xml.etree import ElementTree as ET

import numpy as np

from controller.errors import Se3SyncError

from ..master import NetworkMetrics
from ..plants import DelayedActuation   # noqa: F401  (the masters' loop in cosim; re-exported)
from .ssp import CONTROLLER, NS, PLANT, SSD_NAME, state_connectors

__all__ = ["SystemRun", "DelayedActuation", "ssp_parameters", "run_fmpy", "run_libcosim",
           "samples"]


@dataclass
class SystemRun:
    """``S`` (K + 1, N, 18): the plant state at t_0 … t_K; ``theta`` (K, M): θ after the jump
    stage at t_0 … t_{K−1}; ``jumps``: [(step, edge)] in order; ``h``."""

    S: np.ndarray
    theta: np.ndarray
    jumps: list
    h: float


def samples(scenario, run: SystemRun, every: float = 1.0) -> list:
    """The summary's samples {t, rot_err, pos_err, xi_max, theta, V} at the steps that are
    multiples of ``every`` seconds (as `se3sync run` takes them), within the run."""
    m = NetworkMetrics(scenario)
    spl = max(1, int(round(every / run.h)))
    return [m.sample(n * run.h, np.ascontiguousarray(run.S[n]), run.theta[n])
            for n in range(0, len(run.theta), spl)]


def _read_archive(ssp):
    """(SSD root, {component: [(name, type, value)]} from the SSV files its bindings name)."""
    with zipfile.ZipFile(ssp) as z:
        root = ET.fromstring(z.read(SSD_NAME))
        params = {}
        for comp in root.iter(f"{{{NS['ssd']}}}Component"):
            out = params.setdefault(comp.get("name"), [])
            for b in comp.iter(f"{{{NS['ssd']}}}ParameterBinding"):
                ps = ET.fromstring(z.read(b.get("source")))
                for p in ps.iter(f"{{{NS['ssv']}}}Parameter"):
                    v = p[0]
                    typ = v.tag.split("}")[1]
                    raw = v.get("value")
                    val = (raw in ("true", "1") if typ == "Boolean" else
                           int(raw) if typ == "Integer" else float(raw))
                    out.append((p.get("name"), typ, val))
    return root, params


def ssp_parameters(ssp):
    """The archive's parameter bindings as the ParameterSet `fmpy.ssp.simulate_ssp` takes (FMPy
    applies only the parameter set it is given, with names prefixed by the component)."""
    from fmpy.ssp.ssd import Parameter, ParameterSet

    _, params = _read_archive(ssp)
    return ParameterSet(name="se3sync", parameters=[
        Parameter(name=f"{comp}.{name}", type=typ, value=val)
        for comp, ps in params.items() for name, typ, val in ps])


def _shape(root):
    n = sum(1 for c in root.iter(f"{{{NS['ssd']}}}Connector")
            if c.get("name").endswith(".R[1,1]") and c.get("kind") == "output")
    m = sum(1 for c in root.iter(f"{{{NS['ssd']}}}Connector")
            if c.get("name").startswith("theta["))
    return n, m


def _initial_state(params, n):
    d = {name: val for name, _, val in params[CONTROLLER]}
    S = np.empty((n, 18))
    for i in range(n):
        b = f"body[{i + 1}]"
        S[i, 0:3] = [d[f"{b}.p0[{k}]"] for k in range(1, 4)]
        S[i, 3:12] = [d[f"{b}.R0[{r},{c}]"] for r in range(1, 4) for c in range(1, 4)]
        S[i, 12:18] = [d[f"{b}.xi0[{k}]"] for k in range(1, 7)]
    return S


def run_fmpy(ssp, steps: int, h: float) -> SystemRun:
    """``steps`` communication steps of ``h`` of the archive in `fmpy.ssp.simulate_ssp`."""
    from fmpy.ssp.simulation import simulate_ssp

    root, params = _read_archive(ssp)
    n, m = _shape(root)
    # FMPy's loop runs while its accumulated time is below stop_time: stop half a step early
    res = simulate_ssp(str(ssp), stop_time=(steps - 0.5) * h, step_size=h,
                       parameter_set=ssp_parameters(ssp))
    if len(res) != steps:
        raise Se3SyncError(f"fmpy ran {len(res)} steps, expected {steps}")
    S = np.empty((steps + 1, n, 18))
    S[0] = _initial_state(params, n)
    names = state_connectors(n)
    flat = np.column_stack([res[f"{PLANT}.{c}"] for c in names])   # after each step
    S[1:] = flat.reshape(steps, n, 18)
    theta = np.column_stack([res[f"{CONTROLLER}.theta[{k}]"] for k in range(1, m + 1)])
    jumped = np.column_stack([res[f"{CONTROLLER}.jumped[{k}]"] for k in range(1, m + 1)])
    jumps = [(int(r), int(k) + 1) for r, k in zip(*np.nonzero(jumped))]
    return SystemRun(S=S, theta=theta, jumps=jumps, h=h)


def run_libcosim(ssp, steps: int, h: float) -> SystemRun:
    """``steps`` communication steps of the archive in libcosim (libcosimpy), with the base step
    of its OSP FixedStepAlgorithm annotation (``h``)."""
    from libcosimpy.CosimExecution import CosimExecution
    from libcosimpy.CosimLogging import CosimLogLevel, log_output_level
    from libcosimpy.CosimObserver import CosimObserver

    log_output_level(CosimLogLevel.ERROR)
    root, params = _read_archive(ssp)
    n, m = _shape(root)
    with tempfile.TemporaryDirectory(prefix="se3sync-libcosim-") as d:
        # libcosim reads an SSP from its unpacked folder
        with zipfile.ZipFile(ssp) as z:
            z.extractall(d)
        ex = CosimExecution.from_ssp_file(os.path.join(d, SSD_NAME))
        obs = CosimObserver.create_last_value()
        ex.add_observer(obs)
        pi = ex.slave_index_from_instance_name(PLANT)
        ci = ex.slave_index_from_instance_name(CONTROLLER)
        pv = {v.name.decode(): v.reference for v in ex.slave_variables(pi)}
        cv = {v.name.decode(): v.reference for v in ex.slave_variables(ci)}
        s_refs = [pv[c] for c in state_connectors(n)]
        th_refs = [cv[f"theta[{k}]"] for k in range(1, m + 1)]
        j_refs = [cv[f"jumped[{k}]"] for k in range(1, m + 1)]
        S = np.empty((steps + 1, n, 18))
        S[0] = _initial_state(params, n)
        theta = np.empty((steps, m))
        jumps = []
        for r in range(steps):
            if not ex.step():
                raise Se3SyncError(f"libcosim: step {r} failed")
            S[r + 1] = np.reshape(obs.last_real_values(pi, s_refs), (n, 18))
            theta[r] = obs.last_real_values(ci, th_refs)
            jumps += [(r, k + 1) for k, j in enumerate(obs.last_boolean_values(ci, j_refs)) if j]
        del obs, ex
    return SystemRun(S=S, theta=theta, jumps=jumps, h=h)
