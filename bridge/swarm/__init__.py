"""The distributed agents: one vehicle's controller as its own process (`agent`, `se3sync
agent`), the checked inter-agent link that carries neighbours' poses, velocities and θ
(`agent_link`), and the launcher that starts and merges a swarm (`launcher`, `se3sync swarm`).
They depend on `bridge.mavlink`, never on `bridge.vehicles`."""
