"""The worker side of `se3sync sweep`: the sample generator and one co-simulation per sample.

Everything here runs inside a Dask worker (or in-process) and imports neither Dask nor pyarrow.

A sweep is described by a picklable :class:`SweepSpec` that carries the scenario TEXT (not a
path: a remote worker need not share the file system), its overrides and the generator's
options. Samples are numbered 0, 1, 2, …:

* indices ``0 .. n_adv-1`` are the adversarial samples (``n_adv = 3M + 3`` for M edges), in
  this order: for every edge k = 1..M and every eigenvector e = 1..3 of W = A − bbᵀ/d (ascending
  eigenvalues), edge k on the undesired critical point X̄ = 𝒯(R_a(π, v_e), (I − R_a(π, v_e)) b/d)
  and every other edge at the identity ("adversarial-edge"); then, for e = 1..3, every edge on
  that critical point ("adversarial-all"). They come IN ADDITION to the K random samples;
* indices ``n_adv .. n_adv+K-1`` are random: R_i Haar-uniform on SO(3), p_i uniform in the box
  [−position_box, position_box]³, ξ_i uniform in the 6-ball of radius velocity_ball, θ(0) = 0.
  Sample i draws from ``numpy.random.default_rng(SeedSequence(seed, spawn_key=(i,)))``, so it
  does not depend on the executor, the chunking or the number of samples.

One sample is one run of `cosim.master.Master` (the only step loop), with its wall-clock budget
as the timeout and one plant per process reused across samples through ``Master.restart``
(for the FMU plant: fmi2Reset + parameters + initialise instead of a new instance, ≈ 5 ms saved
per sample). The plant is the registered one named by ``SweepSpec.plant`` (default "fleet"),
and it must be able to ``reset(S0)``; this module keeps only the sample generator and the row a
run records.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import time
from dataclasses import dataclass, field

import numpy as np

from controller import layout

from controller.errors import Se3SyncError

from ..controllers import make_controller
from ..registry import LAWS
from ..initial import critical_pose as _critical_pose
from ..initial import poses_from_relative, random_state
from ..master import Master
from ..plants import make_plant
from ..scenario import parse_scenario
from ..threads import SWEEP_WORKER_THREADS, blas_threads, chosen

__all__ = ["SweepSpec", "COLUMNS", "KINDS", "n_adversarial", "describe_sample",
           "initial_state", "critical_pose", "run_sample", "run_chunk", "error_row",
           "load_spec_scenario", "GENERATOR_VERSION"]

GENERATOR_VERSION = 1  # bump when the sample generator changes (resume refuses a mismatch)

KINDS = ("random", "adversarial-edge", "adversarial-all")

# column name -> type ("int", "float", "bool", "str"); the order of the output file
COLUMNS = {
    "sample": "int",          # sample index (adversarial first)
    "controller": "str",      # "hybrid" | "gradient"
    "kind": "str",            # "random" | "adversarial-edge" | "adversarial-all"
    "edge": "int",            # adversarial-edge: the edge k on the critical point (1-based); else 0
    "eigvec": "int",          # adversarial: eigenvector e of W (1..3, ascending eigenvalues); else 0
    "status": "str",          # "ok" | "error" | "timeout" | "diverged"
    "error": "str",           # one-line message ("" when ok)
    "converged": "bool",      # rot_err < rot_tol and pos_err < pos_tol at the end
    "t_converge": "float",    # first sample time after which both stay below (NaN if not converged)
    "n_jumps": "int",         # number of θ jumps (edge events) over the run
    "jump_bound": "int",      # ⌈V̄(0)/(k_X δ)⌉
    "V0": "float",            # V̄(0)
    "t_last_jump": "float",   # time of the last jump (NaN if none)
    "rot_err0": "float",      # max_k ‖I − R̄_k‖_F at t = 0
    "pos_err0": "float",      # max_k ‖p̄_k‖ at t = 0
    "u0_max": "float",        # max |u| at t = 0 (≈ 0 on a critical point for the gradient law)
    "rot_err": "float",       # final max_k ‖I − R̄_k‖_F
    "pos_err": "float",       # final max_k ‖p̄_k‖
    "xi_max": "float",        # final max |ξ|
    "theta_max": "float",     # final max |θ_k|
    "sim_time": "float",      # simulated time reached (the duration unless timeout/error)
    "steps": "int",           # communication steps done
    "wall_time": "float",     # wall-clock seconds of this sample (NOT deterministic)
}
NONDETERMINISTIC = ("wall_time",)


@dataclass(frozen=True)
class SweepSpec:
    """What defines a sweep's samples and how each is run (picklable, sent to the workers)."""

    scenario_text: str
    scenario_name: str = "scenario"
    scenario_path: str = "<string>"
    overrides: tuple = ()
    seed: int = 0
    n_random: int = 0
    position_box: float = 1.0
    velocity_ball: float = 0.5
    rot_tol: float = 1e-2
    pos_tol: float = 1e-2
    sample_dt: float = 0.1       # error samples for t_converge, in simulated seconds
    timeout: float | None = None  # wall-clock seconds per sample (cooperative), None: none
    plant: str = "fleet"         # the registered plant (cosim.registry.PLANTS) every sample runs on
    # Test-only fault injection: ((sample, controller or "*", "raise" | "hang" | "exit"), ...)
    faults: tuple = field(default=(), compare=False)

    def key_dict(self) -> dict:
        """Everything the result of a sample depends on (not K, the timeout or the faults)."""
        return {
            "generator_version": GENERATOR_VERSION,
            "scenario_sha256": hashlib.sha256(self.scenario_text.encode()).hexdigest(),
            "overrides": list(self.overrides),
            "seed": int(self.seed),
            "position_box": float(self.position_box),
            "velocity_ball": float(self.velocity_ball),
            "rot_tol": float(self.rot_tol),
            "pos_tol": float(self.pos_tol),
            "sample_dt": float(self.sample_dt),
            # the FMU plants give the same trajectories; another plant may not
            **({} if self.plant == "fleet" else {"plant": self.plant}),
        }

    def key(self) -> str:
        return hashlib.sha256(json.dumps(self.key_dict(), sort_keys=True).encode()).hexdigest()[:16]


