"""`se3sync check`: the delay margin and convergence lines, and their consistency."""
import json
import math

import pytest

from cosim.cli import main


def test_check_json_reports_delay_margin_and_rate(capsys):
    assert main(["check", "scenarios/hil_6uav.toml", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    h = out["step"]
    assert out["method"] == "modal"
    dm = out["delay_margin"]
    assert dm["rho_at_margin"] < 1.0 <= dm["rho_beyond"]
    assert dm["delay_margin_s"] == pytest.approx(dm["delay_margin_steps"] * h)
    # at d = 0 the delayed loop is the loop itself: a margin ≥ 1 step needs ρ(0) < 1
    assert out["stable"] and dm["delay_margin_steps"] >= 0
    c = out["convergence"]
    # the slowest mode IS the spectral radius: rate = −ln ρ / h
    assert c["rate"] == pytest.approx(-math.log(out["spectral_radius"]) / h, rel=1e-9)
    assert set(c["sensitivity"]) == {"k_X", "k_xi", "k_e", "k_theta"}


def test_check_text_and_from_error(capsys):
    # k_X = 30, k_e = 1: a margin of five steps, quick to find
    assert main(["check", "scenarios/hil_6uav.toml", "--from-error", "1", "--set", "gains.k_X=30",
                 "--set", "gains.k_e=1"]) == 0
    text = capsys.readouterr().out
    for key in ("delay_margin", "slowest_rate", "time_to_tol", "d rate/d ln k"):
        assert key in text
    rate = float(text.split("slowest_rate")[1].split()[0])
    t = float(text.split("time_to_tol")[1].split()[0])
    assert t == pytest.approx(math.log(100.0) / rate, rel=1e-3)


def test_check_rejects_a_bad_from_error(capsys):
    assert main(["check", "scenarios/hil_6uav.toml", "--from-error", "-1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--from-error" in err[0]


def test_check_skips_the_delay_margin_above_its_agent_limit(tmp_path, capsys):
    """One agent above DELAY_MAX_AGENTS: the margin is reported as not computed, and why, while
    the spectral radius and the convergence rate are still there."""
    from cosim.analysis.stability_cases import tree_scenario_text
    from cosim.analysis.stability_report import DELAY_MAX_AGENTS

    n = DELAY_MAX_AGENTS + 1
    path = tmp_path / "tree.toml"
    path.write_text(tree_scenario_text(n, "random", 0))
    assert main(["check", str(path), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    dm = out["delay_margin"]
    assert dm["delay_margin_steps"] is None
    assert dm["delay_method"] == f"not computed: {n} agents > {DELAY_MAX_AGENTS}"
    assert out["stable"] and out["convergence"]["rate"] > 0.0
