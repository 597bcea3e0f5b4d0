"""Physics of the plant FMU: invariants, SO(3) preservation, order 4, closed forms, reference."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from plant_fmu import build
from plant_fmu.fast import FleetFMU

J_ASYM = np.array([[2.0, 0.1, -0.05], [0.1, 3.0, 0.2], [-0.05, 0.2, 4.0]])


def hat(w):
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def expm_so3(w):
    th = np.linalg.norm(w)
    K = hat(w / th)
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K


def random_rotation(seed):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


@pytest.fixture(scope="module")
def fmu1():
    return build.fmu_path(1)


def make(fmu1, *, J=J_ASYM, m=1.5, p0=(1.0, 2.0, 3.0), R0=None, xi0=(1.0, -2.0, 0.5, 0.3, 0.1, -0.2),
         g=(0.0, 0.0, 0.0), h_internal=None):
    f = FleetFMU(1, fmu_path=fmu1)
    f.set_parameters(mass=[m], J=[J], p0=[p0], R0=[np.eye(3) if R0 is None else R0], xi0=[xi0], gravity=g,
                     h_internal=h_internal)
    f.initialize()
    return f


def split(x):
    return x[0:3].copy(), x[3:12].reshape(3, 3).copy(), x[12:15].copy(), x[15:18].copy()


def test_torque_free_invariants(fmu1):
    m = 1.5
    with make(fmu1, m=m, R0=random_rotation(1)) as f:
        def invariants():
            p, R, w, v = split(f.get_state()[0])
            E = 0.5 * w @ J_ASYM @ w + 0.5 * m * v @ v
            P = m * R @ v
            L = R @ J_ASYM @ w + np.cross(p, P)
            return E, P, L

        E0, P0, L0 = invariants()
        worst = 0.0
        for k in range(100):  # 10 s in steps of 0.1 s, 1e5 internal steps
            f.do_step(0.1 * k, 0.1)
            E, P, L = invariants()
            worst = max(worst, abs(E - E0) / abs(E0), np.linalg.norm(P - P0) / np.linalg.norm(P0),
                        np.linalg.norm(L - L0) / np.linalg.norm(L0))
        assert worst <= 1e-9, worst
        # the body really tumbles (the invariants are not trivially constant)
        assert np.linalg.norm(f.get_state()[0, 12:15] - [1.0, -2.0, 0.5]) > 0.1


def test_rotation_stays_orthogonal_after_1e6_steps(fmu1):
    with make(fmu1, R0=random_rotation(2), xi0=(3.0, -2.0, 5.0, 1.0, 2.0, 3.0)) as f:
        f.do_step(0.0, 100.0)  # 1e6 internal steps of 1e-4 s
        R = f.get_state()[0, 3:12].reshape(3, 3)
        assert np.linalg.norm(R.T @ R - np.eye(3)) <= 1e-12
        assert abs(np.linalg.det(R) - 1.0) <= 1e-12
        q = f.get_quat()[0]
        assert abs(np.linalg.norm(q) - 1.0) <= 1e-12 and q[0] >= 0


@pytest.mark.parametrize("gravity", [(0.0, 0.0, 0.0), (0.5, -1.0, -9.81)])
def test_order_of_convergence_is_4(fmu1, gravity):
    def run(h):
        with make(fmu1, R0=random_rotation(3), xi0=(2.0, -1.5, 1.0, 0.5, -0.3, 0.8), g=gravity,
                  h_internal=h) as f:
            f.set_input(np.array([[0.3, -0.2, 0.1, 0.5, 0.2, -0.4]]))
            f.do_step(0.0, 1.0)
            return f.get_state()[0].copy()

    ref = run(1e-4)
    hs = np.array([0.1, 0.05, 0.025, 0.0125])
    err = np.array([np.abs(run(h) - ref).max() for h in hs])
    order = np.polyfit(np.log(hs), np.log(err), 1)[0]
    assert 3.7 <= order <= 4.3, (order, err)


def test_constant_body_force_without_rotation(fmu1):
    m, f_b, v0, p0 = 2.0, np.array([0.4, -1.0, 0.25]), np.array([0.5, 0.2, -0.1]), np.array([1.0, -2.0, 0.5])
    R0 = random_rotation(4)
    with make(fmu1, m=m, p0=p0, R0=R0, xi0=(0.0, 0.0, 0.0, *v0)) as f:
        f.set_input(np.concatenate([[0.0, 0.0, 0.0], f_b])[None])
        for k in range(20):
            f.do_step(0.1 * k, 0.1)
        t = 2.0
        p, R, w, v = split(f.get_state()[0])
    assert np.allclose(p, p0 + R0 @ (v0 * t + f_b * t**2 / (2 * m)), rtol=0, atol=1e-12)
    assert np.allclose(v, v0 + f_b * t / m, rtol=0, atol=1e-12)
    assert np.array_equal(w, np.zeros(3))
    assert np.allclose(R, R0, rtol=0, atol=1e-15)


def test_pure_spin_about_principal_axis(fmu1):
    R0 = random_rotation(5)
    omega = 2.0
    with make(fmu1, J=np.diag([1.0, 2.0, 3.0]), R0=R0, xi0=(0.0, omega, 0.0, 0.0, 0.0, 0.0)) as f:
        for k in range(30):
            f.do_step(0.1 * k, 0.1)
        p, R, w, v = split(f.get_state()[0])
    assert np.allclose(R, R0 @ expm_so3(np.array([0.0, omega * 3.0, 0.0])), rtol=0, atol=1e-11)
    assert np.allclose(w, [0.0, omega, 0.0], rtol=0, atol=1e-14)
    assert np.allclose(p, [1.0, 2.0, 3.0], rtol=0, atol=1e-15)


def test_gravity_free_fall(fmu1):
    g = np.array([0.3, -0.4, -9.81])
    p0 = np.array([1.0, 2.0, 10.0])
    with make(fmu1, p0=p0, R0=random_rotation(6), xi0=(0.0,) * 6, g=g) as f:
        for k in range(10):
            f.do_step(0.1 * k, 0.1)
        p, R, w, v = split(f.get_state()[0])
        assert np.allclose(p, p0 + g * 0.5, rtol=0, atol=1e-11)  # t = 1
        assert np.allclose(R @ v, g * 1.0, rtol=0, atol=1e-11)


def reference_rhs(J, m, u, g):
    Jinv = np.linalg.inv(J)

    def rhs(t, y):
        q, p, w, v = y[0:4], y[4:7], y[7:10], y[10:13]
        qw, qx, qy, qz = q
        R = np.array([[1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)],
                      [2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)],
                      [2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)]])
        # q' = q (x) [0, w] / 2
        dq = 0.5 * np.array([-qx * w[0] - qy * w[1] - qz * w[2],
                             qw * w[0] + qy * w[2] - qz * w[1],
                             qw * w[1] + qz * w[0] - qx * w[2],
                             qw * w[2] + qx * w[1] - qy * w[0]])
        dp = R @ v
        dw = Jinv @ (np.cross(J @ w, w) + u[:3])
        dv = np.cross(v, w) + u[3:] / m + R.T @ g
        return np.concatenate([dq, dp, dw, dv])

    return rhs


def test_agrees_with_independent_reference(fmu1):
    m, u, g = 1.7, np.array([0.2, -0.1, 0.3, 0.5, -0.2, 0.1]), np.array([0.0, 0.0, -9.81])
    q0 = np.array([0.9, 0.1, -0.3, 0.2])
    q0 /= np.linalg.norm(q0)
    p0, xi0 = np.array([0.5, -1.0, 2.0]), np.array([1.0, 0.5, -0.7, 0.4, 0.0, -0.3])
    f = FleetFMU(1, fmu_path=fmu1)
    f.set_parameters(mass=[m], J=[J_ASYM], p0=[p0], q0=[q0], xi0=[xi0], gravity=g)
    f.initialize()
    f.set_input(u[None])
    T = 2.0
    for k in range(20):
        f.do_step(0.1 * k, 0.1)
    p, R, w, v = split(f.get_state()[0])
    q = f.get_quat()[0].copy()
    f.close()
    sol = solve_ivp(reference_rhs(J_ASYM, m, u, g), (0, T), np.concatenate([q0, p0, xi0]), method="DOP853",
                    rtol=1e-12, atol=1e-13)
    y = sol.y[:, -1]
    q_ref = y[:4] / np.linalg.norm(y[:4])
    q_ref = q_ref if q_ref[0] >= 0 else -q_ref
    tol = 1e-9
    assert np.allclose(q, q_ref, rtol=0, atol=tol), (q, q_ref)
    assert np.allclose(p, y[4:7], rtol=0, atol=tol)
    assert np.allclose(w, y[7:10], rtol=0, atol=tol)
    assert np.allclose(v, y[10:13], rtol=0, atol=tol)
    # the rotation matrix and the quaternion output describe the same rotation
    qw, qx, qy, qz = q
    assert np.allclose(R[0], [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)],
                       atol=1e-14)


def test_n_bodies_are_independent_and_ordered():
    """Body i of a 6-body FMU follows exactly the trajectory of a 1-body FMU with its parameters."""
    n = 6
    rng = np.random.default_rng(7)
    masses = rng.uniform(0.5, 2.0, n)
    J = np.array([np.diag(rng.uniform(1.0, 1.5, 3)) for _ in range(n)])
    p0 = rng.normal(size=(n, 3))
    R0 = np.array([random_rotation(10 + i) for i in range(n)])
    xi0 = rng.normal(size=(n, 6))
    u = rng.normal(size=(n, 6))
    with FleetFMU(n, fmu_path=build.fmu_path(n)) as fleet:
        fleet.set_parameters(mass=masses, J=J, p0=p0, R0=R0, xi0=xi0)
        fleet.initialize()
        fleet.set_input(u)
        for k in range(5):
            fleet.do_step(0.01 * k, 0.01)
        X = fleet.get_state().copy()
    one = build.fmu_path(1)
    for i in (0, 3, 5):
        with FleetFMU(1, fmu_path=one) as f:
            f.set_parameters(mass=masses[i:i + 1], J=J[i:i + 1], p0=p0[i:i + 1], R0=R0[i:i + 1], xi0=xi0[i:i + 1])
            f.initialize()
            f.set_input(u[i:i + 1])
            for k in range(5):
                f.do_step(0.01 * k, 0.01)
            assert np.array_equal(f.get_state()[0], X[i])


def test_two_bodies_per_lane_give_the_one_body_bits(tmp_path, monkeypatch):
    """The plant steps bodies two at a time (one per vector lane, c/rkmk4.h) where the compiler
    allows: against the same sources built with -DSE3SYNC_NO_PAIRS (one body at a time), 7
    bodies (three pairs and a single one) with a fast spin (the closed-form exp, θ² ≥ 1e-4 per
    substep) beside a slow one (the series) in one pair, two fast ones and two slow ones in the
    others, gravity on and random wrenches: every bit of every state is the same."""
    monkeypatch.setattr(build, "CFLAGS", build.CFLAGS + ("-DSE3SYNC_NO_PAIRS",))
    single = build.build_fmu(7, tmp_path / "single.fmu")
    monkeypatch.undo()
    rng = np.random.default_rng(11)
    fast = np.array([True, False, True, True, False, False, True])
    omega = rng.normal(size=(7, 3))
    omega *= (np.where(fast, 30.0, 0.1) / np.linalg.norm(omega, axis=1))[:, None]
    h_int = 1e-3
    assert ((np.linalg.norm(omega, axis=1) * h_int) ** 2 >= 1e-4).tolist() == fast.tolist()
    par = dict(mass=rng.uniform(0.5, 2.0, 7),
               J=np.array([np.diag(rng.uniform(1.0, 2.0, 3)) + 0.05 for _ in range(7)]),
               p0=rng.normal(size=(7, 3)), R0=np.array([random_rotation(s) for s in range(7)]),
               xi0=np.concatenate([omega, rng.normal(size=(7, 3))], axis=1),
               gravity=[0.0, 0.0, -9.81], h_internal=h_int)
    with FleetFMU(7) as pairs, FleetFMU(7, fmu_path=single) as one:
        for f in (pairs, one):
            f.set_parameters(**par)
            f.initialize()
        for k in range(300):
            u = 0.01 * rng.normal(size=(7, 6))
            for f in (pairs, one):
                f.set_input(u)
                f.do_step(k * 0.004, 0.004)
            a, b = pairs.get_state(), one.get_state()
            assert np.array_equal(a, b), f"step {k}: max |diff| {np.abs(a - b).max()}"
        assert not np.array_equal(a[0], b[1])   # the bodies really differ
