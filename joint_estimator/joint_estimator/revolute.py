"""
Revolute joint from the relative track of link A in link B, exactly as Section 4 derives it.

Input: ``^B Theta_A(t)`` (N, 3, 3) and ``^B t_A(t)`` (N, 3) [m]. The joint parameters are the axis
direction in both links, ``^A l`` and ``^B l`` (unit), and a point on the axis in both links,
``^A c`` and ``^B c`` [m], tied by Eqs. (10)-(11)::

    ^B l = ^B Theta_A(t) ^A l                       (10)
    ^B c = ^B Theta_A(t) ^A c + ^B t_A(t)           (11)

Steps (each a public function so that it can be tested against the chapter):

1. Directions, Eq. (17): minimise ``sum_t (1 - Tr(^B Theta_A(t) ^A l ^B l^T))``. Because
   ``Tr(Theta a b^T) = b^T Theta a``, the sum equals ``N - ^B l^T (sum_t ^B Theta_A(t)) ^A l``,
   so the minimum over unit vectors is reached in **closed form** by the top left/right singular
   vectors of ``M = sum_t ^B Theta_A(t)``: ``^B l = u_1``, ``^A l = v_1``
   (:func:`fit_axis_directions`). :func:`fit_axis_directions_iterative` solves the same
   problem by iterative optimisation, as the original C++ implementation does; it serves as the
   benchmark baseline.
2. Corrected orientations: ``^B hat Theta_A(t) = D(t) ^B Theta_A(t)`` where ``D(t)`` is the
   minimal rotation taking ``^B Theta_A(t) ^A l`` onto ``^B l`` (rotation about their cross
   product), i.e. the noise term ``Delta Theta(t)`` of Eq. (13) with ``theta_1 = 0``.
3. Axis points, Eq. (18): ``(sum_t A^T A) (^A c; ^B c) = sum_t A^T ^B t_A(t)`` with
   ``A(t) = (-^B hat Theta_A(t)  I)``. The 6x6 matrix has rank 5 (the point is free along the
   axis: ``(^A c + s ^A l, ^B c + s ^B l)`` solves it for every s), so it is solved with the SVD,
   dropping singular values below ``1e-9`` of the largest; this gives the **minimum-norm**
   solution, i.e. the pair of axis points closest to the two link origins jointly. The
   reported :class:`JointFit` point is the one nearest the data instead (the foot of the
   inlier positions' centre on the axis), the minimum-norm pair is kept in its ``extra``.
4. Corrected track: ``^B hat t_A(t) = ^B c - ^B hat Theta_A(t) ^A c`` which, with step 2,
   satisfies Eqs. (10)-(11) exactly; joint angle ``q(t)`` from
   ``^B hat Theta_A(t) = R(^B l, q(t)) R_0`` where ``R_0`` is the minimal rotation taking
   ``^A l`` onto ``^B l`` (the zero of the joint angle).

Besides the chapter's correction (``correction='chapter'``), ``correction='ml'`` places each
frame at the joint angle minimising the noise-weighted residual of *both* orientation and
position (chordal orientation distance; closed form, see :meth:`RevoluteModel.project`); the
joint parameters are the same.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from joint_estimator.common import (
    compose_track, DegenerateMotionError, frame_residuals, JointFit, JointType,
    minimal_rotations_onto, rotations_about_axis, signed_angles_about_axis, split_track,
    validate_track)
import numpy as np
from scipy.optimize import minimize
from stereo_manip_tools.transforms import skew

__all__ = [
    'eq17_objective',
    'fit_axis_directions',
    'fit_axis_directions_iterative',
    'rotation_range_from_singular_values',
    'correct_orientations',
    'solve_axis_points',
    'AxisLineModel',
    'RevoluteModel',
    'fit_revolute',
    'estimate_revolute_joint',
    'project_track',
    'anisotropic_angles',
    'DEFAULT_MIN_ROTATION_RANGE',
]

#: Smallest rotation range [rad] (equivalent uniform range about the axis) that defines an axis.
DEFAULT_MIN_ROTATION_RANGE = np.deg2rad(10.0)


def eq17_objective(R: np.ndarray, axis_in_a: np.ndarray, axis_in_b: np.ndarray) -> float:
    """
    Eq. (17): ``sum_t (1 - Tr(^B Theta_A(t) ^A l ^B l^T))`` = ``sum_t (1 - cos theta(t))``.

    :param R: (N, 3, 3) orientations ``^B Theta_A(t)``.
    :param axis_in_a: ``^A l`` (3,), unit.
    :param axis_in_b: ``^B l`` (3,), unit.
    """
    return float(np.sum(1.0 - np.einsum('i,nij,j->n', axis_in_b, R, axis_in_a)))


def _canonical_sign(a: np.ndarray, b: np.ndarray) -> tuple:
    """Flip the pair (a, b) together so that b's largest-magnitude component is positive."""
    if b[int(np.argmax(np.abs(b)))] < 0:
        return -a, -b
    return a, b