# ----------------------------------------------------------------------------- scenario cache
_SCENARIOS: dict = {}


def load_spec_scenario(spec: SweepSpec):
    """The spec's Scenario, parsed once per process."""
    k = (spec.scenario_text, spec.scenario_name, spec.scenario_path, tuple(spec.overrides))
    sc = _SCENARIOS.get(k)
    if sc is None:
        sc = parse_scenario(spec.scenario_text, name=spec.scenario_name, path=spec.scenario_path,
                            overrides=spec.overrides)
        if len(_SCENARIOS) > 8:
            _SCENARIOS.clear()
        _SCENARIOS[k] = sc
    return sc


# ----------------------------------------------------------------------------- generator
def n_adversarial(scenario) -> int:
    return 3 * scenario.graph.M + 3


def describe_sample(scenario, index: int) -> tuple[str, int, int]:
    """(kind, edge, eigvec) of sample ``index``."""
    M = scenario.graph.M
    if index < 0:
        raise ValueError(f"sample index must be >= 0, got {index}")
    if index < 3 * M:
        return "adversarial-edge", index // 3 + 1, index % 3 + 1
    if index < 3 * M + 3:
        return "adversarial-all", 0, index - 3 * M + 1
    return "random", 0, 0


def critical_pose(scenario, eigvec: int) -> np.ndarray:
    """X̄ = 𝒯(R_a(π, v), (I − R_a(π, v)) b/d), v the unit eigenvector ``eigvec`` (1..3) of W."""
    return _critical_pose(scenario.weighting, eigvec)


