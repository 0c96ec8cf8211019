"""Pose-error metrics and synthetic observations for evaluating localisation (pure core)."""

from __future__ import annotations

import numpy as np
from object_localizer.localization import facing_sensor, sample_surface
from scipy.spatial import cKDTree
from stereo_manip_tools.mesh_io import PolygonMesh
from stereo_manip_tools.transforms import transform_points

__all__ = ['add_s', 'sample_visible_surface']


def add_s(pose_estimate: np.ndarray, pose_true: np.ndarray, model_points: np.ndarray) -> float:
    """
    Compute the ADD-S pose error [m] (Hinterstoisser et al. 2012).

    Mean distance from each model point placed by ``pose_estimate`` to the nearest model point
    placed by ``pose_true``: the error measure for objects with symmetries (a box is
    indistinguishable under half turns), where a plain pose difference would be meaningless.

    :param model_points: (N, 3) samples of the model surface in the model frame [m].
    """
    A = transform_points(pose_estimate, model_points)
    B = transform_points(pose_true, model_points)
    return float(np.mean(cKDTree(B).query(A)[0]))


def sample_visible_surface(mesh: PolygonMesh, pose: np.ndarray, count: int,
                           seed: int = 0) -> np.ndarray:
    """
    Sample the surface of ``mesh`` at ``pose`` that faces the sensor.

    Uniform surface samples of ``mesh`` placed at ``pose`` (model -> sensor) whose faces face
    a sensor at the origin; (M, 3) [m], M <= count. Self-occlusion is not modelled.
    """
    pcd = sample_surface(mesh, count, seed)
    P = transform_points(pose, np.asarray(pcd.points))
    N = np.asarray(pcd.normals) @ np.asarray(pose)[:3, :3].T
    return P[facing_sensor(P, N)]
