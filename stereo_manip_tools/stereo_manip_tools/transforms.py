"""
Rigid-transform and rotation helpers shared by every stereo_manip package (numpy).

The one home of the workspace's rotation math: single rotations (``skew``,
``rotation_about_axis``, ``rotation_log``, ...) and batched ones over (N, 3, 3) stacks
(``rotations_about_axis``, ``rotation_vectors``, ``minimal_rotations_onto``, ...).

Conventions (REP 103): metres and radians; a pose is a 4x4 homogeneous matrix ``T`` that maps
points from a child frame into a parent frame, ``p_parent = T[:3, :3] @ p_child + T[:3, 3]``.
Quaternions follow ROS ``geometry_msgs/Quaternion`` order ``(x, y, z, w)``.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    'skew',
    'rotation_about_axis',
    'rotations_about_axis',
    'rotation_log',
    'rotation_vectors',
    'signed_angles_about_axis',
    'rotation_angle',
    'is_rotation_matrix',
    'nearest_rotation',
    'make_transform',
    'invert_transform',
    'transform_points',
    'quaternion_from_matrix',
    'matrix_from_quaternion',
    'minimal_rotation_between',
    'minimal_rotations_onto',
    'perpendicular_basis',
    'check_transform',
    'pose_from_xyz_quaternion',
]


def skew(v: np.ndarray) -> np.ndarray:
    """Return the 3x3 cross-product matrix ``[v]x`` (``[v]x @ w == cross(v, w)``)."""
    x, y, z = np.asarray(v, dtype=float).reshape(3)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def rotation_about_axis(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues' formula: rotation of ``angle`` [rad] about ``axis`` (normalised here), 3x3."""
    a = np.asarray(axis, dtype=float).reshape(3)
    n = np.linalg.norm(a)
    if n == 0.0:
        raise ValueError('rotation_about_axis: zero-length axis')
    return rotations_about_axis(a / n, angle)[0]


def rotations_about_axis(axis: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """
    Rodrigues' formula for many angles.

    (N, 3, 3) rotations of ``angles`` [rad] (a scalar or shape (N,)) about a unit ``axis`` (3,).
    """
    K = skew(axis)
    a = np.asarray(angles, dtype=float).reshape(-1, 1, 1)
    return np.eye(3) + np.sin(a) * K + (1.0 - np.cos(a)) * (K @ K)


def rotation_log(R: np.ndarray) -> np.ndarray:
    """Rotation vector (axis * angle [rad], shape (3,)) of a rotation matrix; angle in [0, pi]."""
    R = np.asarray(R, dtype=float)
    cos_theta = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    theta = float(np.arccos(cos_theta))
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if theta < 1e-7:
        return 0.5 * w
    if np.pi - theta < 1e-4:
        # near pi: the symmetric part of R is cos(theta) I + (1 - cos(theta)) a a^T, so a a^T
        # follows exactly (the skew part, O(pi - theta), is left out)
        B = ((R + R.T) / 2.0 - cos_theta * np.eye(3)) / (1.0 - cos_theta)
        i = int(np.argmax(np.diag(B)))
        axis = B[:, i] / np.sqrt(max(B[i, i], 1e-300))
        if np.dot(axis, w) < 0:
            axis = -axis
        return axis / np.linalg.norm(axis) * theta
    return w * (theta / (2.0 * np.sin(theta)))


def rotation_vectors(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (N, 3) [rad] of rotations (N, 3, 3) (robust near 0 and pi)."""
    from scipy.spatial.transform import Rotation
    return Rotation.from_matrix(R).as_rotvec()


def signed_angles_about_axis(R: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Angle [rad] in (-pi, pi] of rotations (N, 3, 3) known to be about the unit ``axis``."""
    w = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], 1)
    c = (np.trace(R, axis1=1, axis2=2) - 1.0) / 2.0
    return np.arctan2(0.5 * (w @ axis), c)


def rotation_angle(R: np.ndarray) -> float:
    """Angle [rad] in [0, pi] of a rotation matrix (robust near 0 and pi)."""
    return float(np.linalg.norm(rotation_log(R)))


_EYE3 = np.eye(3)
_LAST_ROW = np.array([0.0, 0.0, 0.0, 1.0])


def is_rotation_matrix(R: np.ndarray, tol: float = 1e-6) -> bool:
    """Tell if ``R`` is a finite 3x3 matrix with ``R^T R = I`` and ``det R = +1`` within tol."""
    R = np.asarray(R, dtype=float)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        return False
    # np.allclose(R.T @ R, I, atol=tol) for finite values, without its per-call overhead
    return bool(np.all(np.abs(R.T @ R - _EYE3) <= tol + 1e-5 * _EYE3)
                and abs(np.linalg.det(R) - 1.0) < tol)


def nearest_rotation(M: np.ndarray) -> np.ndarray:
    """Closest rotation matrix to a 3x3 matrix in the Frobenius norm (SVD projection on SO(3))."""
    U, _, Vt = np.linalg.svd(np.asarray(M, dtype=float))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    return U @ D @ Vt


