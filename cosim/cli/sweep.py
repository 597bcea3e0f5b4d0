"""Sub-commands `sweep` and `sweep-report` (the driver is `cosim.sweep.runner`)."""
from __future__ import annotations

import math
import os
import sys
from pathlib import Path

from ..registry import LAWS
from . import require

__all__ = ["register"]


def _bad(option: str, reason: str):
    from ..sweep.runner import SweepError

    raise SweepError(f"{option}: {reason}")


def register(sub) -> None:
    p = sub.add_parser(
        "sweep", help="run many seeded co-simulations (random + critical-point initial "
                      "conditions) on Dask and record convergence",
        description="Run the scenario from the 3M+3 adversarial initial conditions (every "
                    "edge, then all edges, on the undesired critical points of each eigenvector "
                    "of W) and K seeded random ones (Haar rotations, positions in a box, body "
                    "velocities in a ball, θ(0) = 0), with every registered law (the hybrid law, "
                    "the gradient-only baseline and the others in cosim/registry.py), for the "
                    "scenario's duration each. Rows are written to --out "
                    "incrementally; a rerun skips the samples already there. Exit codes: 0 ok, "
                    "2 bad input, 130 interrupted (finished rows kept).")
    p.add_argument("scenario", help="scenario TOML file (its [initial] table is ignored)")
    p.add_argument("--samples", type=int, required=True, metavar="K",
                   help="number of random samples (the 3M+3 adversarial ones come in addition)")
    p.add_argument("--seed", type=int, default=0, metavar="S",
                   help="seed of the generator; sample i uses SeedSequence(S, spawn_key=(i,)) "
                        "(default 0)")
    p.add_argument("--out", required=True, metavar="RESULTS.parquet|.csv",
                   help="output file; Parquet (recommended) or CSV from the suffix")
    p.add_argument("--scheduler", metavar="tcp://HOST:8786",
                   help="use a running Dask scheduler instead of a local cluster")
    p.add_argument("--workers", type=int, metavar="W",
                   help="local cluster size (one process, one thread each; default: the number "
                        "of cores); 0 runs in this process without Dask")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY.PATH=VALUE",
                   help="override a scenario value (a TOML value), repeatable")
    p.add_argument("--timeout", type=float, metavar="S",
                   help="wall-clock limit per run in seconds, counted after its first 0.1 s "
                        "of simulated time (recorded as status timeout)")
    p.add_argument("--no-baseline", action="store_true",
                   help="run the hybrid law only (default: every registered law: "
                        + ", ".join(LAWS) + ")")
    p.add_argument("--position-box", type=float, default=1.0, metavar="L",
                   help="random positions uniform in [-L, L]^3 m (default 1)")
    p.add_argument("--velocity-ball", type=float, default=0.5, metavar="R",
                   help="random body velocities ξ = [ω; v] uniform in the 6-ball of radius R "
                        "(default 0.5)")
    p.add_argument("--rot-tol", type=float, default=1e-2, metavar="TOL",
                   help="converged: max_k ‖I − R̄_k‖_F < TOL at the end (default 1e-2)")
    p.add_argument("--pos-tol", type=float, default=1e-2, metavar="TOL",
                   help="converged: max_k ‖p̄_k‖ < TOL m at the end (default 1e-2)")
    p.add_argument("--sample-dt", type=float, default=0.1, metavar="S",
                   help="simulated interval between error samples for the time to converge "
                        "(default 0.1 s)")
    p.add_argument("--chunk", type=int, metavar="C",
                   help="samples per Dask task (default: automatic, ≤ 16, ≥ 4 tasks per worker)")
    p.add_argument("--flush-every", type=float, default=10.0, metavar="S",
                   help="rewrite the output at most every S seconds (default 10)")
    p.add_argument("--retry-failed", action="store_true",
                   help="on resume, rerun the samples recorded as error or timeout")
    p.set_defaults(func=_cmd_sweep)

    p = sub.add_parser(
        "sweep-report", help="plot and summarise sweep results (convergence rate with Wilson "
                             "CI, time to converge, jumps against their bound)",
        description="Read a results file of `se3sync sweep`, print a short summary and plot "
                    "the convergence rate per kind (random / adversarial) and controller with "
                    "95%% Wilson intervals, the time to converge, and the jump counts against "
                    "⌈V̄(0)/(k_X δ)⌉.")
    p.add_argument("results", help="RESULTS.parquet or .csv written by `se3sync sweep`")
    p.add_argument("-o", "--output", required=True, metavar="REPORT.png",
                   help="output figure (png, pdf or svg from the suffix)")
    p.add_argument("--json", metavar="SUMMARY.json", help="also write the summary as JSON")
    p.set_defaults(func=_cmd_report)


