"""The registries of control laws and plants: names → ``"module:attribute"``, resolved when used.

The command line's ``--controller`` and ``--plant`` choices, the sweeps and the analysis read these
tables; nothing else lists laws or plants. The targets are imported only when a law or plant is
built, so `se3sync --help` does not load the compiled kernels or fmpy.

Adding a law: write ``make(scenario) -> cosim.controllers.Controller`` in a module and add one line
to ``LAWS``. Adding a Python plant: write a class with ``from_scenario(scenario, fmu_path=None)``
implementing `cosim.plants.Plant` and add one line to ``PLANTS``.
"""
from __future__ import annotations

import importlib

from controller.errors import Se3SyncError

__all__ = ["AGENT_LAWS", "LAWS", "PLANTS", "resolve"]

# name -> ("module:attribute" of a factory(scenario) -> Controller, one-line description)
LAWS = {
    "hybrid": ("cosim.controllers:hybrid", "the paper's distributed hybrid feedback "
                                           "(ex_controller)"),
    "gradient": ("cosim.controllers:gradient", "the gradient-only baseline (θ ≡ 0, no jumps)"),
}

# the laws of LAWS that also have a per-agent view (`controller.AgentStepper`), which the agent
# processes (`se3sync agent`, `se3sync swarm`) run; a law without one runs in `run` and `connect`
AGENT_LAWS = ("hybrid", "gradient")

# name -> ("module:attribute" of a Plant class with from_scenario(scenario, fmu_path), description)
PLANTS = {
    "fleet": ("cosim.plants:FmuPlant", "one N-body instance of the plant FMU"),
    "per-body": ("cosim.plants:PerBodyFmuPlant", "N single-body instances of the plant FMU"),
}


def resolve(table: dict, name: str, what: str):
    """The object registered as ``name`` in ``table`` (LAWS or PLANTS)."""
    try:
        target = table[name][0]
    except KeyError:
        raise Se3SyncError(f"{what} must be one of {', '.join(table)}, got {name!r}") from None
    mod, _, attr = target.partition(":")
    return getattr(importlib.import_module(mod), attr)
