"""The co-simulation master: fixed communication step h, zero-order hold, t = n·h.

Per step n (the hot path, no allocation, no attribute lookups that can be hoisted):
    S = plant.read(); u, events = controller.step_state(S, h); plant.apply(u); plant.advance(h)
The loop runs in blocks between "ticks" (log records at log_rate, summary samples every
``sample_dt`` of simulated time, and at least every 1000 steps a check for Ctrl-C, the wall-clock
budget and the progress bar), so the inner loop has no logging test at all; jump events are
handled the step they happen.

This is the only step loop in se3sync: `run`, `connect` and the sweeps all drive it.
"""
from __future__ import annotations

import time

import numpy as np

from controller import LawParameters, V_bar, jump_bound
from controller.errors import Se3SyncError
from controller.kernels import metrics, network_U

from . import guards, signals
from .controllers import edge_state_of, law_name, make_controller
from .scenario import design_summary

__all__ = ["Master", "NetworkMetrics", "make_controller", "design_summary"]


class NetworkMetrics:
    """The network's errors at one instant, as the summary and the log report them: per edge
    ‖I − R̄_k‖_F (``rot``), ‖p̄_k‖ (``pos``) and U(X̄_k, θ_k) (``U``), the agents' quaternions
    (``quat``, x y z w), V̄ and max|ξ|. U uses the scenario's hybrid design whatever the law.
    The arrays are reused by every call."""

    def __init__(self, scenario):
        sc = scenario
        N, M = sc.graph.n, sc.graph.M
        self.M = M
        self.edges = np.ascontiguousarray(sc.graph.edges)
        self.P = LawParameters.of(sc.weighting, sc.design, sc.gains).P
        self.kX = float(sc.gains.k_X)
        self.masses = np.ascontiguousarray(sc.masses, float)
        self.J = np.ascontiguousarray(sc.inertias, float)
        self.rot = np.zeros(M)
        self.pos = np.zeros(M)
        self.U = np.zeros(M)
        self.quat = np.zeros((N, 4))

    def compute(self, S, theta) -> tuple:
        """(V̄, max|ξ|) at state S (N, 18) and θ (M,); fills rot, pos, U and quat."""
        network_U(S, theta, self.edges, self.P, self.U)
        return metrics(S, self.edges, self.U, self.kX, self.masses, self.J, self.rot, self.pos,
                       self.quat)

    def sample(self, t: float, S, theta) -> dict:
        """The summary's record {t, rot_err, pos_err, xi_max, theta, V}."""
        V, ximax = self.compute(S, theta)
        return self.record(t, float(self.rot.max()) if self.M else 0.0,
                           float(self.pos.max()) if self.M else 0.0, float(ximax), theta, float(V))

    @staticmethod
    def record(t, rot_err, pos_err, xi_max, theta, V) -> dict:
        """One summary sample, as `sample` and the compiled loop's samples write it."""
        return {"t": t, "rot_err": rot_err, "pos_err": pos_err, "xi_max": xi_max,
                "theta": np.asarray(theta).tolist(), "V": V}


