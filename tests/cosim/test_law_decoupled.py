"""The third law, added through the seams only (cosim/laws/decoupled.py + one line in
cosim/registry.py): its equations against independent computations, its compiled loop against
its Python loop, `check` against a finite-difference linearisation of its own step, its swarm
against its run, and what a law without a capability is told."""
from __future__ import annotations

import json
import math
import os

import numpy as np
import pytest

os.environ.setdefault("MAVLINK20", "1")

from controller import GradientController, WeightingMatrix, layout, se3  # noqa: E402
from controller.errors import Se3SyncError  # noqa: E402
from controller.kernels import relative_pose  # noqa: E402
from cosim.analysis import stability as dense  # noqa: E402
from cosim.analysis.delay_margin import delay_margin  # noqa: E402
from cosim.controllers import agent_view, make_controller  # noqa: E402
from cosim.registry import LAWS  # noqa: E402
from cosim.scenario import load_scenario  # noqa: E402
from _bridge import HIL, load  # noqa: E402
from test_fastloop import PAPER, assert_same, random_tree_scenario, run_both  # noqa: E402

rng = np.random.default_rng(11)


def _random_S(n, vel=1.0):
    X = se3.random_pose(rng, n, scale=2.0)
    return layout.pack_state(X, vel * rng.standard_normal((n, 6)))


def _U_dec(sc, S):
    """k_X Σ_k U_dec(X̄_k) of (1), from the poses directly."""
    A, d = sc.weighting.A, sc.weighting.d
    R, p = layout.rotations(S), layout.positions(S)
    total = 0.0
    for i, j in np.asarray(sc.graph.edges):
        total += np.trace(A @ (np.eye(3) - R[j].T @ R[i])) + 0.5 * d * np.sum((p[i] - p[j]) ** 2)
    return sc.gains.k_X * total


def test_registered_by_one_line_and_declares_what_it_can_do():
    assert LAWS["decoupled"][0] == "cosim.laws.decoupled:make"
    sc = load_scenario(HIL)
    law = make_controller("decoupled", sc)
    assert law.name == "decoupled" and law.edge_state is None
    assert law.compiled_step() is not None and agent_view("decoupled", sc, 2).hybrid is False
    assert law.delayed_step().state is None


def test_its_potential_part_is_minus_half_kX_times_the_gradient_of_U_dec():
    """ξ = 0: u_i = −(k_X/2)∇_i Σ_k U_dec, ∇_i along X_i exp(ε e_c^) (central differences of the
    potential (1) computed from the poses, not from the law's formulas)."""
    sc = load_scenario(HIL)
    law = make_controller("decoupled", sc)
    S = _random_S(sc.graph.n, vel=0.0)
    u = law.step_state(S, sc.step)[0].copy()
    X = layout.poses(S)
    eps = 1e-6
    grad = np.zeros_like(u)
    for i in range(sc.graph.n):
        for c in range(6):
            e = np.zeros(6)
            e[c] = eps
            Xp, Xm = X.copy(), X.copy()
            Xp[i] = X[i] @ se3.exp_se3(e)
            Xm[i] = X[i] @ se3.exp_se3(-e)
            grad[i, c] = (_U_dec(sc, layout.pack_state(Xp)) - _U_dec(sc, layout.pack_state(Xm))) / (2 * eps)
    assert np.abs(u + 0.5 * grad).max() < 1e-6 * np.abs(grad).max()


def test_its_damping_is_the_relative_velocity_in_each_agents_own_frame():
    """u(ξ) − u(0) = −k_ξ ξ_i − k_e Σ_{k ∋ i} (ξ_i − R_iᵀR_j ξ_j), ω and v alike (the world-frame
    relative velocity ṗ_i − ṗ_j = R_i v_i − R_j v_j seen from agent i), from the rotations."""
    sc = load_scenario(HIL)
    law = make_controller("decoupled", sc)
    S = _random_S(sc.graph.n)
    S0 = S.copy()
    S0[:, layout.XI] = 0.0
    du = law.step_state(S, sc.step)[0].copy() - law.step_state(S0, sc.step)[0]
    R, xi = layout.rotations(S), S[:, layout.XI]
    g = sc.gains
    want = -g.k_xi * xi
    for i, j in np.asarray(sc.graph.edges):
        for a, b in ((i, j), (j, i)):
            Rab = R[a].T @ R[b]
            want[a] -= g.k_e * (xi[a] - np.concatenate([Rab @ xi[b, :3], Rab @ xi[b, 3:]]))
    assert np.abs(du - want).max() < 1e-11 * np.abs(want).max()


