"""Start-up time of the command line: `se3sync --help`, `se3sync check` on the paper scenario and
`se3sync run` of its first 0.01 s (analysis, 100 compiled steps, the log), optionally against another revision in the same run (interleaved, so load affects both alike).
With ``--sections agent``, an agent process's start-up and memory instead (issue 31).

    python benchmarks/bench_startup.py [--against REV] [--repeat K] [--sections commands,agent]

Reports the median wall time of K runs of each command (numba's on-disk cache warm: one untimed
run first) and, with --against, the ratio new/old.

Section ``agent``, K fresh processes per tree (medians): ``python -c "import bridge.swarm.agent"``
after choosing the kernels as `se3sync agent` does (`bridge.swarm.aot.use`; the tree column
says which ran): its import time, VmRSS after it, the modules it brings of those an agent does
not need; then
the same process builds agent 2 of hil_6uav (`AgentNode`) and loads its compiled kernels
(`bridge.swarm.agent._warm_up`): process age and VmRSS, RssAnon, RssFile, PSS after that. And
`se3sync agent` itself (agent 2 of hil_6uav against one loopback vehicle process, 0.2 s, no
--start: it steps 0.5 s after it is ready): its summary's ``startup`` (seconds of process age:
``warm_s`` kernels loaded, ``connected_s`` the vehicle's heartbeat and first state,
``ready_s`` ready to step, ``first_step_s`` the first step) and ``memory`` at its end. The
≤ 1 s goal of issue 31 is ``ready_s``.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from _revisions import trees as revision_trees  # noqa: E402
import _markdown  # noqa: E402
COMMANDS = {"--help": ["--help"], "check paper": ["check", "scenarios/paper_6uav.toml"],
            "run paper": ["run", "scenarios/paper_6uav.toml", "--duration", "0.01",
                          "--log", "{tmp}/run.mcap"]}


def once(tree: Path, args) -> float:
    t = time.perf_counter()
    subprocess.run([sys.executable, "-m", "cosim.cli", *args], cwd=tree, check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t


# what a process that runs one agent does not use (issue 31): imported by `import
# bridge.swarm.agent`, they cost start-up and memory in every agent process
NOT_NEEDED = ("scipy", "fmpy", "attrs", "yaml", "tqdm", "matplotlib", "dask", "pyarrow",
              "mcap", "zstandard", "lz4", "email", "urllib.request", "http.client")

AGENT_PROBE = r"""
import json, os, sys, time
def age():
    with open("/proc/self/stat") as f:
        start = int(f.read().rpartition(")")[2].split()[19])
    with open("/proc/uptime") as f:
        return float(f.read().split()[0]) - start / os.sysconf("SC_CLK_TCK")
def mem():
    d = {}
    for path in ("/proc/self/status", "/proc/self/smaps_rollup"):
        with open(path) as f:
            for line in f:
                k, _, v = line.partition(":")
                if k in ("VmRSS", "RssAnon", "RssFile", "Pss"):
                    d[k] = int(v.split()[0]) / 1024
    return d
a0 = age()
t = time.perf_counter()
try:    # what `se3sync agent` does first: its kernels (an older tree has no choice)
    from bridge.swarm import aot
    kernels = aot.use()
except ImportError:
    kernels = "jit"
import bridge.swarm.agent as A
imp = time.perf_counter() - t
after_import = mem()
mods = [m for m in NOT_NEEDED if m in sys.modules]
from cosim.scenario import load_scenario
sc = load_scenario("scenarios/hil_6uav.toml", SETS)
node = A.AgentNode(sc, 2)
t = time.perf_counter()
A._warm_up(node)
warm = time.perf_counter() - t
print(json.dumps({"kernels": kernels, "age_at_main": a0, "import_s": imp, "import": after_import, "not_needed": mods,
                  "warm_up_s": warm, "age_warm": age(), "warm": mem()}))
