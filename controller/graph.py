"""The interaction graph: N agents, M oriented edges, Assumption 1 (connected and acyclic).

Agents and edges are numbered from 1, as in the paper; edge k = (i, j) has i as its positive
end and j as its negative end, and X̄_k = X_j⁻¹ X_i.
"""
from __future__ import annotations

import numpy as np

from . import se3
from .errors import GraphError

__all__ = ["Graph", "B_bar"]


def B_bar(n: int, edge_list, Xbar) -> np.ndarray:
    """B̄(X̄) ∈ ℝ^{6N×6M} (`Bt_def`): I₆ at the positive end, −Ad⁻ᵀ_{X̄_k} at the negative.

    Takes any edge list (no Assumption 1 check), so Lemma 1 can be probed on cyclic graphs.
    """
    M = len(edge_list)
    Xbar = np.asarray(Xbar, float).reshape(M, 4, 4)
    out = np.zeros((6 * n, 6 * M))
    AdT = se3.Ad_inv_T(Xbar)
    for k, (i, j) in enumerate(edge_list):
        out[6 * (i - 1):6 * i, 6 * k:6 * k + 6] = np.eye(6)
        out[6 * (j - 1):6 * j, 6 * k:6 * k + 6] = -AdT[k]
    return out


class Graph:
    """An oriented tree on agents 1..N (`assum:1`)."""

    def __init__(self, n_agents: int, edges):
        if isinstance(n_agents, bool) or not isinstance(n_agents, (int, np.integer)) or n_agents < 1:
            raise GraphError(f"graph: the number of agents must be an integer ≥ 1, got {n_agents!r}")
        n = int(n_agents)
        pairs = []
        for k, e in enumerate(edges, start=1):
            try:
                i, j = e
            except (TypeError, ValueError):
                raise GraphError(f"graph: edge {k} must be a pair (positive end, negative end), got {e!r}") from None
            for end in (i, j):
                if isinstance(end, bool) or not isinstance(end, (int, np.integer)):
                    raise GraphError(f"graph: edge {k} = {tuple(e)!r} has a non-integer end {end!r}")
                if not 1 <= end <= n:
                    raise GraphError(
                        f"graph: edge {k} = ({i}, {j}) names agent {end}, out of range 1..{n}")
            if i == j:
                raise GraphError(f"graph: edge {k} = ({i}, {j}) is a self-loop")
            pairs.append((int(i), int(j)))
        seen = {}
        for k, (i, j) in enumerate(pairs, start=1):
            key = frozenset((i, j))
            if key in seen:
                raise GraphError(
                    f"graph: edge {k} = ({i}, {j}) duplicates edge {seen[key]} = "
                    f"{pairs[seen[key] - 1]}")
            seen[key] = k
        # Union-find: the first edge joining two agents already connected closes a cycle.
        parent = list(range(n + 1))

        def find(x):
            while parent[x] != x:
                parent[x] = parent[parent[x]]
                x = parent[x]
            return x

        adj = {a: [] for a in range(1, n + 1)}
        for k, (i, j) in enumerate(pairs, start=1):
            ri, rj = find(i), find(j)
            if ri == rj:
                cycle = [k] + self._tree_path(adj, i, j)
                names = ", ".join(f"{c} = {pairs[c - 1]}" for c in sorted(cycle))
                raise GraphError(
                    f"graph: edges form a cycle (Assumption 1 needs an acyclic graph): {names}")
            parent[ri] = rj
            adj[i].append((j, k))
            adj[j].append((i, k))
        roots = {find(a) for a in range(1, n + 1)}
        if len(roots) > 1:
            root1 = find(1)
            other = sorted(a for a in range(1, n + 1) if find(a) != root1)
            comp = [a for a in other if find(a) == find(other[0])]
            raise GraphError(
                f"graph: not connected (Assumption 1): agents {comp} are not connected to agent 1")
        self.n = n
        self.M = len(pairs)
        self.edge_list = tuple(pairs)
        # 0-based (positive, negative) pairs for the kernels.
        self.edges = np.array(pairs, dtype=np.int64).reshape(-1, 2) - 1

    @staticmethod
    def _tree_path(adj, src, dst):
        """Edge numbers on the unique path src → dst in the forest built so far."""
        stack = [(src, None, [])]
        while stack:
            node, par, path = stack.pop()
            if node == dst:
                return path
            for nxt, k in adj[node]:
                if nxt != par:
                    stack.append((nxt, node, path + [k]))
        return []

    def M_plus(self, i: int) -> list[int]:
        """Edges whose positive end is agent i (the θ_k agent i owns)."""
        return [k for k, (a, _) in enumerate(self.edge_list, start=1) if a == i]

    def M_minus(self, i: int) -> list[int]:
        return [k for k, (_, b) in enumerate(self.edge_list, start=1) if b == i]

    def M_i(self, i: int) -> list[int]:
        return sorted(self.M_plus(i) + self.M_minus(i))

    def neighbours(self, i: int) -> list[int]:
        """𝒩_i, ascending."""
        out = [b for a, b in self.edge_list if a == i] + [a for a, b in self.edge_list if b == i]
        return sorted(out)

    def local_edges(self, i: int) -> dict:
        """{k: (positive, negative)} for the edges of agent i: all an agent knows of the graph."""
        return {k: self.edge_list[k - 1] for k in self.M_i(i)}

    def B(self) -> np.ndarray:
        """Incidence matrix B ∈ ℝ^{N×M} (`B_def`)."""
        B = np.zeros((self.n, self.M))
        for k, (i, j) in enumerate(self.edge_list):
            B[i - 1, k] = 1.0
            B[j - 1, k] = -1.0
        return B

    def B_bar(self, Xbar) -> np.ndarray:
        """B̄(X̄) ∈ ℝ^{6N×6M} (`Bt_def`)."""
        return B_bar(self.n, self.edge_list, Xbar)

    def relative_poses(self, X) -> np.ndarray:
        """X̄_k = X_j⁻¹ X_i for every edge, from absolute poses X (N, 4, 4)."""
        X = np.asarray(X, float)
        return se3.inverse(X[self.edges[:, 1]]) @ X[self.edges[:, 0]]

    def laplacian(self) -> np.ndarray:
        B = self.B()
        return B @ B.T

    def __repr__(self):
        return f"Graph(n_agents={self.n}, edges={list(self.edge_list)})"
