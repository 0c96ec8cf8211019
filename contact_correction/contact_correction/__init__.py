"""
Vision error correction with contact relations between polyhedra.

Vision error correction with contact relations between polyhedra (non-linear step, then the
linear optimum of Eqs. 2-9).

Modules (pure numpy / scipy / numba, no rclpy, except the node):

* :mod:`.polyhedron` -- closed polyhedra from OBJ / PLY / STL, coplanar faces merged, edges
  with convexity, non-convex solids;
* :mod:`.contact_relation` -- :func:`detect_contact_relation`, contact distances, penetration;
* :mod:`.nonlinear_correction` -- nearby pose meeting every contact (Takamatsu et al. 2007);
* :mod:`.optimal_correction` -- Eq. 2 / Eq. 3 constraints and ranks, Eqs. 4-9, a general
  numerical rule for other rank-1 relations, translation restricted to the constraints;
* :mod:`.correction` -- :func:`correct_pose`, the guarded one-call pipeline;
* :mod:`.trajectory` -- whole tracks;
* :mod:`.contact_correction_node`, :mod:`.offline` -- the ROS node and the
  ``correct_trajectory`` command.
"""
