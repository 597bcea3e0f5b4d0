"""The delay margin against direct simulations of the delayed loop.

Two independent simulations, each following the delay contract of `cosim.delay_margin`:
* hil_6uav (the main case): the linear delayed loop built here from the DENSE finite-difference
  Jacobian of `cosim.stability.linearise` (columns split into fresh/delayed by which agent they
  belong to) and the `expm` ZOH plant, simulated step by step with a history of d samples;
* hil_6uav with k_X = 30, k_e = 1 (a margin of a few steps): the NONLINEAR law, one kernel call
  per agent on its own fresh row and its neighbours' delayed rows and θ, with a rigid-body plant
  integrated by RK4 here.
Stable at d = ⌈0.8 d_max⌉, unstable at ⌈1.2 d_max⌉ (delays of 0.8× and 1.2× the margin in s).
"""
import functools
import math

import numpy as np
import pytest

from controller import LawParameters, se3
from controller.kernels import network_step
from cosim.analysis import stability as dense
from cosim.analysis.delay_margin import (augmented, delay_margin, delayed_loop, delayed_parts,
                                steps_of_delay)
from cosim.scenario import load_scenario
from cosim.analysis.stability_sparse import Linearisation, sparse_loop

HIL = "scenarios/hil_6uav.toml"


def _split_dense(sc):
    """(K₀, K_d, G₀, G_d) from the dense Jacobian: agent i's own δ_i, ξ_i and the θ_k it owns
    are fresh in its wrench; an edge's owner uses its own δ, ξ and θ_k fresh in θ_k's flow."""
    N, M = sc.graph.n, sc.graph.M
    E = np.asarray(sc.graph.edges)
    Kx, G = dense.linearise(sc, True)
    nx = 12 * N + M
    owner_of_col = np.empty(nx, dtype=int)       # agent a column belongs to (θ: its owner)
    owner_of_col[:6 * N] = np.repeat(np.arange(N), 6)
    owner_of_col[6 * N:12 * N] = np.repeat(np.arange(N), 6)
    owner_of_col[12 * N:] = E[:, 0]
    fresh_u = owner_of_col[None, :] == np.repeat(np.arange(N), 6)[:, None]
    fresh_g = owner_of_col[None, :] == E[:, 0][:, None]
    return Kx * fresh_u, Kx * ~fresh_u, G * fresh_g, G * ~fresh_g


def _linear_growth(sc, d, steps, seed=0):
    """‖relative state‖ at the end over its start, for the linear delayed loop built densely."""
    N, M = sc.graph.n, sc.graph.M
    h = sc.step
    K0, Kd, G0, Gd = _split_dense(sc)
    Phi_plant = dense.closed_loop(sc, h, np.zeros_like(K0), np.zeros_like(G0))  # A_d, θ ↦ θ
    Bd_K0 = dense.closed_loop(sc, h, K0, G0) - Phi_plant
    Bd_Kd = dense.closed_loop(sc, h, Kd, Gd) - Phi_plant
    E = np.asarray(sc.graph.edges)
    rng = np.random.default_rng(seed)
    s = np.zeros(12 * N + M)
    s[:6 * N] = 1e-3 * rng.standard_normal(6 * N)
    hist = [s.copy() for _ in range(d)]            # s(n − d), …, s(n − 1); s(< 0) = s(0)

    def rel(x):
        dl = x[:6 * N].reshape(N, 6)
        return np.concatenate([(dl[E[:, 0]] - dl[E[:, 1]]).ravel(), x[6 * N:]])

    e0 = np.linalg.norm(rel(s))
    for _ in range(steps):
        hist.append(s)                             # now hist[0] = s(n − d)
        s = Phi_plant @ s + Bd_K0 @ s + Bd_Kd @ hist.pop(0)
    return np.linalg.norm(rel(s)) / e0


def test_delay_margin_hil_matches_a_linear_simulation_built_from_the_dense_jacobian():
    sc = load_scenario(HIL)
    out = delay_margin(sc)
    dm = out["delay_margin_steps"]
    assert dm is not None and dm >= 1
    assert out["rho_at_margin"] < 1.0 <= out["rho_beyond"]
    assert out["delay_margin_s"] == pytest.approx(dm * sc.step)
    d_lo = steps_of_delay(0.8 * dm * sc.step, sc.step)
    d_hi = steps_of_delay(1.2 * dm * sc.step, sc.step)
    assert d_lo <= dm < d_hi
    assert _linear_growth(sc, d_lo, 20000) < 1e-2
    assert _linear_growth(sc, d_hi, 20000) > 1e2


