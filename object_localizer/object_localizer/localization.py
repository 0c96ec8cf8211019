"""
Model-based localisation of known objects in a point cloud (Section 2.2 of the chapter).

Rough localisation: local descriptors (FPFH) matched between the model and the scene, with
RANSAC rejecting wrong correspondences (Fischler & Bolles) and the rigid transform of each
hypothesis from Umeyama's method. Fine localisation: ICP (Besl & McKay; point-to-plane, Chen &
Medioni) whose residuals are weighted by an M-estimator (Tukey's biweight or Huber), as in
Wheeler & Ikeuchi, so stereo outliers do not drag the pose.

All clouds are (N, 3) arrays in metres in the sensor frame (e.g. ``stereo_left_optical``);
poses are 4x4 transforms model frame -> sensor frame. Open3D does the nearest-neighbour work.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Tuple, TYPE_CHECKING

import numpy as np
import open3d as o3d

from stereo_manip_tools.mesh_io import PolygonMesh

if TYPE_CHECKING:  # pragma: no cover
    from object_localizer.acquisition import AcquisitionModel

__all__ = [
    'fpfh_features',
    'match_features_ransac',
    'ModelTemplate',
    'LocalizationResult',
    'sample_surface',
    'settle_plane',
    'facing_sensor',
    'prepare_model',
    'prepare_scene',
    'remove_dominant_plane',
    'rough_localize',
    'fine_localize',
    'localize',
    'segment_object_points',
    'crop_around',
]


@dataclass
class ModelTemplate:
    """
    A model ready for matching: surface samples, normals and FPFH features.

    :ivar name: model name.
    :ivar points: surface samples [m] in the model frame, shape (N, 3).
    :ivar normals: outward unit normals, shape (N, 3).
    :ivar voxel_size: sampling resolution [m] the features were computed at.
    """

    name: str
    points: np.ndarray
    normals: np.ndarray
    voxel_size: float
    cloud: o3d.geometry.PointCloud
    features: o3d.pipelines.registration.Feature


@dataclass
class LocalizationResult:
    """
    Outcome of a localisation.

    :ivar pose: 4x4 model -> sensor transform.
    :ivar inlier_fraction: share of the model samples facing the sensor that lie within
        2 x the M-estimator scale of the scene after alignment.
    :ivar rmse: RMS point-to-plane residual of the inliers [m].
    :ivar method: ``'rough+fine'`` or ``'fine'``.
    """

    pose: np.ndarray
    inlier_fraction: float
    rmse: float
    method: str


def fpfh_features(cloud: o3d.geometry.PointCloud,
                  voxel: float) -> o3d.pipelines.registration.Feature:
    """FPFH descriptors of ``cloud`` (normals set) at radius ``5 * voxel`` (m)."""
    return o3d.pipelines.registration.compute_fpfh_feature(
        cloud, o3d.geometry.KDTreeSearchParamHybrid(radius=5.0 * voxel, max_nn=100))


def sample_surface(mesh: PolygonMesh, count: int, seed: int = 0) -> o3d.geometry.PointCloud:
    """
    Sample the mesh surface uniformly, with outward face normals.

    ``count`` uniform samples of the mesh surface with their outward face normals, in the
    model frame [m]; seeded (``o3d.utility.random.seed``) so the samples repeat.
    """
    tm = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(mesh.vertices),
                                   o3d.utility.Vector3iVector(mesh.triangles()))
    tm.compute_triangle_normals()
    o3d.utility.random.seed(int(seed))
    return tm.sample_points_uniformly(number_of_points=count, use_triangle_normal=True)


def facing_sensor(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """
    Mask (N,) of the points (N, 3) [m, sensor frame] whose normals face a sensor at the origin.

    The surface stereo can see, self-occlusion aside.
    """
    return np.einsum('ij,ij->i', normals, -points) > 0


def prepare_model(mesh: PolygonMesh, voxel_size: float = 0.003, samples: int = 20000,
                  seed: int = 0) -> ModelTemplate:
    """Sample a model's surface uniformly and compute FPFH features at ``voxel_size`` [m]."""
    if voxel_size <= 0:
        raise ValueError(f'voxel_size must be > 0, got {voxel_size}')
    pcd = sample_surface(mesh, samples, seed).voxel_down_sample(voxel_size)
    return ModelTemplate(mesh.name, np.asarray(pcd.points).copy(), np.asarray(pcd.normals).copy(),
                         voxel_size, pcd, fpfh_features(pcd, voxel_size))


