"""The paper's law as an FMI 2.0 Co-Simulation FMU (`se3sync fmu build --controller SCENARIO`).

The FMU is built by pythonfmu (extra ``fmi``) around `se3sync_law.py` (the slave, copied into
the FMU's resources) and ``se3sync_law.json`` (the scenario's structure and every parameter's
default). It runs inside the host's Python, which must have se3sync installed: the law is the
project's own kernel (`controller.kernels.network_step` through `HybridController`), the one
`se3sync run` steps.
"""
from __future__ import annotations

import json
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

from controller import __version__
from controller.errors import Se3SyncError

from ..files import atomic_path
from ..plants import FmuPlant
from ..scenario import load_scenario

__all__ = ["LAWS", "SLAVE", "law_spec", "plant_start_state", "build_law_fmu", "build_from_cli"]

LAWS = ("hybrid", "gradient")
SLAVE = Path(__file__).with_name("se3sync_law.py")
MODEL_IDENTIFIER = "Se3syncLaw"


def plant_start_state(scenario) -> np.ndarray:
    """The plant FMU's outputs p, R, ξ right after its initialisation with the scenario's
    initial state (R comes back from the quaternion the FMU is given, so it can differ from
    the scenario's in the last bits): what the controller reads at t = 0 in `se3sync run`."""
    plant = FmuPlant.from_scenario(scenario)
    try:
        return np.array(plant.read(), copy=True)
    finally:
        plant.close()


def law_spec(scenario, law: str = "hybrid", S0=None) -> dict:
    """The FMU's ``se3sync_law.json``: structure and parameter defaults (exact floats)."""
    if law not in LAWS:
        raise Se3SyncError(f"--law: expected one of {', '.join(LAWS)}, got {law!r}")
    sc = scenario
    des, wm, g = sc.design, sc.weighting, sc.gains
    S0 = plant_start_state(sc) if S0 is None else np.asarray(S0, float)
    hybrid = law == "hybrid"
    return {
        "format": 1,
        "se3sync_version": __version__,
        "scenario": sc.name,
        "law": law,
        "n": int(sc.graph.n),
        "edges": [[int(a), int(b)] for a, b in sc.graph.edge_list],
        "n_theta": len(des.Theta),
        "experiment": {"start": 0.0, "stop": float(sc.duration), "step": float(sc.step)},
        "defaults": {
            "k_X": float(g.k_X), "k_xi": float(g.k_xi), "k_e": float(g.k_e),
            "k_theta": float(g.k_theta),
            "A": np.asarray(wm.A, float).tolist(), "b": np.asarray(wm.b, float).tolist(),
            "d": float(wm.d),
            "u_c1": np.asarray(des.u_c1, float).tolist(),
            "u_c2": np.asarray(des.u_c2, float).tolist(),
            "Theta": [float(x) for x in des.Theta],
            "gamma": float(des.gamma), "delta": float(des.delta),
            "hybrid": hybrid,
            "theta0": (np.asarray(sc.theta0, float) if hybrid
                       else np.zeros(sc.graph.M)).tolist(),
            "S0": S0.tolist(),
        },
    }


def build_law_fmu(scenario, out, law: str = "hybrid", S0=None) -> Path:
    """Writes the controller FMU for ``scenario`` to ``out`` (atomically); returns its path."""
    from pythonfmu.builder import FmuBuilder   # optional (extra "fmi")

    spec = law_spec(scenario, law, S0)
    out = Path(out)
    with tempfile.TemporaryDirectory(prefix="se3sync-law-") as d:
        d = Path(d)
        src = d / "src"
        src.mkdir()
        script = src / SLAVE.name
        shutil.copyfile(SLAVE, script)
        (src / "se3sync_law.json").write_text(json.dumps(spec, indent=1), encoding="utf-8")
        path_before = list(sys.path)
        try:
            built = FmuBuilder.build_FMU(script, dest=d / f"{MODEL_IDENTIFIER}.fmu",
                                         project_files=[src / "se3sync_law.json"])
        except Se3SyncError:
            raise
        except Exception as exc:  # noqa: BLE001 - pythonfmu's failures are one line for the CLI
            raise Se3SyncError(f"--output: building the controller FMU failed: "
                               f"{type(exc).__name__}: {' '.join(str(exc).split())[:300]}") from None
        finally:
            sys.path[:] = path_before   # the builder puts the build folder on sys.path
        with atomic_path(out) as tmp:
            shutil.copyfile(built, tmp)
    return out


def build_from_cli(scenario_path, output, law="hybrid", overrides=()) -> str:
    """The `se3sync fmu build --controller SCENARIO` job (registered as the entry point
    ``se3sync.fmu_builders: controller``): returns the line the command prints."""
    sc = load_scenario(scenario_path, list(overrides))
    out = build_law_fmu(sc, output, law)
    return (f"wrote {out} (the {law} law of {sc.name}: {sc.graph.n} agents, {sc.graph.M} edges; "
            f"FMI 2.0 Co-Simulation, modelIdentifier {MODEL_IDENTIFIER}; needs a Python with "
            f"se3sync installed on the host)")
