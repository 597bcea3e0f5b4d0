"""The per-vehicle agent processes (`se3sync swarm`) in real time: CPU per agent process, the age
of the neighbour data used, losses, the loopback vehicle process's deadlines, memory, start-up
and the loop's outcome against `se3sync run`.

    python benchmarks/bench_agents.py [--duration S] [--cases 6x250,64x100] [--repeats R]
                                      [--keep DIR] [--against DIR [--label NAME]]

Cases: ``NxRATE`` = N agents at RATE Hz: N = 6 is hil_6uav itself; any other N a random tree of
seed 0 (`cosim.analysis.stability_cases.tree_scenario_text`: hil_6uav's vehicles, weighting and
gains, each agent k ≥ 2 joined to a random earlier one, a random start of seed 1, and
hil_6uav's [bridge] table); ``NxRATEsK`` the random tree of seed K (also for N = 6),
``NxRATEchain`` the chain 1-2-…-N; a suffix ``pK`` (``64x100p8``) runs K agents per process
(`swarm --agents-per-process K`: one thread each), ``pauto`` the K that ``auto`` picks (the
swarm's default); without a suffix, one process per agent (``--agents-per-process 1``). Each
agent has its own loopback vehicle (one `se3sync vehicle` process serves them all, ticking at
RATE), no logs. Per case one swarm run; reported:
- per agent: its CPU while it stepped (share of one core, median and max over the agents; with
  K agents per process, the process's CPU over K, and the agent's own thread's CPU), its late
  steps (share of its steps that ended after their deadline: median, max), its commands past
  the vehicle's tick (share of its commands sent more than (1 − VEHICLE_TICK_LEAD) of a step
  after their step's deadline: the loopback vehicle, locked to the timeline, had ticked, so
  they act a step late, which `late steps` does not count), the
  inter-agent data age p50/p99 (steps) and the losses over every directed link;
- the vehicle process: its CPU from the first command to its end (share of one core), its late
  ticks (a physics tick more than one tick after it was due) of all ticks, and its resyncs (it
  fell 10 ticks behind and skipped them);
- the machine: the CPU of the case's processes and of other work meanwhile (cores, /proc/stat),
  and its wake floor just before the case (`bench_wake_floor.py`'s paced floor at the case's
  rate, 2 s: what a process that only sends and reads a step's datagrams costs per step here
  now; it moves by the hour on a virtual machine, and an agent's figure with it), its packet
  floor just after (`bench_wake_floor.hosted_floor`, 2 s: the first process's K agents on one
  thread, each step a select, its vehicle's state and its neighbours' samples read, its sample
  sent to each neighbour and a command to its vehicle, and nothing else: what the agent's
  datagrams alone cost per agent, hosted as the case hosts it),
  the load average at the start and at the end;
- memory per process at its end (hosting K agents: divide by K for a figure per agent) (`bridge.swarm.agent._memory`: VmHWM, RssAnon, RssFile,
  PSS; median and max) and Σ PSS over the agents (what they hold together: the shared libraries
  counted once); start-up in seconds of process age (kernels loaded ``warm_s``, ready to step
  ``ready_s``, first step ``first_step_s``: that one waits for the slowest agent of the swarm);
- V̄ at the 1 s samples of the merged summary and of `se3sync run` of the same scenario on the
  float32 reference plant (tests/bridge/test_agents.py's reference), final V̄ / V̄(0) of both and
  how many samples rose; the final rot_err of both.
``--repeats R`` runs every case R times, the cases in turn (case 1, case 2, …, case 1, …), and
adds a table per case over its runs: the median of the runs' per-agent CPU (and the lowest and
highest), the same over each run's wake floor (what the agent costs against a bare process
doing one agent's datagrams per step, measured then) and over its packet floor (against its
own datagrams hosted as it is: the factor the agent's own work adds), each run's figure beside
its wake floor, its packet floor and the other work on the machine then, and
the worst late steps, data age and losses of all runs. On a virtual machine one run's CPU
figure moves with the hour (the wake floor with it); the median of several runs spread over a
few minutes is the figure to compare with a goal.
``--against DIR`` runs every case in the code of another checkout too (its packages in DIR: the
swarm, the agents and the vehicle process are that tree's), each run of this tree paired with
one of DIR's made just before or after it (the order alternates from pair to pair), each in a
process of its own; a table per case gives both trees' medians and the median of the pairs'
ratios. On a virtual machine whose figure moves by the minute, the pairs are what can show a
change of a few per cent.
Numbers from one machine at one time: compare them with each other, not across machines; with
other work on the machine the CPU figures include what sharing the cores costs (caches).
"""
from __future__ import annotations