def fit_axis_directions(R: np.ndarray) -> tuple:
    """
    Closed-form solution of Eq. (17): top singular vectors of ``M = sum_t ^B Theta_A(t)``.

    ``sum_t Tr(Theta_t a b^T) = b^T M a`` is maximised over unit a, b by ``b = u_1``,
    ``a = v_1`` (``M = U S V^T``), which minimises Eq. (17). The pair is defined up to a common
    sign; it is chosen so that ``^B l``'s largest component is positive.

    :param R: (N, 3, 3) orientations ``^B Theta_A(t)``.
    :returns: ``(axis_in_a (3,), axis_in_b (3,), singular_values (3,))``.
    """
    M = np.sum(R, axis=0)
    U, S, Vt = np.linalg.svd(M)
    a, b = _canonical_sign(Vt[0].copy(), U[:, 0].copy())
    return a, b, S


def fit_axis_directions_iterative(R: np.ndarray, initial: Optional[tuple] = None,
                                  tol: float = 1e-12) -> tuple:
    """
    Baseline: Eq. (17) minimised iteratively (BFGS over two pairs of spherical angles).

    This is how the original C++ estimator solves Eq. (17); the objective is evaluated as
    written, summing over the frames at every evaluation. Start: the axis of the relative
    rotation between the first and the last frame unless ``initial = (a0, b0)`` is given.

    :param R: (N, 3, 3) orientations.
    :returns: ``(axis_in_a, axis_in_b, n_function_evaluations)``.
    """
    if initial is None:
        from joint_estimator.common import rotation_vectors
        w = rotation_vectors((R[0].T @ R[-1])[None])[0]
        a0 = w / np.linalg.norm(w) if np.linalg.norm(w) > 1e-9 else np.array([0.0, 0.0, 1.0])
        b0 = R[0] @ a0
    else:
        a0, b0 = (np.asarray(v, dtype=float) / np.linalg.norm(v) for v in initial)

    def to_angles(v):
        return np.array([np.arccos(np.clip(v[2], -1.0, 1.0)), np.arctan2(v[1], v[0])])

    def to_vec(th, ph):
        return np.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])

    def cost(x):
        return eq17_objective(R, to_vec(x[0], x[1]), to_vec(x[2], x[3]))

    res = minimize(cost, np.concatenate([to_angles(a0), to_angles(b0)]), method='BFGS',
                   options={'gtol': tol * max(1, R.shape[0])})
    a, b = _canonical_sign(to_vec(res.x[0], res.x[1]), to_vec(res.x[2], res.x[3]))
    return a, b, int(res.nfev)


def rotation_range_from_singular_values(S: np.ndarray) -> float:
    """
    Equivalent uniform rotation range [rad] about the axis from the singular values of M.

    For a pure rotation about the axis by angles q(t), ``s_1 = N`` and
    ``s_2 = s_3 = |sum_t exp(i q(t))|``; for q uniform over a range r,
    ``s_2 / s_1 = sinc(r / 2) ~ 1 - r^2 / 24``, hence ``r ~ sqrt(24 (1 - s_2 / s_1))``.
    Isotropic orientation noise shrinks all three singular values alike and barely moves this.
    """
    return float(np.sqrt(24.0 * max(0.0, 1.0 - S[1] / S[0])))


