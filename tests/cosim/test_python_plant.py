"""A plant in plain Python, no FMU, through `cosim.registry.PLANTS` alone (one entry, made here
with monkeypatch): `run` and `run --plant`, a scenario's ``plant.mode``, the sweeps and the
bridge's warm-up drive it as they drive the FMU plant, and it gives the FMU plant's trajectories
to the accuracy of two different integrators of the same equations."""
from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from controller import layout
from cosim.registry import PLANTS
from cosim.scenario import load_scenario
from _bridge import HIL

SMALL = "scenarios/sweep_small.toml"
NAME = "rigid-python"


class RigidBodies:
    """N rigid bodies (`plant_fmu/c/model.h`: Ẋ = X ξ^, J ω̇ = (Jω) × ω + τ, m v̇ = m v × ω + f +
    m Rᵀg, ξ = [ω; v] in the body frame) by the classical Runge–Kutta method on (p, R, ω, v)
    embedded in R^18, R re-orthonormalised (polar factor) after every communication step; the
    FMU integrates the same equations with Runge–Kutta–Munthe-Kaas on SE(3) × R⁶."""

    def __init__(self, masses, inertias, S0, gravity=(0.0, 0.0, 0.0), internal_step=1e-3):
        S0 = np.asarray(S0, float)
        self.n = S0.shape[0]
        self.m = np.broadcast_to(np.asarray(masses, float), (self.n,)).copy()
        self.J = np.broadcast_to(np.asarray(inertias, float), (self.n, 3, 3)).copy()
        self.Jinv = np.linalg.inv(self.J)
        self.g = np.asarray(gravity, float)
        self.h_int = float(internal_step)
        self.input_buffer = np.zeros((self.n, 6))
        self.reset(S0)

    @classmethod
    def from_scenario(cls, scenario):
        return cls(scenario.masses, scenario.inertias, scenario.S0, scenario.gravity,
                   scenario.internal_step)

    def reset(self, S0) -> None:
        self.S = np.array(S0, float)
        self.steps = 0

    def read(self):
        return self.S

    def apply(self, u) -> None:
        np.copyto(self.input_buffer, u)

    def _f(self, y):
        R = y[:, 3:12].reshape(-1, 3, 3)
        w, v = y[:, 12:15], y[:, 15:18]
        tau, f = self.input_buffer[:, :3], self.input_buffer[:, 3:]
        W = np.zeros((self.n, 3, 3))
        W[:, 0, 1], W[:, 0, 2], W[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
        W[:, 1, 0], W[:, 2, 0], W[:, 2, 1] = w[:, 2], -w[:, 1], w[:, 0]
        Jw = np.einsum("nij,nj->ni", self.J, w)
        out = np.empty_like(y)
        out[:, 0:3] = np.einsum("nij,nj->ni", R, v)
        out[:, 3:12] = (R @ W).reshape(-1, 9)
        out[:, 12:15] = np.einsum("nij,nj->ni", self.Jinv, np.cross(Jw, w) + tau)
        out[:, 15:18] = np.cross(v, w) + f / self.m[:, None] + np.einsum("nji,j->ni", R, self.g)
        return out

    def advance(self, h: float) -> None:
        k = math.ceil(h / self.h_int - 1e-9)
        hs = h / k
        y = self.S
        for _ in range(k):
            k1 = self._f(y)
            k2 = self._f(y + 0.5 * hs * k1)
            k3 = self._f(y + 0.5 * hs * k2)
            k4 = self._f(y + hs * k3)
            y = y + hs / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        U, _, Vt = np.linalg.svd(y[:, 3:12].reshape(-1, 3, 3))
        y[:, 3:12] = (U @ Vt).reshape(-1, 9)
        self.S = y
        self.steps += 1

    def close(self) -> None:
        pass


class NoReset(RigidBodies):
    def __init__(self, *a, **k):
        super().__init__(*a, **k)
        self.reset = None      # the capability withdrawn


@pytest.fixture
def registered(monkeypatch):
    monkeypatch.setitem(PLANTS, NAME, ("test_python_plant:RigidBodies", "RK4 in Python (test)"))
    monkeypatch.setitem(PLANTS, "no-reset", ("test_python_plant:NoReset", "no reset (test)"))


def _close(a, b, rtol):
    for f in ("rot_err", "pos_err", "xi_max", "V"):
        assert a[f] == pytest.approx(b[f], rel=rtol, abs=1e-9), (f, a, b)


@pytest.mark.parametrize("law", ["hybrid", "decoupled"])
def test_run_on_the_python_plant_equals_the_fmu_plant(registered, law):
    from cosim.run import run_scenario

    sc = load_scenario(HIL, ["simulation.duration=2.0"])
    py = run_scenario(sc, plant=NAME, controller=law)
    fmu = run_scenario(sc, plant="fleet", controller=law)
    assert py["plant"] == NAME and py["steps"] == fmu["steps"] == sc.n_steps()
    assert [(j["t"], j["edge"], j["theta_after"]) for j in py["jumps"]] == \
        [(j["t"], j["edge"], j["theta_after"]) for j in fmu["jumps"]]
    assert len(py["samples"]) == len(fmu["samples"]) == 3
    for a, b in zip(py["samples"] + [py["final"]], fmu["samples"] + [fmu["final"]]):
        _close(a, b, 1e-6)
    assert py["final"]["rot_err"] < py["samples"][0]["rot_err"]


def test_the_command_line_and_plant_mode_take_it(registered, tmp_path, capsys):
    from cosim.cli import main

    out = tmp_path / "s.json"
    assert main(["run", HIL, "--plant", NAME, "--duration", "0.2", "--summary", str(out)]) == 0
    a = json.loads(out.read_text())
    assert main(["run", HIL, "--set", f"plant.mode={NAME}", "--duration", "0.2",
                 "--summary", str(out)]) == 0
    b = json.loads(out.read_text())
    assert a["plant"] == b["plant"] == NAME and a["final"] == b["final"]
    with pytest.raises(SystemExit) as e:
        main(["run", HIL, "--plant", "nope"])
    assert e.value.code == 2 and NAME in capsys.readouterr().err   # choices come from PLANTS


def test_sweep_samples_run_on_it_and_a_plant_without_reset_is_refused(registered):
    from cosim.sweep.runner import make_spec
    from cosim.sweep.spec import run_sample

    spec = make_spec(SMALL, ["simulation.duration=4.0"], seed=2, samples=1)[0]
    on_py = dataclasses.replace(spec, plant=NAME)
    assert on_py.key() != spec.key() and "plant" not in spec.key_dict()
    for i in (0, 12):                       # an adversarial and the random sample
        for law in ("hybrid", "gradient"):
            a, b = run_sample(on_py, i, law), run_sample(spec, i, law)
            assert a["status"] == b["status"] == "ok", a["error"]
            assert (a["n_jumps"], a["converged"], a["steps"]) == (b["n_jumps"], b["converged"],
                                                                 b["steps"])
            for f in ("rot_err", "pos_err", "rot_err0", "V0"):
                assert a[f] == pytest.approx(b[f], rel=1e-6, abs=1e-9), (i, law, f)
    row = run_sample(dataclasses.replace(spec, plant="no-reset"), 0, "hybrid")
    assert row["status"] == "error" and "cannot reset(S0)" in row["error"]
    assert "\n" not in row["error"]


def test_the_bridge_warms_up_on_the_scenarios_plant(registered, monkeypatch):
    from bridge.mavlink import hil

    made = []
    real = RigidBodies.from_scenario.__func__
    monkeypatch.setattr(RigidBodies, "from_scenario",
                        classmethod(lambda cls, sc: made.append(cls) or real(cls, sc)))
    hil.warm_up(load_scenario(HIL, [f"plant.mode={NAME}"]))
    assert made == [RigidBodies]


def test_the_integrator_keeps_rotations_and_conserves_energy_without_input():
    """The test plant itself: torque-free bodies keep |R^T R − I| ≈ 0 and their kinetic energy."""
    sc = load_scenario(HIL)
    S0 = sc.S0.copy()
    S0[:, layout.XI] = np.random.default_rng(0).standard_normal((sc.graph.n, 6))
    p = RigidBodies(sc.masses, sc.inertias, S0, internal_step=1e-3)

    def energy(S):
        w, v = S[:, 12:15], S[:, 15:18]
        return float(np.einsum("ni,nij,nj->", w, p.J, w) + np.sum(p.m[:, None] * v * v))

    e0 = energy(p.read())
    for _ in range(100):
        p.advance(0.01)
    R = layout.rotations(p.read())
    assert np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max() < 1e-12
    assert energy(p.read()) == pytest.approx(e0, rel=1e-7)