import argparse
import json
import os
import re
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import _markdown

ROOT = Path(__file__).resolve().parents[1]
HIL = ROOT / "scenarios" / "hil_6uav.toml"


def parse_case(case: str) -> tuple:
    """``NxRATE`` (N = 6: hil_6uav itself; else a random tree of seed 0 with hil_6uav's
    vehicles, weighting and gains), ``NxRATEsK`` (the random tree of seed K, also for N = 6),
    ``NxRATEchain`` (the chain 1-2-…-N), each with an optional ``pK`` (K agents per process)
    -> (N, rate, tree kind or None, seed, K)."""
    m = re.fullmatch(r"(\d+)x([0-9.]+)(?:(chain)|s(\d+))?(?:p(\d+|auto))?", case.strip())
    if not m or (m.group(5) not in (None, "auto") and int(m.group(5)) < 1):
        raise SystemExit(f"--cases: {case!r} is not NxRATE, NxRATEsSEED or NxRATEchain "
                         "(optionally followed by pK, K >= 1, or pauto)")
    n, rate = int(m.group(1)), float(m.group(2))
    k = "auto" if m.group(5) == "auto" else int(m.group(5) or 1)
    if m.group(3):
        return n, rate, "chain", 0, k
    if m.group(4) is None and n == 6:
        return n, rate, None, 0, k
    return n, rate, "random", int(m.group(4) or 0), k


def scenario_for(n: int, rate: float, tmp: Path, kind=None, seed: int = 0) -> tuple[Path, list]:
    """The scenario file and the --set overrides of a case: hil_6uav itself (kind None), or
    `cosim.analysis.stability_cases.tree_scenario_text` (hil_6uav's vehicles, weighting, gains
    and [bridge] table on a chain or a seeded random tree, a random start of seed 1)."""
    from bridge.mavlink.link import free_base_port
    from cosim.analysis.stability_cases import tree_scenario_text

    sets = [f"simulation.step={1.0 / rate!r}", f"bridge.base_port={free_base_port(n)}",
            f"network.base_port={free_base_port(n)}"]
    if kind is None:
        return HIL, sets
    text = tree_scenario_text(n, kind, seed)   # drops [bridge]: hil_6uav's is put back
    text += "[bridge]" + HIL.read_text(encoding="utf-8").split("[bridge]", 1)[1]
    path = tmp / f"{kind}{n}_s{seed}.toml" if kind == "random" else tmp / f"chain{n}.toml"
    path.write_text(text, encoding="utf-8")
    return path, sets


def _busy_seconds():
    """CPU seconds the machine has spent busy since boot (every core; /proc/stat), or None."""
    try:
        with open("/proc/stat") as f:
            v = [int(x) for x in f.readline().split()[1:9]]
    except (OSError, ValueError):
        return None
    return (sum(v) - v[3] - v[4]) / os.sysconf("SC_CLK_TCK")


def _children_seconds() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _med(xs):
    xs = [x for x in xs if x is not None]
    return statistics.median(xs) if xs else None


def _max(xs):
    return max((x for x in xs if x is not None), default=None)


def reference(path, sets, duration) -> dict:
    """`se3sync run` of the same scenario on the float32 reference plant (what MAVLink carries),
    as tests/bridge/test_agents.py's lockstep tests make it."""
    from bridge.mavlink.transport import QuantizedPlant
    from cosim.run import run_scenario
    from cosim.scenario import load_scenario

    sc = load_scenario(path, sets, duration=duration)
    plant = QuantizedPlant(sc)
    try:
        return run_scenario(sc, plant=plant)
    finally:
        plant.close()


