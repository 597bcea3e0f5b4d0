"""The agent's kernels compiled ahead of time (`bridge.swarm.aot`) against numba's JIT of the same
source: every exported kernel gives the same bits on random inputs (the jump branch, stale
neighbours, fail-safe and rejected datagrams included), a lockstep swarm gives the same run
either way, an agent process on them never imports numba, and where they cannot be had the
process says why and stays on the JIT."""
from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bridge.swarm import aot
from controller import kernels as K
from controller import layout

ROOT = Path(__file__).resolve().parents[2]
HIL = ROOT / "scenarios" / "hil_6uav.toml"

pytestmark = pytest.mark.timeout(300)


# what `bridge.swarm.aot` reports when numba refuses a kernel's source (the build's one line
# names the exception)
KERNEL_ERRORS = ("TypingError", "LoweringError", "UnsupportedError", "NumbaError", "NameError",
                 "AttributeError", "TypeError")


@pytest.fixture(scope="module")
def ahead():
    try:
        return aot.load(aot.ensure())
    except aot.AotError as exc:
        # a machine without a C compiler (or Python's headers) cannot build it; a kernel that
        # numba's ahead-of-time compiler refuses (a typing error the JIT let pass) is a bug,
        # never a reason to skip
        if any(f"{e}:" in str(exc) for e in KERNEL_ERRORS):
            pytest.fail(f"the ahead-of-time compiler refused a kernel: {exc}")
        pytest.skip(f"the ahead-of-time module cannot be built here: {exc}")


@pytest.fixture(scope="module")
def P():
    from cosim.controllers import hybrid
    from cosim.scenario import load_scenario

    return np.ascontiguousarray(hybrid(load_scenario(HIL)).P)


def _states(rng, n):
    S = np.empty((n, layout.S_WIDTH))
    S[:, layout.P] = rng.normal(size=(n, 3)) * 3.0
    S[:, layout.R] = Rotation.random(n, random_state=int(rng.integers(1 << 31))).as_matrix() \
        .reshape(n, 9)
    S[:, layout.XI] = rng.normal(size=(n, 6))
    return S


def _same(a, b, what):
    """Every bit: values (NaN where NaN) and types."""
    if isinstance(a, tuple):
        assert isinstance(b, tuple) and len(a) == len(b), what
        for x, y in zip(a, b):
            _same(x, y, what)
        return
    a, b = np.asarray(a), np.asarray(b)
    assert a.dtype == b.dtype and a.shape == b.shape, what
    assert a.tobytes() == b.tobytes(), what


def _both(jit_f, aot_f, args, what):
    """Call each on its own copies of ``args``; the returns and every array after the call
    agree bit for bit."""
    a1 = [x.copy() if isinstance(x, np.ndarray) else x for x in args]
    a2 = [x.copy() if isinstance(x, np.ndarray) else x for x in args]
    r1, r2 = jit_f(*a1), aot_f(*a2)
    _same(r1, r2, f"{what}: return")
    for k, (x, y) in enumerate(zip(a1, a2)):
        if isinstance(x, np.ndarray):
            _same(x, y, f"{what}: argument {k}")
    return r1


def test_the_module_holds_every_export_and_no_numba(ahead):
    assert sorted(n for n in dir(ahead) if not n.startswith("_")) == sorted(aot.EXPORTS)
    code = f"""
        import sys
        from bridge.swarm import aot
        aot.load({str(aot.module_path())!r})
        print("numba" in sys.modules, "llvmlite" in sys.modules)
    """
    r = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True,
                       text=True, cwd=ROOT, timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["False", "False"]


