"""Scenario parsing: generators, shapes, overrides, the bridge table, link statistics."""
from pathlib import Path

import numpy as np
import pytest

from controller import se3
from cosim.scenario import ScenarioError, load_scenario, parse_override, parse_scenario

ROOT = Path(__file__).resolve().parents[2]
PAPER = ROOT / "scenarios" / "paper_6uav.toml"
PAPER_TEXT = PAPER.read_text()
INITIAL = 'generator = "paper"\naxis = [0.2686, 0.8549, 0.4438]'


def _with_initial(block, extra=()):
    assert INITIAL in PAPER_TEXT
    return parse_scenario(PAPER_TEXT.replace(INITIAL, block), "t", "t.toml", list(extra))


def _R(sc):
    return sc.S0[:, 3:12].reshape(-1, 3, 3)


def test_paper_initial_conditions():
    sc = load_scenario(PAPER)
    v = np.array([0.2686, 0.8549, 0.4438])
    v /= np.linalg.norm(v)
    c = sc.weighting.b / sc.weighting.d
    for i in range(6):
        R = se3.R_a(-np.pi / 2 if i % 2 == 0 else np.pi / 2, v)
        np.testing.assert_allclose(_R(sc)[i], R, atol=1e-15)
        np.testing.assert_allclose(sc.S0[i, :3], (np.eye(3) - R) @ c, atol=1e-14)
    assert np.all(sc.S0[:, 12:] == 0) and np.all(sc.theta0 == 0)
    assert sc.masses.tolist() == [2.4] * 6
    np.testing.assert_allclose(sc.inertias[3], np.diag([0.043, 0.041, 0.082]))
    assert sc.step == 1e-4 and sc.duration == 40 and sc.log_rate == 100
    assert sc.internal_step == 1e-4 and sc.plant_mode == "fleet"
    assert sc.design.Theta == pytest.approx((0.3 * np.pi,))
    # eigenvector = 3 gives the exact eigenvector, which the printed axis rounds
    sc3 = _with_initial('generator = "paper"\neigenvector = 3')
    assert np.abs(_R(sc3) - _R(sc)).max() < 1e-3