def axis_directions_or_raise(R: np.ndarray, min_rotation_range: float, kind: str) -> tuple:
    """
    Fit the axis directions by Eq. (17) and correct the orientations about them.

    :returns: ``(^A l, ^B l, corrected orientations (N, 3, 3), rotation range [rad])``.
    :raises DegenerateMotionError: rotation range below ``min_rotation_range`` [rad] (the
        motion does not define a ``kind`` axis).
    """
    a, b, S = fit_axis_directions(R)
    rng = rotation_range_from_singular_values(S)
    if rng < min_rotation_range or S[0] - S[1] <= 1e-12 * S[0]:
        raise DegenerateMotionError(
            f'rotation range {np.rad2deg(rng):.2f} deg is below '
            f'{np.rad2deg(min_rotation_range):.2f}'
            f' deg: the motion does not define a {kind} axis')
    return a, b, correct_orientations(R, a, b), rng


def correct_orientations(R: np.ndarray, axis_in_a: np.ndarray,
                         axis_in_b: np.ndarray) -> np.ndarray:
    """
    Corrected orientations.

    The minimal rotation taking ``Theta(t) ^A l`` onto ``^B l`` applied to ``Theta(t)``; the result
    satisfies Eq. (10) exactly. (N, 3, 3) -> (N, 3, 3).
    """
    D = minimal_rotations_onto(R @ axis_in_a, axis_in_b)
    return D @ R


def solve_axis_points(R_hat: np.ndarray, p: np.ndarray, rcond: float = 1e-9) -> tuple:
    """
    Eq. (18) by SVD: the minimum-norm ``(^A c, ^B c)`` of the rank-deficient normal equations.

    :param R_hat: (N, 3, 3) corrected orientations.
    :param p: (N, 3) positions ``^B t_A(t)`` [m].
    :param rcond: singular values below ``rcond * s_max`` are treated as zero.
    :returns: ``(point_in_a (3,), point_in_b (3,), rank, singular_values (6,))``.
    """
    n = R_hat.shape[0]
    sum_R = R_hat.sum(axis=0)
    AtA = np.empty((6, 6))
    AtA[:3, :3] = n * np.eye(3)         # sum R^T R
    AtA[:3, 3:] = -sum_R.T
    AtA[3:, :3] = -sum_R
    AtA[3:, 3:] = n * np.eye(3)
    Atb = np.concatenate([-np.einsum('nji,nj->i', R_hat, p), p.sum(axis=0)])
    U, S, Vt = np.linalg.svd(AtA)
    keep = S > rcond * S[0]
    x = Vt[keep].T @ ((U[:, keep].T @ Atb) / S[keep])
    return x[:3], x[3:], int(keep.sum()), S


@dataclass
class AxisLineModel:
    """
    Parameters shared by the joints that rotate about one line (revolute, cylindrical).

    The line has direction ``axis_in_a`` / ``axis_in_b`` and passes through ``point_in_a`` /
    ``point_in_b`` in the two links' frames; ``reference`` is ``R_0``.
    """

    axis_in_a: np.ndarray
    axis_in_b: np.ndarray
    point_in_a: np.ndarray
    point_in_b: np.ndarray
    reference: np.ndarray
    rotation_range: float = float('nan')


@dataclass
class RevoluteModel(AxisLineModel):
    """Revolute joint parameters (see the module docstring); ``reference`` is ``R_0``."""

    joint_type: JointType = JointType.REVOLUTE
    n_params: int = 9

    def pose_at(self, angles: np.ndarray) -> np.ndarray:
        """(N, 4, 4) poses ``^B T_A`` of the joint at ``angles`` [rad] (satisfy Eqs. 10-11)."""
        R = rotations_about_axis(self.axis_in_b, angles) @ self.reference
        return compose_track(R, self.point_in_b - R @ self.point_in_a)

    def project_chapter(self, R: np.ndarray, p: np.ndarray) -> tuple:
        """
        Apply the chapter's correction: minimal-rotation orientations, positions by Eq. (11).

        :returns: ``(R_hat (N, 3, 3), p_hat (N, 3), angles (N, 1))``.
        """
        R_hat = correct_orientations(R, self.axis_in_a, self.axis_in_b)
        q = signed_angles_about_axis(R_hat @ self.reference.T, self.axis_in_b)
        return R_hat, self.point_in_b - R_hat @ self.point_in_a, q[:, None]

    def project(self, R: np.ndarray, p: np.ndarray, sigma_position: float,
                sigma_rotation: float) -> tuple:
        """
        Maximum-likelihood joint angle per frame (chordal orientation + position residual).

        :returns: ``(R_hat (N, 3, 3), p_hat (N, 3), angles (N, 1))``.
        """
        q = ml_angles(R, p, self.axis_in_b, self.reference, self.point_in_a, self.point_in_b,
                      sigma_position, sigma_rotation, slide=False)
        T = self.pose_at(q)
        return T[:, :3, :3], T[:, :3, 3], q[:, None]


