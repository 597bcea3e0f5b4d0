"""The [network] table and the law per agent over delayed, lossy links (cosim/network.py).

The delayed runs are checked against a reference written here: one `controller.AgentStepper` per
agent, stepping the plant FMU, fed with neighbour data explicitly taken from a history d steps
back (the delay contract in cosim/network.py).
"""
import math
from pathlib import Path

import numpy as np
import pytest

from controller import AgentStepper, ConfigError
from cosim.cli import main as cli_main
from cosim.controllers import make_controller
from cosim.master import Master
from cosim.network import NetworkController, networked, parse_network
from cosim.plants import make_plant
from cosim.run import run_scenario
from cosim.scenario import parse_scenario

ROOT = Path(__file__).resolve().parents[2]
HIL = (ROOT / "scenarios" / "hil_6uav.toml").read_text()   # h = 4 ms, jumps at t = 0
H = 0.004


def scenario(network: str | None, duration=0.4):
    text = HIL if network is None else HIL + "\n[network]\n" + network + "\n"
    return parse_scenario(text, name="net", path="net.toml", duration=duration)


def same_run(a, b):
    for key in ("final", "samples", "jumps", "n_jumps", "steps"):
        assert a[key] == b[key], key


# ------------------------------------------------------------------ delay 0 is the network step

def test_zero_delay_is_bit_identical_to_the_network_step():
    plain = run_scenario(scenario(None))
    # every link through the delayed path, one of them with an explicit per-link entry
    net = run_scenario(scenario("delay = 0.0\nloss = 0.0\njitter = 0.0\nseed = 5\n"
                                "[[network.link]]\nfrom = 2\nto = 1\ndelay = 0.0"))
    assert plain["n_jumps"] > 0  # the jump path is exercised too
    same_run(plain, net)
    assert "network" not in plain
    tot = net["network"]["total"]
    assert tot["sent"] == 2 * 5 * net["steps"] and tot["lost"] == 0
    assert tot["age_p99_steps"] == 0


@pytest.mark.parametrize("law", ["hybrid", "gradient"])
def test_zero_delay_kernel_equals_network_step_on_moving_states(law):
    """Step by step, wrench, θ, μ and jumps equal the network view's exactly."""
    sc = scenario("delay = 0.0")
    ref = make_controller(law, sc)
    ctrl = networked(sc, make_controller(law, sc))
    assert isinstance(ctrl, NetworkController)
    rng = np.random.default_rng(1)
    S = sc.S0.copy()
    for n in range(30):
        S[:, :3] += 0.01 * rng.standard_normal((6, 3))
        S[:, 12:] += 0.05 * rng.standard_normal((6, 6))
        u_ref, ev_ref = ref.step_state(S, H)
        u, ev = ctrl.step_state(S, H)
        assert np.array_equal(u, u_ref) and ev == ev_ref
        for name in ("theta", "theta_jump", "mu", "jumped"):
            assert np.array_equal(getattr(ctrl, name), getattr(ref, name)), name


def test_reset_starts_the_links_again():
    """After reset(θ0) the same inputs give the same wrenches: no link state survives."""
    sc = scenario("delay = 0.012\njitter = 0.008\nloss = 0.2\nseed = 3")
    ctrl = networked(sc, make_controller("hybrid", sc))
    rng = np.random.default_rng(2)
    states = []
    for n in range(40):
        S = sc.S0.copy()
        S[:, :3] += 0.01 * rng.standard_normal((6, 3))
        states.append(S)
    runs = []
    for _ in range(2):
        ctrl.reset(sc.theta0)
        runs.append([ctrl.step_state(S, H)[0].copy() for S in states])
        runs[-1].append(ctrl.network_stats())
    assert all(np.array_equal(a, b) for a, b in zip(runs[0][:-1], runs[1][:-1]))
    assert runs[0][-1] == runs[1][-1]


# ------------------------------------------------------------------ delay d against AgentSteppers

def _pose(row):
    X = np.eye(4)
    X[:3, :3] = row[3:12].reshape(3, 3)
    X[:3, 3] = row[:3]
    return X


