"""Sub-commands `vehicle` (the loopback test vehicle) and `connect` (hardware in the loop)."""
from __future__ import annotations

import argparse

import sys
from pathlib import Path

from controller.errors import Se3SyncError
from cosim.cli.live_options import add_live_options, live_target
from cosim.cli.outcome import report_outcome
from cosim.guards import EXIT_DIVERGED
from cosim.cli.run import add_log_encoding
from cosim.registry import AGENT_AOT, LAWS

__all__ = ["register", "EXIT_NOT_CONNECTED", "EXIT_LINK"]

EXIT_NOT_CONNECTED = 3
EXIT_LINK = 4


def register(sub) -> None:
    p = sub.add_parser(
        "vehicle", help="run loopback test vehicles (plant FMUs speaking MAVLink 2 over UDP)",
        description="Serve N simulated multirotors over MAVLink 2/UDP: vehicle i (system id i) sends to "
                    "HOST:BASE_PORT+i-1 (PX4 SITL convention). Streams HEARTBEAT, ODOMETRY, "
                    "ATTITUDE_QUATERNION and LOCAL_POSITION_NED; takes SET_ACTUATOR_CONTROL_TARGET or "
                    "COMMAND_LONG DO_SET_ACTUATOR; fails safe (zero wrench) when commands time out. "
                    "Ctrl-C or SIGTERM stops it.")
    p.add_argument("--count", type=int, default=None, metavar="N", help="number of vehicles (default 1; "
                   "with --scenario: the scenario's agent count, and a different N is refused)")
    p.add_argument("--scenario", metavar="FILE", help="take masses, inertias, initial poses, gravity, "
                   "mapping and control step from this scenario")
    p.add_argument("--set", action="append", default=[], metavar="KEY.PATH=VALUE",
                   help="override a scenario value (with --scenario); repeatable")
    p.add_argument("--lockstep", action="store_true",
                   help="advance one control period per received command instead of the wall clock")
    p.add_argument("--key", metavar="FILE", help="MAVLink 2 signing key file (32 raw bytes or 64 hex chars)")
    p.add_argument("--allow-unsigned-heartbeat", action="store_true",
                   help="with --key: accept unsigned HEARTBEATs")
    p.add_argument("--rate", type=float, default=250.0, metavar="HZ",
                   help="physics tick and ODOMETRY rate in real time (default 250)")
    p.add_argument("--aux-rate", type=float, default=10.0, metavar="HZ",
                   help="ATTITUDE_QUATERNION and LOCAL_POSITION_NED rate (default 10; 0 = off)")
    p.add_argument("--start-file", metavar="FILE",
                   help="real time: once FILE holds a swarm's start (Unix time of its step 0, as "
                        "`swarm` writes it), tick 0.3 of a tick before each of the swarm's steps, "
                        "so that every agent reads the state of its step and its command has the "
                        "rest of the period to arrive (`swarm --vehicles loopback` passes it)")
    p.add_argument("--step", type=float, metavar="S",
                   help="control period (lockstep step, command timeout base); default: the scenario's "
                        "step, else 1/rate")
    p.add_argument("--command-timeout", type=float, metavar="S",
                   help="fail safe when no command for this long (default 2 control periods)")
    p.add_argument("--base-port", type=int, default=None,
                   help="first UDP port (default: the scenario's bridge.base_port, else 14540)")
    p.add_argument("--host", default=None, help="the bridge's address (default: the scenario's "
                   "bridge.host, else 127.0.0.1)")
    p.add_argument("--endpoint", action="append", metavar="ENDPOINT",
                   help="vehicle-side endpoint per vehicle (udpout:HOST:PORT or udpin:HOST:PORT); "
                        "repeat once per vehicle; overrides --base-port")
    p.add_argument("--shared-port", action="store_true",
                   help="all vehicles send to BASE_PORT (the bridge routes by system id)")
    p.add_argument("--first-system-id", type=int, default=1, help="system id of vehicle 1 (default 1)")
    p.add_argument("--gravity", metavar="GX,GY,GZ", help="gravity in NED without --scenario (e.g. 0,0,9.81)")
    p.add_argument("--require-arm", action="store_true", help="ignore commands until armed")
    p.add_argument("--tlog", metavar="FILE", help="write all traffic to this tlog")
    _security_options(p)
    p.add_argument("--commander", type=_commander, metavar="SYS[:COMP]",
                   help="the only system (and component; 0 = any) whose packets are obeyed (default: "
                        "the scenario's bridge.source_system:source_component, else 255:191)")
    p.add_argument("--stats", metavar="FILE", help="write the traffic counters (JSON) here on exit")
    p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds of wall time")
    p.add_argument("--sim-protocol", choices=("px4", "ardupilot"),
                   help="instead of MAVLink to a bridge, be a flight stack's simulator (needs --scenario): "
                        "px4 = PX4 SITL's simulator_mavlink interface (TCP 4560 + i, lockstep: "
                        "HIL_ACTUATOR_CONTROLS in, HIL_SENSOR/HIL_GPS/HIL_STATE_QUATERNION out); "
                        "ardupilot = ArduPilot SITL's JSON physics interface (UDP 9002 + 10 i)")
    p.add_argument("--sim-port", type=int, metavar="PORT",
                   help="first port of --sim-protocol (default 4560 for px4, 9002 for ardupilot)")
    p.add_argument("--sim-step", type=float, default=0.004, metavar="S",
                   help="px4: simulation step per HIL_SENSOR (default 0.004; ardupilot takes 1/frame_rate)")
    p.add_argument("--sim-no-noise", action="store_true", help="ideal sensors (no white noise)")
    p.add_argument("--sim-seed", type=int, default=0, help="sensor noise seed (default 0)")
    p.add_argument("--sim-idle-timeout", type=float, default=30.0, metavar="S",
                   help="px4: drop a connection that sent no HIL_ACTUATOR_CONTROLS for S s of wall time "
                        "(default 30), so that an idle client cannot hold its vehicle")
    p.add_argument("--write-params", metavar="FILE",
                   help="with --sim-protocol: write the stack's parameters that make its mixer match the "
                        "scenario's allocation (ArduPilot: a .parm file for --defaults; PX4: param set-default "
                        "lines) and exit; '{i}' in FILE writes one file per vehicle")
    add_live_options(p)
    p.set_defaults(func=_cmd_vehicle)

    p = sub.add_parser(
        "connect", help="run the controller against MAVLink vehicles (hardware in the loop)",
        description="Run a scenario's controller against vehicles over MAVLink 2 at the control rate "
                    "(simulation.step), paced by the wall clock (or --lockstep), through the same "
                    "master as `run`: same MCAP log and summary, plus link statistics. Endpoints come "
                    "from --vehicle or the scenario's [bridge] table. A run whose jumps exceed the "
                    "bound ⌈V̄(0)/(k_X δ)⌉ says so (stderr, \"jump_bound_exceeded\"), as `run` does. "
                    "Exit codes: 0 ok, 2 bad input, "
                    f"{EXIT_NOT_CONNECTED} a vehicle never connected, {EXIT_LINK} a lockstep link failed, "
                    f"{EXIT_DIVERGED} the run diverged and was stopped (log and summary complete, "
                    "\"diverged\"), 130 interrupted by Ctrl-C, 143 by SIGTERM (log and summary "
                    "finished, \"interrupted\": true).")
    p.add_argument("scenario", help="scenario TOML file")
    p.add_argument("--vehicle", action="append", metavar="ENDPOINT",
                   help="the bridge-side endpoint of vehicle i (udpin:HOST:PORT | udpout:HOST:PORT), "
                        "once per vehicle in order")
    p.add_argument("--log", metavar="OUT.mcap", help="write an MCAP log here")
    p.add_argument("--summary", metavar="OUT.json", help="write the run summary JSON here")
    add_log_encoding(p)
    p.add_argument("--duration", type=float, metavar="S", help="duration in s (overrides simulation.duration)")
    p.add_argument("--set", action="append", default=[], metavar="KEY.PATH=VALUE",
                   help="override a scenario value (e.g. --set bridge.base_port=15000); repeatable")
    p.add_argument("--lockstep", action="store_true", help="lockstep with the vehicles (deterministic)")
    p.add_argument("--key", metavar="FILE", help="MAVLink 2 signing key file (32 raw bytes or 64 hex chars)")
    p.add_argument("--connect-timeout", type=float, metavar="S", help="give up if a vehicle has not "
                   "connected after S seconds (default: bridge.connect_timeout, 10)")
    p.add_argument("--tlog", metavar="FILE", help="write all traffic to this tlog (mavlogdump.py reads it)")
    p.add_argument("--force", action="store_true", help="run even if the sampled loop is unstable at this step")
    _security_options(p)
    add_live_options(p)
    p.set_defaults(func=_cmd_connect)


    p = sub.add_parser(
        "agent", help="run one agent's controller as a vehicle's own process (several: --id "
                      "I,J,...); it talks only to its vehicle and its graph neighbours",
        description="Run agent I of a scenario as its own process (several agents in one with "
                    "--id I,J,...): the paper's law for agent I "
                    "only, on its vehicle (over MAVLink, as `connect` drives a vehicle) and on the "
                    "samples its graph neighbours send over UDP (MAVLink 2 ODOMETRY + "
                    "DEBUG_FLOAT_ARRAY for θ, signed with --key; endpoints from the scenario's "
                    "[network] table). Neighbour data older than network.max_age are held for "
                    "network.hold, then the agent fails safe (zero wrench) until fresh data come. "
                    "Writes its own MCAP log and summary. Exit codes: 0 ok, 2 bad input, "
                    f"{EXIT_NOT_CONNECTED} the vehicle never connected, {EXIT_LINK} lockstep: the "
                    "vehicle or a neighbour stopped answering (or a late joiner heard no "
                    "neighbour), 130 Ctrl-C, 143 SIGTERM (log and summary finished).")
    p.add_argument("scenario", help="scenario TOML file")
    p.add_argument("--id", required=True, metavar="I[,J,...]",
                   help="the agent's number, 1..N; several (1,2,3): those agents in one process, "
                        "one thread each, each with its own links, log and summary (a simulation "
                        "machine's many agents share one interpreter; --log, --summary and --tlog "
                        "then contain {id}, replaced by each agent's number)")
    p.add_argument("--start", type=float, metavar="UNIX_TIME",
                   help="real time: wall-clock time (s since 1970) of the swarm's step 0; every "
                        "agent of a swarm must get the same (`swarm` passes it); an agent "
                        "started after it joins at the next whole second of the run. Default: "
                        "0.2 s after the vehicle connects")
    p.add_argument("--start-file", metavar="FILE",
                   help="real time: once connected, create FILE.ready<I> and wait until FILE holds "
                        "the start time (what `swarm` does: it starts the clock when every agent "
                        "is ready)")
    p.add_argument("--lockstep", action="store_true",
                   help="lockstep with the vehicle and the neighbours (deterministic: a swarm in "
                        "lockstep equals `run` on the float32 reference plant)")
    p.add_argument("--vehicle", metavar="ENDPOINT",
                   help="the vehicle's bridge-side endpoint (udpin:HOST:PORT | udpout:HOST:PORT); "
                        "default: vehicle I of the scenario's [bridge] table")
    p.add_argument("--controller", choices=tuple(LAWS), default="hybrid",
                   help="the law (default hybrid), one with a per-agent view; "
                        + "; ".join(f"{k}: {v[1]}" for k, v in LAWS.items()))
    _kernels_option(p, "the agent's")
    p.add_argument("--log", metavar="OUT.mcap", help="write the agent's MCAP log here")
    add_log_encoding(p, "the agent's log's")
    p.add_argument("--summary", metavar="OUT.json", help="write the agent's summary JSON here")
    p.add_argument("--duration", type=float, metavar="S", help="duration in s (overrides "
                   "simulation.duration; the swarm's run ends at step ⌈S/h⌉)")
    p.add_argument("--set", action="append", default=[], metavar="KEY.PATH=VALUE",
                   help="override a scenario value; repeatable")
    p.add_argument("--key", metavar="FILE", help="MAVLink 2 signing key file (vehicle and neighbours)")
    p.add_argument("--connect-timeout", type=float, metavar="S", help="give up if the vehicle has not "
                   "connected after S seconds (default: bridge.connect_timeout, 10)")
    p.add_argument("--tlog", metavar="FILE", help="write the vehicle link's traffic to this tlog")
    _security_options(p)
    # the swarm's merged live view (`swarm --live`): where this agent sends its own row
    p.add_argument("--live-feed", metavar="HOST:PORT", help=argparse.SUPPRESS)
    p.add_argument("--live-rate", type=float, default=30.0, help=argparse.SUPPRESS)
    p.set_defaults(func=_cmd_agent)

    p = sub.add_parser(
        "swarm", help="run every agent of a scenario over the network, then merge their outputs",
        description="Start the scenario's agents as `se3sync agent` processes (several agents per "
                    "process by default: --agents-per-process) and, with --vehicles loopback, "
                    "the loopback vehicles; wait for them, and merge their summaries into one "
                    "with the fields of `run`'s (final, samples, jumps, n_jumps, jump_bound, "
                    "design) plus per-link statistics; --log merges their logs into one that "
                    "`se3sync plot` reads. Ctrl-C or SIGTERM stops every child and still writes "
                    "the merged outputs; the children die with the launcher. Exit codes: 0 ok, 2 "
                    "bad input or a port of the swarm taken or already receiving traffic (one "
                    "line naming it), 5 an agent failed (its last error line is shown), "
                    f"{EXIT_DIVERGED} the merged run diverged (a merged sample, or an agent's own "
                    "view: \"diverged\"), 130 Ctrl-C, 143 SIGTERM. More jumps than the bound "
                    "⌈V̄(0)/(k_X δ)⌉ are said as `run` says them (\"jump_bound_exceeded\").")
    p.add_argument("scenario", help="scenario TOML file")
    p.add_argument("--vehicles", choices=("loopback", "external"), default="external",
                   help="loopback: also start `se3sync vehicle` for the scenario; external "
                        "(default): the vehicles are already there, at the [bridge] endpoints")
    p.add_argument("--lockstep", action="store_true", help="agents and vehicles in lockstep")
    p.add_argument("--log", metavar="OUT.mcap", help="merge the agents' logs into this MCAP")
    add_log_encoding(p, "the agents' logs' and the merged log's")
    p.add_argument("--summary", metavar="OUT.json", help="write the merged summary here")
    p.add_argument("--dir", metavar="DIR",
                   help="keep each agent's log, summary and stderr here (default: a temporary "
                        "directory, removed at the end)")
    p.add_argument("--duration", type=float, metavar="S", help="duration in s (overrides "
                   "simulation.duration)")
    p.add_argument("--set", action="append", default=[], metavar="KEY.PATH=VALUE",
                   help="override a scenario value (passed to every process); repeatable")
    p.add_argument("--controller", choices=tuple(LAWS), default="hybrid",
                   help="the law every agent runs (default hybrid), one with a per-agent view")
    _kernels_option(p, "the agents'")
    p.add_argument("--key", metavar="FILE", help="MAVLink 2 signing key file for every link")
    p.add_argument("--start-delay", type=float, default=None, metavar="S",
                   help="real time: step 0 comes this long after every agent has connected to "
                        "its vehicle and is waiting (default 1 s)")
    p.add_argument("--insecure", action="store_true",
                   help="allow sockets reachable from other machines without --key")
    p.add_argument("--agents-per-process", default="auto", metavar="K",
                   help="run K agents in each process (`agent --id I,J,...`: one thread steps "
                        "them all): the agents share one interpreter's memory and wake together "
                        "each step; what they compute is the same. 'auto' (the default): the "
                        "fewest processes whose agents step within a quarter of a period (6 "
                        "agents at 250 Hz: one process of 6; 64 at 100 Hz: 16 per process). 1: "
                        "one process per agent, as each vehicle's own computer runs it")
    p.add_argument("--force", action="store_true",
                   help="run even if the sampled loop is unstable at this step")
    add_live_options(p)
    # a signal before the agents start still writes the merged summary and log (`main`)
    p.set_defaults(func=_cmd_swarm, stops_cleanly=True)


