"""The paper scenario reproduces the paper's Fig. 2 claims (the full 40 s, h = 0.1 ms)."""
from pathlib import Path

import numpy as np

from cosim.run import run_scenario

ROOT = Path(__file__).resolve().parents[2]
PAPER = ROOT / "scenarios" / "paper_6uav.toml"


def test_paper_scenario_reproduces_the_paper():
    s = run_scenario(str(PAPER))
    assert s["steps"] == 400_000 and abs(s["sim_time_s"] - 40.0) < 1e-9
    assert not s["interrupted"]
    d = s["design"]
    assert d["case"] == 2
    np.testing.assert_allclose(d["u_c1"], [0.1063, 0.9936, 0.0381], atol=1e-4)
    np.testing.assert_allclose(d["u_c2"], [-3.06, 0.20, 3.32], atol=0.01)
    assert d["warnings"], "delta = 0.02 is above Lemma 2's bound: a warning is expected"
    # every θ_k jumps 0 -> 0.3π at t = 0
    first = [j for j in s["jumps"] if j["t"] == 0.0]
    assert sorted(j["edge"] for j in first) == [1, 2, 3, 4, 5]
    for j in first:
        assert j["theta_before"] == 0.0
        assert abs(j["theta_after"] - 0.3 * np.pi) < 1e-12
        assert j["mu"] >= 0.02
    # the number of jumps is within Theorem 1's bound
    assert 5 <= s["n_jumps"] <= s["jump_bound"]
    # samples every simulated second, t = 0 .. 40
    ts = [x["t"] for x in s["samples"]]
    np.testing.assert_allclose(ts, np.arange(41.0), atol=1e-9)
    by_t = {round(x["t"]): x for x in s["samples"]}
    s0 = by_t[0]
    assert s0["rot_err"] > 2.8 and s0["pos_err"] > 5.0  # R̄_k = R_a(π, v): ‖I − R̄‖_F = 2√2
    np.testing.assert_allclose(s0["theta"], [0.3 * np.pi] * 5)  # θ after the jump at t = 0
    # R̄_k → I, p̄_k → 0, ξ → 0, θ → 0: a clear decrease, and steady once the jumps are over
    last_jump = max(j["t"] for j in s["jumps"])
    assert last_jump < 1.0
    for key in ("rot_err", "pos_err", "xi_max"):
        assert by_t[40][key] <= 1e-2 * by_t[5][key], key
        assert by_t[40][key] <= 1e-3 * max(by_t[0][key], 1.0), key
        series = [by_t[t][key] for t in range(10, 41)]
        assert all(b < a for a, b in zip(series, series[1:])), key  # monotone from 10 s on
    assert max(abs(x) for x in by_t[40]["theta"]) < 1e-3
    # V̄ is non-increasing after the last jump (a Lyapunov function of the flow)
    V = [by_t[t]["V"] for t in range(1, 41)]
    assert all(b <= a * (1 + 1e-9) for a, b in zip(V, V[1:]))
    assert V[-1] < 1e-4 * by_t[1]["V"]
    f = s["final"]
    assert f["rot_err"] == by_t[40]["rot_err"] and f["pos_err"] < 2e-3
