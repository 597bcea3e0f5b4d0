"""The loop with its wrenches applied d_a steps late (`cosim.analysis.actuation`, what `check`
reports and `run` refuses) against independent computations:

* d_a = 0 is the delayed loop of `delay_margin` (the same spectrum);
* a linear simulation of the delayed loop built here from the DENSE finite-difference Jacobian
  of `cosim.analysis.stability.linearise` (wrench rows delayed by d_a, θ's flow not), stepped with
  a history of past states: it decays where the radius is below 1 and grows where it is above;
* the co-simulation itself (the FMU plant inside `DelayedActuation`): hil_6uav at 100 Hz with
  one step of actuation delay, which the analysis calls unstable, diverges; at 250 Hz it
  converges.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from cosim.analysis import stability as dense
from cosim.analysis.actuation import actuation_check, actuation_radius
from cosim.analysis.delay_margin import delay_radius
from cosim.analysis.stability_sparse import Linearisation
from cosim.cli import main
from cosim.guards import EXIT_DIVERGED
from cosim.scenario import load_scenario

HIL = "scenarios/hil_6uav.toml"


@pytest.fixture(scope="module")
def hil():
    sc = load_scenario(HIL)
    return sc, Linearisation(sc, "hybrid", force_sparse=True)


@pytest.mark.parametrize("h", [0.004, 0.01])
@pytest.mark.parametrize("d", [0, 2])
def test_no_actuation_delay_is_the_delayed_loop(hil, h, d):
    sc, lin = hil
    assert actuation_radius(lin, h, d, 0) == pytest.approx(delay_radius(lin, h, d), abs=1e-12)


def _parts_from_dense(sc, h):
    """(plant, wrench of fresh data, wrench of delayed data, θ-flow of fresh, of delayed), each
    a map s ↦ its share of s(n+1), from the dense Jacobian: agent i's own δ_i, ξ_i and the θ_k
    it owns are fresh in its wrench; an edge's owner uses its own δ, ξ, θ_k fresh in θ_k's flow."""
    N, M = sc.graph.n, sc.graph.M
    E = np.asarray(sc.graph.edges)
    Kx, G = dense.linearise(sc, True)
    nx = 12 * N + M
    owner = np.empty(nx, dtype=int)
    owner[:6 * N] = np.repeat(np.arange(N), 6)
    owner[6 * N:12 * N] = np.repeat(np.arange(N), 6)
    owner[12 * N:] = E[:, 0]
    fresh_u = owner[None, :] == np.repeat(np.arange(N), 6)[:, None]
    fresh_g = owner[None, :] == E[:, 0][:, None]
    zK, zG = np.zeros_like(Kx), np.zeros_like(G)
    plant = dense.closed_loop(sc, h, zK, zG)
    wrench = lambda K: dense.closed_loop(sc, h, K, zG) - plant        # noqa: E731 (rows :12N)
    flow = lambda g: dense.closed_loop(sc, h, zK, g) - plant          # noqa: E731 (rows 12N:)
    return (plant, wrench(Kx * fresh_u), wrench(Kx * ~fresh_u), flow(G * fresh_g),
            flow(G * ~fresh_g))


def _linear_growth(sc, h, d, d_a, steps, seed=0):
    """‖relative state‖ after ``steps`` over its start, the linear loop stepped directly:
    s(n+1) = A s(n) + W₀ s(n − d_a) + W_d s(n − d − d_a) + F₀ s(n) + F_d s(n − d)."""
    N, M = sc.graph.n, sc.graph.M
    E = np.asarray(sc.graph.edges)
    A, W0, Wd, F0, Fd = _parts_from_dense(sc, h)
    rng = np.random.default_rng(seed)
    s = np.zeros(12 * N + M)
    s[:6 * N] = 1e-3 * rng.standard_normal(6 * N)
    lag = d + d_a
    hist = [np.zeros_like(s) for _ in range(lag)]   # s(n − lag) … s(n − 1); the wrench before
    # step 0 is zero (DelayedActuation), so are the states it would come from

    def rel(x):
        dl = x[:6 * N].reshape(N, 6)
        return np.concatenate([(dl[E[:, 0]] - dl[E[:, 1]]).ravel(), x[6 * N:]])

    def back(k):   # s(n − k)
        return s if k == 0 else hist[lag - k]

    e0 = np.linalg.norm(rel(s))
    for _ in range(steps):
        nxt = A @ s + W0 @ back(d_a) + Wd @ back(d + d_a) + F0 @ s + Fd @ back(d)
        if lag:
            hist.append(s)
            hist.pop(0)
        s = nxt
    return np.linalg.norm(rel(s)) / e0


@pytest.mark.parametrize("h, d, d_a", [(0.004, 0, 1), (0.004, 2, 1), (0.004, 0, 2),
                                       (0.01, 0, 1), (0.01, 2, 1)])
def test_radius_decides_what_the_linear_loop_does(hil, h, d, d_a):
    sc, lin = hil
    rho = actuation_radius(lin, h, d, d_a)
    # unstable: as many steps as take ρⁿ to about 1e6 (beyond, floats overflow)
    steps = 4000 if rho < 1.0 else int(min(4000, 14.0 / np.log(rho)))
    g = _linear_growth(sc, h, d, d_a, steps)
    if rho < 1.0:
        assert g < 10 * rho ** steps + 1e-2, (rho, g)
    else:
        assert rho > 1.01 and g > 1e2, (rho, g)
    # and the rate: the growth over many steps follows ρ^n (within the transient's factor)
    if rho > 1.01:
        assert 1e-3 < g / rho ** steps < 1e3, (rho, g)


def test_max_stable_step_brackets_the_radius(hil):
    sc, lin = hil
    act = actuation_check(load_scenario(HIL, ["simulation.actuation_delay=1"]))
    h = act["max_stable_step"]
    assert act["stable"] and h is not None and h < dense.max_stable_step(sc)
    assert actuation_radius(lin, h, 0, 1) < 1.0 <= actuation_radius(lin, 1.02 * h, 0, 1)


def test_check_and_run_with_actuation_delay(tmp_path, capsys):
    """100 Hz with one step of actuation delay: `check` says unstable (exit 3), `run` refuses
    (exit 2, one line naming the key, nothing written), and forced, the co-simulation diverges.
    At 250 Hz the same delay: stable, and the run converges."""
    bad = ["--set", "simulation.step=0.01", "--set", "simulation.actuation_delay=1"]
    assert main(["check", HIL, *bad]) == 3
    out = capsys.readouterr().out
    line = next(x for x in out.splitlines() if x.startswith("actuation"))
    assert "UNSTABLE" in line and "max_stable_step" in line
    assert main(["check", HIL, *bad, "--json"]) == 3
    act = json.loads(capsys.readouterr().out)["actuation"]
    assert act["stable"] is False and act["spectral_radius"] > 1.0

    summary = tmp_path / "s.json"
    assert main(["run", HIL, *bad, "--duration", "3", "--summary", str(summary)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "simulation.actuation_delay" in err[0] and "--force" in err[0]
    assert not summary.exists()
    assert main(["run", HIL, *bad, "--duration", "3", "--force", "--summary",
                 str(summary)]) == EXIT_DIVERGED
    assert json.loads(summary.read_text())["diverged"] is not None

    good = ["--set", "simulation.step=0.004", "--set", "simulation.actuation_delay=1"]
    assert main(["check", HIL, *good]) == 0
    capsys.readouterr()
    assert main(["run", HIL, *good, "--duration", "3", "--summary", str(summary)]) == 0
    s = json.loads(summary.read_text())
    assert s["actuation_check"]["stable"] is True and s["diverged"] is None
    V = [x["V"] for x in s["samples"]]
    assert V[-1] < V[0]
