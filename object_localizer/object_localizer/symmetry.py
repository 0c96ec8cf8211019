"""
Symmetries of a model and symmetry-aware pose errors (pure core, no ROS).

A pose of a symmetric object is only defined up to its symmetries: a cube turned by a quarter
turn, a cylinder turned about its axis, a sphere turned any way look the same, so "the" error of
an estimate is the smallest error over all poses equivalent to the truth (the BOP convention,
Hodan et al. 2016/2018). :func:`find_symmetries` finds a model's proper rotational symmetries
about its centroid from dense surface samples: continuous axes (tested at several angles) and
the discrete rotations among the 24 rotations of the principal-axis frame and the n-fold turns
(n <= 8) about each principal axis. :func:`symmetric_pose_error` gives the centroid
translation error (symmetry-invariant) and the smallest rotation error over the set.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import itertools
from typing import Any, List, Tuple

import numpy as np
from scipy.spatial import cKDTree

from stereo_manip_tools.mesh_io import surface_centroid
from stereo_manip_tools.transforms import rotation_about_axis

__all__ = ['ModelSymmetry', 'find_symmetries', 'mesh_symmetry', 'symmetric_pose_error',
           'symmetric_add', 'surface_centroid', 'nearest_equivalent_pose']


@dataclass
class ModelSymmetry:
    """
    Proper rotational symmetries of a model about ``centroid`` (model frame).

    :ivar centroid: (3,) centroid of the surface [m], fixed by every symmetry.
    :ivar rotations: (K, 3, 3) discrete symmetry rotations (identity included).
    :ivar continuous_axes: (A, 3) unit axes of continuous rotational symmetry (A = 3 for a
        sphere: any rotation).
    """

    centroid: np.ndarray
    rotations: np.ndarray
    continuous_axes: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    @property
    def fully_symmetric(self) -> bool:
        """Tell whether every rotation is a symmetry (two independent continuous axes)."""
        return len(self.continuous_axes) >= 2

    def rotation_set(self, step_deg: float = 0.25) -> np.ndarray:
        """
        (M, 3, 3) rotations equivalent to the identity.

        The discrete ones, each composed with turns about the continuous axis (if any) every
        ``step_deg`` degrees.
        """
        if len(self.continuous_axes) == 0:
            return self.rotations
        axis = self.continuous_axes[0]
        turns = np.stack([rotation_about_axis(axis, a) for a in
                          np.radians(np.arange(0.0, 360.0, step_deg))])
        return np.einsum('tij,kjl->tkil', turns, self.rotations).reshape(-1, 3, 3)


def _candidate_axes(Q: np.ndarray, normals: np.ndarray | None, count: int = 12) -> np.ndarray:
    """
    Axes a symmetry of the model may turn about.

    The model frame's axes (exact for models built symmetric in their own frame), the
    non-degenerate principal axes of the centred samples and the ``count`` most frequent normal
    directions (antipodes merged): the axes a symmetry of a polyhedron or a solid of
    revolution turns about. Earlier axes win over later ones within 2.5 degrees.
    """
    vals, vecs = np.linalg.eigh(Q.T @ Q)
    axes = [np.eye(3)[k] for k in range(3)]
    for k in range(3):
        # a principal axis is only defined when its moment differs from the other two
        others = np.delete(vals, k)
        if np.min(np.abs(others - vals[k])) > 0.05 * vals.max():
            axes.append(vecs[:, k])
    if normals is not None and len(normals):
        N = np.asarray(normals, float)
        N = N * np.where(N @ np.array([0.577, 0.578, 0.579]) < 0, -1.0, 1.0)[:, None]
        _, label, counts = np.unique(np.round(N * 20.0).astype(int), axis=0,
                                     return_inverse=True, return_counts=True)
        label = label.ravel()
        for k in np.argsort(-counts)[:count]:
            a = N[label == k].mean(axis=0)
            if np.linalg.norm(a) > 0:
                axes.append(a / np.linalg.norm(a))
    out: List[np.ndarray] = []
    for a in axes:
        if all(abs(float(a @ b)) < np.cos(np.radians(2.5)) for b in out):
            out.append(a)
    return np.array(out)


def find_symmetries(points: np.ndarray, spacing: float, normals: np.ndarray | None = None,
                    tolerance: float = 0.5, discrete: bool = True) -> ModelSymmetry:
    """
    Proper rotational symmetries of a surface given by near-uniform samples.

    A rotation about the centroid is a symmetry when the rotated samples lie on the surface:
    mean nearest-sample distance below ``tolerance * spacing`` and 99th percentile below
    ``2 * spacing``. Candidates: n-fold turns (n = 2..8) about the principal axes and the
    dominant normal directions (when ``normals`` are given), then the group they generate.

    :param points: (N, 3) dense surface samples, model frame [m].
    :param spacing: their spacing [m].
    :param normals: (N, 3) their normals (optional; finds the axes of degenerate inertia,
        e.g. a cube's).
    :param discrete: also search the discrete rotations; False: only the continuous axes
        (``rotations`` is the identity alone; what the tracking ICP needs, at a tenth of the
        cost).
    """
    P = np.asarray(points, dtype=float)
    c = P.mean(axis=0)
    Q = P - c
    tree = cKDTree(Q)

    def is_symmetry(R: np.ndarray) -> bool:
        d = tree.query(Q @ R.T)[0]
        return bool(d.mean() < tolerance * spacing and np.percentile(d, 99) < 2.0 * spacing)

    def known(R: np.ndarray, found: List[np.ndarray]) -> bool:
        return any(np.abs(R - F).max() < 0.05 for F in found)

    axes_all = _candidate_axes(Q, normals)
    axes = [a for a in axes_all[:6]
            if all(is_symmetry(rotation_about_axis(a, ang)) for ang in (0.37, 1.13, 2.31, 4.0))]
    found: List[np.ndarray] = [np.eye(3)]
    if len(axes) >= 2 or not discrete:      # a sphere: every rotation
        return ModelSymmetry(c, np.stack(found), np.array(axes).reshape(-1, 3))
    for a in axes_all:
        for n in range(8, 1, -1):
            R = rotation_about_axis(a, 2 * np.pi / n)
            if known(R, found) or not is_symmetry(R):
                continue
            for j in range(1, n):
                Rj = rotation_about_axis(a, 2 * np.pi * j / n)
                if not known(Rj, found):
                    found.append(Rj)
            break
    grown = True
    while grown and len(found) < 64:     # closure: products of symmetries are symmetries
        grown = False
        for A, B in itertools.product(list(found), repeat=2):
            R = A @ B
            if not known(R, found) and is_symmetry(R):
                found.append(R)
                grown = True
    return ModelSymmetry(c, np.stack(found), np.array(axes).reshape(-1, 3))


def symmetric_pose_error(pose_estimate: np.ndarray, pose_true: np.ndarray,
                         symmetry: ModelSymmetry,
                         rotation_set: np.ndarray | None = None) -> Tuple[float, float]:
    """
    Symmetry-aware pose error: (translation of the centroid [m], rotation [rad]).

    The rotation error is the smallest angle of ``R_est^T R_true G`` over the symmetry
    rotations G (0 for a fully symmetric model); the centroid, fixed by every symmetry, gives
    the translation error.

    :param rotation_set: precomputed ``symmetry.rotation_set()`` (saves time in loops).
    """
    Te, Tt = np.asarray(pose_estimate, float), np.asarray(pose_true, float)
    c = symmetry.centroid
    e_t = float(np.linalg.norm(Te[:3, :3] @ c + Te[:3, 3] - Tt[:3, :3] @ c - Tt[:3, 3]))
    if symmetry.fully_symmetric:
        return e_t, 0.0
    G = symmetry.rotation_set() if rotation_set is None else rotation_set
    A = Te[:3, :3].T @ Tt[:3, :3]
    traces = np.einsum('ij,kji->k', A, G)
    cos = np.clip((traces.max() - 1.0) / 2.0, -1.0, 1.0)
    return e_t, float(np.arccos(cos))


def symmetric_add(pose_estimate: np.ndarray, pose_true: np.ndarray, model_points: np.ndarray,
                  symmetry: ModelSymmetry, rotation_set: np.ndarray | None = None,
                  centre: np.ndarray | None = None) -> float:
    """
    ADD over the model's symmetries [m]: the smallest mean point distance to an equivalent truth.

    ``min over G of mean |T_est p - T_true S_G p|`` over the model points ``p`` (N, 3) [m,
    model frame], ``S_G`` the symmetry rotations about the centroid (continuous axes sampled,
    ``rotation_set``). Zero for a pose equivalent to the truth under a symmetry, whatever the
    sampling of the points: ADD-S (nearest model point) has a floor there when the points are
    not themselves symmetric (the peg's 3 mm voxel template, turned upside down onto itself:
    0.57 mm). For a fully symmetric model (a sphere): the distance between the centroids.

    :param rotation_set: precomputed ``symmetry.rotation_set()`` (saves time in loops).
    :param centre: (3,) the point every symmetry fixes [m, model frame], e.g. the mesh's exact
        surface centroid (:func:`surface_centroid`); default ``symmetry.centroid``, the mean
        of the surface samples it was found from, a few tenths of a mm off (the peg: 0.4 mm,
        which leaves 0.5 mm for the upside-down peg).
    """
    Te, Tt = np.asarray(pose_estimate, float), np.asarray(pose_true, float)
    c = symmetry.centroid if centre is None else np.asarray(centre, float)
    if symmetry.fully_symmetric:
        return float(np.linalg.norm(Te[:3, :3] @ c + Te[:3, 3] - Tt[:3, :3] @ c - Tt[:3, 3]))
    G = symmetry.rotation_set() if rotation_set is None else rotation_set
    P = np.asarray(model_points, float)
    A = P @ Te[:3, :3].T + Te[:3, 3]
    # S_G p = R_G (p - c) + c, then the true pose
    B = np.einsum('kij,nj->kni', G, P - c) + c
    B = B @ Tt[:3, :3].T + Tt[:3, 3]
    return float(np.min(np.mean(np.linalg.norm(B - A[None], axis=2), axis=1)))


def mesh_symmetry(mesh: Any, spacing: float = 0.003, max_samples: int = 8000,
                  seed: int = 0) -> Tuple[ModelSymmetry, np.ndarray]:
    """
    Return a polygon mesh's symmetries and the exact point they fix.

    :func:`find_symmetries` on near-uniform surface samples of ``mesh`` (``spacing`` [m], at
    most ``max_samples``, ``seed``), and the mesh's exact :func:`surface_centroid` (3,) [m,
    model frame]: the samples' mean is a few tenths of a mm off it (the peg: 0.4 mm), which
    an equivalent pose turned about it would carry.
    """
    from object_localizer.verification import sample_model_surface
    samples = sample_model_surface(mesh, spacing, max_samples=max_samples, seed=seed)
    return (find_symmetries(samples.points, samples.spacing),
            surface_centroid(np.asarray(mesh.vertices, dtype=float), mesh.triangles()))


def nearest_equivalent_pose(pose: np.ndarray, reference: np.ndarray, rotations: np.ndarray,
                            centre: np.ndarray) -> np.ndarray:
    """
    Return the pose equivalent to ``pose`` whose orientation is nearest ``reference``'s.

    The poses equivalent under the model's discrete symmetries ``S`` (rotations about
    ``centre``) put the same surface in the same place, ``T S_c`` with ``S_c: x -> S (x - c) +
    c``; of them, the one whose rotation is the smallest angle from ``reference``'s. A
    search cannot tell them apart (a square peg upside down is the same shape), but the
    model frame a robot plans with should not flip: a re-acquired pose keeps the frame of the
    pose before the loss, or of the initial pose.

    :param pose: (4, 4) model -> sensor.
    :param reference: (4, 4) model -> sensor, the orientation to stay near.
    :param rotations: (K, 3, 3) the symmetry rotations (``ModelSymmetry.rotations``, the
        identity included).
    :param centre: (3,) the point every symmetry fixes [m, model frame] (the mesh's exact
        :func:`surface_centroid`).
    :return: (4, 4) the equivalent pose (``pose`` itself when the identity is nearest).
    """
    T = np.asarray(pose, dtype=float)
    R = T[:3, :3]
    A = np.asarray(reference, dtype=float)[:3, :3].T @ R
    k = int(np.argmax(np.einsum('ij,kji->k', A, np.asarray(rotations, dtype=float))))
    S = np.asarray(rotations[k], dtype=float)
    if np.allclose(S, np.eye(3)):
        return T
    c = np.asarray(centre, dtype=float)
    out = T.copy()
    out[:3, :3] = R @ S
    out[:3, 3] = T[:3, 3] + R @ c - R @ S @ c
    return out
