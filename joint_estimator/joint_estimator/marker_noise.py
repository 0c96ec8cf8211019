"""
Per-frame pose noise of a square marker seen by one camera, and the revolute fit weighted by it.

A square marker's pose comes from the images of its four corners. To first order its
covariance is ``sigma_n^2 (J^T J)^-1`` with ``J`` (8 x 6) the Jacobian of the corners'
normalised image coordinates (``x / z``, ``y / z``; the camera's focal length only scales
``sigma_n = sigma_px / f``) with respect to the pose (:func:`marker_information`). It is very
anisotropic and differs from frame to frame: the position along the line of sight (depth, from
the marker's apparent size) is 10-50x less certain than across it, the rotation about axes in
the marker plane is poorly known when the marker faces the camera, and all of it grows with the
distance. Weighting each frame's residual with its own information ``J^T J`` (at the pose the
joint predicts, so the weights do not follow the noise) is the maximum-likelihood fit of the
joint to the poses (:func:`refine_revolute_marker`); an unweighted or globally weighted fit
lets the depth noise of the far and frontal frames move the axis line.

The information depends on the marker side ``s`` only through ``s / z``, and only weakly
(halving or doubling ``s`` changed the axis-line error by < 0.5 mm in the issue-14 bench). When
the side is not given it is estimated from the track: the side whose predicted ratio of depth
to lateral position noise matches the ratio measured from the track's second differences
(:func:`joint_estimator.robust.line_of_sight_ratio`; :func:`estimate_marker_side`).

Conventions: link B is the camera (optical frame), link A the marker; a pose perturbation is
``R -> exp([w]) R``, ``p -> p + dp`` with ``w``, ``dp`` in B; residual vectors are ``(w, dp)``
(rotation [rad], position [m]).
"""

from __future__ import annotations

from typing import Optional

from joint_estimator.common import (
    minimal_rotations_onto, perpendicular_basis, rotation_vectors)
from joint_estimator.refine import levenberg_marquardt
from joint_estimator.revolute import RevoluteModel
import numpy as np

__all__ = ['marker_corners', 'marker_information', 'predicted_ray_ratio',
           'estimate_marker_side', 'weighted_angles', 'refine_revolute_marker',
           'MIN_RAY_RATIO', 'project_marker_corners', 'corner_angles',
           'refine_revolute_corners']

#: The per-frame marker weighting is applied only when the track's positions are at least this
#: much noisier along the line of sight than across it (a camera's depth noise); otherwise the
#: poses do not come from a single-camera marker and the isotropic model is kept.
MIN_RAY_RATIO = 3.0