def test_zero_delay_is_the_undelayed_loop():
    sc = load_scenario(HIL)
    lin = Linearisation(sc, True, force_sparse=True)
    P0, Pd = delayed_loop(lin, sc.step)
    assert abs((P0 + Pd) - sparse_loop(lin, sc.step)).max() < 1e-15
    assert abs(augmented(*delayed_parts(lin, sc.step), 0) - sparse_loop(lin, sc.step)).max() < 1e-15


def _plain_companion(lin, h, d):
    """The companion matrix of s(n+1) = Φ₀s(n) + Φ_d s(n−d) on (s(n), …, s(n−d)), dense."""
    P0, Pd = (m.toarray() for m in delayed_loop(lin, h))
    n = P0.shape[0]
    comp = np.zeros(((d + 1) * n, (d + 1) * n))
    comp[:n, :n], comp[:n, d * n:] = P0, Pd
    comp[n:, :-n] = np.eye(d * n)
    return comp


def test_reduced_history_has_the_companion_spectrum():
    """(s, w(n−1..n−d)) with w = C s against the plain companion matrix on (s(n), …, s(n−d))."""
    sc = load_scenario(HIL)
    lin = Linearisation(sc, True, force_sparse=True)
    d = 3
    comp = _plain_companion(lin, sc.step, d)
    big = np.sort(np.abs(np.linalg.eigvals(comp)))[::-1]
    red = augmented(*delayed_parts(lin, sc.step), d).toarray()
    red = np.sort(np.abs(np.linalg.eigvals(red)))[::-1]
    k = 50    # the dominant part of both spectra (the rest are zeros and tiny modes)
    assert np.abs(big[:k] - red[:k]).max() < 1e-8


def test_delay_radius_dense_equals_arpack(monkeypatch):
    """The two eigensolvers of `delay_radius` (dense below DENSE_MAX, ARPACK above) agree."""
    from cosim.analysis import delay_margin as dm

    sc = load_scenario(HIL)
    lin = Linearisation(sc, True, force_sparse=True)
    loop = delayed_parts(lin, sc.step)
    for d in (0, 5, 8):
        dense_r = dm.delay_radius(lin, sc.step, d, loop)
        monkeypatch.setattr(dm, "DENSE_MAX", 10)
        arpack_r = dm.delay_radius(lin, sc.step, d, loop)
        monkeypatch.undo()
        assert abs(dense_r - arpack_r) < 1e-10, (d, dense_r, arpack_r)


@pytest.mark.parametrize("sets", [["gains.k_X=30", "gains.k_e=1"], ["gains.k_X=20"],
                                  ["gains.k_X=30", "gains.k_e=1", "simulation.step=0.002"]])
def test_secant_search_finds_the_bisection_margin(sets):
    """`_probe`'s secant narrows the bracket to the same margin (and radii) as bisection, and the
    search started from `crossing_delay`'s guess ends there too."""
    sc = load_scenario(HIL, sets)
    lin = Linearisation(sc, True, force_sparse=True)
    a = delay_margin(sc, lin=lin, guess=False)
    b = delay_margin(sc, lin=lin, secant=False, guess=False)
    c = delay_margin(sc, lin=lin)
    assert a["delay_margin_steps"] == b["delay_margin_steps"] and a["delay_margin_steps"] >= 2
    assert a["rho_at_margin"] == b["rho_at_margin"] and a["rho_beyond"] == b["rho_beyond"]
    assert (c["delay_margin_steps"], c["rho_at_margin"], c["rho_beyond"]) == \
        (a["delay_margin_steps"], a["rho_at_margin"], a["rho_beyond"])


def _dense_transfer(loop, w):
    """T(e^{jω}) = C (e^{jω}I − Φ₀)⁻¹ B from one dense solve: the reference for `LoopTransfer`."""
    P0, B, C = (x.toarray() for x in loop)
    return C @ np.linalg.solve(np.exp(1j * w) * np.eye(P0.shape[0]) - P0, B)


