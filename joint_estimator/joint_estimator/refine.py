"""
Maximum-likelihood refinement of axis joints (revolute, cylindrical).

Maximum-likelihood refinement of axis joints (revolute, cylindrical) over orientation *and*
position residuals.

Eq. (17) determines the axis directions from the orientations alone. When the positions are
precise compared with ``sigma_rot`` times the link's distance from the axis, they carry more
information about the axis than the orientations (the chapter's Result paragraph notes that an
ML inference may improve the estimate). This step starts from the chapter's estimate and
minimises ``sum_t |v(hat R_t R_t^T)|^2 / sigma_rot^2 + |hat p_t - p_t|^2 / sigma_pos^2`` over
the joint parameters (Levenberg-Marquardt; ``v`` is the vector of the rotation's skew part,
``sin(angle) * axis``, the rotation vector to first order), the per-frame joint coordinates
being projected out in closed form (variable projection; :meth:`RevoluteModel.project`). It
is optional (``refine=True`` in :func:`joint_estimator.selection.estimate_joint`); without it
the estimate is exactly the chapter's. Other joint types are already fitted by (chordal) least
squares of decoupled orientation and position terms and are returned unchanged.
"""

from __future__ import annotations

from joint_estimator.common import minimal_rotations_onto, perpendicular_basis
from joint_estimator.models import CylindricalModel
from joint_estimator.revolute import AxisLineModel, project_track, RevoluteModel
import numpy as np

__all__ = ['is_refinable', 'refine_model', 'levenberg_marquardt', 'axis_uncertainty']


def _unit(v):
    return v / np.linalg.norm(v)


def is_refinable(model) -> bool:
    """Tell whether :func:`refine_model` changes the model (revolute, cylindrical)."""
    return isinstance(model, AxisLineModel)


def levenberg_marquardt(fun, x0: np.ndarray, max_iterations: int = 8, step: float = 1e-6,
                        rtol: float = 1e-6):
    """
    Minimise ``|fun(x)|^2`` from ``x0`` by Levenberg-Marquardt.

    Minimise ``|fun(x)|^2`` from ``x0`` by Levenberg-Marquardt with a forward-difference
    Jacobian, at most ``max_iterations`` accepted steps (the start is close to the optimum, so
    a few Gauss-Newton steps suffice). Returns the solution, or None if no step improved.
    """
    x = np.asarray(x0, dtype=float).copy()
    r = fun(x)
    cost = float(r @ r)
    lam, improved = 1e-4, False
    eye = np.eye(x.size)
    for _ in range(max_iterations):
        J = np.empty((r.size, x.size))
        for j in range(x.size):
            dx = eye[j] * step
            J[:, j] = (fun(x + dx) - r) / step
        A, g = J.T @ J, J.T @ r
        while lam < 1e8:
            delta = np.linalg.solve(A + lam * np.diag(np.diag(A) + 1e-12), -g)
            r_new = fun(x + delta)
            c_new = float(r_new @ r_new)
            if np.isfinite(c_new) and c_new < cost:
                break
            lam *= 10.0
        else:
            break
        x, r, gain = x + delta, r_new, (cost - c_new) / max(cost, 1e-300)
        cost, improved, lam = c_new, True, max(lam / 10.0, 1e-9)
        if gain < rtol:
            break
    return x if improved else None


def _parametrisation(model, R: np.ndarray, p: np.ndarray, sigma_position: float,
                     sigma_rotation: float, ray_ratio: float = 1.0) -> tuple:
    """
    ``(build, residuals, n_params)`` of an axis model about its current value.

    ``build(x)`` is the model at the local parameters ``x`` (zeros: ``model``), ``residuals(x)``
    the noise-normalised residual vector (6 per frame) of the frames ``R``, ``p``.
    """
    cyl = isinstance(model, CylindricalModel)
    a0, b0 = model.axis_in_a, model.axis_in_b
    ga, gb = perpendicular_basis(a0), perpendicular_basis(b0)
    ca0, cb0 = model.point_in_a, model.point_in_b
    v = p / np.maximum(np.linalg.norm(p, axis=1), 1e-12)[:, None]

    def build(x):
        a = _unit(a0 + x[0] * ga[0] + x[1] * ga[1])
        b = _unit(b0 + x[2] * gb[0] + x[3] * gb[1])
        cb = cb0 + x[4] * gb[0] + x[5] * gb[1]
        if cyl:
            ca = ca0 + x[6] * ga[0] + x[7] * ga[1]
        else:
            ca = ca0 + x[6:9]
        R0 = minimal_rotations_onto(a[None], b)[0]
        cls = CylindricalModel if cyl else RevoluteModel
        return cls(a, b, ca, cb, R0, model.rotation_range)

    def residuals(x):
        m = build(x)
        R_hat, p_hat, _ = project_track(m, R, p, sigma_position, sigma_rotation, ray_ratio)
        E = R_hat @ np.transpose(R, (0, 2, 1))
        # sin(angle) * axis of the residual rotation: its rotation vector to first order
        rot = 0.5 * np.stack([E[:, 2, 1] - E[:, 1, 2], E[:, 0, 2] - E[:, 2, 0],
                              E[:, 1, 0] - E[:, 0, 1]], axis=1) / sigma_rotation
        d = p_hat - p
        if ray_ratio != 1.0:       # whiten the component along the line of sight
            d = d + v * (np.einsum('ni,ni->n', d, v) * (1.0 / ray_ratio - 1.0))[:, None]
        return np.concatenate([rot.ravel(), (d / sigma_position).ravel()])

    return build, residuals, (8 if cyl else 9)


