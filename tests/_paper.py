"""The paper's numbers (Section SIMULATION), shared by the controller tests."""
import numpy as np

A = np.array([[69.02, 56.08, 61.19], [56.08, 56.25, 51.17], [61.19, 51.17, 57.66]])
b = np.array([18.24, 14.43, 15.96])
d = 5.0
EDGES = [(1, 2), (2, 3), (3, 4), (2, 5), (5, 6)]
v_printed = np.array([0.2686, 0.8549, 0.4438])
mass = 2.4
J = np.diag([0.043, 0.041, 0.082])
GAINS = dict(k_X=100.0, k_xi=1.0, k_e=0.6, k_theta=1.0)


def inertia():
    I = np.zeros((6, 6))
    I[:3, :3] = J
    I[3:, 3:] = mass * np.eye(3)
    return I


def initial_poses(v, se3):
    """R_i(0) = R_a(−π/2, v) for odd i, R_a(+π/2, v) for even i; p_i(0) = (I − R_i(0)) b/d."""
    v = np.asarray(v, float) / np.linalg.norm(v)
    R = np.array([se3.R_a(-np.pi / 2 if i % 2 == 1 else np.pi / 2, v) for i in range(1, 7)])
    p = np.einsum("nij,j->ni", np.eye(3) - R, b / d)
    return se3.T(R, p)


def random_weighting(rng, case=None):
    """A random admissible 𝔸 = [[W + bbᵀ/d, b], [bᵀ, d]] whose W falls in the requested case."""
    while True:
        l1 = rng.uniform(0.2, 5.0)
        l3 = l1 * rng.uniform(1.2, 20.0)
        tau = l1 * l3 / (l3 - l1)
        if case == 1:
            l2 = l1
        elif case == 2:
            if tau >= l3:
                continue
            l2 = rng.uniform(tau, l3)
        elif case == 3:
            l2 = rng.uniform(l1 * (1 + 1e-3), min(tau, l3) * (1 - 1e-3))
        else:
            l2 = rng.uniform(l1, l3)
        if l2 >= l3 * (1 - 1e-6) and case != 1:
            continue
        q = rng.standard_normal(4)
        q /= np.linalg.norm(q)
        from controller import se3
        V = se3.quat_to_rot(q)
        W = V @ np.diag([l1, l2, l3]) @ V.T
        W = 0.5 * (W + W.T)
        bb = rng.standard_normal(3) * rng.uniform(0, 5)
        dd = rng.uniform(0.5, 10)
        return W + np.outer(bb, bb) / dd, bb, dd, (l1, l2, l3)
