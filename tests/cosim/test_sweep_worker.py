"""The sweep's sample generator and its per-sample loop (in-process, no Dask)."""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from controller import GradientController, se3
from cosim.sweep import spec as sw

ROOT = Path(__file__).resolve().parents[2]
SMALL = ROOT / "scenarios" / "sweep_small.toml"


@pytest.fixture(scope="module")
def spec():
    return sw.SweepSpec(SMALL.read_text(), "sweep_small", str(SMALL), (), seed=11, n_random=4)


@pytest.fixture(scope="module")
def sc(spec):
    return sw.load_spec_scenario(spec)


def _X(S):
    N = S.shape[0]
    X = np.tile(np.eye(4), (N, 1, 1))
    X[:, :3, :3] = S[:, 3:12].reshape(N, 3, 3)
    X[:, :3, 3] = S[:, 0:3]
    return X


def _rel(sc, S):
    X = _X(S)
    return np.stack([se3.inverse(X[j]) @ X[i] for i, j in sc.graph.edges])


def test_sample_order_and_kinds(sc):
    M = sc.graph.M
    assert sw.n_adversarial(sc) == 3 * M + 3 == 12
    kinds = [sw.describe_sample(sc, i) for i in range(14)]
    assert kinds[:9] == [("adversarial-edge", k, e) for k in (1, 2, 3) for e in (1, 2, 3)]
    assert kinds[9:12] == [("adversarial-all", 0, e) for e in (1, 2, 3)]
    assert kinds[12:] == [("random", 0, 0)] * 2


def test_random_samples_seeded_per_index(spec, sc):
    N = sc.graph.n
    a = sw.initial_state(sc, spec, 20)
    # the documented derivation: SeedSequence(seed, spawn_key=(index,))
    rng = np.random.default_rng(np.random.SeedSequence(11, spawn_key=(20,)))
    R = se3.random_rotation(rng, N)
    assert np.array_equal(a[:, 3:12], R.reshape(N, 9))
    # independent of what was generated before, different across indices and seeds
    sw.initial_state(sc, spec, 13)
    assert np.array_equal(sw.initial_state(sc, spec, 20), a)
    assert not np.allclose(sw.initial_state(sc, spec, 21), a)
    other = dataclasses.replace(spec, seed=12)
    assert not np.allclose(sw.initial_state(sc, other, 20), a)
    # rotations, box, ball
    Rs = a[:, 3:12].reshape(N, 3, 3)
    assert np.allclose(np.einsum("nji,njk->nik", Rs, Rs), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(Rs), 1.0)
    many = np.stack([sw.initial_state(sc, spec, i) for i in range(12, 212)])
    assert np.abs(many[:, :, 0:3]).max() <= spec.position_box
    assert np.abs(many[:, :, 0:3]).max() > 0.9 * spec.position_box
    sp = np.linalg.norm(many[:, :, 12:18], axis=-1)
    assert sp.max() <= spec.velocity_ball + 1e-12 and sp.max() > 0.8 * spec.velocity_ball
    # Haar: E[R] = 0 (a biased generator, e.g. Euler angles uniform, fails this)
    meanR = many[:, :, 3:12].reshape(-1, 9).mean(axis=0)
    assert np.abs(meanR).max() < 0.1


def test_adversarial_samples_sit_on_critical_points(spec, sc):
    lam, V = sc.weighting.eig()
    W = sc.weighting.W
    b, d = sc.weighting.b, sc.weighting.d
    grad = GradientController(sc.graph, sc.weighting, sc.gains)
    for i in range(sw.n_adversarial(sc)):
        kind, edge, e = sw.describe_sample(sc, i)
        v = V[:, e - 1]
        assert np.allclose(W @ v, lam[e - 1] * v)
        Rc = se3.R_a(math.pi, v)
        S0 = sw.initial_state(sc, spec, i)
        assert np.abs(S0[:, 12:18]).max() == 0.0
        rel = _rel(sc, S0)
        for k in range(sc.graph.M):
            on = kind == "adversarial-all" or k + 1 == edge
            Rt, pt = (Rc, (np.eye(3) - Rc) @ b / d) if on else (np.eye(3), np.zeros(3))
            assert np.allclose(rel[k, :3, :3], Rt, atol=1e-12), (i, k)
            assert np.allclose(rel[k, :3, 3], pt, atol=1e-12), (i, k)
        # a critical point of the potential: the gradient-only wrench vanishes
        u, ev = grad.step_state(np.ascontiguousarray(S0), sc.step)
        assert np.abs(u).max() < 1e-9 and ev == ()


