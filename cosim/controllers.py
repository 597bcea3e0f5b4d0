"""What the master, the compiled loop, the analysis, the sweeps and the agents need of a control law.

Every law is a `Controller`: a ``name``, ``step_state(S, h) -> (u, events)`` and ``reset``.
Anything else a law can do it declares as a capability, and the code that needs one asks for it
(``getattr(law, name, None)``), never for a concrete type; a law without it is told so on one
line (`require`):

=====================  ==========================================================  ===================
capability             what the law provides                                        who asks
=====================  ==========================================================  ===================
``edge_state``         its θ-like per-edge state (`EdgeState`), or None: no state  master (log, V̄,
                       (θ ≡ 0 is logged; the loop is linearised without it)         summary), analysis
``write_wrench_into``  computes u straight into a plant's input buffer              master
``compiled_step()``    a numba record that `law_step` steps (`compiled_law_step`)   compiled loop
                                                                                    (cosim/fastloop.py)
``agent_view(i)``      agent i's view (the `controller.AgentStepper` interface)     ``agent``, ``swarm``
``delayed_step()``     its step on delayed neighbour data (`DelayedLaw`, built on   ``[network]``
                       the link pieces of `cosim.network_step`)
=====================  ==========================================================  ===================

``check`` asks for nothing more: the loop is linearised by finite differences of the law's own
``step_state`` (and ``edge_state``) on two agents at consensus (`cosim.analysis.linear`), so a new
law is analysed as it runs. The paper's hybrid law and the gradient baseline declare every
capability here (`HybridLaw`, `GradientLaw`); `cosim.laws.decoupled` is a law added through
these seams only. Laws are registered in `cosim.registry.LAWS`.
"""
from __future__ import annotations

from typing import Callable, NamedTuple, Protocol, runtime_checkable

import numpy as np

from controller import AgentStepper, GradientController, HybridController
from controller.jit import aot_module, jit, numba_module
from controller.errors import Se3SyncError
from controller.kernels import network_step

from .network_step import delayed_network_step
from .registry import LAWS, resolve

__all__ = ["Controller", "EdgeState", "make_controller", "law_names", "law_name", "hybrid",
           "gradient", "HybridLaw", "GradientLaw", "PaperStep", "DelayedLaw", "law_step",
           "compiled_law_step", "require", "edge_state_of", "agent_view"]


@runtime_checkable
class Controller(Protocol):
    """The network view of a law at communication points of length h.

    ``step_state(S, h) -> (u (N, 6), events)``: S (N, 18) as `controller.layout`; u may be a
    buffer the next call overwrites; events are `controller.JumpEvent`s (edge from 1).
    ``reset(theta0=None)`` restarts the law's own state (θ(0) = theta0, zeros if None); ``name``
    is what logs and summaries call it. The capabilities in the module docstring are optional.
    """

    name: str

    def step_state(self, S, h: float): ...

    def reset(self, theta0=None) -> None: ...


class EdgeState(NamedTuple):
    """A law's θ-like state, per edge (M,): ``theta`` (after the flow), ``theta_prev`` (on entry
    to the last step), ``theta_jump`` (after its jump stage), ``mu`` (the jump test's value before
    the jump stage; the paper's μ_U) and ``jumped`` (bool). The law updates these arrays in place
    at every step; readers keep the record."""

    theta: np.ndarray
    theta_prev: np.ndarray
    theta_jump: np.ndarray
    mu: np.ndarray
    jumped: np.ndarray

    @classmethod
    def zeros(cls, M: int) -> "EdgeState":
        """The state of a law without one: θ ≡ 0, no jumps, μ = 0."""
        return cls(np.zeros(M), np.zeros(M), np.zeros(M), np.zeros(M), np.zeros(M, np.bool_))


# ------------------------------------------------------------------ capabilities
_WHAT = {
    "edge_state": "θ-like per-edge state",
    "compiled_step": "compiled network step",
    "agent_view": "per-agent view",
    "delayed_step": "per-agent step on delayed data",
}


def require(law, name: str, needed_by: str, hint: str = ""):
    """The law's capability ``name`` (an attribute or a method), or a one-line Se3SyncError
    naming what the law lacks and who needs it."""
    c = getattr(law, name, None)
    if c is None:
        raise Se3SyncError(f"{needed_by}: the law {law_name(law)!r} has no "
                           f"{_WHAT.get(name, name)} ({name})" + (f"; {hint}" if hint else ""))
    return c


def edge_state_of(law, M: int) -> EdgeState:
    """The law's `EdgeState`, or the zero state of a law without one."""
    es = getattr(law, "edge_state", None)
    return EdgeState.zeros(M) if es is None else es


def agent_view(name: str, scenario, agent: int):
    """Agent ``agent``'s view of the law registered as ``name`` (`se3sync agent`)."""
    law = make_controller(name, scenario)
    view = require(law, "agent_view", "--controller",
                   "the agent processes need one (it runs in run and connect)")
    return view(agent)


# ------------------------------------------------------------------ the compiled seam
_PY_STEPS: dict = {}


