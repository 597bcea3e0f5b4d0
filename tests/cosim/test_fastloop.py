"""The compiled block loop (cosim/fastloop.py) against the Python reference loop of Master.run:
the same summaries, the same log messages byte for byte, the same failures and stops."""
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from cosim import fastloop
from cosim.run import with_timing
from cosim.master import Master
from cosim.log.writer import McapLogger
from cosim.log.reader import read_log
from cosim.plants import FmuPlant, PerBodyFmuPlant
from cosim.scenario import load_scenario, parse_scenario
from plant_fmu.fast import FMUError

ROOT = Path(__file__).resolve().parents[2]
PAPER = ROOT / "scenarios" / "paper_6uav.toml"
TIMING = ("wall_time_s", "realtime_factor", "us_per_step")


def random_tree_scenario(n, seed):
    """The paper's weighting, design and gains on a random tree of n agents, random poses."""
    rng = np.random.default_rng(seed)
    edges = []
    for i in range(1, n):
        e = [int(rng.integers(0, i)) + 1, i + 1]
        edges.append(e if rng.random() < 0.5 else e[::-1])
    text = PAPER.read_text()
    text = text.replace("count = 6 ", f"count = {n} ")
    head, rest = text.split("edges = [[1, 2], [2, 3], [3, 4], [2, 5], [5, 6]]")
    text = head + f"edges = {edges}" + rest
    head, rest = text.split('generator = "paper"\naxis = [0.2686, 0.8549, 0.4438]')
    text = head + f'generator = "random"\nseed = {seed}\nposition_box = 1.0' + rest
    return parse_scenario(text, name=f"tree{n}")


