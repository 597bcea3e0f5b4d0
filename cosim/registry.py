"""The registries of control laws and plants: names → ``"module:attribute"``, resolved when used.

The command line's ``--controller`` and ``--plant`` choices, the sweeps and the analysis read these
tables; nothing else lists laws or plants. The targets are imported only when a law or plant is
built, so `se3sync --help` does not load the compiled kernels or fmpy.

Adding a law: write ``make(scenario) -> cosim.controllers.Controller`` in a module, with the
capabilities it has (`cosim.controllers`), and add one line to ``LAWS`` (cosim/laws/decoupled.py
is one). Adding a Python plant: write a class with ``from_scenario(scenario, **options)``
implementing `cosim.plants.Plant` and add one line to ``PLANTS``.
"""
from __future__ import annotations

import importlib

from controller.errors import Se3SyncError

__all__ = ["LAWS", "PLANTS", "AGENT_AOT", "resolve"]

# name -> ("module:attribute" of a factory(scenario) -> Controller, one-line description)
LAWS = {
    "hybrid": ("cosim.controllers:hybrid", "the paper's distributed hybrid feedback "
                                           "(ex_controller)"),
    "gradient": ("cosim.controllers:gradient", "the gradient-only baseline (θ ≡ 0, no jumps)"),
    "decoupled": ("cosim.laws.decoupled:make", "decoupled SO(3) × R³ synchronisation, the design "
                                               "the paper contrasts itself with"),
}

# the laws whose per-agent view runs on the agent kernels compiled ahead of time
# (`bridge.swarm.aot`): an agent process of one of these runs without numba
AGENT_AOT = ("hybrid", "gradient")

# name -> ("module:attribute" of a Plant class with from_scenario(scenario, **options), description)
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
