"""Sub-commands `run`, `check` and `plot` of the se3sync command line."""
from __future__ import annotations

import json
import sys
import time

from controller.errors import Se3SyncError

from .. import signals
from ..analysis import DELAY_MAX_AGENTS
from ..files import check_output
from ..guards import EXIT_DIVERGED, RUN_DELAY_MAX_AGENTS
from ..registry import LAWS, PLANTS
from .live_options import add_live_options, live_target
from .outcome import report_outcome

__all__ = ["register", "add_log_encoding", "EXIT_UNSTABLE", "EXIT_DIVERGED"]

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
                    "unstable, and a [network] delay (delay + jitter, the longest link) beyond "
                    "its delay margin (see `se3sync check`), unless --force. A run whose jumps "
                    "exceed the bound ⌈V̄(0)/(k_X δ)⌉ says so (stderr, \"jump_bound_exceeded\"). "
                    "A run that diverges (a non-finite state, V̄ above 100 V̄(0), |ξ| above 1e6) "
                    f"stops there, its log and summary complete (\"diverged\"). Exit codes: 0 ok, "
                    f"2 bad input or refused, {EXIT_DIVERGED} diverged, 130 interrupted by "
                    "Ctrl-C, 143 by SIGTERM, at any moment (the log, if asked for, is finished "
                    "and the summary has \"interrupted\": true and the steps done, 0 before the "
                    "first). A run that fails leaves no log. See docs/run-guards.md.")
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
                   help="run even if the sampled loop is unstable at this step or the "
                        "[network] delay is beyond the delay margin (neither is computed)")
    p.add_argument("--delay-agents", type=int, metavar="N", dest="delay_agents",
                   default=RUN_DELAY_MAX_AGENTS,
                   help="with a [network] delay or jitter, compute the delay margin before the "
                        f"run only for graphs of at most N agents (default {RUN_DELAY_MAX_AGENTS}"
                        ": 6-10 s on 2 cores at 1000 agents, about 1.6 s at 6; 0 never); "
                        "above, the delay is not checked and a warning says so")
    add_live_options(p, insecure=True)
    p.set_defaults(func=_cmd_run, stops_cleanly=True)

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
    """`run`; a signal at any moment, also before the first step, leaves the outputs asked for
    (`cosim.early_stop`) and exits 130/143."""
    stage = ["loading the command line"]
    sc = None
    for opt, path, sfx in (("--log", args.log, (".mcap",)), ("--summary", args.summary, None)):
        if path is not None:
            check_output(opt, path, sfx)
    if isinstance(args.delay_agents, bool) or args.delay_agents < 0:
        raise Se3SyncError(f"--delay-agents: must be an integer >= 0, got {args.delay_agents!r}")
    live = live_target(args)

    def at(name):
        # a signal noted where Python could not raise (inside a callback from C, as numba
        # loading its cache runs) or while the command line loaded stops the run here
        if signals.requested():
            raise KeyboardInterrupt
        stage[0] = name
        signals.set_stage(name)

    # The set-up (imports of numba, the kernels and fmpy; the analysis; the FMU) runs with the
    # signals only noted: a KeyboardInterrupt raised inside an import would leave a module half
    # initialised, and writing the outputs after it would fail on that module. The stop happens
    # at the next stage (`at`), or at once inside the analysis' long LAPACK calls
    # (`signals.interruptible`); a second signal still raises at once.
    with signals.deferred():
        try:
            at("loading the scenario")
            from ..scenario import load_scenario

            sc = load_scenario(args.scenario, args.overrides, duration=args.duration,
                               step=args.step)
            extra = _guards(args, sc, at)
            at("loading the simulation")
            from ..run import run_scenario

            progress = sys.stderr.isatty()
            try:
                summary = run_scenario(sc, plant=args.plant or sc.plant_mode,
                                       controller=args.controller, log_path=args.log,
                                       summary_path=args.summary, progress=progress,
                                       log_encoding=args.log_encoding, summary_extra=extra,
                                       stage=at, live=live)
            except OSError as exc:  # the streamed log is the file being written when the disk is full
                raise Se3SyncError(f"{exc.filename or args.log or args.summary}: "
                                   f"{exc.strerror or exc}") from None
        except KeyboardInterrupt:
            from ..early_stop import stopped_before_start

            summary = stopped_before_start(
                sc, stage=signals.stage_at_signal() or stage[0], scenario_path=args.scenario,
                controller=args.controller,
                plant=args.plant or (sc.plant_mode if sc is not None else "fleet"),
                log_path=args.log, summary_path=args.summary, log_encoding=args.log_encoding)

    if summary.get("stopped_during"):
        print(f"se3sync run: interrupted while {summary['stopped_during']}, before the first "
              "step" + (" (summary and log written)" if args.summary or args.log else ""),
              file=sys.stderr)
        return 130
    f = summary.get("final") or {}
    msg = (f"{sc.name}: {summary['steps']} steps, {summary['sim_time_s']:.4g} s simulated in "
           f"{summary['wall_time_s']:.3g} s ({summary['realtime_factor'] or 0:.3g}× real time); "
           f"{summary['n_jumps']} jumps (bound {summary['jump_bound']}); final rot_err "
           f"{f.get('rot_err', float('nan')):.3g}, pos_err {f.get('pos_err', float('nan')):.3g}")
    print(msg, file=sys.stderr)
    if sc.actuation_delay:
        print(f"se3sync run: the plant applied each wrench {sc.actuation_delay} step(s) late "
              "(simulation.actuation_delay; the step's stability was checked with it, the "
              "delay margin without it)",
              file=sys.stderr)
    return report_outcome("run", summary)