def test_without_the_coupling_b_and_at_rest_it_is_the_papers_gradient_law():
    """U_dec is the paper's U at θ = 0 with b removed: with ξ = 0 the wrench equals the gradient
    baseline's (`controller.GradientController`, the paper's kernels) on 𝔸 = [[A, 0], [0, d]]."""
    sc = load_scenario(HIL)
    law = make_controller("decoupled", sc)
    w0 = WeightingMatrix.from_blocks(sc.weighting.A, np.zeros(3), sc.weighting.d)
    paper = GradientController(sc.graph, w0, sc.gains)
    for _ in range(5):
        S = _random_S(sc.graph.n, vel=0.0)
        u = law.step_state(S, sc.step)[0].copy()
        ref = paper.step_state(S, sc.step)[0]
        assert np.abs(u - ref).max() < 1e-12 * np.abs(ref).max()


def test_its_per_agent_view_is_its_network_view():
    """Each agent from its own edges, relative poses, ξ and its neighbours' ξ only."""
    from cosim.analysis.stability_cases import tree_scenario_text
    from cosim.scenario import parse_scenario

    for sc in (load_scenario(HIL), parse_scenario(tree_scenario_text(15, "random", 4), "t", "t")):
        g = sc.graph
        law = make_controller("decoupled", sc)
        views = {i: agent_view("decoupled", sc, i) for i in range(1, g.n + 1)}
        for _ in range(10):
            S = _random_S(g.n)
            u = law.step_state(S, sc.step)[0]
            for i, v in views.items():
                assert v.jump({}) == () and v.theta_owned == {k: 0.0 for k in g.M_plus(i)}
                rel = {}
                for k, (a, b) in v.local_edges.items():
                    R, p = np.zeros((3, 3)), np.zeros(3)
                    relative_pose(S, a - 1, S, b - 1, R, p)
                    rel[k] = (R, p)
                nbrs = {j: S[j - 1, layout.XI] for j in g.neighbours(i)}
                ui = v.wrench(rel, S[i - 1, layout.XI], nbrs, {})
                assert np.abs(ui - u[i - 1]).max() <= 1e-12 * max(1.0, np.abs(u).max())


@pytest.mark.parametrize("case", ["paper", "tree50"])
def test_compiled_loop_equals_its_python_loop_bit_for_bit(tmp_path, case):
    from cosim.scenario import with_timing

    sc = (load_scenario(PAPER, ["simulation.duration=0.5", "simulation.log_rate=200"])
          if case == "paper" else with_timing(random_tree_scenario(50, 3), duration=0.3))
    ref, fast = run_both(sc, tmp_path, controller="decoupled")
    assert_same(ref, fast)
    assert ref[0]["controller"] == "decoupled" and ref[0]["n_jumps"] == 0
    assert all(s["theta"] == [0.0] * sc.graph.M for s in ref[0]["samples"])


