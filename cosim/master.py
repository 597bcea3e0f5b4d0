"""The co-simulation master: fixed communication step h, zero-order hold, t = n·h.

Per step n (the hot path, no allocation, no attribute lookups that can be hoisted):
    S = plant.read(); u, events = controller.step_state(S, h); plant.apply(u); plant.advance(h)
The loop runs in blocks between "ticks" (log records at log_rate, summary samples every 1 s of
simulated time, and at least every 1000 steps a check for Ctrl-C and the progress bar), so the
inner loop has no logging test at all; jump events are handled the step they happen.
"""
from __future__ import annotations

import signal
import threading
import time

import numpy as np

from controller import _kernels as K

__all__ = ["Master", "make_controller"]

MAX_BLOCK = 1000  # steps between two checks for Ctrl-C / progress updates


def make_controller(kind, scenario):
    from controller import GradientController, HybridController
    from controller.errors import Se3SyncError

    if kind == "hybrid":
        return HybridController(scenario.graph, scenario.weighting, scenario.design,
                                scenario.gains, theta0=scenario.theta0)
    if kind == "gradient":
        return GradientController(scenario.graph, scenario.weighting, scenario.gains)
    raise Se3SyncError(f"controller must be \"hybrid\" or \"gradient\", got {kind!r}")


