"""Control laws beyond the paper's, each added through the seams of `cosim.controllers` only: its
module here, one line in `cosim.registry.LAWS`, its tests (docs/architecture.md, "Adding a law").
The paper's hybrid law and its gradient baseline live in `controller` (the mathematics) and
`cosim.controllers` (their capabilities)."""
