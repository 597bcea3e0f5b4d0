"""`se3sync swarm`: every agent of a scenario as its own process (`se3sync agent`), and the merge
of what they wrote into the outputs of one run.

The launcher starts N agent processes (and, with ``vehicles="loopback"``, one `se3sync vehicle`
process serving the N vehicles) with the same scenario, overrides and start time, writes each
one's log, summary and stderr into a work directory, waits, and merges:

* `merge_summaries`: the agents' own rows and θ of the edges they own, at the 1 s samples and
  at the end, give the network's state S (N, 18) and θ (M,) at those instants; the network's
  errors come from `cosim.master.NetworkMetrics`, as in `run`. Jumps are the owners'. Per
  directed link j → i: messages sent by j, samples taken by i, lost = the difference, and the
  ages of the data i used.
* `merge_logs`: the agents' logged own rows (/tf, /agents) and owned edges (/edges, /jumps) at
  the log instants all of them recorded become one log written by `cosim.log.writer.McapLogger`
  for the whole scenario, so `se3sync plot`, `animate` and Foxglove read it as a `run` log.
"""
from __future__ import annotations

import json
import math
import os
import select
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from controller import V_bar, jump_bound, layout
from controller.errors import Se3SyncError
from cosim import guards, signals
from cosim.analysis.stability import analyse
from cosim.cli.outcome import report_outcome
from cosim.controllers import agent_view
from cosim.files import check_output_dir, write_json_atomic
from cosim.log.writer import McapLogger
from cosim.log.reader import read_log
from cosim.master import NetworkMetrics
from cosim.scenario import design_summary
from cosim.network import parse_network
from cosim.plants import refuse_actuation_delay
from cosim.registry import AGENT_AOT
from cosim.scenario import ScenarioError, load_scenario

from bridge.live import SwarmLive
from bridge.mavlink import frames
from bridge.mavlink.config import default_config, read_key_file
from bridge.mavlink.link import parse_endpoint, require_key_or_insecure
from bridge.swarm import aot

__all__ = ["merge_summaries", "merge_logs", "run_swarm", "run_swarm_cli", "EXIT_AGENT_FAILED"]

EXIT_AGENT_FAILED = 5
STOP_GRACE_S = 10.0    # after SIGTERM, how long the children get to finish their outputs


# ------------------------------------------------------------------------------ merging
def _full_state(scenario, rows: dict, thetas: dict):
    """S (N, 18) and θ (M,) from each agent's own row and the θ of the edges it owns."""
    N, M = scenario.graph.n, scenario.graph.M
    S = np.zeros((N, layout.S_WIDTH))
    for i in range(1, N + 1):
        S[i - 1] = rows[i]
    theta = np.zeros(M)
    for k in range(1, M + 1):
        theta[k - 1] = thetas[k]
    return S, theta