def test_crossing_delay_predicts_the_root_that_leaves_the_circle():
    """The frequency-domain guess against the exact eigenproblems: on hil_6uav, ⌊τ⌋ is the
    margin the search finds without it, and the loop with one step more has an eigenvalue
    outside the unit circle at the angle ω where T(e^{jω}) has |μ| = 1 (LAPACK on the whole
    augmented matrix, the six rigid 1's set aside)."""
    from cosim.analysis import delay_margin as dm

    sc, lin, ref = _hil_without_guess()
    loop = delayed_parts(lin, sc.step)
    tau, w = dm.crossing_delay(*loop)
    assert math.floor(tau) == ref["delay_margin_steps"] == 24
    lam = np.linalg.eigvals(augmented(*loop, ref["delay_margin_steps"] + 1).toarray())
    out = lam[(np.abs(lam) > 1.0) & (np.abs(lam - 1.0) > 1e-6)]
    assert out.size and np.abs(np.abs(np.angle(out)) - w).min() < 0.02 * w, (w, out)
    # with d = τ the crossing root sits on the circle: T(e^{jω}) has μ with μ e^{−jωτ} ≈ 1
    T = _dense_transfer(loop, w)
    mu = np.linalg.eigvals(T)
    assert np.abs(mu * np.exp(-1j * w * tau) - 1.0).min() < 1e-4


def test_counted_crossing_floors_to_the_margin(tmp_path):
    """A 6-agent random tree (seed 3) on which following eigenvalues across the coarse grid put
    the crossing at τ = 34.04, one step past the margin (33): counting |μ| > 1 and bisecting the
    change gives a τ whose floor is the margin (ρ(33) < 1 ≤ ρ(34)), where T(e^{jω}) has an
    eigenvalue on the unit circle at angle ωτ, and the search needs only d = 0, ⌊τ⌋, ⌊τ⌋ + 1."""
    from cosim.analysis import delay_margin as dm
    from cosim.analysis.stability_cases import tree_scenario_text

    path = tmp_path / "tree.toml"
    path.write_text(tree_scenario_text(6, "random", 3))
    sc = load_scenario(str(path))
    lin = Linearisation(sc, True, force_sparse=True)
    loop = delayed_parts(lin, sc.step)
    tau, w = dm.crossing_delay(*loop)
    T = _dense_transfer(loop, w)
    assert np.abs(np.linalg.eigvals(T) * np.exp(-1j * w * tau) - 1.0).min() < 1e-4
    got = []
    out = delay_margin(sc, lin=lin, progress=lambda d, r, s: got.append(d))
    # 33 is also what the search without a guess finds (doubling to 64, then the secant; 15 s)
    assert math.floor(tau) == out["delay_margin_steps"] == 33
    assert out["rho_at_margin"] < 1.0 <= out["rho_beyond"]
    assert got == [0, 33, 34]


def _tree_loop(tmp_path, N, seed):
    from cosim.analysis.stability_cases import tree_scenario_text

    path = tmp_path / f"tree{N}_{seed}.toml"
    path.write_text(tree_scenario_text(N, "random", seed))
    sc = load_scenario(str(path))
    lin = Linearisation(sc, True, force_sparse=True)
    return sc, lin, delayed_parts(lin, sc.step)


def _same_multiset(a, b, tol):
    """Every element of a has one of b within tol, and the other way round (equal sizes)."""
    assert a.size == b.size
    dist = np.abs(a[:, None] - b[None, :])
    return dist.min(axis=1).max() < tol and dist.min(axis=0).max() < tol


