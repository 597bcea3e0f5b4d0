"""Issue 31 §3: the swarm's endpoints are meant for real networks. Each agent and the vehicles
get a network namespace of their own (a host each, as far as the network can tell: its own
interfaces, addresses, routes and ports), joined by veth pairs to a Linux bridge in a hub
namespace, with an address each in a private /24 drawn per run. The scenario's
``[[network.agent]]`` and ``[[bridge.vehicle]]`` tables point at those addresses; the agents
(`se3sync agent`, one per namespace, as on separate hosts) and the loopback vehicles (one
`se3sync vehicle` process in its own namespace) run a signed lockstep swarm across them. The
result equals the same swarm on loopback bit for bit and `se3sync run` on the float32 reference
plant as `tests/bridge/test_agents.py` compares them, and the interface counters show every datagram
crossed the veths.

Needs root (`ip netns`): skipped, with the reason, where there is none. Every namespace is
named after this process's id and deleted at the end, also when the test fails; namespaces left
by an earlier run that died (its process gone) are deleted first. Kernel delay emulation (tc
netem) is not used: the [network] delay/jitter/loss emulation stays on the sending side, and
lockstep refuses it anyway."""
from __future__ import annotations

import json
import os
import random
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

os.environ.setdefault("MAVLINK20", "1")

from test_agents import _assert_equal_to_float32, _reference  # noqa: E402
from _bridge import HIL, ROOT, free_base_port, load  # noqa: E402

N = 6
DURATION = 1.0       # 250 lockstep steps; the first second holds hil_6uav's 5 jumps
PREFIX = "se3sync-t"
GUARD_S = 180.0      # a hang guard, not a deadline (docs/testing.md)


def _ip(*args, check=True):
    r = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=60)
    if check and r.returncode != 0:
        raise RuntimeError(f"ip {' '.join(args)}: {r.stderr.strip()}")
    return r


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _delete_leaked() -> list:
    """Namespaces of this test whose process is gone (a run killed before its clean-up)."""
    gone = []
    for line in _ip("netns", "list", check=False).stdout.splitlines():
        name = line.split()[0] if line.split() else ""
        m = re.match(rf"^{PREFIX}(\d+)-", name)
        if m and not _alive(int(m.group(1))):
            _ip("netns", "del", name, check=False)
            gone.append(name)
    return gone


class Hosts:
    """N + 1 namespaces ("hosts": agents 1..N and the vehicles) on one Ethernet segment: a veth
    pair each, its inner end ``eth0`` with the host's address, its outer end a port of the
    bridge ``br0`` in the hub namespace. Nothing is created in the root namespace."""

    def __init__(self, n: int):
        self.tag = f"{PREFIX}{os.getpid()}-"
        self.hub = self.tag + "hub"
        rng = random.Random()
        self.net = f"10.{rng.randint(64, 254)}.{rng.randint(0, 255)}"   # a private /24 per run
        self.ns = {i: f"{self.tag}a{i}" for i in range(1, n + 1)}
        self.ns["v"] = self.tag + "veh"
        self.addr = {i: f"{self.net}.{10 + i}" for i in range(1, n + 1)}
        self.addr["v"] = f"{self.net}.200"
        self.port = {k: f"p{k}" for k in self.ns}     # the hub-side ends (names in the hub only)
        self.made: list = []

    def up(self) -> "Hosts":
        _ip("netns", "add", self.hub)
        self.made.append(self.hub)
        _ip("-n", self.hub, "link", "add", "br0", "type", "bridge")
        for k, ns in self.ns.items():
            _ip("netns", "add", ns)
            self.made.append(ns)
            _ip("-n", self.hub, "link", "add", self.port[k], "type", "veth", "peer", "name",
                "eth0", "netns", ns)
            _ip("-n", self.hub, "link", "set", self.port[k], "master", "br0", "up")
            _ip("-n", ns, "addr", "add", f"{self.addr[k]}/24", "dev", "eth0")
            _ip("-n", ns, "link", "set", "eth0", "up")
            _ip("-n", ns, "link", "set", "lo", "up")
        _ip("-n", self.hub, "link", "set", "br0", "up")
        _ip("netns", "exec", self.ns["v"], "true")   # processes can run in them (a container
        return self                                   # may refuse the mounts `exec` makes)

    def down(self) -> None:
        for ns in reversed(self.made):   # the veth pairs go with their namespaces
            _ip("netns", "del", ns, check=False)
        self.made = []

    def counters(self) -> dict:
        """{host: {"eth0": (tx, rx packets), "lo": (tx, rx)}} from the kernel's statistics."""
        out = {}
        for k, ns in self.ns.items():
            out[k] = {}
            for dev in ("eth0", "lo"):
                st = json.loads(_ip("-n", ns, "-s", "-j", "link", "show", "dev", dev).stdout)[0]
                s = st["stats64"]
                out[k][dev] = (s["tx"]["packets"], s["rx"]["packets"])
        return out


