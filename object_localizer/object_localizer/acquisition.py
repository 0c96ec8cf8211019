"""
Global acquisition of a known object in a scene cloud, from nothing (pure core, no ROS).

API (the tracker and the node build on these; signatures are stable)::

    model = prepare_acquisition_model(mesh)                  # once per object model
    scene = prepare_acquisition_scene(points, camera=None)   # once per cloud (optional)
    hyps = acquire_object(model, scene_or_points, scene_normals=None, camera=None,
                          method='ppf', seed=0, time_budget_s=0.5)   # -> list[Hypothesis]
    best = hyps[0]   # best first; best.pose (4x4 model -> optical frame), best.score (0..1)

    observed = observe_depth(points, camera)                 # verification.py
    q = score_pose_visibility(model.surface, pose, observed) # VisibilityScore, the visible-
                                                             # surface quality for tracking too

Stages (each hypothesis keeps the figures of every stage, see :class:`Hypothesis`):

1. **Rough** -- ``method='ppf'`` (default): point-pair-feature voting (Drost et al. 2010,
   :mod:`object_localizer.ppf`) over the scene without its dominant plane, sampled at 5 % of
   the model diameter (at most 1 cm); pose clusters ranked by votes (``max_rough`` kept per
   round; ``rough_rounds`` rounds with different seeds, pooled).
   ``method='fpfh'``: FPFH matching + RANSAC (as
   :func:`object_localizer.localization.rough_localize`) run ``fpfh_attempts`` times with
   different seeds, one hypothesis each.
2. **Verification** -- every rough hypothesis is rendered with the camera intrinsics and
   scored against the observed depth (:func:`~object_localizer.verification.
   score_pose_visibility`: visible-surface inliers minus free-space violations, weighted by
   the silhouette's depth-edge support -- ``VisibilityScore.combined``), at a tolerance
   matched to the rough pose accuracy.
3. **Refinement** -- the ``max_refined`` best go through point-to-plane ICP with a Tukey
   M-estimator annealed from the PPF step to the stereo noise (the tracker's compiled
   :func:`~object_localizer.point_to_plane.icp_point_to_plane`; scene normals estimated once
   per cloud, :meth:`AcquisitionScene.icp_crop`), using only the model samples
   the camera sees (not hidden behind observed surfaces); a hypothesis scoring clearly below
   the best refined one so far is not refined (``skip_margin``) or stops after the wide ICP
   stage (``prune_margin``), nor is one at the place of a refined one up to the model's
   symmetries (``equivalent_distance``: a sphere's rough poses); the best ``max_slide`` are then
   searched along the model's principal axes by the visibility score (ICP cannot slide a long
   prism whose ends are far off) and refined again. Final verification at the stereo depth
   tolerance (``fine_tolerance``, ``Hypothesis.score``).
4. **Ranking** -- by ``score``; with ``final_check=True`` the refined hypotheses are
   polished by the tracker's ICP and sorted by the tracker's per-sample check
   (``tracking.check_pose``, ``Hypothesis.check``) x ``score`` (measured trade-off: see the
   ``final_check`` parameter).

A caller decides acceptance from ``Hypothesis.score`` (and ``inlier_fraction``,
``visibility``): on the synthetic stereo scenes right poses score about 0.45-0.95, poses
sunk into a larger surface keep a high ``visibility.score`` but a low ``edge_fraction``.
Symmetric objects give several hypotheses equivalent under their symmetries with equal
scores; any one is right. Two identical objects in view (e.g. ``link_base`` and ``link_arm``,
the same brick) cannot be told apart by geometry: either may be returned.

Pass the camera with its stereo ``baseline`` (``camera={'fx': .., 'baseline': ..}``): the
visibility score then knows which model pixels stereo can measure (see
:mod:`object_localizer.verification`); without it (virtual camera) it does not.

Limitations (measured in ``bench/localizer_acquisition.py``): thin or mostly occluded objects
in stereo clouds (silhouettes fattened by block matching, holes, parts nearer than the
stereo's minimum depth) are the failures; time is above 0.5 s per object on this 2-core
machine.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import time
from typing import Any, Dict, List, Optional, Tuple, Union

import numba
import numpy as np
from object_localizer.localization import (fpfh_features, match_features_ransac,
                                           ModelTemplate, prepare_model, prepare_scene,
                                           remove_dominant_plane)
from object_localizer.point_to_plane import icp_point_to_plane
from object_localizer.ppf import build_ppf_model, cluster_poses, ppf_vote, PPFModel
from object_localizer.tracking import (check_pose, pose_support, PoseQuality,
                                       prepare_tracking_model, principal_axes,
                                       refine_and_check, SceneCloud,
                                       search_along_axes, slide_along_axes, track_icp,
                                       TrackerSettings, TrackingModel, unexplained)
from object_localizer.verification import (as_camera, CameraLike, observe_depth, ObservedDepth,
                                           sample_model_surface, score_pose_visibility,
                                           SurfaceSamples, unoccluded_mask, VisibilityScore)
import open3d as o3d
from scipy.spatial import cKDTree
from stereo_manip_tools.mesh_io import PolygonMesh

__all__ = [
    'METHODS',
    'AcquisitionModel',
    'AcquisitionScene',
    'Hypothesis',
    'prepare_acquisition_model',
    'prepare_acquisition_scene',
    'acquire_object',
    'polish_hypothesis',
    'score_pose_visibility',
    'observe_depth',
]

#: Rough methods of :func:`acquire_object`.
METHODS = ('ppf', 'fpfh')


@dataclass
class AcquisitionModel:
    """
    Everything acquisition needs about one object model (build once, reuse per cloud).

    :ivar name: model name.
    :ivar template: samples + FPFH features at ``template.voxel_size`` (ICP and the FPFH path).
    :ivar ppf: the point-pair-feature table (sampled at ``ppf.distance_step``).
    :ivar surface: dense surface samples for rendering (verification).
    :ivar centroid: (3,) surface centroid, model frame [m].
    :ivar diameter: model diameter [m].
    :ivar axes: (3, 3) principal axes of the surface (rows), model frame.
    :ivar check: the tracker's model (dense samples) for the final per-sample check
        (``tracking.check_pose``) that ranks the refined hypotheses.
    """

    name: str
    template: ModelTemplate
    ppf: PPFModel
    surface: SurfaceSamples
    centroid: np.ndarray
    diameter: float
    axes: np.ndarray = field(default_factory=lambda: np.eye(3))
    check: Optional[TrackingModel] = None


@dataclass
class Hypothesis:
    """
    One acquisition result (best first in :func:`acquire_object`'s list).

    :ivar pose: 4x4 model -> camera optical frame (after refinement when ``refined``).
    :ivar score: final ranking score in [0, 1]: ``visibility.combined`` (visible-surface
        score weighted by the silhouette edge support).
    :ivar method: rough method, ``'ppf'`` or ``'fpfh'``.
    :ivar rough_score: the rough stage's own support (PPF cluster votes; RANSAC fitness).
    :ivar rough_visibility: visibility score of the rough pose (coarse tolerance).
    :ivar visibility: visibility figures of the final pose (stereo tolerance).
    :ivar inlier_fraction: ICP inlier fraction of the model's visible samples (NaN unrefined).
    :ivar rmse: ICP inlier RMS point-to-plane residual [m] (NaN unrefined).
    :ivar refined: whether the pose went through ICP.
    :ivar check: the tracker's per-sample check of the final pose (``tracking.check_pose``,
        acquisition thresholds) that ranks the refined hypotheses; None when not checked.
    """

    pose: np.ndarray
    score: float
    method: str
    rough_score: float
    rough_visibility: float
    visibility: Optional[VisibilityScore] = None
    inlier_fraction: float = float('nan')
    rmse: float = float('nan')
    refined: bool = False
    check: Optional[PoseQuality] = None


@dataclass
class AcquisitionScene:
    """
    A scene cloud with the derived data acquisition needs.

    A scene cloud with the derived data acquisition needs, computed lazily and cached (one
    per cloud, shared by all objects searched in it).

    :ivar points: (N, 3) finite scene points [m], optical frame.
    :ivar normals: (N, 3) given normals or None (then estimated per sampling step).
    :ivar camera: intrinsics or None (a virtual camera is used for visibility).
    :ivar stereo_baseline: stereo baseline [m] (second camera at +x) used when ``camera`` is
        None or carries none: the visibility score's stereo reasoning (0: not stereo).
    """

    points: np.ndarray
    normals: Optional[np.ndarray] = None
    camera: Any = None
    stereo_baseline: float = 0.0
    _clouds: Dict[Any, o3d.geometry.PointCloud] = field(default_factory=dict, repr=False)
    _observed: Optional[ObservedDepth] = field(default=None, repr=False)
    _rays: Optional[SceneCloud] = field(default=None, repr=False)
    _icp: Dict[float, list] = field(default_factory=dict, repr=False)
    _visibility: Dict[Any, Tuple[SurfaceSamples, VisibilityScore]] = field(
        default_factory=dict, repr=False)

    def cloud(self, voxel: float, drop_plane: bool = False,
              min_plane_extent: float = 0.0, seed: int = 0) -> o3d.geometry.PointCloud:
        """
        Return the scene down-sampled at ``voxel`` [m] with normals towards the sensor.

        The scene down-sampled at ``voxel`` [m] with normals towards the sensor, optionally
        without its dominant plane (a table larger than ``min_plane_extent``).
        """
        key = (round(voxel, 6), drop_plane, round(min_plane_extent, 4) if drop_plane else 0)
        if key in self._clouds:
            return self._clouds[key]
        if drop_plane:
            base = self.cloud(voxel)
            pcd = remove_dominant_plane(base, max(voxel, 0.004), min_plane_extent, seed=seed)
        elif self.normals is not None:
            pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(self.points))
            pcd.normals = o3d.utility.Vector3dVector(self.normals)
            pcd = pcd.voxel_down_sample(voxel)
            pcd.normalize_normals()
            pcd.orient_normals_towards_camera_location(np.zeros(3))
        else:
            pcd = prepare_scene(self.points, voxel)
        self._clouds[key] = pcd
        return pcd

    def downsampled(self, voxel: float) -> o3d.geometry.PointCloud:
        """Return the scene down-sampled at ``voxel`` [m], without normals (cached)."""
        key = ('plain', round(voxel, 6))
        if key not in self._clouds:
            pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(self.points))
            self._clouds[key] = pcd.voxel_down_sample(voxel)
        return self._clouds[key]

    def crop(self, cloud: o3d.geometry.PointCloud, centre_model: np.ndarray, pose: np.ndarray,
             radius: float) -> o3d.geometry.PointCloud:
        """Select points of ``cloud`` within ``radius`` [m] of ``pose`` @ ``centre_model``."""
        c = pose[:3, :3] @ centre_model + pose[:3, 3]
        P = np.asarray(cloud.points)
        idx = np.flatnonzero(np.sum((P - c) ** 2, axis=1) <= radius * radius)
        return cloud.select_by_index(idx)

    def icp_crop(self, voxel: float, centre: np.ndarray, radius: float
                 ) -> Tuple[np.ndarray, np.ndarray, Any]:
        """
        Return the scene points within ``radius`` [m] of ``centre`` with normals, for ICP.

        The scene down-sampled at ``voxel`` [m] (built once); normals (towards the sensor) from
        the principal axes of each point's neighbours within ``3 * voxel`` (at most 30, in
        the whole down-sampled scene) are estimated the first time a crop holds the point and
        kept: the crops of all hypotheses and objects of a cloud overlap, so every point's
        normal is computed once per cloud.

        :return: points (K, 3), unit normals (K, 3), and their indices (K,) in the
            down-sampled scene (for :meth:`crop_distances`).
        """
        from scipy.spatial import cKDTree
        key = round(voxel, 6)
        if key not in self._icp:
            P = np.asarray(self.downsampled(voxel).points)
            self._icp[key] = [P, cKDTree(P), np.full(P.shape, np.nan)]
        P, tree, normals = self._icp[key]
        idx = np.asarray(tree.query_ball_point(np.asarray(centre, dtype=float), radius),
                         dtype=np.int64)
        todo = idx[np.isnan(normals[idx, 0])]
        if len(todo):
            normals[todo] = _pca_normals(P, tree, todo, 3.0 * voxel, 30)
        return P[idx], normals[idx], idx

    def crop_distances(self, voxel: float, crop: np.ndarray, X: np.ndarray,
                       bound: float) -> np.ndarray:
        """
        Distance [m] from each point of ``X`` (M, 3) to the nearest point of a crop.

        ``crop``: the indices :meth:`icp_crop` returned at the same ``voxel``; inf where no
        crop point is within ``bound`` [m]. The scene's KD-tree answers it (a crop's own tree
        cost 6 ms per hole_block acquisition); a point whose nearest scene point lies outside
        the crop is searched among its 16 nearest within ``bound``, else among all the crop's
        points: the distances of the crop's own tree, exactly.
        """
        P, tree, _ = self._icp[round(voxel, 6)]
        inside = np.zeros(len(P), dtype=bool)
        inside[crop] = True
        X = np.asarray(X, dtype=float)
        d, j = tree.query(X, distance_upper_bound=bound)
        found = np.isfinite(d)
        redo = np.flatnonzero(found & ~inside[np.where(found, j, 0)])
        if len(redo):
            dk, jk = tree.query(X[redo], k=16, distance_upper_bound=bound)
            okk = np.isfinite(dk) & inside[np.where(np.isfinite(dk), jk, 0)]
            first = np.argmax(okk, axis=1)
            hit = okk[np.arange(len(redo)), first]
            d[redo] = np.where(hit, dk[np.arange(len(redo)), first], np.inf)
            # all 16 within the bound and none in the crop: every crop point, exactly
            Q = P[crop]
            for r in redo[~hit & np.isfinite(dk[:, -1])]:
                e = np.sqrt(((Q - X[r]) ** 2).sum(axis=1)).min() if len(Q) else np.inf
                d[r] = e if e <= bound else np.inf
        return d

    def rays(self) -> SceneCloud:
        """Return the scene as the tracker's :class:`~object_localizer.tracking.SceneCloud`."""
        if self._rays is None:
            self._rays = SceneCloud(self.points)
        return self._rays

    def observed(self) -> ObservedDepth:
        """Observed depth image for verification (built once)."""
        if self._observed is None:
            self._observed = observe_depth(self.points, self.camera,
                                           stereo_baseline=self.stereo_baseline)
        return self._observed

    def visibility(self, surface: SurfaceSamples, pose: np.ndarray,
                   tolerance: float) -> VisibilityScore:
        """
        Return ``score_pose_visibility`` of ``pose`` against :meth:`observed` (memoised).

        The search scores the same pose several times (before and after ICP, at the start of
        a slide); each (surface, pose, tolerance [m]) is rendered once per cloud.
        """
        pose = np.asarray(pose, dtype=np.float64)
        key = (id(surface), pose.tobytes(), float(tolerance))
        held = self._visibility.get(key)
        if held is None or held[0] is not surface:     # (a freed surface's id reused)
            held = self._visibility[key] = (surface, score_pose_visibility(
                surface, pose, self.observed(), inlier_threshold=tolerance))
        return held[1]


