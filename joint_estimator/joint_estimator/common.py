"""
Shared types, input validation and track helpers of the joint estimator (pure numpy).

The estimator works on the relative track of link A in link B's frame: ``T[t] = ^B T_A(t)``, an
(N, 4, 4) array of rigid transforms (metres, radians), ``R[t] = ^B Theta_A(t)`` and
``p[t] = ^B t_A(t)`` in the chapter's notation (Section 4).
"""

from __future__ import annotations

from dataclasses import dataclass, field
import enum
from typing import Optional, Sequence

import numpy as np
# the batched rotation helpers live in stereo_manip_tools.transforms (the workspace's one home
# of rotation math); re-exported here for the estimator's modules
from stereo_manip_tools.transforms import minimal_rotations_onto, perpendicular_basis, \
    rotation_vectors, rotations_about_axis, signed_angles_about_axis

__all__ = [
    'JointType',
    'JOINT_DOF',
    'DegenerateMotionError',
    'JointFit',
    'validate_track',
    'check_unit_quaternion',
    'QUATERNION_NORM_TOLERANCE',
    'relative_track',
    'split_track',
    'compose_track',
    'rotations_about_axis',
    'rotation_vectors',
    'signed_angles_about_axis',
    'minimal_rotations_onto',
    'frame_residuals',
    'perpendicular_basis',
]


class JointType(enum.IntEnum):
    """Joint types; values equal the constants of ``stereo_manip_msgs/JointEstimate``."""

    FIXED = 0
    REVOLUTE = 1
    PRISMATIC = 2
    SPHERICAL = 3
    CYLINDRICAL = 4
    PLANAR = 5


#: Degrees of freedom (joint coordinates per frame) of each joint type.
JOINT_DOF = {
    JointType.FIXED: 0,
    JointType.REVOLUTE: 1,
    JointType.PRISMATIC: 1,
    JointType.SPHERICAL: 3,
    JointType.CYLINDRICAL: 2,
    JointType.PLANAR: 3,
}


class DegenerateMotionError(ValueError):
    """The motion does not determine the model (e.g. too small a rotation range for an axis)."""