def test_agent_step_equals_the_jit(ahead, P):
    """agent_step over random neighbourhoods: stages 1, 2, 3, hybrid or not, fresh or stale
    neighbours, fail-safe; rows at random attitudes, so the jump stage fires."""
    rng = np.random.default_rng(31)
    jumps = stale = 0
    for trial in range(300):
        nn = int(rng.integers(1, 5))               # neighbours
        S = _states(rng, nn + 1)
        E = nn + int(rng.integers(0, 2))
        ea, eb, owned, nbr = [], [], [], []
        for r in range(E):
            j = 1 + r % nn
            own = bool(rng.integers(2))
            ea.append(0 if own else j)
            eb.append(j if own else 0)
            owned.append(own)
            nbr.append(j)
        mode = rng.integers(0, 2, size=nn + 1) * (rng.random() < 0.5)
        stale += int(np.any(mode[nbr] != K.FRESH))
        theta = rng.uniform(-3, 3, E)
        args = (S, np.array(ea, np.int64), np.array(eb, np.int64), np.array(owned),
                np.array(nbr, np.int64), mode.astype(np.int64), bool(rng.integers(2)), P,
                0.004, int(rng.integers(1, 4)), bool(rng.random() < 0.1), theta,
                rng.uniform(-3, 3, E), np.zeros(E), np.zeros(E), np.zeros(E),
                np.zeros(E, np.bool_), rng.normal(size=(E, 6)), rng.normal(size=(E, 12)),
                np.zeros((nn + 1, 6)))
        jumps += _both(K.agent_step, ahead.agent_step, args, f"agent_step trial {trial}")
    assert jumps > 20 and stale > 20     # both branches were exercised


def test_the_network_kernels_equal_the_jit(ahead, P):
    rng = np.random.default_rng(7)
    for trial in range(100):
        N = int(rng.integers(2, 9))
        S = _states(rng, N)
        edges = np.array([(int(rng.integers(0, k)), k) for k in range(1, N)], np.int64)
        M = len(edges)
        theta = rng.uniform(-3, 3, M)
        U = _both(lambda *a: (K.network_U(*a), a[-1])[1],
                  lambda *a: (ahead.network_U(*a), a[-1])[1],
                  (S, theta, edges, P, np.zeros(M)), f"network_U {trial}")
        _both(K.metrics, ahead.metrics,
              (S, edges, U, 0.7, rng.uniform(0.5, 2, N), rng.normal(size=(N, 3, 3)),
               np.zeros(M), np.zeros(M), np.zeros((N, 4))), f"metrics {trial}")
        R9 = np.ascontiguousarray(S[:, layout.R])
        R9[0] = np.diag([1.0, -1.0, -1.0]).ravel()         # half turns: Shepperd's branches
        R9[1] = np.diag([-1.0, 1.0, -1.0]).ravel()
        _both(K.rot_to_quat_rows, ahead.rot_to_quat_rows, (R9, np.zeros((N, 4))),
              f"rot_to_quat_rows {trial}")
        i, j = (int(x) for x in rng.integers(0, N, 2))
        _both(K.relative_pose, ahead.relative_pose,
              (S, i, S, j, np.zeros((3, 3)), np.zeros(3)), f"relative_pose {trial}")


def test_the_one_edge_pieces_equal_the_jit(ahead, P):
    rng = np.random.default_rng(8)
    for trial in range(200):
        Rb = Rotation.random(random_state=trial).as_matrix()
        pb = rng.normal(size=3)
        th = float(rng.uniform(-3, 3))
        _both(K.edge_term, ahead.edge_term,
              (Rb, pb, th, rng.normal(size=6), rng.normal(size=6), bool(trial % 2), P,
               np.zeros(6)), f"edge_term {trial}")
        _both(K.edge_flow, ahead.edge_flow, (Rb, pb, th, P, 0.004), f"edge_flow {trial}")
        _both(K.wrench_sum, ahead.wrench_sum,
              (rng.normal(size=6), rng.normal(size=(int(rng.integers(0, 5)), 6)), P,
               np.zeros(6)), f"wrench_sum {trial}")


@pytest.mark.parametrize("signed", [False, True])
def test_scan_sample_equals_the_jit(ahead, signed):
    """The neighbour-sample decoder over honest datagrams and every irregular kind the
    reference path refuses or treats specially (test_sample_wire's), as a link calls it."""
    from test_agent_link import KEY, scenario
    from test_sample_wire import _Neighbour

    from bridge.swarm.agent_link import AgentLink
    from bridge.swarm.sample_wire import scan_sample

    rng = np.random.default_rng(5 + signed)
    link = AgentLink.from_scenario(scenario(), 2, compiled=True, key=KEY if signed else None)
    try:
        taken = refused = 0
        for j in link.neighbours:
            nb = _Neighbour(link, j, rng, key=KEY if signed else None)
            nt = link._scan_nt[j]
            for s in range(1, 200):
                data = nb.honest(s) if s % 3 else nb.irregular(s)
                args = (np.frombuffer(data, np.uint8), len(data), link._signed, j, nt, link.h_us,
                        s + link.future_steps, link._scratch, link._scan_out, link._scan_seqs)
                r = _both(scan_sample, ahead.scan_sample, args, f"scan_sample {j} {s}")
                taken += r >= 0
                refused += r < 0
        assert taken > 100 and refused > 30
    finally:
        link.close()