def merge_summaries(scenario, summaries: dict, *, law: str = "hybrid", wall: float | None = None,
                    interrupted: bool = False, lockstep: bool = False) -> dict:
    """One summary of the swarm from {agent id: its summary} (missing agents: listed, and the
    network's errors left out where they need them)."""
    sc = scenario
    N, M = sc.graph.n, sc.graph.M
    h = float(sc.step)
    mx = NetworkMetrics(sc)
    present = sorted(summaries)
    missing = [i for i in range(1, N + 1) if i not in summaries]

    def at(records_of):
        """{step: (rows, θ)} for the steps every agent recorded."""
        per = {i: {r["step"]: r for r in records_of(summaries[i]) if r} for i in present}
        if missing or not per:
            return {}
        common = set.intersection(*(set(p) for p in per.values()))
        out = {}
        for n in sorted(common):
            rows = {i: np.asarray(per[i][n]["S"], float) for i in present}
            th = {}
            for i in present:
                th.update({int(k): float(v) for k, v in per[i][n]["theta"].items()})
            if len(th) == M:
                out[n] = _full_state(sc, rows, th)
        return out

    samples = [mx.sample(n * h, S, th) for n, (S, th) in at(lambda s: s["own"]["samples"]).items()]
    finals = at(lambda s: [s["own"]["final"]])
    final = None
    if finals:
        n_end = max(finals)
        final = mx.sample(n_end * h, *finals[n_end])
        if samples and round(samples[-1]["t"] / h) != n_end and n_end % max(1, round(1 / h)) == 0:
            samples.append(dict(final))
    elif samples:
        final = dict(samples[-1])
    jumps = sorted((j for i in present for j in summaries[i]["jumps"]),
                   key=lambda j: (j["t"], j["edge"]))
    V0 = V_bar(sc.graph, sc.weighting, sc.design, sc.gains, sc.S0,
               sc.theta0 if law == "hybrid" else np.zeros(M), sc.inertia6)
    links = []
    for i in present:
        st = summaries[i].get("link", {}).get("agent_link", {})
        for j_str, ln in sorted(st.get("links", {}).items(), key=lambda x: int(x[0])):
            j = int(j_str)
            sent = None
            if j in summaries:   # samples j published to i
                sent = summaries[j].get("link", {}).get("agent_link", {}).get(
                    "links", {}).get(str(i), {}).get("published")
            lost = None if sent is None else max(0, sent - ln["samples"])
            entry = {"from": j, "to": i, "sent": sent, "received": ln["samples"], "lost": lost,
                     "loss": (lost / sent) if sent else None,
                     # what i refused of the packets that named j, and why (forged ones
                     # included: without a key anyone can name j)
                     "rejected": ln.get("rejected", 0),
                     "rejected_by_reason": ln.get("rejected_by_reason", {}),
                     "conflicts": ln.get("conflicts", 0),
                     "age_p50_steps": ln["age_p50_steps"], "age_p99_steps": ln["age_p99_steps"],
                     "age_p50_s": None if ln["age_p50_steps"] is None else ln["age_p50_steps"] * h,
                     "age_p99_s": None if ln["age_p99_steps"] is None else ln["age_p99_steps"] * h}
            if j in summaries:
                emu = summaries[j].get("link", {}).get("agent_link", {}).get("links", {}).get(
                    str(i), {}).get("emulated_lost")
                if emu is not None:
                    entry["emulated_lost"] = emu
            links.append(entry)
    agents = []
    for i in range(1, N + 1):
        s = summaries.get(i)
        if s is None:
            agents.append({"agent": i, "summary": None})
            continue
        ln = s.get("link", {})
        al = ln.get("agent_link", {})
        agents.append({"agent": i, "steps": s["steps"], "first_step": s.get("first_step", 0),
                       "interrupted": s["interrupted"], "wall_time_s": s["wall_time_s"],
                       "cpu_fraction": s.get("cpu_fraction"), "max_rss_mb": s.get("max_rss_mb"),
                       "memory": s.get("memory"), "startup": s.get("startup"),
                       **({"host": s["host"]} if s.get("host") else {}),
                       "failsafe": s["failsafe"],
                       "late_steps": ln.get("late_steps"),
                       "commands_past_tick": ln.get("commands_past_tick"),
                       "command_lag_ms_p99": ln.get("command_lag_ms_p99"),
                       "vehicle_latency_ms_p99": ln.get("latency_ms_p99"),
                       "vehicle_failsafes": ln.get("vehicle_failsafes"),
                       # everything this agent refused: on its neighbour link (all of it, also
                       # what named no neighbour: junk, strangers) and on its vehicle link
                       "rejected": {
                           "neighbour_link": {"rejected_by_reason": al.get("rejected_by_reason", {}),
                                              "malformed": al.get("malformed", 0),
                                              "kernel_drops": al.get("kernel_drops")},
                           "vehicle_link": {"rejected_by_reason": ln.get("rejected_by_reason", {}),
                                            "malformed": ln.get("malformed", 0),
                                            "dropped": ln.get("dropped", 0),
                                            "other_sources": ln.get("other_sources", {}),
                                            "kernel_drops": ln.get("kernel_drops")}}})
    steps = max((s["first_step"] + s["steps"] for s in summaries.values()), default=0)
    # every jump is an owner's, counted by its agent (an agent lists at most guards.MAX_JUMPS)
    n_jumps = sum(summaries[i].get("n_jumps", len(summaries[i]["jumps"])) for i in present)
    bound = jump_bound(V0, sc.gains.k_X, sc.design.delta)   # as `run`'s master computes it
    return {
        "scenario": sc.name, "scenario_path": str(sc.path), "controller": law,
        "plant": "mavlink (one agent per vehicle)", "lockstep": bool(lockstep),
        "step": h, "steps": steps, "sim_time_s": steps * h, "wall_time_s": wall,
        "interrupted": bool(interrupted or any(s["interrupted"] for s in summaries.values())),
        "agents_missing": missing,
        "design": design_summary(sc), "V0": V0,
        "jump_bound": bound, "n_jumps": n_jumps, "jump_bound_exceeded": n_jumps > bound,
        "diverged": _diverged(sc, V0, samples, summaries),
        "jumps": jumps, "final": final, "samples": samples,
        "links": links,
        "link_total": _link_total(links),
        "agents": agents,
        "rejected_total": _rejected_total(agents),
    }


