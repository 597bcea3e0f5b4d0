"""Sub-commands `run`, `check` and `plot` of the se3sync command line."""
from __future__ import annotations

import json
import sys

__all__ = ["register"]


def _add_set(p):
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY.PATH=VALUE",
                   help="override a scenario value before validation (VALUE is a TOML value, "
                        "e.g. --set gains.k_X=50 --set simulation.duration=2); repeatable")


def register(sub) -> None:
    p = sub.add_parser(
        "run", help="co-simulate a scenario (plant FMU + distributed hybrid controller)",
        description="Co-simulate a scenario: the plant FMU advanced with a fixed communication "
                    "step h under zero-order hold, the controller's network view evaluated at "
                    "every step. Refuses a step h for which the linearised sampled loop is "
                    "unstable (see `se3sync check`) unless --force. Exit codes: 0 ok, 2 bad "
                    "input, 130 interrupted (Ctrl-C: the log is finished and the summary has "
                    "\"interrupted\": true).")
    p.add_argument("scenario", help="scenario TOML file")
    p.add_argument("--log", metavar="OUT.mcap",
                   help="write an MCAP log (streamed; simulated-time stamps) to this path")
    p.add_argument("--summary", metavar="OUT.json",
                   help="write the run summary JSON (atomically) to this path")
    p.add_argument("--duration", type=float, metavar="S",
                   help="simulated duration in s (overrides simulation.duration)")
    p.add_argument("--step", type=float, metavar="H",
                   help="communication step h in s (overrides simulation.step)")
    _add_set(p)
    p.add_argument("--plant", choices=("fleet", "per-body"), default=None,
                   help="one N-body FMU instance (fleet, the default) or N single-body "
                        "instances (per-body); default: the scenario's plant.mode")
    p.add_argument("--controller", choices=("hybrid", "gradient"), default="hybrid",
                   help="the paper's hybrid feedback (default) or the gradient-only baseline")
    p.add_argument("--force", action="store_true",
                   help="run even if the sampled loop is unstable at this step")
    p.set_defaults(func=_cmd_run)

    p = sub.add_parser(
        "check", help="validate a scenario, print its synergy design and sampled-data stability",
        description="Validate a scenario and print the synergy design (Lemma 2) and the "
                    "stability of the zero-order-hold loop at the scenario's step h, linearised "
                    "at consensus: spectral_radius (< 1 is stable) and max_stable_step.")
    p.add_argument("scenario", help="scenario TOML file")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    p.add_argument("--step", type=float, metavar="H", help="check this step instead")
    p.add_argument("--controller", choices=("hybrid", "gradient"), default="hybrid",
                   help="which loop to linearise (default hybrid)")
    p.add_argument("--from-error", type=float, metavar="E", dest="from_error",
                   help="error to converge from (default: the scenario's initial error)")
    _add_set(p)
    p.set_defaults(func=_cmd_check)

    p = sub.add_parser(
        "plot", help="plot a run log like the paper's Fig. 2",
        description="Plot ‖I − R̄_k‖, ‖p̄_k‖, ‖ω_i‖, ‖v_i‖ and θ_k against simulated time from an "
                    "se3sync MCAP log (matplotlib, Agg backend).")
    p.add_argument("log", help="an MCAP log written by `se3sync run --log`")
    p.add_argument("-o", "--output", required=True, metavar="FIG.png",
                   help="output image (format from the suffix: png, pdf, svg)")
    p.set_defaults(func=_cmd_plot)


def _design(sc) -> dict:
    d = sc.design.as_dict()
    return {k: d[k] for k in ("case", "u_c1", "u_c2", "delta_star", "gamma", "delta",
                              "gamma_bound", "delta_bound", "exact_gap", "warnings", "Theta",
                              "eigenvalues_W")}


def _check_outputs(*paths):
    """Refuse unwritable output locations before anything runs."""
    import os
    from pathlib import Path

    from controller.errors import Se3SyncError

    for p in paths:
        if p is None:
            continue
        d = Path(p).parent if str(Path(p).parent) else Path(".")
        if not d.is_dir():
            raise Se3SyncError(f"{p}: directory {d} does not exist")
        if not os.access(d, os.W_OK):
            raise Se3SyncError(f"{p}: directory {d} is not writable")