def reference_run(sc, d, n_steps, sample=None):
    """N AgentSteppers stepping the plant. Agent i uses from neighbour j the data (pose, ξ,
    published θ) of sample ``sample(n, j, i)`` (default n − d), and S0, θ(0) while that is −1
    (no message arrived yet)."""
    if sample is None:
        def sample(n, frm, to):
            return n - d if n >= d else -1
    edges = [(int(a), int(b)) for a, b in sc.graph.edges]
    N = sc.graph.n
    theta0 = {k: float(sc.theta0[k]) for k in range(len(edges))}
    agents = [AgentStepper(i, {k: e for k, e in enumerate(edges) if i in e}, sc.weighting,
                           sc.design, sc.gains, theta0)
              for i in range(N)]
    plant = make_plant("fleet", sc)
    hist, published = [], []
    try:
        for n in range(n_steps):
            S = plant.read().copy()
            hist.append(S)

            def row(frm, to):
                s = sample(n, frm, to)
                return hist[max(s, 0)][frm]

            rel = []
            for i in range(N):
                r = {}
                for k, (a, b) in agents[i].local_edges.items():
                    if a == i:   # owner: X̄ = X_b(s)⁻¹ X_a(n)
                        r[k] = np.linalg.solve(_pose(row(b, a)), _pose(S[a]))
                    else:        # negative end: X̄ = X_b(n)⁻¹ X_a(s)
                        r[k] = np.linalg.solve(_pose(S[b]), _pose(row(a, b)))
                rel.append(r)
            for i in range(N):
                agents[i].jump(rel[i])
            published.append({k: v for ag in agents for k, v in ag.theta_owned.items()})
            u = np.zeros((N, 6))
            for i in range(N):
                nbrs, th_used = {}, {}
                for k, (a, b) in agents[i].local_edges.items():
                    j = b if a == i else a
                    nbrs[j] = row(j, i)[12:]
                    if a == j:
                        s = sample(n, j, i)
                        th_used[k] = published[s][k] if s >= 0 else theta0[k]
                u[i] = agents[i].wrench(rel[i], S[i, 12:], nbrs, th_used)
                agents[i].flow(rel[i], H)
            plant.apply(u)
            plant.advance(H)
        theta = {k: v for ag in agents for k, v in ag.theta_owned.items()}
        return plant.read().copy(), np.array([theta[k] for k in range(len(edges))])
    finally:
        plant.close()


def delayed_run(sc, n_steps):
    plant = make_plant("fleet", sc)
    try:
        ctrl = networked(sc, make_controller("hybrid", sc))
        Master(sc, plant, ctrl).run(n_steps)
        return plant.read().copy(), ctrl.theta.copy(), ctrl
    finally:
        plant.close()


@pytest.mark.parametrize("d", [1, 3, 7])
def test_delay_matches_agent_stepper_reference(d):
    n_steps = 60
    sc = scenario(f"delay = {d * H}")  # ⌈delay/h − 1e-9⌉ = d
    S_ref, th_ref = reference_run(sc, d, n_steps)
    S, th, ctrl = delayed_run(sc, n_steps)
    S0_ref, _ = reference_run(sc, 0, n_steps)
    gap = np.abs(S_ref - S0_ref).max()
    assert gap > 1e-5  # the delay changes the trajectory ...
    assert np.allclose(S, S_ref, rtol=0, atol=1e-9 * max(1.0, np.abs(S_ref).max()))  # ... as d
    assert np.allclose(th, th_ref, rtol=0, atol=1e-9)
    st = ctrl.network_stats()
    for link in st["links"]:
        assert link["sent"] == n_steps and link["lost"] == 0
        # ages: 1, 2, ..., d at start-up (S0 as sample 0), then d: p50 = p99 = d
        assert link["age_p50_steps"] == d and link["age_p99_steps"] == d
        assert link["age_p99_s"] == pytest.approx(d * H)


# ------------------------------------------------------------------ loss and jitter