node.close()
"""


def agent_probe(tree: Path, sets: list) -> dict:
    code = AGENT_PROBE.replace("NOT_NEEDED", repr(NOT_NEEDED)).replace("SETS", repr(sets))
    r = subprocess.run([sys.executable, "-c", code], cwd=tree, check=True, capture_output=True,
                       text=True, env=_env(tree))
    return json.loads(r.stdout.strip().splitlines()[-1])


def agent_run(tree: Path, sets: list, tmp: str) -> dict:
    out = Path(tmp) / "agent.json"
    out.unlink(missing_ok=True)
    argv = [sys.executable, "-m", "cosim.cli", "agent", "scenarios/hil_6uav.toml", "--id", "2",
            "--duration", "0.2", "--summary", str(out)]
    for x in sets:
        argv += ["--set", x]
    subprocess.run(argv, cwd=tree, check=True, stdout=subprocess.DEVNULL,
                   stderr=subprocess.DEVNULL, env=_env(tree))
    s = json.loads(out.read_text())
    return {"startup": s.get("startup") or {}, "memory": s.get("memory") or {},
            "max_rss_mb": s.get("max_rss_mb")}


def _env(tree: Path) -> dict:
    """The tree's code first (PYTHONPATH may name another checkout)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(tree)] + [p for p in env.get(
        "PYTHONPATH", "").split(os.pathsep) if p and Path(p).resolve() != Path(tree).resolve()])
    return env


def _med(values):
    values = [v for v in values if v is not None]
    return statistics.median(values) if values else None


def _f(x, fmt="{:.0f}") -> str:
    return "n/a" if x is None else fmt.format(x)