def _cmd_run(args) -> int:
    from controller.errors import Se3SyncError

    from .api import run_scenario
    from .scenario import ScenarioError, load_scenario
    from .stability import analyse

    sc = load_scenario(args.scenario, args.overrides, duration=args.duration, step=args.step)
    _check_outputs(args.log, args.summary)
    if not args.force:
        st = analyse(sc, hybrid=args.controller == "hybrid", bisect=False)
        if not st["stable"]:
            st = analyse(sc, hybrid=args.controller == "hybrid", bisect=True)
            raise ScenarioError(
                "simulation.step",
                f"h = {sc.step:g} s makes the sampled loop unstable (spectral radius "
                f"{st['spectral_radius']:.6f} >= 1; max_stable_step = {st['max_stable_step']:.3g} s); "
                "use a smaller step or --force", sc.path)
    progress = sys.stderr.isatty()
    try:
        summary = run_scenario(sc, plant=args.plant or sc.plant_mode, controller=args.controller,
                               log_path=args.log, summary_path=args.summary, progress=progress)
    except OSError as exc:
        raise Se3SyncError(f"{exc.filename or ''}: {exc.strerror or exc}") from None
    f = summary.get("final") or {}
    msg = (f"{sc.name}: {summary['steps']} steps, {summary['sim_time_s']:.4g} s simulated in "
           f"{summary['wall_time_s']:.3g} s ({summary['realtime_factor'] or 0:.3g}× real time); "
           f"{summary['n_jumps']} jumps (bound {summary['jump_bound']}); final rot_err "
           f"{f.get('rot_err', float('nan')):.3g}, pos_err {f.get('pos_err', float('nan')):.3g}")
    print(msg, file=sys.stderr)
    if summary.get("interrupted"):
        print(f"se3sync run: interrupted after {summary['sim_time_s']:.4g} s simulated",
              file=sys.stderr)
        return 130
    return 0


def _cmd_check(args) -> int:
    from .scenario import load_scenario
    from .stability import analyse

    from .stability_report import check_extras, check_lines

    sc = load_scenario(args.scenario, args.overrides, step=args.step)
    st = analyse(sc, hybrid=args.controller == "hybrid")
    out = {"scenario": sc.name, "design": _design(sc), "step": sc.step,
           "spectral_radius": st["spectral_radius"], "stable": st["stable"],
           "max_stable_step": st["max_stable_step"]}
    out.update(check_extras(sc, st, args.controller == "hybrid", args.from_error))
    if args.json:
        print(json.dumps(out, indent=1))
        return 0
    d = out["design"]
    fmt = lambda v: "[" + ", ".join(f"{x:.4f}" for x in v) + "]"  # noqa: E731
    lines = [
        f"scenario        {sc.name} ({sc.path}): {sc.graph.n} agents, {sc.graph.M} edges",
        f"case            {d['case']} (eigenvalues of W {fmt(d['eigenvalues_W'])})",
        f"u_c1            {fmt(d['u_c1'])}",
        f"u_c2            {fmt(d['u_c2'])}",
        f"Theta           {fmt(d['Theta'])}",
        f"delta_star      {d['delta_star']:.6g}",
        f"gamma           {d['gamma']:.6g} (bound {d['gamma_bound']:.6g})",
        f"delta           {d['delta']:.6g} (Lemma 2 bound {d['delta_bound']:.6g}, exact gap {d['exact_gap']:.6g})",
    ]
    for w in d["warnings"]:
        lines.append(f"warning         {w}")
    lines += [
        f"step            {sc.step:g} s",
        f"spectral_radius {st['spectral_radius']:.8f} ({'stable' if st['stable'] else 'UNSTABLE'})",
        f"max_stable_step {st['max_stable_step']:.4g} s",
    ]
    lines += check_lines(out)
    print("\n".join(lines))
    return 0


def _cmd_plot(args) -> int:
    from .plot import plot_log

    _check_outputs(args.output)
    out = plot_log(args.log, args.output)
    print(f"wrote {out}", file=sys.stderr)
    return 0
