"""The hybrid law (`ex_controller`): paper initial conditions, the two views, the JIT switch,
and the Lyapunov function along an integrated closed loop."""
import json
import os
import subprocess
import sys
import textwrap
import warnings

import numpy as np
import pytest
from scipy.linalg import expm

import controller as C
from controller import potential, se3

from _paper import A, EDGES, GAINS, b, d, inertia, initial_poses, v_printed

rng = np.random.default_rng(3)


def paper_setup(Theta=(0.3 * np.pi,)):
    wm = C.WeightingMatrix.from_blocks(A, b, d)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        des = C.design_synergy(wm, Theta=list(Theta), gamma=0.33, delta=0.02, alpha_signs=(1, -1, 1))
    return C.Graph(6, EDGES), wm, des, C.Gains(**GAINS)


def random_state(n, scale=1.0, vel=1.0):
    X = se3.random_pose(rng, n, scale=scale)
    xi = vel * rng.standard_normal((n, 6))
    return X, xi


# ---------------------------------------------------------------- the paper's initial conditions
def test_paper_initial_conditions_lie_on_undesired_critical_points():
    g, wm, des, gains = paper_setup()
    lam, V = np.linalg.eigh(wm.W)
    v3 = V[:, 2] * np.sign(V[:, 2] @ v_printed)
    assert np.allclose(v3, v_printed / np.linalg.norm(v_printed), atol=1e-3)  # λ₃ eigenvector, up to the rounding of 𝔸 and v
    for v, tol in ((v3, 1e-10), (v_printed, None)):
        X = initial_poses(v, se3)
        Xb = g.relative_poses(X)
        Rpi = se3.R_a(np.pi, v / np.linalg.norm(v))
        assert np.allclose(Xb[:, :3, :3], Rpi, atol=1e-14)
        assert np.allclose(Xb[:, :3, 3], (np.eye(3) - Rpi) @ b / d, atol=1e-13)
        if tol is not None:  # exactly critical: ψ̄_∇ = 0, so the gradient baseline is stuck
            assert np.abs(potential.psi_bar_nabla(wm, des, Xb, 0.0)).max() < tol
            base = C.GradientController(g, wm, gains)
            xi = np.zeros((6, 6))
            for _ in range(3):
                u, ev = base.step(X, xi, 1e-4)
                assert ev == () and np.abs(u).max() < 1e-8


def test_hybrid_law_jumps_every_edge_to_0_3pi_at_t0():
    g, wm, des, gains = paper_setup()
    ctl = C.HybridController(g, wm, des, gains)
    u, ev = ctl.step(initial_poses(v_printed, se3), np.zeros((6, 6)), 1e-4)
    assert [e.edge for e in ev] == [1, 2, 3, 4, 5]
    assert all(e.theta_before == 0.0 and e.theta_after == pytest.approx(0.3 * np.pi) for e in ev)
    assert all(e.mu >= des.delta for e in ev)
    assert np.abs(u).max() > 1.0  # after the jump the wrench pushes off the critical point
    # a second step from the same place flows: θ moved by −h k_θ ∇_θU, no new jump
    _, ev2 = ctl.step(initial_poses(v_printed, se3), np.zeros((6, 6)), 1e-4)
    assert ev2 == ()


def test_baseline_never_jumps_and_keeps_theta_zero():
    g, wm, des, gains = paper_setup()
    base = C.GradientController(g, wm, gains)
    for _ in range(5):
        X, xi = random_state(6, 2.0)
        u, ev = base.step(X, xi, 1e-3)
        assert ev == () and np.all(base.theta == 0)
        # its wrench is the hybrid formula evaluated at θ = 0
        hyb = C.HybridController(g, wm, des, gains)
        hyb.P[C.law.K.P_DELTA] = np.inf  # disable jumps, keep θ = 0
        uh, _ = hyb.step(X, xi, 0.0)
        assert np.allclose(u, uh, atol=1e-12)