def messages(path, decoded=False):
    """(topic, log time, sequence, payload) of every message; decoded: the payload as the
    repr of its JSON value (exact for floats: repr is shortest round-trip, keeps −0.0)."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        return [(c.topic, m.log_time, m.sequence,
                 repr(json.loads(m.data)) if decoded else bytes(m.data))
                for _, c, m in make_reader(f).iter_messages()]


def run_both(sc, tmp_path, controller="hybrid", log=True, steps=None, fast_json=False,
             encoding="json", make=FmuPlant.from_scenario):
    """(summary, final state, log messages) of the reference loop, then of the compiled one.
    fast_json: the compiled loop's log encodes numbers with orjson (compared as values),
    else with float repr (compared as bytes). encoding: the log's (McapLogger). make: the
    plant of a scenario."""
    out = []
    for compiled in (False, True):
        plant = make(sc)
        path = tmp_path / f"{'c' if compiled else 'py'}.mcap"
        logger = McapLogger(path, sc, controller=controller, encoding=encoding) if log else None
        if logger is not None:
            logger.orjson = fast_json
        try:
            m = Master(sc, plant, controller, logger)
            m.use_compiled = compiled
            assert (fastloop.compiled_pair(plant, m.controller) is not None)
            s = m.run(sc.n_steps() if steps is None else steps)
            S = plant.read().copy()
        finally:
            if logger is not None:
                logger.close()
            plant.close()
        out.append((s, S, messages(path, decoded=fast_json) if log else None))
    return out


def assert_same(ref, fast):
    (s0, S0, m0), (s1, S1, m1) = ref, fast
    assert np.array_equal(S0, S1)  # bit for bit
    for k in s0:
        if k not in TIMING:
            assert s0[k] == s1[k], k
    assert set(s0) == set(s1)
    assert m0 == m1


def test_paper_first_2s_bit_identical(tmp_path):
    sc = load_scenario(PAPER, ["simulation.duration=2"])
    ref, fast = run_both(sc, tmp_path)
    assert_same(ref, fast)
    s = ref[0]
    assert s["n_jumps"] > 0 and len(s["samples"]) == 3
    # jumps in the middle of a block: steps that are neither log nor sample ticks
    dec = round(1 / (sc.log_rate * sc.step))
    mid = [j for j in s["jumps"] if round(j["t"] / sc.step) % dec != 0]
    assert mid, "the paper run should jump between log ticks"
    topics = [m[0] for m in ref[2]]
    assert topics.count("/jumps") == s["n_jumps"]
    assert topics.count("/tf") == sc.n_steps() // dec


@pytest.mark.parametrize("fast_json", [False, True])
def test_random_tree_50_bit_identical(tmp_path, fast_json):
    sc = with_timing(random_tree_scenario(50, 3), duration=0.3)
    assert sc.graph.n == 50 and sc.graph.M == 49
    ref, fast = run_both(sc, tmp_path, fast_json=fast_json)
    assert_same(ref, fast)
    assert ref[0]["steps"] == sc.n_steps()


@pytest.mark.parametrize("scenario", ["paper", "tree50"])
def test_cdr_log_bit_identical(tmp_path, scenario):
    """The CDR log (--log-encoding cdr) of the compiled loop is the reference loop's, byte for
    byte: records arrive there in blocks (record_block), here one by one (record)."""
    sc = (load_scenario(PAPER, ["simulation.duration=1"]) if scenario == "paper"
          else with_timing(random_tree_scenario(50, 3), duration=0.3))
    ref, fast = run_both(sc, tmp_path, encoding="cdr")
    assert_same(ref, fast)
    assert ref[0]["n_jumps"] > 0
    assert {t for t, *_ in ref[2]} >= {"/tf", "/edges", "/agents", "/lyapunov", "/scene"}


def test_paper_orjson_log_decodes_to_the_same_values(tmp_path):
    pytest.importorskip("orjson")
    sc = load_scenario(PAPER, ["simulation.duration=0.5"])
    ref, fast = run_both(sc, tmp_path, fast_json=True)
    assert_same(ref, fast)


def test_gradient_controller_bit_identical(tmp_path):
    sc = load_scenario(PAPER, ["simulation.duration=0.3"])
    ref, fast = run_both(sc, tmp_path, controller="gradient")
    assert_same(ref, fast)


@pytest.mark.parametrize("d", [1, 3])
def test_actuation_delay_bit_identical_in_both_loops(tmp_path, d):
    """simulation.actuation_delay = d: `make_plant` wraps the plant in DelayedActuation, whose
    compiled record has the held wrenches the compiled loop swaps in before fmi2SetReal, as the
    Python loop's ``apply`` does: the same summary, state and log, bit for bit."""
    from cosim.plants import DelayedActuation, make_plant

    sc = load_scenario(PAPER, ["simulation.duration=0.5", f"simulation.actuation_delay={d}"])
    assert sc.actuation_delay == d
    p = make_plant("fleet", sc)
    assert isinstance(p, DelayedActuation) and p.delay == d
    p.close()
    ref, fast = run_both(sc, tmp_path, make=lambda s: make_plant("fleet", s))
    assert_same(ref, fast)
    plain = run_both(load_scenario(PAPER, ["simulation.duration=0.5"]), tmp_path, log=False)[0]
    assert not np.array_equal(plain[1], ref[1])   # the delay changes the run


def test_actuation_delay_applies_the_wrench_of_d_steps_before():
    """DelayedActuation checked by hand, in both loops: 40 steps of the plant FMU driven with
    u(t_{n−d}) computed by the law on the state at t_{n−d} (u ≡ 0 for n < d) give the state of
    the master's run with simulation.actuation_delay = d; the log and summary keep the law's
    own u(t_0) (the wrench commanded, not the one applied)."""
    from cosim.controllers import make_controller
    from cosim.plants import make_plant

    for d in (1, 2):
        sc = load_scenario(PAPER, ["simulation.duration=0.1", f"simulation.actuation_delay={d}"])
        n = 40
        p = FmuPlant.from_scenario(sc)
        law = make_controller("hybrid", sc)
        sent = [np.zeros((sc.graph.n, 6))] * d
        u0 = None
        for _ in range(n):
            u, _ = law.step_state(p.read().copy(), sc.step)
            u0 = u.copy() if u0 is None else u0
            sent.append(u.copy())
            p.apply(sent.pop(0))
            p.advance(sc.step)
        S = p.read().copy()
        p.close()
        for compiled in (True, False):
            plant = make_plant("fleet", sc)
            m = Master(sc, plant, "hybrid")
            m.use_compiled = compiled
            m.run(n)
            assert np.array_equal(plant.read(), S), (d, compiled)
            assert np.array_equal(m.u0, u0)
            plant.close()