def project_track(model, R: np.ndarray, p: np.ndarray, sigma_position: float,
                  sigma_rotation: float, ray_ratio: float = 1.0, exact: bool = True) -> tuple:
    """
    Project a track onto any joint ``model`` with anisotropic position noise.

    Project a track onto any joint ``model`` with position noise that is ``ray_ratio`` times
    larger along the line of sight from B's origin (a camera's depth) than across it
    (``sigma_position``).

    ``ray_ratio = 1``: the model's own closed-form projection. Otherwise the joint coordinates
    are first taken from the isotropic projection at the depth noise (so depth noise cannot
    drive them), and for a revolute joint refined to the exact minimiser of the anisotropic
    cost by safeguarded Newton steps on the angle (:func:`anisotropic_angles`).

    ``exact=False`` skips the Newton steps (a cheaper approximation, used to rank hypotheses).

    :returns: ``(R_hat (N, 3, 3), p_hat (N, 3), coordinates (N, dof))``.
    """
    if ray_ratio == 1.0:
        return model.project(R, p, sigma_position, sigma_rotation)
    R_hat, p_hat, q = model.project(R, p, sigma_position * ray_ratio, sigma_rotation)
    if exact and isinstance(model, RevoluteModel) and R.shape[0]:
        q = anisotropic_angles(R, p, model, q[:, 0], sigma_position, sigma_rotation,
                               ray_ratio)[:, None]
        T = model.pose_at(q[:, 0])
        R_hat, p_hat = T[:, :3, :3], T[:, :3, 3]
    return R_hat, p_hat, q


def anisotropic_angles(R: np.ndarray, p: np.ndarray, model, q0: np.ndarray,
                       sigma_position: float, sigma_rotation: float, ray_ratio: float,
                       iterations: int = 6) -> np.ndarray:
    """
    Estimate revolute joint angles under anisotropic position noise.

    Revolute joint angles (N,) [rad] minimising, per frame,
    ``(3 - Tr(R(q) R^T)) / s_r^2 + |W (hat p(q) - p)|^2 / s_p^2`` with
    ``W = I + (1 / ray_ratio - 1) v v^T`` (``v``: unit line of sight of ``p``). With
    ``c = cos q``, ``s = sin q`` the cost is ``-A c - B s + P c^2 + Q s^2 + 2 S c s`` + const;
    Newton steps from ``q0``, a step kept only where it lowers the cost.
    """
    ax = model.axis_in_b
    K = skew(ax)
    M = model.reference[None] @ np.transpose(R, (0, 2, 1))
    a_r = ((np.trace(M, axis1=1, axis2=2) - np.einsum('i,nij,j->n', ax, M, ax))
           / sigma_rotation ** 2)
    b_r = np.einsum('ij,nji->n', K, M) / sigma_rotation ** 2
    w = model.reference @ model.point_in_a
    w_par = ax * (ax @ w)
    u1, u2 = w - w_par, np.cross(ax, w)
    e0 = model.point_in_b - w_par - p                    # hat p(q) - p = e0 - c u1 - s u2
    v = p / np.maximum(np.linalg.norm(p, axis=1), 1e-12)[:, None]
    k = 1.0 / ray_ratio - 1.0

    def whiten(x):
        return x + v * (np.einsum('ni,ni->n', x, v) * k)[:, None]

    g0, g1, g2 = whiten(e0), whiten(np.broadcast_to(u1, p.shape)), whiten(
        np.broadcast_to(u2, p.shape))
    sp2 = sigma_position ** 2
    A = a_r + 2.0 * np.einsum('ni,ni->n', g0, g1) / sp2
    B = b_r + 2.0 * np.einsum('ni,ni->n', g0, g2) / sp2
    P = np.einsum('ni,ni->n', g1, g1) / sp2
    Q = np.einsum('ni,ni->n', g2, g2) / sp2
    S = np.einsum('ni,ni->n', g1, g2) / sp2

    def cost(q):
        c, s = np.cos(q), np.sin(q)
        return -A * c - B * s + P * c * c + Q * s * s + 2.0 * S * c * s

    q = np.asarray(q0, dtype=float).copy()
    J = cost(q)
    for _ in range(iterations):
        c, s = np.cos(q), np.sin(q)
        d1 = A * s - B * c + 2.0 * (Q - P) * c * s + 2.0 * S * (c * c - s * s)
        d2 = A * c + B * s + 2.0 * (Q - P) * (c * c - s * s) - 8.0 * S * c * s
        step = np.where(d2 > 1e-12, -d1 / np.where(d2 > 1e-12, d2, 1.0), -np.sign(d1) * 1e-3)
        step = np.clip(step, -0.5, 0.5)
        q_new = q + step
        J_new = cost(q_new)
        better = J_new < J
        q[better], J[better] = q_new[better], J_new[better]
        if not better.any():
            break
    return q