def _agent_ids(text: str) -> tuple:
    """--id: ``I`` or ``I,J,…`` (several agents hosted in one process), distinct numbers."""
    try:
        ids = tuple(int(x) for x in str(text).split(","))
    except ValueError:
        raise Se3SyncError(f"--id: must be an agent number or numbers separated by commas "
                           f"(1 or 1,2,3), got {text!r}") from None
    if len(set(ids)) != len(ids):
        raise Se3SyncError(f"--id: an agent is named twice in {text!r}")
    return ids


def _per_agent(option: str, path, ids: tuple):
    """An output path of agent i: the path itself for one agent; for several, the path must hold
    ``{id}`` (replaced by each agent's number)."""
    if path is None:
        return lambda i: None
    if len(ids) > 1 and "{id}" not in path:
        raise Se3SyncError(f"{option}: with several agents in --id the path must contain {{id}} "
                           f"(replaced by each agent's number), got {path!r}")
    return lambda i: path.replace("{id}", str(i))


def _kernels_option(p, whose: str) -> None:
    p.add_argument("--kernels", choices=("aot", "jit"), default="aot",
                   help=f"{whose} compiled kernels: aot (default) compiled ahead of time by "
                        "numba.pycc, built once per source beside numba's cache (~12 s), so the "
                        "process runs without numba and LLVM (about 100 MB less; laws "
                        f"{', '.join(AGENT_AOT)}; where it cannot be built, jit, and the summary's "
                        "startup.kernels says why); jit: numba's JIT, from its on-disk cache")