@pytest.mark.parametrize("signed", [False, True])
def test_drain_and_send_equal_the_jit(ahead, signed):
    """The compiled drain (libc's recv, the decoder, the held arrays and the counts) through a
    link of each kind over the same honest and irregular traffic: the same held samples,
    counters, refusals and sequence bookkeeping (signing windows) at every step; and what each
    link publishes (libc's send to every neighbour) arrives the same (unsigned: the same bytes;
    signed, the signatures' timestamps are each link's own)."""
    import socket
    import time

    from test_agent_link import KEY, endpoint, scenario
    from test_sample_wire import _Neighbour, _state

    from bridge.swarm.agent_link import AgentLink

    rng = np.random.default_rng(17)
    links, socks = [], []
    try:
        for _ in range(2):
            sc = scenario()
            link = AgentLink.from_scenario(sc, 2, compiled=True, key=KEY if signed else None)
            links.append(link)
            s = {}
            for j in link.neighbours:
                s[j] = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                s[j].bind(endpoint(sc, j))
            socks.append((sc, s))
        links[1].drain_kernel = ahead.drain_samples
        links[1].send_kernel = ahead.send_all
        for _, s in socks:
            for x in s.values():
                x.settimeout(5.0)
        nbs = [_Neighbour(links[0], j, np.random.default_rng(30 + j), key=KEY if signed else None)
               for j in links[0].neighbours]
        sent = 0
        for n in range(200):
            for link in links:
                link.set_step(n)
            for nb in nbs:
                r = rng.random()
                data = nb.honest(n) if r < 0.6 else nb.irregular(n)
                for sc, s in socks:
                    s[nb.j].sendto(data, endpoint(sc, 2))
                sent += 1
            for link in links:
                end = time.monotonic() + 5.0
                while link.counters.datagrams < sent and time.monotonic() < end:
                    link.poll()
            assert _state(links[0]) == _state(links[1]), n
            S = _states(rng, 1)[0]
            theta = {k: float(x) for k, x in zip(links[0].owned, rng.normal(size=8))}
            got = []
            for link, (_, s) in zip(links, socks):
                assert link.publish(n, S, theta) == len(link.neighbours)
                got.append({j: x.recv(65535) for j, x in s.items()})
            if signed:
                assert {j: len(x) for j, x in got[0].items()} == \
                    {j: len(x) for j, x in got[1].items()}, n
            else:
                assert got[0] == got[1], n
        assert links[1].drained > 50 and links[1].counters.datagrams == sent
    finally:
        for link in links:
            link.close()
        for _, s in socks:
            for x in s.values():
                x.close()


@pytest.mark.parametrize("signed", [False, True])
def test_scan_odometry_equals_the_jit(ahead, signed):
    """The vehicle-state decoder over honest and irregular vehicle datagrams (test_state_wire's)."""
    from test_state_wire import _Vehicle

    from bridge.mavlink.state_wire import ODOMETRY_SIZE, scan_odometry

    rng = np.random.default_rng(23)
    veh = _Vehicle(rng, key=bytes(32) if signed else None)
    taken = 0
    for n in range(400):
        data = veh.honest(n) if n % 2 else veh.irregular(n)
        args = (np.frombuffer(data, np.uint8), len(data), int(signed),
                np.zeros(ODOMETRY_SIZE, np.uint8), np.zeros(13), np.zeros(5, np.int64))
        taken += _both(scan_odometry, ahead.scan_odometry, args, f"scan_odometry {n}")
    assert 200 < taken < 400


