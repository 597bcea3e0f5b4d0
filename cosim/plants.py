"""Plants the master can drive: the protocol, `make_plant` over the registry the command line's
``--plant`` choices read, and the two FMU-backed implementations.

A plant holds N rigid bodies. Per communication step the master calls, in this order,
``read()`` (the state at t_n), ``apply(u)`` (held constant over the step: zero-order hold) and
``advance(h)`` (t_n → t_n + h). A plant owns its time: it counts the steps it has advanced
(t = k·h), and nothing else counts them for it. Plants are registered in
`cosim.registry.PLANTS`; a Python plant needs no FMU (tests/cosim/test_python_plant.py shows one).
"""
from __future__ import annotations

import zipfile
from typing import NamedTuple, Protocol, runtime_checkable

import numpy as np

from controller.errors import ConfigError, Se3SyncError
from controller import layout
from plant_fmu.fast import FleetFMU, FmiCalls

from .registry import PLANTS, resolve

__all__ = ["Plant", "CompiledPlant", "FmuPlant", "PerBodyFmuPlant", "DelayedActuation",
           "make_plant", "refuse_actuation_delay"]


@runtime_checkable
class Plant(Protocol):
    """n: number of bodies; read() -> S (N, 18) [p, R row-major, ξ] (may be a reused buffer);
    apply(u (N, 6)): the wrench held over the next step; advance(h); close(). A registered plant
    class also has ``from_scenario(scenario, **options)`` (options: what a caller may pass
    through `make_plant`, e.g. an FMU plant's ``fmu_path``).

    Optional capabilities, each asked for by the code that uses it: ``stats() -> dict`` (link
    statistics; logged on /link/stats at 1 Hz and put in the summary under "link"),
    ``model_description() -> str | None`` (attached to the log), ``input_buffer`` (an (N, 6)
    array the controller may write its wrench into), ``reset(S0)`` (start again from S0 at
    t = 0, so that one plant serves many runs: the sweeps need it), ``max_block`` (steps the
    master may run between two checks for Ctrl-C) and ``compiled_plant()`` (a `CompiledPlant`:
    the compiled loop of cosim/fastloop.py steps it without Python).
    """

    n: int

    def read(self) -> np.ndarray: ...

    def apply(self, u: np.ndarray) -> None: ...

    def advance(self, h: float) -> None: ...

    def close(self) -> None: ...


def _md_text(path) -> str | None:
    try:
        with zipfile.ZipFile(path) as z:
            return z.read("modelDescription.xml").decode("utf-8")
    except (OSError, KeyError, zipfile.BadZipFile):
        return None


class CompiledPlant(NamedTuple):
    """What the compiled loop (cosim/fastloop.py) needs of a plant: the FMU's raw calls and
    buffers (`plant_fmu.fast.FmiCalls`), the plant's clock, an int64 (1,) holding the steps
    advanced since t = 0 — the same memory `FmuPlant.advance` counts in, so either loop moves
    the one clock and neither copies it — and ``held``, the wrenches of an actuation delay of
    d steps (d, N, 6): at step k the loop sends the FMU ``held[k % d]`` (the wrench of step
    k − d) and keeps the law's wrench there; d = 0 (an empty array): the law's wrench itself
    (`DelayedActuation` shares its array with the Python loop)."""

    fmi: FmiCalls
    clock: np.ndarray
    held: np.ndarray


