"""Errors raised for input the mathematics refuses.

Every message names the condition that failed and the offending values, on one line,
so that the command line can print it as it is.
"""


class Se3SyncError(ValueError):
    """Base class of every refusal raised by se3sync (bad parameters, bad graphs, ...)."""


class WeightingError(Se3SyncError):
    """The weighting matrix 𝔸 violates a condition of `AA_def`."""


class DesignError(Se3SyncError):
    """The synergy parameters violate Lemma 2 (`eqn:P_A`)."""


class GraphError(Se3SyncError):
    """The graph violates Assumption 1 or is malformed."""
