"""The slave module of the controller FMU (`se3sync fmu build --controller`): the network view of
the paper's law (`controller.HybridController`, or the gradient baseline) as an FMI 2.0
Co-Simulation slave, run by pythonfmu's binary inside the host's Python.

This file is copied into the FMU's resources as it is; the structure of the scenario it was built
for (N agents, the graph's edges, the size of Θ and every parameter's default, the scenario's
values) is the JSON file ``se3sync_law.json`` beside it. The host's Python must have se3sync
installed: the law is `controller.kernels.network_step`, the kernel `se3sync run` steps.

Semantics of a communication step [t_n, t_n + h] (`doStep`):

1. the state S(t_n) is the input ``body[i].p/R/xi`` (at the first step after initialisation the
   parameters ``body[i].p0/R0/xi0`` instead, the plant's state at the start time: a master that
   steps every FMU on the values of the previous communication point has no plant output yet,
   FMPy gives 0 there);
2. the law's step at t_n: every edge in its jump set jumps, the wrench u(t_n) is computed with
   the post-jump θ, θ flows over h (`controller.law`);
3. the outputs become u(t_n) (``body[i].u``), θ after the jump stage (``theta``), μ_U before it
   (``mu_U``), which edges jumped (``jumped``), the jump counts (``jumps``, ``n_jumps``).

Before the first step the outputs are u = 0 and θ(0). A master that exchanges values after every
FMU has stepped (FMPy's `simulate_ssp`, libcosim's fixed-step algorithm) therefore applies u(t_n)
to the plant over [t_{n+1}, t_{n+2}]: one communication step of computational delay
(docs/fmi-system.md).

Bad parameters (a non-positive gain, a weighting matrix outside the paper's conditions, …) are
refused in exitInitializationMode: an exception, which pythonfmu answers with fmi2Error and the
message logged.
"""
import json
import os

import numpy as np
from pythonfmu import Boolean, Fmi2Causality, Fmi2Initial, Fmi2Slave, Fmi2Variability, Integer, Real
from pythonfmu.default_experiment import DefaultExperiment

from controller import (Gains, GradientController, Graph, HybridController, SynergyDesign,
                        WeightingMatrix)

_P = Fmi2Causality.parameter
_IN = Fmi2Causality.input
_OUT = Fmi2Causality.output
_FIXED = Fmi2Variability.fixed
_DISCRETE = Fmi2Variability.discrete
_EXACT = Fmi2Initial.exact   # outputs have a defined value before the first step (u = 0, θ(0))


