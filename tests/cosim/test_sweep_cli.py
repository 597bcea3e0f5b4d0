"""`se3sync sweep` / `sweep-report` command lines: bad input, the report's numbers, formats."""
from __future__ import annotations

import csv
import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("pyarrow")

from cosim.cli import main  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
SMALL = str(ROOT / "scenarios" / "sweep_small.toml")


def test_commands_registered_without_heavy_imports():
    code = ("import argparse, sys; import cosim.cli.sweep as s; p = argparse.ArgumentParser(); "
            "s.register(p.add_subparsers()); "
            "print([m for m in ('dask', 'distributed', 'pyarrow', 'matplotlib') if m in sys.modules])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
    from cosim.cli import build_parser
    from cosim.plugins import command_modules

    assert "cosim.cli.sweep" in command_modules()
    help_text = build_parser().format_help()
    assert "sweep-report" in help_text and " sweep " in help_text.replace("\n", " ")


@pytest.mark.parametrize("args, option", [
    (["--samples", "-1"], "--samples"),
    (["--samples", "2", "--seed", "-3"], "--seed"),
    (["--samples", "2", "--workers", "-1"], "--workers"),
    (["--samples", "2", "--workers", "2", "--scheduler", "tcp://127.0.0.1:8786"], "--workers"),
    (["--samples", "2", "--timeout", "0"], "--timeout"),
    (["--samples", "2", "--rot-tol", "-1"], "--rot-tol"),
    (["--samples", "2", "--pos-tol", "nan"], "--pos-tol"),
    (["--samples", "2", "--position-box", "-1"], "--position-box"),
    (["--samples", "2", "--velocity-ball", "inf"], "--velocity-ball"),
    (["--samples", "2", "--chunk", "0"], "--chunk"),
    (["--samples", "2", "--set", "gains.k_X=-1"], "gains.k_X"),
    (["--samples", "2", "--set", "nosuch.key=1"], "nosuch.key"),
])
def test_bad_input_exit_2_nothing_written(tmp_path, capsys, args, option):
    out = tmp_path / "r.parquet"
    rc = main(["sweep", SMALL, "--out", str(out), "--workers", "0"][:4] + args
              + ([] if "--workers" in args or "--scheduler" in args else ["--workers", "0"]))
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert len(err.splitlines()) == 1 and option in err, err
    assert list(tmp_path.iterdir()) == []


def test_bad_paths(tmp_path, capsys):
    assert main(["sweep", SMALL, "--samples", "1", "--out", str(tmp_path / "r.txt")]) == 2
    assert "--out" in capsys.readouterr().err
    assert main(["sweep", SMALL, "--samples", "1", "--out", str(tmp_path / "no" / "r.csv")]) == 2
    assert "--out" in capsys.readouterr().err
    assert main(["sweep", str(tmp_path / "none.toml"), "--samples", "1",
                 "--out", str(tmp_path / "r.csv")]) == 2
    assert "no such file" in capsys.readouterr().err
    assert main(["sweep-report", str(tmp_path / "none.parquet"), "-o", str(tmp_path / "a.png")]) == 2
    assert "results" in capsys.readouterr().err
    (tmp_path / "junk.parquet").write_text("not parquet")
    assert main(["sweep-report", str(tmp_path / "junk.parquet"), "-o", str(tmp_path / "a.png")]) == 2
    assert "results: cannot read results" in capsys.readouterr().err
    assert main(["sweep", SMALL, "--samples", "1", "--workers", "0",
                 "--out", str(tmp_path / "junk.parquet")]) == 2
    assert "--out: cannot read results" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["junk.parquet"]


def _wilson_independent(k, n, z=1.959963984540054):
    """The Wilson interval as the two roots p of (k/n − p)² = z² p (1 − p) / n."""
    ph = k / n
    a = 1 + z * z / n
    b = -(2 * ph + z * z / n)
    c = ph * ph
    disc = math.sqrt(max(b * b - 4 * a * c, 0.0))
    return (-b - disc) / (2 * a), (-b + disc) / (2 * a)


def test_sweep_then_report(tmp_path, capsys):
    """`sweep` runs every registered law (the third one, cosim/laws/decoupled.py, too) and the
    report summarises and draws each."""
    from cosim.registry import LAWS

    out = tmp_path / "res.parquet"
    rc = main(["sweep", SMALL, "--samples", "3", "--seed", "9", "--workers", "0",
               "--out", str(out), "--set", "simulation.duration=12.0", "--rot-tol", "0.02"])
    assert rc == 0, capsys.readouterr().err
    assert f"ran {15 * len(LAWS)}" in capsys.readouterr().err and len(LAWS) >= 3
    png, js = tmp_path / "rep.png", tmp_path / "sum.json"
    assert main(["sweep-report", str(out), "-o", str(png), "--json", str(js)]) == 0
    text = capsys.readouterr().out
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
    summary = json.loads(js.read_text())

    # independent computation from the file
    import pyarrow.parquet as pq

    t = pq.read_table(out).to_pydict()
    n = len(t["sample"])
    assert n == 15 * len(LAWS)
    assert summary["settings"]["rot_tol"] == 0.02 and summary["settings"]["seed"] == 9
    assert summary["controllers"] == list(LAWS)
    groups = {(g["controller"], g["kind"]): g for g in summary["groups"]}
    for ctrl in LAWS:
        for kind in ("random", "adversarial", "all"):
            idx = [i for i in range(n) if t["controller"][i] == ctrl and t["status"][i] == "ok"
                   and (kind == "all" or t["kind"][i].startswith(kind))]
            k = sum(t["rot_err"][i] < 0.02 and t["pos_err"][i] < 0.01 for i in idx)
            g = groups[(ctrl, kind)]
            assert (g["n_ok"], g["converged"]) == (len(idx), k)
            assert g["rate"] == pytest.approx(k / len(idx))
            lo, hi = _wilson_independent(k, len(idx))
            assert g["ci_low"] == pytest.approx(lo, abs=1e-12)
            assert g["ci_high"] == pytest.approx(hi, abs=1e-12)
            line = next(ln for ln in text.splitlines() if ln.split()[:2] == [ctrl, kind])
            assert f"{k / len(idx):.3f}" in line and f"[{lo:.3f}, {hi:.3f}]" in line
    assert groups[("hybrid", "adversarial")]["rate"] == 1.0
    assert groups[("gradient", "adversarial")]["rate"] == 0.0
    assert groups[("gradient", "adversarial")]["ci_high"] < 0.3
    assert groups[("hybrid", "all")]["jumps_over_bound"] == 0


def test_csv_output_reads_with_the_csv_module(tmp_path, capsys):
    out = tmp_path / "res.csv"
    assert main(["sweep", SMALL, "--samples", "1", "--workers", "0", "--no-baseline",
                 "--out", str(out), "--set", "simulation.duration=8.0"]) == 0
    with open(out, newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 13 and {r["controller"] for r in rows} == {"hybrid"}
    assert [int(r["sample"]) for r in rows] == list(range(13))
    assert all(r["status"] == "ok" for r in rows)
    meta = json.loads((tmp_path / "res.csv.meta.json").read_text())
    assert meta["scenario_name"] == "sweep_small" and meta["settings"]["seed"] == 0
    # resume through the CSV: nothing to do
    assert main(["sweep", SMALL, "--samples", "1", "--workers", "0", "--no-baseline",
                 "--out", str(out), "--set", "simulation.duration=8.0"]) == 0
    assert "skipped 13" in capsys.readouterr().err