def test_adversarial_gradient_stuck_hybrid_converges(spec, sc):
    for i in (0, 5, 7, 9, 11):  # edges 1..3, every eigenvector, and all edges at once
        g = sw.run_sample(spec, i, "gradient")
        h = sw.run_sample(spec, i, "hybrid")
        assert g["status"] == h["status"] == "ok", (g["error"], h["error"])
        assert g["u0_max"] < 1e-9 and g["n_jumps"] == 0
        assert not g["converged"] and math.isnan(g["t_converge"])
        assert g["rot_err"] == pytest.approx(2 * math.sqrt(2), rel=1e-9)  # never moved
        assert h["converged"] and h["rot_err"] < spec.rot_tol and h["pos_err"] < spec.pos_tol
        assert h["n_jumps"] >= 1 and h["t_last_jump"] >= 0 and h["u0_max"] > 1.0
        assert h["n_jumps"] <= h["jump_bound"]
        assert h["rot_err0"] == pytest.approx(2 * math.sqrt(2), rel=1e-9)


def test_row_comes_from_one_master_run(spec, monkeypatch):
    """The sweep has no step loop of its own: a row is read off one `Master.run`."""
    from cosim.master import Master

    runs = []
    real = Master.run

    def spy(self, n_steps, **kw):
        out = real(self, n_steps, **kw)
        runs.append(out)
        return out

    monkeypatch.setattr(Master, "run", spy)
    for i, ctrl in ((13, "hybrid"), (2, "gradient")):
        runs.clear()
        row = sw.run_sample(spec, i, ctrl)
        assert len(runs) == 1
        summ = runs[0]
        assert row["status"] == "ok" and row["steps"] == summ["steps"]
        assert row["rot_err"] == summ["final"]["rot_err"]
        assert row["pos_err"] == summ["final"]["pos_err"]
        assert row["n_jumps"] == summ["n_jumps"] == len(summ["jumps"])
        assert row["V0"] == summ["V0"] and row["jump_bound"] == summ["jump_bound"]


def test_reused_master_matches_a_fresh_one(spec, sc):
    """A sample run on the per-process Master (plant reset, FMU reused) equals a fresh Master
    with a fresh FMU on the same initial state."""
    from cosim.master import Master
    from cosim.plants import FmuPlant

    sw.run_sample(spec, 3, "hybrid")  # leaves a used FMU in the per-process cache
    for i, ctrl in ((13, "hybrid"), (2, "hybrid"), (14, "gradient")):
        row = sw.run_sample(spec, i, ctrl)
        sci = dataclasses.replace(sc, S0=sw.initial_state(sc, spec, i), theta0=np.zeros(sc.graph.M))
        plant = FmuPlant.from_scenario(sci)
        try:
            summ = Master(sci, plant, ctrl).run(sci.n_steps())
        finally:
            plant.close()
        f = summ["final"]
        assert row["steps"] == summ["steps"] and row["sim_time"] == summ["sim_time_s"]
        assert row["rot_err"] == f["rot_err"] and row["pos_err"] == f["pos_err"]
        assert row["xi_max"] == f["xi_max"]
        assert row["n_jumps"] == summ["n_jumps"] and row["jump_bound"] == summ["jump_bound"]
        assert row["V0"] == pytest.approx(summ["V0"], rel=1e-12)
        if ctrl == "hybrid":
            assert row["theta_max"] == max(abs(x) for x in f["theta"])
        # t_converge: the master's 1-s samples agree (below tolerance after, above before)
        if row["converged"]:
            tc = row["t_converge"]
            for s in summ["samples"]:
                below = s["rot_err"] < spec.rot_tol and s["pos_err"] < spec.pos_tol
                if s["t"] >= tc - 1e-9:
                    assert below, (i, s["t"], tc)
            before = [s for s in summ["samples"] if s["t"] <= tc - spec.sample_dt - 1e-9]
            if before and tc > 0:
                # the 0.1-s sample just before t_converge is above tolerance
                assert any(not (s["rot_err"] < spec.rot_tol and s["pos_err"] < spec.pos_tol)
                           for s in before)