def _pca_normals(P: np.ndarray, tree: Any, idx: np.ndarray, radius: float,
                 max_nn: int) -> np.ndarray:
    """
    Return unit normals (K, 3) of points ``P[idx]``, towards the sensor at the origin.

    The eigenvector of the smallest eigenvalue of the covariance of each point's nearest
    ``max_nn`` neighbours within ``radius`` [m] (Open3D's hybrid search); (0, 0, -1) ... turned
    towards the sensor when fewer than 3 neighbours. The covariances and eigenvectors are
    compiled (:func:`_pca_normals_kernel`): the same normals as the vectorised NumPy version
    it replaced, at a third of its time (slot_block's crop of 11850 points: 108 -> 39 ms,
    of which 25 ms is the neighbour search).
    """
    d, nn = tree.query(P[idx], k=max_nn, distance_upper_bound=radius)
    ok = np.isfinite(np.asarray(d).reshape(len(idx), -1))
    nn = np.where(ok, np.asarray(nn).reshape(len(idx), -1), 0)
    return _pca_normals_kernel(np.ascontiguousarray(P, dtype=np.float64), nn, ok,
                               np.asarray(idx, dtype=np.int64))


@numba.njit(cache=True)
def _pca_normals_kernel(P, nn, ok, idx):  # pragma: no cover - numba
    K, k = nn.shape
    out = np.empty((K, 3))
    for i in range(K):
        cnt = 0
        m = np.zeros(3)
        for j in range(k):
            if ok[i, j]:
                m += P[nn[i, j]]
                cnt += 1
        if cnt < 3:
            out[i, 0], out[i, 1], out[i, 2] = 0.0, 0.0, -1.0
        else:
            m /= cnt
            C = np.zeros((3, 3))
            for j in range(k):
                if ok[i, j]:
                    dv = P[nn[i, j]] - m
                    for a in range(3):
                        for b in range(3):
                            C[a, b] += dv[a] * dv[b]
            C /= cnt
            V = np.linalg.eigh(C)[1]
            out[i] = V[:, 0]
        p = P[idx[i]]
        if out[i, 0] * p[0] + out[i, 1] * p[1] + out[i, 2] * p[2] > 0:
            out[i] = -out[i]
    return out


