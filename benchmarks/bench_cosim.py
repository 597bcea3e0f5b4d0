"""Benchmark of the co-simulation master on the paper scenario (not a test).

    python benchmarks/bench_cosim.py [--seconds 20] [--naive-steps 10000] [--skip-fmpy]

Measures, side by side in one process:
  ours      `cosim.run.run_scenario`: fleet FMU + numba network controller, MCAP log at 100 Hz;
  naive     fmpy's high-level FMU2Slave API every step (setReal / doStep / getReal) and a
            controller looping over edges in plain numpy with controller.se3 functions
            (timed over --naive-steps and scaled to the full run; said so in the output);
  fmpy      fmpy.simulate_fmu stepping the same fleet FMU open loop at the same step with
            output every step (no controller at all);
and the per-step breakdown of ours: FMI calls, controller, logging, loop overhead.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
import _markdown  # noqa: E402
PAPER = ROOT / "scenarios" / "paper_6uav.toml"


# ------------------------------------------------------------------ the naive version
class NaiveController:
    """The hybrid law per edge with 4×4 / 6×6 numpy matrices (controller.se3 functions)."""

    def __init__(self, sc):
        from controller import potential, se3

        self.se3, self.pot = se3, potential
        self.sc = sc
        self.AA = sc.weighting.AA
        self.W = sc.weighting.W
        self.c = sc.weighting.b / sc.weighting.d
        self.d = sc.weighting.d
        self.des = sc.design
        self.u_c = sc.design.u_c
        self.theta = np.array(sc.theta0, float)
        self.g = sc.gains

    def U(self, Xb, th):
        G = Xb @ self.pot.T_uc(self.des, self.sc.weighting, th)
        Rg, pg = G[:3, :3], G[:3, 3]
        e = pg - (np.eye(3) - Rg) @ self.c
        return (np.trace(self.W @ (np.eye(3) - Rg)) + 0.5 * self.des.gamma * th * th
                + 0.5 * self.d * e @ e)

    def step(self, X, xi, h):
        se3, g = self.se3, self.g
        N = X.shape[0]
        u = -g.k_xi * xi
        events = []
        for k, (i, j) in enumerate(self.sc.graph.edges):
            Xb = se3.inverse(X[j]) @ X[i]
            th = self.theta[k]
            Uth = self.U(Xb, th)
            cand = [self.U(Xb, t) for t in self.des.Theta]
            jstar = int(np.argmin(cand))
            if Uth - cand[jstar] >= self.des.delta:
                events.append((k + 1, th, self.des.Theta[jstar]))
                th = self.des.Theta[jstar]
            T = self.pot.T_uc(self.des, self.sc.weighting, th)
            Gm = Xb @ T
            aw = se3.psi_bar((np.eye(4) - se3.inverse(Gm)) @ self.AA)
            psi_nabla = se3.Ad_inv_T(T) @ aw
            dth = self.des.gamma * th + 2 * self.u_c @ aw
            dxi = xi[i] - xi[j]
            u[i] = u[i] - g.k_X * psi_nabla - g.k_e * dxi
            u[j] = u[j] + g.k_X * (se3.Ad_inv_T(Xb) @ psi_nabla) + g.k_e * dxi
            self.theta[k] = th - h * g.k_theta * dth
        return u, events


def run_naive(sc, n_steps):
    from fmpy import extract, read_model_description
    from fmpy.fmi2 import FMU2Slave

    from controller import se3
    from plant_fmu import layout
    from plant_fmu.build import fmu_path
    from controller.se3 import rot_to_quat as quat_from_R

    N = sc.graph.n
    path = str(fmu_path(N))
    md = read_model_description(path)
    unzip = extract(path)
    fmu = FMU2Slave(guid=md.guid, unzipDirectory=unzip, modelIdentifier=md.coSimulation.modelIdentifier,
                    instanceName="naive")
    fmu.instantiate()
    S0 = sc.S0
    vr = list(map(int, np.concatenate([layout.vr_mass(N), layout.vr_inertia(N), layout.vr_p0(N),
                                       layout.vr_q0(N), layout.vr_xi0(N), [4]])))
    vals = np.concatenate([sc.masses, sc.inertias.ravel(), S0[:, :3].ravel(),
                           quat_from_R(S0[:, 3:12].reshape(N, 3, 3)).ravel(), S0[:, 12:].ravel(),
                           [sc.internal_step]])
    fmu.setReal(vr, list(map(float, vals)))
    fmu.setupExperiment(startTime=0.0)
    fmu.enterInitializationMode()
    fmu.exitInitializationMode()
    vr_state = list(map(int, layout.vr_state(N)))
    vr_u = list(map(int, layout.vr_input(N)))
    ctrl = NaiveController(sc)
    h = sc.step
    t0 = time.perf_counter()
    for n in range(n_steps):
        S = np.array(fmu.getReal(vr_state)).reshape(N, 18)
        X = se3.T(S[:, 3:12].reshape(N, 3, 3), S[:, :3])
        u, _ = ctrl.step(X, S[:, 12:], h)
        fmu.setReal(vr_u, list(u.ravel()))
        fmu.doStep(currentCommunicationPoint=n * h, communicationStepSize=h)
    wall = time.perf_counter() - t0
    S = np.array(fmu.getReal(vr_state)).reshape(N, 18)
    fmu.terminate()
    fmu.freeInstance()
    return wall, S


def check_naive_agrees(sc, n_steps=200):
    """The naive version must compute the same closed loop (else the ratio means nothing)."""
    from cosim.master import Master
    from cosim.plants import FmuPlant

    sc2 = sc
    _, S_naive = run_naive(sc2, n_steps)
    p = FmuPlant.from_scenario(sc2)
    Master(sc2, p, "hybrid").run(n_steps)
    S = p.read().copy()
    p.close()
    return float(np.abs(S - S_naive).max())


# ------------------------------------------------------------------ breakdown
def breakdown(sc, n_steps):
    """Per-step µs: FMI calls alone, controller alone, the full loop with and without log."""
    from cosim.run import run_scenario
    from cosim.master import make_controller
    from cosim.plants import FmuPlant

    h = sc.step
    p = FmuPlant.from_scenario(sc)
    read, apply, advance = p.read, p.apply, p.advance
    u = np.zeros((sc.graph.n, 6))
    t0 = time.perf_counter()
    for _ in range(n_steps):
        S = read()
        apply(u)
        advance(h)
    fmi = (time.perf_counter() - t0) / n_steps * 1e6
    p.close()
    ctrl = make_controller("hybrid", sc)
    step = ctrl.step_state
    S = np.ascontiguousarray(sc.S0.copy())
    step(S, h)
    t0 = time.perf_counter()
    for _ in range(n_steps):
        step(S, h)
    ctl = (time.perf_counter() - t0) / n_steps * 1e6
    dur = n_steps * h
    s_nolog = run_scenario(sc, duration=dur)
    with tempfile.TemporaryDirectory() as d:
        s_log = run_scenario(sc, duration=dur, log_path=os.path.join(d, "b.mcap"))
    tot_nolog = s_nolog["wall_time_s"] / s_nolog["steps"] * 1e6
    tot_log = s_log["wall_time_s"] / s_log["steps"] * 1e6
    return {"fmi_calls": fmi, "controller": ctl, "logging": tot_log - tot_nolog,
            "loop_overhead": tot_nolog - fmi - ctl, "total_with_log": tot_log,
            "total_without_log": tot_nolog}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="simulated seconds (default 20)")
    ap.add_argument("--naive-steps", type=int, default=10_000,
                    help="steps of the naive version actually timed (scaled to the full run)")
    ap.add_argument("--skip-fmpy", action="store_true", help="skip fmpy.simulate_fmu")
    _markdown.add_option(ap)
    args = ap.parse_args()
    with _markdown.Report(args.markdown):
        bench(args)


def bench(args):

    from cosim.run import run_scenario
    from cosim.scenario import load_scenario
    from plant_fmu.build import fmu_path

    sc = load_scenario(PAPER, [f"simulation.duration={args.seconds}"])
    n = sc.n_steps()
    print(f"paper scenario: {sc.graph.n} agents, {sc.graph.M} edges, h = {sc.step:g} s, "
          f"{args.seconds:g} s simulated = {n} steps, log at {sc.log_rate:g} Hz")
    run_scenario(sc, duration=0.01)  # warm up: FMU build cache, numba cache
    with tempfile.TemporaryDirectory() as d:
        s = run_scenario(sc, log_path=os.path.join(d, "bench.mcap"))
        size = os.path.getsize(os.path.join(d, "bench.mcap"))
    ours = s["wall_time_s"]
    print(f"ours   : {ours:8.3f} s wall  ({ours / n * 1e6:6.2f} µs/step, "
          f"{s['realtime_factor']:.1f}× real time, log {size / 1e6:.1f} MB)")

    diff = check_naive_agrees(sc)
    nn = min(args.naive_steps, n)
    wall_naive, _ = run_naive(sc, nn)
    naive_full = wall_naive * n / nn
    print(f"naive  : {naive_full:8.3f} s wall  ({wall_naive / nn * 1e6:6.2f} µs/step; timed "
          f"{nn} steps and scaled ×{n / nn:g}; no logging; agrees with ours to {diff:.1e} "
          f"after 200 steps)")
    print(f"         ours is {naive_full / ours:.1f}× faster than the naive version")

    if not args.skip_fmpy:
        from fmpy import simulate_fmu

        path = str(fmu_path(sc.graph.n))
        t0 = time.perf_counter()
        res = simulate_fmu(path, stop_time=args.seconds, step_size=sc.step,
                           output_interval=sc.step, fmi_type="CoSimulation")
        wall_fmpy = time.perf_counter() - t0
        print(f"fmpy   : {wall_fmpy:8.3f} s wall  ({wall_fmpy / n * 1e6:6.2f} µs/step; "
              f"simulate_fmu open loop, {len(res)} output rows)")
        print(f"         ours / fmpy.simulate_fmu wall time = {ours / wall_fmpy:.2f}×")

    b = breakdown(sc, 50_000)
    print("per-step breakdown of ours (µs, 50k steps each):")
    for k in ("fmi_calls", "controller", "logging", "loop_overhead", "total_without_log",
              "total_with_log"):
        print(f"  {k:18s} {b[k]:6.2f}")


if __name__ == "__main__":
    main()