def initial_state(scenario, spec: SweepSpec, index: int) -> np.ndarray:
    """S0 (N, 18) [p, R row-major, ξ] of sample ``index``."""
    N, M = scenario.graph.n, scenario.graph.M
    kind, edge, e = describe_sample(scenario, index)
    if kind == "random":
        rng = np.random.default_rng(np.random.SeedSequence(int(spec.seed), spawn_key=(int(index),)))
        return random_state(rng, N, spec.position_box, spec.velocity_ball)
    Xc = critical_pose(scenario, e)
    Xbar = np.tile(np.eye(4), (M, 1, 1))
    if kind == "adversarial-edge":
        Xbar[edge - 1] = Xc
    else:
        Xbar[:] = Xc
    return layout.pack_state(poses_from_relative(scenario.graph, Xbar))


# ----------------------------------------------------------------------------- plant reuse
_MASTERS: dict = {}


def _master(spec: SweepSpec, scenario, controller: str, S0) -> Master:
    """A Master over a reusable plant, one per process, scenario, plant and law, restarted at
    S0 with θ(0) = 0; not cached while in use, so a failure leaves no broken instance behind."""
    key = (id(scenario), spec.plant, controller, spec.sample_dt)
    m = _MASTERS.pop(key, None)
    if m is not None:
        try:
            m.restart(S0)
            return m
        except BaseException:
            m.plant.close()
            raise
    if len(_MASTERS) > 8:
        for old in _MASTERS.values():
            old.plant.close()
        _MASTERS.clear()
    plant = make_plant(spec.plant, dataclasses.replace(scenario, S0=S0))
    try:
        if not callable(getattr(plant, "reset", None)):
            raise Se3SyncError(f"sweep: the plant {spec.plant!r} cannot reset(S0), which a "
                               f"sweep needs to run many samples on one plant")
        ctrl = make_controller(controller, scenario)
        ctrl.reset(None)
        return Master(scenario, plant, ctrl, sample_dt=spec.sample_dt, S0=S0)
    except BaseException:
        plant.close()
        raise


class _Hanging:
    """Test-only fault: the plant of a hanging sample sleeps at every step."""

    def __init__(self, plant):
        self._plant = plant
        self.n = plant.n
        self.read, self.apply = plant.read, plant.apply

    def advance(self, h):
        time.sleep(0.002)
        self._plant.advance(h)


# ----------------------------------------------------------------------------- one sample
def error_row(spec: SweepSpec, scenario, index: int, controller: str, status: str,
              message: str, wall: float = float("nan")) -> dict:
    if scenario is not None:
        kind, edge, e = describe_sample(scenario, index)
    else:
        kind, edge, e = "", 0, 0
    row = {}
    for c, t in COLUMNS.items():
        row[c] = {"int": 0, "float": float("nan"), "bool": False, "str": ""}[t]
    row.update(sample=int(index), controller=controller, kind=kind, edge=edge, eigvec=e,
               status=status, error=" ".join(str(message).split())[:500], wall_time=wall,
               n_jumps=0, jump_bound=0, steps=0)
    return row


def run_sample(spec: SweepSpec, index: int, controller: str) -> dict:
    """Runs one sample with one controller; returns its row (never raises for a sample's
    own failure: status "error" or "timeout" with the message)."""
    t_wall = time.perf_counter()
    sc = None
    try:
        sc = load_spec_scenario(spec)
        return _run(spec, sc, index, controller, t_wall)
    except Exception as exc:
        return error_row(spec, sc, index, controller, "error", f"{type(exc).__name__}: {exc}",
                         time.perf_counter() - t_wall)


def _fault(spec, index, controller):
    for f in spec.faults:
        if int(f[0]) == index and f[1] in ("*", controller):
            return f[2]
    return None


