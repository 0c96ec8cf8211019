"""
The square-marker pose ambiguity (IPPE twin) as a structured outlier model (pure numpy).

A planar marker seen by a camera has two poses that explain its image almost equally well
(Collins & Bartoli 2014, IPPE; OpenCV's ``SOLVEPNP_IPPE_SQUARE`` returns both): under the
affine approximation the second one has the marker's normal mirrored about the line of sight
and nearly the same translation. When noise makes the wrong one win, the pose is *flipped*:
its orientation is off by twice the angle between the normal and the line of sight (tens of
degrees), its position nearly right, often for runs of frames.

Given the pose the detector returned, the twin is rebuilt here: with ``n`` the marker normal
(axis ``normal_axis`` of the marker frame, z for ArUco/AprilTag/OpenCV) and ``v`` the unit line
of sight from the camera to the marker's origin, the twin normal is ``n' = 2 (n.v) v - n`` and
the twin orientation is the minimal rotation taking ``n`` to ``n'`` applied to the pose's
orientation; the translation is kept. On OpenCV's solutions this reproduces the second IPPE
solution to about 0.1 deg (checked in the tests).

The joint estimator (:func:`joint_estimator.selection.estimate_joint`) takes, per frame, a set
of candidate poses (the pose and its twin; four combinations when both links are markers seen
by one camera) and uses for every frame the candidate that fits the joint hypothesis best, so a
flipped frame is repaired instead of dropped.
"""

from __future__ import annotations

from joint_estimator.common import relative_track
import numpy as np

__all__ = ['marker_twins', 'relative_candidates', 'two_link_candidates', 'AXIS_INDEX',
           'MIN_MARKER_DISTANCE']

#: Markers closer to the camera than this [m] get no twin (no camera sees them; the line of
#: sight of a pose near the camera centre is noise).
MIN_MARKER_DISTANCE = 0.05

#: Marker-normal axis names and their column index.
AXIS_INDEX = {'x': 0, 'y': 1, 'z': 2}


def marker_twins(poses: np.ndarray, normal_axis: int = 2) -> np.ndarray:
    """
    Return the ambiguous twin of every marker pose in the camera frame.

    :param poses: (N, 4, 4) poses of the marker in the camera's frame ``^C T_M`` [m].
    :param normal_axis: column of the marker's rotation that is its normal (2 = z).
    :returns: (N, 4, 4) twin poses: same translation, normal mirrored about the line of sight.
        Poses closer than :data:`MIN_MARKER_DISTANCE` to the camera are returned unchanged.
    """
    T = np.asarray(poses, dtype=float)
    t = T[:, :3, 3]
    dist = np.linalg.norm(t, axis=1)
    ok = dist > MIN_MARKER_DISTANCE
    v = np.zeros_like(t)
    v[ok] = t[ok] / dist[ok, None]
    n = T[:, :3, normal_axis]
    n_twin = 2.0 * np.einsum('ni,ni->n', n, v)[:, None] * v - n
    n_twin /= np.maximum(np.linalg.norm(n_twin, axis=1), 1e-300)[:, None]
    # minimal rotation taking n onto n_twin (Rodrigues about n x n_twin; both unit)
    c = np.cross(n, n_twin)
    s = np.linalg.norm(c, axis=1)
    d = np.clip(np.einsum('ni,ni->n', n, n_twin), -1.0, 1.0)
    rot = ok & (s > 1e-12)
    out = T.copy()
    if rot.any():
        k = c[rot] / s[rot, None]
        K = np.zeros((k.shape[0], 3, 3))
        K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
        K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
        D = np.eye(3) + s[rot, None, None] * K + (1.0 - d[rot, None, None]) * (K @ K)
        out[rot, :3, :3] = D @ T[rot, :3, :3]
    return out


def relative_candidates(poses: np.ndarray, normal_axis: int = 2) -> np.ndarray:
    """
    Candidates (N, 2, 4, 4) of a relative track seen by a camera on link B.

    Candidates (N, 2, 4, 4) of a relative track ``^B T_A`` where link B is the camera and
    link A carries the marker: the pose and its twin (:func:`marker_twins`).
    """
    T = np.asarray(poses, dtype=float)
    return np.stack([T, marker_twins(T, normal_axis)], axis=1)


def two_link_candidates(link_a: np.ndarray, link_b: np.ndarray,
                        normal_axis: int = 2) -> np.ndarray:
    """
    Candidates (N, 4, 4, 4) of the relative track when both links carry markers.

    Candidates (N, 4, 4, 4) of the relative track when both links carry markers whose poses
    are given in the camera's frame: ``(A, B), (twin A, B), (A, twin B), (twin A, twin B)``;
    the first is the relative track of the poses as given.
    """
    A = np.asarray(link_a, dtype=float)
    B = np.asarray(link_b, dtype=float)
    A2, B2 = marker_twins(A, normal_axis), marker_twins(B, normal_axis)
    return np.stack([relative_track(A, B), relative_track(A2, B), relative_track(A, B2),
                     relative_track(A2, B2)], axis=1)
