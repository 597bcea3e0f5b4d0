"""Vehicles on se3sync's physics: the loopback MAVLink vehicle (`loopback`, `se3sync vehicle`)
and the flight-stack simulator servers (`sim_px4`: PX4's simulator MAVLink over TCP,
`sim_ardupilot`: ArduPilot's JSON SITL interface), which share the body, sensor and ground model
of `sim_body`; `sim_cli` is the `--sim-protocol` command. They depend on `bridge.mavlink`, never
on `bridge.swarm`."""