def test_jump_buffers_full_end_the_block_early(tmp_path, monkeypatch):
    # with room for one step's jumps only, every jump step ends its block: the result must
    # not change
    monkeypatch.setattr(fastloop, "JUMP_CAPACITY", 0)
    sc = load_scenario(PAPER, ["simulation.duration=1", "simulation.log_rate=10"])
    ref, fast = run_both(sc, tmp_path)
    assert ref[0]["n_jumps"] > 1
    assert_same(ref, fast)


def test_steps_not_multiple_of_ticks(tmp_path, monkeypatch):
    """Also: a logged compiled run shortens the GIL switch interval while it steps (its blocks
    would wait for the encoder thread) and gives the caller's back."""
    seen = []
    real = fastloop._block_loop

    def loop_for(law):
        block = real(law)

        def spy(*args):
            seen.append(sys.getswitchinterval())
            return block(*args)
        return spy

    monkeypatch.setattr(fastloop, "_block_loop", loop_for)
    before = sys.getswitchinterval()
    sc = load_scenario(PAPER, ["simulation.duration=1", "simulation.log_rate=30"])
    ref, fast = run_both(sc, tmp_path, steps=4321)
    assert_same(ref, fast)
    want = min(before, fastloop.LOGGED_SWITCH_S)   # Python keeps it in whole microseconds
    assert seen and all(abs(x - want) < 1e-9 for x in seen)
    assert sys.getswitchinterval() == before


def test_record_buffers_are_reused_once_encoded(tmp_path, monkeypatch):
    """The loop refills the record buffers of a block the writer has encoded (fresh ones cost
    a page fault per 4 KiB at N = 1000), and the log stays the reference loop's. With the
    writer encoding each block as it is handed over (so that reuse does not depend on timing),
    one set of buffers serves every 40-step block of 4 records."""
    made = []
    real = fastloop.LogRecords.empty.__func__

    def counted(cls, cap, N, M):
        made.append(cap)
        return real(cls, cap, N, M)

    monkeypatch.setattr(fastloop.LogRecords, "empty", classmethod(counted))
    monkeypatch.setattr(fastloop, "FIRST_LOGGED_BLOCK", 40)
    monkeypatch.setattr(fastloop, "MAX_BLOCK", 40)
    monkeypatch.setattr(fastloop, "TARGET_LOGGED_BLOCK_S", 10.0)   # never cut shorter
    monkeypatch.setattr(fastloop._Writer, "put", lambda self, fn: fn())
    sc = load_scenario(PAPER, ["simulation.duration=0.5", "simulation.log_rate=1000"])
    for encoding in ("json", "cdr"):
        made.clear()
        ref, fast = run_both(sc, tmp_path, encoding=encoding)
        assert_same(ref, fast)
        assert made == [4] and sc.n_steps() // 40 > 50


def test_without_logger(tmp_path):
    sc = load_scenario(PAPER, ["simulation.duration=1.2"])
    ref, fast = run_both(sc, tmp_path, log=False)
    assert_same(ref, fast)


def test_fmu_failure_is_the_same_divergence(tmp_path):
    # h = 10 ms makes the paper loop diverge: the plant refuses a non-finite state, which both
    # loops report as the run's divergence at the same step (cosim.guards), with the same log
    sc = load_scenario(PAPER, ["simulation.duration=20", "simulation.step=0.01",
                               "simulation.log_rate=200"])
    res = []
    for compiled in (False, True):
        plant = FmuPlant.from_scenario(sc)
        path = tmp_path / f"f{compiled}.mcap"
        logger = McapLogger(path, sc)
        m = Master(sc, plant, "hybrid", logger)
        m.use_compiled = compiled
        s = m.run(sc.n_steps())
        logger.close()
        res.append((s["diverged"], s["steps"], plant.steps, m.jumps, messages(path)))
        plant.close()
    assert res[0] == res[1]
    assert "fmi2DoStep" in res[0][0]["reason"] and res[0][1] == res[0][0]["step"] == res[0][2]


