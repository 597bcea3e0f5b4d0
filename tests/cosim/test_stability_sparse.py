"""The sparse/modal stability analysis against the dense one, and its pieces against mathematics."""
import numpy as np
import pytest

from cosim.analysis import stability as dense
from cosim.analysis import stability_sparse as F
from cosim.analysis.linear import edge_jacobian
from cosim.scenario import load_scenario, parse_scenario
from cosim.analysis.stability_cases import tree_edges, tree_scenario_text


def _tree(N, kind="random", seed=0, masses=None):
    return parse_scenario(tree_scenario_text(N, kind, seed, masses), "t", "t.toml")


@pytest.mark.parametrize("N,kind,seed,hetero", [(12, "random", 1, False), (20, "chain", 0, False),
                                                (15, "random", 2, True)])
def test_spectral_radius_equals_the_dense_analysis(N, kind, seed, hetero):
    masses = np.random.default_rng(seed).uniform(1.0, 4.0, N) if hetero else None
    sc = _tree(N, kind, seed, masses)
    for hybrid in (True, False):
        Kx, G = dense.linearise(sc, hybrid)
        lin = F.Linearisation(sc, hybrid)
        assert lin.method == ("sparse" if hetero else "modal")
        for h in (0.002, 0.004, 0.012, 0.03):     # stable and unstable steps
            ref = dense.spectral_radius(sc, h, Kx, G)
            assert abs(lin.spectral_radius(h) - ref) < 1e-9
            if not hetero:   # the general sparse path on the same case
                lin_s = F.Linearisation(sc, hybrid, force_sparse=True)
                assert abs(lin_s.spectral_radius(h) - ref) < 1e-9


def test_sparse_loop_is_the_dense_closed_loop():
    """Per-edge assembly + closed-form per-agent ZOH = dense FD Jacobian + expm, entry by entry."""
    sc = _tree(9, "random", 4, np.linspace(1.0, 3.0, 9))
    Kx, G = dense.linearise(sc, True)
    h = 0.004
    ref = dense.closed_loop(sc, h, Kx, G)
    got = F.sparse_loop(F.Linearisation(sc, True), h).toarray()
    assert np.abs(got - ref).max() < 1e-9 * max(1.0, np.abs(ref).max())


def test_modal_blocks_reproduce_the_whole_spectrum():
    """The SVD of B decouples the loop exactly: the union of the 13 × 13 blocks' eigenvalues,
    the common mode's six velocity eigenvalues and six 1's is the full matrix's spectrum."""
    sc = _tree(10, "random", 7)
    h = 0.004
    lin = F.Linearisation(sc, True)
    lam, com = lin.mode_eigenvalues(h)
    modal = np.concatenate([lam.ravel(), com, np.ones(6)])
    full = np.linalg.eigvals(F.sparse_loop(lin, h).toarray())
    assert modal.size == full.size
    # match greedily: every full eigenvalue has a modal partner (no sorting ambiguity)
    left = list(modal)
    for z in full:
        k = int(np.argmin(np.abs(np.array(left) - z)))
        assert abs(left[k] - z) < 1e-7     # six-fold eigenvalue 1 is defective: ~sqrt(eps)
        left.pop(k)


@pytest.mark.parametrize("kind", ["chain", "random", "star"])
def test_laplacian_eigenvalues_by_inertia_counts(kind):
    N = 600      # above the LAPACK cut-off, so the tree bisection runs
    if kind == "star":
        E = np.array([[0, k] for k in range(1, N)])
    else:
        E = np.array(tree_edges(N, kind, 5)) - 1
    lam = F.laplacian_eigenvalues(N, E)
    L = np.zeros((N, N))
    L[E[:, 0], E[:, 1]] = L[E[:, 1], E[:, 0]] = -1.0
    L[np.arange(N), np.arange(N)] = -L.sum(axis=1)
    tol = 1e-12 * (2 * np.abs(L).max() + 1)      # the bisection stops at 1e-13 of its range
    assert np.abs(lam - np.linalg.eigvalsh(L)).max() < tol
    if kind == "chain":   # path graph: 2 − 2cos(πk/N)
        assert np.abs(lam - np.sort(2 - 2 * np.cos(np.pi * np.arange(N) / N))).max() < 1e-11