def law_step(args, S, h):
    """The compiled network step of a law: the wrench at state S (N, 18) into the law's output
    buffer (held in ``args``), the law's edge state updated; returns the number of jumps.
    ``args`` is what the law's ``compiled_step()`` returns, a NamedTuple of arrays and numbers;
    each law registers its step for the type of that record (`compiled_law_step`), and compiled
    code calling `law_step` (cosim/fastloop.py) is specialised per record type. Called from
    Python (or with NUMBA_DISABLE_JIT=1) it dispatches on the record's class."""
    return _PY_STEPS[type(args)](args, S, h)


def compiled_law_step(record):
    """Decorator: the compiled function ``step(args, S, h) -> jumps`` is `law_step` for
    ``args`` of the NamedTuple class ``record``. Compile ``step`` with ``inline="always"``: a
    compiled call that passes the record's arrays counts references on each (atomic operations,
    about 8 % of the paper's step), which inlining removes."""
    def register(step):
        _PY_STEPS[record] = step
        if aot_module() is not None:
            return step     # a process without numba (an agent's) never runs the compiled loop
        numba = numba_module()
        from numba.extending import overload

        @overload(law_step, inline="always")
        def _typed(args, S, h):
            if isinstance(args, numba.types.BaseNamedTuple) and args.instance_class is record:
                return lambda args, S, h: step(args, S, h)
        return step
    return register


# ------------------------------------------------------------------ the paper's two laws
class PaperStep(NamedTuple):
    """`controller.kernels.network_step`'s arguments: the compiled step of `HybridLaw` and
    `GradientLaw`."""

    theta: np.ndarray
    edges: np.ndarray
    P: np.ndarray
    hybrid: bool
    u: np.ndarray
    mu: np.ndarray
    jumped: np.ndarray
    theta_prev: np.ndarray
    theta_jump: np.ndarray


@compiled_law_step(PaperStep)
@jit(inline=True)
def _paper_step(a, S, h):
    return network_step(S, a.theta, a.edges, a.P, h, a.hybrid, a.u, a.mu, a.jumped,
                        a.theta_prev, a.theta_jump)


class DelayedLaw(NamedTuple):
    """What `cosim.network.NetworkController` needs of a law to run it per agent on delayed data:
    ``step(S, n, sched, r, ring_S, ring_theta, arrival, held, recv_S, recv_theta, term, max_age,
    hold, h, age_hist, counts, failsafe) -> jumps``, the law's delayed step with its parameters
    bound (the arrays of `cosim.network_step`), its `EdgeState` (None: no θ) and its wrench
    buffer u."""

    step: Callable
    state: EdgeState | None
    u: np.ndarray


class _PaperCapabilities:
    """The capabilities of the paper's network view (`controller.HybridController`)."""

    @property
    def edge_state(self):
        if not self.hybrid:
            return None
        return EdgeState(self.theta, self.theta_prev, self.theta_jump, self.mu, self.jumped)

    def compiled_step(self):
        if type(self).step_state is not HybridController.step_state:
            return None  # a subclass with its own step: only the Python loop knows it
        return PaperStep(self.theta, self.edges, self.P, bool(self.hybrid), self.u, self.mu,
                         self.jumped, self.theta_prev, self.theta_jump)

    def agent_view(self, i: int):
        """Agent i's `controller.AgentStepper`, θ(0) of its owned edges from the law's θ now."""
        i = int(i)
        local = self.graph.local_edges(i)
        return AgentStepper(i, local, self.weighting, self.design if self.hybrid else None,
                            self.gains, theta0={k: float(self.theta[k - 1]) for k, (a, _)
                                                in local.items() if a == i})

    def delayed_step(self):
        theta, edges, P, hybrid, u = self.theta, self.edges, self.P, bool(self.hybrid), self.u
        mu, jumped, theta_prev, theta_jump = self.mu, self.jumped, self.theta_prev, self.theta_jump

        def step(S, n, sched, r, ring_S, ring_theta, arrival, held, recv_S, recv_theta, term,
                 max_age, hold, h, age_hist, counts, failsafe):
            return delayed_network_step(S, n, sched, r, ring_S, ring_theta, arrival, held,
                                        recv_S, recv_theta, term, max_age, hold, theta, edges,
                                        P, h, hybrid, u, mu, jumped, theta_prev, theta_jump,
                                        age_hist, counts, failsafe)

        return DelayedLaw(step, EdgeState(theta, theta_prev, theta_jump, mu, jumped), u)


class HybridLaw(_PaperCapabilities, HybridController):
    """The paper's law (`controller.HybridController`) with its capabilities."""


class GradientLaw(_PaperCapabilities, GradientController):
    """The gradient-only baseline (`controller.GradientController`) with its capabilities:
    no θ-like state (θ ≡ 0)."""


def hybrid(scenario) -> HybridLaw:
    """The paper's law with the scenario's design, gains and θ(0)."""
    return HybridLaw(scenario.graph, scenario.weighting, scenario.design, scenario.gains,
                     theta0=scenario.theta0)


def gradient(scenario) -> GradientLaw:
    """The gradient-only baseline with the scenario's gains."""
    return GradientLaw(scenario.graph, scenario.weighting, scenario.gains)


def law_names() -> tuple:
    return tuple(LAWS)


def make_controller(name: str, scenario) -> Controller:
    """A fresh controller of the law registered as ``name`` (`cosim.registry.LAWS`)."""
    return resolve(LAWS, name, "controller")(scenario)


def law_name(controller) -> str:
    """The name a controller instance reports in logs and summaries."""
    return getattr(controller, "name", type(controller).__name__)
