"""The sweep driver: evidence of global convergence at scale, on Dask (`se3sync sweep`).

`se3sync sweep SCENARIO --samples K --seed S --out results.parquet` runs the scenario from the
3M + 3 adversarial initial conditions (the undesired critical points) PLUS K seeded random ones,
with the hybrid law and (unless --no-baseline) the gradient-only baseline, on a Dask local
cluster (default), a remote scheduler (--scheduler) or in-process (--workers 0). See
docs/guide/sweeps.md. Dask and pyarrow are imported where they are used (optional extra `sweep`).

Output format. Parquet is the default and the recommended one: typed columns (int64, float64
with NaN, bool, string) that read back exactly, schema metadata that records what the rows
depend on (seed, tolerances, scenario hash, generator version; a resume refuses a mismatch), a
compact columnar file read by pandas, polars, DuckDB, Arrow, Spark. Parquet files cannot be
appended to, so the sweep rewrites the WHOLE file periodically (every --flush-every seconds and
at the end) into a temporary file in the same directory and renames it into place: the output
is always a complete, valid file, an interrupted sweep keeps every row flushed before the
interruption, and a rerun resumes from it. Rewriting costs O(rows) per flush (≈ 10 ms per
10,000 rows), negligible against the samples. A `.csv` suffix writes the same columns as CSV
(same atomic rewrite; the metadata goes to a `<out>.meta.json` sidecar) for tools without a
Parquet reader; its types are restored from the known schema when it is read back.
"""
from __future__ import annotations

import json
import logging
import math
import signal
import threading
import time
from pathlib import Path

from tqdm import tqdm

from controller.errors import Se3SyncError

from ..controllers import law_names
from ..files import atomic_path, write_json_atomic
from ..scenario import load_scenario
from ..threads import override as blas_override
from .spec import COLUMNS, SweepSpec, error_row, load_spec_scenario, n_adversarial, run_chunk

__all__ = ["SweepError", "run_sweep", "read_results", "write_results", "make_spec"]

CONTROLLERS = law_names()
SINGLE_RETRIES = 1  # extra tries of a single sample whose task failed (e.g. its worker died)


class SweepError(Se3SyncError):
    """Bad input or a sweep problem: one line naming the option and the reason."""


# ----------------------------------------------------------------------------- CLI
def _bad(option: str, reason: str):
    raise SweepError(f"{option}: {reason}")


def make_spec(scenario_path, overrides=(), *, seed=0, samples=0, position_box=1.0,
              velocity_ball=0.5, rot_tol=1e-2, pos_tol=1e-2, sample_dt=0.1, timeout=None):
    """Validates the options (SweepError naming the option) and the scenario (ScenarioError);
    returns (spec, scenario)."""
    def finite(x):
        return isinstance(x, (int, float)) and math.isfinite(x)

    if isinstance(samples, bool) or not isinstance(samples, int) or samples < 0:
        _bad("--samples", f"must be an integer >= 0, got {samples!r}")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        _bad("--seed", f"must be an integer >= 0, got {seed!r}")
    if not finite(position_box) or position_box < 0:
        _bad("--position-box", f"must be a finite number >= 0, got {position_box!r}")
    if not finite(velocity_ball) or velocity_ball < 0:
        _bad("--velocity-ball", f"must be a finite number >= 0, got {velocity_ball!r}")
    if not finite(rot_tol) or rot_tol <= 0:
        _bad("--rot-tol", f"must be a finite number > 0, got {rot_tol!r}")
    if not finite(pos_tol) or pos_tol <= 0:
        _bad("--pos-tol", f"must be a finite number > 0, got {pos_tol!r}")
    if not finite(sample_dt) or sample_dt <= 0:
        _bad("--sample-dt", f"must be a finite number > 0, got {sample_dt!r}")
    if timeout is not None and (not finite(timeout) or timeout <= 0):
        _bad("--timeout", f"must be a finite number > 0, got {timeout!r}")
    sc = load_scenario(scenario_path, tuple(overrides))
    spec = SweepSpec(scenario_text=sc.text, scenario_name=sc.name, scenario_path=str(sc.path),
                     overrides=tuple(overrides), seed=int(seed), n_random=int(samples),
                     position_box=float(position_box), velocity_ball=float(velocity_ball),
                     rot_tol=float(rot_tol), pos_tol=float(pos_tol), sample_dt=float(sample_dt),
                     timeout=None if timeout is None else float(timeout))
    return spec, sc


# ----------------------------------------------------------------------------- results I/O
def _schema(meta: dict | None = None):
    import pyarrow as pa

    types = {"int": pa.int64(), "float": pa.float64(), "bool": pa.bool_(), "str": pa.string()}
    md = None if meta is None else {b"se3sync.sweep": json.dumps(meta, sort_keys=True).encode()}
    return pa.schema([(c, types[t]) for c, t in COLUMNS.items()], metadata=md)


def _meta_path(path: Path) -> Path:
    return path.with_name(path.name + ".meta.json")


