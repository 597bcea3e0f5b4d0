"""The outputs of a run stopped (Ctrl-C, SIGTERM) before its first step: while the command line
loads, while the scenario is read, during the stability and delay analysis, while the plant FMU
is built or loaded. A batch system then still finds a summary that says so (``"interrupted":
true``, ``"steps": 0``, ``"stopped_during"``) and, when a log was asked for, a finished MCAP.

The command line imports this module in its handler of such a signal (loading it costs what
loading the scenario does, about 1.5 s, once).
"""
from __future__ import annotations

from pathlib import Path

from mcap.writer import Writer

from controller import __version__

from . import signals
from .files import atomic_path, write_json_atomic
from .guards import outcome_metadata
from .log.writer import McapLogger
from .scenario import design_summary

__all__ = ["stopped_before_start", "write_bare_log"]


def write_bare_log(path, scenario_path, stage: str, summary: dict) -> None:
    """A finished MCAP that holds only the se3sync metadata record (no scenario was read yet)
    and the outcome record of ``summary``, written whole or not at all."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            w = Writer(f)
            w.start(profile="", library=f"se3sync {__version__}")
            w.add_metadata("se3sync", {
                "scenario_path": str(scenario_path or ""), "se3sync_version": __version__,
                "time_base": "simulated", "time_unit": "ns", "interrupted": "true",
                "stopped_during": stage})
            w.add_metadata("se3sync.outcome", outcome_metadata(summary))
            w.finish()


def stopped_before_start(scenario=None, *, stage: str, scenario_path=None, controller="hybrid",
                         plant="fleet", log_path=None, summary_path=None, log_encoding="json",
                         logger=None, log_metadata=None, summary_extra=None,
                         wall: float = 0.0) -> dict:
    """Writes and returns the summary of a run stopped before its first step (``stage`` says
    what it was doing), and finishes its log: ``logger`` if it was opened, else a log of the
    scenario with no records, else (no scenario yet) `write_bare_log`. Further signals are held
    while the files are written (well under a second)."""
    with signals.catching(lambda: None):
        sc = scenario
        out = {
            "scenario": sc.name if sc is not None else _stem(scenario_path),
            "scenario_path": str(sc.path if sc is not None else scenario_path),
            "controller": controller,
            "step": float(sc.step) if sc is not None else None,
            "steps": 0, "sim_time_s": 0.0, "wall_time_s": wall, "realtime_factor": None,
            "us_per_step": None, "interrupted": True, "stopped_during": stage,
            "n_jumps": 0, "jump_bound_exceeded": False, "diverged": None, "jumps": [],
            "final": None, "samples": [], "plant": plant,
        }
        if sc is not None:
            out["design"] = design_summary(sc)
        out.update(summary_extra or {})
        if log_path is not None:
            counts = {}
            if logger is None and sc is not None:
                logger = McapLogger(log_path, sc, controller=controller, encoding=log_encoding,
                                    extra_metadata={"plant": plant, **(log_metadata or {})})
            if logger is not None:
                logger.outcome(out)
                logger.close()
                counts = dict(logger.counts)
            else:
                write_bare_log(log_path, scenario_path, stage, out)
            out["log"] = str(log_path)
            out["log_messages"] = counts
        if summary_path is not None:
            write_json_atomic(summary_path, out)
    return out


def _stem(path) -> str:
    return Path(str(path)).stem if path else ""