def test_loop_transfer_per_block_equals_the_dense_solve_and_pairs_its_eigenvalues(tmp_path):
    """`LoopTransfer` on an 8-agent random tree: T(e^{jω}) from one solve per agent block equals
    C (e^{jω}I − Φ₀)⁻¹ B from a dense solve; the slots split into two sides with Σ T Σ = −T; and
    the eigenvalues of T are ±√ν for the eigenvalues ν of T₁₂T₂₁, plus zeros for the larger side."""
    from cosim.analysis import delay_margin as dm

    sc, lin, (P0, B, C) = _tree_loop(tmp_path, 8, 1)
    tf = dm.LoopTransfer(P0, B, C)
    m = C.shape[0]
    S = np.where(tf.side == 0, 1.0, -1.0)
    assert 0 < (tf.side == 0).sum() < m
    for w in (0.003, 0.03, 0.5, 3.0):
        ref = _dense_transfer((P0, B, C), w)
        T = tf.matrix(w)
        assert np.abs(T - ref).max() < 1e-12 * np.abs(ref).max()
        assert np.abs(S[:, None] * T * S[None, :] + T).max() == 0.0
        nu, p = tf.eigenvalues(w)
        assert p == 2
        mu = np.sqrt(nu.astype(complex))
        pairs = np.concatenate([mu, -mu, np.zeros(m - 2 * nu.size)])
        assert _same_multiset(np.linalg.eigvals(ref), pairs, 1e-7 * np.abs(ref).max())


@pytest.mark.parametrize("N, seed", [(6, 3), (10, 2)])
def test_paired_crossing_equals_the_one_from_t_itself(tmp_path, N, seed):
    """`crossing_delay` counting and matching ν = μ² finds the crossing it finds on the
    eigenvalues of T itself: the same frequency and delay (the bisections stop at different
    depths, hence 1e-3), the same floor."""
    from cosim.analysis import delay_margin as dm

    sc, lin, loop = _tree_loop(tmp_path, N, seed)
    tau, w = dm.crossing_delay(*loop)
    tau_full, w_full = dm.crossing_delay(*loop, paired=False)
    assert abs(tau - tau_full) < 1e-3 * tau and abs(w - w_full) < 1e-3 * w
    assert math.floor(tau) == math.floor(tau_full)


@pytest.mark.parametrize("N, seed", [(8, 0), (12, 1), (16, 2)])
def test_shallow_narrowing_finds_the_crossing_the_deep_one_finds(tmp_path, N, seed):
    """The default `NARROW_DEPTH` (3 halvings) finds the crossing 12 halvings find: the same
    floor of τ, τ and ω within 1e-3 relative, in fewer eigenproblems."""
    from cosim.analysis import delay_margin as dm

    sc, lin, loop = _tree_loop(tmp_path, N, seed)
    count = {}
    got = {}
    for depth in (dm.NARROW_DEPTH, 12):
        seen = []
        got[depth] = dm.crossing_delay(*loop, depth=depth, sweep=lambda k, g, n: seen.append(k))
        count[depth] = len(seen)
    (tau, w), (tau12, w12) = got[dm.NARROW_DEPTH], got[12]
    assert dm.NARROW_DEPTH < 12 and count[dm.NARROW_DEPTH] < count[12]
    assert math.floor(tau) == math.floor(tau12)
    assert abs(tau - tau12) < 1e-3 * tau12 and abs(w - w12) < 1e-3 * w12


def test_loop_transfer_where_an_agents_block_splits():
    """scenarios/sweep_small.toml: its gains leave parts of each agent's Φ₀ block uncoupled (12
    blocks for 4 agents) and B stores zeros where 𝕀⁻¹ is diagonal. T per block still equals the
    dense solve, the slots still split into two sides, and the search from the guess ends at
    the margin the search without it finds."""
    from cosim.analysis import delay_margin as dm
    from scipy.sparse.csgraph import connected_components

    sc = load_scenario("scenarios/sweep_small.toml")
    lin = Linearisation(sc, True, force_sparse=True)
    P0, B, C = delayed_parts(lin, sc.step)
    assert connected_components(abs(P0) + abs(P0.T), directed=False)[0] > lin.N
    assert (B.data == 0).any()
    tf = dm.LoopTransfer(P0, B, C)
    assert tf.side is not None
    for w in (0.01, 0.5):
        ref = _dense_transfer((P0, B, C), w)
        assert np.abs(tf.matrix(w) - ref).max() < 1e-12 * np.abs(ref).max()
    a, b = delay_margin(sc, lin=lin), delay_margin(sc, lin=lin, guess=False)
    assert a["delay_margin_steps"] == b["delay_margin_steps"] >= 1
    assert (a["rho_at_margin"], a["rho_beyond"]) == (b["rho_at_margin"], b["rho_beyond"])