def _cmd_sweep(args) -> int:
    from ..files import check_output
    from ..sweep.runner import make_spec, read_results, run_sweep

    if args.workers is not None and args.workers < 0:
        _bad("--workers", f"must be >= 0, got {args.workers}")
    if args.workers is not None and args.scheduler:
        _bad("--workers", "cannot be combined with --scheduler (the scheduler's workers run the "
                          "samples)")
    if args.scheduler is not None and "://" not in args.scheduler and ":" not in args.scheduler:
        _bad("--scheduler", f"expected an address like tcp://HOST:8786, got {args.scheduler!r}")
    if args.chunk is not None and args.chunk < 1:
        _bad("--chunk", f"must be >= 1, got {args.chunk}")
    if not (math.isfinite(args.flush_every) and args.flush_every >= 0):
        _bad("--flush-every", f"must be a finite number >= 0, got {args.flush_every}")
    out = check_output("--out", args.out, (".parquet", ".csv"))
    spec, sc = make_spec(args.scenario, args.overrides, seed=args.seed, samples=args.samples,
                         position_box=args.position_box, velocity_ball=args.velocity_ball,
                         rot_tol=args.rot_tol, pos_tol=args.pos_tol, sample_dt=args.sample_dt,
                         timeout=args.timeout)

    ctrls = ("hybrid",) if args.no_baseline else tuple(LAWS)
    # refuse a mismatching existing file before starting a cluster
    if out.exists():
        read_results(out, spec=spec)
    # pyarrow writes the results; Dask runs the samples unless --workers 0
    require("pyarrow")
    if args.workers != 0:
        require("distributed")
    if args.workers is None and args.scheduler is None:
        workers = os.cpu_count() or 1
    else:
        workers = args.workers
    res = run_sweep(spec, out, controllers=ctrls, workers=workers, scheduler=args.scheduler,
                    chunk=args.chunk, flush_every=args.flush_every,
                    retry_failed=args.retry_failed, progress=sys.stderr.isatty())
    c = res["counts"]
    print(f"{sc.name}: {res['total']} runs ({res['n_adversarial']} adversarial + "
          f"{spec.n_random} random samples × {len(ctrls)} controller(s)); skipped "
          f"{res['skipped']} already in {out}, ran {res['ran']} in {res['wall_time']:.3g} s "
          f"on {res['executor']}; ok {c.get('ok', 0)}, error {c.get('error', 0)}, "
          f"timeout {c.get('timeout', 0)}", file=sys.stderr)
    if res["interrupted"]:
        print(f"se3sync sweep: interrupted; {res['rows']} rows kept in {out} (rerun to resume)",
              file=sys.stderr)
        return 130
    return 0


def _cmd_report(args) -> int:
    from ..files import check_output

    p = Path(args.results)
    if not p.is_file():
        _bad("results", f"no such file: {args.results!r}")
    check_output("--output", args.output, (".png", ".pdf", ".svg"))
    if args.json:
        check_output("--json", args.json, (".json",))
    from ..sweep.report import report

    summary = report(p, args.output, json_path=args.json)
    print(summary["text"])
    print(f"wrote {args.output}" + (f" and {args.json}" if args.json else ""), file=sys.stderr)
    return 0