def prepare_scene(points: np.ndarray, voxel_size: float) -> o3d.geometry.PointCloud:
    """
    Down-sample a scene cloud (N, 3) [m] and estimate normals oriented towards the sensor.

    :raises ValueError: wrong shape or fewer than 10 finite points.
    """
    P = np.asarray(points, dtype=float)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f'scene points must have shape (N, 3), got {P.shape}')
    P = P[np.all(np.isfinite(P), axis=1)]
    if len(P) < 10:
        raise ValueError(f'scene has only {len(P)} finite points')
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P)).voxel_down_sample(voxel_size)
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=3.0 * voxel_size,
                                                              max_nn=30))
    pcd.orient_normals_towards_camera_location(np.zeros(3))
    return pcd


def settle_plane(points: np.ndarray, inliers: np.ndarray, distance: float,
                 max_iterations: int = 20) -> np.ndarray:
    """
    Settle a RANSAC plane: least-squares refits until its inlier set no longer changes.

    The plane through the inliers' centroid normal to their least-variance direction; its
    inliers are the points within ``distance`` [m]; repeated until they repeat. Nearby RANSAC
    planes of one surface (Open3D's threaded ``segment_plane`` returns one of them from run to
    run with the same seed: 47 463 or 47 661 table points of one cloud) settle on the same
    inlier set: the acquisitions that start from the scene repeat (11 of 54 differed between
    two runs before).

    :param points: (N, 3) points [m].
    :param inliers: indices of the RANSAC plane's inliers (at least 3).
    :return: sorted indices of the settled plane's inliers (those of the last refit when
        ``max_iterations`` is reached).
    """
    P = np.asarray(points, dtype=float)
    idx = np.sort(np.asarray(inliers, dtype=np.int64))
    for _ in range(max_iterations):
        Q = P[idx]
        c = Q.mean(axis=0)
        n = np.linalg.eigh(Q.T @ Q / len(Q) - np.outer(c, c))[1][:, 0]
        new = np.flatnonzero(np.abs(P @ n - c @ n) <= distance)
        if len(new) < 3 or np.array_equal(new, idx):
            break
        idx = new
    return idx


def remove_dominant_plane(scene: o3d.geometry.PointCloud, distance: float, min_extent: float,
                          min_fraction: float = 0.3, seed: int = 0) -> o3d.geometry.PointCloud:
    """
    Drop the largest plane (a table) of a scene cloud.

    Drop the largest plane (a table) if it holds at least ``min_fraction`` of the points and
    spans more than ``min_extent`` [m] (so an object's own face is never taken for a table).
    The RANSAC plane is settled by least squares (:func:`settle_plane`): Open3D's RANSAC runs
    in threads and, with one seed, returns one of several nearby planes from run to run.
    """
    o3d.utility.random.seed(seed)
    if len(scene.points) < 3:
        return scene
    _, inliers = scene.segment_plane(distance, 3, 500)
    points = np.asarray(scene.points)
    if len(inliers) >= 3:
        inliers = settle_plane(points, np.asarray(inliers), distance)
    if len(inliers) < min_fraction * len(scene.points):
        return scene
    plane = points[inliers]
    if np.linalg.norm(plane.max(axis=0) - plane.min(axis=0)) < min_extent:
        return scene
    return scene.select_by_index(np.asarray(inliers).tolist(), invert=True)


def rough_localize(model: ModelTemplate, scene: o3d.geometry.PointCloud, *,
                   seed: int = 0, max_iterations: int = 200000,
                   confidence: float = 0.999) -> np.ndarray:
    """
    Global pose hypothesis by FPFH matching + RANSAC (Umeyama per hypothesis); 4x4.

    Seeded (``o3d.utility.random.seed``) so results repeat.
    """
    features = fpfh_features(scene, model.voxel_size)
    pose, _ = match_features_ransac(model, scene, features, seed=seed,
                                    max_iterations=max_iterations, confidence=confidence)
    return pose