def test_loop_transfer_falls_back_to_t_where_the_blocks_are_not_two_sided():
    """Three one-state blocks coupled in a triangle (not bipartite): no sides, and the
    eigenvalues returned are those of T itself."""
    import scipy.sparse as sp

    from cosim.analysis import delay_margin as dm

    P0 = sp.csr_matrix(np.diag([0.5, 0.2, -0.1]))
    C = sp.csr_matrix(np.ones((3, 3)) - np.eye(3))
    tf = dm.LoopTransfer(P0, sp.identity(3, format="csr"), C)
    assert tf.side is None
    w = 0.7
    T = C.toarray() @ np.linalg.inv(np.exp(1j * w) * np.eye(3) - P0.toarray())
    lam, p = tf.eigenvalues(w)
    assert p == 1 and _same_multiset(lam, np.linalg.eigvals(T), 1e-12)


def test_two_shift_invert_searches_give_lapacks_radius():
    """hil_6uav well below its margin (d = 1, 10), where the largest eigenvalue is a slow real
    mode near z = 1, and one step past it (d = 25), where it is the root that left the circle
    at the crossing angle: the larger modulus of the shift-invert searches near z = 1 and near
    e^{jω} equals LAPACK's radius on the whole augmented matrix, and each search is the one
    that finds it in its case."""
    from cosim.analysis import delay_margin as dm

    sc = load_scenario(HIL)
    lin = Linearisation(sc, True, force_sparse=True)
    loop = delayed_parts(lin, sc.step)
    tau, w = dm.crossing_delay(*loop)
    for d, which in ((1, 0), (10, 0), (25, 1)):
        near = (dm._radius_near(loop, 0.0, d), dm._radius_near(loop, w, d))
        exact = dm.delay_radius(lin, sc.step, d, loop)
        assert abs(near[which] - exact) < 1e-10 and near[1 - which] < exact - 1e-5, (d, near)


@pytest.mark.parametrize("d", [0, 1, 7])
def test_shift_inverse_from_the_small_lu_inverts_the_augmented_loop(d):
    """`_shift_inverse` (one LU of Φ₀ − σI + σ^{−d}BC, the delay line solved by recursion) is
    (A − σI)⁻¹ for the augmented A: applied to (A − σI)z it gives z back, for σ on the unit
    circle and just off it, and (A − σI) applied to its output gives y back."""
    from cosim.analysis import delay_margin as dm

    sc = load_scenario(HIL)
    loop = delayed_parts(Linearisation(sc, True, force_sparse=True), sc.step)
    A = augmented(*loop, d)
    m = A.shape[0]
    rng = np.random.default_rng(d)
    for sigma in (np.exp(0.03j), 1.0 + 1e-3, 0.7 - 0.2j):
        op = dm._shift_inverse(*loop, d, complex(sigma))
        assert op.shape == (m, m)
        z = rng.standard_normal(m) + 1j * rng.standard_normal(m)
        y = A @ z - sigma * z
        assert np.abs(op.matvec(y) - z).max() < 1e-8 * np.abs(z).max()
        x = op.matvec(z)
        assert np.abs(A @ x - sigma * x - z).max() < 1e-8 * np.abs(z).max()


def test_shift_invert_at_the_crossing_finds_the_root_largest_modulus_misses(tmp_path,
                                                                            monkeypatch):
    """A 12-agent random tree one step past its margin (d = 23, 2064 states, above DENSE_MAX):
    with the crossing angle, `delay_radius` gives the radius LAPACK gives on the whole augmented
    matrix (> 1). On this case ARPACK's largest-modulus search with 3 eigenvalues returned
    0.99928 (stable); that search (a stand-in returning 0.5 here, so that the test does not rest
    on ARPACK's random start) is what `delay_radius` falls back to without the angle."""
    from cosim.analysis import delay_margin as dm

    sc, lin, loop = _tree_loop(tmp_path, 12, 0)
    tau, w = dm.crossing_delay(*loop)
    d = math.floor(tau) + 1
    monkeypatch.setattr(dm, "DENSE_MAX", 10_000)
    exact = dm.delay_radius(lin, sc.step, d, loop)
    monkeypatch.undo()
    assert d == 23 and exact > 1.0 and augmented(*loop, d).shape[0] > dm.DENSE_MAX
    eigs = dm.sla.eigs

    def missing(op, **kw):       # the largest-modulus search runs on the real operator
        return np.full(kw["k"], 0.5 + 0j) if op.dtype == float else eigs(op, **kw)

    monkeypatch.setattr(dm.sla, "eigs", missing)
    assert dm.delay_radius(lin, sc.step, d, loop) == 0.5
    assert abs(dm.delay_radius(lin, sc.step, d, loop, near=w) - exact) < 1e-10


