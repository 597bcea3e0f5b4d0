"""`run_sweep` on Dask: a local cluster of 2 workers inside the suite, determinism across
executors, isolation of crashing / timing-out / worker-killing samples, incremental writes and
resume."""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import pytest

pytest.importorskip("distributed")
pytest.importorskip("pyarrow")

from cosim.sweep.runner import SweepError, make_spec, read_results, run_sweep  # noqa: E402
from cosim.sweep.spec import COLUMNS, NONDETERMINISTIC, with_faults  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
SMALL = ROOT / "scenarios" / "sweep_small.toml"
N_RANDOM = 8
N_ADV = 12  # 3 edges × 3 eigenvectors + 3
LAWS2 = ("hybrid", "gradient")   # the paper's two laws (tests/cosim/test_law_decoupled.py sweeps all)
N_RUNS = 2 * (N_ADV + N_RANDOM)


@pytest.fixture(scope="module")
def client():
    import logging

    from distributed import Client, LocalCluster

    cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                           dashboard_address=":0", silence_logs=logging.ERROR)
    c = Client(cluster)
    yield c
    c.close()
    cluster.close()


@pytest.fixture(scope="module")
def spec():
    return make_spec(SMALL, seed=5, samples=N_RANDOM)[0]


@pytest.fixture(scope="module")
def reference(tmp_path_factory, spec):
    """The in-process (no Dask) result."""
    out = tmp_path_factory.mktemp("ref") / "ref.parquet"
    st = run_sweep(spec, out, workers=0, controllers=LAWS2)
    assert st["ran"] == N_RUNS and st["skipped"] == 0 and st["executor"] == "in-process"
    return read_results(out)[0]


def _same(a, b):
    """Rows equal in every column except the wall-clock ones (NaN == NaN)."""
    assert len(a) == len(b)
    for ra, rb in zip(a, b):
        for c in COLUMNS:
            if c in NONDETERMINISTIC:
                continue
            x, y = ra[c], rb[c]
            if isinstance(x, float) and math.isnan(x):
                assert isinstance(y, float) and math.isnan(y), (ra["sample"], c, x, y)
            else:
                assert x == y, (ra["sample"], ra["controller"], c, x, y)


def test_cluster_sweep_results(client, spec, reference, tmp_path):
    out = tmp_path / "r.parquet"
    st = run_sweep(spec, out, client=client, controllers=LAWS2)
    assert st["ran"] == N_RUNS and st["counts"] == {"ok": N_RUNS}
    rows, meta = read_results(out)
    assert meta["key"] == spec.key() and meta["n_adversarial"] == N_ADV
    # sorted by sample index then controller, every (sample, controller) exactly once
    assert [(r["sample"], r["controller"]) for r in rows] == [
        (i, c) for i in range(N_ADV + N_RANDOM) for c in ("hybrid", "gradient")]
    for r in rows:
        adv = r["sample"] < N_ADV
        assert r["kind"] == ("adversarial-edge" if r["sample"] < 9 else
                             "adversarial-all" if adv else "random")
        assert r["status"] == "ok" and r["sim_time"] == 20.0 and r["wall_time"] > 0
        if r["controller"] == "hybrid" or not adv:
            assert r["converged"] and 0 < r["t_converge"] < 20, r
        else:
            assert not r["converged"], r  # the baseline stays on the critical point
        assert r["n_jumps"] <= r["jump_bound"]
        if r["controller"] == "gradient":
            assert r["n_jumps"] == 0
    _same(rows, reference)


def test_same_rows_with_one_worker(spec, reference, tmp_path):
    out = tmp_path / "one.csv"  # and through the CSV format
    st = run_sweep(spec, out, workers=1, chunk=3, controllers=LAWS2)
    assert st["executor"].startswith("local cluster of 1")
    _same(read_results(out)[0], reference)