@pytest.fixture
def hosts():
    if not hasattr(os, "geteuid") or os.geteuid() != 0:
        pytest.skip(f"network namespaces need root (`ip netns`); running as uid "
                    f"{os.geteuid() if hasattr(os, 'geteuid') else '?'}")
    if shutil.which("ip") is None:
        pytest.skip("network namespaces need iproute2's `ip`, not found on PATH")
    _delete_leaked()
    h = Hosts(N)
    try:
        try:
            h.up()
        except RuntimeError as exc:
            pytest.skip(f"cannot build the test network: {exc}")
        yield h
    finally:
        h.down()


def _scenario(tmp_path, hosts, net_port, veh_port) -> Path:
    """hil_6uav with every agent at its host's address (the same ports on every host, as on
    separate machines) and vehicle i talking to agent i's host."""
    text = Path(HIL).read_text()
    # a silent lockstep peer is an error after bridge.lockstep_timeout (5 s): here a guard of
    # GUARD_S against a hang, not a deadline (a loaded machine, or a first run that compiles the
    # kernels, can stall a process for seconds)
    assert text.count("\n[bridge]\n") == 1
    text = text.replace("\n[bridge]\n", f"\n[bridge]\nlockstep_timeout = {GUARD_S}\n")
    text += f"\n[network]\nbase_port = {net_port}\n"
    for i in range(1, N + 1):
        if hosts is not None:
            text += f'\n[[network.agent]]\nid = {i}\naddress = "{hosts.addr[i]}"\nport = {net_port}\n'
    for i in range(1, N + 1):
        ep = (f"udpin:{hosts.addr[i]}:{veh_port}" if hosts is not None
              else f"udpin:127.0.0.1:{veh_port + i - 1}")
        text += f'\n[[bridge.vehicle]]\nid = {i}\nendpoint = "{ep}"\n'
    path = tmp_path / "swarm.toml"
    path.write_text(text)
    return path


def _run(tmp_path, scenario, key, where=lambda who: []) -> dict:
    """The vehicles, then agents 1..N, each ``where(who) + [python -m cosim.cli ...]``, as on
    separate hosts; returns the agents' summaries. Every process is stopped at the end."""
    py = [sys.executable, "-m", "cosim.cli"]
    procs = {}
    errs = {}

    def start(who, argv):
        errs[who] = tmp_path / f"{who}.err"
        with open(errs[who], "w") as f:
            procs[who] = subprocess.Popen([*where(who), *py, *argv], cwd=str(ROOT),
                                          stdout=subprocess.DEVNULL, stderr=f,
                                          stdin=subprocess.DEVNULL)

    try:
        start("v", ["vehicle", "--scenario", str(scenario), "--lockstep", "--aux-rate", "0",
                    "--key", str(key), "--stats", str(tmp_path / "vehicle.json")])
        t_end = time.monotonic() + GUARD_S
        while "vehicle(s)" not in errs["v"].read_text():   # its start-up line
            assert procs["v"].poll() is None and time.monotonic() < t_end, errs["v"].read_text()
            time.sleep(0.05)
        for i in range(1, N + 1):
            start(i, ["agent", str(scenario), "--id", str(i), "--lockstep", "--key", str(key),
                      "--duration", repr(DURATION), "--connect-timeout", repr(GUARD_S),
                      "--summary", str(tmp_path / f"agent_{i}.json")])
        for i in range(1, N + 1):
            rc = procs[i].wait(timeout=GUARD_S)
            assert rc == 0, (i, errs[i].read_text())
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.terminate()
        for p in procs.values():
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
    return {i: json.loads((tmp_path / f"agent_{i}.json").read_text()) for i in range(1, N + 1)}