def _choose_kernels(kernels: str, law: str) -> str:
    """The agent process's kernels, chosen before anything imports one (`bridge.swarm.aot`)."""
    if kernels == "jit":
        return "jit"
    if law not in AGENT_AOT:
        return f"jit: the law {law!r} has kernels of its own"
    from bridge.swarm import aot

    return aot.use(progress=lambda s: print(f"se3sync agent: {s}", file=sys.stderr, flush=True))


def _cmd_agent(args) -> int:
    kernels = _choose_kernels(args.kernels, args.controller)
    from cosim.plants import refuse_actuation_delay
    from cosim.scenario import load_scenario

    from bridge.swarm.agent import run_agent
    from bridge.mavlink.plant import ConnectError, LinkError

    ids = _agent_ids(args.id)
    log_of = _per_agent("--log", args.log, ids)
    summary_of = _per_agent("--summary", args.summary, ids)
    tlog_of = _per_agent("--tlog", args.tlog, ids)
    for i in ids:
        _outputs(("--log", log_of(i), (".mcap",)), ("--summary", summary_of(i), None),
                 ("--tlog", tlog_of(i), None))
    if len(ids) > 1 and args.vehicle is not None:
        raise Se3SyncError("--vehicle: names one agent's vehicle; with several agents in --id "
                           "each takes its own from the scenario's [bridge] table")
    _timeout("--connect-timeout", args.connect_timeout)
    if args.start_file is not None and not Path(args.start_file).parent.is_dir():
        raise Se3SyncError(f"--start-file: {args.start_file!r}: directory "
                           f"{str(Path(args.start_file).parent)!r} does not exist")
    feed = None
    if args.live_feed is not None:
        from cosim.log.live import parse_live

        feed = (*parse_live(args.live_feed, option="--live-feed"), args.live_rate)
    sc = load_scenario(args.scenario, args.set, duration=args.duration)
    refuse_actuation_delay(sc, "se3sync agent (the vehicle is the plant)")
    N = sc.graph.n
    bad = [i for i in ids if not 1 <= i <= N]
    if bad:
        raise Se3SyncError(f"--id: must be an agent number in 1..{N}, got {bad[0]}")
    if args.start is not None and not (args.start == args.start and abs(args.start) < 1e11):
        raise Se3SyncError(f"--start: must be a Unix time in seconds, got {args.start!r}")
    if args.start is not None and args.start_file is not None:
        raise Se3SyncError("--start-file: give --start or --start-file, not both")

    def kwargs(i):
        return dict(law=args.controller, lockstep=args.lockstep, start=args.start,
                    start_file=args.start_file, key_file=args.key, insecure=args.insecure,
                    vehicle=args.vehicle, connect_timeout=args.connect_timeout,
                    signing_state=args.signing_state, tlog=tlog_of(i), log_path=log_of(i),
                    summary_path=summary_of(i), log_encoding=args.log_encoding,
                    progress=len(ids) == 1 and sys.stderr.isatty(), live_feed=feed,
                    kernels=kernels)

    if len(ids) == 1:
        try:
            results = {ids[0]: run_agent(sc, ids[0], **kwargs(ids[0]))}
        except (ConnectError, LinkError) as exc:
            results = {ids[0]: exc}
    else:
        from bridge.swarm.host import run_agents
        from cosim.threads import AGENT_THREADS, limit_process

        limit_process(AGENT_THREADS)   # once for the process's agents (each alone sets its own)
        results = run_agents(lambda agent_id, **kw: run_agent(sc, agent_id, **kw), ids, kwargs)
    rc = 0
    for i, res in results.items():
        if isinstance(res, BaseException):
            code = (EXIT_NOT_CONNECTED if isinstance(res, ConnectError) else
                    EXIT_LINK if isinstance(res, LinkError) else None)
            if code is None:
                if isinstance(res, KeyboardInterrupt):
                    rc = rc or 130
                    continue
                raise res
            print(f"se3sync agent: error: {'' if len(ids) == 1 else f'agent {i}: '}{res}",
                  file=sys.stderr)
            rc = rc if rc not in (0, 130) else code
            continue
        _agent_line(i, res, args.lockstep)
        if res.get("interrupted"):
            rc = rc or 130
    if rc == 130 and len(ids) > 1 and not any(isinstance(r, dict) for r in results.values()):
        raise KeyboardInterrupt   # none ran: as one agent stopped before its first step
    return rc