def test_failures_are_isolated(client, spec, tmp_path):
    bad = with_faults(dataclasses.replace(spec, timeout=0.5),
                      [(3, "hybrid", "raise"), (14, "*", "hang")])
    out = tmp_path / "f.parquet"
    st = run_sweep(bad, out, client=client, chunk=4, controllers=LAWS2)
    assert st["counts"] == {"ok": N_RUNS - 3, "error": 1, "timeout": 2}
    rows = {(r["sample"], r["controller"]): r for r in read_results(out)[0]}
    assert rows[(3, "hybrid")]["status"] == "error"
    assert "injected fault" in rows[(3, "hybrid")]["error"]
    for c in ("hybrid", "gradient"):
        assert rows[(14, c)]["status"] == "timeout" and not rows[(14, c)]["converged"]
    # the chunk-mates of the failing samples are fine
    assert rows[(3, "gradient")]["status"] == "ok" and rows[(2, "hybrid")]["converged"]
    # --retry-failed reruns exactly the failed ones (here without the faults: they succeed)
    st = run_sweep(dataclasses.replace(spec, timeout=0.5), out, client=client,
                   retry_failed=True, controllers=LAWS2)
    assert st["ran"] == 3 and st["skipped"] == N_RUNS - 3 and st["counts"] == {"ok": N_RUNS}


def test_killed_worker_is_recorded(spec, tmp_path):
    """A sample that kills its worker process: recorded as an error, the others kept."""
    import dask

    bad = with_faults(spec, [(13, "gradient", "exit")])
    out = tmp_path / "k.parquet"
    small = dataclasses.replace(bad, n_random=2)
    with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
        st = run_sweep(small, out, workers=2, chunk=4, controllers=LAWS2)
    rows = {(r["sample"], r["controller"]): r for r in read_results(out)[0]}
    assert len(rows) == 2 * (N_ADV + 2)
    r = rows[(13, "gradient")]
    assert r["status"] == "error" and "Killed" in r["error"], r
    assert st["counts"]["ok"] == 2 * (N_ADV + 2) - 1


def test_interrupt_and_resume(client, spec, reference, tmp_path):
    out = tmp_path / "res.parquet"
    st = run_sweep(spec, out, client=client, chunk=2, stop_after=10, flush_every=0,
                   controllers=LAWS2)
    assert st["interrupted"]
    first, _ = read_results(out)
    assert 10 <= len(first) < N_RUNS
    st = run_sweep(spec, out, client=client, chunk=2, controllers=LAWS2)
    assert not st["interrupted"]
    assert st["skipped"] == len(first) and st["ran"] == N_RUNS - len(first)
    final, _ = read_results(out)
    _same(final, reference)
    # the rows kept from the first run are unchanged (wall time included: not rerun)
    old = {(r["sample"], r["controller"]): r["wall_time"] for r in first}
    for r in final:
        if (r["sample"], r["controller"]) in old:
            assert r["wall_time"] == old[(r["sample"], r["controller"])]
    # a rerun with nothing left
    st = run_sweep(spec, out, client=client, controllers=LAWS2)
    assert st["ran"] == 0 and st["skipped"] == N_RUNS
    # extending K keeps the old samples and adds the new ones only
    more = dataclasses.replace(spec, n_random=N_RANDOM + 2)
    st = run_sweep(more, out, workers=0, controllers=LAWS2)
    assert st["ran"] == 4 and st["skipped"] == N_RUNS
    # other settings: refused, file untouched
    before = out.read_bytes()
    with pytest.raises(SweepError, match="--out: .*seed 5 != 6"):
        run_sweep(dataclasses.replace(spec, seed=6), out, workers=0, controllers=LAWS2)
    assert out.read_bytes() == before


def test_a_dask_worker_runs_its_chunks_on_one_blas_thread(client, spec):
    """cosim/threads.py in a worker process of the cluster: one BLAS thread per library while
    it runs samples, even when the worker's libraries were set to two."""
    def probe(spec):
        import os

        from test_sweep_worker import blas_threads_in_chunk
        return os.getpid(), blas_threads_in_chunk(spec)

    import os

    pid, (before, seen, after) = client.submit(probe, spec, pure=False).result(timeout=300)
    assert pid != os.getpid()
    assert len(seen) == 2 and all(set(s) == {1} for s in seen), seen
    assert after == before
