"""Hardware in the loop: cosim's one master loop over a connected `MavlinkPlant`."""
from __future__ import annotations

from cosim.master import Master
from cosim.plants import make_plant
from cosim.run import run_scenario

__all__ = ["warm_up", "run_hil"]


def warm_up(scenario, controller: str = "hybrid") -> None:
    """Two co-simulation steps of the scenario on its registered plant (``plant.mode``): JIT
    compilation of the controller and metrics, so that the first control steps over the links
    are on time."""
    p = make_plant(scenario.plant_mode, scenario)
    try:
        Master(scenario, p, controller).run(2)
    finally:
        p.close()


def run_hil(scenario, plant, *, log_path=None, summary_path=None, progress=False,
            controller="hybrid", log_encoding: str = "json", live=None) -> dict:
    """cosim's run over a connected MavlinkPlant; the MCAP log says the time base is the wall
    clock (t = n·h, paced) or lockstep. live: (host, port, rate) of a live view, or None."""
    tb = "simulated (lockstep)" if plant.lockstep else "wall (paced: t = n·h from the start of the run)"
    return run_scenario(
        scenario, plant=plant, controller=controller, log_path=log_path,
        summary_path=summary_path, progress=progress, log_encoding=log_encoding, live=live,
        log_metadata={"plant": "mavlink", "time_base": tb,
                      "endpoints": ",".join(v.sock.endpoint for v in plant.vehicles)},
        summary_extra={"plant": "mavlink", "lockstep": bool(plant.lockstep)})