@dataclass
class JointFit:
    """
    A fitted joint with its corrected track.

    Directions are unit vectors, points in metres. ``axis_in_a``/``axis_in_b`` are ``^A l`` and
    ``^B l`` (the plane normal for PLANAR, the sliding direction for PRISMATIC, zero for FIXED and
    SPHERICAL); ``point_in_a``/``point_in_b`` are ``^A c`` and ``^B c`` (the centre for SPHERICAL;
    for PRISMATIC ``point_in_b`` is the position of A's origin at joint coordinate 0 and
    ``point_in_a`` is zero; for PLANAR ``point_in_b`` is the foot of B's origin on the plane swept
    by A's origin and ``point_in_a`` is zero; zero for FIXED).

    :ivar corrected: (N, 4, 4) corrected relative poses ``^B T_A(t)`` satisfying the joint exactly.
    :ivar coordinates: (N, dof) joint coordinates: angle [rad] (REVOLUTE), displacement [m]
        (PRISMATIC), (angle, displacement) (CYLINDRICAL), (angle, u, v) (PLANAR, u and v along
        ``plane_basis``), rotation vector [rad] (SPHERICAL), nothing (FIXED).
    :ivar rotation_residuals: (N,) angle [rad] between each raw and corrected orientation.
    :ivar position_residuals: (N,) distance [m] between each raw and corrected position.
    :ivar chi2: (N,) per-frame squared residual normalised by the noise levels.
    :ivar inliers: (N,) bool, False for frames rejected as outliers.
    :ivar n_params: number of model parameters (without the per-frame coordinates).
    :ivar score: BIC (lower is better), NaN until scored by the model selection.
    :ivar repaired: (N,) bool, inlier frames whose pose was replaced by its ambiguous twin
        (:mod:`joint_estimator.ambiguity`); the residuals are those of the pose used.
    :ivar sigma_position: position noise scale [m] the residuals are normalised by (estimated
        from the data unless given); :ivar sigma_rotation: the same for orientations [rad].
    :ivar scale_estimated: True when the noise scales were estimated from the data.
    :ivar coordinate_range: ``(lo, hi)`` of the first joint coordinate over the inlier frames
        (unwrapped angle [rad] or displacement [m]); :ivar motion_range: the same over all
        frames (rejected ones projected on the joint); :ivar coverage: inlier span / motion
        span (1 when the motion has no span); NaN for types without a 1-d coordinate.
    :ivar axis_angle_std_in_a: 1-sigma axis direction uncertainty [rad] in A (and
        ``axis_angle_std_in_b`` in B), :ivar axis_point_std: 1-sigma uncertainty [m] of the
        axis position across the axis at ``point_in_b`` (first order, from the Jacobian of the
        refinement; revolute and cylindrical only, NaN otherwise).
    :ivar warnings: reasons not to trust the estimate (many rejected frames, inliers covering
        little of the motion, degenerate motion).
    """

    joint_type: JointType
    axis_in_a: np.ndarray
    axis_in_b: np.ndarray
    point_in_a: np.ndarray
    point_in_b: np.ndarray
    corrected: np.ndarray
    coordinates: np.ndarray
    rotation_residuals: np.ndarray
    position_residuals: np.ndarray
    chi2: np.ndarray
    inliers: np.ndarray
    n_params: int
    model: object = None
    degenerate: bool = False
    status: str = ''
    rotation_range: float = float('nan')
    translation_range: float = float('nan')
    score: float = float('nan')
    extra: dict = field(default_factory=dict)
    repaired: Optional[np.ndarray] = None
    sigma_position: float = float('nan')
    sigma_rotation: float = float('nan')
    scale_estimated: bool = False
    coordinate_range: tuple = (float('nan'), float('nan'))
    motion_range: tuple = (float('nan'), float('nan'))
    coverage: float = float('nan')
    axis_angle_std_in_a: float = float('nan')
    axis_angle_std_in_b: float = float('nan')
    axis_point_std: float = float('nan')
    warnings: list = field(default_factory=list)

    @property
    def repaired_indices(self) -> np.ndarray:
        """Return the indices (int array) of the frames whose ambiguous twin pose was used."""
        if self.repaired is None:
            return np.zeros(0, dtype=int)
        return np.flatnonzero(self.repaired)

    @property
    def dof(self) -> int:
        """Joint coordinates per frame."""
        return JOINT_DOF[self.joint_type]

    @property
    def outlier_indices(self) -> np.ndarray:
        """Return the indices (int array) of the frames rejected as outliers."""
        return np.flatnonzero(~self.inliers)

    @property
    def rotation_rms(self) -> float:
        """RMS rotation residual [rad] over the inlier frames."""
        return float(np.sqrt(np.mean(self.rotation_residuals[self.inliers] ** 2)))

    @property
    def position_rms(self) -> float:
        """RMS position residual [m] over the inlier frames."""
        return float(np.sqrt(np.mean(self.position_residuals[self.inliers] ** 2)))


#: A pose message's quaternion must have a norm within this of 1 (a producer normalises it;
#: float32 round-off is ~1e-7); norms like 2, 1e12 or 1e-12 mark a malformed message, which a
#: silent normalisation would let into the estimation window as a plausible pose.
QUATERNION_NORM_TOLERANCE = 0.01


def check_unit_quaternion(q: Sequence[float],
                          tolerance: float = QUATERNION_NORM_TOLERANCE) -> None:
    """
    Check that a quaternion ``q`` (x, y, z, w) of a pose message is (nearly) unit.

    :raises ValueError: naming the norm, when it is not finite or differs from 1 by more than
        ``tolerance``.
    """
    norm = float(np.linalg.norm(np.asarray(q, dtype=float)))
    if not np.isfinite(norm) or abs(norm - 1.0) > tolerance:
        raise ValueError(f'quaternion norm {norm:.6g} is not 1 (tolerance {tolerance:g}): '
                         'not a rotation')


