"""The paper's distributed hybrid feedback for pose synchronisation on SE(3).

No I/O: this package is the mathematics (Lin, Wang, Su, Tayebi), in the paper's names.

`errors` and `layout` (numpy only) load with the package; every other name below loads its module
on first use (PEP 562 ``__getattr__``), so that ``from controller.errors import ...`` — which the
command line's start-up and every package's error path do — does not load numba and the compiled
kernels. This is the project's one lazy import of its own code.
"""
__version__ = "0.1.0"

import importlib

from . import errors, layout  # noqa: F401
from .errors import ConfigError, DesignError, GraphError, Se3SyncError, WeightingError

# public name -> the submodule that defines it (loaded on first access)
_LAZY = {
    "se3": None, "potential": None, "design": None, "graph": None, "law": None, "params": None,
    "kernels": None,
    "DesignWarning": "design", "SynergyDesign": "design", "WeightingMatrix": "design",
    "design_synergy": "design", "Delta": "design", "delta_min": "design", "detect_case": "design",
    "Graph": "graph",
    "AgentStepper": "law", "Gains": "law", "GradientController": "law", "HybridController": "law",
    "JumpEvent": "law", "V_bar": "law", "jump_bound": "law", "pack_state": "law",
    "LawParameters": "params",
}

__all__ = [
    "se3", "potential", "WeightingMatrix", "SynergyDesign", "design_synergy", "DesignWarning",
    "Delta", "delta_min", "detect_case", "Graph", "Gains", "HybridController",
    "GradientController", "AgentStepper", "JumpEvent", "V_bar", "jump_bound", "pack_state",
    "Se3SyncError", "ConfigError", "WeightingError", "DesignError", "GraphError",
    "LawParameters", "layout",
]


def __getattr__(name):
    try:
        mod = _LAZY[name]
    except KeyError:
        raise AttributeError(f"module 'controller' has no attribute {name!r}") from None
    value = importlib.import_module(f".{name if mod is None else mod}", __name__)
    if mod is not None:
        value = getattr(value, name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_LAZY))