class Master:
    """``Master(scenario, plant, controller, logger=None, sample_dt=1.0)``: plant a
    `cosim.plants.Plant`, controller a `cosim.controllers.Controller` (or a registered law name;
    its θ-like state, if it has one, is logged and summarised, else θ ≡ 0),
    logger an McapLogger or None. ``run(n_steps, progress=False, budget=None) -> dict`` (the
    summary, without file names); ``budget`` is a wall-clock limit in seconds, counted from the
    end of the first block (one-time set-up is not held against a run), after which the run stops
    with ``"timed_out": true``. ``restart(S0)`` starts again from another initial state with a
    plant that can ``reset`` (sweeps reuse one plant and master for many samples).

    Guards (`cosim.guards`, docs/run-guards.md): a summary sample that shows the run diverged
    (non-finite, V̄ past `guards.DIVERGE_FACTOR` × V̄(0), |ξ| past `guards.XI_LIMIT`), or a plant
    that fails with a non-finite state or wrench, ends the run early with ``"diverged"`` (t,
    step, reason) in the summary instead of an error; the summary keeps at most
    `guards.MAX_SAMPLES` samples (thinned evenly) and lists the first `guards.MAX_JUMPS` jumps
    (``n_jumps`` counts them all; ``jump_bound_exceeded`` compares it with the bound).

    ``first_step`` places step 0 of this run at step n₀ of a longer timeline (an agent process
    that joins a running swarm): times in the log, the jumps and the summary are (n₀ + n)·h. The
    log and sample ticks stay at multiples of their periods from step 0 of this run, so n₀
    should be a multiple of them for the ticks to fall on the timeline's.

    The master counts the steps of its run (n, its ticks and times); the plant owns its own
    clock (`cosim.plants`), which the master never reads or writes.
    """

    use_compiled = True  # False forces the Python reference loop (tests compare the two)

    def __init__(self, scenario, plant, controller, logger=None, sample_dt: float = 1.0,
                 S0=None, first_step: int = 0):
        self.scenario = sc = scenario
        self.plant = plant
        if isinstance(controller, str):
            controller = make_controller(controller, scenario)
        self.controller = controller
        self.controller_kind = law_name(controller)
        buf = getattr(plant, "input_buffer", None)
        if buf is not None and hasattr(controller, "write_wrench_into"):
            controller.write_wrench_into(buf)
        self.logger = logger
        self.h = float(sc.step)
        self.first_step = int(first_step)
        self.sample_dt = float(sample_dt)
        N, M = sc.graph.n, sc.graph.M
        self.N, self.M = N, M
        self.edges = np.ascontiguousarray(sc.graph.edges)
        self.metrics = NetworkMetrics(sc)
        self.edge_state = edge_state_of(controller, M)
        self._stop = False
        self._start(sc.S0 if S0 is None else np.asarray(S0, float))

    def _start(self, S0) -> None:
        sc = self.scenario
        self.jumps = []          # the first guards.MAX_JUMPS jumps (add_jump)
        self.n_jumps = 0
        self.last_jump = None
        self.samples = []        # every `_smp_stride`-th sample, at most guards.MAX_SAMPLES
        self._smp_seen = 0
        self._smp_stride = 1
        self.diverged = None     # {"t", "step", "reason"} once the run has diverged
        self._plant_broken = False
        self.link_samples = 0
        self.u0 = None
        self.n_done = 0
        self.V0 = V_bar(sc.graph, sc.weighting, sc.design, sc.gains, S0, self.edge_state.theta,
                        sc.inertia6)
        self.jump_bound = jump_bound(self.V0, sc.gains.k_X, sc.design.delta)
        self.V_limit = guards.V_limit(self.V0, sc.gravity)

    def restart(self, S0, theta0=None) -> None:
        """Start again at t = 0 from S0 (and θ(0) = theta0, zeros if None); the plant must
        implement ``reset(S0)``."""
        self.plant.reset(S0)
        self.controller.reset(theta0)
        self._stop = False
        self._start(np.asarray(S0, float))

    # -------------------------------------------------------------- slow path
    def _metrics(self, S, theta):
        return self.metrics.compute(S, theta)

    def add_jump(self, rec: dict) -> None:
        """One jump {t, edge, theta_before, theta_after, mu}, in time order (both loops)."""
        self.n_jumps += 1
        self.last_jump = rec
        if len(self.jumps) < guards.MAX_JUMPS:
            self.jumps.append(rec)

    def add_sample(self, rec: dict) -> None:
        """One summary sample, in time order (both loops): kept if it falls on the current
        stride (halved evenly past guards.MAX_SAMPLES), and checked for divergence."""
        k = self._smp_seen
        self._smp_seen = k + 1
        if k % self._smp_stride == 0:
            self.samples.append(rec)
            if len(self.samples) > guards.MAX_SAMPLES:
                del self.samples[1::2]
                self._smp_stride *= 2
        if self.diverged is None:
            why = guards.sample_divergence(rec, self.V_limit)
            if why is not None:
                self.diverged = {"t": rec["t"], "step": round(rec["t"] / self.h), "reason": why}

    def plant_failed(self, n: int, u, exc: Exception) -> bool:
        """A plant error at step n (of this run) is the run's divergence when the wrench it was
        given or its state is no longer finite: recorded (True) rather than raised."""
        bad_u = u is not None and not np.isfinite(u).all()
        try:
            bad_S = not np.isfinite(self.plant.read()).all()
        except Exception:  # noqa: BLE001 - a plant that cannot even be read: a plain error
            bad_S = False
        if not (bad_u or bad_S):
            return False
        what = "the wrench" if bad_u else "the plant's state"
        msgs = getattr(exc, "messages", None)
        detail = (f"{exc.function}: {msgs[0]}" + (f" (+{len(msgs) - 1} more)" if len(msgs) > 1
                                                 else "")
                  if msgs and getattr(exc, "function", None) else str(exc))
        step = self.first_step + n
        if self.diverged is None:   # else a sample before it showed it first (the compiled
            # loop runs on to the end of the block holding that sample, and may fail there)
            self.diverged = {"t": step * self.h, "step": step,
                             "reason": f"{what} is no longer finite "
                                       f"({' '.join(detail.split())[:200]})"}
        self._plant_broken = True
        return True

    def _on_jumps(self, n, events):
        t = (self.first_step + n) * self.h
        t_ns = round(t * 1e9)
        for e in events:
            self.add_jump({"t": t, "edge": e.edge, "theta_before": e.theta_before,
                           "theta_after": e.theta_after, "mu": e.mu})
            if self.logger is not None:
                self.logger.jump(t_ns, t, e.edge, e.theta_before, e.theta_after, e.mu)

    def _sample(self, t, S, theta):
        self.add_sample(self.metrics.sample(t, S, theta))

    def _tick(self, n, S, u, do_log, do_sample):
        es = self.edge_state
        theta = es.theta_jump  # θ at t_n after the jump stage
        t = (self.first_step + n) * self.h
        if n == 0:
            self.u0 = np.array(u, copy=True)
        if do_sample:
            self._sample(t, S, theta)
            stats = getattr(self.plant, "stats", None)
            if stats is not None and self.logger is not None:
                self.logger.link_stats(round(t * 1e9), stats())
                self.link_samples += 1
        if do_log and self.logger is not None:
            V, _ = self._metrics(S, theta)
            mx = self.metrics
            kxu = float(mx.kX * mx.U.sum())
            self.logger.record(round(t * 1e9), S, u, theta, es.mu, es.jumped, mx.rot, mx.pos,
                               mx.U, mx.quat, float(V), kxu)

    def request_stop(self) -> None:
        """Stop the run at the next check (between two blocks), as Ctrl-C does."""
        self._stop = True

    @property
    def stop_requested(self) -> bool:
        """A stop was asked for (`request_stop`, Ctrl-C, SIGTERM) and the run has not ended."""
        return self._stop

    def _on_signal(self):
        if self._stop:  # a second Ctrl-C or SIGTERM: stop right now
            raise KeyboardInterrupt
        self._stop = True

    # -------------------------------------------------------------- the loop
    def run(self, n_steps: int, progress: bool = False, budget: float | None = None) -> dict:
        """Runs ``n_steps`` steps (fewer if stopped, diverged or out of ``budget`` seconds of
        wall time) and returns the summary."""
        steps = self.steps(n_steps, progress, budget)
        try:
            while True:
                next(steps)
        except StopIteration as done:
            return done.value

    def steps(self, n_steps: int, progress: bool = False, budget: float | None = None):
        """`run` one step at a time: a generator that yields after each step's
        ``plant.advance`` and returns the summary. A process stepping several master loops
        from one thread drives them this way (`bridge.swarm.host`); `run` drives one."""
        n_steps = int(n_steps)
        h = self.h
        plant, ctrl = self.plant, self.controller
        read, apply, advance, step = plant.read, plant.apply, plant.advance, ctrl.step_state
        on_jumps = self._on_jumps
        logging = self.logger is not None
        dec = max(1, int(round(1.0 / (self.scenario.log_rate * h)))) if logging else 0
        spl = self._sample_every()
        bar = None
        if progress:
            from tqdm import tqdm      # only a run with a bar pays its import (7 ms)
            bar = tqdm(total=n_steps, unit="step", unit_scale=True, mininterval=0.5,
                       desc=self.scenario.name)
        catcher = signals.catching(self._on_signal).__enter__()
        if signals.pending():  # a signal arrived before the loop (and may have been swallowed)
            self._stop = True
        # a plant paced by the wall clock says how many steps it may run between two checks
        # for Ctrl-C (MavlinkPlant: ~0.1 s of steps), so a stop never waits for 1000 periods
        block = max(1, min(signals.MAX_BLOCK, int(getattr(plant, "max_block", signals.MAX_BLOCK))))
        interrupted = False
        broken = False
        timed_out = False
        deadline = None
        n = k = 0
        u = None
        t0 = time.perf_counter()
        fleet = None
        if (self.use_compiled and self.first_step == 0
                and getattr(plant, "compiled_plant", None) is not None):
            # imported only here: a process whose plant has no compiled loop (an agent's, on a
            # vehicle) runs without numba (controller.jit.use_aot)
            from .fastloop import compiled_pair, run_compiled
            fleet = compiled_pair(plant, ctrl)
        try:
            if fleet is not None:
                # the plant and controller support the compiled loop (cosim/fastloop.py): the
                # same steps, ticks and events, blocks of steps without returning to Python
                n, interrupted, timed_out = run_compiled(self, *fleet, n_steps, bar, spl, dec,
                                                         budget)
            # else: the reference loop in Python
            while fleet is None and n < n_steps and not self._stop:
                # tick step: a full step with the slow-path work
                k = n
                S = read()
                u, ev = step(S, h)
                if ev:
                    on_jumps(n, ev)
                do_log = logging and n % dec == 0
                do_sample = n % spl == 0
                if do_log or do_sample:
                    self._tick(n, S, u, do_log, do_sample)
                    if self.diverged is not None:
                        break
                apply(u)
                advance(h)
                yield
                n += 1
                if self._stop:
                    interrupted = True
                    break
                # the next tick
                nxt = min(n_steps, n + block, -(-n // spl) * spl)
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
                    yield
                n = nxt
                if budget is not None:
                    now = time.perf_counter()
                    if deadline is None:
                        deadline = now + float(budget)
                    elif now > deadline and n < n_steps:
                        timed_out = True
                        break
        except KeyboardInterrupt:
            interrupted = True
            broken = True  # the plant may be mid-step: do not read it again
        except Se3SyncError as exc:   # the Python loop's plant (or controller) failed at step k
            if fleet is not None or not self.plant_failed(k, u, exc):
                raise
            n = k
        finally:
            catcher.__exit__()
            if bar is not None:
                bar.update(n - bar.n)
                bar.close()
        wall = time.perf_counter() - t0
        broken = broken or self._plant_broken
        interrupted = interrupted or (self._stop and n < n_steps)
        self.n_done = n
        return self._summary(n, wall, interrupted, broken, timed_out)

    def _sample_every(self) -> int:
        return max(1, int(round(self.sample_dt / self.h)))

    def _summary(self, n, wall, interrupted, broken=False, timed_out=False) -> dict:
        sc = self.scenario
        h = self.h
        t_end = (self.first_step + n) * h
        S = self.plant.read() if not broken else None
        theta_end = self.edge_state.theta.copy()
        final = None
        if S is not None:
            final = self.metrics.sample(t_end, S, theta_end)
            if n > 0 and n % self._sample_every() == 0 and self.diverged is None:
                self.add_sample(dict(final))
        elif self.samples:
            final = dict(self.samples[-1])
        design = design_summary(sc)
        out = {
            "scenario": sc.name,
            "scenario_path": str(sc.path),
            "controller": self.controller_kind,
            "step": h,
            "steps": n,
            **({"first_step": self.first_step} if self.first_step else {}),
            "sim_time_s": n * h,
            "wall_time_s": wall,
            "realtime_factor": (n * h / wall) if wall > 0 else None,
            "us_per_step": (wall / n * 1e6) if n else None,
            "interrupted": bool(interrupted),
            **({"timed_out": True} if timed_out else {}),
            "design": design,
            "V0": self.V0,
            "jump_bound": self.jump_bound,
            "n_jumps": self.n_jumps,
            "jump_bound_exceeded": self.n_jumps > self.jump_bound,
            "diverged": self.diverged,
            "jumps": self.jumps,
            **({"jumps_listed": len(self.jumps)} if len(self.jumps) < self.n_jumps else {}),
            "final": final,
            "samples": self.samples,
            **({"sample_every_s": self._sample_every() * self._smp_stride * h}
               if self._smp_stride > 1 else {}),
        }
        stats = getattr(self.plant, "stats", None)
        if stats is not None:
            try:
                out["link"] = stats()
            except Exception as exc:  # pragma: no cover
                out["link"] = {"error": str(exc)}
        return out