def agent_section(trees: dict, repeat: int, tmp: str):
    """The agent's import, warm-up and start-up, per tree (interleaved); returns table rows."""
    from bridge.mavlink.link import free_base_port

    sets = [f"bridge.base_port={free_base_port(6)}", f"network.base_port={free_base_port(6)}"]
    vehicle = subprocess.Popen(
        [sys.executable, "-m", "cosim.cli", "vehicle", "--scenario", "scenarios/hil_6uav.toml",
         *[x for v in sets for x in ("--set", v)], "--aux-rate", "0"], cwd=ROOT,
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=_env(ROOT))
    probes = {k: [] for k in trees}
    runs = {k: [] for k in trees}
    try:
        for tree in trees.values():   # warm the caches
            agent_probe(tree, sets)
            agent_run(tree, sets, tmp)
        for _ in range(repeat):
            for k, tree in trees.items():
                probes[k].append(agent_probe(tree, sets))
                runs[k].append(agent_run(tree, sets, tmp))
    finally:
        vehicle.terminate()
        vehicle.wait()
    rows = []
    for k in trees:
        p, r = probes[k], runs[k]
        imp = {f: _med([x["import"].get(f) for x in p]) for f in ("VmRSS", "RssAnon", "RssFile")}
        warm = {f: _med([x["warm"].get(f) for x in p]) for f in ("VmRSS", "RssAnon", "RssFile", "Pss")}
        st = {f: _med([x["startup"].get(f) for x in r]) for f in ("warm_s", "connected_s",
                                                                  "ready_s", "first_step_s")}
        mem = {f: _med([x["memory"].get(f) for x in r]) for f in ("vm_hwm_mb", "rss_anon_mb",
                                                                  "rss_file_mb", "pss_mb")}
        mods = sorted({m for x in p for m in x["not_needed"]})
        kern = ", ".join(sorted({x["kernels"].partition(":")[0] for x in p}))
        print(f"{k} ({kern}): import bridge.swarm.agent {_med([x['import_s'] for x in p]) * 1e3:.0f} ms, "
              f"VmRSS {imp['VmRSS']:.1f} MB (anon {imp['RssAnon']:.1f}, file "
              f"{imp['RssFile']:.1f}); not needed but imported: {', '.join(mods) or 'none'}; "
              f"after AgentNode + _warm_up ({_med([x['warm_up_s'] for x in p]) * 1e3:.0f} ms, "
              f"process age {_med([x['age_warm'] for x in p]):.2f} s): VmRSS {warm['VmRSS']:.1f}, "
              f"anon {warm['RssAnon']:.1f}, file {warm['RssFile']:.1f}, PSS {warm['Pss']:.1f} MB; "
              f"se3sync agent: warm {_f(st['warm_s'], '{:.2f}')} s, connected "
              f"{_f(st['connected_s'], '{:.2f}')} s, ready {_f(st['ready_s'], '{:.2f}')} s, first "
              f"step {_f(st['first_step_s'], '{:.2f}')} s; at its end VmHWM "
              f"{_f(mem['vm_hwm_mb'], '{:.1f}')}, RssAnon {_f(mem['rss_anon_mb'], '{:.1f}')}, "
              f"RssFile {_f(mem['rss_file_mb'], '{:.1f}')}, PSS {_f(mem['pss_mb'], '{:.1f}')} MB "
              f"(max_rss_mb {_f(_med([x['max_rss_mb'] for x in r]), '{:.1f}')})")
        rows.append([f"{k} ({kern})", f"{_med([x['import_s'] for x in p]) * 1e3:.0f}",
                     f"{imp['VmRSS']:.1f} ({imp['RssAnon']:.1f} + {imp['RssFile']:.1f})",
                     ", ".join(mods) or "none",
                     f"{warm['VmRSS']:.1f} ({warm['RssAnon']:.1f} + {warm['RssFile']:.1f}), "
                     f"PSS {warm['Pss']:.1f}",
                     " / ".join(_f(st[f], "{:.2f}") for f in ("warm_s", "connected_s", "ready_s",
                                                             "first_step_s")),
                     f"{_f(mem['vm_hwm_mb'], '{:.1f}')} / {_f(mem['rss_anon_mb'], '{:.1f}')} / "
                     f"{_f(mem['rss_file_mb'], '{:.1f}')} / {_f(mem['pss_mb'], '{:.1f}')}"])
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--against", metavar="REV", help="also time this revision (git worktree)")
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--sections", default="commands",
                    help="commands (the CLI's start-up, the default), agent (an agent process), "
                         "or commands,agent")
    _markdown.add_option(ap)
    args = ap.parse_args()
    sections = set(args.sections.split(","))
    rows = []
    with _markdown.Report(args.markdown) as rep, revision_trees(args.against) as trees, \
            tempfile.TemporaryDirectory() as tmp:
        for name, cmd in (COMMANDS.items() if "commands" in sections else ()):
            cmd = [c.format(tmp=tmp) for c in cmd]
            times = {k: [] for k in trees}
            for tree in trees.values():
                once(tree, cmd)  # warm the numba cache and the file system
            for _ in range(args.repeat):
                for k, tree in trees.items():
                    times[k].append(once(tree, cmd))
            med = {k: statistics.median(v) for k, v in times.items()}
            line = ", ".join(f"{k} {v * 1e3:.0f} ms" for k, v in med.items())
            if args.against:
                line += f"; ratio {med['this tree'] / med[args.against]:.2f}"
            print(f"se3sync {name:12s} median of {args.repeat}: {line}")
            rows.append([f"`se3sync {' '.join(COMMANDS[name])}`".replace("{tmp}/", "")]
                        + [f"{v * 1e3:.0f}" for v in med.values()]
                        + ([f"{med['this tree'] / med[args.against]:.2f}"] if args.against else []))
        if rows:
            rep.table(["command"] + [f"{k} (ms)" for k in trees]
                      + (["ratio"] if args.against else []), rows,
                      caption=f"median wall time of {args.repeat} fresh processes each, numba's "
                              f"on-disk cache warm")
        if "agent" in sections:
            rep.table(["tree", "import bridge.swarm.agent (ms)", "VmRSS after it (MB: anon + file)",
                       "imported, not needed", "after AgentNode + _warm_up: VmRSS (anon + file), PSS (MB)",
                       "se3sync agent: warm / connected / ready / first step (s of process age)",
                       "its end: VmHWM / RssAnon / RssFile / PSS (MB)"],
                      agent_section(trees, args.repeat, tmp),
                      caption=f"agent 2 of hil_6uav, medians of {args.repeat} fresh processes "
                              f"each, caches warm; one loopback vehicle process")
    return 0


if __name__ == "__main__":
    sys.exit(main())