def test_failures_are_rows_not_exceptions(spec):
    bad = sw.with_faults(dataclasses.replace(spec, timeout=0.3),
                         [(12, "hybrid", "raise"), (13, "*", "hang")])
    r = sw.run_sample(bad, 12, "hybrid")
    assert r["status"] == "error" and "injected fault" in r["error"] and not r["converged"]
    assert r["kind"] == "random" and r["sample"] == 12
    t = sw.run_sample(bad, 13, "gradient")
    assert t["status"] == "timeout" and "timeout" in t["error"] and not t["converged"]
    assert 0 < t["sim_time"] < 20 and 0.3 <= t["wall_time"] < 3
    ok = sw.run_sample(bad, 12, "gradient")
    assert ok["status"] == "ok" and ok["converged"]
    e = sw.run_sample(spec, 0, "nonsense")
    assert e["status"] == "error" and "controller" in e["error"]


def blas_threads_in_chunk(spec, threads_outside=2):
    """(BLAS threads before, during each sample of, and after `run_chunk`), with the process's
    libraries first set to ``threads_outside`` threads (as a worker without Dask's nanny
    environment, or a machine default, would have them). Runs where it is called: in this
    process or, submitted, in a Dask worker (tests/cosim/test_sweep_dask.py)."""
    from threadpoolctl import threadpool_limits

    from cosim.sweep import spec as sw_
    from cosim.threads import blas_info

    seen = []
    orig = sw_.run_sample

    def spy(*a):
        seen.append([n for _, n in blas_info()])
        return orig(*a)

    with threadpool_limits(limits=threads_outside, user_api="blas"):
        before = [n for _, n in blas_info()]
        sw_.run_sample = spy
        try:
            rows = sw_.run_chunk(spec, [(0, "hybrid"), (12, "gradient")])
        finally:
            sw_.run_sample = orig
        after = [n for _, n in blas_info()]
    assert [r["status"] for r in rows] == ["ok", "ok"]
    return before, seen, after


def test_a_sweep_chunk_runs_blas_on_one_thread(spec, monkeypatch):
    """cosim/threads.py: a chunk of samples gets SWEEP_WORKER_THREADS = 1 BLAS thread per
    library (the workers share the cores), and the process's own count back afterwards."""
    from cosim.threads import ENV, SWEEP_WORKER_THREADS

    monkeypatch.delenv(ENV, raising=False)
    assert SWEEP_WORKER_THREADS == 1
    short = dataclasses.replace(spec, timeout=None)
    before, seen, after = blas_threads_in_chunk(short)
    assert len(seen) == 2 and all(set(s) == {1} for s in seen), seen
    assert after == before


def test_a_bad_blas_override_is_refused_before_any_sample(spec, monkeypatch, tmp_path):
    from controller.errors import Se3SyncError
    from cosim.sweep.runner import run_sweep
    from cosim.threads import ENV

    monkeypatch.setenv(ENV, "-3")
    with pytest.raises(Se3SyncError, match=f"{ENV}: must be an integer >= 0"):
        run_sweep(spec, tmp_path / "o.parquet", workers=0)
    assert not (tmp_path / "o.parquet").exists()