def ml_angles(R: np.ndarray, p: np.ndarray, axis_b: np.ndarray, reference: np.ndarray,
              point_a: np.ndarray, point_b: np.ndarray, sigma_position: Optional[float],
              sigma_rotation: float, slide: bool) -> np.ndarray:
    """
    Estimate maximum-likelihood revolute joint angles (N,) [rad].

    Angles q (N,) [rad] minimising, per frame, for ``R(q) = R(^B l, q) R_0``::

        (3 - Tr(R(q) R^T)) / sigma_rot^2 + |P (p - ^B c + R(q) ^A c)|^2 / sigma_pos^2

    (``3 - Tr`` is the chordal distance, ~ the squared angle; ``P`` projects out the axis when
    ``slide`` (cylindrical), else is I; ``sigma_position=None`` ignores positions). The cost is
    ``const - (a cos q + b sin q)``, so ``q = atan2(b, a)`` is the exact minimiser.
    """
    ax = axis_b
    K = skew(ax)
    M = reference[None] @ np.transpose(R, (0, 2, 1))
    trM = np.trace(M, axis1=1, axis2=2)
    lMl = np.einsum('i,nij,j->n', ax, M, ax)
    a = (trM - lMl) / sigma_rotation ** 2
    b = np.einsum('ij,nji->n', K, M) / sigma_rotation ** 2
    if sigma_position is not None:
        d = p - point_b
        if slide:
            d = d - np.outer(d @ ax, ax)
        w = reference @ point_a
        w_perp = w - ax * (ax @ w)
        a = a - 2.0 * (d @ w_perp) / sigma_position ** 2
        b = b - 2.0 * (d @ np.cross(ax, w)) / sigma_position ** 2
    return np.arctan2(b, a)


def fit_revolute(R: np.ndarray, p: np.ndarray,
                 min_rotation_range: float = DEFAULT_MIN_ROTATION_RANGE) -> RevoluteModel:
    """
    Revolute joint parameters by Eqs. (17) (closed form) and (18) (SVD, minimum norm).

    :param R: (N, 3, 3) orientations ``^B Theta_A(t)``; :param p: (N, 3) positions [m].
    :param min_rotation_range: below this equivalent rotation range [rad] the axis is undefined.
    :raises DegenerateMotionError: rotation range below ``min_rotation_range``.
    """
    a, b, R_hat, rng = axis_directions_or_raise(R, min_rotation_range, 'revolute')
    ca, cb, _, _ = solve_axis_points(R_hat, p)
    R0 = minimal_rotations_onto(a[None], b)[0]
    return RevoluteModel(a, b, ca, cb, R0, rng)