def _guards(args, sc, at) -> dict:
    """The checks before a run (unless --force): the step's stability, then the [network]
    delay against the delay margin (`cosim.guards.delay_guard`); what they found, for the
    summary."""
    from ..analysis.stability import analyse
    from ..scenario import ScenarioError

    net = sc.tables.get("network")
    if args.force:
        if net is None:
            return {}
        d, key, _ = net.worst_delay(sc.graph, sc.step)
        return {"delay_check": {"worst_delay_steps": d, "worst_delay_s": round(d * sc.step, 12),
                                "key": key, "delay_margin_steps": None, "delay_margin_s": None,
                                "checked": d == 0, "why": "no delay" if d == 0 else "--force"}}
    at("checking the step's stability")
    st = analyse(sc, law=args.controller, bisect=False)
    if not st["stable"]:
        st = analyse(sc, law=args.controller, bisect=True)
        raise ScenarioError(
            "simulation.step",
            f"h = {sc.step:g} s makes the sampled loop unstable (spectral radius "
            f"{st['spectral_radius']:.6f} >= 1; max_stable_step = {st['max_stable_step']:.3g} s); "
            "use a smaller step or --force", sc.path)
    out = {}
    if sc.actuation_delay:
        at("checking the step's stability with the actuation delay")
        from ..analysis.actuation import actuation_check
        act = actuation_check(sc, law=args.controller, bisect=False)
        if act["stable"] is False:
            act = actuation_check(sc, law=args.controller, bisect=True)
            upto = ("" if act["max_stable_step"] is None else
                    f"; with it max_stable_step = {act['max_stable_step']:.3g} s")
            raise ScenarioError(
                "simulation.actuation_delay",
                f"{sc.actuation_delay} step(s) of actuation delay make the sampled loop at h = "
                f"{sc.step:g} s unstable (spectral radius {act['spectral_radius']:.6f} >= 1"
                f"{upto}); use a smaller step or --force", sc.path)
        out["actuation_check"] = act
    if net is None:
        return out
    at("computing the delay margin")
    from ..analysis.delay_guard import delay_guard     # scipy: only with a [network] table
    progress = None
    if sys.stderr.isatty():
        def progress(d, rho, seconds, outside=None):
            what = (f"spectral radius {rho:.8f}" if outside is None
                    else f"{outside} roots outside the unit circle")
            print(f"se3sync run: delay margin: d = {d} steps, {what} ({seconds:.1f} s)",
                  file=sys.stderr, flush=True)
    out["delay_check"] = delay_guard(sc, args.controller, args.delay_agents, progress)
    return out


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
    act = None
    if sc.actuation_delay:   # simulation.actuation_delay: the loop with it, besides the one without
        from ..analysis.actuation import actuation_check
        out["actuation_delay_steps"] = sc.actuation_delay
        out["actuation"] = act = actuation_check(sc, law=args.controller)
    rc = 0 if st["stable"] and (act is None or act["stable"] is not False) else EXIT_UNSTABLE
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
    if act is not None:
        what = f"{act['actuation_delay_steps']} step(s) late (simulation.actuation_delay"
        if act["network_delay_steps"]:
            what += f", with the network's {act['network_delay_steps']} step(s)"
        if act["spectral_radius"] is None:
            lines.append(f"actuation       {what}): {act['method']}")
        else:
            upto = ("" if act["max_stable_step"] is None else
                    f"; max_stable_step {act['max_stable_step']:.4g} s with it")
            lines.append(f"actuation       {what}): spectral radius {act['spectral_radius']:.8f} "
                         f"({'stable' if act['stable'] else 'UNSTABLE'}{upto})")
        lines.append("                the delay margin and the rates below are of the loop "
                     "without it")
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
