"""The MAVLink link and plant: sockets, framing, signing and counters (`link`, `signing_state`),
the `[bridge]` table (`config`), frames and the wire rows (`frames`, `transport`, `state`), the
wrench-to-actuator mapping and the airframe presets (`mapping`, `airframes`), the output
profiles (`output`), and `MavlinkPlant`, the cosim `Plant` over UDP, with `hil.run_hil` (`plant`,
`hil`). Import the submodules directly; this package imports nothing, so a submodule loads only
what it needs."""