def v_bar(summary) -> dict:
    """V̄ at the 1 s samples: the values, the final one over V̄(0), and how many samples rose."""
    vs = [s["V"] for s in summary.get("samples") or []]
    if not vs:
        return {"V": [], "ratio": None, "rises": None}
    return {"V": vs, "ratio": vs[-1] / vs[0] if vs[0] else None,
            "rises": sum(1 for a, b in zip(vs, vs[1:]) if b > a)}


def run_case(case: str, duration: float, keep=None) -> dict:
    from bridge.swarm.launcher import run_swarm

    import bench_wake_floor

    n, rate, kind, seed, per = parse_case(case)
    floor_us = bench_wake_floor.floor(rate, max(50, int(2 * rate)))
    load0 = os.getloadavg()
    with tempfile.TemporaryDirectory() as d:
        wd = Path(keep) / case if keep else Path(d)
        wd.mkdir(parents=True, exist_ok=True)
        path, sets = scenario_for(n, rate, wd, kind, seed)
        nbrs = bench_wake_floor.graph_of(path)
        busy0, own0, t0 = _busy_seconds(), _children_seconds(), time.monotonic()
        merged, rc = run_swarm(path, sets, vehicles="loopback", duration=duration,
                               workdir=wd / "work", on_event=lambda s: None,
                               agents_per_process=per)
        wall = time.monotonic() - t0
        busy1, own = _busy_seconds(), (_children_seconds() - own0) / wall
        other = None if busy0 is None or busy1 is None else max(0.0, (busy1 - busy0) / wall - own)
        load1 = os.getloadavg()
        ref = reference(path, sets, duration)
    per = merged.get("agents_per_process", per) if per == "auto" else per
    # the floor of the first process's agents (K of them) doing their datagrams alone, just after
    packet_us = bench_wake_floor.hosted_floor(rate, max(50, int(2 * rate)), nbrs,
                                              hosted=range(1, min(_int_or(per, n), n) + 1))
    ag = [a for a in merged["agents"] if a.get("steps") is not None]
    # one entry per process: an agent alone, or the first of the agents a process hosts (the
    # memory and the process's CPU are the process's)
    procs = [a for a in ag if not a.get("host") or a["host"]["agents"][0] == a["agent"]]
    per_agent = [(a["host"]["cpu_fraction"] / len(a["host"]["agents"])) if a.get("host")
                 else a.get("cpu_fraction") for a in ag]
    late = [a["late_steps"] / a["steps"] for a in ag if a.get("late_steps") is not None
            and a["steps"]]
    past = [a["commands_past_tick"] / a["steps"] for a in ag
            if a.get("commands_past_tick") is not None and a["steps"]]
    links = merged["links"]
    mem = {f: [((a.get("memory") or {}).get(f)) for a in procs]
           for f in ("vm_hwm_mb", "rss_anon_mb", "rss_file_mb", "pss_mb", "uss_mb")}
    st = {f: [((a.get("startup") or {}).get(f)) for a in ag]
          for f in ("warm_s", "connected_s", "ready_s", "first_step_s")}
    veh = merged.get("vehicles") or {}
    vcpu = (veh["ticking_cpu_s"] / veh["ticking_s"]) if veh.get("ticking_s") else None
    vb, vr = v_bar(merged), v_bar(ref)
    pss = [x for x in mem["pss_mb"] if x is not None]
    return {"case": case, "agents": n, "rate_hz": rate, "tree": kind or "hil_6uav", "seed": seed,
            "agents_per_process": per, "processes": len(procs),
            "scenario": str(path.name), "exit": rc, "steps": merged["steps"],
            "wall_s": wall, "load_start": load0, "load_end": load1,
            "own_cores": own, "other_cores": other,
            "wake_floor_us": floor_us, "wake_floor_cpu": floor_us * rate * 1e-6,
            "packet_floor_us": packet_us, "packet_floor_cpu": packet_us * rate * 1e-6,
            "cpu_median": _med(per_agent), "cpu_max": _max(per_agent),
            "thread_cpu_median": _med(a.get("cpu_fraction") for a in ag) if per > 1 else None,
            "thread_cpu_max": _max(a.get("cpu_fraction") for a in ag) if per > 1 else None,
            "late_frac_median": _med(late), "late_frac_max": _max(late),
            "past_tick_frac_median": _med(past), "past_tick_frac_max": _max(past),
            "command_lag_ms_p99_max": _max(a.get("command_lag_ms_p99") for a in ag),
            "first_steps": sorted({a.get("first_step", 0) for a in ag}),
            "age_p50_steps_max": _max(ln["age_p50_steps"] for ln in links),
            "age_p99_steps_median": _med(ln["age_p99_steps"] for ln in links),
            "age_p99_steps_max": _max(ln["age_p99_steps"] for ln in links),
            "sent": merged["link_total"]["sent"], "lost": merged["link_total"]["lost"],
            "rss_mb_median": _med(a.get("max_rss_mb") for a in ag),
            "rss_mb_max": _max(a.get("max_rss_mb") for a in ag),
            "memory": {f: {"median": _med(v), "max": _max(v)} for f, v in mem.items()},
            "pss_total_mb": sum(pss) if len(pss) == len(procs) and pss else None,
            "startup": {f: {"median": _med(v), "max": _max(v)} for f, v in st.items()},
            "vehicle": {"tick_s": veh.get("tick_s"), "ticks": veh.get("ticks"),
                        "late_ticks": veh.get("late_ticks"), "resyncs": veh.get("resyncs"),
                        "cpu": vcpu, "cpu_s": veh.get("cpu_s"), "wall_s": veh.get("wall_s"),
                        "failsafe": veh.get("failsafe")},
            "V_swarm": vb, "V_run": vr,
            "final": merged["final"], "final_run": ref.get("final"),
            "missing": merged["agents_missing"]}