def validate_track(poses: np.ndarray, stamps_ns: Optional[Sequence[int]] = None,
                   min_poses: int = 1, tol: float = 1e-5,
                   name: str = 'relative track') -> np.ndarray:
    """
    Check a pose track and return it as a float (N, 4, 4) array, raising ``ValueError``.

    :param poses: (N, 4, 4) rigid transforms.
    :param stamps_ns: optional (N,) stamps [ns]; they must be strictly increasing.
    :param min_poses: fewest poses the caller's model needs.
    :param tol: tolerance on ``R^T R = I`` and ``det R = 1``.
    :param name: what the track is, for the error message.
    :raises ValueError: wrong shape, too few poses, NaN/inf, a bad last row, a non-orthonormal
        rotation, stamps of the wrong length or out of order (the message names the frame).
    """
    T = np.asarray(poses, dtype=float)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ValueError(f'{name}: expected an (N, 4, 4) array of poses, got shape {T.shape}')
    n = T.shape[0]
    if n < min_poses:
        raise ValueError(f'{name}: {n} poses given, at least {min_poses} needed')
    bad = ~np.all(np.isfinite(T), axis=(1, 2))
    if bad.any():
        raise ValueError(f'{name}: pose {int(np.flatnonzero(bad)[0])} contains NaN or inf '
                         f'({int(bad.sum())} such poses)')
    bad = np.any(np.abs(T[:, 3] - np.array([0.0, 0.0, 0.0, 1.0])) > tol, axis=1)
    if bad.any():
        raise ValueError(f'{name}: pose {int(np.flatnonzero(bad)[0])} has last row '
                         f'{T[int(np.flatnonzero(bad)[0]), 3].tolist()}, not [0, 0, 0, 1]')
    R = T[:, :3, :3]
    err = np.abs(np.einsum('nji,njk->nik', R, R) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(R)
    bad = (err > tol) | (np.abs(det - 1.0) > tol)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f'{name}: rotation of pose {i} is not orthonormal with det +1 '
                         f'(max |R^T R - I| = {err[i]:.3g}, det = {det[i]:.6g}, tol {tol:g})')
    if stamps_ns is not None:
        s = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
        if s.shape[0] != n:
            raise ValueError(f'{name}: {s.shape[0]} stamps for {n} poses')
        d = np.diff(s)
        if np.any(d <= 0):
            i = int(np.flatnonzero(d <= 0)[0])
            raise ValueError(f'{name}: stamps out of order or repeated at pose {i + 1} '
                             f'({int(s[i + 1])} ns after {int(s[i])} ns)')
    return T


def relative_track(link_a: np.ndarray, link_b: np.ndarray) -> np.ndarray:
    """
    Relative track ``^B T_A = (^W T_B)^-1 ^W T_A`` from two tracks in a common frame W.

    :param link_a: (N, 4, 4) poses of link A in W.
    :param link_b: (N, 4, 4) poses of link B in W (same stamps as link A).
    :returns: (N, 4, 4) poses of A in B's frame.
    """
    A = np.asarray(link_a, dtype=float)
    B = np.asarray(link_b, dtype=float)
    if A.shape != B.shape:
        raise ValueError(f'link tracks differ in shape: A {A.shape}, B {B.shape}')
    Rb_t = np.transpose(B[:, :3, :3], (0, 2, 1))
    out = np.zeros_like(A)
    out[:, :3, :3] = Rb_t @ A[:, :3, :3]
    out[:, :3, 3] = np.einsum('nij,nj->ni', Rb_t, A[:, :3, 3] - B[:, :3, 3])
    out[:, 3, 3] = 1.0
    return out


def split_track(T: np.ndarray) -> tuple:
    """Rotations (N, 3, 3) and translations (N, 3) of an (N, 4, 4) track."""
    return T[:, :3, :3], T[:, :3, 3]


def compose_track(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(N, 4, 4) track from rotations (N, 3, 3) and translations (N, 3)."""
    T = np.zeros((R.shape[0], 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = p
    T[:, 3, 3] = 1.0
    return T


def frame_residuals(R: np.ndarray, p: np.ndarray, R_hat: np.ndarray, p_hat: np.ndarray,
                    sigma_position: float, sigma_rotation: float) -> tuple:
    """
    Per-frame residuals of a raw track about a corrected one.

    :returns: (rotation angle [rad] (N,), position distance [m] (N,), chi-square (N,)) where the
        chi-square is ``|log(R_hat R^T)|^2 / sigma_rotation^2 + |p_hat - p|^2 / sigma_position^2``.
    """
    rot = np.linalg.norm(rotation_vectors(np.einsum('nij,nkj->nik', R_hat, R)), axis=1)
    pos = np.linalg.norm(p_hat - p, axis=1)
    chi2 = (rot / sigma_rotation) ** 2 + (pos / sigma_position) ** 2
    return rot, pos, chi2