def _diverged(sc, V0, samples, summaries):
    """How the swarm diverged, the earliest of: a merged sample of the whole network that
    `run`'s guard calls diverged (`cosim.guards.sample_divergence`), and an agent that stopped
    because its own view diverged (with ``"agent"``); None if neither."""
    found = []
    limit = guards.V_limit(V0, sc.gravity)
    for rec in samples:
        why = guards.sample_divergence(rec, limit)
        if why is not None:
            found.append({"t": rec["t"], "step": round(rec["t"] / sc.step), "reason": why,
                          "agent": None})
            break
    for i, s in sorted(summaries.items()):
        dv = s.get("diverged")
        if dv:
            found.append({"t": dv["t"], "step": dv["step"],
                          "reason": f"agent {i}'s own view: {dv['reason']}", "agent": i})
    return min(found, key=lambda d: (d["t"], d["agent"] is not None)) if found else None


def _rejected_total(agents) -> dict:
    """Every refusal of every agent, by link kind and reason."""
    out = {"neighbour_link": {}, "vehicle_link": {}}
    for a in agents:
        for kind, d in (a.get("rejected") or {}).items():
            tot = out[kind]
            for k, v in d["rejected_by_reason"].items():
                tot[k] = tot.get(k, 0) + v
            if d.get("malformed"):
                tot["malformed"] = tot.get("malformed", 0) + d["malformed"]
    return out


def _link_total(links) -> dict:
    sent = sum(ln["sent"] or 0 for ln in links)
    lost = sum(ln["lost"] or 0 for ln in links)
    p99 = [ln["age_p99_steps"] for ln in links if ln["age_p99_steps"] is not None]
    return {"sent": sent, "lost": lost, "loss": (lost / sent) if sent else None,
            "age_p99_steps_max": max(p99) if p99 else None}


def _own_records(path, agent: int, owned: set) -> dict:
    """{t_ns: {"S": row, "u": wrench, "theta"/"mu"/"jumped": {k: …}}} of agent's own log, and
    its jumps."""
    log = read_log(path)
    msgs = log["messages"]
    frame = f"agent_{agent}"
    rec: dict = {}
    for t, m in msgs.get("/tf", []):
        for x in m["transforms"]:
            if x["child_frame_id"] == frame:
                tr, ro = x["translation"], x["rotation"]
                rec.setdefault(t, {})["pq"] = ([tr["x"], tr["y"], tr["z"]],
                                               [ro["w"], ro["x"], ro["y"], ro["z"]])
    for t, m in msgs.get("/agents", []):
        for a in m["agents"]:
            if a["agent"] == agent and t in rec:
                rec[t]["xi"] = a["omega"] + a["v"]
                rec[t]["u"] = a["torque"] + a["force"]
    for t, m in msgs.get("/edges", []):
        if t not in rec:
            continue
        e = rec[t]
        e["edges"] = {x["edge"]: x for x in m["edges"] if x["edge"] in owned}
    jumps = [(t, m) for t, m in msgs.get("/jumps", [])]
    return {t: r for t, r in rec.items() if {"pq", "xi", "u", "edges"} <= set(r)}, jumps


def merge_logs(scenario, logs: dict, out_path, *, law: str = "hybrid",
               extra_metadata: dict | None = None, encoding: str = "json") -> dict:
    """One log of the swarm from {agent id: [its log paths]} (a restarted agent has several),
    its per-record channels in ``encoding``; returns {"records": …, "jumps": …}. Records are
    kept at the log instants every agent recorded. The agents' logs may be JSON or CDR."""
    sc = scenario
    N, M = sc.graph.n, sc.graph.M
    owned = {i: set(sc.graph.M_plus(i)) for i in range(1, N + 1)}
    recs, jumps, unreadable = {}, [], []
    for i in range(1, N + 1):
        recs[i] = {}
        for p in logs.get(i, []):
            try:
                r, js = _own_records(p, i, owned[i])
            except Exception:  # noqa: BLE001 - an agent killed mid-write leaves a torn log
                unreadable.append(str(p))
                continue
            recs[i].update(r)
            jumps += js
    common = sorted(set.intersection(*(set(r) for r in recs.values()))) if recs else []
    mx = NetworkMetrics(sc)
    logger = McapLogger(out_path, sc, controller=law, encoding=encoding, extra_metadata={
        "plant": "mavlink (one agent per vehicle)",
        "merged_from": json.dumps({str(i): [str(p) for p in logs.get(i, [])] for i in logs}),
        **(extra_metadata or {})})
    failed = True
    try:
        jumps.sort(key=lambda x: (x[0], x[1]["edge"]))
        ji = 0
        S = np.zeros((N, layout.S_WIDTH))
        u = np.zeros((N, 6))
        theta, mu = np.zeros(M), np.zeros(M)
        jumped = np.zeros(M, dtype=bool)
        for t in common:
            while ji < len(jumps) and jumps[ji][0] <= t:
                tj, m = jumps[ji]
                logger.jump(tj, m["t"], m["edge"], m["theta_before"], m["theta_after"], m["mu"])
                ji += 1
            for i in range(1, N + 1):
                r = recs[i][t]
                p, q = r["pq"]
                S[i - 1, layout.P] = p
                S[i - 1, layout.R] = frames.quat_to_rot(np.array([q]))[0]
                S[i - 1, layout.XI] = r["xi"]
                u[i - 1] = r["u"]
                for k, e in r["edges"].items():
                    theta[k - 1] = e["theta"]
                    mu[k - 1] = e["mu_U"] if e["mu_U"] is not None else np.nan
                    jumped[k - 1] = e["mode"] == "jump"
            V, _ = mx.compute(S, theta)
            logger.record(t, S, u, theta, mu, jumped, mx.rot, mx.pos, mx.U, mx.quat, float(V),
                          float(mx.kX * mx.U.sum()))
        for tj, m in jumps[ji:]:
            logger.jump(tj, m["t"], m["edge"], m["theta_before"], m["theta_after"], m["mu"])
        failed = False
    finally:
        logger.close(discard=failed)
    return {"records": len(common), "jumps": len(jumps), "unreadable": unreadable,
            "agents_without_log": [i for i in range(1, N + 1) if not logs.get(i)]}