def _agent_line(i: int, summary: dict, lockstep: bool) -> None:
    f = summary.get("final") or {}
    al = summary.get("link", {}).get("agent_link", {})
    fs = summary["failsafe"]
    print(f"agent {i}: {summary['steps']} steps from step {summary['first_step']} "
          f"({'lockstep' if lockstep else 'real time'}) in {summary['wall_time_s']:.3g} s; "
          f"{summary['n_jumps']} jumps; its edges' max rot_err {f.get('rot_err', float('nan')):.3g}; "
          f"neighbour link: sent {al.get('sent')}, received {al.get('received')}, refused "
          f"{_refused(al)}; vehicle link: refused {_refused(summary.get('link', {}))}; "
          f"fail-safe {fs['steps']} steps ({fs['entries']} times)",
          file=sys.stderr)


def _cmd_swarm(args) -> int:
    from cosim import signals

    # a signal while the launcher loads (numpy, numba, mcap: about a second) is only noted:
    # the launcher then starts no process and still writes both outputs (`run_swarm_cli`)
    with signals.deferred():
        from bridge.swarm.launcher import run_swarm_cli

        _outputs(("--log", args.log, (".mcap",)), ("--summary", args.summary, None))
        args.live_target = live_target(args)
        return run_swarm_cli(args)


