"""Sub-commands `run`, `check` and `plot` of the se3sync command line."""
from __future__ import annotations

import json
import sys
import time

from controller.errors import Se3SyncError

from ..files import check_output
from .live_options import add_live_options, live_target
from ..analysis import DELAY_MAX_AGENTS
from ..registry import LAWS, PLANTS

__all__ = ["register", "add_log_encoding", "EXIT_UNSTABLE"]

EXIT_UNSTABLE = 3   # `check`: the sampled loop is unstable at the step checked
SWEEP_EVERY = 2.0   # `check` on a terminal: seconds between lines of the delay margin's sweep
PLOT_FORMATS = (".png", ".pdf", ".svg", ".eps", ".ps")


def add_log_encoding(p, whose: str = "the log's") -> None:
    """--log-encoding, the same for every command that writes a run log."""
    p.add_argument("--log-encoding", choices=("json", "cdr"), default="json",
                   help=f"messages of {whose} per-record channels (/tf, /edges, /agents, "
                        "/lyapunov, /scene, trails): json (default; readable as text) or cdr "
                        "(ROS 2 CDR with .msg schemas: the same values, for large swarms, where "
                        "formatting JSON costs more than the simulation; Foxglove reads both)")


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
                    "input, 130 interrupted by Ctrl-C, 143 by SIGTERM (either way the log is "
                    "finished and the summary has \"interrupted\": true). A run that fails "
                    "leaves no log.")
    p.add_argument("scenario", help="scenario TOML file")
    p.add_argument("--log", metavar="OUT.mcap",
                   help="write an MCAP log (streamed; simulated-time stamps) to this path")
    add_log_encoding(p)
    p.add_argument("--summary", metavar="OUT.json",
                   help="write the run summary JSON (atomically) to this path")
    p.add_argument("--duration", type=float, metavar="S",
                   help="simulated duration in s (overrides simulation.duration)")
    p.add_argument("--step", type=float, metavar="H",
                   help="communication step h in s (overrides simulation.step)")
    _add_set(p)
    p.add_argument("--plant", choices=tuple(PLANTS), default=None,
                   help="; ".join(f"{k}: {v[1]}" for k, v in PLANTS.items())
                   + " (default: the scenario's plant.mode)")
    p.add_argument("--controller", choices=tuple(LAWS), default="hybrid",
                   help="; ".join(f"{k}: {v[1]}" for k, v in LAWS.items()) + " (default hybrid)")
    p.add_argument("--force", action="store_true",
                   help="run even if the sampled loop is unstable at this step")
    add_live_options(p, insecure=True)
    p.set_defaults(func=_cmd_run)

    p = sub.add_parser(
        "check", help="validate a scenario, print its synergy design and sampled-data stability",
        description="Validate a scenario and print the synergy design (Lemma 2) and the "
                    "stability of the zero-order-hold loop at the scenario's step h, linearised "
                    "at consensus: spectral_radius (< 1 is stable) and max_stable_step. Exit "
                    f"codes: 0 stable, 2 bad input, {EXIT_UNSTABLE} unstable at this step (the "
                    "report is printed either way), so that check can gate a CI job.")
    p.add_argument("scenario", help="scenario TOML file")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    p.add_argument("--step", type=float, metavar="H", help="check this step instead")
    p.add_argument("--controller", choices=tuple(LAWS), default="hybrid",
                   help="which law's loop to linearise (default hybrid)")
    p.add_argument("--from-error", type=float, metavar="E", dest="from_error",
                   help="error to converge from (default: the scenario's initial error)")
    p.add_argument("--delay-agents", type=int, metavar="N", dest="delay_agents",
                   default=DELAY_MAX_AGENTS,
                   help="compute the delay margin only for graphs of at most N agents (default "
                        f"{DELAY_MAX_AGENTS}; 0 never). On a tree of 16 agents or more the roots "
                        "outside the unit circle are counted exactly (argument principle, O(N) "
                        "per frequency): on 2 cores under 1 s to 100 agents, 6-10 s at 1000 and "
                        "about 80 s at 10,000. Below 16 agents a frequency sweep guesses the "
                        "margin and spectral radii decide (about 2 s). Graphs that are not "
                        "trees above about 214 agents: not computed. On a terminal, each delay "
                        "tried prints a progress line to stderr, and the sweep prints one every "
                        "2 s")
    _add_set(p)
    p.set_defaults(func=_cmd_check)

    p = sub.add_parser(
        "plot", help="plot a run log like the paper's Fig. 2",
        description="Plot ‖I − R̄_k‖, ‖p̄_k‖, ‖ω_i‖, ‖v_i‖, V̄ and θ_k against simulated time from "
                    "an se3sync MCAP log (matplotlib, Agg backend).")
    p.add_argument("log", nargs="+", help="MCAP log(s) written by `se3sync run --log`; "
                   "several are overlaid")
    p.add_argument("-o", "--output", required=True, metavar="FIG.png",
                   help="output image (format from the suffix: png, pdf, svg, eps, ps)")
    p.add_argument("--labels", metavar="A,B,...",
                   help="comma-separated names of the overlaid runs (default: file names)")
    p.add_argument("--linear", action="store_true",
                   help="linear y axes (default: log axes for errors, speeds and V̄)")
    p.add_argument("--tmin", type=float, metavar="S", help="start of the time axis (s)")
    p.add_argument("--tmax", type=float, metavar="S", help="end of the time axis (s)")
    p.add_argument("--dpi", type=int, default=150, help="raster resolution (default 150)")
    p.set_defaults(func=_cmd_plot)

    p = sub.add_parser(
        "animate", help="render a 3D animation (MP4 or GIF) of a run log",
        description="Render the bodies (boxes of their inertia, with axes, one colour and a "
                    "number label per agent; bodies at one place drawn as nested boxes under "
                    "one label, e.g. 1 = 3 = 5) and the graph edges (coloured by ‖I − R̄_k‖_F, "
                    "green to red on a log scale, with a colour bar) of an se3sync MCAP log, "
                    "with the simulated time and the max edge error. MP4 needs ffmpeg; GIF "
                    "uses Pillow.")
    p.add_argument("log", help="an MCAP log written by `se3sync run --log`")
    p.add_argument("-o", "--output", required=True, metavar="OUT.mp4|OUT.gif",
                   help="output animation (.mp4 via ffmpeg, .gif via Pillow)")
    p.add_argument("--duration", type=float, default=10.0, metavar="S",
                   help="length of the animation in s of playback (default 10)")
    p.add_argument("--fps", type=float, default=20.0, help="frames per second (default 20)")
    p.add_argument("--tmin", type=float, metavar="S", help="first simulated time shown")
    p.add_argument("--tmax", type=float, metavar="S", help="last simulated time shown")
    p.add_argument("--dpi", type=int, default=100, help="resolution (default 100)")
    p.set_defaults(func=_cmd_animate)


