"""Maximum-likelihood refinement of axis joints (revolute, cylindrical) over orientation *and*
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

import numpy as np

from joint_estimator.common import minimal_rotations_onto, perpendicular_basis
from joint_estimator.models import CylindricalModel
from joint_estimator.revolute import AxisLineModel, RevoluteModel

__all__ = ['is_refinable', 'refine_model', 'levenberg_marquardt']


def _unit(v):
    return v / np.linalg.norm(v)


def is_refinable(model) -> bool:
    """True for the models :func:`refine_model` changes (revolute, cylindrical)."""
    return isinstance(model, AxisLineModel)


def levenberg_marquardt(fun, x0: np.ndarray, max_iterations: int = 8, step: float = 1e-6,
                        rtol: float = 1e-6):
    """Minimise ``|fun(x)|^2`` from ``x0`` by Levenberg-Marquardt with a forward-difference
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


def refine_model(model, R: np.ndarray, p: np.ndarray, sigma_position: float,
                 sigma_rotation: float, max_iterations: int = 8):
    """Refined copy of a revolute or cylindrical ``model`` (others are returned as they are).

    Parameters: ``^A l`` and ``^B l`` (2 each, tangent steps), ``^B c`` across the axis (2) and
    ``^A c`` (3 for revolute, 2 across the axis for cylindrical): the gauge (sliding the points
    along the axis) is fixed, and the result is brought back to the minimum-norm points.

    :param R: (N, 3, 3) orientations, :param p: (N, 3) positions [m] of the frames to fit.
    """
    if not is_refinable(model):
        return model
    cyl = isinstance(model, CylindricalModel)
    a0, b0 = model.axis_in_a, model.axis_in_b
    ga, gb = perpendicular_basis(a0), perpendicular_basis(b0)
    ca0, cb0 = model.point_in_a, model.point_in_b

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
        R_hat, p_hat, _ = m.project(R, p, sigma_position, sigma_rotation)
        E = R_hat @ np.transpose(R, (0, 2, 1))
        # sin(angle) * axis of the residual rotation: its rotation vector to first order
        rot = 0.5 * np.stack([E[:, 2, 1] - E[:, 1, 2], E[:, 0, 2] - E[:, 2, 0],
                              E[:, 1, 0] - E[:, 0, 1]], axis=1) / sigma_rotation
        return np.concatenate([rot.ravel(), ((p_hat - p) / sigma_position).ravel()])

    x0 = np.zeros(8 if cyl else 9)
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