def _own(summaries) -> dict:
    """What each agent computed: its own rows and owned θ at the samples and the end, its jumps."""
    return {i: (s["own"], s["jumps"], s["steps"]) for i, s in summaries.items()}


@pytest.mark.slow
@pytest.mark.realtime
@pytest.mark.root
@pytest.mark.timeout(600)
def test_lockstep_swarm_across_network_namespaces_equals_loopback(hosts, tmp_path):
    from bridge.swarm.launcher import merge_summaries

    key = tmp_path / "swarm.key"
    key.write_bytes(os.urandom(32))   # non-loopback sockets: signed (or --insecure)
    port = free_base_port(2)          # the namespaces are new, but keep to the suite's rule
    (tmp_path / "ns").mkdir()
    (tmp_path / "lo").mkdir()
    sc_ns = _scenario(tmp_path / "ns", hosts, port, port + 1)
    before = hosts.counters()
    got = _run(tmp_path / "ns", sc_ns, key,
               where=lambda who: ["ip", "netns", "exec", hosts.ns[who]])
    after = hosts.counters()

    # the same swarm on loopback, in this namespace
    lo_net, lo_veh = free_base_port(N), free_base_port(N)
    sc_lo = _scenario(tmp_path / "lo", None, lo_net, lo_veh)
    ref_lo = _run(tmp_path / "lo", sc_lo, key)

    # 1. what every agent computed is the loopback swarm's, bit for bit (the same code on the
    # same float32 wire values: only the transport differs)
    assert _own(got) == _own(ref_lo)
    sc = load(path=str(sc_ns), duration=DURATION)
    merged = merge_summaries(sc, got, lockstep=True)
    # 2. and `run` on the float32 reference plant, as tests/bridge/test_agents.py compares them
    ref = _reference(HIL, [], DURATION)
    assert len(ref["jumps"]) == 5
    _assert_equal_to_float32(merged, ref)
    assert merged["link_total"]["lost"] == 0 and merged["link_total"]["age_p99_steps_max"] == 0
    # refused: only the lockstep's re-sent copies of what had arrived (`duplicate`)
    assert set(merged["rejected_total"]["neighbour_link"]) <= {"duplicate"}, merged["rejected_total"]
    assert merged["rejected_total"]["vehicle_link"] == {}, merged["rejected_total"]

    # 3. every datagram crossed the veths: an agent accepts a neighbour's samples only from the
    # neighbour's endpoint (another source is `wrong_address`), so each one came from the
    # neighbour's host, and the interface counters hold at least one datagram per step to each
    # neighbour and to the vehicle; nothing went through a namespace's loopback
    steps = round(DURATION / sc.step)
    for i, s in got.items():
        for j, ln in s["link"]["agent_link"]["links"].items():
            assert ln["samples"] >= steps and set(ln["rejected_by_reason"]) <= {"duplicate"}, \
                (i, j, ln)
    d = {k: tuple(a - b for a, b in zip(after[k]["eth0"], before[k]["eth0"])) for k in after}
    for i in range(1, N + 1):
        deg = len(sc.graph.neighbours(i))
        assert d[i][0] >= steps * (deg + 1) and d[i][1] >= steps * (deg + 1), (i, d[i], deg)
        assert after[i]["lo"] == before[i]["lo"], (i, before[i]["lo"], after[i]["lo"])
    assert d["v"][0] >= steps * N and d["v"][1] >= steps * N, d["v"]
    vst = json.loads((tmp_path / "ns" / "vehicle.json").read_text())
    assert vst["rejected"] == 0 and vst["malformed"] == 0, vst
    print(f"\nnetwork {hosts.net}.0/24: packets (tx, rx) per host's eth0 {d}")
