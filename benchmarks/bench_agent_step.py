"""The CPU one agent process spends per control step, by phase, independent of pacing.

    python benchmarks/bench_agent_step.py [--steps N] [--repeats R] [--agent I] [--signed]
                                          [--publish] [--kernels aot|jit]
                                          [--against DIR [--label NAME]]

Agent I (default 2: three neighbours, two owned edges) of hil_6uav in real-time mode, driven by
`cosim.master.Master` as `se3sync agent` drives it, but flat out: its timeline starts in the
past, so no step waits for its deadline. Its vehicle and its neighbours are sockets of this
process that send, before each step's poll, that step's ODOMETRY (stamped with the clock) and
samples (built before the run); what the harness does is timed and left out. Reported per step, in µs
of this thread's CPU (`time.thread_time`, which other work on the machine inflates only through
shared caches, not through waiting): reading the state (`plant.read`: the vehicle's row and the
neighbours' newest samples), the step (`controller.step_state`: the age rule, the jumps, the
publish to the neighbours, the law, the flow), the command (`plant.apply`: mapping, encode,
send) and the poll (`plant.advance`: the vehicle's and the neighbours' datagrams decoded and
checked), the total, and the share of one core at 250 Hz and 100 Hz. Medians of the repeats.
The kernels are the ones `se3sync agent` runs by default, compiled ahead of time (``--kernels
jit``: numba's JIT, whose dispatch costs more per call).
``--paced HZ`` runs the agent at HZ in real time instead (step h = 1/HZ, every step waits for its
deadline as in a swarm): the same work, plus what waking up from each wait costs the thread (on
a virtual machine whose CPU halts while idle, far more than the work itself).
``--publish`` also times the step's publish to the neighbours (`AgentLink.publish`: encode and
one send per neighbour), part of the step (its timer adds a little to the step's figure).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import socket
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

import _markdown

KERNELS_ENV = "SE3SYNC_BENCH_KERNELS"
if os.environ.get(KERNELS_ENV, "aot") == "aot":
    # the kernels `se3sync agent` runs by default (`--kernels aot`), chosen before any is
    # imported; where the module cannot be built the worker stays on the JIT, as an agent does
    from bridge.swarm import aot as _aot
    _aot.use()

from bridge.mavlink.link import Peer, Counters, free_base_port  # noqa: E402
from bridge.swarm.agent import AgentNode, _warm_up  # noqa: E402
from bridge.swarm.agent_link import encode_sample  # noqa: E402
from controller import layout  # noqa: E402
from controller.se3 import rot_to_quat  # noqa: E402
from cosim.master import Master  # noqa: E402
from cosim.scenario import load_scenario  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
HIL = ROOT / "scenarios" / "hil_6uav.toml"
PHASES = ("read", "step", "apply", "poll")
PACED_ENV = "SE3SYNC_BENCH_PACED"
_kernels = "aot"          # the workers' (`--kernels`)


def once(steps: int, agent: int, key: bytes | None, publish: bool = False) -> dict:
    from bridge.mavlink.link import mavlink2 as M

    nb, bb = free_base_port(6), free_base_port(6)
    paced = float(os.environ.get(PACED_ENV, "0"))   # (the worker's argv stays as it was)
    sc = load_scenario(HIL, [f"network.base_port={nb}", f"bridge.base_port={bb}",
                             "simulation.duration=100000",
                             *([f"simulation.step={1.0 / paced!r}"] if paced else [])])
    node = AgentNode(sc, agent, on_event=lambda s: None, insecure=True)
    if key is not None:    # sign both links as `--key` would (the same key everywhere)
        node.close()
        import tempfile
        kf = Path(tempfile.mkdtemp()) / "key"
        kf.write_bytes(key)
        node = AgentNode(sc, agent, on_event=lambda s: None, key_file=kf,
                         signing_state=str(kf) + ".state")
    socks = []
    try:
        h_us = round(sc.step * 1e6)
        vport = int(node.vehicle.cfg.vehicles[0].endpoint.split(":")[2])
        vs = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        vs.bind(("127.0.0.1", 0))
        socks.append(vs)
        vpeer = Peer(agent, 1, Counters(), key=key)
        nsock, npeer = {}, {}
        for j in node.neighbours:
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.bind(("127.0.0.1", nb + j - 1))
            socks.append(s)
            nsock[j], npeer[j] = s, Peer(j, 191, Counters(), key=key)
        row = sc.S0[agent - 1]
        q = rot_to_quat(np.asarray(row[layout.R]).reshape(3, 3)).tolist()
        p, w, v = row[layout.P].tolist(), row[layout.OMEGA].tolist(), row[layout.V].tolist()
        nan21 = (math.nan,) + (0.0,) * 20
        mav = vpeer.mav   # pymavlink's messages: the harness runs against older trees too

        def vehicle_packets(n):
            """The vehicle's datagrams before step n, stamped now (a vehicle's clock)."""
            out = [vpeer.pack(mav.heartbeat_encode(M.MAV_TYPE_QUADROTOR, M.MAV_AUTOPILOT_GENERIC,
                                                   0, 0, M.MAV_STATE_ACTIVE))] \
                if n % 250 == 0 else []
            out.append(vpeer.pack(mav.odometry_encode(
                int(time.monotonic() * 1e6), M.MAV_FRAME_LOCAL_NED, M.MAV_FRAME_BODY_FRD, *p, q,
                *v, *w, list(nan21), list(nan21), 0, 0, 100)))
            return out

        pre_n = []
        for n in range(steps + 2):
            pre_n.append({j: b"".join(npeer[j].pack(m) for m in encode_sample(
                npeer[j].mav, n, h_us, sc.S0[j - 1],
                [float(sc.theta0[k - 1]) for k in sc.graph.M_plus(j)]))
                for j in node.neighbours})
        vaddr, naddr = ("127.0.0.1", vport), ("127.0.0.1", nb + agent - 1)
        _warm_up(node)
        # the first state after the warm-up: sent before a compile of seconds, it would set the
        # vehicle's clock offset seconds off, and every later state would be refused as future
        for d in vehicle_packets(0):
            vs.sendto(d, vaddr)
        node.connect()
        node.n_steps = steps
        # flat out: every step already due, no sleep; paced: step 0 due in 50 ms
        node.vehicle.pace_from(time.monotonic() + (0.05 if paced else -1e6))
        for j, s in nsock.items():
            s.sendto(pre_n[0][j], naddr)
        node.vehicle.poll(0.01)
        acc = dict.fromkeys(PHASES, 0.0)
        acc["harness"] = 0.0
        clock = time.thread_time
        plant, ctl = node.plant, node.controller

        def timed(name, f):
            def g(*a):
                c0 = clock()
                r = f(*a)
                acc[name] += clock() - c0
                return r
            return g

        adv = plant.advance

        def advance(h):
            c0 = clock()
            n = node.n + 1
            for d in vehicle_packets(n):
                vs.sendto(d, vaddr)
            for j, s in nsock.items():
                s.sendto(pre_n[n][j], naddr)
            c1 = clock()
            adv(h)
            c2 = clock()
            acc["harness"] += c1 - c0
            acc["poll"] += c2 - c1

        plant.read = timed("read", plant.read)
        plant.apply = timed("apply", plant.apply)
        plant.advance = advance
        ctl.step_state = timed("step", ctl.step_state)
        if publish:
            acc["publish"] = 0.0
            node.link.publish = timed("publish", node.link.publish)
        master = Master(node.local, plant, ctl, None)
        import resource
        r0 = resource.getrusage(resource.RUSAGE_THREAD)
        c0 = clock()
        master.run(steps)
        total = clock() - c0 - acc["harness"]
        r1 = resource.getrusage(resource.RUSAGE_THREAD)
        st = node.stats()
        links = st["agent_link"]["links"]
        taken = min(v["samples"] for v in links.values())
        # (a state delayed by a descheduling of the harness is refused as stale: the machine's)
        other = {r: c for r, c in st["rejected_by_reason"].items() if r != "stale"}
        if taken < steps or st["agent_link"]["rejected"] or other:
            raise RuntimeError(f"the harness's traffic was not all taken: {taken} samples of "
                               f"{steps}, rejected {st['agent_link']['rejected_by_reason']} + "
                               f"{st['rejected_by_reason']}")
        out = {k: acc[k] / steps * 1e6 for k in PHASES}
        out["total"] = total / steps * 1e6
        out["other"] = out["total"] - sum(out[k] for k in PHASES)   # the master's own share
        # the thread's user and kernel time per step, the harness's sends included: where a
        # paced step's extra time goes (user code running slower after a wait, or the kernel)
        out["user"] = (r1.ru_utime - r0.ru_utime) / steps * 1e6
        out["sys"] = (r1.ru_stime - r0.ru_stime) / steps * 1e6
        if publish:
            out["publish"] = acc["publish"] / steps * 1e6
        return out
    finally:
        node.close()
        for s in socks:
            s.close()


def _worker(tree: Path, steps: int, agent: int, signed: bool, publish: bool = False,
            paced: float = 0.0) -> dict:
    """`once` in a process running the code of ``tree`` (this script, that tree's packages)."""
    env = dict(os.environ, PYTHONPATH=str(tree), **{PACED_ENV: repr(float(paced))},
               **{KERNELS_ENV: _kernels})
    out = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--worker", str(steps),
                          str(agent), "1" if signed else "0", "1" if publish else "0"], env=env,
                         capture_output=True, text=True, cwd=tree)
    if out.returncode:
        raise RuntimeError(f"{tree}: {out.stderr.strip().splitlines()[-1:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> None:
    if argv is None and len(sys.argv) == 6 and sys.argv[1] == "--worker":
        steps, agent, signed = int(sys.argv[2]), int(sys.argv[3]), sys.argv[4] == "1"
        print(json.dumps(once(steps, agent, bytes(range(32)) if signed else None,
                              publish=sys.argv[5] == "1")))
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=5000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--agent", type=int, default=2)
    ap.add_argument("--signed", action="store_true", help="also with signed links (--key)")
    ap.add_argument("--paced", type=float, default=0.0, metavar="HZ",
                    help="run at HZ in real time (each step waits for its deadline) instead of "
                         "flat out")
    ap.add_argument("--publish", action="store_true",
                    help="also the step's publish to the neighbours (part of the step)")
    ap.add_argument("--against", metavar="DIR", type=Path,
                    help="also the code of another checkout of se3sync (its packages in DIR), "
                         "the two alternating, one process per measurement")
    ap.add_argument("--label", help="what to call the --against code in the output (default DIR)")
    ap.add_argument("--kernels", choices=("aot", "jit"), default="aot",
                    help="the workers' kernels: compiled ahead of time, as `se3sync agent` runs "
                         "them by default, or numba's JIT (default aot)")
    _markdown.add_option(ap)
    a = ap.parse_args(argv)
    global _kernels
    _kernels = a.kernels
    if a.paced < 0 or a.paced > 10000:
        ap.error(f"--paced: must be a rate in Hz in (0, 10000], got {a.paced:g}")
    other = a.label or str(a.against)
    trees = {"this tree": ROOT, **({other: a.against.resolve()} if a.against else {})}
    rows = []
    with _markdown.Report(a.markdown) as rep:
        for name, signed in (("unsigned", False),) + ((("signed", True),) if a.signed else ()):
            runs = {t: [] for t in trees}
            for _ in range(a.repeats):
                for t, d in trees.items():
                    runs[t].append(_worker(d, a.steps, a.agent, signed, a.publish, a.paced))
            for t in trees:
                med = {k: statistics.median(r[k] for r in runs[t]) for k in runs[t][0]}
                pub = f" of which publish {med['publish']:.1f}" if a.publish else ""
                print(f"{t}: agent {a.agent}, {name}: {med['total']:.1f} µs CPU per step (read "
                      f"{med['read']:.1f}, step {med['step']:.1f}{pub}, apply "
                      f"{med['apply']:.1f}, poll {med['poll']:.1f}, master {med['other']:.1f}) = {med['total'] / 4000:.4f} "
                      f"of a core at 250 Hz, {med['total'] / 10000:.4f} at 100 Hz; user "
                      f"{med['user']:.0f} + kernel {med['sys']:.0f} µs per step with the "
                      f"harness's sends")
                rows.append((t, name, f"{med['total']:.0f}", f"{med['read']:.0f}",
                             f"{med['step']:.0f}",
                             *((f"{med['publish']:.0f}",) if a.publish else ()),
                             f"{med['apply']:.0f}", f"{med['poll']:.0f}",
                             f"{med['other']:.0f}", f"{med['total'] / 4000:.3f}",
                             f"{med['total'] / 10000:.3f}"))
            if a.against:
                tot = {t: statistics.median(r["total"] for r in runs[t]) for t in trees}
                ratio = tot["this tree"] / tot[other]
                print(f"{name}: this tree / {other} = {ratio:.2f}")
                rep.note(f"{name}: this tree's CPU per step is {ratio:.2f} × that of {other}")
        rep.table(["code", "links", "µs per step", "read", "step (law + publish)",
                   *(("of which publish",) if a.publish else ()), "apply (command)",
                   "poll (decode + checks)", "master", "core at 250 Hz", "core at 100 Hz"], rows,
                  caption=f"agent {a.agent} of hil_6uav, {a.steps} steps, {a.kernels} kernels, "
                          f"{f'paced at {a.paced:g} Hz' if a.paced else 'flat out'}, CPU of its "
                          f"thread (the harness's sends left out), medians of {a.repeats}")


if __name__ == "__main__":
    main()
