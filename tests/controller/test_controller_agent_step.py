"""`kernels.agent_step` (an agent's whole step over its neighbourhood, one compiled call) against
`AgentStepper` driven edge by edge as `bridge.swarm.agent` drives it (fresh edges jump, get their
terms and flow; stale ones hold their term and θ; fail-safe: zero wrench): bit for bit."""
from __future__ import annotations

import numpy as np
import pytest

import controller as C
from controller import layout, se3
from controller.kernels import FRESH, agent_step, relative_pose
from test_controller_law import paper_setup


class Reference:
    """Agent i's step on AgentStepper's dict interface (the agent process's reference path)."""

    def __init__(self, st: C.AgentStepper, ends: dict, rows: dict, theta_rx: dict):
        self.st, self.ends, self.rows = st, ends, rows
        self.term = {k: np.zeros(6) for k in ends}
        self.theta_rx = dict(theta_rx)

    def step(self, S, fresh: set, theta_rx: dict, h: float, failsafe: bool):
        st, i = self.st, self.st.agent
        rel = {}
        for k in fresh:
            a, b = self.ends[k]
            R, p = np.zeros((3, 3)), np.zeros(3)
            relative_pose(S, self.rows[a], S, self.rows[b], R, p)
            rel[k] = (R, p)
        events = st.jump(rel, [k for k in st.owned if k in fresh])
        self.theta_rx.update(theta_rx)
        xi = {j: S[r, layout.XI] for j, r in self.rows.items() if j != i}
        self.term.update(st.terms(rel, S[0, layout.XI], xi, self.theta_rx, fresh))
        u = np.zeros(6) if failsafe else st.wrench_of(S[0, layout.XI], self.term)
        mu = dict(st.last_mu)
        theta_jump = dict(st.theta)
        st.flow(rel, h, [k for k in st.owned if k in fresh])
        return u, events, mu, theta_jump


@pytest.mark.parametrize("hybrid", [True, False])
@pytest.mark.parametrize("agent", [1, 2, 3, 6])
@pytest.mark.parametrize("split", [False, True])
def test_agent_step_is_agent_stepper_bit_for_bit(agent, hybrid, split):
    g, wm, des, gains = paper_setup(Theta=(0.3 * np.pi, -0.3 * np.pi))
    rng = np.random.default_rng(100 * agent + hybrid)
    local = dict(g.local_edges(agent))
    nbrs = sorted(g.neighbours(agent))
    rows = {j: r for r, j in enumerate([agent, *nbrs])}
    ks = sorted(local)
    owned = [k for k in ks if local[k][0] == agent]
    theta0 = {k: float(rng.uniform(-1, 1)) for k in owned}
    st = C.AgentStepper(agent, local, wm, des if hybrid else None, gains, theta0=theta0)
    rx0 = {k: float(rng.uniform(-1, 1)) for k in ks if k not in owned}
    ref = Reference(C.AgentStepper(agent, local, wm, des if hybrid else None, gains,
                                   theta0=theta0), local, rows, rx0)
    # the compiled step's tables and buffers
    E = len(ks)
    ea = np.array([rows[local[k][0]] for k in ks], dtype=np.int64)
    eb = np.array([rows[local[k][1]] for k in ks], dtype=np.int64)
    own = np.array([k in owned for k in ks])
    nbr = np.array([nbrs.index(local[k][1] if k in owned else local[k][0]) for k in ks],
                   dtype=np.int64)
    mode = np.zeros(len(nbrs), dtype=np.int64)
    theta = np.array([st.theta.get(k, rx0.get(k)) for k in ks])
    rx = np.array([rx0.get(k, 0.0) for k in ks])
    theta_prev, theta_jump, mu = np.zeros(E), np.zeros(E), np.zeros(E)
    jumped = np.zeros(E, dtype=bool)
    term, rel = np.zeros((E, 6)), np.zeros((E, 12))
    u = np.zeros((len(rows), 6))
    h = 4e-3
    n_jumps = n_stale = n_fs = 0
    for n in range(150):
        S = C.pack_state(se3.random_pose(rng, len(rows), scale=2.0),
                         rng.standard_normal((len(rows), 6)))
        stale = rng.random(len(nbrs)) < 0.3
        mode[:] = np.where(stale, FRESH + 1, FRESH)
        failsafe = bool(stale.any() and rng.random() < 0.5)
        fresh = {k for k, q in zip(ks, nbr) if not stale[q]}
        new_rx = {k: float(rng.uniform(-2, 2)) for k in rx0}
        for r, k in enumerate(ks):
            if k in new_rx:
                rx[r] = new_rx[k]
        u_ref, ev_ref, mu_ref, thj_ref = ref.step(S, fresh, new_rx, h, failsafe)
        args = (S, ea, eb, own, nbr, mode, hybrid, st.P, h)
        out = (theta, rx, theta_prev, theta_jump, mu, jumped, term, rel, u)
        if split:    # lockstep: the jump stage, (θ published), then the law
            nj = agent_step(*args, 1, failsafe, *out)
            agent_step(*args, 2, failsafe, *out)
        else:
            nj = agent_step(*args, 3, failsafe, *out)
        assert u[0].tobytes() == u_ref.tobytes(), n
        assert not np.any(u[1:])
        for r, k in enumerate(ks):
            want = ref.st.theta[k] if k in owned else ref.theta_rx[k]
            assert theta[r] == want and np.float64(want).tobytes() == theta[r].tobytes(), (n, k)
            want_j = thj_ref[k] if k in owned else ref.theta_rx[k]
            assert theta_jump[r].tobytes() == np.float64(want_j).tobytes(), (n, k)
            m = mu_ref.get(k, np.nan) if k in owned else np.nan
            assert np.float64(m).tobytes() == mu[r].tobytes(), (n, k)
        events = [C.JumpEvent(ks[r], float(theta_prev[r]), float(theta_jump[r]), float(mu[r]))
                  for r in range(E) if jumped[r]]
        assert nj == len(events) and events == list(ev_ref), n
        n_jumps += nj
        n_stale += int(stale.any())
        n_fs += failsafe
    assert n_stale > 20 and n_fs > 3
    assert (n_jumps > 0) == (hybrid and bool(owned))