def test_edge_jacobian_has_the_incidence_structure_on_the_paper_design():
    sc = load_scenario("scenarios/paper_6uav.toml")
    J, k_xi, has_state = edge_jacobian(sc, "hybrid")
    assert has_state and k_xi == sc.gains.k_xi
    assert F.modal_blocks(J) is not None
    # and K_δ is symmetric positive semidefinite-ish: −k_X times the Hessian of U at consensus
    Kd = F.modal_blocks(J)[0]
    assert np.abs(Kd - Kd.T).max() < 1e-6 * np.abs(Kd).max()


@pytest.mark.parametrize("hybrid", [True, False])
def test_the_law_linearised_from_its_own_step_is_the_kernels(hybrid):
    """`check` linearises a law through its `step_state` (cosim/analysis/linear.py); for the
    paper's two laws that is `network_step` on two agents with no jump possible (δ = ∞), as the
    analysis computed it before laws declared capabilities: the same arithmetic, the same bits."""
    from controller import LawParameters, se3
    from controller.kernels import network_step
    from controller.layout import pack_state

    sc = load_scenario("scenarios/hil_6uav.toml")
    P = LawParameters.of(sc.weighting, sc.design if hybrid else None, sc.gains, delta=np.inf).P
    edges = np.array([[0, 1]], dtype=np.int64)
    u, mu, tp, tj = np.zeros((2, 6)), np.zeros(1), np.zeros(1), np.zeros(1)
    jumped = np.zeros(1, dtype=np.bool_)

    def f(x):
        S = pack_state(se3.exp_se3(x[:12].reshape(2, 6)), x[12:24].reshape(2, 6))
        th = np.array([x[24]])
        network_step(S, th, edges, P, 1.0, hybrid, u, mu, jumped, tp, tj)
        return np.concatenate([u.ravel(), th - x[24:25]])

    ref = np.zeros((13, 25))
    for c in range(25 if hybrid else 24):
        e = np.zeros(25)
        e[c] = 1e-6
        ref[:, c] = (f(e) - f(-e)) / 2e-6
    ref[0:6, 12:18] += sc.gains.k_xi * np.eye(6)
    ref[6:12, 18:24] += sc.gains.k_xi * np.eye(6)
    if not hybrid:
        ref[12] = 0.0
    J, k_xi, has_state = edge_jacobian(sc, "hybrid" if hybrid else "gradient")
    assert has_state is hybrid and k_xi == sc.gains.k_xi
    assert np.array_equal(J, ref)


def test_thousand_agent_chain_is_analysed_without_dense_matrices():
    sc = _tree(1000, "chain")
    out = dense.analyse(sc, bisect=False)
    assert out["method"] == "modal" and out["stable"]
    # the slowest graph mode of a chain is λ₂ = 2 − 2cos(π/N): ρ must sit just below 1
    assert 1.0 - out["spectral_radius"] < 1e-6


def test_arpack_path_equals_dense(monkeypatch):
    """Heterogeneous agents above DENSE_MAX go to ARPACK on the rigid-projected operator."""
    N = 10
    sc = _tree(N, "random", 3, np.random.default_rng(3).uniform(1.0, 4.0, N))
    Kx, G = dense.linearise(sc, True)
    monkeypatch.setattr(F, "DENSE_MAX", 20)
    lin = F.Linearisation(sc, True)
    assert lin.method == "sparse"
    for h in (0.004, 0.03):
        assert abs(lin.spectral_radius(h) - dense.spectral_radius(sc, h, Kx, G)) < 1e-9
