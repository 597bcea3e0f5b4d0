"""`se3sync vehicle --sim-protocol px4|ardupilot`: serve the scenario's bodies to a flight stack's
SITL (bridge.sim_px4, bridge.sim_ardupilot) until Ctrl-C, SIGTERM or --duration."""
from __future__ import annotations

import json
import signal
import sys

from controller.errors import Se3SyncError


def run_sim_cli(args) -> int:
    if not args.scenario:
        raise Se3SyncError("--sim-protocol: needs --scenario (the bodies' masses, inertias, poses and mapping)")
    if args.sim_step is not None and not args.sim_step > 0:
        raise Se3SyncError(f"--sim-step: must be > 0, got {args.sim_step:g}")
    if args.sim_port is not None and not 0 <= args.sim_port <= 65535:
        raise Se3SyncError(f"--sim-port: must be in 0..65535, got {args.sim_port}")
    from cosim.scenario import load_scenario

    sc = load_scenario(args.scenario, args.set or [])
    host = args.host or "127.0.0.1"
    try:
        if args.sim_protocol == "px4":
            from .sim_px4 import DEFAULT_PORT, Px4SimServer

            port = DEFAULT_PORT if args.sim_port is None else args.sim_port
            srv = Px4SimServer(sc, host=host, port=port, step=args.sim_step, noise=not args.sim_no_noise,
                               seed=args.sim_seed)
            where = f"TCP {host}:{port}" + (f"..{port + sc.n_agents - 1}" if sc.n_agents > 1 else "")
        else:
            from .sim_ardupilot import DEFAULT_PORT, ArduPilotJsonServer

            port = DEFAULT_PORT if args.sim_port is None else args.sim_port
            srv = ArduPilotJsonServer(sc, host=host, port=port, noise=not args.sim_no_noise, seed=args.sim_seed)
            where = f"UDP {host}:{port}" + (f" (+10 per vehicle, {sc.n_agents})" if sc.n_agents > 1 else "")
    except OSError as exc:
        raise Se3SyncError(f"--sim-port: cannot listen on {host}:{args.sim_port or 'default'}: "
                           f"{exc.strerror or exc}") from None
    print(f"se3sync vehicle: {args.sim_protocol} simulator interface for {sc.n_agents} vehicle(s) on {where}",
          file=sys.stderr, flush=True)
    old = signal.signal(signal.SIGTERM, lambda *a: srv.stop())
    try:
        st = srv.run(args.duration)
    finally:
        signal.signal(signal.SIGTERM, old)
        srv.close()
    if args.stats:
        import os

        tmp = f"{args.stats}.tmp"
        with open(tmp, "w") as f:
            json.dump(st, f, indent=1)
        os.replace(tmp, args.stats)
    print(f"se3sync vehicle: stopped; {json.dumps({k: v for k, v in st.items() if k != 'ports'})}",
          file=sys.stderr, flush=True)
    return 0