# ------------------------------------------------------------------------------ launching
READY_TIMEOUT_S = 120.0   # every agent imports, loads its kernels and connects before the start
START_LEAD_S = 1.0        # from "all ready" to step 0: the start file reaches every agent
LOOPBACK_CONNECT_S = 120.0   # an agent's wait for a loopback vehicle the launcher started


PORT_LISTEN_S = 0.5       # start-up: how long the swarm's ports must be silent (lockstep
#                           vehicles repeat their state every 0.2 s, real-time ones stream)


class _Children:
    """The child processes, stopped together (SIGTERM, then SIGKILL after a grace period), and
    killed by the kernel if the launcher dies first (Linux: `cosim.signals.die_with`)."""

    def __init__(self):
        self.procs: dict = {}   # name -> (Popen, stderr path)
        self._setup = signals.die_with(os.getpid())

    def start(self, name: str, argv: list, err_path: Path) -> subprocess.Popen:
        f = open(err_path, "wb")
        try:
            p = subprocess.Popen(argv, stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                 preexec_fn=self._setup)
        finally:
            f.close()
        self.procs[name] = (p, err_path)
        return p

    def stop(self, names=None, grace: float = STOP_GRACE_S) -> None:
        names = list(self.procs) if names is None else names
        live = [self.procs[n][0] for n in names if self.procs[n][0].poll() is None]
        for p in live:
            try:
                p.send_signal(signal.SIGTERM)
            except OSError:
                pass
        t_end = time.monotonic() + grace
        for p in live:
            try:
                p.wait(timeout=max(0.0, t_end - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()

    def last_line(self, name: str) -> str:
        try:
            lines = [ln for ln in Path(self.procs[name][1]).read_text(
                encoding="utf-8", errors="replace").splitlines() if ln.strip()]
        except OSError:
            return ""
        return lines[-1] if lines else ""


def vehicle_argv(py, sc, scenario_path, sets: list, wd: Path, lockstep: bool, sec: list,
                 start_file=None) -> list:
    """The loopback vehicles' command line: one `se3sync vehicle` process for the scenario's
    vehicles, ticking (physics and ODOMETRY) at the swarm's control rate 1/h: each agent steps
    once per h and reads one state per step, so a faster stream would only be decoded and
    dropped (at 250 Hz, 64 vehicles cost that process twice the CPU of 100 Hz, and every agent
    2.5 ODOMETRY per step), and with a tick of h the vehicle holds each wrench for one control
    period, as `run`'s plant does. Real time: its ticks are locked to the swarm's steps
    (``start_file``, `bridge.vehicles.loopback.locked_tick`), so that a command applies from the
    tick after the state it was computed from, as in `run`, whatever phase the process started
    at."""
    return [py, "-m", "cosim.cli", "vehicle", "--scenario", str(Path(scenario_path)), *sets,
            "--rate", repr(1.0 / float(sc.step)), "--aux-rate", "0",
            "--stats", str(wd / "vehicle.json"), *(["--lockstep"] if lockstep else []),
            *(["--start-file", str(start_file)] if start_file is not None and not lockstep
              else []), *sec]


def check_ports(sc, vehicles: str, listen: float = PORT_LISTEN_S) -> None:
    """Start-up: every endpoint the swarm will bind must be free, and none may already receive
    traffic (something that is not part of this swarm, e.g. a vehicle or agent left over from an
    earlier run, would otherwise feed it foreign packets: a stale vehicle on the same ports
    turned a run's final rot_err from 0.036 into 2.0, silently). Listened to for ``listen``
    seconds: the agents' endpoints, and the vehicles' bridge-side ``udpin`` endpoints when the
    swarm starts the (loopback) vehicles itself. Raises Se3SyncError naming the port."""
    net = sc.tables.get("network") or parse_network({}, sc.n_agents)
    cfg = sc.bridge or default_config(sc.n_agents)
    eps = [(f"udpin:{h}:{p}", "network.base_port / [[network.agent]]", True) for h, p in net.endpoints]
    for v in cfg.vehicles:
        mode, _ = parse_endpoint(v.endpoint)
        if mode == "udpin":
            eps.append((v.endpoint, "bridge.base_port / [[bridge.vehicle]] endpoint",
                        vehicles == "loopback"))
    socks = []
    try:
        for ep, key, _ in eps:
            _, (host, port) = parse_endpoint(ep)
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            socks.append(s)
            try:
                s.bind((host, port))
            except OSError as exc:
                raise Se3SyncError(f"{host}:{port} ({ep}) cannot be bound: "
                                   f"{exc.strerror or exc}; another process (an agent or vehicle "
                                   f"left over from an earlier run?) has it: stop it or choose "
                                   f"other ports ({key})") from None
            s.setblocking(False)
        quiet = [(s, ep, key) for s, (ep, key, q) in zip(socks, eps) if q]
        t_end = time.monotonic() + listen
        while quiet and time.monotonic() < t_end:
            r, _, _ = select.select([q[0] for q in quiet], [], [], max(0.0, t_end - time.monotonic()))
            for s, ep, key in quiet:
                if s in r:
                    try:
                        _, addr = s.recvfrom(65535)
                    except OSError:
                        continue
                    raise Se3SyncError(f"{ep}: traffic from {addr[0]}:{addr[1]} before the swarm "
                                       "has started anything: a process that is not part of this "
                                       "swarm (a vehicle or agent left over from an earlier run?) "
                                       f"sends to this port; stop it or choose other ports ({key})")
    finally:
        for s in socks:
            s.close()


# `--agents-per-process auto`: the fewest processes whose agents step (one after another,
# `bridge.swarm.host`) within a quarter of a period, an agent's step taking about AUTO_STEP_S of
# CPU (hosted, 100 Hz: 0.013–0.016 of a core per agent, i.e. 130–160 µs a step). Why the fewest:
# every process pays a wake-up per period, which on a virtual machine costs about as much as an
# agent's step (`benchmarks/bench_wake_floor.py`: 0.016–0.019 of a core at 250 Hz), and the
# agents of one process share it. Measured on 2 cores, 6 agents at 250 Hz, CPU per agent: 1 per
# process 0.033, 2 0.028, 3 0.021, 6 0.017; 64 agents at 100 Hz: 16 per process (4 processes)
# 0.1–0.9 % late steps (median), 8 (8 processes) 1.8–2.1 %, 32 (2 processes, a period's queue of
# 4.5 ms) 0.5–1 % with the worst agent at 3.9–7.6 %; one per process, 20 %
AUTO_STEP_S = 150e-6
AUTO_QUEUE_SHARE = 0.25


def auto_agents_per_process(n_agents: int, h: float) -> int:
    """K for `--agents-per-process auto`: N agents in the fewest processes whose agents step
    within a quarter of a period h, spread evenly over them."""
    n = max(1, int(n_agents))
    fit = max(1, int(AUTO_QUEUE_SHARE * float(h) / AUTO_STEP_S))
    processes = -(-n // fit)
    return -(-n // processes)


def run_swarm(scenario_path, overrides=(), *, vehicles: str = "external", lockstep: bool = False,
              log_path=None, summary_path=None, workdir=None, duration=None, law: str = "hybrid",
              key_file=None, start_delay=None, insecure: bool = False, progress: bool = False,
              python=None, on_event=None, log_encoding: str = "json",
              stop_requested: list | None = None, live=None,
              agents_per_process: int | str = "auto", kernels: str = "aot") -> tuple:
    """Launches the swarm and merges its outputs; returns (merged summary, exit status): 0 all
    agents finished, EXIT_AGENT_FAILED an agent failed (the others are stopped), 130/143 a
    signal stopped everything (also one noted in ``stop_requested`` before the call: then no
    process is started). The merged outputs are written in every case. Raises Se3SyncError
    before starting anything when a port of the swarm is taken or already receives traffic
    (`check_ports`). live: (host, port, rate) of the merged live view (bridge/live.py), or
    None. agents_per_process: K > 1 runs agents 1..K in one process, K+1..2K in the next, …
    (`bridge.swarm.host`: one thread per agent; for a machine that simulates many vehicles);
    "auto": `auto_agents_per_process` for this swarm's size and step. The merged summary's
    ``agents_per_process`` says which K ran. kernels: the agents' (`se3sync agent --kernels`);
    "aot" builds the ahead-of-time module here first, once for all of them (`bridge.swarm.aot`),
    and each agent's ``startup.kernels`` says what it ran."""
    say = on_event or (lambda s: print(f"se3sync swarm: {s}", file=sys.stderr, flush=True))
    sc = load_scenario(scenario_path, overrides, duration=duration)
    stop_requested = [] if stop_requested is None else stop_requested
    if not stop_requested:
        check_ports(sc, vehicles)
    N = sc.graph.n
    py = python or sys.executable
    own_dir = workdir is None
    wd = Path(tempfile.mkdtemp(prefix="se3sync-swarm-") if own_dir else workdir)
    wd.mkdir(exist_ok=True)
    # a previous run's outputs in --dir must not be merged as this run's
    for pattern in ("agent_*.json", "agent_*.mcap", "agent_*.err", "agents_*.err",
                    "agent_*.layout.json",
                    "vehicle.json", "vehicle.err", "start", "start.*"):
        for old in wd.glob(pattern):
            old.unlink(missing_ok=True)
    sets = [x for o in overrides for x in ("--set", o)]
    common = [str(Path(scenario_path)), *sets]
    if duration is not None:
        common += ["--duration", repr(float(duration))]
    sec = (["--key", str(key_file)] if key_file else []) + (["--insecure"] if insecure else [])
    # loopback: the vehicle process starts with the agents and comes up when they do; started
    # with 64 agents importing numba on two cores it came up 43 s later, and an agent that had
    # loaded its kernels at 36 s waited 7.4 s of bridge.connect_timeout's 10 s for it
    wait = [] if vehicles != "loopback" else [
        "--connect-timeout", repr(max(LOOPBACK_CONNECT_S, float(
            (sc.bridge or default_config(sc.n_agents)).connect_timeout)))]
    kids = _Children()
    view = None
    if live is not None:   # the merged live view; each agent feeds it its own row
        view = SwarmLive(sc, live[0], live[1], rate=live[2], encoding=log_encoding)
        view.announce()
    feed = ([] if view is None else
            ["--live-feed", view.feed, "--live-rate", repr(float(live[2]))])
    rc = 0
    interrupted = False
    K = (auto_agents_per_process(N, sc.step) if agents_per_process == "auto"
         else max(1, int(agents_per_process)))
    t0 = time.monotonic()
    bar = None
    try:
        with signals.catching(lambda: stop_requested.append(True)):
            if stop_requested:
                interrupted = True
                say("stopped (signal) before any process started")
            elif vehicles == "loopback":
                kids.start("vehicle", vehicle_argv(py, sc, scenario_path, sets, wd, lockstep, sec,
                                                   wd / "start"), wd / "vehicle.err")
            if kernels == "aot" and law in AGENT_AOT and not stop_requested:
                _build_kernels(say)
            start = None
            start_file = wd / "start"
            groups = [list(range(a, min(N, a + K - 1) + 1)) for a in range(1, N + 1, K)]
            names = [f"agent {g[0]}" if len(g) == 1 else f"agents {g[0]}-{g[-1]}" for g in groups]
            for g, name in zip(groups, names):
                if stop_requested:
                    break
                one = len(g) == 1
                tag = str(g[0]) if one else "{id}"
                kids.start(name, [
                    py, "-m", "cosim.cli", "agent", *common, "--id", ",".join(map(str, g)),
                    "--controller", law, "--kernels", kernels,
                    "--summary", str(wd / f"agent_{tag}.json"),
                    *(["--log", str(wd / f"agent_{tag}.mcap"), "--log-encoding", log_encoding]
                      if log_path is not None else []),
                    *(["--lockstep"] if lockstep else ["--start-file", str(start_file)]), *sec,
                    *wait, *feed],
                    wd / (f"agent_{g[0]}.err" if one else f"agents_{g[0]}-{g[-1]}.err"))
            agents = [a for a in names if a in kids.procs]
            if agents:
                say(f"{len(agents)} agent processes"
                    f"{'' if K == 1 else f' ({N} agents, up to {K} per process)'}"
                    f"{' and the loopback vehicles' if vehicles == 'loopback' else ''}"
                    f" started ({'lockstep' if lockstep else 'real time'}); outputs in {wd}")
            if not lockstep and not stop_requested:
                # the clock starts when every agent is connected and waiting (ready files)
                t_ready = time.monotonic() + READY_TIMEOUT_S
                while not stop_requested:
                    ready = [i for i in range(1, N + 1) if Path(f"{start_file}.ready{i}").exists()]
                    dead = [a for a in agents if kids.procs[a][0].poll() is not None]
                    if len(ready) == N or dead or time.monotonic() > t_ready:
                        break
                    time.sleep(0.05)
                delay = START_LEAD_S if start_delay is None else float(start_delay)
                start = time.time() + delay
                tmp = start_file.with_suffix(".tmp")
                tmp.write_text(repr(start), encoding="utf-8")
                os.replace(tmp, start_file)
            if progress:
                bar = tqdm(total=sc.n_steps() * sc.step, unit="s", desc=f"{sc.name} (swarm)",
                           bar_format="{l_bar}{bar}| {n:.1f}/{total:.1f} s")
            while agents or stop_requested:
                codes = {a: kids.procs[a][0].poll() for a in agents}
                if stop_requested:
                    interrupted = True
                    say("stopping every process (signal)")
                    kids.stop(agents)   # the agents first: they finish their step and outputs
                    break
                failed = [a for a, c in codes.items() if c not in (None, 0)]
                if failed:
                    a = failed[0]
                    say(f"{a} failed (exit status {codes[a]}): {kids.last_line(a)}; stopping the others")
                    kids.stop(agents)
                    rc = EXIT_AGENT_FAILED
                    break
                if all(c == 0 for c in codes.values()):
                    break
                if "vehicle" in kids.procs and kids.procs["vehicle"][0].poll() is not None:
                    say(f"the vehicle process ended (status {kids.procs['vehicle'][0].returncode}): "
                        f"{kids.last_line('vehicle')}; stopping the agents")
                    kids.stop()
                    rc = EXIT_AGENT_FAILED
                    break
                if bar is not None and start is not None:
                    bar.update(min(bar.total, max(0.0, time.time() - start)) - bar.n)
                time.sleep(0.1)
            if "vehicle" in kids.procs:
                kids.stop(["vehicle"])
    finally:
        if bar is not None:
            bar.close()
        kids.stop()
        if view is not None:
            view.close()
    wall = time.monotonic() - t0
    summaries = {}
    for i in range(1, N + 1):
        p = wd / f"agent_{i}.json"
        try:
            summaries[i] = json.loads(p.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            pass
    merged = merge_summaries(sc, summaries, law=law, wall=wall, interrupted=interrupted,
                             lockstep=lockstep)
    merged["agents_per_process"] = K
    merged["exit_status"] = {name: p.returncode for name, (p, _) in kids.procs.items()}
    merged["workdir"] = None if own_dir else str(wd)
    try:
        vst = json.loads((wd / "vehicle.json").read_text(encoding="utf-8"))
        merged["vehicles"] = {k: vst.get(k) for k in (
            "received", "datagrams", "malformed", "rejected", "rejected_by_reason", "failsafe",
            "commands", "dropped", "commander",
            # its deadlines and its cost (real time; ticks counted from the first command)
            "tick_s", "ticks", "late_ticks", "resyncs", "cpu_s", "wall_s", "ticking_cpu_s",
            "ticking_s", "tick_lead_s", "tick_locked")}
    except (OSError, ValueError):
        pass
    if log_path is not None:
        # written at every stop, also one before any agent wrote a log (then without records)
        logs = {i: [wd / f"agent_{i}.mcap"] for i in range(1, N + 1)
                if (wd / f"agent_{i}.mcap").exists()}
        merged["log"] = str(log_path)
        merged["log_merge"] = merge_logs(sc, logs, log_path, law=law, extra_metadata={
            "time_base": "simulated (lockstep)" if lockstep else
                         "wall (paced: t = n·h from the swarm's start)",
            "interrupted": str(bool(interrupted)).lower()}, encoding=log_encoding)
        missing = merged["log_merge"]["agents_without_log"] + merged["log_merge"]["unreadable"]
        if missing:
            say(f"merged log {log_path} has no records from agent log(s) {missing} (missing or torn)")
    if summary_path is not None:
        write_json_atomic(summary_path, merged)
    if own_dir:
        shutil.rmtree(wd, ignore_errors=True)
    if interrupted:
        rc = signals.exit_status()
    return merged, rc


def _refused_line(merged) -> str:
    parts = []
    for kind, name in (("neighbour_link", "neighbour links"), ("vehicle_link", "vehicle links")):
        d = merged["rejected_total"][kind]
        parts.append(f"{name} {sum(d.values())}" + (
            f" ({', '.join(f'{k} {v}' for k, v in sorted(d.items()))})" if d else ""))
    return "; ".join(parts)


def _build_kernels(say) -> None:
    """The agents' ahead-of-time kernels built before they start, so that they do not all wait
    for one build (or, where it cannot be built, each learns why at once and runs on the JIT)."""
    try:
        aot.ensure(progress=say)
    except aot.AotError as exc:
        say(f"the agents run on numba's JIT: {exc}")


def run_swarm_cli(args) -> int:
    """Handler of ``se3sync swarm``."""
    early = [True] if signals.requested() else []   # noted while the command line loaded
    with signals.catching(lambda: early.append(True)):
        # a signal from here on still writes both outputs (run_swarm starts nothing then)
        return _swarm_cli(args, early)


def _timing_line(merged) -> str:
    """Real time: the agents' late steps and their commands past the vehicles' ticks (a step of
    actuation delay each; `MavlinkPlant.stats`), summed over the agents; '' in lockstep."""
    ag = [a for a in merged["agents"] if a.get("commands_past_tick") is not None]
    if merged.get("lockstep") or not ag:
        return ""
    late = sum(a.get("late_steps") or 0 for a in ag)
    past = sum(a["commands_past_tick"] for a in ag)
    return f" late steps {late}, commands past the vehicles' ticks {past};"


def _swarm_cli(args, early: list) -> int:
    # everything an agent would refuse is refused here, once, before a process starts
    if args.dir is not None:
        check_output_dir("--dir", args.dir)
    app = args.agents_per_process
    if app != "auto":
        try:
            app = int(app)
        except (TypeError, ValueError):
            app = 0
        if app < 1:
            raise Se3SyncError(f"--agents-per-process: must be an integer >= 1 or auto, got "
                               f"{args.agents_per_process!r}")
    if args.start_delay is not None and not (math.isfinite(args.start_delay)
                                             and 0 <= args.start_delay <= 3600):
        raise Se3SyncError(f"--start-delay: must be a number of seconds in [0, 3600], got "
                           f"{args.start_delay!r}")
    sc = load_scenario(args.scenario, args.set, duration=args.duration)
    refuse_actuation_delay(sc, "se3sync swarm (the vehicles are the plant)")
    agent_view(args.controller, sc, 1)   # the law has a per-agent view, or one line saying not
    key = read_key_file(args.key) if args.key else None
    net = sc.tables.get("network") or parse_network({}, sc.n_agents)
    cfg = sc.bridge or default_config(sc.n_agents)
    require_key_or_insecure([f"udpin:{h}:{p}" for h, p in net.endpoints], key, args.insecure,
                            "feed the agents false neighbour states")
    require_key_or_insecure([v.endpoint for v in cfg.vehicles], key, args.insecure)
    if args.lockstep and (net.default.delay or net.default.jitter or net.default.loss
                          or any(x.delay or x.jitter or x.loss for x in net.links.values())):
        raise ScenarioError("network.delay", "lockstep exchanges every step's data exactly; an "
                            "emulated delay, jitter or loss contradicts it", sc.path)
    if not args.force:
        st = analyse(sc, law=args.controller, bisect=False)
        if not st["stable"]:
            raise ScenarioError("simulation.step", f"h = {sc.step:g} s makes the sampled loop "
                                f"unstable (spectral radius {st['spectral_radius']:.6f} >= 1); "
                                "use --force to run anyway", sc.path)
    merged, rc = run_swarm(args.scenario, args.set, vehicles=args.vehicles, lockstep=args.lockstep,
                           log_path=args.log, summary_path=args.summary, workdir=args.dir,
                           duration=args.duration, law=args.controller, key_file=args.key,
                           start_delay=args.start_delay, insecure=args.insecure,
                           progress=sys.stderr.isatty(), log_encoding=args.log_encoding,
                           stop_requested=early, live=getattr(args, "live_target", None),
                           agents_per_process=app, kernels=args.kernels)
    f = merged.get("final") or {}
    tot = merged["link_total"]
    print(f"{sc.name}: {len(merged['agents']) - len(merged['agents_missing'])} agents, "
          f"{merged['steps']} steps ({'lockstep' if args.lockstep else 'real time'}) in "
          f"{merged['wall_time_s']:.3g} s; {merged['n_jumps']} jumps; final rot_err "
          f"{f.get('rot_err', float('nan')):.3g}, pos_err {f.get('pos_err', float('nan')):.3g}; "
          f"inter-agent messages {tot['sent']}, lost {tot['lost']}, age p99 "
          f"{tot['age_p99_steps_max']} steps;{_timing_line(merged)} refused: "
          f"{_refused_line(merged)}", file=sys.stderr)
    status = report_outcome("swarm", merged)   # the jump bound, a divergence: as `run` says them
    return rc or status