def _worker(tree: Path, case: str, duration: float, keep) -> dict:
    """`run_case` in a process running the code of ``tree`` (this script, that tree's packages;
    the swarm it starts inherits both). It dies with this process."""
    from cosim.signals import die_with

    env = dict(os.environ, PYTHONPATH=str(tree))
    out = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--worker", case,
                          repr(float(duration)), "" if keep is None else str(keep)], env=env,
                         capture_output=True, text=True, cwd=tree,
                         preexec_fn=die_with(os.getpid()))
    if out.returncode:
        last = (out.stderr.strip().splitlines() or [f"exit {out.returncode}"])[-1]
        raise RuntimeError(f"{tree}: {case}: {last}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> None:
    if argv is None and len(sys.argv) == 5 and sys.argv[1] == "--worker":
        print(json.dumps(run_case(sys.argv[2], float(sys.argv[3]), sys.argv[4] or None)))
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=10.0, metavar="S",
                    help="simulated seconds per case (default 10)")
    ap.add_argument("--cases", default="6x250,32x100",
                    help="comma-separated cases NxRATE[sSEED|chain][pK|pauto] (the module's "
                         "docstring; default 6x250,32x100: one process per agent)")
    ap.add_argument("--repeats", type=_positive, default=1, metavar="R",
                    help="run every case R times, the cases in turn, and add a table of each "
                         "case's runs (default 1)")
    ap.add_argument("--keep", metavar="DIR", help="keep each case's scenario and work directory "
                    "(the agents' summaries and stderr, the vehicle's stats) in DIR/CASE")
    ap.add_argument("--against", metavar="DIR", type=Path,
                    help="also every run in the code of another checkout of se3sync (its "
                         "packages in DIR), the two in pairs, one process per run")
    ap.add_argument("--label", help="what to call the --against code in the output (default DIR)")
    _markdown.add_option(ap)
    a = ap.parse_args(argv)
    if a.against is not None and not (a.against / "bridge" / "swarm").is_dir():
        ap.error(f"--against: {str(a.against)!r} is not a checkout of se3sync (no bridge/swarm)")
    if a.label is not None and a.against is None:
        ap.error("--label: names the --against code; give --against DIR")
    with _markdown.Report(a.markdown) as rep:
        rows, runs, others = bench(a)
        cap = (f"one swarm run per case, {a.duration:g} s, loopback vehicles, no logs"
               if a.repeats == 1 else f"{a.repeats} swarm runs per case, the cases in turn, "
               f"{a.duration:g} s each, loopback vehicles, no logs")
        rep.table(["case", "CPU per agent (share of a core; K per process: the process's / K)",
                   "late steps (median / max over agents)",
                   "commands past the vehicle's tick (median / max)", "data age p50 / p99 (steps)", "lost",
                   "vehicle process: CPU (share of a core), late ticks, resyncs",
                   "machine: this case / other work (cores), load; wake floor / packet floor "
                   "per agent (share of a core)",
                   "exit"],
                  [r[0] for r in rows], caption=cap)
        rep.table(["case", "peak RSS per process, VmHWM (MB)", "RssAnon / RssFile at the end (MB)",
                   "PSS per process (MB)", "Σ PSS of the agent processes (MB)",
                   "start-up: kernels loaded / ready / first step (s of process age)"],
                  [r[1] for r in rows], caption="memory per agent process and start-up per agent: median, "
                  "max over the agents (PSS counts a page shared by k processes as 1/k)")
        rep.table(["case", "V̄ at the 1 s samples, swarm", "`run`", "final V̄ / V̄(0): swarm, "
                   "`run`", "rises at the 1 s samples: swarm, `run`", "final rot_err: swarm, `run`"],
                  [r[2] for r in rows], caption="the loop's outcome against `se3sync run` of the "
                  "same scenario on the float32 reference plant")
        if a.repeats > 1:
            rep.table(["case", "CPU per agent: median of the runs (lowest – highest)",
                       "CPU per agent / wake floor: median of the runs (lowest – highest)",
                       "CPU per agent / packet floor: median of the runs (lowest – highest)",
                       "each run: CPU per agent / wake floor / packet floor / other work (cores)",
                       "late steps, worst agent of any run", "data age p99, worst link of any run",
                       "lost, all runs"],
                      over_runs(runs), caption=f"each case over its {a.repeats} runs (CPU per "
                      "agent: the run's median over its agents, as above)")
        if others:
            label = a.label or str(a.against)
            rep.table(["case", "CPU per agent, this tree: median (lowest – highest)",
                       f"{label}: median (lowest – highest)",
                       f"this tree / {label}, pair by pair: median (lowest – highest)",
                       "pairs in which this tree's figure is lower"],
                      against_pairs(runs, others),
                      caption=f"each case over {a.repeats} pairs of runs (CPU per agent: the "
                      "run's median over its agents), the pair's two runs one after the other")