def test_a_failure_that_is_not_a_divergence_raises_in_both_loops(tmp_path):
    """A plant error while the state is finite stays an error (FMUError), the same in both."""
    sc = load_scenario(PAPER, ["simulation.duration=0.05", "simulation.step=0.01"])
    res = []
    for compiled in (False, True):
        # an internal step so short that one communication step needs more body-substeps than
        # the FMU allows per doStep: refused at the first step, the state still finite
        plant = FmuPlant(sc.masses, sc.inertias, sc.S0, sc.gravity, 1e-9)
        m = Master(sc, plant, "hybrid")
        m.use_compiled = compiled
        with pytest.raises(FMUError) as ei:
            m.run(sc.n_steps())
        res.append((ei.value.function, m.diverged))
        plant.close()
    assert res[0] == res[1] and res[0][1] is None


def test_only_fleet_fmu_with_network_controller_is_compiled():
    """The compiled loop asks for capabilities: the plant's `compiled_plant()` (the fleet FMU
    plant has it, the per-body one not), the law's `compiled_step()` whose wrench buffer is the
    plant's input buffer (which the master arranges), not a type."""
    sc = load_scenario(PAPER, ["simulation.duration=0.01"])
    from cosim.master import make_controller

    ctrl = make_controller("hybrid", sc)
    p = PerBodyFmuPlant.from_scenario(sc)
    try:
        assert fastloop.compiled_pair(p, ctrl) is None
    finally:
        p.close()
    p = FmuPlant.from_scenario(sc)
    try:
        assert fastloop.compiled_pair(p, ctrl) is None   # the law writes its own buffer
        Master(sc, p, ctrl)                             # ... until the master hands it the plant's
        cp, law = fastloop.compiled_pair(p, ctrl)
        assert law.u is cp.fmi.inputs is p.input_buffer and cp.clock[0] == p.steps == 0
        assert fastloop.compiled_pair(p, object()) is None
    finally:
        p.close()
    assert p.compiled_plant() is None


def test_record_fast_equals_record(tmp_path):
    """record/record_fast and jump/jump_fast: the same bytes with float repr, the same values
    with orjson, also for non-finite values and jumping edges (the fallbacks)."""
    sc = random_tree_scenario(7, 1)
    rng = np.random.default_rng(0)
    N, M = 7, 6
    paths = [tmp_path / "a.mcap", tmp_path / "b.mcap", tmp_path / "c.mcap"]
    lgs = [McapLogger(p, sc) for p in paths]
    lgs[1].orjson = False
    for r in range(6):
        args = (rng.standard_normal((N, 18)) * 10.0 ** rng.integers(-20, 20, (N, 18)),
                rng.standard_normal((N, 6)), rng.standard_normal(M), rng.random(M),
                rng.random(M) < (0.3 if r == 2 else 0.0), rng.random(M), rng.random(M),
                rng.random(M), rng.standard_normal((N, 4)), float(rng.random()),
                float(rng.random()))
        if r == 4:
            args[0][1, 2] = np.nan
            args[1][0, 0] = np.inf
        t_ns = 1_000_000_000 * r + 123_456 * r
        lgs[0].record(t_ns, *args)
        lgs[1].record_fast(t_ns, *args)
        lgs[2].record_fast(t_ns, *args)
        lgs[0].jump(t_ns, t_ns * 1e-9, r + 1, *args[2][:3].tolist())
        lgs[1].jump_fast(t_ns, t_ns * 1e-9, r + 1, *args[2][:3].tolist())
        lgs[2].jump_fast(t_ns, t_ns * 1e-9, r + 1, *args[2][:3].tolist())
    for lg in lgs:
        (lg.jump if lg is lgs[0] else lg.jump_fast)(7, 7e-9, 2, 0.5, float("nan"), -np.inf)
        lg.close()
    a, b = messages(paths[0]), messages(paths[1])
    assert len(a) >= 31 and a == b  # + /scene and /trail messages when due
    # orjson: same values (exactly), and really another text for some numbers
    assert messages(paths[0], decoded=True) == messages(paths[2], decoded=True)
    if fastloop_orjson():
        assert messages(paths[2]) != a
    json.loads(a[0][3])


