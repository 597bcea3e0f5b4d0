"""The compiled entry points other packages may call (the kernels themselves are private).

* ``network_step(S, theta, edges, P, h, hybrid, u, mu, jumped, theta_prev, theta_jump)``: the law
  (`ex_controller`) for every agent at one communication point; returns the number of jumps.
* ``network_U(S, theta, edges, P, out)``: U(X̄_k, θ_k) (`U_explicit`) for every edge.
* ``metrics(S, edges, U, k_X, masses, J, rot_err, pos_err, quat)``: ‖I − R̄_k‖_F, ‖p̄_k‖, the
  agents' quaternions (x, y, z, w) and (V̄, max|ξ|) (`V_def`).
* ``delayed_network_step(...)``: the law per agent when neighbour data arrives over delayed,
  lossy links (`cosim.network` drives it; its docstring states the arguments).
* ``rot_to_quat_rows(R9, out)``: quaternions (w, x, y, z) of row-major rotation matrices.
* ``relative_pose(A, i, B, j, R, p)``: X̄ = X_j⁻¹X_i into R (3, 3) and p (3,), X_i from row i of
  A and X_j from row j of B (the network step's own products).

``P`` is ``LawParameters.P``; S follows `controller.layout`; ``edges`` is ``Graph.edges``
(0-based, (M, 2)). All arrays are C-contiguous float64 (edges int64) and outputs are written in
place, so a caller can keep its buffers across calls.
"""
from ._kernels import (delayed_network_step, metrics, network_step, network_U, relative_pose,
                       rot_to_quat_rows)

__all__ = ["network_step", "delayed_network_step", "network_U", "metrics", "rot_to_quat_rows",
           "relative_pose"]