def make_transform(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 homogeneous transform from a 3x3 rotation and a translation [m] of shape (3,)."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def invert_transform(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform (uses ``R^T``, not a general matrix inverse)."""
    T = np.asarray(T, dtype=float)
    R = T[:3, :3]
    return make_transform(R.T, -R.T @ T[:3, 3])


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to points of shape (N, 3); returns shape (N, 3)."""
    P = np.asarray(points, dtype=float)
    return P @ T[:3, :3].T + T[:3, 3]


def quaternion_from_matrix(R: np.ndarray) -> np.ndarray:
    """Convert a 3x3 rotation matrix to a unit quaternion ``(x, y, z, w)``, ``w >= 0``."""
    R = np.asarray(R, dtype=float)
    tr = np.trace(R)
    cands = np.array([tr, R[0, 0], R[1, 1], R[2, 2]])
    i = int(np.argmax(cands))
    if i == 0:
        s = np.sqrt(1.0 + tr) * 2.0
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s]
    elif i == 1:
        s = np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2]) * 2.0
        q = [0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s]
    elif i == 2:
        s = np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2]) * 2.0
        q = [(R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s]
    else:
        s = np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1]) * 2.0
        q = [(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s, (R[1, 0] - R[0, 1]) / s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def matrix_from_quaternion(q: np.ndarray) -> np.ndarray:
    """Convert a quaternion ``(x, y, z, w)`` to a 3x3 rotation matrix (ValueError: zero/NaN)."""
    q = np.asarray(q, dtype=float).reshape(4)
    n = np.linalg.norm(q)
    if not np.isfinite(n) or n < 1e-9:
        raise ValueError(f'quaternion {q.tolist()} is zero or not finite')
    x, y, z, w = q / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def minimal_rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """
    Smallest-angle rotation taking direction ``a`` onto direction ``b`` (both shape (3,)).

    The axis is ``a x b``; for antiparallel vectors any axis perpendicular to ``a`` is used.
    """
    a = np.asarray(a, dtype=float) / np.linalg.norm(a)
    b = np.asarray(b, dtype=float) / np.linalg.norm(b)
    c = np.cross(a, b)
    s = np.linalg.norm(c)
    d = float(np.clip(np.dot(a, b), -1.0, 1.0))
    if s < 1e-12:
        if d > 0:
            return np.eye(3)
        perp = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(perp) < 1e-6:
            perp = np.cross(a, [0.0, 1.0, 0.0])
        return rotation_about_axis(perp, np.pi)
    return rotation_about_axis(c, np.arctan2(s, d))


def minimal_rotations_onto(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """
    Smallest rotations (N, 3, 3) taking each unit vector ``a[i]`` (N, 3) onto unit ``b`` (3,).

    Rodrigues with axis ``a x b``; for (nearly) antiparallel pairs a half turn about an axis
    perpendicular to ``b`` is used.
    """
    a = np.asarray(a, dtype=float)
    c = np.stack([a[:, 1] * b[2] - a[:, 2] * b[1], a[:, 2] * b[0] - a[:, 0] * b[2],
                  a[:, 0] * b[1] - a[:, 1] * b[0]], axis=1)
    s = np.sqrt(np.einsum('ni,ni->n', c, c))
    d = np.clip(a @ b, -1.0, 1.0)
    out = np.empty((a.shape[0], 3, 3))
    ok = s > 1e-12
    if ok.any():
        k = c[ok] / s[ok, None]
        K = np.zeros((k.shape[0], 3, 3))
        K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
        K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
        # sin = s, cos = d (exact, no arctan round trip)
        out[ok] = np.eye(3) + s[ok, None, None] * K + (1.0 - d[ok, None, None]) * (K @ K)
    for i in np.flatnonzero(~ok):
        if d[i] > 0:
            out[i] = np.eye(3)
        else:
            e1, _ = perpendicular_basis(b)
            out[i] = 2.0 * np.outer(e1, e1) - np.eye(3)
    return out


def perpendicular_basis(n: np.ndarray) -> tuple:
    """Two unit vectors (3,) completing unit ``n`` to a right-handed orthonormal basis."""
    n = np.asarray(n, dtype=float)
    helper = np.eye(3)[int(np.argmin(np.abs(n)))]
    e1 = np.cross(n, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(n, e1)


def check_transform(T: np.ndarray, name: str = 'pose', tol: float = 1e-6) -> np.ndarray:
    """Validate a 4x4 rigid transform; return it as float array or raise ValueError naming why."""
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4):
        raise ValueError(f'{name}: expected a 4x4 transform, got shape {T.shape}')
    if not np.all(np.isfinite(T)):
        raise ValueError(f'{name}: contains NaN or infinite values')
    if not np.all(np.abs(T[3] - _LAST_ROW) <= 1e-8 + 1e-5 * _LAST_ROW):   # np.allclose
        raise ValueError(f'{name}: last row is {T[3].tolist()}, not [0, 0, 0, 1]')
    if not is_rotation_matrix(T[:3, :3], tol):
        raise ValueError(f'{name}: rotation block is not orthonormal with det +1 (tol {tol})')
    return T


def pose_from_xyz_quaternion(values, name: str = 'pose') -> np.ndarray:
    """
    Parse a pose parameter ``[x, y, z, qx, qy, qz, qw]`` into a 4x4 pose.

    The one parser of this parameter form in the workspace: metres; quaternion in ROS order,
    normalised here.

    :raises ValueError: naming ``name``: not 7 numbers, non-finite, or a zero quaternion.
    """
    try:
        v = np.asarray(list(values), dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f'{name} must be 7 numbers [x y z qx qy qz qw]: {exc}') from None
    if v.shape != (7,) or not np.all(np.isfinite(v)):
        raise ValueError(f'{name} must be 7 finite numbers [x y z qx qy qz qw], '
                         f'got {v.tolist()}')
    try:
        return make_transform(matrix_from_quaternion(v[3:]), v[:3])
    except ValueError as exc:
        raise ValueError(f'{name}: {exc}') from None