def fastloop_orjson():
    from cosim.log import writer as mcaplog

    return mcaplog._orjson is not None


STOP_SCRIPT = r"""
import sys, json
sys.path.insert(0, {root!r})
from cosim.run import run_scenario
s = run_scenario({paper!r}, log_path={log!r}, duration=400)
print(json.dumps({{"steps": s["steps"], "interrupted": s["interrupted"]}}))
"""


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_signal_stops_within_a_block_with_a_complete_log(tmp_path, sig):
    log = tmp_path / "s.mcap"
    code = STOP_SCRIPT.format(root=str(ROOT), paper=str(PAPER), log=str(log))
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, cwd=tmp_path)
    try:
        deadline = time.monotonic() + 120  # a guard against a hang, not a speed assertion
        while time.monotonic() < deadline:
            if log.exists() and log.stat().st_size > 200_000:
                break
            if proc.poll() is not None:
                pytest.fail("the run ended before it could be stopped")
            time.sleep(0.05)
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    s = json.loads(out.decode().strip().splitlines()[-1])
    assert s["interrupted"] is True and 0 < s["steps"] < 4_000_000
    back = read_log(log)
    assert not back["truncated"]
    # every log tick of the steps done is in the log (the stop came between two blocks)
    dec = 100
    n_ticks = -(-s["steps"] // dec)
    assert len(back["messages"]["/tf"]) == n_ticks
    assert len(back["messages"]["/lyapunov"]) == n_ticks


def test_budget_and_request_stop_between_blocks(tmp_path):
    # a zero wall-clock budget stops after the second block (the budget counts from the end
    # of the first, as in the reference loop); request_stop() before a run stops it at once
    sc = load_scenario(PAPER, ["simulation.duration=0.5"])
    plant = FmuPlant.from_scenario(sc)
    try:
        m = Master(sc, plant, "hybrid")
        s = m.run(sc.n_steps(), budget=0.0)
        assert s.get("timed_out") is True and s["interrupted"] is False
        n1 = s["steps"]
        assert 0 < n1 <= 2000 and plant.steps == n1
        S_mid = plant.read().copy()
        m2 = Master(sc, plant, "hybrid")
        m2.request_stop()
        assert m2.run(100)["steps"] == 0
    finally:
        plant.close()
    ref = FmuPlant.from_scenario(sc)
    try:
        m = Master(sc, ref, "hybrid")
        m.use_compiled = False
        m.run(n1)
        assert np.array_equal(ref.read(), S_mid)
    finally:
        ref.close()


def test_second_run_on_the_same_plant(tmp_path):
    # a Master run on a plant that has already stepped: doStep times continue from the
    # plant's own clock, which either loop advances in place (nothing copies it back)
    sc = load_scenario(PAPER, ["simulation.duration=0.1"])
    finals = []
    for compiled in (False, True):
        plant = FmuPlant.from_scenario(sc)
        times = []
        real = plant._do_step if not compiled else None
        if real is not None:   # the Python loop's doStep times
            plant._do_step = lambda t, h: (times.append(t), real(t, h))
        try:
            for _ in range(2):
                m = Master(sc, plant, "hybrid")
                m.use_compiled = compiled
                m.run(sc.n_steps())
            finals.append((plant.read().copy(), plant.steps))
        finally:
            plant.close()
        if times:
            assert times == [k * sc.step for k in range(2 * sc.n_steps())]
    assert np.array_equal(finals[0][0], finals[1][0])
    assert finals[0][1] == finals[1][1] == 2 * sc.n_steps()


def test_record_block_equals_record_per_row(tmp_path):
    sc = random_tree_scenario(5, 2)
    rng = np.random.default_rng(1)
    R, N, M = 6, 5, 4
    S = rng.standard_normal((R, N, 18)) * 10.0 ** rng.integers(-30, 30, (R, N, 18))
    u, quat = rng.standard_normal((R, N, 6)), rng.standard_normal((R, N, 4))
    e = rng.standard_normal((5, R, M))
    jumped = np.zeros((R, M), np.bool_)
    jumped[2, 1] = True
    S[4, 0, 13] = np.nan
    t_ns = [10_000_000 * r + 7 for r in range(R)]
    V, kxu = rng.random(R).tolist(), rng.random(R).tolist()
    paths = [tmp_path / f"{k}.mcap" for k in "abc"]
    lgs = [McapLogger(p, sc) for p in paths]
    lgs[2].orjson = False
    for r in range(R):
        lgs[0].record(t_ns[r], S[r], u[r], e[0, r], e[1, r], jumped[r], e[2, r], e[3, r],
                      e[4, r], quat[r], V[r], kxu[r])
    for lg in lgs[1:]:
        lg.record_block(t_ns, S, u, e[0], e[1], jumped, e[2], e[3], e[4], quat, V, kxu)
    for lg in lgs:
        lg.close()
    a = messages(paths[0])
    assert sum(m[0] == "/lyapunov" for m in a) == R
    assert messages(paths[2]) == a
    assert messages(paths[1], decoded=True) == messages(paths[0], decoded=True)


def test_each_law_gets_its_own_loop_cache_renewed_when_its_module_changes(tmp_path, monkeypatch):
    """numba checks a cached function against its own file only: the compiled loop of a law is
    cached under a name carrying the stamp of the law's module, so that an edited law is
    compiled again rather than run from the old machine code; and two laws never share an index
    (loading one would import the other)."""
    import importlib
    import os

    mod = tmp_path / "law_stamp_probe.py"
    mod.write_text("from typing import NamedTuple\nclass Rec(NamedTuple):\n    x: int\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    m = importlib.import_module("law_stamp_probe")
    monkeypatch.setattr(fastloop, "_BLOCKS", {})
    a = fastloop._block_loop(m.Rec(1)).py_func.__qualname__
    assert a.startswith("run_block_law_stamp_probe_Rec_")
    st = mod.stat()
    os.utime(mod, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    monkeypatch.setattr(fastloop, "_BLOCKS", {})
    b = fastloop._block_loop(m.Rec(1)).py_func.__qualname__
    assert b != a and b.startswith("run_block_law_stamp_probe_Rec_")
    from cosim.controllers import PaperStep
    from cosim.laws.decoupled import DecoupledStep
    names = {fastloop._block_loop(cls.__new__(cls, *[None] * len(cls._fields))).py_func.__qualname__
             for cls in (PaperStep, DecoupledStep)}
    assert len(names) == 2


@pytest.mark.parametrize("want", [False, True])
def test_a_logger_that_wants_no_record_gets_none_from_the_block(want):
    """A logger with ``frame_wanted`` (the live view without a log): the compiled loop asks it
    before each block; a block it says no to computes no record (its jumps still come), a block
    it says yes to computes only its last record on the grid. The summary is the same."""
    sc = load_scenario(PAPER, ["simulation.duration=0.5", "simulation.log_rate=30"])
    dec = round(1 / (sc.log_rate * sc.step))
    got, jumps, asked = [], [], []

    class Wanting:
        inline = True
        block_seconds = None
        counts = {}

        def frame_wanted(self):
            asked.append(True)
            return want

        def record_block(self, t_ns, *a):
            got.append(list(t_ns))

        def jump(self, *a):
            jumps.append(a[0])

    plant = FmuPlant.from_scenario(sc)
    try:
        m = Master(sc, plant, "hybrid", Wanting())
        s = m.run(sc.n_steps())
    finally:
        plant.close()
    ref_plant = FmuPlant.from_scenario(sc)
    try:
        ref = Master(sc, ref_plant, "hybrid").run(sc.n_steps())
    finally:
        ref_plant.close()
    assert asked and s["n_jumps"] == ref["n_jumps"] > 0 and s["samples"] == ref["samples"]
    assert jumps == [round(j["t"] * 1e9) for j in ref["jumps"]]
    if not want:
        assert got == []
    else:   # one record per block that crosses the grid: its last one
        assert got and all(len(r) == 1 for r in got)
        steps = [round(r[0] / (sc.step * 1e9)) for r in got]
        assert all(k % dec == 0 for k in steps) and steps == sorted(set(steps))
        assert len(steps) <= len(asked)
        assert steps[-1] == (sc.n_steps() - 1) // dec * dec   # the last block's last one