class Master:
    """``Master(scenario, plant, controller, logger=None)``: plant a Plant, controller a
    HybridController/GradientController (or "hybrid"/"gradient"), logger an McapLogger or
    None. ``run(n_steps, progress=False) -> dict`` (the summary, without file names)."""

    use_compiled = True  # False forces the Python reference loop (tests compare the two)

    def __init__(self, scenario, plant, controller, logger=None):
        from controller import V_bar, jump_bound

        self.scenario = sc = scenario
        self.plant = plant
        if isinstance(controller, str):
            self.controller_kind = controller
            controller = make_controller(controller, scenario)
        else:
            self.controller_kind = "hybrid" if getattr(controller, "hybrid", True) else "gradient"
        self.controller = controller
        buf = getattr(plant, "input_buffer", None)
        if buf is not None and hasattr(controller, "write_wrench_into"):
            controller.write_wrench_into(buf)
        self.logger = logger
        self.h = float(sc.step)
        N, M = sc.graph.n, sc.graph.M
        self.N, self.M = N, M
        self.edges = np.ascontiguousarray(sc.graph.edges)
        # parameter vector for U in the metrics (the hybrid design even for the gradient run)
        self._P = K.pack(sc.weighting.A, sc.weighting.b, sc.weighting.d, sc.design.u_c1,
                         sc.design.u_c2, sc.design.gamma, sc.design.delta, sc.design.Theta,
                         sc.gains.k_X, sc.gains.k_xi, sc.gains.k_e, sc.gains.k_theta)
        self._kX = float(sc.gains.k_X)
        self._masses = np.ascontiguousarray(sc.masses, float)
        self._J = np.ascontiguousarray(sc.inertias, float)
        self._rot = np.zeros(M)
        self._pos = np.zeros(M)
        self._U = np.zeros(M)
        self._quat = np.zeros((N, 4))
        self._zeros_M = np.zeros(M)
        self._false_M = np.zeros(M, dtype=np.bool_)
        self.jumps = []
        self.samples = []
        self.link_samples = 0
        self._stop = False
        theta_init = (np.asarray(sc.theta0, float) if self.controller_kind == "hybrid"
                      else np.zeros(M))
        self.V0 = V_bar(sc.graph, sc.weighting, sc.design, sc.gains, sc.S0, theta_init,
                        sc.inertia6)
        self.jump_bound = jump_bound(self.V0, sc.gains.k_X, sc.design.delta)
        self.n_done = 0

    # -------------------------------------------------------------- slow path
    def _metrics(self, S, theta):
        from ._metrics import metrics

        K.network_U(S, theta, self.edges, self._P, self._U)
        V, ximax = metrics(S, self.edges, self._U, self._kX, self._masses, self._J, self._rot,
                           self._pos, self._quat)
        return V, ximax

    def _on_jumps(self, n, events):
        t = n * self.h
        t_ns = round(t * 1e9)
        for e in events:
            self.jumps.append({"t": t, "edge": e.edge, "theta_before": e.theta_before,
                               "theta_after": e.theta_after, "mu": e.mu})
            if self.logger is not None:
                self.logger.jump(t_ns, t, e.edge, e.theta_before, e.theta_after, e.mu)

    def _sample(self, t, S, theta):
        V, ximax = self._metrics(S, theta)
        self.samples.append({
            "t": t,
            "rot_err": float(self._rot.max()) if self.M else 0.0,
            "pos_err": float(self._pos.max()) if self.M else 0.0,
            "xi_max": float(ximax),
            "theta": theta.tolist(),
            "V": float(V),
        })

    def _tick(self, n, S, u, do_log, do_sample):
        ctrl = self.controller
        hybrid = self.controller_kind == "hybrid"
        theta = ctrl.theta_jump if hybrid else self._zeros_M  # θ at t_n after the jump stage
        t = n * self.h
        if do_sample:
            self._sample(t, S, theta)
            stats = getattr(self.plant, "stats", None)
            if stats is not None and self.logger is not None:
                self.logger.link_stats(round(t * 1e9), stats())
                self.link_samples += 1
        if do_log and self.logger is not None:
            V, _ = self._metrics(S, theta)
            kxu = float(self._P[K.P_KX] * self._U.sum())
            self.logger.record(round(t * 1e9), S, u, theta, ctrl.mu if hybrid else self._zeros_M,
                               ctrl.jumped if hybrid else self._false_M, self._rot, self._pos,
                               self._U, self._quat, float(V), kxu)

    def _on_sigint(self, signum, frame):
        if self._stop:  # a second Ctrl-C: stop right now
            raise KeyboardInterrupt
        self._stop = True

    # -------------------------------------------------------------- the loop
    def run(self, n_steps: int, progress: bool = False) -> dict:
        n_steps = int(n_steps)
        h = self.h
        plant, ctrl = self.plant, self.controller
        read, apply, advance, step = plant.read, plant.apply, plant.advance, ctrl.step_state
        on_jumps = self._on_jumps
        logging = self.logger is not None
        dec = max(1, int(round(1.0 / (self.scenario.log_rate * h)))) if logging else 0
        spl = max(1, int(round(1.0 / h)))  # summary sample every 1 s of simulated time
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=n_steps, unit="step", unit_scale=True, mininterval=0.5,
                       desc=self.scenario.name)
        old_handler = None
        if threading.current_thread() is threading.main_thread():
            try:
                old_handler = signal.signal(signal.SIGINT, self._on_sigint)
            except ValueError:  # pragma: no cover
                old_handler = None
        interrupted = False
        broken = False
        n = 0
        t0 = time.perf_counter()
        fleet = None
        if self.use_compiled:
            from .fastloop import compiled_fleet

            fleet = compiled_fleet(plant, ctrl)
        try:
            if fleet is not None:
                # the plant and controller support the compiled loop (cosim/fastloop.py): the
                # same steps, ticks and events, blocks of steps without returning to Python
                from .fastloop import run_compiled

                n, interrupted = run_compiled(self, fleet, n_steps, bar, spl, dec)
            # else: the reference loop in Python
            while fleet is None and n < n_steps:
                # tick step: a full step with the slow-path work
                S = read()
                u, ev = step(S, h)
                if ev:
                    on_jumps(n, ev)
                do_log = logging and n % dec == 0
                do_sample = n % spl == 0
                if do_log or do_sample:
                    self._tick(n, S, u, do_log, do_sample)
                apply(u)
                advance(h)
                n += 1
                if self._stop:
                    interrupted = True
                    break
                # the next tick
                nxt = min(n_steps, n + MAX_BLOCK, -(-n // spl) * spl)
                if logging:
                    nxt = min(nxt, -(-n // dec) * dec)
                if bar is not None:
                    bar.update(n - bar.n)
                # hot loop up to the next tick
                for k in range(n, nxt):
                    S = read()
                    u, ev = step(S, h)
                    if ev:
                        on_jumps(k, ev)
                    apply(u)
                    advance(h)
                n = nxt
        except KeyboardInterrupt:
            interrupted = True
            broken = True  # the plant may be mid-step: do not read it again
        finally:
            if old_handler is not None:
                signal.signal(signal.SIGINT, old_handler)
            if bar is not None:
                bar.update(n - bar.n)
                bar.close()
        wall = time.perf_counter() - t0
        self.n_done = n
        return self._summary(n, wall, interrupted, broken)

    def _summary(self, n, wall, interrupted, broken=False) -> dict:
        sc = self.scenario
        h = self.h
        t_end = n * h
        S = self.plant.read() if not broken else None
        theta_end = (self.controller.theta.copy() if self.controller_kind == "hybrid"
                     else self._zeros_M)
        final = None
        if S is not None:
            V, ximax = self._metrics(S, theta_end)
            final = {"t": t_end, "rot_err": float(self._rot.max()) if self.M else 0.0,
                     "pos_err": float(self._pos.max()) if self.M else 0.0,
                     "xi_max": float(ximax), "theta": theta_end.tolist(), "V": float(V)}
            spl = max(1, int(round(1.0 / h)))
            if n > 0 and n % spl == 0:
                self.samples.append(dict(final))
        elif self.samples:
            final = dict(self.samples[-1])
        d = sc.design.as_dict()
        design = {k: d[k] for k in ("case", "u_c1", "u_c2", "delta_star", "gamma", "delta",
                                    "gamma_bound", "delta_bound", "exact_gap", "warnings",
                                    "Theta", "eigenvalues_W")}
        out = {
            "scenario": sc.name,
            "scenario_path": str(sc.path),
            "controller": self.controller_kind,
            "step": h,
            "steps": n,
            "sim_time_s": t_end,
            "wall_time_s": wall,
            "realtime_factor": (t_end / wall) if wall > 0 else None,
            "us_per_step": (wall / n * 1e6) if n else None,
            "interrupted": bool(interrupted),
            "design": design,
            "V0": self.V0,
            "jump_bound": self.jump_bound,
            "n_jumps": len(self.jumps),
            "jumps": self.jumps,
            "final": final,
            "samples": self.samples,
        }
        stats = getattr(self.plant, "stats", None)
        if stats is not None:
            try:
                out["link"] = stats()
            except Exception as exc:  # pragma: no cover
                out["link"] = {"error": str(exc)}
        return out
