"""`se3sync vehicle --sim-protocol px4|ardupilot`: serve the scenario's bodies to a flight stack's
SITL (bridge.vehicles.sim_px4, bridge.vehicles.sim_ardupilot) until Ctrl-C, SIGTERM or --duration; or, with
--write-params, write the stack's parameters for the scenario's airframes (bridge.mavlink.airframes)."""
from __future__ import annotations

import json
import os
import signal
import sys

import numpy as np

from controller.errors import Se3SyncError
from cosim import signals


def run_sim_cli(args) -> int:
    if not args.scenario:
        raise Se3SyncError("--sim-protocol: needs --scenario (the bodies' masses, inertias, poses and mapping)")
    if args.sim_step is not None and not args.sim_step > 0:
        raise Se3SyncError(f"--sim-step: must be > 0, got {args.sim_step:g}")
    if args.sim_port is not None and not 0 <= args.sim_port <= 65535:
        raise Se3SyncError(f"--sim-port: must be in 0..65535, got {args.sim_port}")
    if not args.sim_idle_timeout > 0:
        raise Se3SyncError(f"--sim-idle-timeout: must be > 0, got {args.sim_idle_timeout:g}")
    from cosim.scenario import load_scenario

    from bridge.mavlink.config import default_config
    from bridge.mavlink.mapping import DIRECT
    from .loopback import check_count

    sc = load_scenario(args.scenario, args.set or [])
    check_count(args.count, sc)
    cfg = sc.bridge or default_config(sc.n_agents)
    if args.sim_protocol == "px4":
        direct = [i + 1 for i, m in enumerate(cfg.mappings) if m.kind == DIRECT]
        if direct:
            raise Se3SyncError(f"bridge.mapping: \"direct\" (vehicle {direct[0]}) reads PX4's outputs 1-6 as a wrench, "
                               "which no PX4 output function produces: use mapping = \"allocation\" with an "
                               "allocation.frame and --write-params")
    if args.write_params:
        return write_params(args, sc, cfg)
    host = args.host or "127.0.0.1"
    try:
        if args.sim_protocol == "px4":
            from .sim_px4 import DEFAULT_PORT, Px4SimServer

            port = DEFAULT_PORT if args.sim_port is None else args.sim_port
            srv = Px4SimServer(sc, host=host, port=port, step=args.sim_step, noise=not args.sim_no_noise,
                               seed=args.sim_seed, idle_timeout=args.sim_idle_timeout)
            where = _where("TCP", host, [ln.port for ln in srv.links], 1)
        else:
            from .sim_ardupilot import DEFAULT_PORT, ArduPilotJsonServer

            port = DEFAULT_PORT if args.sim_port is None else args.sim_port
            srv = ArduPilotJsonServer(sc, host=host, port=port, noise=not args.sim_no_noise, seed=args.sim_seed)
            where = _where("UDP", host, [ln.port for ln in srv.links], 10)
    except OSError as exc:
        raise Se3SyncError(f"--sim-port: cannot listen on {host}:{args.sim_port or 'default'}: "
                           f"{exc.strerror or exc}") from None
    old = signal.signal(signal.SIGTERM, lambda signum, frame: (signals.note(signum), srv.stop()))
    try:
        print(f"se3sync vehicle: {args.sim_protocol} simulator interface for {sc.n_agents} vehicle(s) on {where} "
              "(no authentication: anyone who reaches the port drives the vehicle)", file=sys.stderr, flush=True)
        if np.any(sc.gravity) and not sc.plant_terms.get("ground"):
            print("se3sync vehicle: note: gravity without [plant] ground = true: the bodies are held at their "
                  "initial poses until the stack spins the motors, then fall freely", file=sys.stderr, flush=True)
        st = srv.run(args.duration)
    finally:
        signal.signal(signal.SIGTERM, old)
        srv.close()
    if args.stats:
        tmp = f"{args.stats}.tmp"
        with open(tmp, "w") as f:
            json.dump(st, f, indent=1)
        os.replace(tmp, args.stats)
    print(f"se3sync vehicle: stopped; {json.dumps({k: v for k, v in st.items() if k != 'ports'})}",
          file=sys.stderr, flush=True)
    return signals.exit_status() if signals.requested() else 0


def _where(proto: str, host: str, ports: list, stride: int) -> str:
    """The ports the servers listen on, as bound (with --sim-port 0 the OS chose them)."""
    if len(ports) == 1:
        return f"{proto} {host}:{ports[0]}"
    if ports == [ports[0] + stride * i for i in range(len(ports))]:
        return f"{proto} {host}:{ports[0]}..{ports[-1]}" + (f" (+{stride} per vehicle)" if stride != 1 else "")
    return f"{proto} {host}, ports {', '.join(map(str, ports))} for vehicles 1..{len(ports)}"


def write_params(args, sc, cfg) -> int:
    """--write-params FILE: the stack parameters of every vehicle's airframe ('{i}' in FILE: one file
    per vehicle; without, the vehicles must share mass and airframe)."""
    from bridge.mavlink.airframes import params_text
    from bridge.mavlink.mapping import ALLOCATION

    g = float(np.linalg.norm(sc.gravity))
    if not g > 0:
        raise Se3SyncError("--write-params: the hover throttle needs gravity: set plant.gravity")
    for i, m in enumerate(cfg.mappings):
        if m.kind != ALLOCATION:
            raise Se3SyncError(f"--write-params: vehicle {i + 1} has mapping = \"{m.kind}\": the stack allocates, so "
                               "its airframe must be described: mapping = \"allocation\" with allocation.frame")
    per_vehicle = "{i}" in args.write_params
    if not per_vehicle:
        first = (float(sc.masses[0]), cfg.mappings[0].allocation)
        for i in range(1, sc.n_agents):
            if (float(sc.masses[i]), cfg.mappings[i].allocation) != first:
                raise Se3SyncError(f"--write-params: vehicle {i + 1} differs from vehicle 1 (mass or allocation): "
                                   "put '{i}' in the file name to write one file per vehicle")
    targets = [(i, args.write_params.replace("{i}", str(i + 1))) for i in range(sc.n_agents)] if per_vehicle \
        else [(0, args.write_params)]
    texts = []
    for i, path in targets:
        spec = cfg.mappings[i].allocation
        header = (f"se3sync vehicle --sim-protocol {args.sim_protocol} --write-params: scenario {sc.path}, "
                  f"vehicle {i + 1 if per_vehicle else '1..' + str(sc.n_agents)}\n"
                  f"frame {spec.frame}, arm {spec.arm_length:g} m, tilt {spec.tilt_deg:g} deg, "
                  f"{spec.max_thrust:g} N per rotor, torque coefficient {spec.torque_coeff:g} m, "
                  f"mass {float(sc.masses[i]):g} kg, g {g:g} m/s^2")
        texts.append((path, params_text(args.sim_protocol, spec, float(sc.masses[i]), g, header)))
    for path, text in texts:          # everything computed first: an error writes nothing
        tmp = f"{path}.tmp"
        try:
            with open(tmp, "w") as f:
                f.write(text)
            os.replace(tmp, path)
        except OSError as exc:
            raise Se3SyncError(f"--write-params: cannot write {path}: {exc.strerror or exc}") from None
        print(f"se3sync vehicle: wrote {path}", file=sys.stderr, flush=True)
    return 0