def test_recv_state_equals_the_jit(ahead):
    """The vehicle socket's compiled read: each datagram read by one and then the other (the
    same bytes sent twice), and the empty socket."""
    from test_state_wire import _Vehicle

    from bridge.mavlink.state_wire import ODOMETRY_SIZE, recv_state

    rng = np.random.default_rng(37)
    veh = _Vehicle(rng)
    a, b = (socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(2))
    try:
        for s in (a, b):
            s.bind(("127.0.0.1", 0))
        a.connect(b.getsockname())
        b.connect(a.getsockname())
        b.setblocking(False)
        codes = set()
        for n in range(200):
            data = veh.honest(n) if n % 2 else veh.irregular(n)
            a.send(data)
            a.send(data)
            time.sleep(0.0005)
            args = (b.fileno(), np.zeros(1 << 16, np.uint8), 0, np.zeros(ODOMETRY_SIZE, np.uint8),
                    np.zeros(13), np.zeros(6, np.int64))
            codes.add(_both(recv_state, ahead.recv_state, args, f"recv_state {n}"))
        assert {1, 2} <= codes
        args = (b.fileno(), np.zeros(64, np.uint8), 0, np.zeros(ODOMETRY_SIZE, np.uint8),
                np.zeros(13), np.zeros(6, np.int64))
        assert _both(recv_state, ahead.recv_state, args, "empty") == 0
    finally:
        a.close()
        b.close()


def test_take_states_equals_the_jit(ahead):
    """A vehicle's states taken whole: each datagram read by one and then the other (the same
    bytes sent twice) from the same tracker arrays at the same wall time, which then move as
    the JIT moved them: taken, handed on (scanned or not), late and early."""
    from test_state_wire import _Vehicle

    from bridge.mavlink.state_wire import (ODOMETRY_SIZE, TAKE_FULL, TAKE_OTHER, TAKE_SCANNED,
                                           TAKE_SLOTS, take_states)

    rng = np.random.default_rng(61)
    veh = _Vehicle(rng)
    a, b = (socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(2))
    try:
        for s in (a, b):
            s.bind(("127.0.0.1", 0))
        a.connect(b.getsockname())
        b.connect(a.getsockname())
        b.setblocking(False)
        codes = set()
        mine = [np.full(3, np.nan), np.zeros(1, np.uint64), np.full(1, -1, np.int64),
                np.zeros(13)]
        now = 3000.0
        for n in range(300):
            now += 0.004 + float(rng.choice([0.0, 0.0, 0.0, 0.2, 1.5]))
            data = veh.honest(n) if n % 3 else veh.irregular(n)
            a.send(data)
            a.send(data)
            time.sleep(0.0005)
            args = (b.fileno(), np.zeros(1 << 16, np.uint8), np.zeros(ODOMETRY_SIZE, np.uint8),
                    np.zeros(13), np.zeros(6, np.int64), 1, 1, 1, now, 5e4, *mine,
                    np.zeros(TAKE_SLOTS, np.int64))
            a1 = [x.copy() if isinstance(x, np.ndarray) else x for x in args]
            a2 = [x.copy() if isinstance(x, np.ndarray) else x for x in args]
            r1, r2 = take_states(*a1), ahead.take_states(*a2)
            assert r1 == r2, n
            for k, (x, y) in enumerate(zip(a1, a2)):
                if isinstance(x, np.ndarray):
                    _same(x, y, f"take_states {n}: argument {k}")
            codes.add(r1)
            mine = a1[10:14]
        assert {TAKE_FULL, TAKE_SCANNED, TAKE_OTHER} <= codes
    finally:
        a.close()
        b.close()


def test_pack_command_equals_the_jit(ahead):
    from bridge.mavlink.state_wire import COMMAND_BYTES, pack_command

    rng = np.random.default_rng(41)
    for trial in range(300):
        c = (rng.uniform(-1, 1, 6) * 10.0 ** rng.integers(-40, 40)).tolist()
        if trial % 7 == 0:
            c[int(rng.integers(6))] = float(rng.choice([0.0, np.nan, 1e39]))
        args = (np.zeros(COMMAND_BYTES, np.uint8), int(rng.integers(0, 1 << 62)), *c,
                *(int(x) for x in rng.integers(0, 256, 6)), int(rng.integers(2)),
                np.zeros(8, np.float32))
        _both(pack_command, ahead.pack_command, args, f"pack_command {trial}")


