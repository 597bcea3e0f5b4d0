"""`run_scenario`: one run of a scenario, from its file to its log and summary — the library entry
point that `se3sync run`, `se3sync connect` and other packages call."""
from __future__ import annotations

import dataclasses
import math

from . import signals
from .controllers import law_name, make_controller
from .files import write_json_atomic
from .log.live import live_logger, live_only
from .log.mcap import McapLogger
from .master import Master
from .network import networked
from .plants import make_plant
from .scenario import MAX_DEFAULT_INTERNAL_STEP, Scenario, ScenarioError, load_scenario

__all__ = ["run_scenario", "with_timing", "finish_summary", "write_json_atomic"]


def with_timing(scenario, duration=None, step=None):
    """A copy of the scenario with another duration and/or communication step (the internal
    step follows h unless the scenario sets plant.internal_step)."""
    if duration is None and step is None:
        return scenario
    changes = {}
    if duration is not None:
        duration = float(duration)
        if not (math.isfinite(duration) and duration > 0):
            raise ScenarioError("simulation.duration", f"must be > 0, got {duration}", scenario.path)
        changes["duration"] = duration
    if step is not None:
        step = float(step)
        if not (math.isfinite(step) and step > 0):
            raise ScenarioError("simulation.step", f"must be > 0, got {step}", scenario.path)
        changes["step"] = step
        if "internal_step" not in scenario.values.get("plant", {}):
            changes["internal_step"] = min(step, MAX_DEFAULT_INTERNAL_STEP)
    return dataclasses.replace(scenario, **changes)


def run_scenario(scenario, *, plant="fleet", controller="hybrid", log_path=None,
                 summary_path=None, duration=None, step=None, progress=False,
                 fmu_path=None, log_metadata=None, summary_extra=None,
                 log_encoding="json", live=None) -> dict:
    """Runs a scenario (a Scenario or a path to a TOML file) and returns the summary dict.

    plant: "fleet" | "per-body" | a Plant instance (closed by the caller);
    controller: "hybrid" | "gradient" | a controller instance. log_path: MCAP written
    (streamed) there, its per-record channels in log_encoding ("json" or "cdr"); summary_path: summary JSON written atomically. live: (host, port, rate) of a
    live view (cosim/log/live.py) or None. log_metadata adds to (or
    overrides) the MCAP metadata record, summary_extra to the summary. On Ctrl-C or SIGTERM the
    run stops cleanly, the log is finished and the summary has "interrupted": true. A run that
    fails (an exception) removes its log: no output is better than one that looks whole.
    """
    if not isinstance(scenario, Scenario):
        scenario = load_scenario(scenario)
    scenario = with_timing(scenario, duration, step)
    if log_path is None:
        scenario = live_only(scenario, live)   # records at most at the live view's rate
    own_plant = isinstance(plant, str)
    plant_kind = plant if own_plant else type(plant).__name__
    ctrl = make_controller(controller, scenario) if isinstance(controller, str) else controller
    ctrl = networked(scenario, ctrl)  # the law per agent over the [network] links, if any
    ctrl_kind = law_name(ctrl)
    p = make_plant(plant, scenario, fmu_path) if own_plant else plant
    logger = None
    failed = False
    try:
        # A signal while the log and the master are set up stops the run at its first step
        # (with a finished log and a summary), rather than somewhere inside the set-up.
        requested = []
        with signals.catching(lambda: requested.append(True)):
            if log_path is not None:
                md = getattr(p, "model_description", None)
                logger = McapLogger(log_path, scenario, controller=ctrl_kind,
                                    model_description=md() if md is not None else None,
                                    encoding=log_encoding,
                                    extra_metadata={"plant": plant_kind, **(log_metadata or {})})
            logger = live_logger(logger, live, scenario, encoding=log_encoding)
            master = Master(scenario, p, ctrl, logger)
        if requested:
            master.request_stop()
        summary = master.run(scenario.n_steps(), progress=progress)
    except Exception:
        failed = True
        raise
    finally:
        try:
            if logger is not None:
                logger.close(discard=failed)
        except OSError:
            if not failed:
                raise
        finally:
            if own_plant:
                p.close()
    summary["plant"] = plant_kind
    net_stats = getattr(ctrl, "network_stats", None)
    if net_stats is not None:
        summary["network"] = net_stats()
    summary.update(summary_extra or {})
    return finish_summary(summary, logger, log_path, summary_path)


def finish_summary(summary: dict, logger, log_path, summary_path) -> dict:
    """Adds the log's name and message counts to a run's summary and writes it (atomically)."""
    if log_path is not None:
        summary["log"] = str(log_path)
        summary["log_messages"] = dict(logger.counts)
    if summary_path is not None:
        write_json_atomic(summary_path, summary)
    return summary