def test_check_equals_a_finite_difference_linearisation_of_its_own_step():
    """`check`'s spectral radius (modal path, from the two-agent edge Jacobian) equals the dense
    loop built from central differences of the law's whole network step and `expm`; also on
    heterogeneous agents (the sparse path), and max_stable_step brackets ρ = 1 there."""
    from cosim.analysis.stability_cases import tree_scenario_text
    from cosim.scenario import parse_scenario

    homo = load_scenario(HIL)
    hetero = parse_scenario(tree_scenario_text(8, "random", 2, np.linspace(1.5, 3.5, 8)), "t", "t")
    for sc, method in ((homo, "modal"), (hetero, "sparse")):
        Kx, G = dense.linearise(sc, "decoupled")
        assert G.shape[0] == 0 and Kx.shape == (6 * sc.graph.n, 12 * sc.graph.n)
        for h in (sc.step, 0.012, 0.03):
            ref = dense.spectral_radius(sc, h, Kx, G)
            st = dense.analyse(sc, h, law="decoupled", bisect=False)
            assert st["method"] == method and abs(st["spectral_radius"] - ref) < 1e-9
        hmax = dense.analyse(sc, law="decoupled")["max_stable_step"]
        assert dense.spectral_radius(sc, hmax, Kx, G) < 1.0
        assert dense.spectral_radius(sc, hmax * 1.011, Kx, G) >= 1.0


def test_delay_margin_brackets_the_dense_delayed_loop_of_its_own_step():
    """The delay margin d (the loop with neighbour data d steps old) against the companion
    matrix of the delayed loop built from the dense finite-difference Jacobian of the law's own
    step, split into each agent's own columns (fresh) and its neighbours' (delayed)."""
    sc = load(["gains.k_X=30", "gains.k_e=1.0"])
    out = delay_margin(sc, law="decoupled")
    d = out["delay_margin_steps"]
    assert d is not None and 1 <= d < 40
    N, h = sc.graph.n, sc.step
    Kx, G = dense.linearise(sc, "decoupled")
    own = np.repeat(np.arange(N), 6)
    col_agent = np.concatenate([own, own])
    fresh = col_agent[None, :] == own[:, None]
    P0 = dense.closed_loop(sc, h, Kx * fresh, G)
    Pd = dense.closed_loop(sc, h, Kx * ~fresh, G) - dense.closed_loop(sc, h, 0 * Kx, G)

    def rho(dd):
        n = P0.shape[0]
        comp = np.zeros(((dd + 1) * n, (dd + 1) * n))
        comp[:n, :n] = P0 + (Pd if dd == 0 else 0)
        if dd:
            comp[:n, dd * n:] = Pd
            comp[n:, :-n] = np.eye(dd * n)
        lam = np.linalg.eigvals(comp)
        return float(np.abs(lam[np.argsort(np.abs(lam - 1.0))[6:]]).max())

    assert rho(d) < 1.0 <= rho(d + 1)


