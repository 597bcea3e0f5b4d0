"""The paper's distributed hybrid feedback for pose synchronisation on SE(3).

No I/O: this package is the mathematics (Lin, Wang, Su, Tayebi), in the paper's names.
"""
__version__ = "0.1.0"

from . import se3  # noqa: E402
from .design import (DesignWarning, SynergyDesign, WeightingMatrix, design_synergy,  # noqa: E402
                     Delta, delta_min, detect_case)
from .errors import ConfigError, DesignError, GraphError, Se3SyncError, WeightingError  # noqa: E402
from .graph import Graph  # noqa: E402
from .law import (AgentStepper, Gains, GradientController, HybridController,  # noqa: E402
                  JumpEvent, V_bar, jump_bound, pack_state)
from .params import LawParameters  # noqa: E402
from . import layout, potential  # noqa: E402

__all__ = [
    "se3", "potential", "WeightingMatrix", "SynergyDesign", "design_synergy", "DesignWarning",
    "Delta", "delta_min", "detect_case", "Graph", "Gains", "HybridController",
    "GradientController", "AgentStepper", "JumpEvent", "V_bar", "jump_bound", "pack_state",
    "Se3SyncError", "ConfigError", "WeightingError", "DesignError", "GraphError",
    "LawParameters", "layout",
]