def match_features_ransac(model: ModelTemplate, scene: o3d.geometry.PointCloud,
                          scene_features: o3d.pipelines.registration.Feature, *, seed: int,
                          max_iterations: int, confidence: float = 0.999
                          ) -> Tuple[np.ndarray, float]:
    """
    One seeded FPFH-correspondence RANSAC run of ``model`` against ``scene``.

    :returns: the pose (4x4, model -> scene frame) and Open3D's fitness (inlier fraction of
        the model cloud, 0..1).
    """
    reg = o3d.pipelines.registration
    voxel = model.voxel_size
    o3d.utility.random.seed(seed)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        result = reg.registration_ransac_based_on_feature_matching(
            model.cloud, scene, model.features, scene_features, True, 2.0 * voxel,
            reg.TransformationEstimationPointToPoint(False), 3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
             reg.CorrespondenceCheckerBasedOnDistance(2.0 * voxel)],
            reg.RANSACConvergenceCriteria(max_iterations, confidence))
    return np.asarray(result.transformation).copy(), float(result.fitness)


def _visible_model(model: ModelTemplate, pose: np.ndarray) -> o3d.geometry.PointCloud:
    """Model samples whose normals face the sensor at ``pose`` (the part stereo can see)."""
    R, t = pose[:3, :3], pose[:3, 3]
    P = model.points @ R.T + t
    N = model.normals @ R.T
    keep = facing_sensor(P, N)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(model.points[keep]))
    pcd.normals = o3d.utility.Vector3dVector(model.normals[keep])
    return pcd


def fine_localize(model: ModelTemplate, scene: o3d.geometry.PointCloud, initial: np.ndarray, *,
                  max_distance: float = 0.01, loss: str = 'tukey', loss_scale: float = 0.0015,
                  max_iterations: int = 50) -> LocalizationResult:
    """
    Point-to-plane ICP from ``initial`` with M-estimator weights (``tukey``/``huber``/``l2``).

    Only the model samples facing the sensor take part (the far side is never observed).

    :param max_distance: final correspondence search radius [m] (annealed from twice that).
    :param loss_scale: the M-estimator's scale k [m] (Tukey: residuals beyond k get weight 0);
        the kernel is annealed 4k -> 2k -> k.
    """
    reg = o3d.pipelines.registration
    kernels = {'tukey': reg.TukeyLoss, 'huber': reg.HuberLoss}
    if loss not in ('tukey', 'huber', 'l2'):
        raise ValueError(f'loss must be tukey, huber or l2, got {loss!r}')
    if not scene.has_normals():
        raise ValueError('scene cloud needs normals (use prepare_scene)')
    pose = np.asarray(initial, dtype=float).copy()
    # Graduated M-estimation: start wide (kernel 4k, search radius 2 x max_distance) so a distant
    # start converges, end at k and max_distance so that outliers beyond k get no weight; the
    # visible part of the model is refreshed at each stage.
    for scale, reach in ((4.0 * loss_scale, 2.0 * max_distance),
                         (2.0 * loss_scale, 1.5 * max_distance), (loss_scale, max_distance)):
        src = _visible_model(model, pose)
        est = reg.TransformationEstimationPointToPlane(kernels[loss](k=scale)) \
            if loss != 'l2' else reg.TransformationEstimationPointToPlane()
        result = reg.registration_icp(src, scene, reach, pose, est,
                                      reg.ICPConvergenceCriteria(1e-9, 1e-9, max_iterations))
        pose = np.asarray(result.transformation).copy()
    src = _visible_model(model, pose)
    ev = reg.evaluate_registration(src, scene, 2.0 * loss_scale, pose)
    return LocalizationResult(pose, float(ev.fitness), float(ev.inlier_rmse), 'fine')