def write_results(path, rows, meta: dict) -> None:
    """Writes every row (sorted by sample, controller) atomically: a temporary file in the same
    directory, then os.replace."""
    import pyarrow as pa

    path = Path(path)
    rows = sorted(rows, key=lambda r: (r["sample"], CONTROLLERS.index(r["controller"])
                                       if r["controller"] in CONTROLLERS else 9))
    schema = _schema(meta)
    table = pa.Table.from_pydict({c: [r[c] for r in rows] for c in COLUMNS}, schema=schema)
    csv = path.suffix.lower() == ".csv"
    if csv:
        write_json_atomic(_meta_path(path), meta)
    with atomic_path(path) as tmp:
        if csv:
            import pyarrow.csv as pacsv

            pacsv.write_csv(table, tmp)
        else:
            import pyarrow.parquet as pq

            pq.write_table(table, tmp, compression="zstd")


def read_results(path, spec=None, option="--out"):
    """(rows: list of dicts, meta: dict). With a SweepSpec, refuses (SweepError naming --out) a
    file written for other settings (the spec's key_dict)."""
    import pyarrow as pa

    path = Path(path)
    try:
        if path.suffix.lower() == ".csv":
            import pyarrow.csv as pacsv

            schema = _schema()
            table = pacsv.read_csv(path, convert_options=pacsv.ConvertOptions(
                column_types={f.name: f.type for f in schema},
                strings_can_be_null=False, quoted_strings_can_be_null=False))
            mp = _meta_path(path)
            meta = json.loads(mp.read_text()) if mp.exists() else {}
        else:
            import pyarrow.parquet as pq

            table = pq.read_table(path)
            raw = (table.schema.metadata or {}).get(b"se3sync.sweep")
            meta = json.loads(raw) if raw else {}
    except (OSError, pa.ArrowException, ValueError) as exc:
        raise SweepError(f"{option}: cannot read results {str(path)!r}: "
                         f"{' '.join(str(exc).split())[:200]}") from None
    missing = [c for c in COLUMNS if c not in table.column_names]
    if missing:
        raise SweepError(f"{option}: {str(path)!r} is not a sweep results file (missing columns "
                         f"{', '.join(missing[:5])})")
    if spec is not None and meta.get("key") != spec.key():
        old = meta.get("settings", {})
        new = spec.key_dict()
        diff = [k for k in new if old.get(k) != new[k]] or ["key"]
        what = ", ".join(f"{k} {old.get(k)!r} != {new[k]!r}" if k != "scenario_sha256"
                         else "scenario text differs" for k in diff[:3])
        raise SweepError(f"{option}: {str(path)!r} holds results of other settings ({what}); "
                         f"choose another --out")
    d = table.select(list(COLUMNS)).to_pydict()
    n = table.num_rows
    rows = [{c: d[c][i] for c in COLUMNS} for i in range(n)]
    floats = [c for c, t in COLUMNS.items() if t == "float"]
    for r in rows:  # CSV: "nan" reads as null
        if r["error"] is None:
            r["error"] = ""
        for c in floats:
            if r[c] is None:
                r[c] = float("nan")
    return rows, meta


# ----------------------------------------------------------------------------- driver
def _chunks(tasks, size):
    return [tasks[i:i + size] for i in range(0, len(tasks), size)]


