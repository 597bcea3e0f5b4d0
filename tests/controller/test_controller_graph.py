"""Graph checks (Assumption 1), incidence matrices and Lemma 1."""
import numpy as np
import pytest
from scipy.linalg import expm

import controller as C
from controller import se3
from controller.graph import B_bar

from _paper import EDGES

rng = np.random.default_rng(5)


def random_tree(n):
    """A random labelled tree with random orientations."""
    edges = []
    perm = rng.permutation(n) + 1
    for k in range(1, n):
        parent = perm[rng.integers(0, k)]
        e = (int(perm[k]), int(parent))
        edges.append(e if rng.random() < 0.5 else e[::-1])
    return edges


def test_paper_graph_neighbour_sets():
    g = C.Graph(6, EDGES)
    assert [g.neighbours(i) for i in range(1, 7)] == [[2], [1, 3, 5], [2, 4], [3], [2, 6], [5]]
    assert g.M_plus(2) == [2, 4] and g.M_minus(2) == [1]
    B = g.B()
    assert B.shape == (6, 5)
    assert np.all(B.sum(axis=0) == 0) and np.all(np.abs(B).sum(axis=0) == 2)
    L = g.laplacian()
    assert np.allclose(np.diag(L), [len(g.neighbours(i)) for i in range(1, 7)])


@pytest.mark.parametrize("n,edges,pattern", [
    (4, [(1, 2), (2, 3), (3, 1), (3, 4)], r"cycle .*: 1 = \(1, 2\), 2 = \(2, 3\), 3 = \(3, 1\)"),
    (5, [(1, 2), (3, 4), (4, 5)], r"not connected .*agents \[3, 4, 5\] are not connected to agent 1"),
    (3, [(1, 2), (2, 2)], r"edge 2 = \(2, 2\) is a self-loop"),
    (3, [(1, 2), (2, 3), (2, 1)], r"edge 3 = \(2, 1\) duplicates edge 1"),
    (3, [(1, 2), (2, 4)], r"edge 2 = \(2, 4\) names agent 4, out of range 1..3"),
    (3, [(1, 2), (0, 3)], r"names agent 0, out of range"),
    (3, [(1, 2), (2.5, 3)], r"non-integer end"),
    (0, [], r"number of agents must be an integer ≥ 1"),
])
def test_graph_refusals_name_the_problem(n, edges, pattern):
    with pytest.raises(C.GraphError, match=pattern):
        C.Graph(n, edges)


def test_cycle_message_names_only_cycle_edges():
    with pytest.raises(C.GraphError) as ei:
        C.Graph(6, [(1, 2), (2, 3), (3, 4), (4, 5), (5, 6), (6, 4)])
    msg = str(ei.value)
    assert "4 = (4, 5)" in msg and "5 = (5, 6)" in msg and "6 = (6, 4)" in msg
    assert "1 = (1, 2)" not in msg


@pytest.mark.parametrize("n", [2, 3, 7, 20, 50])
def test_lemma1_full_column_rank_on_trees(n):
    for _ in range(3):
        edges = random_tree(n)
        g = C.Graph(n, edges)
        Xb = se3.random_pose(rng, n - 1, scale=3.0)
        Bb = g.B_bar(Xb)
        assert np.linalg.matrix_rank(Bb) == 6 * (n - 1)
        # and B̄ᵀ has exactly a 6-dimensional null space (`lem: HE`'s proof)
        assert np.linalg.matrix_rank(Bb.T) == 6 * n - 6


def test_lemma1_rank_drops_with_a_cycle():
    n = 8
    edges = random_tree(n)
    a, b_ = edges[0][0], edges[-1][1]
    extra = (a, b_) if a != b_ and frozenset((a, b_)) not in {frozenset(e) for e in edges} else (edges[0][0], edges[1][1])
    cyc = edges + [extra]
    M = len(cyc)
    X = se3.random_pose(rng, n, scale=2.0)
    # consistent relative poses X̄_k = X_j⁻¹X_i, as a real network would have
    Xb = np.array([np.linalg.inv(X[j - 1]) @ X[i - 1] for i, j in cyc])
    assert np.linalg.matrix_rank(B_bar(n, cyc, Xb)) < 6 * M


def test_bar_xi_equals_B_bar_transpose_xi():
    """`eqn:bar_xi` against a finite difference of X̄_k(t) = X_j(t)⁻¹X_i(t), X_i(t) = X_i exp(tξ_i^)."""
    n = 9
    g = C.Graph(n, random_tree(n))
    X = se3.random_pose(rng, n, scale=2.0)
    xi = rng.standard_normal((n, 6))
    s = 1e-6
    Xp = X @ np.array([expm(s * se3.hat(x)) for x in xi])
    Xm = X @ np.array([expm(-s * se3.hat(x)) for x in xi])
    Xb = g.relative_poses(X)
    dXb = (g.relative_poses(Xp) - g.relative_poses(Xm)) / (2 * s)
    xibar_fd = se3.vee(np.linalg.inv(Xb) @ dXb)
    xibar = (g.B_bar(Xb).T @ xi.ravel()).reshape(-1, 6)
    assert np.allclose(xibar, xibar_fd, atol=1e-7)