class FmuPlant:
    """All N bodies in ONE instance of the plant FMU (a handful of FMI calls per step).

    ``FmuPlant(masses (N,), inertias (N,3,3), S0 (N,18), gravity=(0,0,0), internal_step=1e-4,
    fmu_path=None)``; ``FmuPlant.from_scenario(scenario, fmu_path=None)``. ``steps`` is its
    clock: doStep runs from steps·h.
    """

    def __init__(self, masses, inertias, S0, gravity=(0.0, 0.0, 0.0), internal_step=1e-4,
                 fmu_path=None, instance_name="plant", terms=None):
        S0 = np.asarray(S0, float)
        self.n = n = S0.shape[0]
        # terms: the optional ground and drag (Scenario.plant_terms; none for the paper's runs)
        self._fixed = dict(mass=np.asarray(masses, float), J=np.asarray(inertias, float),
                           gravity=np.asarray(gravity, float), h_internal=float(internal_step),
                           **(terms or {}))
        self._fmu = fmu = FleetFMU(n, fmu_path=fmu_path, instance_name=instance_name)
        try:
            fmu.set_initial_state(S0, **self._fixed)
            fmu.initialize(0.0)
        except BaseException:
            fmu.close()
            raise
        self._clock = np.zeros(1, np.int64)
        self._no_delay = np.zeros((0, n, 6))
        self.read = fmu.get_state
        self.apply = fmu.set_input
        self._do_step = fmu.do_step
        # The controller may compute its wrench straight into this buffer (Master does):
        # apply() then sends it without a copy.
        self.input_buffer = fmu.u

    @classmethod
    def from_scenario(cls, scenario, fmu_path=None, instance_name="plant"):
        return cls(scenario.masses, scenario.inertias, scenario.S0, scenario.gravity,
                   scenario.internal_step, fmu_path, instance_name,
                   terms=scenario.plant_terms)

    @property
    def steps(self) -> int:
        """Communication steps advanced since t = 0 (the plant's clock)."""
        return int(self._clock[0])

    def advance(self, h: float) -> None:
        clock = self._clock
        k = int(clock[0])
        self._do_step(k * h, h)
        clock[0] = k + 1

    def compiled_plant(self) -> CompiledPlant | None:
        """The FMU's raw calls and this plant's clock, for the compiled loop (None once
        closed). A call it reports failed is raised by `raise_fmi_status`."""
        fmu = self._fmu
        if fmu is None or type(self).advance is not FmuPlant.advance:
            return None  # closed, or a subclass with its own step: only Python knows it
        return CompiledPlant(fmu.fmi_calls(), self._clock, self._no_delay)

    def raise_fmi_status(self, function: str, status: int) -> None:
        """The FMUError of an FMI call the compiled loop saw fail, with what the FMU logged."""
        self._fmu.raise_status(function, status)

    def reset(self, S0) -> None:
        """fmi2Reset, the same parameters with the initial state S0, initialise at t = 0."""
        fmu = self._fmu
        try:
            fmu.terminate()
        except Se3SyncError:
            pass  # already terminated, or the last run ended in an error: reset clears both
        fmu.reset()
        fmu.set_initial_state(np.asarray(S0, float), **self._fixed)
        fmu.initialize(0.0)
        self._clock[0] = 0

    def model_description(self) -> str | None:
        return _md_text(self._fmu.fmu_path)

    def close(self) -> None:
        fmu = self._fmu
        if fmu is not None:
            self._fmu = None
            try:
                fmu.terminate()
            except Exception:
                pass
            fmu.close()


class PerBodyFmuPlant:
    """N single-body instances of the plant FMU (FleetFMU(1) each): the composition any FMI
    master would build. Gives the same trajectory as FmuPlant (the model steps bodies
    independently)."""

    def __init__(self, masses, inertias, S0, gravity=(0.0, 0.0, 0.0), internal_step=1e-4,
                 fmu_path=None, terms=None):
        S0 = np.asarray(S0, float)
        self.n = n = S0.shape[0]
        masses = np.broadcast_to(np.asarray(masses, float), (n,))
        inertias = np.broadcast_to(np.asarray(inertias, float), (n, 3, 3))
        self._fmus = []
        try:
            for i in range(n):
                f = FleetFMU(1, fmu_path=fmu_path, instance_name=f"body{i + 1}")
                self._fmus.append(f)
                f.set_initial_state(S0[i:i + 1], mass=masses[i:i + 1], J=inertias[i:i + 1],
                                    gravity=np.asarray(gravity, float),
                                    h_internal=float(internal_step), **(terms or {}))
                f.initialize(0.0)
        except BaseException:
            self.close()
            raise
        self._S = np.zeros((n, layout.S_WIDTH))
        self._rows = [self._S[i:i + 1] for i in range(n)]
        self._u = np.zeros((n, 6))
        self._urows = [self._u[i:i + 1] for i in range(n)]
        self._get = [f.get_state for f in self._fmus]
        self._set = [f.set_input for f in self._fmus]
        self._step = [f.do_step for f in self._fmus]
        self._k = 0

    @classmethod
    def from_scenario(cls, scenario, fmu_path=None):
        return cls(scenario.masses, scenario.inertias, scenario.S0, scenario.gravity,
                   scenario.internal_step, fmu_path, terms=scenario.plant_terms)

    @property
    def steps(self) -> int:
        """Communication steps advanced since t = 0 (the plant's clock)."""
        return self._k

    def read(self) -> np.ndarray:
        copyto = np.copyto
        for row, get in zip(self._rows, self._get):
            copyto(row, get())
        return self._S

    def apply(self, u) -> None:
        np.copyto(self._u, u)
        for row, s in zip(self._urows, self._set):
            s(row)

    def advance(self, h: float) -> None:
        t = self._k * h
        for s in self._step:
            s(t, h)
        self._k += 1

    def model_description(self) -> str | None:
        return _md_text(self._fmus[0].fmu_path) if self._fmus else None

    def close(self) -> None:
        fmus, self._fmus = self._fmus, []
        for f in fmus:
            try:
                f.terminate()
            except Exception:
                pass
            f.close()


