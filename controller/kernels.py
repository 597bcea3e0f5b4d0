"""The compiled entry points other packages may call (the kernels themselves are private).

* ``network_step(S, theta, edges, P, h, hybrid, u, mu, jumped, theta_prev, theta_jump)``: the law
  (`ex_controller`) for every agent at one communication point; returns the number of jumps.
* ``network_U(S, theta, edges, P, out)``: U(X̄_k, θ_k) (`U_explicit`) for every edge.
* ``metrics(S, edges, U, k_X, masses, J, rot_err, pos_err, quat)``: ‖I − R̄_k‖_F, ‖p̄_k‖, the
  agents' quaternions (x, y, z, w) and (V̄, max|ξ|) (`V_def`).
* ``rot_to_quat_rows(R9, out)``: quaternions (w, x, y, z) of row-major rotation matrices.
* ``relative_pose(A, i, B, j, R, p)``: X̄ = X_j⁻¹X_i into R (3, 3) and p (3,), X_i from row i of
  A and X_j from row j of B (the network step's own products).

The per-edge pieces of the network step, for compiled code elsewhere that evaluates the law on
other data (`cosim.network_step`: each agent on its neighbours' delayed samples), inlined into
the caller: ``rel_pose_rows(A, i, B, j)`` (X̄ as (R̄ 9-tuple, p̄ 3-tuple)), ``edge_update(R̄, p̄,
θ, hybrid, P, h)`` (jump, ψ̄_∇, Ad⁻ᵀψ̄_∇ and the flow of θ), ``prepare(R̄, θ, P)``,
``gradient_core(R̄, p̄, θ, P, R_a, R_g)`` and ``Ad_inv_T(R̄, p̄, g)``; ``P_KX``, ``P_KXI``,
``P_KE`` are the offsets of k_X, k_ξ, k_e in P; ``quat_of(r00, …, r22)`` the quaternion (w, x,
y, z) of a rotation matrix, as `rot_to_quat_rows` computes it (the MAVLink encoder's).

The per-agent view (`controller._agent_kernels`): ``agent_step(S, ea, eb, owned, nbr, mode,
hybrid, P, h, stages, failsafe, theta, theta_rx, theta_prev, theta_jump, mu, jumped, term, rel,
u)``, agent i's law over its neighbourhood's edges at one communication point (the agent
process's step; ``FRESH`` is the age rule's verdict it computes with), and the one-edge pieces
`AgentStepper` calls, from the same cores: ``edge_term``, ``edge_flow``, ``wrench_sum``.

``P`` is ``LawParameters.P``; S follows `controller.layout`; ``edges`` is ``Graph.edges``
(0-based, (M, 2)). All arrays are C-contiguous float64 (edges int64) and outputs are written in
place, so a caller can keep its buffers across calls.
"""
from ._agent_kernels import FRESH, agent_step, edge_flow, edge_term, wrench_sum
from ._kernels import (P_KE, P_KX, P_KXI, Ad_inv_T, edge_update, gradient_core, metrics,
                       network_step, network_U, prepare, quat_of, rel_pose_rows, relative_pose,
                       rot_to_quat_rows)

__all__ = ["network_step", "network_U", "metrics", "rot_to_quat_rows", "relative_pose",
           "rel_pose_rows", "edge_update", "prepare", "gradient_core", "Ad_inv_T", "P_KX",
           "P_KXI", "P_KE", "agent_step", "FRESH", "edge_term", "edge_flow", "wrench_sum",
           "quat_of"]