def _cmd_run(args) -> int:
    from ..analysis.stability import analyse
    from ..run import run_scenario
    from ..scenario import ScenarioError, load_scenario

    for opt, path, sfx in (("--log", args.log, (".mcap",)), ("--summary", args.summary, None)):
        if path is not None:
            check_output(opt, path, sfx)
    live = live_target(args)
    sc = load_scenario(args.scenario, args.overrides, duration=args.duration, step=args.step)
    if not args.force:
        st = analyse(sc, law=args.controller, bisect=False)
        if not st["stable"]:
            st = analyse(sc, law=args.controller, bisect=True)
            raise ScenarioError(
                "simulation.step",
                f"h = {sc.step:g} s makes the sampled loop unstable (spectral radius "
                f"{st['spectral_radius']:.6f} >= 1; max_stable_step = {st['max_stable_step']:.3g} s); "
                "use a smaller step or --force", sc.path)
    progress = sys.stderr.isatty()
    try:
        summary = run_scenario(sc, plant=args.plant or sc.plant_mode, controller=args.controller,
                               log_path=args.log, summary_path=args.summary, progress=progress,
                               log_encoding=args.log_encoding, live=live)
    except OSError as exc:  # the streamed log is the file being written when the disk fills up
        raise Se3SyncError(f"{exc.filename or args.log or args.summary}: "
                           f"{exc.strerror or exc}") from None
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
    from ..analysis.stability import analyse
    from ..scenario import design_summary
    from ..scenario import load_scenario

    from ..analysis.stability_report import check_extras, check_lines, check_options

    check_options(args.from_error, args.delay_agents)
    sc = load_scenario(args.scenario, args.overrides, step=args.step)
    st = analyse(sc, law=args.controller)
    out = {"scenario": sc.name, "design": design_summary(sc), "step": sc.step,
           "spectral_radius": st["spectral_radius"], "stable": st["stable"],
           "max_stable_step": st["max_stable_step"]}
    progress = sweep = None
    if sys.stderr.isatty():
        def progress(d, rho, seconds, outside=None):
            what = (f"spectral radius {rho:.8f}" if outside is None
                    else f"{outside} roots outside the unit circle")
            print(f"se3sync check: delay margin: d = {d} steps, {what} ({seconds:.1f} s)",
                  file=sys.stderr, flush=True)

        t0 = [time.perf_counter()] * 2          # start, last line

        def sweep(k, g, n):
            now = time.perf_counter()
            if now - t0[1] >= SWEEP_EVERY:
                t0[1] = now
                stage = f"{g}/{n} grid points" if g < n else "grid done, narrowing the crossings"
                print(f"se3sync check: delay margin: frequency sweep, {k} eigenproblems of T, "
                      f"{stage} ({now - t0[0]:.0f} s)", file=sys.stderr, flush=True)
    out.update(check_extras(sc, st, args.controller, args.from_error, args.delay_agents,
                            progress, sweep))
    rc = 0 if st["stable"] else EXIT_UNSTABLE
    if args.json:
        print(json.dumps(out, indent=1))
        return rc
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
    return rc


def _cmd_plot(args) -> int:
    from ..log.plot import plot_logs

    labels = None
    if args.labels is not None:
        labels = [x.strip() for x in args.labels.split(",")]
        if len(labels) != len(args.log):
            raise Se3SyncError(f"--labels: {len(labels)} labels for {len(args.log)} logs")
    if not 1 <= args.dpi <= 2400:
        raise Se3SyncError(f"--dpi: must be in 1..2400, got {args.dpi}")
    check_output("--output", args.output, PLOT_FORMATS)
    out = plot_logs(args.log, args.output, labels, linear=args.linear, tmin=args.tmin,
                    tmax=args.tmax, dpi=args.dpi)
    print(f"wrote {out}", file=sys.stderr)
    return 0


def _cmd_animate(args) -> int:
    from ..log.animate import animate_log

    if not 1 <= args.dpi <= 1200:
        raise Se3SyncError(f"--dpi: must be in 1..1200, got {args.dpi}")
    check_output("--output", args.output, (".gif", ".mp4"))
    n = animate_log(args.log, args.output, duration=args.duration, fps=args.fps,
                    tmin=args.tmin, tmax=args.tmax, dpi=args.dpi, progress=sys.stderr.isatty())
    print(f"wrote {args.output} ({n} frames)", file=sys.stderr)
    return 0