class Se3syncLaw(Fmi2Slave):

    author = "se3sync"
    description = ("Distributed hybrid feedback for pose synchronisation on SE(3) (network "
                   "view): state S in, body wrenches u, theta and the jumps out")

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        here = self.resources or os.path.dirname(os.path.abspath(__file__))
        with open(os.path.join(here, "se3sync_law.json"), encoding="utf-8") as f:
            spec = json.load(f)
        self.spec = spec
        ex = spec["experiment"]
        self.default_experiment = DefaultExperiment(start_time=ex["start"], stop_time=ex["stop"],
                                                    step_size=ex["step"])
        N, edges = int(spec["n"]), [tuple(e) for e in spec["edges"]]
        M, nT = len(edges), int(spec["n_theta"])
        self.N, self.M, self.edges = N, M, edges
        d = spec["defaults"]
        self.k_X, self.k_xi, self.k_e, self.k_theta = d["k_X"], d["k_xi"], d["k_e"], d["k_theta"]
        self.A = np.array(d["A"], float)
        self.b = np.array(d["b"], float)
        self.d = float(d["d"])
        self.u_c1 = np.array(d["u_c1"], float)
        self.u_c2 = np.array(d["u_c2"], float)
        self.Theta = np.array(d["Theta"], float)
        self.gamma, self.delta = float(d["gamma"]), float(d["delta"])
        self.hybrid = bool(d["hybrid"])
        self.theta0 = np.array(d["theta0"], float)
        self.S0 = np.array(d["S0"], float)
        self.S = self.S0.copy()
        self.u = np.zeros((N, 6))
        self.theta_out = self.theta0.copy()
        self.mu_out = np.zeros(M)
        self.jumped_out = np.zeros(M, bool)
        self.jump_counts = np.zeros(M, np.int64)
        self.law = None
        self.steps = 0

        def real(name, arr, idx, causality, description=None, variability=None):
            def get():
                return float(arr[idx])

            def put(v):
                arr[idx] = v

            self.register_variable(Real(name, causality=causality, variability=variability,
                                        initial=_EXACT if causality is _OUT else None,
                                        description=description, getter=get, setter=put))

        def scalar(name, attr, description):
            self.register_variable(Real(
                name, causality=_P, variability=_FIXED, description=description,
                getter=lambda: float(getattr(self, attr)),
                setter=lambda v: setattr(self, attr, float(v))))

        for attr, desc in (("k_X", "gain k_X of the potential term"),
                           ("k_xi", "gain k_xi of the damping term"),
                           ("k_e", "gain k_e of the velocity-coupling term"),
                           ("k_theta", "gain k_theta of theta's flow")):
            scalar(attr, attr, desc)
        for r in range(3):
            for c in range(3):
                real(f"A[{r + 1},{c + 1}]", self.A, (r, c), _P, variability=_FIXED,
                     description="block A of the weighting matrix")
        for k in range(3):
            real(f"b[{k + 1}]", self.b, k, _P, variability=_FIXED,
                 description="block b of the weighting matrix")
        scalar("d", "d", "block d of the weighting matrix")
        for k in range(3):
            real(f"u_c1[{k + 1}]", self.u_c1, k, _P, variability=_FIXED,
                 description="synergy design u_c1")
        for k in range(3):
            real(f"u_c2[{k + 1}]", self.u_c2, k, _P, variability=_FIXED,
                 description="synergy design u_c2")
        for j in range(nT):
            real(f"Theta[{j + 1}]", self.Theta, j, _P, variability=_FIXED,
                 description="the set Theta (rad)")
        scalar("gamma", "gamma", "synergy design gamma")
        scalar("delta", "delta", "synergy design delta (jump threshold on mu_U)")
        self.register_variable(Boolean(
            "hybrid", causality=_P, variability=_FIXED,
            description="true: the hybrid law; false: the gradient baseline (theta = 0, no jumps)",
            getter=lambda: self.hybrid, setter=lambda v: setattr(self, "hybrid", bool(v))))
        for k in range(M):
            real(f"theta0[{k + 1}]", self.theta0, k, _P, variability=_FIXED,
                 description=f"theta_{k + 1}(0) (rad)")
        for i in range(N):
            for k in range(3):
                real(f"body[{i + 1}].p0[{k + 1}]", self.S0, (i, k), _P, variability=_FIXED,
                     description="the plant's position at the start time (m)")
            for r in range(3):
                for c in range(3):
                    real(f"body[{i + 1}].R0[{r + 1},{c + 1}]", self.S0, (i, 3 + 3 * r + c), _P,
                         variability=_FIXED, description="the plant's rotation at the start time")
            for k in range(6):
                real(f"body[{i + 1}].xi0[{k + 1}]", self.S0, (i, 12 + k), _P,
                     variability=_FIXED, description="the plant's body velocity at the start time")
        for i in range(N):
            for k in range(3):
                real(f"body[{i + 1}].p[{k + 1}]", self.S, (i, k), _IN,
                     description="position, world frame (m)")
            for r in range(3):
                for c in range(3):
                    real(f"body[{i + 1}].R[{r + 1},{c + 1}]", self.S, (i, 3 + 3 * r + c), _IN,
                         description="rotation matrix body to world, row-major")
            for k in range(6):
                real(f"body[{i + 1}].xi[{k + 1}]", self.S, (i, 12 + k), _IN,
                     description="body velocity [omega; v] (rad/s, m/s)")
        for i in range(N):
            for k in range(6):
                real(f"body[{i + 1}].u[{k + 1}]", self.u, (i, k), _OUT, variability=_DISCRETE,
                     description="body wrench [torque; force] (N.m, N)")
        for k in range(M):
            real(f"theta[{k + 1}]", self.theta_out, k, _OUT, variability=_DISCRETE,
                 description=f"theta_{k + 1} after the jump stage (rad)")
        for k in range(M):
            real(f"mu_U[{k + 1}]", self.mu_out, k, _OUT, variability=_DISCRETE,
                 description=f"mu_U of edge {k + 1} before the jump stage")
        for k in range(M):
            self.register_variable(Boolean(
                f"jumped[{k + 1}]", causality=_OUT, variability=_DISCRETE, initial=_EXACT,
                description=f"edge {k + 1} jumped at the last communication point",
                getter=(lambda k=k: bool(self.jumped_out[k]))))
        for k in range(M):
            self.register_variable(Integer(
                f"jumps[{k + 1}]", causality=_OUT, variability=_DISCRETE, initial=_EXACT,
                description=f"jumps of edge {k + 1} so far",
                getter=(lambda k=k: int(self.jump_counts[k]))))
        self.register_variable(Integer(
            "n_jumps", causality=_OUT, variability=_DISCRETE, initial=_EXACT,
            description="jumps so far",
            getter=lambda: int(self.jump_counts.sum())))

    def exit_initialization_mode(self):
        wm = WeightingMatrix.from_blocks(self.A, self.b, self.d)
        gains = Gains(float(self.k_X), float(self.k_xi), float(self.k_e), float(self.k_theta))
        graph = Graph(self.N, self.edges)
        if self.hybrid:
            # only u_c1, u_c2, Θ, γ and δ enter the law (LawParameters); the rest describes
            # how Lemma 2 found them
            nan = float("nan")
            design = SynergyDesign(case=0, eigvals=(nan, nan, nan), u_c1=self.u_c1.copy(),
                                   u_c2=self.u_c2.copy(), Theta=tuple(self.Theta.tolist()),
                                   gamma=float(self.gamma), delta=float(self.delta),
                                   delta_star=nan, gamma_bound=nan, delta_bound=nan,
                                   exact_gap=nan)
            self.law = HybridController(graph, wm, design, gains, theta0=self.theta0.copy())
        else:
            self.law = GradientController(graph, wm, gains)
        self.theta_out[:] = self.law.theta
        self.steps = 0

    def do_step(self, current_time, step_size):
        law = self.law
        S = self.S0 if self.steps == 0 else self.S
        u, events = law.step_state(np.ascontiguousarray(S), float(step_size))
        self.u[...] = u
        self.theta_out[:] = law.theta_jump
        self.mu_out[:] = law.mu
        self.jumped_out[:] = law.jumped
        self.jump_counts += law.jumped
        self.steps += 1
        return True
