"""`run_scenario`: one run of a scenario, from its file to its log and summary — the library entry
point that `se3sync run`, `se3sync connect` and other packages call."""
from __future__ import annotations

import time

from . import signals
from .controllers import law_name, make_controller
from .early_stop import stopped_before_start
from .files import write_json_atomic
from .log.live import live_logger, live_only
from .log.writer import McapLogger
from .master import Master
from .network import networked
from .plants import make_plant, refuse_actuation_delay
from .scenario import Scenario, load_scenario, with_timing

__all__ = ["run_scenario", "with_timing", "finish_summary", "write_json_atomic"]


def run_scenario(scenario, *, plant="fleet", controller="hybrid", log_path=None,
                 summary_path=None, duration=None, step=None, progress=False,
                 fmu_path=None, log_metadata=None, summary_extra=None,
                 log_encoding="json", stage=None, live=None) -> dict:
    """Runs a scenario (a Scenario or a path to a TOML file) and returns the summary dict.

    plant: a registered plant name (`cosim.registry.PLANTS`; with ``simulation.actuation_delay``
    inside `cosim.plants.DelayedActuation`) or a Plant instance (closed by the caller; a
    scenario with an actuation delay is refused); fmu_path: the FMU an FMU plant loads; controller: a registered law name
    (`cosim.registry.LAWS`) or a controller instance. log_path: MCAP written (streamed) there,
    its per-record channels in log_encoding ("json" or "cdr"); summary_path: summary JSON
    written atomically. live: (host, port, rate) of a live view (cosim/log/live.py) or None.
    log_metadata adds to (or
    overrides) the MCAP metadata record, summary_extra to the summary. On Ctrl-C or SIGTERM the
    run stops cleanly, the log is finished and the summary has "interrupted": true, also
    before the first step (building the controller, the plant FMU, the log: `"steps": 0` and
    `"stopped_during"`, `cosim.early_stop`). A run that diverges stops early with
    ``"diverged"`` in the summary (`cosim.guards`); its log is finished too. A run that fails
    (an exception) removes its log: no output is better than one that looks whole.
    ``stage(name)``, if given, is called as each part of the set-up starts.
    """
    t_start = time.perf_counter()
    where = ["loading the scenario"]   # what the set-up is doing, for a stop before step 0

    def at(name):
        where[0] = name
        signals.set_stage(name)
        if stage is not None:
            stage(name)

    own_plant = isinstance(plant, str)
    plant_kind = plant if own_plant else type(plant).__name__
    ctrl_kind = controller if isinstance(controller, str) else law_name(controller)
    p = None if own_plant else plant
    logger = None
    try:
        try:
            if not isinstance(scenario, Scenario):
                scenario = load_scenario(scenario)
            scenario = with_timing(scenario, duration, step)
            if not own_plant:   # only the plants make_plant builds delay the wrench
                refuse_actuation_delay(scenario, f"a plant given to the run ({plant_kind})")
            if log_path is None:
                scenario = live_only(scenario, live)   # records at most at the live view's rate
            at("building the controller")
            ctrl = (make_controller(controller, scenario) if isinstance(controller, str)
                    else controller)
            ctrl = networked(scenario, ctrl)  # the law per agent over the [network] links
            ctrl_kind = law_name(ctrl)
            if own_plant:
                at("loading the plant FMU")
                options = {} if fmu_path is None else {"fmu_path": fmu_path}   # an FMU plant's
                p = make_plant(plant, scenario, **options)
            at("opening the log" if log_path is not None else "setting up the master")
            # A signal while the log and the master are set up stops the run at its first
            # step (with a finished log and a summary), rather than somewhere inside the set-up.
            requested = []
            with signals.catching(lambda: requested.append(True)):
                if log_path is not None:
                    md = getattr(p, "model_description", None)
                    logger = McapLogger(log_path, scenario, controller=ctrl_kind,
                                        model_description=md() if md is not None else None,
                                        encoding=log_encoding,
                                        extra_metadata={"plant": plant_kind,
                                                        **(log_metadata or {})})
                logger = live_logger(logger, live, scenario, encoding=log_encoding)
                master = Master(scenario, p, ctrl, logger)
            if requested:
                master.request_stop()
            at("starting the run")
            summary = master.run(scenario.n_steps(), progress=progress)
        except KeyboardInterrupt:
            # before the loop (which handles its own signals): nothing was stepped
            lg, logger = logger, None
            return stopped_before_start(
                scenario if isinstance(scenario, Scenario) else None,
                stage=signals.stage_at_signal() or where[0],
                scenario_path=getattr(scenario, "path", scenario), controller=ctrl_kind,
                plant=plant_kind, log_path=log_path, summary_path=summary_path,
                log_encoding=log_encoding, logger=lg, log_metadata=log_metadata,
                summary_extra=summary_extra, wall=time.perf_counter() - t_start)
        except BaseException:
            if logger is not None:
                logger.close(discard=True)
            raise
        # the run is over: a signal now is held until the outputs are written
        with signals.catching(lambda: None):
            summary["plant"] = plant_kind
            if scenario.actuation_delay:
                summary["actuation_delay_steps"] = scenario.actuation_delay
            net_stats = getattr(ctrl, "network_stats", None)
            if net_stats is not None:
                summary["network"] = net_stats()
            summary.update(summary_extra or {})
            if logger is not None:
                try:
                    logger.outcome(summary)
                except BaseException:
                    logger.close(discard=True)
                    raise
                logger.close()   # a log that cannot be finished is removed, the error raised
            return finish_summary(summary, logger, log_path, summary_path)
    finally:
        if own_plant and p is not None:
            p.close()


def finish_summary(summary: dict, logger, log_path, summary_path) -> dict:
    """Adds the log's name and message counts to a run's summary and writes it (atomically)."""
    if log_path is not None:
        summary["log"] = str(log_path)
        summary["log_messages"] = dict(logger.counts)
    if summary_path is not None:
        write_json_atomic(summary_path, summary)
    return summary