def test_a_law_without_a_capability_is_told_on_one_line(monkeypatch, capsys):
    from cosim.cli import main
    from cosim.network import networked

    monkeypatch.setitem(LAWS, "bare", ("test_law_decoupled:Bare", "step_state only"))
    sc = load_scenario(HIL)
    net = load(["network.delay=0.01"])
    with pytest.raises(Se3SyncError) as e:
        networked(net, make_controller("bare", net))
    msg = str(e.value)
    assert "\n" not in msg and "[network]" in msg and "'bare'" in msg and "delayed" in msg
    with pytest.raises(Se3SyncError, match=r"--controller: the law 'bare' has no per-agent view"):
        agent_view("bare", sc, 1)
    assert main(["swarm", HIL, "--controller", "bare", "--insecure", "--vehicles",
                 "loopback", "--lockstep"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "has no per-agent view" in err


# ------------------------------------------------------------------------------ [network]
def _moving_states(sc, n, seed=1):
    r = np.random.default_rng(seed)
    S = sc.S0.copy()
    out = []
    for _ in range(n):
        S = S.copy()
        S[:, :3] += 0.01 * r.standard_normal((sc.graph.n, 3))
        S[:, 12:] += 0.05 * r.standard_normal((sc.graph.n, 6))
        out.append(S)
    return out


def test_network_with_zero_delay_is_its_network_step_bit_for_bit():
    from cosim.network import NetworkController, networked

    sc = load(["network.delay=0.0"])
    ref = make_controller("decoupled", sc)
    ctrl = networked(sc, make_controller("decoupled", sc))
    assert isinstance(ctrl, NetworkController) and ctrl.edge_state is None
    for S in _moving_states(sc, 30):
        u_ref, _ = ref.step_state(S, sc.step)
        u, ev = ctrl.step_state(S, sc.step)
        assert np.array_equal(u, u_ref) and ev == ()
    assert ctrl.network_stats()["total"]["age_p99_steps"] == 0


@pytest.mark.parametrize("d", [1, 3])
def test_network_delay_is_each_agent_on_its_neighbours_rows_d_steps_old(d):
    """With every link d steps late, agent i's wrench is its per-agent view fed its own row of
    step n and each neighbour's row of step n − d (of step 0 before one has arrived)."""
    from cosim.network import networked

    sc = load([f"network.delay={d * 0.004 - 1e-6}"])
    ctrl = networked(sc, make_controller("decoupled", sc))
    views = {i: agent_view("decoupled", sc, i) for i in range(1, sc.graph.n + 1)}
    hist = _moving_states(sc, 25, seed=d)
    for n, S in enumerate(hist):
        u = ctrl.step_state(S, sc.step)[0]
        old = hist[max(n - d, 0)]
        for i, v in views.items():
            rel = {}
            for k, (a, b) in v.local_edges.items():
                R, p = np.zeros((3, 3)), np.zeros(3)
                if a == i:
                    relative_pose(S, a - 1, old, b - 1, R, p)
                else:
                    relative_pose(old, a - 1, S, b - 1, R, p)
                rel[k] = (R, p)
            nbrs = {j: old[j - 1, layout.XI] for j in sc.graph.neighbours(i)}
            ui = v.wrench(rel, S[i - 1, layout.XI], nbrs, {})
            assert np.abs(ui - u[i - 1]).max() <= 1e-12 * max(1.0, np.abs(u).max()), (n, i)


class Bare:
    """The decoupled law with nothing but the Controller protocol: no compiled step, no
    per-agent view, no θ (the gradient of a law someone writes first)."""

    name = "bare"

    def __init__(self, scenario):
        self._law = make_controller("decoupled", scenario)

    def step_state(self, S, h):
        return self._law.step_state(S, h)

    def reset(self, theta0=None):
        pass


def test_a_law_with_only_step_state_runs_and_is_checked(monkeypatch, tmp_path):
    """What a law gets for nothing: `run` (the Python loop, the same steps as the compiled loop of
    the full law, bit for bit) and `check` (linearised from its step)."""
    from cosim.run import run_scenario

    monkeypatch.setitem(LAWS, "bare", ("test_law_decoupled:Bare", "step_state only"))
    sc = load_scenario(PAPER, ["simulation.duration=0.3"])
    a = run_scenario(sc, controller="bare")
    b = run_scenario(sc, controller="decoupled")
    for k in ("wall_time_s", "realtime_factor", "us_per_step", "controller"):
        a.pop(k), b.pop(k)
    assert a == b
    hil = load_scenario(HIL)
    assert dense.analyse(hil, law="bare") == dense.analyse(hil, law="decoupled")


# ------------------------------------------------------------------------------ as agents
@pytest.mark.slow
@pytest.mark.timeout(300)
def test_lockstep_swarm_equals_its_run_on_the_float32_plant(tmp_path):
    from test_agents import _assert_equal_to_float32, _ports, _swarm

    from bridge.mavlink.transport import QuantizedPlant
    from cosim.run import run_scenario

    sets, _, _ = _ports()
    p, merged = _swarm(tmp_path, sets, "--lockstep", "--duration", "1.0", "--controller",
                       "decoupled")
    assert p.returncode == 0, p.stderr
    sc = load(sets, duration=1.0)
    plant = QuantizedPlant(sc)
    try:
        ref = run_scenario(sc, plant=plant, controller="decoupled")
    finally:
        plant.close()
    assert merged["controller"] == ref["controller"] == "decoupled"
    assert ref["n_jumps"] == 0 and ref["final"]["rot_err"] < ref["samples"][0]["rot_err"]
    _assert_equal_to_float32(merged, ref)
    assert merged["link_total"]["lost"] == 0 and merged["link_total"]["age_p99_steps_max"] == 0
    assert json.loads(json.dumps(merged))["agents_missing"] == [] and math.isfinite(merged["V0"])
