"""`run_scenario`: one run of a scenario, from its file to its log and summary — the library entry
point that `se3sync run`, `se3sync connect` and other packages call."""
from __future__ import annotations

from . import signals
from .controllers import law_name, make_controller
from .files import write_json_atomic
from .log.mcap import McapLogger
from .master import Master
from .network import networked
from .plants import make_plant
from .scenario import Scenario, load_scenario, with_timing

__all__ = ["run_scenario", "with_timing", "finish_summary", "write_json_atomic"]


def run_scenario(scenario, *, plant="fleet", controller="hybrid", log_path=None,
                 summary_path=None, duration=None, step=None, progress=False,
                 fmu_path=None, log_metadata=None, summary_extra=None,
                 log_encoding="json") -> dict:
    """Runs a scenario (a Scenario or a path to a TOML file) and returns the summary dict.

    plant: a registered plant name (`cosim.registry.PLANTS`) or a Plant instance (closed by
    the caller); fmu_path: the FMU an FMU plant loads; controller: a registered law name
    (`cosim.registry.LAWS`) or a controller instance. log_path: MCAP written
    (streamed) there, its per-record channels in log_encoding ("json" or "cdr"); summary_path: summary JSON written atomically. log_metadata adds to (or
    overrides) the MCAP metadata record, summary_extra to the summary. On Ctrl-C or SIGTERM the
    run stops cleanly, the log is finished and the summary has "interrupted": true. A run that
    fails (an exception) removes its log: no output is better than one that looks whole.
    """
    if not isinstance(scenario, Scenario):
        scenario = load_scenario(scenario)
    scenario = with_timing(scenario, duration, step)
    own_plant = isinstance(plant, str)
    plant_kind = plant if own_plant else type(plant).__name__
    ctrl = make_controller(controller, scenario) if isinstance(controller, str) else controller
    ctrl = networked(scenario, ctrl)  # the law per agent over the [network] links, if any
    ctrl_kind = law_name(ctrl)
    options = {} if fmu_path is None else {"fmu_path": fmu_path}   # an FMU plant's option
    p = make_plant(plant, scenario, **options) if own_plant else plant
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
