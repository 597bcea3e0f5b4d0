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

One sample runs the cosim master's step semantics in a small loop of its own (t = n·h; per
step S = read; u, ev = controller.step_state(S, h); apply u; do_step), because the sweep needs
two things `cosim.master.Master` has not: a cooperative wall-clock timeout, and one loaded FMU
reused across samples (fmi2Reset + parameters + initialise instead of a new instance: ≈ 5 ms
saved per sample). `tests/test_sweep_worker.py` checks the loop against `Master`.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from dataclasses import dataclass, field

import numpy as np

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
    "status": "str",          # "ok" | "error" | "timeout"
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
        from .scenario import parse_scenario

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
    from controller import se3

    w = scenario.weighting
    v = w.eig()[1][:, eigvec - 1]
    # R_a(π, v) = I + sin(π) v^× + 2 (v^×)² = 2vvᵀ − I, written without the rounding of sin(π)
    # ≈ 1.2e-16 (which the unstable critical point amplifies); se3.R_a(π, v) agrees to 1e-15.
    R = 2.0 * np.outer(v, v) - np.eye(3)
    return se3.T(R, (np.eye(3) - R) @ (w.b / w.d))


def _poses_from_relative(graph, Xbar) -> np.ndarray:
    """Absolute poses (N,4,4) with X_1 = I and X̄_k = X_j⁻¹ X_i on every edge k = (i, j),
    walking the tree from agent 1."""
    from controller import se3

    N = graph.n
    X = [None] * N
    X[0] = np.eye(4)
    adj = {a: [] for a in range(N)}
    for k, (i, j) in enumerate(graph.edges):
        adj[int(i)].append((int(j), k, True))    # i known -> X_j = X_i X̄_k⁻¹
        adj[int(j)].append((int(i), k, False))   # j known -> X_i = X_j X̄_k
    stack = [0]
    while stack:
        a = stack.pop()
        for b, k, a_is_pos in adj[a]:
            if X[b] is None:
                X[b] = X[a] @ se3.inverse(Xbar[k]) if a_is_pos else X[a] @ Xbar[k]
                stack.append(b)
    return np.stack(X)


def initial_state(scenario, spec: SweepSpec, index: int) -> np.ndarray:
    """S0 (N, 18) [p, R row-major, ξ] of sample ``index``."""
    from controller import se3

    N, M = scenario.graph.n, scenario.graph.M
    kind, edge, e = describe_sample(scenario, index)
    S0 = np.zeros((N, 18))
    if kind == "random":
        rng = np.random.default_rng(np.random.SeedSequence(int(spec.seed), spawn_key=(int(index),)))
        R = se3.random_rotation(rng, N)
        p = rng.uniform(-spec.position_box, spec.position_box, size=(N, 3))
        d = rng.standard_normal((N, 6))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        r = spec.velocity_ball * rng.uniform(0.0, 1.0, size=(N, 1)) ** (1.0 / 6.0)
        S0[:, 0:3] = p
        S0[:, 3:12] = R.reshape(N, 9)
        S0[:, 12:18] = d * r
        return S0
    Xc = critical_pose(scenario, e)
    Xbar = np.tile(np.eye(4), (M, 1, 1))
    if kind == "adversarial-edge":
        Xbar[edge - 1] = Xc
    else:
        Xbar[:] = Xc
    X = _poses_from_relative(scenario.graph, Xbar)
    S0[:, 0:3] = X[:, :3, 3]
    S0[:, 3:12] = X[:, :3, :3].reshape(N, 9)
    return S0


# ----------------------------------------------------------------------------- FMU reuse
_FMUS: dict = {}


def _plant(scenario, S0):
    """A FleetFMU(N) initialised at S0: one per process and N, reset between samples."""
    from plant_fmu.fast import FleetFMU

    n = scenario.graph.n
    fmu = _FMUS.get(n)
    if fmu is None:
        fmu = FleetFMU(n, instance_name="sweep")
    else:
        fmu.reset()
    _FMUS.pop(n, None)  # not cached while in use: a failure below leaves no broken instance
    try:
        fmu.set_parameters(mass=scenario.masses, J=scenario.inertias, p0=S0[:, 0:3],
                           R0=S0[:, 3:12].reshape(n, 3, 3), xi0=S0[:, 12:18],
                           gravity=scenario.gravity, h_internal=float(scenario.internal_step))
        fmu.initialize(0.0)
    except BaseException:
        fmu.close()
        raise
    return fmu


def _release(scenario, fmu, ok: bool) -> None:
    if ok:
        try:
            fmu.terminate()
            _FMUS[scenario.graph.n] = fmu
            return
        except Exception:
            pass
    fmu.close()


# ----------------------------------------------------------------------------- one sample
class _Timeout(Exception):
    pass


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
    except _Timeout as exc:  # pragma: no cover - _run records timeouts itself
        return error_row(spec, sc, index, controller, "timeout", str(exc),
                         time.perf_counter() - t_wall)
    except Exception as exc:
        return error_row(spec, sc, index, controller, "error", f"{type(exc).__name__}: {exc}",
                         time.perf_counter() - t_wall)


def _fault(spec, index, controller):
    for f in spec.faults:
        if int(f[0]) == index and f[1] in ("*", controller):
            return f[2]
    return None