def test_wrench_matches_matrix_formula_of_ex_controller():
    """u_i = −k_X Σ_κ B̄_iκ ψ̄_∇(X̄_κ, θ_κ) − k_ξ ξ_i − k_e Σ_j (ξ_i − ξ_j) with B̄ and ψ̄_∇ from
    their 6×6 / 4×4 matrix definitions (`hybridcontroller`, `Bt_def`, `st_b`)."""
    g, wm, des, gains = paper_setup()
    ctl = C.HybridController(g, wm, des, gains)
    X, xi = random_state(6, 1.5)
    theta = rng.uniform(-0.5, 0.5, 5)
    ctl.reset(theta)
    ctl.P[C.law.K.P_DELTA] = np.inf
    u, _ = ctl.step(X, xi, 0.0)
    Xb = g.relative_poses(X)
    psi = []
    for Xk, t in zip(Xb, theta):
        Tu = expm(t * se3.hat(des.u_c))
        psi.append(np.linalg.inv(se3.Ad(Tu)).T @ se3.psi_bar((np.eye(4) - np.linalg.inv(Xk @ Tu)) @ wm.AA))
    L = g.laplacian()
    ref = (-gains.k_X * (g.B_bar(Xb) @ np.concatenate(psi)).reshape(6, 6) - gains.k_xi * xi
           - gains.k_e * (np.kron(L, np.eye(6)) @ xi.ravel()).reshape(6, 6))
    assert np.allclose(u, ref, atol=1e-10)


# ---------------------------------------------------------------- two views
def _run_agents(agents, g, X, xi, h):
    """Drive per-agent steppers through one communication point with only local information."""
    Xb = g.relative_poses(X)
    rel = {i: {k: Xb[k - 1] for k in ag.local_edges} for i, ag in agents.items()}
    events = []
    for i, ag in agents.items():
        events += ag.jump(rel[i])
    published = {k: th for ag in agents.values() for k, th in ag.theta_owned.items()}
    u = np.zeros((g.n, 6))
    for i, ag in agents.items():
        nbr_theta = {k: published[k] for k, (a, _) in ag.local_edges.items() if a != i}
        nbrs = {j: xi[j - 1] for k, (a, bb) in ag.local_edges.items() for j in (a, bb) if j != i}
        u[i - 1] = ag.wrench(rel[i], xi[i - 1], nbrs, nbr_theta)
        ag.flow(rel[i], h)
    return u, sorted(events)


@pytest.mark.parametrize("n", [6, 15])
def test_per_agent_view_equals_network_view(n):
    if n == 6:
        g, wm, des, gains = paper_setup(Theta=(0.3 * np.pi, -0.3 * np.pi))
    else:
        from test_controller_graph import random_tree
        g0, wm, des, gains = paper_setup(Theta=(0.3 * np.pi, -0.3 * np.pi))
        g = C.Graph(n, random_tree(n))
    theta0 = rng.uniform(-1, 1, g.M)
    net = C.HybridController(g, wm, des, gains, theta0=theta0)
    # each agent is built from its own edges only, never from the Graph object
    agents = {i: C.AgentStepper(i, dict(g.local_edges(i)), wm, des, gains,
                                theta0={k: theta0[k - 1] for k in g.M_plus(i)})
              for i in range(1, g.n + 1)}
    total_jumps = 0
    h = 1e-3
    for step in range(25):
        X, xi = random_state(g.n, 2.0)
        u_net, ev_net = net.step(X, xi, h)
        u_ag, ev_ag = _run_agents(agents, g, X, xi, h)
        scale = max(1.0, np.abs(u_net).max())
        assert np.abs(u_ag - u_net).max() <= 1e-12 * scale
        assert [e.edge for e in ev_net] == [e.edge for e in ev_ag]
        theta_ag = np.array([agents[g.edge_list[k][0]].theta[k + 1] for k in range(g.M)])
        assert np.allclose(theta_ag, net.theta, rtol=0, atol=1e-12)
        total_jumps += len(ev_net)
    assert total_jumps > 0  # the comparison covered jumps as well as flows


def test_agent_refuses_foreign_edge():
    g, wm, des, gains = paper_setup()
    with pytest.raises(C.Se3SyncError, match="edge 5 = \\(5, 6\\) is not one of its edges"):
        C.AgentStepper(1, {1: (1, 2), 5: (5, 6)}, wm, des, gains)


# ---------------------------------------------------------------- one implementation, JIT on or off
_SCRIPT = textwrap.dedent("""
    import json, sys, warnings
    import numpy as np
    sys.path.insert(0, {tests!r})
    import controller as C
    from controller import se3
    from _paper import A, b, d, EDGES, GAINS
    warnings.simplefilter("ignore")
    wm = C.WeightingMatrix.from_blocks(A, b, d)
    des = C.design_synergy(wm, Theta=[0.3 * np.pi, -0.7], gamma=0.33, delta=0.02)
    ctl = C.HybridController(C.Graph(6, EDGES), wm, des, C.Gains(**GAINS))
    rng = np.random.default_rng(99)
    out = []
    for _ in range(20):
        X = se3.random_pose(rng, 6, scale=2.0)
        xi = rng.standard_normal((6, 6))
        u, ev = ctl.step(X, xi, 1e-3)
        out.append([u.tolist(), ctl.theta.tolist(), [list(e) for e in ev]])
    print(json.dumps(out))
""")