def test_margin_declines_above_the_sweeps_size_without_an_eigenproblem(monkeypatch):
    """Above `CROSSING_MAX` delayed inputs the guided search without counting (``count=False``;
    by default a tree's roots are counted instead, `test_delay_count`) declines at once (no
    eigenproblem, the count named), rather than fall back on the largest-modulus search; the
    reference search without a guess still runs."""
    from cosim.analysis import delay_margin as dm

    sc = load_scenario(HIL)
    lin = Linearisation(sc, True, force_sparse=True)
    m = delayed_parts(lin, sc.step)[2].shape[0]
    monkeypatch.setattr(dm, "CROSSING_MAX", m - 1)
    seen = []
    out = dm.delay_margin(sc, lin=lin, progress=lambda d, r, s: seen.append(d), count=False)
    assert out["delay_margin_steps"] is None and seen == []
    assert out["delay_method"].startswith(f"not computed: {m} delayed inputs, more than the {m - 1}")
    assert dm.crossing_delay(*delayed_parts(lin, sc.step)) is None
    monkeypatch.setattr(dm, "CROSSING_MAX", m)
    assert dm.crossing_delay(*delayed_parts(lin, sc.step)) is not None
    monkeypatch.setattr(dm, "CROSSING_MAX", m - 1)
    ref = dm.delay_margin(sc, lin=lin, guess=False, d_cap=4, count=False)
    assert ref["delay_margin_steps"] is None and ref["rho_at_margin"] < 1.0


def test_delay_method_names_each_solver_when_they_differ(monkeypatch):
    """With DENSE_MAX between the augmented sizes at the margin (24) and one step past it,
    the search gives the same margin and radii, and `delay_method` names both solvers."""
    from cosim.analysis import delay_margin as dm

    sc, lin, ref = _hil_without_guess()
    n0, m = dm.delayed_parts(lin, sc.step)[0].shape[0], dm.delayed_parts(lin, sc.step)[2].shape[0]
    monkeypatch.setattr(dm, "DENSE_MAX", n0 + 24 * m)
    out = dm.delay_margin(sc, lin=lin)
    assert (out["delay_margin_steps"], out["rho_at_margin"]) == \
        (ref["delay_margin_steps"], ref["rho_at_margin"])
    assert abs(out["rho_beyond"] - ref["rho_beyond"]) < 1e-10
    assert "d = 24: dense eigvals; d = 25: shift-invert ARPACK near z = 1 and near the " \
           "crossing angle" in out["delay_method"], out["delay_method"]


@functools.lru_cache(maxsize=1)
def _hil_without_guess():
    sc = load_scenario(HIL)
    lin = Linearisation(sc, True, force_sparse=True)
    return sc, lin, delay_margin(sc, lin=lin, guess=False)


@pytest.mark.parametrize("tau", [3.5, 20.5, 40.5])
def test_a_wrong_guess_still_ends_at_the_margin(monkeypatch, tau):
    """A guess far below the margin (24), just below it and far above it: the search recovers
    from each and ends with the same margin and radii as the search without a guess."""
    from cosim.analysis import delay_margin as dm

    sc, lin, ref = _hil_without_guess()
    monkeypatch.setattr(dm, "crossing_delay", lambda *a, **k: (tau, 0.1))
    got = []
    out = dm.delay_margin(sc, lin=lin, progress=lambda d, r, s: got.append(d))
    assert (out["delay_margin_steps"], out["rho_at_margin"], out["rho_beyond"]) == \
        (ref["delay_margin_steps"], ref["rho_at_margin"], ref["rho_beyond"])
    assert got[1] == math.floor(tau)            # the guess is probed first, after d = 0