def test_command_row_equals_the_jit(ahead):
    from bridge.mavlink.state_wire import COMMAND_BYTES, command_row

    rng = np.random.default_rng(43)
    for trial in range(300):
        u = rng.normal(size=6) * 10.0 ** rng.integers(-3, 4)
        if trial % 5 == 0:
            u[int(rng.integers(6))] = float(rng.choice([np.nan, np.inf, -0.0, 1e300]))
        args = (u, _states(rng, 1), rng.uniform(0.5, 20.0, 6), bool(trial % 2),
                bool(trial % 3), float(rng.uniform(0.5, 3.0)), rng.normal(size=3) * 9.81,
                np.zeros((1, 6)), int(rng.integers(0, 1 << 62)),
                *(int(x) for x in rng.integers(0, 256, 6)), np.zeros(COMMAND_BYTES, np.uint8),
                np.zeros(8, np.float32), np.full(1, -1, np.int64), np.zeros(1, np.int64),
                np.zeros(3, np.int64))
        _both(command_row, ahead.command_row, args, f"command_row {trial}")


def test_age_rules_equals_the_jit(ahead):
    from bridge.swarm.sample_wire import AGE_BINS, SCAN_WIDTH, age_rules

    rng = np.random.default_rng(31)
    for trial in range(200):
        m, e = int(rng.integers(1, 6)), int(rng.integers(0, 8))
        n = int(rng.integers(0, 3 * AGE_BINS))
        steps = np.where(rng.random(m) < 0.2, -1,
                         n - rng.choice([-9, -1, 0, 3, 12, 40, AGE_BINS], m)).astype(np.int64)
        args = (n, steps, int(rng.choice([-1, 10])), 5, 5, np.zeros(m, np.int64),
                np.zeros(m, np.int64), np.zeros(m, np.int64),
                rng.integers(0, 9, (m, AGE_BINS)).astype(np.int64),
                rng.normal(size=(m, SCAN_WIDTH)), np.zeros(e),
                rng.integers(0, m, e).astype(np.int64), rng.permutation(e).astype(np.int64),
                rng.integers(13, 71, e).astype(np.int64))
        _both(age_rules, ahead.age_rules, args, f"age_rules {trial}")


def test_wire_to_state_ned_equals_the_jit(ahead):
    from bridge.mavlink.state_wire import wire_to_state_ned

    rng = np.random.default_rng(29)
    for trial in range(100):
        wire = rng.normal(size=(int(rng.integers(1, 8)), 13)) * 10.0 ** rng.integers(-3, 4)
        _both(wire_to_state_ned, ahead.wire_to_state_ned, (wire, np.zeros((wire.shape[0], 18))),
              f"wire_to_state_ned {trial}")


def test_pack_sample_equals_the_jit(ahead):
    from bridge.swarm.sample_wire import PACK_BYTES, pack_sample

    rng = np.random.default_rng(9)
    for trial in range(300):
        nt = int(rng.integers(0, 59))
        S = _states(rng, 1)[0]
        S[layout.XI] *= 10.0 ** rng.integers(-30, 30)
        theta = rng.normal(size=max(nt, 1)) * 10.0 ** rng.integers(-30, 30)
        if trial % 50 == 0:
            theta[0] = 1e39                     # beyond float32: refused by both
        args = (np.zeros(PACK_BYTES, np.uint8), int(rng.integers(0, 1 << 50)), S,
                bool(rng.integers(2)), theta, nt, int(rng.integers(1, 256)),
                int(rng.integers(0, 256)), int(rng.integers(2)), np.zeros(58, np.float32),
                np.zeros(2, np.int64))
        _both(pack_sample, ahead.pack_sample, args, f"pack_sample {trial}")


def test_publish_sample_equals_the_jit(ahead):
    from bridge.swarm.sample_wire import PACK_BYTES, publish_sample

    rng = np.random.default_rng(11)
    none = np.zeros(0, np.int64)
    for trial in range(200):
        E = int(rng.integers(1, 9))
        rows = np.sort(rng.choice(E, int(rng.integers(0, E + 1)), replace=False)).astype(np.int64)
        theta = rng.normal(size=E) * 10.0 ** rng.integers(-30, 30)
        if trial % 40 == 0:
            theta[:] = 1e39                     # beyond float32: refused by both
        args = (np.zeros(PACK_BYTES, np.uint8), int(rng.integers(0, 1 << 50)), _states(rng, 2),
                theta, rows, np.zeros(max(E, 1)), int(rng.integers(1, 256)),
                int(rng.integers(0, 256)), np.zeros(58, np.float32), np.zeros(2, np.int64),
                none, none, np.zeros(1, np.int64))
        _both(publish_sample, ahead.publish_sample, args, f"publish_sample {trial}")