def refine_model(model, R: np.ndarray, p: np.ndarray, sigma_position: float,
                 sigma_rotation: float, max_iterations: int = 8, ray_ratio: float = 1.0):
    """
    Refined copy of a revolute or cylindrical ``model`` (others are returned as they are).

    Parameters: ``^A l`` and ``^B l`` (2 each, tangent steps), ``^B c`` across the axis (2) and
    ``^A c`` (3 for revolute, 2 across the axis for cylindrical): the gauge (sliding the points
    along the axis) is fixed, and the result is brought back to the minimum-norm points.

    :param R: (N, 3, 3) orientations, :param p: (N, 3) positions [m] of the frames to fit.
    :param ray_ratio: position noise along the line of sight from B's origin over the noise
        across it (``sigma_position``); the residual's component along it is divided by it.
    """
    if not is_refinable(model):
        return model
    cyl = isinstance(model, CylindricalModel)
    build, residuals, k = _parametrisation(model, R, p, sigma_position, sigma_rotation,
                                           ray_ratio)
    x0 = np.zeros(k)
    if R.shape[0] * 6 <= x0.size:
        return model
    x = levenberg_marquardt(residuals, x0, max_iterations)
    if x is None:
        return model
    m = build(x)
    a, b = m.axis_in_a, m.axis_in_b
    if cyl:
        m.point_in_a = m.point_in_a - a * (m.point_in_a @ a)
        m.point_in_b = m.point_in_b - b * (m.point_in_b @ b)
    else:
        s = -(m.point_in_a @ a + m.point_in_b @ b) / 2.0
        m.point_in_a = m.point_in_a + s * a
        m.point_in_b = m.point_in_b + s * b
    return m


def axis_uncertainty(model, R: np.ndarray, p: np.ndarray, sigma_position: float,
                     sigma_rotation: float, anchor_in_b: np.ndarray, step: float = 1e-6,
                     ray_ratio: float = 1.0) -> dict:
    """
    First-order (Gauss-Newton) uncertainty of an axis joint from the frames it was fitted to.

    The covariance of the local parameters is ``(J^T J)^-1`` with ``J`` the Jacobian of the
    noise-normalised residuals (forward differences), i.e. it assumes the noise scales are right
    (they are the estimated ones by default). It is propagated to the axis directions (angle
    std, the root of the trace of the 2x2 tangent covariance) and to the axis point nearest
    ``anchor_in_b`` (distance std across the axis, root of the trace of its 2x2 covariance).

    :param R: (N, 3, 3) orientations, :param p: (N, 3) positions [m] of the inlier frames.
    :param anchor_in_b: (3,) point [m] in link B (the data's centre) at which the axis position
        uncertainty is evaluated.
    :returns: ``{'axis_angle_std_in_a', 'axis_angle_std_in_b'`` [rad], ``'axis_point_std'`` [m],
        ``'covariance'`` (k, k) of the local parameters}, NaN where the Jacobian is singular;
        None for models without an axis line.
    """
    if not is_refinable(model) or R.shape[0] * 6 <= 9:
        return None
    build, residuals, k = _parametrisation(model, R, p, sigma_position, sigma_rotation,
                                           ray_ratio)
    r0 = residuals(np.zeros(k))
    J = np.empty((r0.size, k))
    eye = np.eye(k)
    for j in range(k):
        J[:, j] = (residuals(eye[j] * step) - r0) / step
    nan = {'axis_angle_std_in_a': float('nan'), 'axis_angle_std_in_b': float('nan'),
           'axis_point_std': float('nan'), 'covariance': np.full((k, k), np.nan)}
    try:
        cov = np.linalg.pinv(J.T @ J, rcond=1e-12, hermitian=True)
    except np.linalg.LinAlgError:
        return nan
    if not np.all(np.isfinite(cov)):
        return nan

    def near_point(x):
        m = build(x)
        b, cb = m.axis_in_b, m.point_in_b
        return cb + b * ((anchor_in_b - cb) @ b)

    c0 = near_point(np.zeros(k))
    G = np.empty((3, k))
    for j in range(k):
        G[:, j] = (near_point(eye[j] * step) - c0) / step
    P = np.eye(3) - np.outer(model.axis_in_b, model.axis_in_b)
    cov_c = P @ G @ cov @ G.T @ P
    return {'axis_angle_std_in_a': float(np.sqrt(max(np.trace(cov[:2, :2]), 0.0))),
            'axis_angle_std_in_b': float(np.sqrt(max(np.trace(cov[2:4, 2:4]), 0.0))),
            'axis_point_std': float(np.sqrt(max(np.trace(cov_c), 0.0))),
            'covariance': cov}