def test_ten_agent_tree_radius_equals_the_plain_companion_spectrum():
    """A 10-agent random tree (hil_6uav's bodies and gains): `delay_radius` at d = 6 equals the
    largest eigenvalue modulus of the plain companion matrix on (s(n), …, s(n−d)) once the six
    rigid-motion eigenvalues 1 are set aside, computed here with LAPACK on the whole matrix."""
    import random

    from cosim.analysis import delay_margin as dm

    rnd = random.Random(4)
    edges = ", ".join(f"[{i + 1}, {rnd.randrange(1, i + 1)}]" for i in range(1, 10))
    sc = load_scenario(HIL, ["agents.count=10", f"graph.edges=[{edges}]"])
    lin = Linearisation(sc, True, force_sparse=True)
    d = 6
    comp = _plain_companion(lin, sc.step, d)
    n = comp.shape[0] // (d + 1)
    lam = np.linalg.eigvals(comp)
    mods = np.sort(np.abs(lam[np.abs(lam - 1.0) > 1e-6]))[::-1]
    assert np.sum(np.abs(lam - 1.0) <= 1e-6) == 6
    r = dm.delay_radius(lin, sc.step, d)
    assert abs(r - mods[0]) < 1e-9, (r, mods[:3])
    assert (lin.N, n + d * dm.delayed_parts(lin, sc.step)[2].shape[0]) == (10, 129 + 6 * 69)


def test_steps_of_delay():
    assert steps_of_delay(0.0, 0.004) == 0
    assert steps_of_delay(0.004, 0.004) == 1        # exactly one step, despite rounding
    assert steps_of_delay(0.004 * 3, 0.004) == 3
    assert steps_of_delay(0.0041, 0.004) == 2


# ---- nonlinear law with delayed neighbour data -------------------------------------------


def _rigid_body_rk4(S, u, J, m, h):
    """One RK4 step of Ṙ = Rω^, ṗ = Rv, Jω̇ = Jω×ω + τ, m v̇ = m v×ω + f (ξ = [ω; v])."""
    def f(y):
        p, R, w, v = y
        dp = np.einsum("nab,nb->na", R, v)
        dR = R @ _hat(w)
        Jw = np.einsum("nab,nb->na", J, w)
        dw = np.linalg.solve(J, (np.cross(Jw, w) + u[:, :3])[..., None])[..., 0]
        dv = np.cross(v, w) + u[:, 3:] / m[:, None]
        return dp, dR, dw, dv

    y = (S[:, 0:3].copy(), S[:, 3:12].reshape(-1, 3, 3).copy(), S[:, 12:15].copy(),
         S[:, 15:18].copy())
    k1 = f(y)
    k2 = f(tuple(a + 0.5 * h * b for a, b in zip(y, k1)))
    k3 = f(tuple(a + 0.5 * h * b for a, b in zip(y, k2)))
    k4 = f(tuple(a + h * b for a, b in zip(y, k3)))
    y = tuple(a + h / 6 * (b + 2 * c + 2 * e + g) for a, b, c, e, g in zip(y, k1, k2, k3, k4))
    out = np.empty_like(S)
    out[:, 0:3], out[:, 3:12] = y[0], y[1].reshape(-1, 9)
    out[:, 12:15], out[:, 15:18] = y[2], y[3]
    return out


def _hat(w):
    Z = np.zeros(w.shape[:-1] + (3, 3))
    Z[..., 0, 1], Z[..., 0, 2], Z[..., 1, 2] = -w[..., 2], w[..., 1], -w[..., 0]
    Z[..., 1, 0], Z[..., 2, 0], Z[..., 2, 1] = w[..., 2], -w[..., 1], w[..., 0]
    return Z