def _skew_n(v: np.ndarray) -> np.ndarray:
    S = np.zeros((v.shape[0], 3, 3))
    S[:, 0, 1], S[:, 0, 2], S[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    S[:, 1, 0], S[:, 2, 0], S[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    return S


def marker_corners(side: float, normal_axis: int = 2) -> np.ndarray:
    """
    Return the (4, 3) corners [m] of a square marker of ``side`` in its own frame.

    The corners are centred, in the plane normal to axis ``normal_axis``.
    """
    h = side / 2.0
    uv = np.array([[-h, h], [h, h], [h, -h], [-h, -h]])
    C = np.zeros((4, 3))
    C[:, [i for i in range(3) if i != normal_axis]] = uv
    return C


def marker_information(R: np.ndarray, p: np.ndarray, side: float,
                       normal_axis: int = 2) -> np.ndarray:
    """
    Compute the per-frame information ``J^T J`` (N, 6, 6) of a marker pose, normalised image units.

    ``J`` (8 x 6) is the Jacobian of the four corners' normalised image coordinates with
    respect to ``(w, dp)`` (rotation [rad] and position [m] perturbations in the camera frame);
    the pose covariance is ``sigma_n^2 (J^T J)^-1`` with ``sigma_n`` the corner noise in
    normalised coordinates (pixels / focal length).

    :param R: (N, 3, 3) marker orientations in the camera frame; :param p: (N, 3) positions [m]
        (z > 0). :param side: marker side [m].
    """
    C = marker_corners(side, normal_axis)
    n = R.shape[0]
    W = np.zeros((n, 6, 6))
    eye = np.broadcast_to(np.eye(3), (n, 3, 3))
    for c in C:
        Rc = R @ c
        X = Rc + p
        z = X[:, 2]
        D = np.zeros((n, 2, 3))
        D[:, 0, 0] = D[:, 1, 1] = 1.0 / z
        D[:, 0, 2], D[:, 1, 2] = -X[:, 0] / z ** 2, -X[:, 1] / z ** 2
        J = D @ np.concatenate([-_skew_n(Rc), eye], axis=2)
        W += np.transpose(J, (0, 2, 1)) @ J
    return W


def predicted_ray_ratio(R: np.ndarray, p: np.ndarray, side: float,
                        normal_axis: int = 2) -> float:
    """
    Return the predicted ratio of position noise along the line of sight to across it.

    Median over the frames of the predicted position noise along the line of sight over the
    noise across it (per axis), for a marker of ``side`` [m] at poses ``R`` (N, 3, 3), ``p``
    (N, 3) [m].
    """
    cov = np.linalg.pinv(marker_information(R, p, side, normal_axis), hermitian=True)[:, 3:, 3:]
    v = p / np.linalg.norm(p, axis=1)[:, None]
    along = np.einsum('ni,nij,nj->n', v, cov, v)
    across = np.maximum(np.trace(cov, axis1=1, axis2=2) - along, 1e-300) / 2.0
    return float(np.median(np.sqrt(np.maximum(along, 0.0) / across)))


def estimate_marker_side(R: np.ndarray, p: np.ndarray, ray_ratio: float,
                         normal_axis: int = 2, iterations: int = 4) -> float:
    """
    Estimate the marker side [m] from the measured line-of-sight noise ratio.

    Marker side [m] whose predicted depth / lateral noise ratio
    (:func:`predicted_ray_ratio`) equals the measured ``ray_ratio`` (the ratio is ~ inversely
    proportional to the side: fixed-point iterations), clamped to 0.5-100 % of the median
    distance.
    """
    z = float(np.median(np.linalg.norm(p, axis=1)))
    side = 0.05 * z
    for _ in range(iterations):
        side *= predicted_ray_ratio(R, p, side, normal_axis) / max(ray_ratio, 1.0)
        side = float(np.clip(side, 0.005 * z, 1.0 * z))
    return side


def _residuals(model: RevoluteModel, q: np.ndarray, R: np.ndarray, p: np.ndarray) -> tuple:
    T = model.pose_at(q)
    R_hat, p_hat = T[:, :3, :3], T[:, :3, 3]
    r = np.concatenate([rotation_vectors(R @ np.transpose(R_hat, (0, 2, 1))), p - p_hat], axis=1)
    return r, p_hat


def weighted_angles(model: RevoluteModel, R: np.ndarray, p: np.ndarray, W: np.ndarray,
                    q0: np.ndarray, iterations: int = 4) -> np.ndarray:
    """
    Compute the joint angles (N,) [rad] minimising each frame's weighted residual.

    Joint angles (N,) [rad] minimising each frame's ``r^T W r`` (``r``: residual of the
    pose about the joint at the angle; ``W`` (N, 6, 6) the frame's information), by
    Gauss-Newton steps from ``q0``.
    """
    q = np.asarray(q0, dtype=float).copy()
    ax = model.axis_in_b
    for _ in range(iterations):
        r, p_hat = _residuals(model, q, R, p)
        g = np.concatenate([-np.broadcast_to(ax, p_hat.shape),
                            -np.cross(ax, p_hat - model.point_in_b)], axis=1)
        Wg = np.einsum('nij,nj->ni', W, g)
        den = np.einsum('ni,ni->n', Wg, g)
        q = q - np.einsum('ni,ni->n', Wg, r) / np.maximum(den, 1e-300)
    return q


def _build(model: RevoluteModel):
    a0, b0 = model.axis_in_a, model.axis_in_b
    ga, gb = perpendicular_basis(a0), perpendicular_basis(b0)

    def build(x):
        a = a0 + x[0] * ga[0] + x[1] * ga[1]
        b = b0 + x[2] * gb[0] + x[3] * gb[1]
        a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
        cb = model.point_in_b + x[4] * gb[0] + x[5] * gb[1]
        ca = model.point_in_a + x[6:9]
        return RevoluteModel(a, b, ca, cb, minimal_rotations_onto(a[None], b)[0],
                             model.rotation_range)
    return build


def _joint_covariances(residuals, build, model: RevoluteModel, p: np.ndarray,
                       sigma_n: float) -> dict:
    """
    Return the covariance of the 9 joint parameters and of the axis point near the data.

    :param residuals: whitened residual vector as a function of the 9-parameter step ``x``
        (``build(x)`` the stepped model); its Jacobian is taken by central differences.
    :param p: (N, 3) positions [m] in B; the axis point is the one nearest their mean.
    :param sigma_n: noise scale [residual units] of the whitened residuals.
    :returns: ``covariance`` (9, 9), ``axis_angle_std_in_a``/``_in_b`` [rad],
        ``axis_point_std`` [m] and ``axis_point_covariance`` (3, 3) [m^2], across the axis.
    """
    step = 1e-6
    eye = np.eye(9) * step
    J = np.column_stack([(residuals(e) - residuals(-e)) / (2.0 * step) for e in eye])
    cov = sigma_n ** 2 * np.linalg.pinv(J.T @ J, rcond=1e-12, hermitian=True)
    anchor = p.mean(axis=0)

    def near(x):
        mx = build(x)
        return mx.point_in_b + mx.axis_in_b * ((anchor - mx.point_in_b) @ mx.axis_in_b)

    c0 = near(np.zeros(9))
    G = np.column_stack([(near(e) - c0) / step for e in eye])
    P = np.eye(3) - np.outer(model.axis_in_b, model.axis_in_b)
    cov_c = P @ G @ cov @ G.T @ P
    return {'covariance': cov,
            'axis_angle_std_in_a': float(np.sqrt(max(np.trace(cov[:2, :2]), 0.0))),
            'axis_angle_std_in_b': float(np.sqrt(max(np.trace(cov[2:4, 2:4]), 0.0))),
            'axis_point_std': float(np.sqrt(max(np.trace(cov_c), 0.0))),
            'axis_point_covariance': cov_c}


def refine_revolute_marker(model: RevoluteModel, R: np.ndarray, p: np.ndarray,
                           side: float, normal_axis: int = 2, rounds: int = 3,
                           q0: Optional[np.ndarray] = None) -> dict:
    """
    Fit the maximum-likelihood revolute joint for marker poses with per-frame information.

    Minimises ``sum_t r_t^T W_t r_t`` over the joint parameters (Levenberg-Marquardt over the
    axis directions, ``^B c`` across the axis and ``^A c``; the per-frame angles projected out
    by :func:`weighted_angles`), with ``W_t`` the information of the marker pose the joint
    predicts for frame t (:func:`marker_information`), recomputed over ``rounds`` rounds.

    :param model: the starting revolute model; :param R: (N, 3, 3), :param p: (N, 3) [m]: the
        inlier poses (twins chosen) of the marker in the camera frame.
    :param side: marker side [m] (given, or :func:`estimate_marker_side`).
    :returns: ``{'model', 'angles' (N,), 'information' (N, 6, 6) at the final joint poses,
        'sigma_n' (corner noise in normalised image units, from the weighted residuals),
        'neg2_log_likelihood' of the frames under the per-frame model (with ``sigma_n``),
        'covariance' (9, 9) of the local parameters, 'axis_angle_std_in_a/b' [rad],
        'axis_point_std' [m] (across the axis at the data's centre), 'axis_point_covariance'
        (3, 3) [m^2] of that point}``.
    """
    q = (model.project(R, p, 1e-3, 1e-2)[2][:, 0] if q0 is None
         else np.asarray(q0, dtype=float))
    m = model
    for _ in range(rounds):
        T = m.pose_at(q)
        W = marker_information(T[:, :3, :3], T[:, :3, 3], side, normal_axis)
        L = np.linalg.cholesky(W + 1e-12 * np.eye(6))
        build = _build(m)
        q_ref = q.copy()

        def fun(x, build=build, q_ref=q_ref, W=W, L=L):
            mx = build(x)
            qx = weighted_angles(mx, R, p, W, q_ref)
            r, _ = _residuals(mx, qx, R, p)
            return np.einsum('nji,nj->ni', L, r).ravel()

        x = levenberg_marquardt(fun, np.zeros(9), 20)
        if x is not None:
            m = build(x)
        q = weighted_angles(m, R, p, W, q)
    T = m.pose_at(q)
    W = marker_information(T[:, :3, :3], T[:, :3, 3], side, normal_axis)
    L = np.linalg.cholesky(W + 1e-12 * np.eye(6))
    r, _ = _residuals(m, q, R, p)
    chi = np.einsum('nji,nj->ni', L, r)
    n = R.shape[0]
    sigma_n = float(np.sqrt(np.sum(chi ** 2) / max(5 * n - 9, 1)))
    # -2 log-likelihood of the frames under this noise model (covariance sigma_n^2 W^-1)
    logdet = np.linalg.slogdet(W)[1]
    neg2ll = float(np.sum(chi ** 2) / sigma_n ** 2 + np.sum(
        6.0 * np.log(2.0 * np.pi) + 12.0 * np.log(sigma_n) - logdet))
    # first-order covariance of the local parameters at the solution
    build = _build(m)

    def fun0(x):
        mx = build(x)
        r_x, _ = _residuals(mx, weighted_angles(mx, R, p, W, q), R, p)
        return np.einsum('nji,nj->ni', L, r_x).ravel()

    # central differences of the profiled residuals (angles re-minimised under the final W on
    # both sides): a forward difference from ``chi`` (angles minimised under the previous
    # round's W) mixed that mismatch into J and made the point std ~3x too small
    return {'model': m, 'angles': q, 'information': W, 'sigma_n': sigma_n,
            'neg2_log_likelihood': neg2ll, **_joint_covariances(fun0, build, m, p, sigma_n)}


def project_marker_corners(R: np.ndarray, p: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """
    Project a marker's corners into the camera's normalised image plane.

    :param R: (N, 3, 3) marker orientations in the camera frame; :param p: (N, 3) positions [m]
        (z > 0); :param corners: (4, 3) corners [m] in the marker frame
        (:func:`marker_corners`). :returns: (N, 4, 2) normalised image coordinates
        (``x / z``, ``y / z``).
    """
    X = np.einsum('nij,kj->nki', R, corners) + p[:, None, :]
    return X[..., :2] / X[..., 2:3]


def _corner_residuals(model: RevoluteModel, q: np.ndarray, uv: np.ndarray,
                      corners: np.ndarray) -> np.ndarray:
    T = model.pose_at(q)
    return (project_marker_corners(T[:, :3, :3], T[:, :3, 3], corners) - uv).reshape(
        q.size, -1)


def corner_angles(model: RevoluteModel, uv: np.ndarray, corners: np.ndarray, q0: np.ndarray,
                  iterations: int = 5, step: float = 1e-6) -> np.ndarray:
    """
    Joint angles (N,) [rad] whose predicted marker corners best match ``uv`` (N, 4, 2).

    Per-frame Gauss-Newton steps on the squared corner distance in the normalised image
    (forward-difference derivative in the angle), from ``q0``; steps clipped to 0.3 rad.
    """
    q = np.asarray(q0, dtype=float).copy()
    for _ in range(iterations):
        r0 = _corner_residuals(model, q, uv, corners)
        g = (_corner_residuals(model, q + step, uv, corners) - r0) / step
        den = np.einsum('ni,ni->n', g, g)
        q = q + np.clip(-np.einsum('ni,ni->n', g, r0) / np.maximum(den, 1e-300), -0.3, 0.3)
    return q


def refine_revolute_corners(model: RevoluteModel, R: np.ndarray, p: np.ndarray, side: float,
                            normal_axis: int = 2, rounds: int = 2,
                            q0: Optional[np.ndarray] = None) -> dict:
    """
    Fit the maximum-likelihood revolute joint to marker poses in the image (corner) space.

    Each pose is turned back into the normalised image coordinates of the marker's four
    corners it reprojects to (``uv_t``; the pose a square-marker solver returns is the one
    that reprojects closest to the detected corners, so ``uv_t`` are the detected corners up
    to their 2 components the pose cannot explain), and the joint is fitted by minimising
    ``sum_t |uv(^B T_A(q_t)) - uv_t|^2`` over the joint parameters (Levenberg-Marquardt over
    the same 9 local parameters as :func:`refine_revolute_marker`) with the angles ``q_t``
    projected out per frame (:func:`corner_angles`).

    To first order this is :func:`refine_revolute_marker` (``|J dx|^2 = dx^T (J^T J) dx``), but
    it keeps the exact, non-linear dependence of the corners on the pose: a marker seen nearly
    face-on has corners that depend on its tilt only to second order, so its pose error is far
    from Gaussian (a tilt of tens of degrees, up to the ambiguity twin, reprojects within the
    noise), and a pose-space weight from the Jacobian either trusts such a frame's tilt far too
    much or not at all. In the image the same frame has an ordinary, nearly Gaussian residual,
    and a flipped pose (the other solution of the ambiguity) reprojects nearly like the
    correct one, so it needs no repair. On the issue-14 tracks this removed the tail of the
    axis-line error that the pose-space fit had even with the flips undone by the truth.

    :param model: the starting revolute model; :param R: (N, 3, 3), :param p: (N, 3) [m]: the
        poses of the marker in the camera frame (as measured; z > 0).
    :param side: marker side [m]; :param normal_axis: marker normal's axis in A.
    :param q0: (N,) starting angles [rad] (default: the model's projection of the poses).
    :returns: ``{'model', 'angles' (N,), 'information' (N, 6, 6) at the final joint poses,
        'sigma_n' (corner noise in normalised image units from the residuals, ``5 N - 9``
        degrees of freedom: 6 per pose minus the angle, minus the joint),
        'frame_chi2' (N,) squared corner residual over ``sigma_n^2``,
        'neg2_log_likelihood' of the poses under this model (per-frame Gaussian of covariance
        ``sigma_n^2 W^-1``, chi-square from the corners), 'covariance' (9, 9) of the local
        parameters, 'axis_angle_std_in_a/b' [rad], 'axis_point_std' [m] (across the axis at
        the data's centre), 'axis_point_covariance' (3, 3) [m^2]}``.
    """
    C = marker_corners(side, normal_axis)
    uv = project_marker_corners(R, p, C)
    q = (model.project(R, p, 1e-3, 1e-2)[2][:, 0] if q0 is None
         else np.asarray(q0, dtype=float))
    m = model
    q = corner_angles(m, uv, C, q)
    for _ in range(rounds):
        build = _build(m)
        q_ref = q.copy()

        def fun(x, build=build, q_ref=q_ref):
            mx = build(x)
            return _corner_residuals(mx, corner_angles(mx, uv, C, q_ref, 3), uv, C).ravel()

        x = levenberg_marquardt(fun, np.zeros(9), 20)
        if x is not None:
            m = build(x)
        q = corner_angles(m, uv, C, q)
    r = _corner_residuals(m, q, uv, C)
    n = R.shape[0]
    sigma_n = float(np.sqrt(np.sum(r ** 2) / max(5 * n - 9, 1)))
    frame_chi2 = np.sum(r ** 2, axis=1) / sigma_n ** 2
    T = m.pose_at(q)
    W = marker_information(T[:, :3, :3], T[:, :3, 3], side, normal_axis)
    logdet = np.linalg.slogdet(W)[1]
    neg2ll = float(np.sum(frame_chi2) + np.sum(
        6.0 * np.log(2.0 * np.pi) + 12.0 * np.log(sigma_n) - logdet))
    build = _build(m)

    def fun0(x):
        mx = build(x)
        return _corner_residuals(mx, corner_angles(mx, uv, C, q, 3), uv, C).ravel()

    return {'model': m, 'angles': q, 'information': W, 'sigma_n': sigma_n,
            'frame_chi2': frame_chi2, 'neg2_log_likelihood': neg2ll,
            **_joint_covariances(fun0, build, m, p, sigma_n)}