def test_random_generator_is_seeded():
    a = _with_initial('generator = "random"\nseed = 7\nposition_box = 2.0\nvelocity_ball = 0.5')
    b = _with_initial('generator = "random"\nseed = 7\nposition_box = 2.0\nvelocity_ball = 0.5')
    c = _with_initial('generator = "random"\nseed = 8')
    assert np.array_equal(a.S0, b.S0) and not np.array_equal(a.S0, c.S0)
    R = _R(a)
    np.testing.assert_allclose(np.einsum("nji,njk->nik", R, R), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    assert np.all(np.abs(a.S0[:, :3]) <= 2.0)
    assert np.all(np.linalg.norm(a.S0[:, 12:], axis=1) <= 0.5 + 1e-12)
    assert np.any(a.S0[:, 12:] != 0)
    assert np.all(c.S0[:, 12:] == 0)  # velocity_ball defaults to 0


def test_explicit_agents_and_theta0():
    blocks = ["theta0 = [0.1, 0.2, 0.3, 0.4, 0.5]"]
    for i in range(6):
        rot = (f"axis_angle = [0, 0, 1, {0.1 * i}]" if i % 2 == 0
               else "quaternion = [0.0, 1.0, 0.0, 0.0]")
        blocks.append(f"[[initial.agent]]\n{rot}\nposition = [{i}, 0, 0]\n"
                      f"velocity = [0, 0, {i}, 1, 0, 0]")
    sc = _with_initial("\n".join(blocks))
    np.testing.assert_allclose(_R(sc)[2], se3.R_a(0.2, np.array([0.0, 0, 1])), atol=1e-15)
    np.testing.assert_allclose(_R(sc)[1], np.diag([1.0, -1.0, -1.0]), atol=1e-15)
    assert sc.S0[4, :3].tolist() == [4, 0, 0] and sc.S0[3, 12:].tolist() == [0, 0, 3, 1, 0, 0]
    assert sc.theta0.tolist() == [0.1, 0.2, 0.3, 0.4, 0.5]
    with pytest.raises(ScenarioError, match=r"t.toml: initial.agent: must have one table per agent"):
        _with_initial("[[initial.agent]]\nposition = [0, 0, 0]")


def test_inertia_forms_and_per_agent_mass():
    base = "inertia = [0.043, 0.041, 0.082]"
    full = "inertia = [[0.043, 0, 0], [0, 0.041, 0], [0, 0, 0.082]]"
    per = "inertia = [" + ", ".join(["[[0.05, 0, 0], [0, 0.04, 0], [0, 0, 0.08]]"] * 6) + "]"
    a = parse_scenario(PAPER_TEXT, "a", "a.toml")
    b = parse_scenario(PAPER_TEXT.replace(base, full), "b", "b.toml")
    c = parse_scenario(PAPER_TEXT.replace(base, per).replace("mass = 2.4", "mass = [1, 2, 3, 4, 5, 6]"),
                       "c", "c.toml")
    assert np.array_equal(a.inertias, b.inertias)
    assert c.inertias[5, 0, 0] == 0.05 and c.masses.tolist() == [1, 2, 3, 4, 5, 6]
    assert c.inertia6[2, 3:, 3:].tolist() == (3 * np.eye(3)).tolist()
    with pytest.raises(ScenarioError, match=r"c.toml: agents.inertia: must be positive definite"):
        parse_scenario(PAPER_TEXT.replace(base, "inertia = [0.1, -0.1, 0.1]"), "c", "c.toml")


def test_overrides():
    assert parse_override("gains.k_X=50") == (["gains", "k_X"], 50)
    assert parse_override("plant.mode=per-body") == (["plant", "mode"], "per-body")
    assert parse_override("plant.gravity=[0, 0, -9.81]") == (["plant", "gravity"], [0, 0, -9.81])
    sc = load_scenario(PAPER, ["gains.k_X=50", "simulation.step=5e-5", "plant.mode=per-body"])
    assert sc.gains.k_X == 50 and sc.step == 5e-5 and sc.internal_step == 5e-5
    assert sc.plant_mode == "per-body"
    with pytest.raises(ScenarioError, match=r"paper_6uav.toml: initial.agent: unknown key"):
        load_scenario(PAPER, ["initial.agent=1"])


def test_bridge_table_is_passed_on():
    text = PAPER_TEXT + "\n[bridge]\n"
    sc = parse_scenario(text, "b", "b.toml")
    assert sc.bridge is not None
    bad = PAPER_TEXT + "\n[bridge]\nno_such_bridge_key = 1\n"
    with pytest.raises(ScenarioError) as e:
        parse_scenario(bad, "b", "b.toml")
    assert str(e.value).startswith("b.toml: bridge.") and "\n" not in str(e.value)


def test_link_stats_are_logged_and_summarised(tmp_path):
    from cosim.run import run_scenario
    from cosim.log.reader import read_log
    from cosim.plants import FmuPlant

    sc = load_scenario(PAPER, ["simulation.duration=2.0"])

    class LinkPlant(FmuPlant):
        calls = 0

        def stats(self):
            LinkPlant.calls += 1
            return {"sent": LinkPlant.calls, "lost": 0}

    plant = LinkPlant.from_scenario(sc)
    try:
        s = run_scenario(sc, plant=plant, log_path=tmp_path / "l.mcap")
    finally:
        plant.close()
    assert s["link"]["sent"] == LinkPlant.calls
    msgs = read_log(tmp_path / "l.mcap")["messages"]["/link/stats"]
    assert [t for t, _ in msgs] == [0, 1_000_000_000]
    assert msgs[1][1]["sent"] == 2


def test_with_timing_checks_h_against_every_limit_of_the_loader():
    """One validation of h (cosim.scenario._timing): a library override of the step or the
    duration meets the same limits as the file, on one line naming the key."""
    from cosim.scenario import MAX_STEPS, with_timing

    sc = load_scenario(PAPER)
    for kw, needle in (({"step": 0.0}, "must be > 0"), ({"step": float("nan")}, "finite"),
                       ({"duration": 1e6}, f"at most {MAX_STEPS:.0e}"),
                       ({"step": 2 * sc.duration}, "must be <= simulation.duration")):
        with pytest.raises(ScenarioError) as e:
            with_timing(sc, **kw)
        msg = str(e.value)
        assert "simulation." in msg and needle in msg and "\n" not in msg, msg
    big = load_scenario(PAPER, ["plant.internal_step=1e-9"], duration=1e-3, step=1e-4)
    with pytest.raises(ScenarioError, match="plant.internal_step: .*body-substeps"):
        with_timing(big, step=1e-3)
    fine = with_timing(sc, duration=2.0, step=2e-4)
    assert (fine.duration, fine.step, fine.internal_step) == (2.0, 2e-4, 2e-4)
