"""The se3sync run / check / plot commands: scenario errors, stability refusal, Ctrl-C, plots."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from cosim.cli import main

ROOT = Path(__file__).resolve().parents[2]
PAPER = ROOT / "scenarios" / "paper_6uav.toml"
PAPER_TEXT = PAPER.read_text()


def _scenario(tmp_path, text, name="bad.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def _sub(old, new, text=PAPER_TEXT):
    assert old in text, old
    return text.replace(old, new)


BAD = {
    # name: (scenario text, extra args, expected key path, reason fragment)
    "unknown_key": (_sub("k_theta = 1.0", "k_theta = 1.0\nk_Y = 3"), [], "gains.k_Y", "unknown key"),
    "unknown_table": (PAPER_TEXT + "\n[foo]\nx = 1\n", [], "foo", "unknown key"),
    "unknown_key_agent": (_sub('generator = "paper"\naxis = [0.2686, 0.8549, 0.4438]',
                               "\n".join(["[[initial.agent]]\nposition = [0, 0, 0]\nspin = 1"] * 6)),
                          [], "initial.agent[1].spin", "unknown key"),
    "wrong_shape": (_sub("b = [18.24, 14.43, 15.96]", "b = [18.24, 14.43]"), [], "weighting.b", "shape 3"),
    "wrong_type": (_sub("k_X = 100.0", 'k_X = "fast"'), [], "gains.k_X", "must be a number"),
    "negative_gain": (_sub("k_X = 100.0", "k_X = -1"), [], "gains.k_X", "must be > 0, got -1"),
    "missing_key": (_sub("d = 5.0", ""), [], "weighting.d", "missing"),
    "missing_table": (_sub("[gains]", "[gainz]"), [], "gainz", "unknown key"),
    "bad_toml": (_sub("k_e = 0.6", "k_e = = 0.6"), [], None, "line 5"),
    "weighting_refused": (_sub("d = 5.0", "d = 0.5"), [], "weighting", "positive semi-definite"),
    "design_refused_gamma": (_sub("gamma = 0.33", "gamma = 0.5"), [], "synergy.gamma", "bound"),
    "design_refused_delta": (_sub("delta = 0.02", "delta = 0.5"), [], "synergy.delta", "exact gap"),
    "graph_refused": (_sub("[5, 6]]", "[5, 6], [6, 1]]"), [], "graph.edges", "cycle"),
    "graph_disconnected": (_sub(", [5, 6]]", "]"), [], "graph.edges", "not connected"),
    "both_theta": (_sub("Theta_over_pi = [0.3]", "Theta_over_pi = [0.3]\nTheta = [0.9]"), [],
                   "synergy.Theta_over_pi", "not both"),
    "bad_generator": (_sub('generator = "paper"', 'generator = "magic"'), [], "initial.generator", "magic"),
    "bad_set_unknown": (PAPER_TEXT, ["--set", "gains.k_Y=50"], "gains.k_Y", "unknown key"),
    "bad_set_value": (PAPER_TEXT, ["--set", "gains.k_X=-5"], "gains.k_X", "must be > 0"),
    "bad_set_syntax": (PAPER_TEXT, ["--set", "gains.k_X"], "--set gains.k_X", "key.path=value"),
    "bad_set_type": (PAPER_TEXT, ["--set", "simulation.step=[1,2]"], "simulation.step", "number"),
}

# the bad_toml case: line 5 of the gains table
BAD["bad_toml"] = (_sub("k_e = 0.6", "k_e = = 0.6"), [], None,
                   f"line {_sub('k_e = 0.6', 'k_e = = 0.6').splitlines().index('k_e = = 0.6') + 1}")


@pytest.mark.parametrize("case", sorted(BAD))
@pytest.mark.parametrize("command", ["run", "check"])
def test_scenario_errors_are_one_line_exit_2_and_write_nothing(tmp_path, capsys, case, command):
    text, extra, key, reason = BAD[case]
    path = _scenario(tmp_path, text)
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    log, summ = out_dir / "x.mcap", out_dir / "x.json"
    argv = [command, str(path)] + extra
    if command == "run":
        argv += ["--log", str(log), "--summary", str(summ), "--duration", "0.01"]
    rc = main(argv)
    err = capsys.readouterr().err
    assert rc == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    line = lines[0]
    assert line.startswith(f"se3sync {command}: error: {path}: ")
    if key is not None:
        assert f": {key}: " in line, line
    assert reason in line, line
    assert list(out_dir.iterdir()) == []


def test_missing_file(tmp_path, capsys):
    assert main(["run", str(tmp_path / "nope.toml")]) == 2
    assert "nope.toml: no such file" in capsys.readouterr().err


def test_check_stability_of_the_paper_gains(capsys):
    from cosim.scenario import load_scenario
    from cosim.analysis.stability import analyse, spectral_radius

    sc = load_scenario(PAPER)
    assert spectral_radius(sc, 2e-4) > 1.0
    assert spectral_radius(sc, 1e-4) < 1.0
    a = analyse(sc)
    assert a["stable"] and 1e-4 < a["max_stable_step"] < 2e-4
    # bisection to 1 %: just above max_stable_step * 1.01 is unstable
    assert spectral_radius(sc, a["max_stable_step"] * 1.011) > 1.0
    assert main(["check", str(PAPER), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    for k in ("case", "u_c1", "u_c2", "delta_star", "gamma", "delta", "gamma_bound",
              "delta_bound", "exact_gap", "warnings"):
        assert k in out["design"]
    assert out["stable"] and out["spectral_radius"] < 1 and out["step"] == 1e-4
    assert main(["check", str(PAPER), "--json", "--step", "2e-4"]) == 3  # unstable: exit 3
    out = json.loads(capsys.readouterr().out)
    assert not out["stable"] and out["spectral_radius"] > 1
    assert main(["check", str(PAPER)]) == 0
    assert "spectral_radius" in capsys.readouterr().out


def test_run_refuses_an_unstable_step_unless_forced(tmp_path, capsys):
    log, summ = tmp_path / "x.mcap", tmp_path / "x.json"
    rc = main(["run", str(PAPER), "--step", "2e-4", "--duration", "0.01", "--log", str(log),
               "--summary", str(summ)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1
    assert "simulation.step" in err[0] and "spectral radius" in err[0] and "max_stable_step" in err[0]
    assert not log.exists() and not summ.exists()
    rc = main(["run", str(PAPER), "--step", "2e-4", "--duration", "0.01", "--summary", str(summ),
               "--force"])
    assert rc == 0
    assert json.loads(summ.read_text())["steps"] == 50


def test_run_writes_summary_and_set_overrides(tmp_path, capsys):
    summ = tmp_path / "s.json"
    rc = main(["run", str(PAPER), "--set", "simulation.duration=0.02", "--set", "gains.k_e=0.7",
               "--summary", str(summ), "--plant", "per-body"])
    assert rc == 0
    s = json.loads(summ.read_text())
    for k in ("scenario", "steps", "sim_time_s", "wall_time_s", "realtime_factor", "design",
              "jumps", "jump_bound", "final", "samples"):
        assert k in s
    assert s["steps"] == 200 and s["plant"] == "per-body" and s["interrupted"] is False
    assert set(s["final"]) >= {"rot_err", "pos_err", "xi_max", "theta"}
    assert s["samples"][0]["t"] == 0 and set(s["samples"][0]) == {"t", "rot_err", "pos_err",
                                                                   "xi_max", "theta", "V"}
    assert [f.name for f in tmp_path.iterdir()] == ["s.json"]  # no temporary left behind


def test_ctrl_c_finishes_log_and_summary(tmp_path):
    from mcap.reader import make_reader

    log, summ = tmp_path / "i.mcap", tmp_path / "i.json"
    proc = subprocess.Popen([sys.executable, "-m", "cosim.cli", "run", str(PAPER), "--log", str(log),
                             "--summary", str(summ)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, cwd=tmp_path)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            if log.exists() and log.stat().st_size > 300_000:
                break
            if proc.poll() is not None:
                pytest.fail("the run ended before it could be interrupted")
            time.sleep(0.05)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, err
    s = json.loads(summ.read_text())
    assert s["interrupted"] is True
    assert 0 < s["steps"] < 400_000
    with open(log, "rb") as f:
        r = make_reader(f)
        summary = r.get_summary()
        assert summary is not None and summary.statistics.message_count > 0
        n = sum(1 for _ in r.iter_messages())
    assert n == summary.statistics.message_count


def test_plot_writes_a_png(tmp_path, capsys):
    import matplotlib.image as mpimg

    log, png = tmp_path / "p.mcap", tmp_path / "p.png"
    assert main(["run", str(PAPER), "--duration", "0.3", "--log", str(log)]) == 0
    assert main(["plot", str(log), "-o", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert png.stat().st_size > 20_000
    img = mpimg.imread(png)
    assert img.shape[0] > 800 and img.shape[1] > 600
    assert np.std(img[..., :3]) > 0.05


def test_plot_refuses_a_bad_log(tmp_path, capsys):
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"this is not an mcap file at all" * 10)
    png = tmp_path / "x.png"
    assert main(["plot", str(bad), "-o", str(png)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "bad.mcap" in err[0]
    assert not png.exists()
    assert main(["plot", str(tmp_path / "none.mcap"), "-o", str(png)]) == 2
    assert "no such file" in capsys.readouterr().err


def test_help_lists_the_commands(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    for c in ("run", "check", "plot"):
        assert c in out


def test_closed_pipe_is_not_a_traceback():
    """`se3sync check --json | head -c 10`: the reader is gone before we write; no traceback."""
    import subprocess
    import sys

    p = subprocess.Popen([sys.executable, "-m", "cosim.cli", "check", str(PAPER), "--json"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    p.stdout.close()  # nobody will read what it prints
    err = p.stderr.read().decode()
    assert p.wait(timeout=120) == 141, err
    assert "Traceback" not in err and "BrokenPipeError" not in err and "Exception ignored" not in err


def test_missing_optional_dependency_is_one_line():
    """Without the 'mavlink' extra, `se3sync vehicle` names the extra instead of a traceback."""
    import subprocess
    import sys

    code = ("import sys; sys.modules['pymavlink'] = None; from cosim.cli import main; "
            "sys.exit(main(['vehicle', '--count', '1']))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "needs the 'mavlink' extra" in lines[0], r.stderr