def _timeout(option: str, value) -> None:
    """A waiting time from the command line: a finite number of seconds > 0."""
    import math

    if value is not None and not (math.isfinite(value) and 0 < value <= 86400):
        raise Se3SyncError(f"{option}: must be a number of seconds in (0, 86400], got {value!r}")


def _outputs(*pairs) -> None:
    """Refuse unwritable outputs before waiting for any network peer."""
    from cosim.files import check_output

    for option, path, suffixes in pairs:
        if path is not None:
            check_output(option, path, suffixes)


def _security_options(p) -> None:
    p.add_argument("--insecure", action="store_true",
                   help="allow a socket reachable from other machines (not 127.x) without --key")
    p.add_argument("--signing-state", metavar="FILE",
                   help="with --key: where the signing timestamps persist across restarts "
                        "(default: KEYFILE.bridge.signing.json, KEYFILE.vehicle.signing.json)")


def _commander(text: str):
    import argparse

    try:
        parts = [int(x) for x in text.split(":")]
        if len(parts) == 1:
            parts.append(0)
        if len(parts) != 2 or not 1 <= parts[0] <= 255 or not 0 <= parts[1] <= 255:
            raise ValueError
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be SYS or SYS:COMP with SYS in 1..255 and COMP in 0..255, "
                                         f"got {text!r}") from None
    return tuple(parts)


