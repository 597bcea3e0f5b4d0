"""MAVLink 2 hardware-in-the-loop bridge and the loopback test vehicle (see docs/guide/hardware.md).

Public API (imported lazily by the command line; import the submodules directly):

* ``bridge.config.parse_bridge(table, n_agents) -> BridgeConfig`` -- the scenario's [bridge] table;
* ``bridge.plant.MavlinkPlant(scenario, config=None, ...)`` -- the cosim Plant over MAVLink
  (``connect()`` first; ``ConnectError``, ``LinkError``);
* ``bridge.transport.QuantizedPlant(scenario)`` -- the bit-faithful reference for lockstep HIL;
* ``bridge.mapping.FleetMapping`` -- wrench <-> actuator controls (direct, allocation);
* ``bridge.vehicle.VehicleServer`` -- the loopback vehicles;
* ``bridge.hil.run_hil(scenario, plant, ...)`` -- cosim's Master over a connected MavlinkPlant.
"""