class DelayedActuation:
    """A plant that applies each wrench ``steps`` = d communication steps late: over
    [t_n, t_{n+1}] it applies u(t_{n−d}), and zero for n < d (`simulation.actuation_delay`).
    With d = 1 it is what the plant FMU receives from the controller FMU in a Jacobi FMI master
    (FMPy's `simulate_ssp`, libcosim's fixed-step algorithm: docs/fmi-system.md).

    Everything else is the inner plant's (read, advance, its clock, statistics, reset, ...).
    Both loops run it: the Python loop through ``apply``, the compiled loop through
    ``compiled_plant`` (the inner FMU plant's record with this plant's held wrenches, swapped
    in by the loop before fmi2SetReal). Both index the held wrenches by the inner plant's clock
    when it has one (``steps``), so they are the same state whichever loop steps."""

    def __init__(self, inner, steps: int = 1):
        d = int(steps)
        if d < 1:
            raise Se3SyncError(f"DelayedActuation: steps must be >= 1, got {steps!r}")
        self.inner = inner
        self.n = n = inner.n
        self.delay = d
        self._held = np.zeros((d, n, 6))   # slot k % d: the wrench of step k − d until step k
        self._out = np.zeros((n, 6))
        self._k = 0                        # the steps advanced, for an inner plant without clock
        self._clocked = isinstance(getattr(type(inner), "steps", None), property)

    def __getattr__(self, name):   # the inner plant's capabilities (input_buffer, stats, ...)
        inner = self.__dict__.get("inner")
        if inner is None:
            raise AttributeError(name)
        return getattr(inner, name)

    def read(self):
        return self.inner.read()

    def apply(self, u) -> None:
        k = self.inner.steps if self._clocked else self._k
        slot = self._held[k % self.delay]
        np.copyto(self._out, slot)
        np.copyto(slot, u)
        self.inner.apply(self._out)

    def advance(self, h: float) -> None:
        self.inner.advance(h)
        self._k += 1

    def compiled_plant(self) -> CompiledPlant | None:
        cp = getattr(self.inner, "compiled_plant", None)
        p = cp() if cp is not None else None
        return None if p is None else p._replace(held=self._held)

    def reset(self, S0) -> None:
        self.inner.reset(S0)
        self._held[...] = 0.0
        self._k = 0

    def model_description(self):
        md = getattr(self.inner, "model_description", None)
        return md() if md is not None else None

    def close(self) -> None:
        self.inner.close()


def make_plant(kind: str, scenario, **options):
    """The plant registered as ``kind`` (`cosim.registry.PLANTS`), built from the scenario;
    ``options`` go to its ``from_scenario`` (e.g. ``fmu_path`` for the FMU plants). With
    ``simulation.actuation_delay`` = d > 0, that plant inside `DelayedActuation` (d steps)."""
    p = resolve(PLANTS, kind, "plant").from_scenario(scenario, **options)
    d = getattr(scenario, "actuation_delay", 0)
    return DelayedActuation(p, d) if d else p


def refuse_actuation_delay(scenario, what: str) -> None:
    """One line naming ``simulation.actuation_delay`` when the scenario sets it and ``what`` (a
    command, a plant) does not apply it: only the plants `make_plant` builds delay the wrench."""
    d = getattr(scenario, "actuation_delay", 0)
    if d:
        raise ConfigError("simulation.actuation_delay",
                            f"{d} step(s): only the co-simulation's plants apply it (se3sync run, "
                            f"the sweeps), not {what}; remove it or set it to 0",
                            getattr(scenario, "path", None))
