"""`se3sync check`: the delay margin and convergence lines, and their consistency."""
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from cosim.analysis.stability_sparse import Linearisation
from cosim.cli import main
from cosim.scenario import load_scenario


def test_check_json_reports_delay_margin_and_rate(capsys):
    assert main(["check", "scenarios/hil_6uav.toml", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    h = out["step"]
    assert out["method"] == "modal"
    dm = out["delay_margin"]
    assert dm["rho_at_margin"] < 1.0 <= dm["rho_beyond"]
    assert dm["delay_margin_s"] == pytest.approx(dm["delay_margin_steps"] * h)
    # at d = 0 the delayed loop is the loop itself: a margin ≥ 1 step needs ρ(0) < 1
    assert out["stable"] and dm["delay_margin_steps"] >= 0
    c = out["convergence"]
    # the slowest mode IS the spectral radius: rate = −ln ρ / h
    assert c["rate"] == pytest.approx(-math.log(out["spectral_radius"]) / h, rel=1e-9)
    assert set(c["sensitivity"]) == {"k_X", "k_xi", "k_e", "k_theta"}


def test_check_text_and_from_error(capsys):
    # k_X = 30, k_e = 1: a margin of five steps, quick to find
    assert main(["check", "scenarios/hil_6uav.toml", "--from-error", "1", "--set", "gains.k_X=30",
                 "--set", "gains.k_e=1"]) == 0
    text = capsys.readouterr().out
    for key in ("delay_margin", "slowest_rate", "time_to_tol", "d rate/d ln k"):
        assert key in text
    rate = float(text.split("slowest_rate")[1].split()[0])
    t = float(text.split("time_to_tol")[1].split()[0])
    assert t == pytest.approx(math.log(100.0) / rate, rel=1e-3)


def test_check_rejects_a_bad_from_error(capsys):
    assert main(["check", "scenarios/hil_6uav.toml", "--from-error", "-1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--from-error" in err[0]


def test_check_skips_the_delay_margin_above_its_agent_limit(tmp_path, capsys):
    """One agent above the limit: the margin is reported as not computed, and why, while the
    spectral radius and the convergence rate are still there. The default limit is the
    10,000 agents the count handles within 2 minutes; a 60-agent tree with the limit 59 shows
    the same path without the 10,001-agent analysis."""
    from cosim.analysis.stability_cases import tree_scenario_text
    from cosim.analysis.stability_report import DELAY_MAX_AGENTS

    assert DELAY_MAX_AGENTS == 10000
    n = 60
    path = tmp_path / "tree.toml"
    path.write_text(tree_scenario_text(n, "random", 0))
    assert main(["check", str(path), "--json", "--delay-agents", str(n - 1)]) == 0
    out = json.loads(capsys.readouterr().out)
    dm = out["delay_margin"]
    assert dm["delay_margin_steps"] is None
    assert dm["delay_method"] == f"not computed: {n} agents > {n - 1} (--delay-agents)"
    assert out["stable"] and out["convergence"]["rate"] > 0.0


QUICK = ["scenarios/hil_6uav.toml", "--json", "--set", "gains.k_X=30", "--set", "gains.k_e=1"]


def test_delay_agents_sets_the_limit_and_nothing_else(capsys):
    """hil_6uav has 6 agents: --delay-agents 5 and 0 skip the margin and say why; the default
    computes it; the rest of the report is the same either way."""
    reports = {}
    for extra in ([], ["--delay-agents", "5"], ["--delay-agents", "0"], ["--delay-agents", "6"]):
        assert main(["check", *QUICK, *extra]) == 0
        reports[tuple(extra)] = json.loads(capsys.readouterr().out)
    base = reports[()]["delay_margin"]
    assert base["delay_margin_steps"] == 5 and base["rho_at_margin"] < 1.0 <= base["rho_beyond"]
    assert reports[("--delay-agents", "6")]["delay_margin"] == base
    assert reports[("--delay-agents", "5")]["delay_margin"]["delay_method"] == \
        "not computed: 6 agents > 5 (--delay-agents)"
    assert reports[("--delay-agents", "0")]["delay_margin"]["delay_method"] == \
        "not computed: --delay-agents 0"
    for r in reports.values():
        r.pop("delay_margin")
    assert all(r == reports[()] for r in reports.values())


@pytest.mark.parametrize("value", ["-1", "x", "2.5"])
def test_delay_agents_rejects_what_is_not_a_count(capsys, value):
    try:
        rc = main(["check", *QUICK, "--delay-agents", value])
    except SystemExit as exc:      # argparse: not an integer
        rc = exc.code
    assert rc == 2
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and "--delay-agents" in err[0] and captured.out == ""


def test_frequency_sweep_progress(capsys, monkeypatch):
    """`crossing_delay` reports each of its eigenproblems in order, the grid first; `check` on a
    terminal turns them into lines (here with no pause between lines), all before the
    eigenproblems at the guess, the last one after the grid."""
    from cosim.analysis import delay_margin as dm
    from cosim.cli import run as run_cli

    sc = load_scenario(QUICK[0], [QUICK[3], QUICK[5]])
    lin = Linearisation(sc, True, force_sparse=True)
    calls = []
    guess = dm.crossing_delay(*dm.delayed_parts(lin, sc.step), sweep=lambda *a: calls.append(a))
    assert guess == dm.crossing_delay(*dm.delayed_parts(lin, sc.step))
    k, g, n = (np.array(c) for c in zip(*calls))
    assert list(k) == list(range(1, len(calls) + 1)) and set(n) == {200}
    assert np.all(np.diff(g) >= 0) and g[0] == 0 and g[-1] == 200
    assert (g < 200).sum() == 200 and len(calls) > 200       # the grid, then the bisections
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    monkeypatch.setattr(run_cli, "SWEEP_EVERY", 0.0)
    assert main(["check", *QUICK]) == 0
    lines = capsys.readouterr().err.strip().splitlines()
    sweep = [i for i, line in enumerate(lines) if "frequency sweep" in line]
    assert len(sweep) == len(calls)
    assert lines[sweep[-1]].startswith(f"se3sync check: delay margin: frequency sweep, "
                                       f"{len(calls)} eigenproblems of T, grid done")
    later = [i for i, line in enumerate(lines) if "d = " in line and "d = 0 " not in line]
    assert later and min(later) > max(sweep)


def test_delay_margin_progress_lines_on_a_terminal(capsys, monkeypatch):
    """One line per eigenproblem on a terminal, none otherwise; the lines at the margin and one
    step beyond carry the radii of the report."""
    assert main(["check", *QUICK]) == 0
    quiet = capsys.readouterr()
    assert quiet.err == ""
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    assert main(["check", *QUICK]) == 0
    cap = capsys.readouterr()
    dm = json.loads(cap.out)["delay_margin"]
    assert dm == json.loads(quiet.out)["delay_margin"]
    seen = {}
    for line in cap.err.strip().splitlines():
        if "frequency sweep" in line:         # one every 2 s: none here unless the machine stalls
            continue
        assert line.startswith("se3sync check: delay margin: d = ")
        d = int(line.split("d = ")[1].split()[0])
        seen[d] = float(line.split("spectral radius ")[1].split()[0])
    d = dm["delay_margin_steps"]
    assert 0 in seen and d in seen and d + 1 in seen
    assert seen[d] == pytest.approx(dm["rho_at_margin"], abs=1e-8)
    assert seen[d + 1] == pytest.approx(dm["rho_beyond"], abs=1e-8)
    assert f"{len(seen)} eigenproblems" in dm["delay_method"]


# ------------------------------------------------------------------ BLAS threads (cosim/threads.py)
def _spy_blas(monkeypatch):
    """Every eigenproblem np.linalg solves, with the BLAS libraries' thread counts at the time
    (threadpoolctl)."""
    from cosim.threads import blas_info

    seen = []
    for name in ("eigvals", "eig"):
        orig = getattr(np.linalg, name)

        def spy(*a, _orig=orig, **k):
            if len(seen) < 50:        # threadpool_info reads every loaded library: a few ms
                seen.append(tuple(n for _, n in blas_info()))
            return _orig(*a, **k)
        monkeypatch.setattr(np.linalg, name, spy)
    return seen


def test_check_runs_its_eigenproblems_on_one_blas_thread(capsys, monkeypatch):
    """The policy (cosim/threads.py): `check`'s analysis runs BLAS on one thread per library,
    whatever the library's default, and gives the default back afterwards; the override
    SE3SYNC_BLAS_THREADS=0 leaves the default; a bad override is one line, exit 2."""
    import cosim.analysis.delay_margin  # noqa: F401 - scipy's BLAS is loaded too
    from cosim.threads import ENV, blas_info

    monkeypatch.delenv(ENV, raising=False)
    before = blas_info()
    assert len(before) >= 1
    seen = _spy_blas(monkeypatch)
    assert main(["check", *QUICK]) == 0
    assert json.loads(capsys.readouterr().out)["delay_margin"]["delay_margin_steps"] == 5
    assert len(seen) >= 3 and set(seen) == {(1,) * len(before)}, seen[:5]
    assert blas_info() == before          # restored
    seen.clear()
    monkeypatch.setenv(ENV, "0")          # the library's default, as before the policy
    assert main(["check", *QUICK]) == 0
    capsys.readouterr()
    assert seen and set(seen) == {tuple(n for _, n in before)}
    monkeypatch.setenv(ENV, "two")
    assert main(["check", *QUICK]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and ENV in err[0]


@pytest.mark.parametrize("entry", ["analyse", "delay_margin", "convergence"])
def test_every_analysis_entry_point_chooses_its_blas_threads(monkeypatch, entry):
    """Called as a library (run's pre-check, swarm's, the delay guard), each entry point applies
    the policy by itself: one BLAS thread for hil_6uav's 77-state loop."""
    from cosim import threads
    from cosim.analysis.convergence_rate import convergence
    from cosim.analysis.delay_margin import delay_margin
    from cosim.analysis.stability import analyse

    monkeypatch.delenv(threads.ENV, raising=False)
    assert threads.analysis_threads(77) == 1
    fn = {"analyse": analyse, "delay_margin": delay_margin, "convergence": convergence}[entry]
    seen = _spy_blas(monkeypatch)
    fn(load_scenario(QUICK[0], [QUICK[3], QUICK[5]]))
    assert seen and all(set(s) == {1} for s in seen), seen[:5]


def test_limit_process_covers_blas_loaded_later():
    """An agent process (`limit_process`, bridge/swarm/agent.py's run_agent): one thread in
    NumPy's BLAS, loaded, and in SciPy's, loaded afterwards."""
    import os
    import subprocess

    code = ("import json, sys, numpy; from cosim.threads import limit_process, blas_info; "
            "assert 'scipy' not in sys.modules; limit_process(1); import scipy.linalg; "
            "print(json.dumps(blas_info()))")
    env = {k: v for k, v in os.environ.items()
           if k not in ("SE3SYNC_BLAS_THREADS", "OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS",
                        "MKL_NUM_THREADS")}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                       cwd=str(Path(__file__).resolve().parents[2]))
    assert r.returncode == 0, r.stderr
    info = json.loads(r.stdout)   # [[file, threads]]
    assert len(info) == 2 and all(n == 1 for _, n in info), info