def test_held_rows_equals_the_jit(ahead):
    from bridge.swarm.sample_wire import SCAN_WIDTH, held_rows

    rng = np.random.default_rng(13)
    for trial in range(50):
        m = int(rng.integers(0, 5))
        args = (_states(rng, m + 1), _states(rng, 1), rng.integers(-1, 3, m).astype(np.int64),
                rng.normal(size=(m, SCAN_WIDTH)))
        _both(held_rows, ahead.held_rows, args, f"held_rows {trial}")


def test_agent_tick_equals_the_jit(ahead):
    from bridge.swarm.tick import agent_tick
    from test_tick import hil_node, random_ticks

    with hil_node() as node:
        for trial, args in enumerate(random_ticks(node, 200, 17)):
            _both(agent_tick, ahead.agent_tick, args, f"agent_tick {trial}")


def test_the_cdr_scatter_equals_numbas(ahead):
    """The CDR log's scatter (an agent's `--log-encoding cdr`) against numba's JIT of it."""
    import numba

    from cosim.log import cdr

    jitted = numba.njit(cache=True)(cdr._scatter_py)
    rng = np.random.default_rng(11)
    for trial in range(50):
        R, W = int(rng.integers(1, 6)), 40
        idx = rng.permutation(np.arange(1, W))
        f8, sec, nsec, mode = (np.ascontiguousarray(np.sort(x)) for x in
                               np.split(idx[:16], [8, 10, 12]))
        a = rng.normal(size=(R, W))
        args = (a, a.view(np.uint32), R, f8, rng.normal(size=(R, len(f8))), sec, nsec,
                rng.integers(0, 1 << 62, R), mode,
                rng.integers(0, 1 << 32, (R, len(mode))).astype(np.uint32))
        a1, a2 = args[0].copy(), args[0].copy()
        jitted(a1, a1.view(np.uint32), *args[2:])
        ahead.cdr_scatter(a2, a2.view(np.uint32), *args[2:])
        assert a1.tobytes() == a2.tobytes()


def _swarm(tmp_path, kernels, extra=()):
    from bridge.mavlink.link import free_base_port

    d = tmp_path / kernels
    d.mkdir()
    sets = [f"network.base_port={free_base_port(6)}", f"bridge.base_port={free_base_port(6)}"]
    cmd = [sys.executable, "-m", "cosim.cli", "swarm", str(HIL), "--vehicles", "loopback",
           "--lockstep", "--duration", "0.6", "--kernels", kernels, "--dir", str(d),
           "--summary", str(tmp_path / f"{kernels}.json"), *extra]
    for s in sets:
        cmd += ["--set", s]
    r = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=240)
    assert r.returncode == 0, r.stderr
    return json.loads((tmp_path / f"{kernels}.json").read_text()), {
        i: json.loads((d / f"agent_{i}.json").read_text()) for i in range(1, 7)}


@pytest.mark.realtime
@pytest.mark.slow
def test_a_lockstep_swarm_is_the_same_run_on_either_kernels(ahead, tmp_path):
    """hil_6uav in lockstep, 150 steps, jumps included, CDR logs: the ahead-of-time agents and
    the JIT agents give the same merged run, every sample's every number, and the same merged
    log; the former never import numba (their log's scatter included) and hold less memory."""
    m_aot, a_aot = _swarm(tmp_path, "aot", ["--log", str(tmp_path / "aot.mcap"),
                                            "--log-encoding", "cdr"])
    m_jit, a_jit = _swarm(tmp_path, "jit", ["--log", str(tmp_path / "jit.mcap"),
                                            "--log-encoding", "cdr"])
    assert m_aot["n_jumps"] == m_jit["n_jumps"] > 0
    for key in ("final", "samples", "jumps"):
        assert json.dumps(m_aot[key]) == json.dumps(m_jit[key]), key
    for i in range(1, 7):
        assert a_aot[i]["startup"]["kernels"] == "aot"
        assert a_aot[i]["startup"]["numba_loaded"] is False
        assert a_jit[i]["startup"]["kernels"] == "jit"
        assert a_jit[i]["startup"]["numba_loaded"] is True
        assert a_aot[i]["own"] == a_jit[i]["own"]
        assert a_aot[i]["memory"]["vm_hwm_mb"] < a_jit[i]["memory"]["vm_hwm_mb"]
    from cosim.log.reader import read_log

    msgs = [read_log(tmp_path / f"{k}.mcap")["messages"] for k in ("aot", "jit")]
    assert sum(len(v) for v in msgs[0].values()) > 150
    assert json.dumps(msgs[0], sort_keys=True, default=str) == \
        json.dumps(msgs[1], sort_keys=True, default=str)