def estimate_revolute_joint(poses: np.ndarray, sigma_position: float = 0.005,
                            sigma_rotation: float = np.deg2rad(2.0), correction: str = 'chapter',
                            min_rotation_range: float = DEFAULT_MIN_ROTATION_RANGE,
                            stamps_ns=None) -> JointFit:
    """
    Estimate a revolute joint and the corrected track (Section 4, Eqs. 10-18), no outlier test.

    :param poses: (N, 4, 4) relative track ``^B T_A(t)`` (N >= 2) [m].
    :param sigma_position: position noise std [m] per axis (scales the residual chi-square).
    :param sigma_rotation: orientation noise std [rad] per axis.
    :param correction: ``'chapter'`` (minimal rotation + Eq. 11) or ``'ml'`` (see module doc).
    :param min_rotation_range: equivalent rotation range [rad] below which the motion is
        reported degenerate.
    :param stamps_ns: optional (N,) stamps [ns] checked for order.
    :raises ValueError: bad input; :raises DegenerateMotionError: too small a rotation range.
    """
    T = validate_track(poses, stamps_ns, min_poses=2)
    R, p = split_track(T)
    model = fit_revolute(R, p, min_rotation_range)
    return make_fit(model, R, p, sigma_position, sigma_rotation, correction)


def make_fit(model, R: np.ndarray, p: np.ndarray, sigma_position: float, sigma_rotation: float,
             correction: str = 'ml', inliers: Optional[np.ndarray] = None,
             ray_ratio: float = 1.0) -> JointFit:
    """
    Project the track onto ``model`` and package the residuals into a JointFit.

    Project the track onto ``model`` (:func:`project_track`) and package residuals into a
    :class:`JointFit` (``chi2`` with the position residual's line-of-sight component divided
    by ``ray_ratio``).
    """
    if correction == 'chapter' and hasattr(model, 'project_chapter'):
        R_hat, p_hat, q = model.project_chapter(R, p)
    elif correction in ('chapter', 'ml'):
        R_hat, p_hat, q = project_track(model, R, p, sigma_position, sigma_rotation, ray_ratio)
    else:
        raise ValueError(f"correction must be 'chapter' or 'ml', got {correction!r}")
    rot, pos, chi2 = frame_residuals(R, p, R_hat, p_hat, sigma_position, sigma_rotation)
    if ray_ratio != 1.0:
        d = p_hat - p
        v = p / np.maximum(np.linalg.norm(p, axis=1), 1e-12)[:, None]
        d = d + v * (np.einsum('ni,ni->n', d, v) * (1.0 / ray_ratio - 1.0))[:, None]
        chi2 = (rot / sigma_rotation) ** 2 + np.sum(d ** 2, axis=1) / sigma_position ** 2
    zero = np.zeros(3)
    inliers = np.ones(R.shape[0], bool) if inliers is None else inliers
    point_a, point_b = (getattr(model, 'point_in_a', zero), getattr(model, 'point_in_b', zero))
    extra = {}
    if isinstance(model, AxisLineModel) and inliers.any():
        # the point of the (free) axis line nearest the data: foot of the inlier positions'
        # centre, the same point in both links
        s = float((p[inliers].mean(axis=0) - point_b) @ model.axis_in_b)
        extra = {'minimum_norm_point_in_a': point_a, 'minimum_norm_point_in_b': point_b}
        point_a, point_b = point_a + s * model.axis_in_a, point_b + s * model.axis_in_b
    return JointFit(
        joint_type=model.joint_type,
        axis_in_a=getattr(model, 'axis_in_a', zero), axis_in_b=getattr(model, 'axis_in_b', zero),
        point_in_a=point_a, point_in_b=point_b,
        corrected=compose_track(R_hat, p_hat), coordinates=q, rotation_residuals=rot,
        position_residuals=pos, chi2=chi2, inliers=inliers, extra=extra,
        sigma_position=float(sigma_position), sigma_rotation=float(sigma_rotation),
        n_params=model.n_params, model=model, degenerate=bool(getattr(model, 'degenerate', False)),
        status=getattr(model, 'status', ''),
        rotation_range=float(getattr(model, 'rotation_range', float('nan'))),
        translation_range=float(getattr(model, 'translation_range', float('nan'))))