def prepare_acquisition_model(mesh: PolygonMesh, *, ppf_relative_step: float = 0.05,
                              ppf_max_step: float = 0.01, icp_voxel: float = 0.003,
                              surface_spacing: float = 0.0015,
                              seed: int = 0,
                              check_model: Optional[TrackingModel] = None) -> AcquisitionModel:
    """
    Build the matching data of a model: ICP/FPFH template, PPF table, render samples.

    :param ppf_relative_step: PPF sampling and distance step as a fraction of the diameter
        (Drost: 0.05) ...
    :param ppf_max_step: ... but at most this [m], so thin parts of long objects (a 2 cm high
        rail 30 cm long) keep enough samples and usable normals.
    :param icp_voxel: voxel [m] of the ICP/FPFH template (:func:`prepare_model`).
    :param surface_spacing: spacing [m] of the render samples for verification.
    :param check_model: the tracker's model of the same mesh (built when None).
    """
    if not 0 < ppf_relative_step < 0.5:
        raise ValueError(f'ppf_relative_step must be in (0, 0.5), got {ppf_relative_step}')
    template = prepare_model(mesh, voxel_size=icp_voxel, seed=seed)
    surface = sample_model_surface(mesh, surface_spacing, seed=seed)
    centroid = surface.points.mean(axis=0)
    diameter = 2.0 * float(np.max(np.linalg.norm(surface.points - centroid, axis=1)))
    step = min(ppf_relative_step * diameter, ppf_max_step)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(surface.points))
    pcd.normals = o3d.utility.Vector3dVector(surface.normals)
    pcd = pcd.voxel_down_sample(step)
    pcd.normalize_normals()
    ppf = build_ppf_model(np.asarray(pcd.points), np.asarray(pcd.normals), step)
    axes = principal_axes(surface.points)
    if check_model is None:
        check_model = prepare_tracking_model(mesh, icp_voxel, seed=seed, template=template)
    return AcquisitionModel(mesh.name, template, ppf, surface, centroid, diameter, axes,
                            check_model)


