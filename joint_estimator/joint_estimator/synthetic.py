"""
Synthetic joint motions with ground truth, for tests and benchmarks (pure numpy).

Relative tracks ``^B T_A(t)`` (N, 4, 4) [m] of random joints: random axis directions, axis points
and link offsets (A's origin up to ``offset_radius`` from the axis), joint coordinates spread
over a motion range; noise is added per axis (rotation vector ``N(0, sigma_rot^2 I)``
left-multiplied, position ``N(0, sigma_pos^2 I)``); outliers are tracking failures (pose jumps).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from joint_estimator.common import compose_track, JointType, perpendicular_basis, \
    rotations_about_axis
import numpy as np
from scipy.spatial.transform import Rotation

__all__ = ['SyntheticJoint', 'random_joint_motion', 'add_noise', 'add_outliers']


@dataclass
class SyntheticJoint:
    """Ground truth of a synthetic motion; unused fields are zero."""

    joint_type: JointType
    poses: np.ndarray              # (N, 4, 4) true relative track
    axis_in_a: np.ndarray
    axis_in_b: np.ndarray
    point_in_a: np.ndarray
    point_in_b: np.ndarray
    coordinates: np.ndarray        # (N, dof)


def _unit(rng) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def random_joint_motion(joint_type: JointType, n: int, rng: np.random.Generator,
                        rotation_range: float = np.deg2rad(90.0),
                        translation_range: float = 0.2,
                        offset_radius: float = 0.2) -> SyntheticJoint:
    """
    Random joint of ``joint_type`` and a motion of ``n`` poses.

    Revolute/cylindrical/planar angles: sorted uniform over ``rotation_range`` [rad] (the
    first and last at its ends); prismatic/cylindrical displacement and planar in-plane
    positions over ``translation_range`` [m]; spherical: rotation vectors uniform in a ball of
    radius ``rotation_range / 2``.
    """
    jt = JointType(joint_type)
    R0 = Rotation.random(random_state=rng).as_matrix()
    zero = np.zeros(3)

    def spread(width):
        u = np.sort(rng.uniform(0.0, 1.0, n))
        u[0], u[-1] = 0.0, 1.0
        return (u - 0.5) * width

    def angles():
        u = np.sort(rng.uniform(0.0, 1.0, n))
        u[0], u[-1] = 0.0, 1.0
        return rng.uniform(-np.pi, np.pi) + u * rotation_range

    if jt == JointType.FIXED:
        t = rng.uniform(-offset_radius, offset_radius, 3)
        T = compose_track(np.broadcast_to(R0, (n, 3, 3)), np.broadcast_to(t, (n, 3)))
        return SyntheticJoint(jt, T, zero, zero, zero, zero, np.zeros((n, 0)))
    if jt == JointType.PRISMATIC:
        d = _unit(rng)
        c = rng.uniform(-offset_radius, offset_radius, 3)
        s = spread(translation_range)
        T = compose_track(np.broadcast_to(R0, (n, 3, 3)), c + np.outer(s, d))
        return SyntheticJoint(jt, T, R0.T @ d, d, zero, c, s[:, None])
    if jt == JointType.SPHERICAL:
        ca = _unit(rng) * rng.uniform(0.3, 1.0) * offset_radius
        cb = rng.uniform(-offset_radius, offset_radius, 3)
        w = np.stack([_unit(rng) for _ in range(n)]) * (
            rotation_range / 2.0 * np.cbrt(rng.uniform(0.0, 1.0, (n, 1))))
        R = Rotation.from_rotvec(w).as_matrix() @ R0
        T = compose_track(R, cb - R @ ca)
        return SyntheticJoint(jt, T, zero, zero, ca, cb, w)
    lb = _unit(rng)
    la = R0.T @ lb
    q = angles()
    Rq = rotations_about_axis(lb, q) @ R0
    if jt == JointType.PLANAR:
        e1, e2 = perpendicular_basis(lb)
        h = rng.uniform(-offset_radius, offset_radius)
        uv = rng.uniform(-translation_range / 2, translation_range / 2, (n, 2))
        T = compose_track(Rq, h * lb + np.outer(uv[:, 0], e1) + np.outer(uv[:, 1], e2))
        return SyntheticJoint(jt, T, la, lb, zero, h * lb, np.column_stack([q, uv]))
    # point on the axis in A at distance up to offset_radius from A's origin
    ca = rng.uniform(-offset_radius, offset_radius, 3)
    cb = rng.uniform(-offset_radius, offset_radius, 3)
    p = cb - Rq @ ca
    if jt == JointType.REVOLUTE:
        return SyntheticJoint(jt, compose_track(Rq, p), la, lb, ca, cb, q[:, None])
    s = spread(translation_range)
    return SyntheticJoint(jt, compose_track(Rq, p + np.outer(s, lb)), la, lb, ca, cb,
                          np.column_stack([q, s]))


def add_noise(poses: np.ndarray, sigma_position: float, sigma_rotation: float,
              rng: np.random.Generator) -> np.ndarray:
    """
    Noisy copy of a track.

    ``R <- exp([e]x) R``, ``e ~ N(0, sigma_rotation^2 I)`` [rad]; ``p <- p + N(0, sigma_position^2
    I)`` [m].
    """
    n = poses.shape[0]
    E = Rotation.from_rotvec(rng.normal(0.0, sigma_rotation, (n, 3))).as_matrix()
    return compose_track(E @ poses[:, :3, :3],
                         poses[:, :3, 3] + rng.normal(0.0, sigma_position, (n, 3)))


def add_outliers(poses: np.ndarray, fraction: float, rng: np.random.Generator,
                 min_angle: float = np.deg2rad(20.0), max_angle: float = np.deg2rad(60.0),
                 min_jump: float = 0.05, max_jump: float = 0.2,
                 count: Optional[int] = None) -> tuple:
    """
    Replace ``fraction`` of the frames by tracking failures.

    The pose rotated by a random angle in [min_angle, max_angle] about a random axis and moved by
    [min_jump, max_jump] m.

    :returns: ``(track, outlier mask (N,) bool)``.
    """
    n = poses.shape[0]
    k = int(round(fraction * n)) if count is None else count
    idx = rng.choice(n, size=k, replace=False)
    out = poses.copy()
    for i in idx:
        w = _unit(rng) * rng.uniform(min_angle, max_angle)
        out[i, :3, :3] = Rotation.from_rotvec(w).as_matrix() @ out[i, :3, :3]
        out[i, :3, 3] += _unit(rng) * rng.uniform(min_jump, max_jump)
    mask = np.zeros(n, bool)
    mask[idx] = True
    return out, mask