def _run(spec: SweepSpec, sc, index: int, controller: str, t_wall: float) -> dict:
    kind, edge, e = describe_sample(sc, index)
    fault = _fault(spec, index, controller)
    if fault == "raise":
        raise RuntimeError(f"injected fault in sample {index}")
    if fault == "exit":  # kills the worker process (tests the executor's isolation)
        os._exit(3)
    if controller not in LAWS:
        raise ValueError(f"controller must be one of {', '.join(LAWS)}, got {controller!r}")
    S0 = initial_state(sc, spec, index)
    m = _master(spec, sc, controller, S0)
    plant = m.plant
    if fault == "hang":
        m.plant = _Hanging(plant)
    ok = False
    try:
        # The budget counts from the end of the first block: the one-time set-up of a fresh
        # worker (loading the compiled kernels and the FMU) is not held against a sample.
        summary = m.run(sc.n_steps(), budget=spec.timeout)
        ok = True
    finally:
        m.plant = plant
        if ok:
            _MASTERS[(id(sc), spec.plant, controller, spec.sample_dt)] = m
        else:
            plant.close()
    if summary["interrupted"]:
        raise KeyboardInterrupt
    h = m.h
    n = summary["steps"]
    final = summary["final"]
    series = list(m.samples)
    if not series or series[-1]["t"] != final["t"]:
        series.append(final)
    status, message = "ok", ""
    if summary.get("timed_out"):
        status = "timeout"
        message = f"wall-clock timeout of {spec.timeout:g} s after {n * h:.6g} s simulated"
    elif summary.get("diverged"):   # stopped by the master's guard (cosim.guards)
        status = "diverged"
        message = f"diverged at t = {summary['diverged']['t']:.6g} s: {summary['diverged']['reason']}"
    rf, pf, xf = final["rot_err"], final["pos_err"], final["xi_max"]
    rot0, pos0 = series[0]["rot_err"], series[0]["pos_err"]
    u0_max = float(np.abs(m.u0).max()) if m.u0 is not None else float("nan")
    converged = status == "ok" and rf < spec.rot_tol and pf < spec.pos_tol
    t_conv = float("nan")
    if converged:
        # earliest sample time from which every later sample (and the end) is below tolerance
        t_conv = series[-1]["t"]
        for smp in reversed(series):
            if smp["rot_err"] < spec.rot_tol and smp["pos_err"] < spec.pos_tol:
                t_conv = smp["t"]
            else:
                break
    theta_end = m.edge_state.theta
    M = sc.graph.M
    return {
        "sample": int(index), "controller": controller, "kind": kind, "edge": int(edge),
        "eigvec": int(e), "status": status, "error": message, "converged": bool(converged),
        "t_converge": float(t_conv), "n_jumps": int(m.n_jumps), "jump_bound": int(m.jump_bound),
        "V0": float(m.V0),
        "t_last_jump": float(m.last_jump["t"]) if m.last_jump else float("nan"),
        "rot_err0": float(rot0), "pos_err0": float(pos0), "u0_max": u0_max,
        "rot_err": float(rf), "pos_err": float(pf), "xi_max": float(xf),
        "theta_max": float(np.abs(theta_end).max()) if M else 0.0,
        "sim_time": float(n * h), "steps": int(n), "wall_time": time.perf_counter() - t_wall,
    }


def run_chunk(spec: SweepSpec, tasks) -> list[dict]:
    """Runs (sample, controller) pairs in order; one row each. BLAS runs on
    `cosim.threads.SWEEP_WORKER_THREADS` thread(s): the cores are shared by the workers."""
    with blas_threads(chosen(SWEEP_WORKER_THREADS)):
        return [run_sample(spec, int(i), str(c)) for i, c in tasks]


def with_faults(spec: SweepSpec, faults) -> SweepSpec:
    """A copy of the spec with test-only injected faults."""
    return dataclasses.replace(spec, faults=tuple(tuple(f) for f in faults))
