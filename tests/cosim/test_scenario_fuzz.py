"""A seeded scenario fuzz: hundreds of mutations of the shipped scenarios (wrong types, NaN, inf,
huge and tiny numbers, empty arrays, cycles, unicode, deleted or duplicated lines, deep nesting).
Every case must end in success or in one clean line with exit status 2 (3: `check` found the
step unstable) — never a traceback, a hang or a crash."""
from __future__ import annotations

import random
import tomllib
from pathlib import Path

import pytest

from cosim.cli import main
from cosim.scenario import SCHEMA

ROOT = Path(__file__).resolve().parents[2]
SCENARIOS = sorted((ROOT / "scenarios").glob("*.toml"))
N_CASES = 300

VALUES = ["nan", "inf", "-inf", "1e308", "-1e308", "1e-320", "0", "-1", "9223372036854775807",
          "-9223372036854775808", "[]", "[[]]", "[1, 2]", "[nan, 0, 0]", "[1e308, 1e308, 1e308]",
          '"ünïcødé"', '"𝔸"', "true", "{}", "{a = 1}", "[[1, 2], [2, 1]]", "[[1, 2], [2, 3], [3, 1]]",
          "0.5", "3", "[0.1, 0.1, 0.1]", "[[1, 0, 0], [0, 1, 0], [0, 0, -1]]", "1e-12", "2.0",
          '"paper"', '"random"', "[1, -1, 1]", "[0, 0, 0]", "100000", "[3.2, 3.2]"]


def _keys():
    keys = []
    for sec, allowed in SCHEMA.items():
        keys += [f"{sec}.{k}" for k in sorted(allowed) if k != "agent"]
    return keys


def _text_mutation(rng, text):
    lines = text.splitlines()
    op = rng.randrange(4)
    i = rng.randrange(len(lines))
    if op == 0:
        del lines[i]
    elif op == 1:
        lines.insert(i, lines[rng.randrange(len(lines))])
    elif op == 2:
        lines[i] = lines[i][: rng.randrange(len(lines[i]) + 1)]
    else:
        lines.insert(i, "[" * rng.randrange(1, 800))
    return "\n".join(lines) + "\n"


def _same_as_before(seen: set, text: str, sets: list) -> bool:
    """True when this case's TOML (parsed, so comments and spacing do not count) with these
    overrides was already checked: a mutation that only deleted a comment line is the shipped
    scenario again, and analysing it again (seconds each) would test nothing new."""
    try:
        key = (repr(tomllib.loads(text)), tuple(sets))
    except (tomllib.TOMLDecodeError, RecursionError):
        return False
    if key in seen:
        return True
    seen.add(key)
    return False


@pytest.mark.slow
@pytest.mark.timeout(300)  # a hang fails the test here; a case's time is not asserted
# a numpy warning is two more lines on a user's stderr ("weighting.d = -1e308" printed one from
# the design's symmetrisation before its one-line error, which then read "d = -inf")
@pytest.mark.filterwarnings("error::RuntimeWarning")
def test_scenario_fuzz(tmp_path, capsys):
    rng = random.Random(20261122)
    keys = _keys()
    outcomes = {}
    seen: set = set()
    for case in range(N_CASES):
        src = rng.choice(SCENARIOS)
        path, sets = src, []
        if case % 4 == 3:
            path = tmp_path / f"m{case}.toml"
            path.write_text(_text_mutation(rng, src.read_text()), encoding="utf-8")
        else:
            for _ in range(rng.randrange(1, 3)):
                sets += ["--set", f"{rng.choice(keys)}={rng.choice(VALUES)}"]
        if _same_as_before(seen, Path(path).read_text(encoding="utf-8"), sets):
            outcomes["repeat"] = outcomes.get("repeat", 0) + 1
            continue
        argv = ["check", str(path), *sets]
        try:
            rc = main(argv)
        except SystemExit as exc:
            rc = exc.code
        except BaseException as exc:  # a traceback: the failure this test exists for
            pytest.fail(f"case {case}: {argv} raised {type(exc).__name__}: {exc}")
        err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
        assert rc in (0, 2, 3), (case, argv, rc, err)
        if rc == 2:
            assert len(err) == 1 and "Traceback" not in err[0], (case, argv, err)
        outcomes[rc] = outcomes.get(rc, 0) + 1
    assert outcomes.get(2, 0) > N_CASES // 3  # the mutations do reach the validation