def _run(spec: SweepSpec, sc, index: int, controller: str, t_wall: float) -> dict:
    from controller import GradientController, HybridController, V_bar, jump_bound

    from ._metrics import metrics

    kind, edge, e = describe_sample(sc, index)
    fault = _fault(spec, index, controller)
    if fault == "raise":
        raise RuntimeError(f"injected fault in sample {index}")
    if fault == "exit":  # kills the worker process (tests the executor's isolation)
        import os

        os._exit(3)
    S0 = initial_state(sc, spec, index)
    N, M = sc.graph.n, sc.graph.M
    if controller == "hybrid":
        ctrl = HybridController(sc.graph, sc.weighting, sc.design, sc.gains, theta0=np.zeros(M))
    elif controller == "gradient":
        ctrl = GradientController(sc.graph, sc.weighting, sc.gains)
    else:
        raise ValueError(f"controller must be \"hybrid\" or \"gradient\", got {controller!r}")
    V0 = V_bar(sc.graph, sc.weighting, sc.design, sc.gains, S0, np.zeros(M), sc.inertia6)
    bound = jump_bound(V0, sc.gains.k_X, sc.design.delta)

    edges = np.ascontiguousarray(sc.graph.edges)
    masses = np.ascontiguousarray(sc.masses, float)
    J = np.ascontiguousarray(sc.inertias, float)
    rot = np.zeros(M)
    pos = np.zeros(M)
    Ubuf = np.zeros(M)  # metrics() adds k_X ΣU to V̄, which the sweep does not use
    quat = np.zeros((N, 4))

    def errors(S):
        _, ximax = metrics(S, edges, Ubuf, 1.0, masses, J, rot, pos, quat)
        return float(rot.max()) if M else 0.0, float(pos.max()) if M else 0.0, float(ximax)

    h = float(sc.step)
    n_steps = sc.n_steps()
    spl = max(1, int(round(spec.sample_dt / h)))
    # The timeout counts from the end of the first block of steps: the one-time set-up of a
    # fresh worker (loading the compiled kernels and the FMU) is not held against a sample.
    deadline = None
    hang = fault == "hang"

    fmu = _plant(sc, S0)
    ok = False
    try:
        read, apply, do_step, step = fmu.get_state, fmu.set_input, fmu.do_step, ctrl.step_state
        times, rerr, perr = [], [], []
        n_jumps = 0
        t_last_jump = float("nan")
        u0_max = float("nan")
        status, message = "ok", ""
        n = 0
        while n < n_steps:
            # a sampling step: errors at t_n (before the step, as the master's ticks)
            S = read()
            u, ev = step(S, h)
            if ev:
                n_jumps += len(ev)
                t_last_jump = n * h
            r, p, _ = errors(S)
            if n == 0:
                u0_max = float(np.abs(u).max())
                rot0, pos0 = r, p
            times.append(n * h)
            rerr.append(r)
            perr.append(p)
            apply(u)
            do_step(n * h, h)
            n += 1
            nxt = min(n_steps, -(-n // spl) * spl)
            for k in range(n, nxt):
                S = read()
                u, ev = step(S, h)
                if ev:
                    n_jumps += len(ev)
                    t_last_jump = k * h
                apply(u)
                do_step(k * h, h)
            n = nxt
            if hang:
                time.sleep(0.02)
            if deadline is None and spec.timeout is not None:
                deadline = time.perf_counter() + float(spec.timeout)
            elif deadline is not None and time.perf_counter() > deadline:
                if n < n_steps:
                    status = "timeout"
                    message = (f"wall-clock timeout of {spec.timeout:g} s after {n * h:.6g} s "
                               f"simulated")
                break
        S = read()
        rf, pf, xf = errors(S)
        if n_steps == 0:
            rot0, pos0 = rf, pf
            u0_max = float("nan")
        times.append(n * h)
        rerr.append(rf)
        perr.append(pf)
        ok = True
    finally:
        _release(sc, fmu, ok)

    converged = status == "ok" and rf < spec.rot_tol and pf < spec.pos_tol
    t_conv = float("nan")
    if converged:
        # earliest sample time from which every later sample (and the end) is below tolerance
        t_conv = times[-1]
        for t, r, p in zip(reversed(times), reversed(rerr), reversed(perr)):
            if r < spec.rot_tol and p < spec.pos_tol:
                t_conv = t
            else:
                break
    theta_end = ctrl.theta if controller == "hybrid" else np.zeros(M)
    return {
        "sample": int(index), "controller": controller, "kind": kind, "edge": int(edge),
        "eigvec": int(e), "status": status, "error": message, "converged": bool(converged),
        "t_converge": float(t_conv), "n_jumps": int(n_jumps), "jump_bound": int(bound),
        "V0": float(V0), "t_last_jump": float(t_last_jump), "rot_err0": float(rot0),
        "pos_err0": float(pos0), "u0_max": float(u0_max), "rot_err": float(rf),
        "pos_err": float(pf), "xi_max": float(xf),
        "theta_max": float(np.abs(theta_end).max()) if M else 0.0,
        "sim_time": float(n * h), "steps": int(n), "wall_time": time.perf_counter() - t_wall,
    }


def run_chunk(spec: SweepSpec, tasks) -> list[dict]:
    """Runs (sample, controller) pairs in order; one row each."""
    return [run_sample(spec, int(i), str(c)) for i, c in tasks]


def with_faults(spec: SweepSpec, faults) -> SweepSpec:
    """A copy of the spec with test-only injected faults."""
    return dataclasses.replace(spec, faults=tuple(tuple(f) for f in faults))