def _use(env_extra, code="print(aot.use())"):
    env = dict(os.environ)
    env.pop("NUMBA_DISABLE_JIT", None)
    env.update(env_extra)
    r = subprocess.run([sys.executable, "-c", "import sys\nfrom bridge.swarm import aot\n" + code
                        + "\nprint('numba' in sys.modules)"],
                       capture_output=True, text=True, cwd=ROOT, timeout=240, env=env)
    assert r.returncode == 0, r.stderr
    return r.stdout.splitlines()


def test_without_a_compiler_the_agent_stays_on_the_jit_and_says_why(tmp_path):
    """A build that fails (no C compiler: CC is /bin/false) is reported on one line, kept (the
    next caller is told at once, without building), and leaves numba unimported until a kernel
    is: the process then runs on the JIT."""
    env = {"NUMBA_CACHE_DIR": str(tmp_path), "CC": "/bin/false"}
    first = _use(env)
    assert first[0].startswith("jit: the build failed: ") and first[1] == "False"
    assert len(first[0].splitlines()) == 1
    failed = list((tmp_path / "se3sync_aot").glob("*.failed"))
    assert len(failed) == 1 and not list((tmp_path / "se3sync_aot").glob("*.so"))
    again = _use(env, "import time\nt = time.monotonic()\nprint(aot.use())\n"
                      "print(time.monotonic() - t < 1.0)\nimport controller.kernels")
    assert again[0] == first[0] and again[1] == "True" and again[2] == "True"


def test_kernels_loaded_before_the_choice_keep_the_jit():
    out = _use({}, "import controller.kernels\nprint(aot.use())")
    assert out == ["jit: the kernels were loaded before the choice", "True"]


def test_the_choice_in_an_aot_process_never_loads_numba(ahead):
    """Every export replaces its own source function, and only it (by module and name): the
    inline helpers stay plain Python, never called."""
    code = """print(aot.use())
import importlib, controller.kernels, bridge.swarm.agent
m = aot.load()
for src, name in aot.source_names().items():
    mod, _, fn = src.rpartition(".")
    f = getattr(importlib.import_module(mod), fn)
    assert (f is getattr(m, name)) == (mod != "cosim.log.cdr"), src   # cdr's: looked up by name
assert controller.kernels.quat_of.__module__ == "controller._kernels"   # a plain function"""
    out = _use({}, code)
    assert out == ["aot", "False"]


def test_numba_is_refused_once_the_process_chose_aot(ahead):
    code = ("print(aot.use())\nfrom controller import jit as _jit\ntry:\n    _jit.numba_module()\n"
            "except RuntimeError as e:\n    print('refused')")
    assert _use({}, code) == ["aot", "refused", "False"]


def _builders(tag: str) -> list:
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                argv = (d / "cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            if b"bridge.swarm.aot" in argv and any(tag.encode() in a for a in argv):
                out.append(int(d.name))
    return out


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_a_build_dies_with_the_process_that_started_it(tmp_path):
    """SIGKILL to a process while its kernels build: the builder (a child) dies with it, and
    nothing half-built is left where a later process would load it."""
    import signal
    import time

    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path))
    env.pop("NUMBA_DISABLE_JIT", None)
    p = subprocess.Popen([sys.executable, "-c", "from bridge.swarm import aot; aot.ensure()"],
                         cwd=ROOT, env=env)
    try:
        end = time.monotonic() + 60
        while not _builders(str(tmp_path)) and time.monotonic() < end and p.poll() is None:
            time.sleep(0.05)
        assert _builders(str(tmp_path)), "the build never started"
    finally:
        p.send_signal(signal.SIGKILL)
        p.wait()
    end = time.monotonic() + 10
    while _builders(str(tmp_path)) and time.monotonic() < end:
        time.sleep(0.05)
    assert not _builders(str(tmp_path))
    assert not list((tmp_path / "se3sync_aot").glob("*.so"))