def run_sweep(spec, out, *, controllers=CONTROLLERS, workers=None, scheduler=None, chunk=None,
              flush_every=10.0, retry_failed=False, progress=False, stop_after=None,
              client=None) -> dict:
    """Runs the sweep, writing ``out`` incrementally; returns statistics.

    Executors: ``client`` (a distributed.Client, used as is), ``scheduler`` (an address),
    ``workers`` = W ≥ 1 (a LocalCluster of W processes, one thread each) or 0 (in-process,
    no Dask). ``stop_after``: test hook, stop (as if interrupted) after that many new rows.
    """
    out = Path(out)
    blas_override()   # a bad SE3SYNC_BLAS_THREADS: one line here, not an error row per sample
    sc = load_spec_scenario(spec)
    n_adv = n_adversarial(sc)
    n_total = n_adv + spec.n_random
    key = spec.key()
    meta = {"key": key, "settings": spec.key_dict(), "n_adversarial": n_adv,
            "n_random": spec.n_random, "controllers": list(controllers),
            "scenario_name": spec.scenario_name, "scenario_path": spec.scenario_path,
            "format": 1}
    rows = {}
    if out.exists():
        old, old_meta = read_results(out, spec=spec)
        for r in old:
            rows[(r["sample"], r["controller"])] = r
        # the union of what was asked, so that a smaller rerun does not shrink the metadata
        meta["n_random"] = max(spec.n_random, int(old_meta.get("n_random", 0)))
        meta["controllers"] = [c for c in CONTROLLERS if c in set(controllers)
                               | set(old_meta.get("controllers", []))]
    wanted = [(i, c) for i in range(n_total) for c in controllers]
    todo = []
    skipped = 0
    for t in wanted:
        r = rows.get(t)
        if r is not None and not (retry_failed and r["status"] != "ok"):
            skipped += 1
        else:
            todo.append(t)
    stats = {"total": len(wanted), "n_adversarial": n_adv, "skipped": skipped, "ran": 0,
             "interrupted": False, "executor": "", "wall_time": 0.0}
    t0 = time.perf_counter()
    last_flush = [time.perf_counter()]
    dirty = [False]

    def flush(force=False):
        if dirty[0] and (force or time.perf_counter() - last_flush[0] >= flush_every):
            write_results(out, rows.values(), meta)
            last_flush[0] = time.perf_counter()
            dirty[0] = False

    bar = None
    if progress and todo:
        bar = tqdm(total=len(todo), unit="run", desc=spec.scenario_name, mininterval=0.5)

    def take(new_rows):
        for r in new_rows:
            rows[(r["sample"], r["controller"])] = r
        stats["ran"] += len(new_rows)
        dirty[0] = True
        if bar is not None:
            bar.update(len(new_rows))
        flush()
        return stop_after is not None and stats["ran"] >= stop_after

    try:
        if not todo:
            stats["executor"] = "nothing to do"
        elif client is None and scheduler is None and workers == 0:
            stats["executor"] = "in-process"
            for t in todo:
                if take(run_chunk(spec, [t])):
                    stats["interrupted"] = True
                    break
        else:
            stats["interrupted"] = _run_dask(spec, todo, take, error_row, sc, stats,
                                             client=client, scheduler=scheduler,
                                             workers=workers, chunk=chunk)
    except KeyboardInterrupt:
        stats["interrupted"] = True
    finally:
        if bar is not None:
            bar.close()
        if dirty[0]:
            write_results(out, rows.values(), meta)
    stats["wall_time"] = time.perf_counter() - t0
    stats["rows"] = len(rows)
    counts = {}
    for t in wanted:
        r = rows.get(t)
        if r is not None:
            counts[r["status"]] = counts.get(r["status"], 0) + 1
    stats["counts"] = counts
    return stats


def _run_dask(spec, todo, take, error_row, sc, stats, *, client, scheduler, workers, chunk):
    from distributed import Client, LocalCluster, as_completed

    cluster = None
    own_client = client is None
    try:
        if client is None:
            if scheduler is not None:
                try:
                    client = Client(scheduler, timeout="10s")
                except (OSError, TimeoutError) as exc:
                    raise SweepError(f"--scheduler: cannot connect to {scheduler!r}: "
                                     f"{' '.join(str(exc).split())[:200]}") from None
                stats["executor"] = f"scheduler {scheduler}"
            else:
                # The worker processes inherit "ignore SIGINT": Ctrl-C stops the sweep (this
                # process writes the finished rows), not the workers with tracebacks.
                main = threading.current_thread() is threading.main_thread()
                old = signal.signal(signal.SIGINT, signal.SIG_IGN) if main else None
                try:
                    cluster = LocalCluster(n_workers=int(workers), threads_per_worker=1,
                                           processes=True, dashboard_address=":0",
                                           silence_logs=logging.ERROR)
                finally:
                    if main:
                        signal.signal(signal.SIGINT, old)
                client = Client(cluster)
                stats["executor"] = f"local cluster of {workers} worker(s)"
        else:
            stats["executor"] = "client"
        n_workers = max(1, len(client.scheduler_info().get("workers", {})) or (workers or 1))
        size = chunk or max(1, min(16, math.ceil(len(todo) / (4 * n_workers))))
        pending = {}
        attempts = {}
        futs = []
        for c in _chunks(todo, size):
            f = client.submit(run_chunk, spec, c, pure=False)
            pending[f.key] = c
            futs.append(f)
        # Samples of a failed chunk are rerun one at a time ("isolation"): with a single
        # isolation task in flight, a sample whose own task dies is the one that kills its
        # worker, not a bystander queued behind it on the same worker.
        iso = []
        iso_key = None
        ac = as_completed(futs)

        def next_isolation():
            nonlocal iso_key
            if iso_key is None and iso:
                t = iso.pop(0)
                g = client.submit(run_chunk, spec, [t], pure=False)
                pending[g.key] = [t]
                iso_key = g.key
                ac.add(g)

        for f in ac:
            c = pending.pop(f.key)
            if f.key == iso_key:
                iso_key = None
            try:
                rows = f.result()
            except Exception as exc:  # a worker died (KilledWorker) or the task broke
                if len(c) > 1:
                    iso.extend(c)
                    next_isolation()
                    continue
                if attempts.get(c[0], 0) < SINGLE_RETRIES:
                    attempts[c[0]] = attempts.get(c[0], 0) + 1
                    iso.append(c[0])
                    next_isolation()
                    continue
                msg = f"{type(exc).__name__}: {exc}"
                rows = [error_row(spec, sc, t[0], t[1], "error", msg) for t in c]
            next_isolation()
            if take(rows):
                for g in list(ac.futures):
                    g.cancel()
                return True
        return False
    finally:
        if own_client and client is not None:
            try:
                client.close()
            except Exception:
                pass
        if cluster is not None:
            try:
                cluster.close()
            except Exception:
                pass