def _vehicle_ports(args) -> None:
    """--first-system-id in 1..255 and --base-port in 1..65535, every vehicle's port too
    (vehicle with system id s sends to BASE_PORT + s − 1): port 0 or one past 65535 would be a
    silent send to nowhere or a traceback at the first datagram. One line naming the option."""
    if not 1 <= args.first_system_id <= 255:
        raise Se3SyncError(f"--first-system-id: must be a MAVLink system id in 1..255, got "
                           f"{args.first_system_id}")
    bp = args.base_port
    if bp is None:
        return
    if not 1 <= bp <= 65535:
        raise Se3SyncError(f"--base-port: must be a UDP port in 1..65535, got {bp}")
    if args.endpoint or args.shared_port or args.sim_protocol:
        return   # every vehicle sends to BASE_PORT itself, or the ports come from elsewhere
    if args.scenario:
        from bridge.mavlink.config import default_config
        from cosim.scenario import load_scenario

        sc = load_scenario(args.scenario, args.set or [])
        cfg = sc.bridge or default_config(sc.n_agents)
        if cfg.routing == "shared":
            return
        top = max(v.system_id for v in cfg.vehicles)
    else:
        top = args.first_system_id + (args.count or 1) - 1
    if bp + top - 1 > 65535:
        raise Se3SyncError(f"--base-port: the vehicle with system id {top} would send to port "
                           f"{bp + top - 1}, past 65535; use a lower --base-port")