def prepare_acquisition_scene(scene_points: np.ndarray, scene_normals: Optional[np.ndarray] = None,
                              camera: CameraLike = None, *,
                              stereo_baseline: float = 0.0) -> AcquisitionScene:
    """
    Wrap a scene cloud for :func:`acquire_object` (reuse it for every object of the cloud).

    :param scene_points: (N, 3) or organised (H, W, 3) points [m], optical frame; non-finite
        points are dropped (with their normals).
    :param scene_normals: optional normals of the same shape.
    :param camera: intrinsics (:func:`~object_localizer.verification.as_camera` forms) or None.
    :param stereo_baseline: stereo baseline [m] when ``camera`` is None or has none (the
        virtual camera of :func:`~object_localizer.verification.observe_depth` then reasons
        about what stereo can measure too); 0: not stereo.
    :raises ValueError: wrong shapes, fewer than 10 finite points, negative baseline.
    """
    if not stereo_baseline >= 0:
        raise ValueError(f'stereo_baseline must be >= 0, got {stereo_baseline}')
    P = np.asarray(scene_points, dtype=float)
    if P.ndim == 3 and P.shape[2] == 3:
        P = P.reshape(-1, 3)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f'scene points must have shape (N, 3) or (H, W, 3), got {P.shape}')
    N = None
    ok = np.all(np.isfinite(P), axis=1)
    if scene_normals is not None:
        N = np.asarray(scene_normals, dtype=float).reshape(-1, 3)
        if N.shape != P.shape:
            raise ValueError(f'scene normals {N.shape} do not match the points {P.shape}')
        ok &= np.all(np.isfinite(N), axis=1)
        N = N[ok]
    P = P[ok]
    if len(P) < 10:
        raise ValueError(f'scene has only {len(P)} finite points')
    return AcquisitionScene(P, N, as_camera(camera), float(stereo_baseline))


def _unexplained(cloud: o3d.geometry.PointCloud, exclude: Optional[np.ndarray],
                 radius: float) -> Tuple[np.ndarray, np.ndarray]:
    """Return the points (K, 3) and normals (K, 3) of ``cloud`` no other object explains."""
    S, SN = np.asarray(cloud.points), np.asarray(cloud.normals)
    keep = unexplained(S, exclude, radius)
    return S[keep], SN[keep]