def test_jitter_and_loss_use_the_newest_arrived_sample():
    """Against the reference fed, per link, with the newest sample whose message has arrived,
    found by brute force from the transit times the controller drew (−1: lost)."""
    n_steps = 60
    sc = scenario("delay = 0.008\njitter = 0.012\nloss = 0.3\nseed = 11")
    S, th, ctrl = delayed_run(sc, n_steps)
    sched = ctrl.sched[:n_steps].copy()          # (steps, links): transit steps or −1
    edges = [(int(a), int(b)) for a, b in sc.graph.edges]
    link = {}
    for k, (a, b) in enumerate(edges):
        link[(a, b)], link[(b, a)] = 2 * k, 2 * k + 1
    assert (sched < 0).any() and len(set(sched[sched >= 0].ravel())) > 1  # loss and jitter

    def sample(n, frm, to):
        col = sched[:n + 1, link[(frm, to)]]
        ok = [s for s in range(n + 1) if col[s] >= 0 and s + col[s] <= n]
        return max(ok) if ok else -1

    S_ref, th_ref = reference_run(sc, 0, n_steps, sample)
    assert np.allclose(S, S_ref, rtol=0, atol=1e-9 * max(1.0, np.abs(S_ref).max()))
    assert np.allclose(th, th_ref, rtol=0, atol=1e-9)
    # the age statistics: nearest-rank percentiles of the brute-force ages
    st = ctrl.network_stats()
    for frm_to, l in link.items():
        ages = np.sort([n - max(sample(n, *frm_to), 0) for n in range(n_steps)])
        rec = next(x for x in st["links"] if (x["from"] - 1, x["to"] - 1) == frm_to)
        assert rec["lost"] == int((sched[:, l] < 0).sum())
        assert rec["age_p50_steps"] == ages[math.ceil(0.5 * n_steps) - 1]
        assert rec["age_p99_steps"] == ages[math.ceil(0.99 * n_steps) - 1]


def test_loss_and_jitter_are_seeded_and_counted():
    net = "delay = 0.008\njitter = 0.012\nloss = 0.2\nseed = {}"
    a = run_scenario(scenario(net.format(1)))
    b = run_scenario(scenario(net.format(1)))
    c = run_scenario(scenario(net.format(2)))
    same_run(a, b)
    assert a["network"] == b["network"]
    assert a["final"] != c["final"]
    assert [x["lost"] for x in a["network"]["links"]] != [x["lost"] for x in c["network"]["links"]]
    n = a["steps"]
    d, jmax = 2, 3
    for link in a["network"]["links"]:
        assert link["sent"] == n
        # binomial(n, 0.2): within 5 standard deviations
        assert abs(link["lost"] - 0.2 * n) < 5 * math.sqrt(n * 0.2 * 0.8)
        assert d <= link["age_p50_steps"] <= link["age_p99_steps"]
        assert link["age_p99_s"] == pytest.approx(link["age_p99_steps"] * H)
    tot = a["network"]["total"]
    assert tot["sent"] == 10 * n and tot["lost"] == sum(x["lost"] for x in a["network"]["links"])
    # without loss the newest arrived sample is never older than d + J_max
    nl = run_scenario(scenario("delay = 0.008\njitter = 0.012\nseed = 1"))
    for link in nl["network"]["links"]:
        assert link["lost"] == 0 and d <= link["age_p50_steps"] and link["age_p99_steps"] <= d + jmax


def test_per_link_override_applies_to_that_direction_only():
    s = run_scenario(scenario("delay = 0.0\n[[network.link]]\nfrom = 3\nto = 2\ndelay = 0.02"))
    ages = {(x["from"], x["to"]): x["age_p50_steps"] for x in s["network"]["links"]}
    assert ages[(3, 2)] == 5
    assert all(v == 0 for k, v in ages.items() if k != (3, 2))


# ------------------------------------------------------------------ the age rule

def test_age_rule_holds_then_fails_safe_and_rejoins():
    sc_plain = scenario("delay = 0.02")                      # d = 5 steps
    sc_age = scenario("delay = 0.02\nmax_age = 0.008\nhold = 0.004")  # 2 steps, then 1 held
    ref = networked(sc_plain, make_controller("hybrid", sc_plain))
    ctrl = networked(sc_age, make_controller("hybrid", sc_age))
    kxi = sc_age.gains.k_xi
    S = sc_age.S0.copy()
    terms = None
    for n in range(8):
        S[:, 12:] += 0.01 * (n + 1)  # the own state moves; every agent's ξ is used fresh
        u_ref = ref.step_state(S, H)[0].copy()
        th_before = ctrl.theta.copy()
        u = ctrl.step_state(S, H)[0].copy()
        if n <= 2:      # ages 0..2 ≤ max_age: the law as without the rule
            assert np.array_equal(u, u_ref)
            terms = u + kxi * S[:, 12:]    # Σ of the edge terms, per agent
        elif n == 3:    # age 3: terms held at their last value, θ frozen
            assert np.allclose(u, -kxi * S[:, 12:] + terms, rtol=0, atol=1e-12)
            assert np.array_equal(ctrl.theta, th_before)
        else:           # age > max_age + hold: zero wrench
            assert np.array_equal(u, np.zeros_like(u))
    st = ctrl.network_stats()
    assert st["failsafe_steps"] == [4] * 6 and st["failsafe_entries"] == [1] * 6


