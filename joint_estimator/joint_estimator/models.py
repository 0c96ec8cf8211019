"""
Fixed, prismatic, spherical, cylindrical and planar joints (Takamatsu 2004; Sturm et al.).

Every model is fitted from the relative track ``^B Theta_A(t)`` (N, 3, 3), ``^B t_A(t)`` (N, 3)
[m] and projects a track onto itself with :meth:`project`, which returns the corrected track
(satisfying the joint exactly) and the joint coordinates; the projection minimises, per frame,
``(3 - Tr(hat R R^T)) / sigma_rot^2 + |hat p - p|^2 / sigma_pos^2`` (chordal orientation
distance, ~ squared angle), in closed form for every type. The revolute joint lives in
:mod:`joint_estimator.revolute`.

Parameters (``n_params``, the count used by the model selection): fixed 6 (a pose), revolute 9
(axis line in B: 4, pose of A at angle 0 modulo the motion: 5), prismatic 7 (orientation 3,
direction 2, line 2), cylindrical 8, spherical 6 (the centre in A and in B), planar 5 (normal
in A and in B, offset).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Dict, Tuple

from joint_estimator.common import (
    DegenerateMotionError, JointType, minimal_rotations_onto, perpendicular_basis,
    rotation_vectors, rotations_about_axis)
from joint_estimator.revolute import (
    axis_directions_or_raise, AxisLineModel, DEFAULT_MIN_ROTATION_RANGE, fit_axis_directions,
    fit_revolute, ml_angles, rotation_range_from_singular_values, solve_axis_points)
import numpy as np

__all__ = [
    'DEFAULT_MIN_TRANSLATION_RANGE',
    'FixedModel',
    'PrismaticModel',
    'SphericalModel',
    'CylindricalModel',
    'PlanarModel',
    'fit_fixed',
    'fit_prismatic',
    'fit_spherical',
    'fit_cylindrical',
    'fit_planar',
    'fit_model',
    'MIN_SAMPLES',
]

#: Smallest equivalent translation range [m] that defines a sliding direction.
DEFAULT_MIN_TRANSLATION_RANGE = 0.02


def _mean_rotation(R: np.ndarray) -> np.ndarray:
    """Chordal L2 mean of rotations (N, 3, 3): projection of their sum onto SO(3)."""
    U, _, Vt = np.linalg.svd(R.sum(axis=0))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    return U @ D @ Vt


def _canonical(v: np.ndarray) -> np.ndarray:
    return -v if v[int(np.argmax(np.abs(v)))] < 0 else v


@dataclass
class FixedModel:
    """Rigid connection: ``^B T_A`` constant (``rotation``, ``translation`` [m])."""

    rotation: np.ndarray
    translation: np.ndarray
    joint_type: JointType = JointType.FIXED
    n_params: int = 6

    def project(self, R, p, sigma_position, sigma_rotation):
        n = R.shape[0]
        return (np.broadcast_to(self.rotation, (n, 3, 3)).copy(),
                np.broadcast_to(self.translation, (n, 3)).copy(), np.zeros((n, 0)))


def fit_fixed(R: np.ndarray, p: np.ndarray, **_) -> FixedModel:
    """Fit a fixed joint: chordal mean orientation and mean position."""
    return FixedModel(_mean_rotation(R), p.mean(axis=0))


@dataclass
class PrismaticModel:
    """Sliding joint: orientation constant, ``p(s) = point_in_b + s axis_in_b``."""

    rotation: np.ndarray
    axis_in_b: np.ndarray
    point_in_b: np.ndarray
    translation_range: float = float('nan')
    joint_type: JointType = JointType.PRISMATIC
    n_params: int = 7

    @property
    def axis_in_a(self) -> np.ndarray:
        return self.rotation.T @ self.axis_in_b

    @property
    def point_in_a(self) -> np.ndarray:
        return np.zeros(3)

    def project(self, R, p, sigma_position, sigma_rotation):
        n = R.shape[0]
        s = (p - self.point_in_b) @ self.axis_in_b
        return (np.broadcast_to(self.rotation, (n, 3, 3)).copy(),
                self.point_in_b + np.outer(s, self.axis_in_b), s[:, None])


def _principal_axes(p: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    c = p.mean(axis=0)
    evals, evecs = np.linalg.eigh((p - c).T @ (p - c) / p.shape[0])
    return c, evals[::-1], evecs[:, ::-1]


def fit_prismatic(R: np.ndarray, p: np.ndarray,
                  min_translation_range: float = DEFAULT_MIN_TRANSLATION_RANGE,
                  **_) -> PrismaticModel:
    """
    Prismatic joint.

    Mean orientation; line through the mean position along the principal direction of the
    positions.

    :raises DegenerateMotionError: equivalent translation range ``sqrt(12 (l1 - l2))`` (l: the
        position covariance eigenvalues) below ``min_translation_range`` [m].
    """
    c, evals, evecs = _principal_axes(p)
    rng = float(np.sqrt(12.0 * max(0.0, evals[0] - evals[1])))
    if rng < min_translation_range or p.shape[0] < 2:
        raise DegenerateMotionError(
            f'translation range {rng * 1000:.1f} mm is below {min_translation_range * 1000:.1f}'
            ' mm: the motion does not define a sliding direction')
    return PrismaticModel(_mean_rotation(R), _canonical(evecs[:, 0]), c, rng)


@dataclass
class SphericalModel:
    """Ball joint: ``^B c = Theta(t) ^A c + t(t)`` for every frame, orientation free."""

    point_in_a: np.ndarray
    point_in_b: np.ndarray
    degenerate: bool = False
    status: str = ''
    joint_type: JointType = JointType.SPHERICAL
    n_params: int = 6

    def project(self, R, p, sigma_position, sigma_rotation):
        """
        Weighted Procrustes per frame.

        Maximise ``Tr(hat R B)`` with ``B = R^T / s_r^2 - 2 ^A c (p - ^B c)^T / s_p^2``; positions
        from the centre.
        """
        d = p - self.point_in_b
        B = (np.transpose(R, (0, 2, 1)) / sigma_rotation ** 2
             - 2.0 * np.einsum('i,nj->nij', self.point_in_a, d) / sigma_position ** 2)
        U, _, Vt = np.linalg.svd(B)
        V = np.transpose(Vt, (0, 2, 1))
        Ut = np.transpose(U, (0, 2, 1))
        det = np.sign(np.linalg.det(V @ Ut))
        V[:, :, 2] *= det[:, None]
        R_hat = V @ Ut
        p_hat = self.point_in_b - R_hat @ self.point_in_a
        return R_hat, p_hat, rotation_vectors(R_hat)


def fit_spherical(R: np.ndarray, p: np.ndarray, **_) -> SphericalModel:
    """
    Ball joint.

    Eq. (18)'s least squares with the raw orientations, ``[-Theta(t) I] (^A c; ^B c) = t(t)``,
    minimum norm by SVD. If the rotations span a single axis (or none) the centre is not unique:
    the model is flagged degenerate.
    """
    ca, cb, rank, _ = solve_axis_points(R, p, rcond=1e-6)
    status = '' if rank == 6 else (f'spherical: centre not unique (rank {rank} of 6), '
                                   'minimum-norm centre returned')
    return SphericalModel(ca, cb, rank < 6, status)


@dataclass
class CylindricalModel(AxisLineModel):
    """
    Rotation about and translation along one line.

    ``^B l = Theta ^A l`` and ``^B c + s ^B l = Theta ^A c + t`` for some s per frame.
    """

    joint_type: JointType = JointType.CYLINDRICAL
    n_params: int = 8

    def project(self, R, p, sigma_position, sigma_rotation):
        q = ml_angles(R, p, self.axis_in_b, self.reference, self.point_in_a, self.point_in_b,
                      sigma_position, sigma_rotation, slide=True)
        R_hat = rotations_about_axis(self.axis_in_b, q) @ self.reference
        base = self.point_in_b - R_hat @ self.point_in_a
        s = (p - base) @ self.axis_in_b
        return R_hat, base + np.outer(s, self.axis_in_b), np.stack([q, s], axis=1)


def fit_cylindrical(R: np.ndarray, p: np.ndarray,
                    min_rotation_range: float = DEFAULT_MIN_ROTATION_RANGE,
                    **_) -> CylindricalModel:
    """
    Cylindrical joint.

    Directions by Eq. (17) (closed form), orientations corrected as for the revolute joint, then
    the line from ``P (^B c - hat Theta ^A c - t) = 0`` (``P = I - ^B l ^B l^T``) by SVD minimum
    norm (rank 4 of 6).

    :raises DegenerateMotionError: rotation range below ``min_rotation_range`` [rad].
    """
    a, b, R_hat, rng = axis_directions_or_raise(R, min_rotation_range, 'cylindrical')
    P = np.eye(3) - np.outer(b, b)
    PR = P @ R_hat                                   # (N, 3, 3)
    AtA = np.zeros((6, 6))
    AtA[:3, :3] = np.einsum('nki,nkj->ij', PR, PR)
    AtA[:3, 3:] = -np.sum(np.transpose(PR, (0, 2, 1)), axis=0) @ P
    AtA[3:, :3] = AtA[:3, 3:].T
    AtA[3:, 3:] = R.shape[0] * P
    Pp = p @ P
    Atb = np.concatenate([-np.einsum('nki,nk->i', PR, Pp), Pp.sum(axis=0)])
    U, Sv, Vt = np.linalg.svd(AtA)
    keep = Sv > 1e-9 * Sv[0]
    x = Vt[keep].T @ ((U[:, keep].T @ Atb) / Sv[keep])
    R0 = minimal_rotations_onto(a[None], b)[0]
    return CylindricalModel(a, b, x[:3], x[3:], R0, rng)


@dataclass
class PlanarModel:
    """
    Planar joint.

    Rotation about the plane normal (``^B n = Theta ^A n``) and translation in the plane ``^B n . t
    = offset``.
    """

    axis_in_a: np.ndarray
    axis_in_b: np.ndarray
    offset: float
    reference: np.ndarray
    rotation_range: float = float('nan')
    degenerate: bool = False
    status: str = ''
    joint_type: JointType = JointType.PLANAR
    n_params: int = 5

    @property
    def point_in_b(self) -> np.ndarray:
        return self.offset * self.axis_in_b

    @property
    def point_in_a(self) -> np.ndarray:
        return np.zeros(3)

    @property
    def plane_basis(self) -> tuple:
        return perpendicular_basis(self.axis_in_b)

    def project(self, R, p, sigma_position, sigma_rotation):
        n = self.axis_in_b
        q = ml_angles(R, p, n, self.reference, np.zeros(3), np.zeros(3), None, sigma_rotation,
                      slide=False)
        R_hat = rotations_about_axis(n, q) @ self.reference
        p_hat = p - np.outer(p @ n - self.offset, n)
        e1, e2 = self.plane_basis
        return R_hat, p_hat, np.stack([q, p_hat @ e1, p_hat @ e2], axis=1)


def fit_planar(R: np.ndarray, p: np.ndarray,
               min_rotation_range: float = DEFAULT_MIN_ROTATION_RANGE, **_) -> PlanarModel:
    """
    Planar joint.

    The normal from Eq. (17) when the rotation range defines it, otherwise the least-variance
    direction of the positions (flagged degenerate if the positions do not span a plane either);
    offset = mean of ``^B n . t``.
    """
    a, b, S = fit_axis_directions(R)
    rng = rotation_range_from_singular_values(S)
    status, degenerate = '', False
    if rng < min_rotation_range:
        _, evals, evecs = _principal_axes(p)
        b = _canonical(evecs[:, 2])
        a = _mean_rotation(R).T @ b
        if evals[1] - evals[2] <= 1e-6 * max(evals[0], 1e-300) or p.shape[0] < 3:
            degenerate = True
            status = 'planar: neither rotations nor positions define the plane normal'
    R0 = minimal_rotations_onto(a[None], b)[0]
    return PlanarModel(a, b, float(np.mean(p @ b)), R0, rng, degenerate, status)


#: Fitting function of each joint type.
_FITTERS: Dict[JointType, Callable] = {
    JointType.FIXED: fit_fixed,
    JointType.REVOLUTE: fit_revolute,
    JointType.PRISMATIC: fit_prismatic,
    JointType.SPHERICAL: fit_spherical,
    JointType.CYLINDRICAL: fit_cylindrical,
    JointType.PLANAR: fit_planar,
}

#: Size of the minimal frame sets drawn by the robust estimator (and fewest poses per model).
MIN_SAMPLES: Dict[JointType, int] = {
    JointType.FIXED: 1,
    JointType.REVOLUTE: 2,
    JointType.PRISMATIC: 2,
    JointType.SPHERICAL: 3,
    JointType.CYLINDRICAL: 2,
    JointType.PLANAR: 3,
}


def fit_model(joint_type: JointType, R: np.ndarray, p: np.ndarray,
              min_rotation_range: float = DEFAULT_MIN_ROTATION_RANGE,
              min_translation_range: float = DEFAULT_MIN_TRANSLATION_RANGE):
    """
    Fit one joint type to orientations (N, 3, 3) and positions (N, 3) [m] (all frames).

    :raises ValueError: fewer frames than the type needs; :raises DegenerateMotionError.
    """
    jt = JointType(joint_type)
    if R.shape[0] < MIN_SAMPLES[jt]:
        raise ValueError(f'{jt.name.lower()} joint: {R.shape[0]} poses given, at least '
                         f'{MIN_SAMPLES[jt]} needed')
    if jt == JointType.REVOLUTE:
        return fit_revolute(R, p, min_rotation_range)
    return _FITTERS[jt](R, p, min_rotation_range=min_rotation_range,
                        min_translation_range=min_translation_range)