def _rough_ppf(model: AcquisitionModel, scene: AcquisitionScene, seed: int,
               max_hypotheses: int, reference_stride: int,
               max_references: int = 2500, exclude: Optional[np.ndarray] = None,
               exclude_radius: float = 0.0) -> List[tuple]:
    step = model.ppf.distance_step
    search = scene.cloud(step, drop_plane=True, min_plane_extent=2.0 * model.diameter,
                         seed=seed)
    S, SN = _unexplained(search, exclude, exclude_radius)
    if len(S) < 10:
        return []
    # bounded work: voting costs references x neighbours and the clustering grows with the
    # square of the votes' peaks, so a huge cloud (a million random points) gets a longer
    # stride; the synthetic scenes have 900-1200 references at stride 5 (unchanged)
    stride = max(int(reference_stride), -(-len(S) // max(int(max_references), 1)))
    poses, votes = ppf_vote(model.ppf, S, SN, reference_stride=stride, seed=seed)
    poses, scores = cluster_poses(poses, votes, model.centroid, 0.1 * model.diameter,
                                  np.radians(20.0), max_clusters=max_hypotheses)
    return [(T, float(s)) for T, s in zip(poses, scores)]


def _rough_fpfh(model: AcquisitionModel, scene: AcquisitionScene, seed: int,
                attempts: int, exclude: Optional[np.ndarray] = None,
                exclude_radius: float = 0.0) -> List[tuple]:
    t = model.template
    search = scene.cloud(t.voxel_size, drop_plane=True, min_plane_extent=2.0 * model.diameter,
                         seed=seed)
    if exclude is not None and len(exclude):
        S, SN = _unexplained(search, exclude, exclude_radius)
        if len(S) < 10:
            return []
        search = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(S))
        search.normals = o3d.utility.Vector3dVector(SN)
    feats = fpfh_features(search, t.voxel_size)
    return [match_features_ransac(t, search, feats, seed=seed + k, max_iterations=100000)
            for k in range(attempts)]


def _refine(model: AcquisitionModel, scene: AcquisitionScene, pose: np.ndarray,
            max_points: int = 2000, wide: bool = True,
            guard_tolerance: Optional[float] = None,
            stop_below: Optional[float] = None) -> Tuple[np.ndarray, float, float]:
    """
    Refine a pose by point-to-plane ICP with an annealed Tukey M-estimator.

    Point-to-plane ICP with a Tukey M-estimator annealed from the PPF step down to the stereo
    noise (k = step -> 4 mm -> 1.5 mm, search radius 2k -> 2k -> 5 mm), on the scene around the
    pose; only the model samples the camera sees (facing it and not hidden behind observed
    surfaces: :func:`~object_localizer.verification.unoccluded_mask`), refreshed per stage, at
    most ``max_points``.

    :param wide: start with the wide stage (False: a pose already within a few mm).
    :param guard_tolerance: if given, the start pose and every stage's pose are scored by the
        visibility score at this depth tolerance [m] (``VisibilityScore.combined``) and the
        last pose is kept unless an earlier one scores more than 0.02 higher. ICP on a scene
        crop that holds a contact partner (a ball in its socket, a carriage on its rail) or a
        stereo-fattened thin part can walk away from a right pose: measured on the benchmark's
        failures, ICP started at the truth drifted 2-55 mm in 26 of 43, while the visibility
        score of the truth stayed higher than the drifted pose's.
    :param stop_below: with ``guard_tolerance``: stop after the first stage when its pose
        scores below this (a hypothesis that cannot win; the fine stages are the costly part).
    :return: pose, inlier fraction (model samples within 3 mm), inlier RMS [m].
    """
    step = model.ppf.distance_step
    t = model.template
    Q, QN, crop = scene.icp_crop(t.voxel_size, pose[:3, :3] @ model.centroid + pose[:3, 3],
                                 0.5 * model.diameter + step)
    if len(Q) < 10:
        return pose, 0.0, float('nan')
    rng = np.random.default_rng(0)
    src = None
    tried: List[Tuple[float, np.ndarray]] = []

    def guard(T: np.ndarray) -> None:
        if guard_tolerance is not None:
            tried.append((scene.visibility(model.surface, T, guard_tolerance).combined,
                          T.copy()))
    guard(pose)
    stages = ((step, 2.0 * step, 15), (0.004, 0.008, 20), (0.0015, 0.005, 30),
              (0.0015, 0.003, 30))
    for n_stage, (k, reach, iters) in enumerate(stages if wide else stages[1:]):
        if n_stage == 1 and stop_below is not None and tried and tried[-1][0] < stop_below:
            break
        R, tr = pose[:3, :3], pose[:3, 3]
        keep = np.flatnonzero(unoccluded_mask(t.points @ R.T + tr, t.normals @ R.T,
                                              scene.observed(), max(reach, 0.006)))
        if len(keep) < 10:
            return pose, 0.0, float('nan')
        if len(keep) > max_points:
            keep = np.sort(rng.choice(keep, max_points, replace=False))
        src = t.points[keep]
        # compiled point-to-plane ICP with the Tukey loss (the tracker's), scene crop as target
        delta = icp_point_to_plane(src @ R.T + tr, Q, QN, reach, k, max_iterations=iters,
                                   tolerance=1e-7, fine_cell=t.voxel_size)[0]
        pose = delta @ pose
        guard(pose)
    if tried and max(v for v, _ in tried[:-1]) > tried[-1][0] + 0.02:
        pose = max(tried[:-1], key=lambda vt: vt[0])[1]
    d = scene.crop_distances(t.voxel_size, crop, src @ pose[:3, :3].T + pose[:3, 3], 0.003)
    ok = np.isfinite(d)
    return pose, float(ok.mean()), float(np.sqrt(np.mean(d[ok] ** 2))) if ok.any() else 0.0


def _slide_search(model: AcquisitionModel, pose: np.ndarray, scene: AcquisitionScene,
                  tolerance: float) -> Tuple[np.ndarray, bool]:
    """
    Search the pose's translation along the model's principal axes.

    Pattern search of the pose's translation along the model's principal axes (steps of
    diam/4 halved down to 4 mm), keeping moves that raise the combined visibility score by
    more than 0.01 (the score's resolution on coarse pixels); ICP then does the fine part.

    ICP cannot slide a long prism along its axis when the end faces are far from where they
    should be (no correspondence reaches them); the rendered silhouette and the free-space
    violations of the visibility score do see the ends.

    :return: the pose and whether it moved.
    """
    def score(T: np.ndarray) -> float:
        return scene.visibility(model.surface, T, tolerance).combined
    slid = search_along_axes(pose, model.axes, [model.diameter / 4.0] * len(model.axes), score,
                             0.01, 0.004)[0]
    return slid, slid is not pose


def _same_place(model: AcquisitionModel, pose_a: np.ndarray, pose_b: np.ndarray,
                distance: float) -> bool:
    """
    Return whether two poses put the model at the same place, up to its symmetries.

    Both the surface centroid and the ADD-S (256 surface samples) must be within ``distance``
    [m]: poses related by a symmetry of the model keep its centroid and its surface, a pose slid
    along a long part keeps most of its surface but moves its centroid.
    """
    P = model.surface.points
    cached = _SURFACE_TREES.get(id(model))
    if cached is None or cached[0] is not P:
        cached = _SURFACE_TREES[id(model)] = (P, P.mean(axis=0), cKDTree(P))
    _, c, tree = cached
    if np.linalg.norm(pose_a[:3, :3] @ c + pose_a[:3, 3] - pose_b[:3, :3] @ c
                      - pose_b[:3, 3]) > distance:
        return False
    # 256 samples placed by pose_a, in pose_b's model frame, against all of the surface
    R = pose_b[:3, :3].T @ pose_a[:3, :3]
    t = pose_b[:3, :3].T @ (pose_a[:3, 3] - pose_b[:3, 3])
    Q = P[::max(len(P) // 256, 1)] @ R.T + t
    return float(np.mean(tree.query(Q)[0])) <= distance


#: (surface points, their centroid, KD-tree) per acquisition model, for :func:`_same_place`
_SURFACE_TREES: Dict[int, Tuple[np.ndarray, np.ndarray, Any]] = {}


def polish_hypothesis(model: AcquisitionModel, scene: AcquisitionScene, hypothesis: Hypothesis,
                      quality: PoseQuality, settings: TrackerSettings,
                      tolerance: float = 0.004) -> bool:
    """
    Polish a hypothesis in place by the tracker's ICP; return whether its pose was replaced.

    ``tracking.refine_and_check`` (Tukey point-to-plane on the scene points on the pose's
    rays, exact model normals) from ``hypothesis.pose``; the result replaces it when it passes
    the tracker's check with a quality no lower than ``quality`` (the check of the unpolished
    pose), or with more scene support (inliers minus contradicted samples) by the margin of
    ``tracking.slide_along_axes`` (2 % of the visible samples; a superquadric 3.0 -> 0.4 deg:
    quality 0.711 -> 0.704, supported samples 2715 -> 2798). A rail's ICP can walk 7-10 mm
    along it; its check's quality and support then drop, and it is not kept. The score is
    then the visibility score of the polished pose at ``tolerance`` [m].
    """
    polished, q = refine_and_check(model.check, scene.rays(), hypothesis.pose, settings,
                                   acquisition=True)
    gain = max(0.02 * quality.visible_samples, settings.min_visible_samples)
    if not q.passed or (q.quality < quality.quality and q.support <= quality.support + gain):
        return False
    hypothesis.pose = polished
    hypothesis.visibility = scene.visibility(model.surface, polished, tolerance)
    hypothesis.score = hypothesis.visibility.combined
    return True


def acquire_object(model: Union[AcquisitionModel, PolygonMesh],
                   scene_points: Union[AcquisitionScene, np.ndarray],
                   scene_normals: Optional[np.ndarray] = None, camera: CameraLike = None, *,
                   method: str = 'ppf', seed: int = 0, time_budget_s: float = 0.5,
                   max_rough: int = 50, max_refined: int = 8, max_slide: int = 2,
                   skip_margin: float = 0.5, prune_margin: float = float('inf'),
                   equivalent_distance: float = 0.002,
                   reference_stride: int = 5, max_references: int = 2500,
                   fpfh_attempts: int = 4, rough_rounds: int = 2,
                   rough_tolerance: Optional[float] = None,
                   fine_tolerance: float = 0.004,
                   final_check: bool = False, polish: bool = True,
                   tie_margin: float = 0.015,
                   check_settings: Optional[TrackerSettings] = None,
                   exclude_points: Optional[np.ndarray] = None,
                   exclude_radius: float = 0.005) -> List[Hypothesis]:
    """
    Find ``model`` in a scene cloud with no initial pose.

    Find ``model`` in a scene cloud with no initial pose (module doc: rough, verification,
    refinement).

    :param model: :func:`prepare_acquisition_model` output (a mesh is prepared on the fly).
    :param scene_points: (N, 3)/(H, W, 3) points [m] in the camera optical frame, or a
        :func:`prepare_acquisition_scene` (then ``scene_normals``/``camera`` are ignored).
    :param scene_normals: optional normals of the points (estimated otherwise).
    :param camera: camera intrinsics for the visibility score; None = virtual camera.
    :param method: ``'ppf'`` or ``'fpfh'`` (rough stage).
    :param seed: seeds the reference-point order (PPF) or RANSAC.
    :param time_budget_s: refinement stops once this much wall time [s] is spent (at least one
        hypothesis is refined).
    :param max_rough: rough hypotheses verified.
    :param reference_stride: PPF: every k-th scene sample is a reference point (Drost: 5).
    :param max_references: PPF: at most this many reference points (a longer stride for larger
        clouds: bounded work per cloud).
    :param max_refined: best rough hypotheses refined by ICP.
    :param skip_margin: a rough hypothesis whose pose scores (at ``fine_tolerance``) more than
        this below the best refined hypothesis so far is not refined (returned unrefined);
        ``inf``: never skipped.
    :param equivalent_distance: a rough hypothesis whose model centre and ADD-S are both within
        this [m] of a hypothesis already refined is the same place (a sphere, a cylinder, a
        torus: its rough poses are mostly turns about its symmetries) and is not refined
        (returned unrefined); a pose slid along a long part moves its centre and is refined.
        0: off. Paired on the stereo benchmark's 210 trials (same clouds and seeds): 2 mm ->
        CPU per object 0.64 / 1.03 / 1.28 s (median / p95 / max) against 0.66 / 1.24 / 1.67
        (sphere 1.19 -> 0.79 s, cylinder 1.02 -> 0.80, torus 1.08 -> 0.74 median), success 178
        against 179: the trials that differ (peg 23, 25; superquadric 179) also differ between
        runs of the same code (Open3D's plane RANSAC; 179 failed at 1 mm with nothing skipped).
    :param prune_margin: a hypothesis whose score after the wide ICP stage is more than this
        below the best refined score so far is not refined further (it keeps that pose and
        score); ``inf``: every refined hypothesis goes through every stage.
    :param max_slide: best refined hypotheses whose position is then searched along the model
        axes by the visibility score (and refined again when it moved). The best one, if it
        then fails the tracker's check, is also searched along the model's longest axis by the
        check's scene support (``tracking.slide_along_axes``) and replaced when that passes.
    :param rough_rounds: PPF: voting rounds with different seeds (``seed``, ``seed + 7919``,
        ...), their rough hypotheses pooled before the verification. The seed sets the
        reference points and the dominant-plane fit; one round missed a visible peg in 3 of 4
        seeds on some stereo clouds (the truth never among its hypotheses). Measured on the
        stereo benchmark's 210 trials, same clouds and seeds: 2 rounds -> success 195 vs 191
        of 210, `search` failures 1 vs 7, wall time per object median / p95 0.32 / 0.46 s vs
        0.27 / 0.41 s (a round's voting is 65-90 ms; the refinement is the costly part).
    :param rough_tolerance: depth tolerance [m] of the rough verification (default: 1.5 x
        the PPF step, at least 6 mm).
    :param fine_tolerance: depth tolerance [m] of the final verification.
    :param final_check: polish each refined hypothesis with the tracker's ICP (kept when the
        tracker's per-sample check, ``tracking.check_pose`` with the acquisition thresholds,
        does not get worse) and rank them by check quality x ``score`` instead of ``score``.
        The pixel score on the coarse image counts occluded pixels against a pose and knows
        no normals nor stereo visibility: a wrong pose fully visible on another surface (a
        peg lying on its block's top face) outscored a right pose half hidden by its contact
        partner. Off by default: measured, it wins trials on the stereo benchmark but loses
        as many elsewhere -- the check prefers poses 5-14 mm off that fit a surface patch
        displaced by 7 mm (``bench/localizer_accuracy.py``: 0.867 vs 0.917 within 1 mm) and
        let the slot block turned onto its side win on stereo clouds (README, Figures).
    :param polish: the best pose is polished by the tracker's ICP (:func:`polish_hypothesis`).
        The coarse stages end 2-3 mm off on some stereo clouds (a rail's or a link's length,
        a superquadric's turn); on the stereo benchmark's 210 trials, paired, 197 -> 201
        within 2 mm / 2 deg, no trial lost (unguarded: 197, three lost; by quality alone:
        200). The tracker passes False: it refines and checks every candidate itself.
    :param tie_margin: when the runner-up's score is within this of the best's, the one with
        more scene support in the tracker's check (``tracking.pose_support``: inliers minus
        contradicted samples, per surface sample) is taken as the best. The coarse pixels (stride
        4, 4 mm tolerance) do not see a 1.7 mm shift of hole_block's equivalent pose or a 3 deg
        turn of the superquadric (scores 0.778 vs 0.768, 0.926 vs 0.915); the samples do (6108
        vs 6227, 2733 vs 2762 supported samples). On the stereo benchmark's 210 trials, paired:
        199 / 200 / 201 -> 202 / 202 / 201 within 2 mm / 2 deg (acquisition seeds offset by
        0 / 1000 / 2000), about 4 ms more per block. The tracker passes 0: it checks every
        candidate itself.
    :param check_settings: thresholds of that check (default ``TrackerSettings()``).
    :param exclude_points: (M, 3) [m, optical frame] surface samples of other objects already
        verified in this cloud: the scene points within ``exclude_radius`` [m] of them do not
        vote in the rough stage (a part of the same shape as one already found is then looked
        for in the rest of the scene; verification and refinement still see every point).
    :return: hypotheses, best first (refined ones by ``check.quality`` x ``score`` when
        ``final_check``, else by ``score``, the first being the runner-up of a near-tie when
        ``tie_margin`` chose it); empty if the rough stage found none.
    :raises ValueError: unknown method, unusable scene.
    """
    t0 = time.perf_counter()
    if method not in METHODS:
        raise ValueError(f'method must be one of {METHODS}, got {method!r}')
    if isinstance(model, PolygonMesh):
        model = prepare_acquisition_model(model)
    scene = scene_points if isinstance(scene_points, AcquisitionScene) else \
        prepare_acquisition_scene(scene_points, scene_normals, camera)
    if method == 'ppf':
        rough = []
        for k in range(max(int(rough_rounds), 1)):
            rough += _rough_ppf(model, scene, seed + 7919 * k, max_rough, reference_stride,
                                max_references, exclude_points, exclude_radius)
    else:
        rough = _rough_fpfh(model, scene, seed, fpfh_attempts, exclude_points, exclude_radius)
    if not rough:
        return []
    tol = rough_tolerance if rough_tolerance is not None else \
        max(0.006, 1.5 * model.ppf.distance_step)
    hyps = []
    for T, support in rough:
        vis = scene.visibility(model.surface, T, tol)
        hyps.append(Hypothesis(T, vis.combined, method, support, vis.combined, vis))
    hyps.sort(key=lambda h: (h.rough_visibility, h.rough_score), reverse=True)
    refined: List[Hypothesis] = []
    skipped: List[Hypothesis] = []
    chosen: List[np.ndarray] = []      # rough poses refined (or skipped by score)
    tried = 0
    for h in hyps[:max_refined]:
        if refined and time.perf_counter() - t0 > time_budget_s:
            break
        tried += 1
        # refinement is the costly part (about 65 ms of CPU per hypothesis on this machine, 55 %
        # of an acquisition): a rough pose scoring far below the best refined one so far is
        # not refined. Measured on the stereo benchmark's 210 trials, paired, same clouds and
        # seeds (bench/localizer_acquisition.py): skip_margin 0.5 -> success 181 vs 180 of
        # 210, CPU per object median 0.66 vs 0.94 s; 0.3 with prune_margin 0.1 -> 174 (right
        # poses dropped: ICP can raise a right pose's score by more than 0.3); prune_margin
        # 0.1 alone -> 178
        if equivalent_distance > 0 and any(
                _same_place(model, h.pose, r, equivalent_distance) for r in chosen):
            skipped.append(h)
            continue
        chosen.append(h.pose)
        best = max(r.score for r in refined) if refined else None
        if best is not None and scene.visibility(
                model.surface, h.pose, fine_tolerance).combined < best - skip_margin:
            skipped.append(h)
            continue
        pose, inliers, rmse = _refine(model, scene, h.pose, guard_tolerance=fine_tolerance,
                                      stop_below=None if best is None else best - prune_margin)
        vis = scene.visibility(model.surface, pose, fine_tolerance)
        refined.append(Hypothesis(pose, vis.combined, method, h.rough_score,
                                  h.rough_visibility, vis, inliers, rmse, True))
    rest = skipped + hyps[tried:]
    refined.sort(key=lambda h: (h.score, h.inlier_fraction), reverse=True)
    for i, h in enumerate(refined[:max_slide]):
        slid, moved = _slide_search(model, h.pose, scene, fine_tolerance)
        if not moved:
            continue
        pose, inliers, rmse = _refine(model, scene, slid, wide=False,
                                      guard_tolerance=fine_tolerance)
        vis = scene.visibility(model.surface, pose, fine_tolerance)
        if vis.combined > h.score:
            refined[i] = Hypothesis(pose, vis.combined, method, h.rough_score,
                                    h.rough_visibility, vis, inliers, rmse, True)
    refined.sort(key=lambda h: (h.score, h.inlier_fraction), reverse=True)
    settings = check_settings if check_settings is not None else TrackerSettings()
    q0: Optional[PoseQuality] = None
    if tie_margin > 0 and len(refined) > 1 and model.check is not None \
            and refined[1].score >= refined[0].score - tie_margin:
        # a near-tie of the coarse pixel score: the runner-up is taken when the tracker's
        # check, per surface sample, finds more scene support for it (the pixels at stride 4
        # and a 4 mm tolerance do not see a 1.7 mm shift of hole_block or a 3 deg turn of the
        # superquadric; the samples do)
        rays = scene.rays()
        _, q0 = refine_and_check(model.check, rays, refined[0].pose, settings,
                                 acquisition=True, refine=False)
        if pose_support(model.check, rays, refined[1].pose, settings) > round(q0.support):
            refined[0], refined[1] = refined[1], refined[0]
            _, q0 = refine_and_check(model.check, rays, refined[0].pose, settings,
                                     acquisition=True, refine=False)
    if refined and model.check is not None:
        # the best pose, when it fails the tracker's check, searched along the model's longest
        # axis by the check's scene support: a bar slid along itself with its end hidden
        # scores as well as the truth on the coarse pixels of the visibility score, not on
        # the check's samples (ball_link slid 13.6 and 31.8 mm, found at 0.4 and 1.3 mm)
        h, rays = refined[0], scene.rays()
        if q0 is None:
            _, q0 = refine_and_check(model.check, rays, h.pose, settings, acquisition=True,
                                     refine=False)
        if not q0.passed:
            slid, q_slid, how = slide_along_axes(model.check, rays, h.pose, q0, settings,
                                                 longest_only=True)
            if how:
                vis = scene.visibility(model.surface, slid, fine_tolerance)
                refined[0] = h = Hypothesis(slid, vis.combined, method, h.rough_score,
                                            h.rough_visibility, vis, h.inlier_fraction,
                                            h.rmse, True)
                q0 = q_slid
        if polish:
            polish_hypothesis(model, scene, h, q0, settings, fine_tolerance)
    if final_check and model.check is not None:
        rays = scene.rays()
        for h in refined:
            c = h.pose[:3, :3] @ model.check.centre + h.pose[:3, 3]
            cone = rays.cone(c, model.check.radius)
            h.check = check_pose(model.check, h.pose, cone, settings, acquisition=True)
            # the tracker's ICP (scene samples onto the model's visible samples, exact model
            # normals) from the pose: kept when the check does not get worse
            polished = track_icp(model.check, cone, h.pose, settings)
            q = check_pose(model.check, polished, cone, settings, acquisition=True)
            if q.quality >= h.check.quality:
                vis = scene.visibility(model.surface, polished, fine_tolerance)
                h.pose, h.check, h.visibility, h.score = polished, q, vis, vis.combined
        refined.sort(key=lambda h: (h.check.quality * h.score, h.score), reverse=True)
    for h in rest:
        h.score = 0.0          # unrefined: not a usable pose, kept for diagnosis
    return refined + rest
