"""
Non-linear vision error correction (step 1 of Section 3; after Takamatsu et al. 2007).

From the observed pose, find a nearby pose of the moving object at which every pair of the
contact relation has zero distance. As the chapter says, any such configuration is accepted:
this step does not care where the correction goes along the unconstrained directions (which it
"often contaminates"); the optimal step (:mod:`.optimal_correction`) removes that.

Method: Gauss-Newton on the signed distances with minimum-norm steps, the Jacobian rows being
Eq. 2 rows ``[p x f, f]`` (exact at contact). Steps are screws ``[w, v]`` applied to the moving
object in the fixed frame, ``x -> R(w) x + v``; the minimum-norm step uses the metric
``|v|^2 + (L |w|)^2`` with ``L`` the moving object's size, so that the result is the feasible
pose closest to the observation in that metric (to first order), ``L`` = a quarter of the
bounding-box diagonal by default.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from stereo_manip_tools.transforms import rotation_about_axis, rotation_log

from .contact_relation import ContactEvaluator, ContactPair
from .polyhedron import cross3, Polyhedron

__all__ = ['NonlinearResult', 'correct_nonlinear', 'apply_screw', 'constraint_rows',
           'RESIDUAL_TOLERANCE']

#: The one contact residual tolerance [m] of the package: the non-linear step stops there and
#: every later check (optimal step, acceptance in correct_pose) uses the same value.
RESIDUAL_TOLERANCE = 1e-9


@dataclass
class NonlinearResult:
    """
    Outcome of :func:`correct_nonlinear`.

    :ivar T_rel: corrected pose of the moving object in the fixed frame (4x4).
    :ivar max_residual: largest |distance| of the relation at ``T_rel`` [m].
    :ivar iterations: Gauss-Newton iterations used.
    :ivar converged: True when ``max_residual <= residual_tolerance``.
    """

    T_rel: np.ndarray
    max_residual: float
    iterations: int
    converged: bool


def apply_screw(T: np.ndarray, w: np.ndarray, v: np.ndarray) -> np.ndarray:
    """
    Move a pose by the finite screw ``x -> R(w) x + v`` in its parent frame.

    :param T: 4x4 pose.
    :param w: rotation vector [rad], shape (3,).
    :param v: translation [m], shape (3,).
    """
    angle = float(np.linalg.norm(w))
    Rw = rotation_about_axis(w, angle) if angle > 0 else np.eye(3)
    out = np.eye(4)
    out[:3, :3] = Rw @ T[:3, :3]
    out[:3, 3] = Rw @ T[:3, 3] + v
    return out


def constraint_rows(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Rows ``[p x f, f]`` of Eq. 2 (screw order ``[s0, s1]``), shape (K, 6)."""
    P = np.asarray(points, dtype=float).reshape(-1, 3)
    F = np.asarray(normals, dtype=float).reshape(-1, 3)
    return np.hstack([cross3(P, F), F])


def correct_nonlinear(moving: Polyhedron, fixed: Polyhedron, T_rel_observed: np.ndarray,
                      pairs: Sequence[ContactPair], max_iterations: int = 30,
                      residual_tolerance: float = RESIDUAL_TOLERANCE,
                      length_scale: float | None = None, rcond: float = 1e-6,
                      anchor_schedule: tuple = (3e-2, 3e-3)) -> NonlinearResult:
    """
    Nearby pose satisfying every contact of ``pairs`` (non-linear step, Takamatsu 2007).

    :param T_rel_observed: observed pose of the moving object in the fixed frame (4x4).
    :param pairs: the contact relation to satisfy.
    :param residual_tolerance: the result is ``converged`` when every |distance| is below
        this [m]; the iteration itself continues to 1e-3 of it (Gauss-Newton converges
        quadratically, so the last steps cost little and leave the optimal step an exact
        start).
    :param length_scale: ``L`` of the step metric [m] (default: a quarter of the moving
        object's bounding-box diagonal, about its radius). A larger ``L`` makes rotations
        expensive and can send the solution to a distant, degenerate configuration (a peg
        just inside a hole pulled up to the rim, where it may tilt).
    :param rcond: relative singular-value cut-off of the final Gauss-Newton steps.
    :param anchor_schedule: decreasing weights of the pull towards the observed pose in the
        Levenberg-Marquardt stages run before Gauss-Newton (scaled units).
    :param max_iterations: iteration limit per stage.
    :returns: the corrected pose; ``converged`` is False when the relation could not be
        satisfied within the iteration limit (e.g. a relation that no pose realises).
    """
    T_obs = np.array(T_rel_observed, dtype=float)
    T = T_obs.copy()
    if not pairs:
        return NonlinearResult(T, 0.0, 0, True)
    L = float(length_scale) if length_scale else max(moving.size / 4.0, 1e-6)
    scale = np.array([1.0 / L] * 3 + [1.0] * 3)
    best = None
    it = 0
    evaluate = ContactEvaluator(moving, fixed, pairs)
    # Levenberg-Marquardt anchored at the observation, with continuation of the anchor weight
    # mu -> 0, then plain Gauss-Newton. Directions that are free at the solution (sliding
    # along a hole) look weakly constrained at a noisy, tilted pose; the anchor keeps the
    # iterate from drifting along them (to a degenerate configuration) while the well
    # constrained directions converge.
    for mu in tuple(anchor_schedule) + (0.0,):
        first = None
        for k in range(max_iterations if mu == 0.0 else min(max_iterations, 8)):
            g = evaluate(T)
            res = float(np.max(np.abs(g.distances)))
            if mu == 0.0 and (best is None or res < best[1]):
                best = (T.copy(), res, it)
            if mu == 0.0 and res <= 1e-3 * residual_tolerance:
                break       # converged well past the acceptance tolerance (quadratic steps)
            J = constraint_rows(g.points, g.normals) * scale
            if mu > 0.0:
                e = np.concatenate([L * rotation_log(T[:3, :3] @ T_obs[:3, :3].T),
                                    T[:3, 3] - T_obs[:3, 3]])
                J = np.vstack([J, mu * np.eye(6)])
                rhs = np.concatenate([-g.distances, -mu * e])
                step, *_ = np.linalg.lstsq(J, rhs, rcond=None)
            else:
                # truncated SVD: drop singular values below rcond x the largest
                step, *_ = np.linalg.lstsq(J, -g.distances, rcond=rcond)
            it += 1
            step *= scale
            # damp very large rotation steps (far from the solution)
            ang = np.linalg.norm(step[:3])
            if ang > 0.3:
                step *= 0.3 / ang
            T = apply_screw(T, step[:3], step[3:])
            size = float(np.linalg.norm(step / scale))
            first = size if first is None else first
            if mu > 0.0 and size < 1e-2 * first:
                break   # close enough to this stage's anchored optimum
    T_best, res_best, it_best = best
    return NonlinearResult(T_best, res_best, it_best, res_best <= residual_tolerance)