def test_lossy_link_fails_safe_and_rejoins_without_restart():
    s = run_scenario(scenario("loss = 0.7\nseed = 4\nmax_age = 0.004\nhold = 0.0"))
    fs, entries = s["network"]["failsafe_steps"], s["network"]["failsafe_entries"]
    assert max(entries) > 1                     # entered, rejoined, entered again
    assert all(f < s["steps"] for f in fs)      # and spent steps out of fail-safe


# ------------------------------------------------------------------ parsing

def test_parse_defaults_and_endpoints():
    net = parse_network({}, 3)
    assert net.endpoints == (("127.0.0.1", 15600), ("127.0.0.1", 15601), ("127.0.0.1", 15602))
    assert net.max_age == math.inf and net.default.delay == 0 and net.default.loss == 0
    net = parse_network({"host": "10.0.0.1", "base_port": 20000,
                         "agent": [{"id": 2, "address": "10.0.0.9", "port": 7000}]}, 3)
    assert net.endpoints == (("10.0.0.1", 20000), ("10.0.0.9", 7000), ("10.0.0.1", 20002))
    net = parse_network({"delay": 0.1, "link": [{"from": 1, "to": 2, "loss": 0.5}]}, 2)
    assert net.link(1, 2).delay == 0.1 and net.link(1, 2).loss == 0.5
    assert net.link(2, 1).loss == 0.0


@pytest.mark.parametrize("table, key", [
    ({"delay": -0.1}, "delay"),
    ({"delay": float("nan")}, "delay"),
    ({"jitter": float("inf")}, "jitter"),
    ({"loss": 1.0}, "loss"),
    ({"loss": -0.1}, "loss"),
    ({"seed": -1}, "seed"),
    ({"base_port": 65535}, "base_port"),       # agents 2..3 would be past 65535
    ({"base_port": "x"}, "base_port"),
    ({"host": ""}, "host"),
    ({"max_age": 0}, "max_age"),
    ({"hold": -1}, "hold"),
    ({"colour": 1}, "colour"),
    ({"agent": [{"id": 4}]}, "agent[0].id"),
    ({"agent": [{"id": 1}, {"id": 1}]}, "agent[1].id"),
    ({"agent": [{"id": 1, "port": 70000}]}, "agent[0].port"),
    ({"agent": [{"id": 1, "port": 15601}]}, "agent"),   # the same endpoint as agent 2
    ({"agent": {"id": 1}}, "agent"),
    ({"link": [{"from": 1}]}, "link[0].to"),
    ({"link": [{"from": 1, "to": 1}]}, "link[0].to"),
    ({"link": [{"from": 1, "to": 2}, {"from": 1, "to": 2}]}, "link[1]"),
    ({"link": [{"from": 1, "to": 2, "loss": 2}]}, "link[0].loss"),
])
def test_parse_refuses_bad_values(table, key):
    with pytest.raises(ConfigError) as e:
        parse_network(table, 3)
    assert e.value.keypath == key


def test_cli_refuses_bad_network_on_one_line(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text(HIL + "\n[network]\nloss = 1.5\n")
    summ = tmp_path / "s.json"
    assert cli_main(["run", str(bad), "--summary", str(summ)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "network.loss" in err and "bad.toml" in err
    # a link between agents that are not neighbours (1 and 3: edges 1-2, 2-3)
    bad.write_text(HIL + "\n[network]\n[[network.link]]\nfrom = 1\nto = 3\n")
    assert cli_main(["run", str(bad), "--summary", str(summ), "--duration", "0.01"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "network.link[0]" in err and "not neighbours" in err
    assert not summ.exists()