def _nonlinear_growth(sc, d, steps, seed=1):
    N, M = sc.graph.n, sc.graph.M
    E = np.asarray(sc.graph.edges)
    h = sc.step
    P = LawParameters.of(sc.weighting, sc.design, sc.gains).P
    rng = np.random.default_rng(seed)
    X = se3.exp_se3(1e-4 * rng.standard_normal((N, 6)))
    S = np.zeros((N, 18))
    S[:, 0:3] = X[:, :3, 3]
    S[:, 3:12] = X[:, :3, :3].reshape(N, 9)
    theta = np.zeros(M)
    inc = [[k for k in range(M) if i in E[k]] for i in range(N)]
    S_hist = [S.copy() for _ in range(d)]           # published rows of steps n − d … n − 1
    th_hist = [theta.copy() for _ in range(d)]      # published θ (after the jump stage)

    def err(S, theta):
        R = S[:, 3:12].reshape(N, 3, 3)
        Rb = np.einsum("kea,kec->kac", R[E[:, 1]], R[E[:, 0]])
        pb = np.einsum("kea,ke->ka", R[E[:, 1]], S[E[:, 0], :3] - S[E[:, 1], :3])
        return math.sqrt(((np.eye(3) - Rb) ** 2).sum() + (pb ** 2).sum() + (theta ** 2).sum()
                         + (S[:, 12:] ** 2).sum())

    e0 = err(S, theta)
    for _ in range(steps):
        S_hist.append(S)                  # rows are published at once, θ after its jump stage
        Sd = S_hist.pop(0)                # = S(n − d)
        # near consensus no jump fires (asserted below), so θ after the jump stage is θ(n)
        th_hist.append(theta.copy())
        thd = th_hist.pop(0)
        u = np.zeros((N, 6))
        th_new = theta.copy()
        for i in range(N):
            nb = [int(E[k, 1] if E[k, 0] == i else E[k, 0]) for k in inc[i]]
            rows = [i] + nb
            S_loc = np.ascontiguousarray(np.vstack([S[i]] + [Sd[j] for j in nb]))
            loc = {a: b for b, a in enumerate(rows)}
            e_loc = np.array([[loc[int(E[k, 0])], loc[int(E[k, 1])]] for k in inc[i]],
                             dtype=np.int64).reshape(-1, 2)
            th_loc = np.array([theta[k] if E[k, 0] == i else thd[k] for k in inc[i]])
            m_ = len(inc[i])
            u_loc = np.zeros((len(rows), 6))
            jumped = np.zeros(m_, dtype=np.bool_)
            network_step(S_loc, th_loc, e_loc, P, h, True, u_loc, np.zeros(m_), jumped,
                           np.zeros(m_), np.zeros(m_))
            assert not jumped.any()
            u[i] = u_loc[0]
            for c, k in enumerate(inc[i]):
                if E[k, 0] == i:           # the owner flows θ_k
                    th_new[k] = th_loc[c]
        S = _rigid_body_rk4(S, u, sc.inertias, sc.masses, h)
        theta = th_new
    return err(S, theta) / e0


def test_delay_margin_matches_the_nonlinear_law_with_delayed_neighbour_data():
    sc = load_scenario(HIL, ["gains.k_X=30", "gains.k_e=1"])
    out = delay_margin(sc)
    dm = out["delay_margin_steps"]
    assert dm is not None and dm >= 2
    d_lo = steps_of_delay(0.8 * dm * sc.step, sc.step)
    d_hi = steps_of_delay(1.2 * dm * sc.step, sc.step)
    assert _nonlinear_growth(sc, d_lo, 4000) < 0.1
    assert _nonlinear_growth(sc, d_hi, 4000) > 10.0


def test_interruptible_runs_the_eigenproblem_beside_a_waiting_thread():
    """The value and the exception of fn come back; fn runs in another thread; and an interrupt
    reaches the waiting caller while fn is still running (a 4000-state eigvals is one 20–30 s
    LAPACK call that would otherwise hold Ctrl-C and SIGTERM until it returns)."""
    import _thread
    import threading

    from cosim.signals import interruptible

    A = np.diag([0.5, -2.0, 1.5])
    assert sorted(np.abs(interruptible(np.linalg.eigvals, A))) == [0.5, 1.5, 2.0]
    assert interruptible(threading.get_ident) != threading.get_ident()
    boom = ValueError("from the worker")

    def fail():
        raise boom

    with pytest.raises(ValueError) as info:
        interruptible(fail)
    assert info.value is boom
    release = threading.Event()
    started = threading.Event()

    def blocked():
        started.set()
        release.wait()
        return 1

    threading.Thread(target=lambda: (started.wait(), _thread.interrupt_main()),
                     daemon=True).start()
    with pytest.raises(KeyboardInterrupt):
        interruptible(blocked)
    assert not release.is_set()          # fn was still running when the caller let go
    release.set()
