"""Errors raised for input se3sync refuses.

Every message names the condition that failed and the offending values, on one line, so that the
command line can print it as it is. The classes live here, in the package every other one imports,
so that the scenario parser, the bridge and the plant can all raise them without importing each
other.
"""


def _one_line(text) -> str:
    return " ".join(str(text).split())


class Se3SyncError(ValueError):
    """Base class of every refusal raised by se3sync (bad parameters, bad graphs, ...)."""


class ConfigError(Se3SyncError):
    """A problem with a configuration value: ``ConfigError(keypath, reason, file=None)``.

    ``str(err)`` is one line: ``FILE: KEYPATH: REASON`` (or ``KEYPATH: REASON`` without a file).
    Scenario tables owned by other packages (``[bridge]``, ``[network]``) raise it too; the
    scenario loader adds the file name.
    """

    def __init__(self, keypath, reason, file=None):
        self.keypath = "" if keypath is None else str(keypath)
        self.reason = _one_line(reason)
        self.file = None if file is None else str(file)
        super().__init__(self._line())

    def _line(self) -> str:
        parts = [p for p in (self.file, self.keypath) if p]
        return ": ".join(parts + [self.reason])

    def __str__(self) -> str:
        return self._line()

    def with_file(self, file) -> "ConfigError":
        return type(self)(self.keypath, self.reason, None if file is None else str(file))

    def under(self, prefix: str) -> "ConfigError":
        """The same error with its key path inside table ``prefix`` (``bridge`` + ``port``)."""
        kp = self.keypath or prefix
        if kp != prefix and not kp.startswith(prefix + ".") and not kp.startswith(prefix + "["):
            kp = f"{prefix}.{kp}"
        return type(self)(kp, self.reason, self.file)


class WeightingError(Se3SyncError):
    """The weighting matrix 𝔸 violates a condition of `AA_def`."""


class DesignError(Se3SyncError):
    """The synergy parameters violate Lemma 2 (`eqn:P_A`).

    ``param`` names the parameter the refusal is about: one of "alpha_signs", "u_c1", "W",
    "gamma", "Theta", "delta".
    """

    def __init__(self, message, param=None):
        self.param = param
        super().__init__(message)


class GraphError(Se3SyncError):
    """The graph violates Assumption 1 or is malformed."""