def test_jit_and_plain_python_agree():
    here = os.path.dirname(os.path.dirname(__file__))
    script = _SCRIPT.format(tests=here)
    res = {}
    for flag in ("0", "1"):
        env = dict(os.environ, NUMBA_DISABLE_JIT=flag)
        r = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, r.stderr
        res[flag] = json.loads(r.stdout)
    n_events = 0
    for (u0, t0, e0), (u1, t1, e1) in zip(res["0"], res["1"]):
        assert np.allclose(u0, u1, rtol=1e-13, atol=1e-12)
        assert np.allclose(t0, t1, rtol=1e-13, atol=1e-14)
        assert [e[0] for e in e0] == [e[0] for e in e1]
        n_events += len(e0)
    assert n_events > 0


# ---------------------------------------------------------------- Lyapunov function
def _closed_loop_rhs(ctl, g, wm, des, I, X, xi, theta):
    """Continuous-time closed loop (`hybsys`, flow): Ẋ_i = X_iξ_i^, 𝕀ξ̇ = ad_ξᵀ𝕀ξ + u, θ̇ = −k_θ∇_θU."""
    ctl.theta[:] = theta
    u, ev = ctl.step(X, xi, 0.0)
    assert ev == ()
    xidot = np.array([np.linalg.solve(I, se3.ad(x).T @ I @ x + uu) for x, uu in zip(xi, u)])
    thdot = -ctl.gains.k_theta * potential.grad_theta_U(wm, des, g.relative_poses(X), theta)
    return xidot, thdot


def _Vbar(g, wm, des, gains, I, X, xi, theta):
    return C.V_bar(g, wm, des, gains, C.pack_state(X, xi), theta, I)


def test_Vbar_derivative_identity():
    """dV̄/dt = −k_X k_θ‖Ψ^θ‖² − 2k_ξ‖ξ‖² − 2k_e‖𝓑ξ‖² (`eqn:re_dot_V`), by central differences
    of V̄ along the exact flow directions."""
    g, wm, des, gains = paper_setup()
    I = inertia()
    ctl = C.HybridController(g, wm, des, gains)
    ctl.P[C.law.K.P_DELTA] = np.inf
    for _ in range(10):
        X, xi = random_state(6, 1.0, 0.5)
        theta = rng.uniform(-1, 1, 5)
        xidot, thdot = _closed_loop_rhs(ctl, g, wm, des, I, X, xi, theta)
        s = 1e-6
        Vp = _Vbar(g, wm, des, gains, I, X @ np.array([expm(s * se3.hat(x)) for x in xi]), xi + s * xidot, theta + s * thdot)
        Vm = _Vbar(g, wm, des, gains, I, X @ np.array([expm(-s * se3.hat(x)) for x in xi]), xi - s * xidot, theta - s * thdot)
        grad_th = potential.grad_theta_U(wm, des, g.relative_poses(X), theta)
        Bxi = (np.kron(g.B().T, np.eye(6)) @ xi.ravel())
        expected = (-gains.k_X * gains.k_theta * grad_th @ grad_th - 2 * gains.k_xi * np.sum(xi**2)
                    - 2 * gains.k_e * Bxi @ Bxi)
        assert (Vp - Vm) / (2 * s) == pytest.approx(expected, rel=1e-5, abs=1e-5)