def _g(x, fmt="{:.3g}") -> str:
    return "n/a" if x is None else fmt.format(x)


def _pct(x) -> str:
    return "n/a" if x is None else f"{100 * x:.2g} %"


def _vs(v) -> str:
    return ", ".join(f"{x:.4g}" for x in v["V"])


def _int_or(x, default: int) -> int:
    try:
        return int(x)
    except (TypeError, ValueError):
        return default


def _positive(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        v = 0
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be a whole number ≥ 1, got {text!r}")
    return v


def over_runs(runs: dict) -> list:
    """The table of each case over its runs ({name: [result of run_case, …]})."""
    out = []
    for name, rs in runs.items():
        cpu = [r["cpu_median"] for r in rs if r["cpu_median"] is not None]
        rel = [r["cpu_median"] / r["wake_floor_cpu"] for r in rs
               if r["cpu_median"] is not None and r["wake_floor_cpu"]]
        pk = [r["cpu_median"] / r["packet_floor_cpu"] for r in rs
              if r["cpu_median"] is not None and r.get("packet_floor_cpu")]
        out.append((name, f"{_g(_med(cpu))} ({_g(min(cpu, default=None))} – "
                          f"{_g(max(cpu, default=None))})",
                    f"{_g(_med(rel), '{:.2f}')} ({_g(min(rel, default=None), '{:.2f}')} – "
                    f"{_g(max(rel, default=None), '{:.2f}')})",
                    f"{_g(_med(pk), '{:.2f}')} ({_g(min(pk, default=None), '{:.2f}')} – "
                    f"{_g(max(pk, default=None), '{:.2f}')})",
                    "; ".join(f"{_g(r['cpu_median'])} / {r['wake_floor_cpu']:.3g} / "
                              f"{_g(r.get('packet_floor_cpu'), '{:.2g}')} / "
                              f"{_g(r['other_cores'], '{:.2f}')}" for r in rs),
                    _pct(_max(r["late_frac_max"] for r in rs)),
                    _g(_max(r["age_p99_steps_max"] for r in rs)),
                    f"{sum(r['lost'] for r in rs)} of {sum(r['sent'] for r in rs)}"))
    return out


def against_pairs(runs: dict, others: dict) -> list:
    """The table of each case's pairs of runs (this tree's {name: runs}, the other's)."""
    out = []
    for name, rs in runs.items():
        pairs = [(r["cpu_median"], o["cpu_median"]) for r, o in zip(rs, others.get(name, []))
                 if r["cpu_median"] is not None and o["cpu_median"] is not None]
        if not pairs:
            continue
        mine, theirs = [x for x, _ in pairs], [y for _, y in pairs]
        ratio = [x / y for x, y in pairs if y]
        out.append((name, f"{_g(_med(mine))} ({_g(min(mine))} – {_g(max(mine))})",
                    f"{_g(_med(theirs))} ({_g(min(theirs))} – {_g(max(theirs))})",
                    f"{_g(_med(ratio), '{:.3f}')} ({_g(min(ratio, default=None), '{:.2f}')} – "
                    f"{_g(max(ratio, default=None), '{:.2f}')})",
                    f"{sum(x < y for x, y in pairs)} of {len(pairs)}"))
    return out


def bench(a) -> tuple:
    """Every case ``a.repeats`` times, the cases in turn, each run paired with one of the
    ``--against`` tree's: (the rows of the three tables, one per run; {case name: this tree's
    runs' results}; {case name: the other tree's})."""
    rows = []
    runs, others = {}, {}
    base = a.cases.split(",")
    against = getattr(a, "against", None)
    label = (getattr(a, "label", None) or str(against)) if against is not None else None
    jobs = []
    for i, case in enumerate(base * a.repeats):
        run = i // len(base) + 1
        pair = [(None, ROOT)] + ([(label, against.resolve())] if against is not None else [])
        jobs += [(run, case, who, tree) for who, tree in (pair if run % 2 else pair[::-1])]
    for run, case, who, tree in jobs:
        keep = a.keep if a.keep is None or a.repeats == 1 else Path(a.keep) / f"run{run}"
        if keep is not None and who is not None:
            keep = Path(keep) / "against"
        r = run_case(case, a.duration, keep) if against is None else \
            _worker(tree, case, a.duration, keep)
        f, fr = r["final"] or {}, r["final_run"] or {}
        m, st, v = r["memory"], r["startup"], r["vehicle"]
        vs, vr = r["V_swarm"], r["V_run"]
        tree = r["tree"] if r["tree"] != "random" else f"random tree, seed {r['seed']}"
        name = f"{r['agents']} agents ({tree}) at {r['rate_hz']:g} Hz, {r['steps']} steps" + (
            "" if r["agents_per_process"] == 1 else
            f", {r['agents_per_process']} per process ({r['processes']} processes)")
        (runs if who is None else others).setdefault(name, []).append(r)
        if a.repeats > 1:
            name += f", run {run} of {a.repeats}"
        if who is not None:
            name = f"{who}: {name}"
        load = "/".join(f"{x:.1f}" for x in r["load_start"]) + " → " + \
            "/".join(f"{x:.1f}" for x in r["load_end"])
        print(f"{name}: CPU per agent median {_g(r['cpu_median'])} / max {_g(r['cpu_max'])} of a "
              f"core; late steps median {_pct(r['late_frac_median'])} / max "
              f"{_pct(r['late_frac_max'])}; commands past the vehicle's tick median "
              f"{_pct(r['past_tick_frac_median'])} / max {_pct(r['past_tick_frac_max'])} "
              f"(command lag p99 ≤ {_g(r['command_lag_ms_p99_max'])} ms); first steps {r['first_steps'][:5]}; data age p50 ≤ "
              f"{r['age_p50_steps_max']}, p99 median {r['age_p99_steps_median']} / max "
              f"{r['age_p99_steps_max']} steps; lost {r['lost']} of {r['sent']}; vehicle process "
              f"(tick {_g(v['tick_s'])} s): CPU {_g(v['cpu'])} of a core, late ticks "
              f"{v['late_ticks']} of {v['ticks']}, resyncs {v['resyncs']}; VmHWM median "
              f"{_g(m['vm_hwm_mb']['median'])} / max {_g(m['vm_hwm_mb']['max'])} MB, RssAnon "
              f"{_g(m['rss_anon_mb']['median'])}, RssFile {_g(m['rss_file_mb']['median'])}, PSS "
              f"{_g(m['pss_mb']['median'])} MB (Σ {_g(r['pss_total_mb'], '{:.0f}')} MB); start-up: "
              f"kernels loaded {_g(st['warm_s']['median'])} / {_g(st['warm_s']['max'])} s, ready "
              f"{_g(st['ready_s']['median'])} / {_g(st['ready_s']['max'])} s; V̄ final/V̄(0) "
              f"swarm {_g(vs['ratio'])} (rises {vs['rises']}), run {_g(vr['ratio'])} (rises "
              f"{vr['rises']}); final rot_err {f.get('rot_err', float('nan')):.3g} (run "
              f"{fr.get('rot_err', float('nan')):.3g}); machine: this case "
              f"{_g(r['own_cores'], '{:.2f}')} cores, other work {_g(r['other_cores'], '{:.2f}')},"
              f" load {load}, wake floor {r['wake_floor_us']:.0f} µs a step = "
              f"{r['wake_floor_cpu']:.3g} of a core, packet floor {r['packet_floor_us']:.0f} µs "
              f"per agent and step = {r['packet_floor_cpu']:.2g} of a core (exit {r['exit']})")
        print(json.dumps(r), file=sys.stderr)
        rows.append((
            (name, f"median {_g(r['cpu_median'])}, max {_g(r['cpu_max'])}",
             f"{_pct(r['late_frac_median'])} / {_pct(r['late_frac_max'])}",
             f"{_pct(r['past_tick_frac_median'])} / {_pct(r['past_tick_frac_max'])}",
             f"≤ {r['age_p50_steps_max']} / median {r['age_p99_steps_median']}, "
             f"max {r['age_p99_steps_max']}",
             f"{r['lost']} of {r['sent']}",
             f"{_g(v['cpu'])}, {v['late_ticks']} of {v['ticks']} (tick {_g(v['tick_s'])} s), "
             f"{v['resyncs']}",
             f"{_g(r['own_cores'], '{:.2f}')} / {_g(r['other_cores'], '{:.2f}')}, {load}; "
             f"{r['wake_floor_cpu']:.3g} / {r['packet_floor_cpu']:.2g}",
             r["exit"]),
            (name, f"{_g(m['vm_hwm_mb']['median'])}, {_g(m['vm_hwm_mb']['max'])}",
             f"{_g(m['rss_anon_mb']['median'])} / {_g(m['rss_file_mb']['median'])}",
             f"{_g(m['pss_mb']['median'])}, {_g(m['pss_mb']['max'])}",
             _g(r["pss_total_mb"], "{:.0f}"),
             " / ".join(f"{_g(st[k]['median'])} ({_g(st[k]['max'])})"
                        for k in ("warm_s", "ready_s", "first_step_s"))),
            (name, _vs(vs), _vs(vr), f"{_g(vs['ratio'])}, {_g(vr['ratio'])}",
             f"{vs['rises']}, {vr['rises']}",
             f"{f.get('rot_err', float('nan')):.3g}, {fr.get('rot_err', float('nan')):.3g}")))
    for name, rs in runs.items() if a.repeats > 1 else ():
        cpu = [r["cpu_median"] for r in rs if r["cpu_median"] is not None]
        print(f"{name}: CPU per agent over {len(rs)} runs: median {_g(_med(cpu))}, lowest "
              f"{_g(min(cpu, default=None))}, highest {_g(max(cpu, default=None))}; wake floors "
              + ", ".join(f"{r['wake_floor_cpu']:.3g}" for r in rs) + "; packet floors "
              + ", ".join(f"{r['packet_floor_cpu']:.2g}" for r in rs))
    for name, (mine, theirs, ratio, lower) in (
            (row[0], row[1:]) for row in against_pairs(runs, others)):
        print(f"{name}: CPU per agent, this tree {mine}, {label} {theirs}; this tree / {label} "
              f"pair by pair {ratio}; this tree lower in {lower} pairs")
    return rows, runs, others


if __name__ == "__main__":
    main()
