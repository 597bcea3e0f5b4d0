"""What the master, the stability analysis, the sweeps and the bridge need of a control law (the
`Controller` protocol), the built-in laws' factories, and `make_controller` over the registry
`cosim.registry.LAWS`."""
from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from controller import GradientController, HybridController, LawParameters

from .registry import LAWS, resolve

__all__ = ["Controller", "make_controller", "law_names", "law_name", "hybrid", "gradient"]


@runtime_checkable
class Controller(Protocol):
    """The network view of a law at communication points of length h.

    ``step_state(S, h) -> (u (N, 6), events)``: S (N, 18) as `controller.layout`; u may be a
    buffer the next call overwrites; events are `controller.JumpEvent`s. After a step, per edge:
    ``theta`` (after the flow), ``theta_jump`` (after the jump stage), ``mu`` (μ_U before the jump
    stage) and ``jumped`` (M,). ``reset(theta0)`` restarts the law's own state. ``hybrid`` says
    whether θ is a state of the law (it is linearised and logged as one); ``params`` is the
    `controller.LawParameters` the law runs with; ``name`` is what logs and summaries call it.
    Optional: ``write_wrench_into(buf)`` computes future wrenches straight into a plant's input
    buffer (N, 6).
    """

    name: str
    hybrid: bool
    params: LawParameters
    theta: np.ndarray
    theta_jump: np.ndarray
    mu: np.ndarray
    jumped: np.ndarray

    def step_state(self, S, h: float): ...

    def reset(self, theta0=None) -> None: ...


def hybrid(scenario) -> HybridController:
    """The paper's law with the scenario's design, gains and θ(0)."""
    return HybridController(scenario.graph, scenario.weighting, scenario.design, scenario.gains,
                            theta0=scenario.theta0)


def gradient(scenario) -> GradientController:
    """The gradient-only baseline with the scenario's gains."""
    return GradientController(scenario.graph, scenario.weighting, scenario.gains)


def law_names() -> tuple:
    return tuple(LAWS)


def make_controller(name: str, scenario) -> Controller:
    """A fresh controller of the law registered as ``name`` (`cosim.registry.LAWS`)."""
    return resolve(LAWS, name, "controller")(scenario)


def law_name(controller) -> str:
    """The name a controller instance reports in logs and summaries."""
    return getattr(controller, "name", type(controller).__name__)