def test_Vbar_non_increasing_along_integrated_flow():
    """RK4 on the group (stages X exp(c h K^)), the law evaluated at every stage, h = 5e-5."""
    g, wm, des, gains = paper_setup()
    I = inertia()
    ctl = C.HybridController(g, wm, des, gains)
    ctl.P[C.law.K.P_DELTA] = np.inf  # pure flow; jumps are tested separately
    X, xi = random_state(6, 0.7, 0.5)
    theta = rng.uniform(-0.3, 0.3, 5)
    h = 5e-5
    V = [_Vbar(g, wm, des, gains, I, X, xi, theta)]
    ex = lambda w, c: X @ np.array([expm(c * se3.hat(x)) for x in w])  # noqa: E731
    for _ in range(2000):
        k1x, (k1v, k1t) = xi, _closed_loop_rhs(ctl, g, wm, des, I, X, xi, theta)
        k2x = xi + h / 2 * k1v
        k2v, k2t = _closed_loop_rhs(ctl, g, wm, des, I, ex(k1x, h / 2), k2x, theta + h / 2 * k1t)
        k3x = xi + h / 2 * k2v
        k3v, k3t = _closed_loop_rhs(ctl, g, wm, des, I, ex(k2x, h / 2), k3x, theta + h / 2 * k2t)
        k4x = xi + h * k3v
        k4v, k4t = _closed_loop_rhs(ctl, g, wm, des, I, ex(k3x, h), k4x, theta + h * k3t)
        X = ex((k1x + 2 * k2x + 2 * k3x + k4x) / 6, h)
        xi = xi + h / 6 * (k1v + 2 * k2v + 2 * k3v + k4v)
        theta = theta + h / 6 * (k1t + 2 * k2t + 2 * k3t + k4t)
        V.append(_Vbar(g, wm, des, gains, I, X, xi, theta))
    V = np.array(V)
    assert np.all(np.diff(V) <= 1e-9 * V[0])
    assert V[-1] < 0.9 * V[0]  # and it did dissipate


def test_Vbar_drops_by_kX_delta_at_every_jump():
    g, wm, des, gains = paper_setup(Theta=(0.3 * np.pi, -0.6 * np.pi))
    I = inertia()
    ctl = C.HybridController(g, wm, des, gains)
    seen = 0
    for _ in range(200):
        X, xi = random_state(6, 2.0)
        theta = rng.uniform(-2, 2, 5)
        ctl.reset(theta)
        V0 = _Vbar(g, wm, des, gains, I, X, xi, theta)
        _, ev = ctl.step(X, xi, 1e-4)
        if not ev:
            continue
        seen += 1
        V1 = _Vbar(g, wm, des, gains, I, X, xi, ctl.theta_jump)
        assert V1 <= V0 - gains.k_X * des.delta * len(ev) + 1e-9
    assert seen > 20


def test_controller_V_bar_method_matches_function_and_baseline_refuses_theta0():
    g, wm, des, gains = paper_setup()
    X, xi = random_state(6, 1.0)
    S = C.pack_state(X, xi)
    th = rng.uniform(-1, 1, 5)
    ctl = C.HybridController(g, wm, des, gains, theta0=th)
    I = inertia()
    ref = gains.k_X * potential.U(wm, des, g.relative_poses(X), th).sum() + np.einsum("ni,ij,nj->", xi, I, xi)
    assert ctl.V_bar(S, I) == pytest.approx(ref, rel=1e-13)
    assert C.V_bar(g, wm, des, gains, S, th, I) == pytest.approx(ref, rel=1e-13)
    with pytest.raises(C.Se3SyncError, match="theta0 must be zero"):
        C.GradientController(g, wm, gains, theta0=th)


def test_jump_bound():
    g, wm, des, gains = paper_setup()
    X = initial_poses(v_printed, se3)
    V0 = C.V_bar(g, wm, des, gains, C.pack_state(X, np.zeros((6, 6))), np.zeros(5), inertia())
    n = C.jump_bound(V0, gains.k_X, des.delta)
    assert n == int(np.ceil(V0 / (gains.k_X * des.delta)))
    assert (n - 1) * gains.k_X * des.delta < V0 <= n * gains.k_X * des.delta
    assert n >= 5  # the five jumps at t = 0 fit in it


def test_wrench_written_into_a_given_buffer():
    g, wm, des, gains = paper_setup()
    X, xi = random_state(6, 1.0)
    ref, _ = C.HybridController(g, wm, des, gains).step(X, xi, 1e-4)
    ref = ref.copy()
    ctl = C.HybridController(g, wm, des, gains)
    buf = np.full((6, 6), np.nan)
    ctl.write_wrench_into(buf)
    u, _ = ctl.step(X, xi, 1e-4)
    assert u is buf and np.array_equal(buf, ref)
    for bad in (np.zeros((6, 5)), np.zeros((6, 6), dtype=np.float32), np.zeros((6, 12))[:, ::2]):
        with pytest.raises(C.Se3SyncError, match="wrench buffer"):
            ctl.write_wrench_into(bad)