def localize(model: ModelTemplate, scene_points: np.ndarray, *,
             prior: Optional[np.ndarray] = None, min_inlier_fraction: float = 0.5,
             seed: int = 0, max_distance: float = 0.01, loss: str = 'tukey',
             loss_scale: float = 0.0015, drop_plane: bool = True, attempts: int = 5,
             accept_fraction: float = 0.9, acquisition: Optional['AcquisitionModel'] = None,
             camera: Optional[object] = None) -> LocalizationResult:
    """
    Localise ``model`` in a scene cloud (N, 3) [m].

    Fine from ``prior`` when it holds, else rough + fine.

    The global search runs up to ``attempts`` seeded RANSAC hypotheses, each refined, and keeps
    the one with the most inliers (then the lowest RMS); it stops early once a hypothesis
    explains ``accept_fraction`` of the visible model. With ``acquisition`` (an
    :class:`~object_localizer.acquisition.AcquisitionModel` of the same object) the global
    search is :func:`~object_localizer.acquisition.acquire_object` instead: PPF voting,
    visibility verification (``camera`` intrinsics, or a virtual camera) and ICP, then this
    function's fine stage from its best hypothesis (method ``'acquisition+fine'``).

    :raises ValueError: unusable clouds.
    """
    if prior is not None:
        # tracking: only the neighbourhood of the prior matters (and keeps ICP fast)
        near = crop_around(scene_points, model, prior, 2.0 * max_distance + 0.01)
        if len(near) >= 10:
            res = fine_localize(model, prepare_scene(near, model.voxel_size / 2.0), prior,
                                max_distance=max_distance, loss=loss, loss_scale=loss_scale)
            if res.inlier_fraction >= min_inlier_fraction:
                return res
    scene = prepare_scene(scene_points, model.voxel_size / 2.0)
    if acquisition is not None:
        from object_localizer.acquisition import acquire_object
        hyps = acquire_object(acquisition, scene_points, camera=camera, seed=seed)
        if hyps:
            res = fine_localize(model, scene, hyps[0].pose, max_distance=max_distance,
                                loss=loss, loss_scale=loss_scale)
            res.method = 'acquisition+fine'
            return res
    search = prepare_scene(scene_points, model.voxel_size)
    if drop_plane:
        diameter = float(np.linalg.norm(model.points.max(axis=0) - model.points.min(axis=0)))
        search = remove_dominant_plane(search, model.voxel_size, 2.0 * diameter, seed=seed)
    best: Optional[LocalizationResult] = None
    for attempt in range(attempts):
        rough = rough_localize(model, search, seed=seed + attempt)
        res = fine_localize(model, scene, rough, max_distance=max_distance, loss=loss,
                            loss_scale=loss_scale)
        res.method = 'rough+fine'
        if best is None or (res.inlier_fraction, -res.rmse) > (best.inlier_fraction, -best.rmse):
            best = res
        if best.inlier_fraction >= max(min_inlier_fraction, accept_fraction):
            break
    assert best is not None
    return best


def crop_around(points: np.ndarray, model: ModelTemplate, pose: np.ndarray,
                margin: float) -> np.ndarray:
    """Finite points (N, 3) [m] within the model's bounding sphere at ``pose`` plus ``margin``."""
    P = np.asarray(points, dtype=float)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f'scene points must have shape (N, 3), got {P.shape}')
    P = P[np.all(np.isfinite(P), axis=1)]
    centre_model = 0.5 * (model.points.min(axis=0) + model.points.max(axis=0))
    radius = float(np.max(np.linalg.norm(model.points - centre_model, axis=1)))
    centre = pose[:3, :3] @ centre_model + pose[:3, 3]
    return P[np.linalg.norm(P - centre, axis=1) <= radius + margin]


def segment_object_points(points: np.ndarray, model: ModelTemplate, pose: np.ndarray,
                          margin: float = 0.005) -> np.ndarray:
    """
    Cut the object's own points out of a scene cloud.

    Scene points (N, 3) [m] that fall inside the model's bounding box at ``pose``, grown by
    ``margin`` [m] on every side: the object's own cloud, e.g. for implicit-polynomial fitting.
    """
    P = np.asarray(points, dtype=float)
    P = P[np.all(np.isfinite(P), axis=1)]
    local = (P - pose[:3, 3]) @ pose[:3, :3]
    lo = model.points.min(axis=0) - margin
    hi = model.points.max(axis=0) + margin
    return P[np.all((local >= lo) & (local <= hi), axis=1)]
