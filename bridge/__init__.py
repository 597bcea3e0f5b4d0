"""MAVLink 2 hardware-in-the-loop bridge and the loopback test vehicle (see docs/guide/hardware.md).

Public API (imported lazily by the command line; import the submodules directly):

* ``bridge.mavlink.config.parse_bridge(table, n_agents) -> BridgeConfig`` -- the scenario's [bridge] table;
* ``bridge.mavlink.plant.MavlinkPlant(scenario, config=None, ...)`` -- the cosim Plant over MAVLink
  (``connect()`` first; ``ConnectError``, ``LinkError``);
* ``bridge.mavlink.transport.QuantizedPlant(scenario)`` -- the bit-faithful reference for lockstep HIL;
* ``bridge.mavlink.mapping.FleetMapping`` -- wrench <-> actuator controls (direct, allocation);
* ``bridge.vehicles.loopback.VehicleServer`` -- the loopback vehicles;
* ``bridge.mavlink.hil.run_hil(scenario, plant, ...)`` -- cosim's Master over a connected MavlinkPlant.
"""
