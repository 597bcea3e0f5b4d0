"""The predicted slowest decay rate against the decay of a co-simulation near consensus."""
import math

import numpy as np

from cosim.run import run_scenario
from cosim.analysis.convergence_rate import convergence, initial_error
from cosim.scenario import parse_scenario
from cosim.analysis.stability_cases import HIL


def _near_consensus(seed=0, size=1e-3, duration=40.0):
    """hil_6uav from a small random perturbation of consensus (explicit agent tables)."""
    text = open(HIL).read().split("[bridge]")[0]
    rng = np.random.default_rng(seed)
    tables = []
    for _ in range(6):
        ax = rng.standard_normal(3)
        pos = size * rng.standard_normal(3)
        tables.append("[[initial.agent]]\naxis_angle = [%.17g, %.17g, %.17g, %.17g]\n"
                      "position = [%.17g, %.17g, %.17g]\n" % (*ax, size, *pos))
    text = text.replace('generator = "paper"\naxis = [0.2997, 0.8380, 0.4560]\n', "\n".join(tables))
    text = text.replace("duration = 20.0", f"duration = {duration}")
    return parse_scenario(text, "near", "near.toml")


def test_slowest_rate_matches_the_cosimulation_decay():
    sc = _near_consensus()
    pred = convergence(sc)
    s = run_scenario(sc, plant="fleet", controller="hybrid")
    assert s["n_jumps"] == 0
    t = np.array([x["t"] for x in s["samples"]])
    e = np.array([max(x["rot_err"], x["pos_err"]) for x in s["samples"]])
    w = (t >= 20.0) & (t <= 40.0)          # the faster modes have died out by 20 s
    slope = np.polyfit(t[w], np.log(e[w]), 1)[0]
    assert abs(-slope - pred["rate"]) < 0.10 * pred["rate"]
    # the initial error is the largest relative error the run logged at t = 0
    assert math.isclose(initial_error(sc), e[0], rel_tol=1e-9)
    # the time to tolerance is the same logarithm
    c1 = convergence(sc, e0=1.0)
    assert math.isclose(c1["time_to_tolerance"], math.log(100.0) / pred["rate"], rel_tol=1e-12)


def test_sensitivities_are_derivatives_of_the_rate():
    """∂r/∂ln k_θ by the module against a wider central difference computed here."""
    from cosim.scenario import load_scenario
    base = load_scenario(HIL)
    c = convergence(base)
    r = []
    for f in (1.2, 1 / 1.2):
        sc = load_scenario(HIL, [f"gains.k_theta={base.gains.k_theta * f!r}"])
        r.append(convergence(sc)["rate"])
    fd = (r[0] - r[1]) / (2 * math.log(1.2))
    assert abs(c["sensitivity"]["k_theta"] - fd) < 0.05 * abs(fd)
    fr = c["slowest_mode"]
    assert math.isclose(fr["pose"] + fr["velocity"] + fr["theta"], 1.0, rel_tol=1e-12)