def _cmd_vehicle(args) -> int:
    if args.count is not None and args.count < 1:
        raise Se3SyncError(f"--count: must be >= 1, got {args.count}")
    _vehicle_ports(args)
    _outputs(("--tlog", args.tlog, None), ("--stats", args.stats, None))
    if args.start_file is not None:
        if args.lockstep or getattr(args, "sim_protocol", None):
            raise Se3SyncError("--start-file: real time only, not with --lockstep or "
                               "--sim-protocol")
        if not Path(args.start_file).parent.is_dir():
            raise Se3SyncError(f"--start-file: {args.start_file!r}: directory "
                               f"{str(Path(args.start_file).parent)!r} does not exist")
    args.live_target = live_target(args)
    if args.live_target is not None and not args.scenario:
        raise Se3SyncError("--live: needs --scenario (the graph and the bodies to draw)")
    if args.live_target is not None and getattr(args, "sim_protocol", None):
        raise Se3SyncError("--live: not with --sim-protocol")
    if getattr(args, "sim_protocol", None):
        from bridge.vehicles.sim_cli import run_sim_cli

        return run_sim_cli(args)
    from bridge.vehicles.loopback import run_vehicle_cli

    return run_vehicle_cli(args)


def _cmd_connect(args) -> int:
    from cosim.plants import refuse_actuation_delay
    from cosim.scenario import ScenarioError, load_scenario

    from bridge.mavlink.config import default_config
    from bridge.mavlink.plant import ConnectError, LinkError, MavlinkPlant

    _outputs(("--log", args.log, (".mcap",)), ("--summary", args.summary, None),
             ("--tlog", args.tlog, None))
    _timeout("--connect-timeout", args.connect_timeout)
    live = live_target(args)
    sc = load_scenario(args.scenario, args.set, duration=args.duration)
    refuse_actuation_delay(sc, "se3sync connect (the vehicles are the plant)")
    cfg = sc.bridge or default_config(sc.n_agents)
    if args.vehicle:
        cfg = cfg.with_endpoints(args.vehicle)
    from bridge.mavlink.link import require_key_or_insecure  # before the slow stability check and warm-up

    require_key_or_insecure([v.endpoint for v in cfg.vehicles], args.key or cfg.key_file, args.insecure)
    if not args.force:
        from cosim.analysis.stability import analyse

        st = analyse(sc, law="hybrid", bisect=False)
        if not st["stable"]:
            raise ScenarioError("simulation.step", f"h = {sc.step:g} s makes the sampled loop unstable "
                                f"(spectral radius {st['spectral_radius']:.6f} >= 1); use --force to run anyway",
                                sc.path)
    warm_up(sc)  # compile the controller and metrics now, not while the vehicles wait for commands
    plant = MavlinkPlant(sc, cfg, lockstep=True if args.lockstep else None, key=args.key, tlog=args.tlog,
                         connect_timeout=args.connect_timeout, insecure=args.insecure,
                         signing_state=args.signing_state)
    try:
        try:
            plant.connect()
        except ConnectError as exc:
            print(f"se3sync connect: error: {exc}", file=sys.stderr)
            return EXIT_NOT_CONNECTED
        try:
            summary = run_hil(sc, plant, log_path=args.log, summary_path=args.summary,
                              log_encoding=args.log_encoding, progress=sys.stderr.isatty(),
                              live=live)
        except LinkError as exc:
            print(f"se3sync connect: error: {exc}", file=sys.stderr)
            return EXIT_LINK
    finally:
        plant.close()
    f = summary.get("final") or {}
    ln = summary.get("link", {})
    print(f"{sc.name}: {summary['steps']} steps over MAVLink ({'lockstep' if plant.lockstep else 'real time'}) "
          f"in {summary['wall_time_s']:.3g} s; {summary['n_jumps']} jumps; final rot_err "
          f"{f.get('rot_err', float('nan')):.3g}, pos_err {f.get('pos_err', float('nan')):.3g}; "
          f"packets sent {ln.get('sent')}, received {ln.get('received')}, lost on the way "
          f"{ln.get('dropped')} (gaps in the vehicles' sequence numbers), refused "
          f"{_refused(ln)}, latency p50/p99 {_ms(ln.get('latency_ms_p50'))}/"
          f"{_ms(ln.get('latency_ms_p99'))} ms, link losses {ln.get('link_losses')}", file=sys.stderr)
    return report_outcome("connect", summary)


def _refused(ln: dict) -> str:
    """'N (reason n, …)': the packets a link refused and why (malformed: did not frame or check)."""
    by = dict(ln.get("rejected_by_reason") or {})
    if ln.get("malformed"):
        by["malformed"] = ln["malformed"]
    n = sum(by.values())
    return f"{n} ({', '.join(f'{k} {v}' for k, v in sorted(by.items()))})" if n else "0"


def _ms(x):
    return "n/a" if x is None else f"{x:.3g}"


def warm_up(scenario) -> None:
    from bridge.mavlink.hil import warm_up as _warm_up

    _warm_up(scenario)


def run_hil(scenario, plant, **kw) -> dict:
    from bridge.mavlink.hil import run_hil as _run_hil

    return _run_hil(scenario, plant, **kw)
