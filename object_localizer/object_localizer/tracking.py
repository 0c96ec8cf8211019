"""
6-DOF tracking of known models at camera rate, with a quality check on every pose (pure core).

Per cloud and object (:meth:`ObjectTracker.update`):

1. **Prediction.** Constant velocity: the object's centre keeps its last linear velocity and the
   object its last angular velocity (both from the last two accepted poses and their stamps;
   a track re-acquired after a loss keeps the velocity it had before it, ``motion_memory``).
2. **Tracking.** Point-to-plane ICP with a Tukey M-estimator from the prediction. The scene points
   near the predicted object (a cone crop, then a sphere crop, voxel down-sampled) are the
   source; the model samples expected visible at the prediction, with their exact normals, are
   the target — so no scene normals are estimated, and every iteration is cheap. Stopping
   criteria are relative changes of 1e-6 (not 1e-9), small steps, and steps that no longer
   change the residuals; the step never turns the model about a continuous symmetry axis
   (a torus', a cylinder's; any axis of a sphere), which no residual observes. The crops (the
   rays through the object, the points near it) are single compiled passes over the cloud
   (``crop.py``).
3. **Quality check** (:func:`check_pose`), visibility-aware: the model is z-buffered at the pose
   into a range image built from the scene points along the same rays. Each model sample the
   sensor should see (facing it, not hidden by the model itself) is compared with the observed
   depth on its ray: within ``inlier_distance`` (along the surface normal) it is an inlier; an
   observed point clearly in front of it means it is occluded (not counted); an observed point
   clearly behind it is a free-space violation (the sensor sees through where the object would
   be); no observation counts as missing. From these: the inlier fraction, the RMS residual of
   the inliers (the visible-surface residual), the free-space violation fraction, and the mean
   displacement of the model points from the prediction. Then the silhouette: an object of
   its own makes a depth edge along its outline (the observed depth just outside jumps behind
   it), a pose sunk into a larger surface does not -- every visible sample is an inlier, but
   the observed surface goes on past the outline (a box face inside a table top, a wall, the
   flat surface a stereo matcher makes at the limit of its disparity band); the share of the
   outline with an edge must reach ``min_edge_fraction``. The pose passes only if all of them
   pass their thresholds. A pose that fails is never returned as a pose.
4. **States.** ``ACQUIRING`` (no pose yet: the global acquisition runs on the whole cloud),
   ``TRACKING``, ``LOST`` (the last pose failed: the next cloud is searched globally, from
   scratch), ``STATIC`` (objects declared static: localised and verified once, then the pose is
   held and re-verified every ``static_recheck_period`` seconds of stamps; the held pose is
   the mean of the verified re-check poses, ``static_average``).

An initial pose is a hint: it goes through the same ICP and check as a prediction, and the
global acquisition runs when it fails.

All clouds are (N, 3) arrays [m] in the sensor's optical frame (z forward); poses are 4x4
transforms model frame -> sensor frame.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field, replace
import enum
import time
from typing import Any, Callable, Deque, List, Optional, Sequence, Tuple

import numpy as np
from object_localizer.crop import crop_near, crop_rays, crop_window, nearest_depth_image
from object_localizer.localization import localize, ModelTemplate, prepare_model, sample_surface
from object_localizer.point_to_plane import icp_point_to_plane
from object_localizer.symmetry import find_symmetries, mesh_symmetry, \
    nearest_equivalent_pose
import open3d as o3d
from stereo_manip_tools.mesh_io import PolygonMesh
from stereo_manip_tools.transforms import nearest_rotation, rotation_about_axis, rotation_angle, \
    rotation_log

__all__ = ['TrackState', 'TrackerSettings', 'TrackingModel', 'PoseQuality', 'TrackUpdate',
           'SceneCloud', 'prepare_tracking_model', 'predict_constant_velocity', 'carried_motion',
           'track_icp', 'check_pose', 'refine_and_check', 'slide_along_axes', 'unexplained',
           'ObjectTracker', 'Acquirer', 'make_acquirer', 'acquire_rough_fine', 'same_shape',
           'symmetric_distance']


class TrackState(enum.IntEnum):
    """Track states; the values are those of ``stereo_manip_msgs/TrackStatus``."""

    ACQUIRING = 0
    TRACKING = 1
    LOST = 2
    STATIC = 3


@dataclass
class TrackerSettings:
    """
    Tracker parameters (metres, seconds).

    :ivar max_distance: ICP correspondence radius [m] at the last ICP stage (twice that first).
    :ivar loss_scale: Tukey M-estimator scale k [m] at the last stage (annealed from 3k).
    :ivar icp_iterations: largest number of ICP iterations per stage.
    :ivar icp_min_step: the last ICP stage also stops when its step turns the scene by less
        than this [rad] and moves it by less than this [m].
    :ivar icp_coarse_min_step: the same for the first (coarse, wide) stage, which the last one
        refines (0.1 mm / 0.1 mrad: its last micrometre steps are redone by the last stage).
    :ivar icp_min_residual_step: the last ICP stage also stops when its step changes the
        point-to-plane residuals by less than this [m] (weighted RMS ``sqrt(x' A x / sum w)``,
        A the normal matrix): converged in every direction the correspondences observe. 1 um
        leaves every peg pose of ``bench/localizer_tracking.py`` unchanged. (A turn about a
        continuous symmetry axis, which changes no residual, is not left to this test: the
        ICP never turns about ``TrackingModel.symmetry_axes``.)
    :ivar icp_coarse_min_residual_step: the same for the first stage. Measured on the peg
        sequence: 1e-4 m (the first stage's ``min_step``) saved a fifth of the CPU but stopped
        the wide first stage early enough to change where the last one converged (ADD-S mean
        0.339 -> 0.384 mm, p95 0.85 -> 0.98 mm), so it stays at 1 um (no change).
    :ivar scene_voxel: voxel size [m] the scene crop is down-sampled to for ICP.
    :ivar max_icp_points: at most this many of those points take part (evenly chosen): a fixed
        budget per object (1000: the primitives graph's cube/torus crops have ~2000-2500 after
        the voxel filter; on the live graphs' clouds ADD-S p95 is unchanged against 2500 and
        ICP CPU falls by a third, see bench/results/localizer_graph_cpu.json).
    :ivar inlier_distance: largest distance [m] (along the model normal) of an observed point
        from the model surface for the model sample to count as seen (inlier).
    :ivar min_inlier_fraction: smallest inlier fraction of a published tracked pose.
    :ivar min_acquisition_inlier_fraction: the same for a pose with no motion prediction to
        compare with (global acquisition, hints): stricter, since a part slid along itself
        (e.g. a brick along its length, its end hidden) can keep most of its surface on the
        observed one.
    :ivar max_visible_residual: largest RMS inlier residual [m] of a published pose.
    :ivar max_free_space_fraction: largest share of expected-visible model samples through which
        the sensor sees a surface behind the model.
    :ivar max_prediction_error: largest mean displacement [m] of the model points between the
        pose and the motion prediction.
    :ivar stereo_baseline: position [m] of the second camera on the x axis of the cloud's
        optical frame (REP 103 stereo: the right camera at +x); model samples must face both
        cameras at ``min_view_cos`` to be expected visible (0: a single viewpoint).
    :ivar prediction_horizon: largest gap [s] between clouds over which the motion is
        extrapolated and the pose checked against the prediction; after a longer gap (or from a
        single pose) tracking starts from the last pose with no prediction check.
    :ivar min_view_cos: a model sample counts as expected visible only if the cosine between its
        normal and its line of sight is at least this (surfaces seen at grazing angles are not
        measured reliably by stereo, and are often hidden from the second camera).
    :ivar min_visible_samples: a pose whose expected-visible samples (after occlusion) are fewer
        cannot be verified and is not published.
    :ivar min_edge_fraction: smallest share of the model's judged silhouette where the observed
        depth just outside jumps behind the model (or is missing): a model whose visible
        surface lies inside a larger observed surface (a face sunk into a table top, a wall,
        the flat band-limit surface of a stereo matcher, a bigger part) explains every visible
        sample but has no silhouette edges; such a pose is rejected
        (:func:`object_localizer.verification.silhouette_edges`).
    :ivar edge_threshold: depth jump [m] that counts as a silhouette edge.
    :ivar edge_gap: distance [m, at the object] from the outline of the observed depth judged
        by the edge test (at least ``EDGE_GAP`` pixels of the check's image): stereo matching
        fattens foreground silhouettes by about half its window (3-4 camera pixels, 2-3 mm
        at 0.5 m with 600 px), and that band must be stepped over.
    :ivar min_edge_samples: fewer judged silhouette pixels (the rest occluded) leave the edge
        test undecided: it neither passes nor fails the pose.
    :ivar max_penetration: a pose that puts more than 10 % of the model's volume deeper than
        this [m] inside another object's verified pose is rejected (physically impossible; the
        typical wrong pose of a part lying on a bigger one).
    :ivar explained_radius: the global search's rough stage leaves out the scene points within
        this [m] of the surface of an identical part verified in the same cloud (their votes
        only find that part again: after revolute_pair's loop jump, link_arm's search found only
        the place of its identical twin link_base, tracked there, and failed the penetration
        check for a cloud); verification and refinement still see every point. 0: off.
    :ivar ambiguity_distance: acquisition results farther apart than this (ADD-S [m]) are
        distinct solutions; when several pass the check the object is ambiguous (identical
        parts) and is only published if the last known pose is clearly nearer one of them, or
        (a part with no identical twin) if the places overlap and one is clearly better
        supported (``min_support_ratio``).
    :ivar min_support_ratio: of distinct places that pass the check, the one the scene supports
        with at least this many times the samples of every other (inliers minus contradicted
        expected-visible samples, :attr:`PoseQuality.support`) is taken when every other place
        overlaps it (more than 10 % of the volume deeper than ``max_penetration``): one part
        cannot be in two overlapping places, and the one explaining clearly more of the scene
        is it (hole_block in the stereo cloud of peg_in_hole frame 15: 6480 samples at 1.0 mm
        from the truth, 4443 at 25.8 mm; left ambiguous, the block was not verified, and the
        peg's search put the peg 77 mm off inside the block, published). 0 turns it off.
    :ivar twin_reacquire_radius: a part with an identical twin is re-acquired only within this
        mean displacement [m] of its last known pose (and clearly nearer it than the twin's).
    :ivar relock_window: for this long [s, cloud stamps] after a loss (from the cloud of the
        loss), the search of a lost track first re-acquires it locally (:meth:`ObjectTracker.
        local_starts`: ICP from the prediction, the last verified pose and perturbed starts,
        each through the acquisition check; a part with an identical twin named by
        :func:`object_localizer.naming.may_name`); 0 turns it off. A track lost to a brief
        occlusion, a borderline check or a motion beyond the ICP's reach comes back at the cost
        of ~14 ICP + check (0.1-0.4 s CPU) instead of a global search, and identical parts keep
        their names.
    :ivar relock_shift: local re-acquisition (within ``relock_window``) also starts the ICP
        from the predicted / last pose shifted by +-this [m] along each model axis ...
    :ivar relock_turn: ... and turned by +-this [rad] about each model axis about its centre
        (12 more starts; each is one ICP + check, ~20 ms): a part that moved farther than the
        ICP's reach between two processed clouds, or that slid along itself, comes back
        without a global search.
    :ivar slide_min_step: a pose found without a motion prediction to compare with (local
        re-acquisition, tracking after a gap longer than ``prediction_horizon``, a hint, the
        global search) is searched along the model's principal axes
        (:meth:`ObjectTracker.slide_along_axes`: steps of a quarter of the model's extent,
        halved down to this [m]) for a position the scene supports clearly better, then
        refined and checked again: a long part slid along itself with its end hidden (a peg
        34.7 mm deeper than the truth in the hole, 1079 instead of 1997 supported samples)
        passes every ratio of the check, and its ICP cannot slide it back when the end face
        is beyond ``max_distance``. 0 turns it off.
    :ivar twin_max_speed: a part with an identical twin is named at a place only if the place
        is within ``twin_reacquire_radius + twin_max_speed x age`` [m, mean displacement] of
        its own last known pose or motion prediction (age [s]: since that pose was verified)
        and, measured in those radii, less than half as far from it as from every unverified
        twin's (its own radius from its own age): the older a known pose, the less it says.
    :ivar motion_memory: a track re-acquired within this long [s, cloud stamps] of its last
        verified pose keeps the velocity it had before the loss (:func:`carried_motion`); 0:
        a re-acquired track starts without a velocity. On a slow graph (clouds farther apart
        than ``prediction_horizon``, e.g. a loaded machine) a moving object is only followed
        through the extrapolated start, so a track re-acquired without its velocity was lost
        again in the next cloud (measured: peg graph under 2 busy loops, a loss / search /
        re-acquire / loss cycle at 1.6 Hz).
    :ivar static: the object does not move: after a verified pose it is held and re-verified
        every ``static_recheck_period`` [s] (cloud stamps).
    :ivar static_average: a static object's held pose is the mean of the last this many
        poses refined by ICP at its re-checks (each verified; translation mean, chordal mean
        of the rotations; the mean itself verified before it is held). The stereo error of one
        cloud moves with what the other parts hide and with the matching noise: hole_block
        re-refined on 29 clouds of peg_in_hole read 0.07-1.21 mm ADD-S (the pose held from
        the first cloud 0.55 mm), their mean 0.31 mm. A refined pose more than
        ``static_average_gate`` from the mean restarts it (the object was moved). 1: the
        first verified pose is held (no averaging).
    :ivar static_average_gate: mean displacement [m] of the model samples beyond which a
        re-check's refined pose restarts the static mean.
    :ivar max_history: accepted poses kept in :attr:`ObjectTracker.history` (bounded).
    :ivar seed: seed of the global acquisition.
    """

    max_distance: float = 0.01
    loss_scale: float = 0.0015
    icp_iterations: int = 30
    icp_min_step: float = 1e-6
    icp_coarse_min_step: float = 1e-4
    icp_min_residual_step: float = 1e-6
    icp_coarse_min_residual_step: float = 1e-6
    scene_voxel: float = 0.003
    max_icp_points: int = 1000
    inlier_distance: float = 0.003
    min_inlier_fraction: float = 0.75
    min_acquisition_inlier_fraction: float = 0.85
    max_visible_residual: float = 0.0015
    max_free_space_fraction: float = 0.15
    max_prediction_error: float = 0.02
    min_edge_fraction: float = 0.25
    edge_threshold: float = 0.01
    edge_gap: float = 0.005
    min_edge_samples: int = 12
    prediction_horizon: float = 0.25
    stereo_baseline: float = 0.1
    min_view_cos: float = 0.3
    min_visible_samples: int = 30
    max_penetration: float = 0.005
    explained_radius: float = 0.005
    ambiguity_distance: float = 0.005
    min_support_ratio: float = 1.25
    twin_reacquire_radius: float = 0.02
    relock_window: float = 1.0
    relock_shift: float = 0.012
    relock_turn: float = 0.15
    slide_min_step: float = 0.004
    twin_max_speed: float = 0.1
    motion_memory: float = 2.0
    static: bool = False
    static_recheck_period: float = 1.0
    static_average: int = 30
    static_average_gate: float = 0.003
    max_history: int = 300
    seed: int = 0


@dataclass
class TrackingModel:
    """
    A model prepared for tracking and checking.

    :ivar template: the acquisition template (FPFH features, see ``prepare_model``).
    :ivar points: dense surface samples [m] in the model frame, (N, 3).
    :ivar normals: their outward unit normals, (N, 3).
    :ivar centre: centre of the bounding box [m], model frame.
    :ivar radius: radius [m] of the bounding sphere about ``centre``.
    :ivar probe: a few hundred of ``points`` for displacement measures.
    :ivar interior: a few hundred points inside the model [m] (for penetration tests).
    :ivar symmetry_axes: (K, 3) unit axes [model frame] of continuous rotational symmetry
        (:func:`object_localizer.symmetry.find_symmetries`: one for a torus or a cylinder,
        three for a sphere, none for a cube): the tracking ICP never turns the model about
        them (a turn about them is unobservable).
    :ivar axes: (3, 3) principal axes of the surface samples (rows, longest extent first),
        model frame (:func:`principal_axes`).
    :ivar extents: (3,) extent [m] of the surface samples along each of ``axes``.
    """

    name: str
    template: ModelTemplate
    points: np.ndarray
    normals: np.ndarray
    centre: np.ndarray
    radius: float
    probe: np.ndarray
    solid: o3d.t.geometry.RaycastingScene
    interior: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    mesh: Optional[PolygonMesh] = None
    box_min: np.ndarray = field(default_factory=lambda: np.zeros(3))
    box_max: np.ndarray = field(default_factory=lambda: np.zeros(3))
    acquisition: Any = None       # object_localizer.acquisition.AcquisitionModel, built lazily
    symmetry_axes: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    axes: np.ndarray = field(default_factory=lambda: np.eye(3))
    extents: np.ndarray = field(default_factory=lambda: np.zeros(3))
    _symmetries: Optional[Tuple[np.ndarray, np.ndarray]] = field(default=None, repr=False)

    def discrete_symmetries(self) -> Tuple[np.ndarray, np.ndarray]:
        """
        Return the model's symmetry rotations (K, 3, 3) and the point they fix (3,) [m].

        Found once, when first needed (:func:`object_localizer.symmetry.mesh_symmetry`: 3 mm
        samples of ``mesh``, 30-130 ms on the shipped models), about the mesh's exact surface
        centroid. Without a mesh: the identity alone.
        """
        if self._symmetries is None:
            if self.mesh is None:
                self._symmetries = (np.eye(3)[None], np.asarray(self.centre, dtype=float))
            else:
                found, centre = mesh_symmetry(self.mesh)
                self._symmetries = (found.rotations, centre)
        return self._symmetries

    def signed_distance(self, points: np.ndarray) -> np.ndarray:
        """Signed distance [m] of points (M, 3) in the model frame to its surface (< 0 inside)."""
        q = o3d.core.Tensor(np.asarray(points, dtype=np.float32))
        return self.solid.compute_signed_distance(q).numpy().astype(float)


def principal_axes(points: np.ndarray, tie: float = 0.05) -> np.ndarray:
    """
    Return the principal axes (3, 3) of points (N, 3), as rows, largest spread first.

    The eigenvectors of the scatter matrix about the points' mean. Where eigenvalues differ by
    at most ``tie`` x the largest, any direction in their plane (or space) is principal: the
    model frame's axes nearest that subspace, projected into it and orthonormalised, are
    returned instead (the square cross-section of a peg: its side faces' normals, not its
    diagonals).
    """
    Q = np.asarray(points, dtype=float)
    Q = Q - Q.mean(axis=0)
    w, V = np.linalg.eigh(Q.T @ Q)
    w, V = w[::-1], V[:, ::-1]
    axes: List[np.ndarray] = []
    i = 0
    while i < 3:
        j = i + 1
        while j < 3 and w[j - 1] - w[j] <= tie * max(w[0], 1e-30):
            j += 1
        B = V[:, i:j]                     # orthonormal basis of a (near) repeated eigenvalue
        if j - i == 1:
            axes.append(B[:, 0])
        else:
            near = np.argsort(-np.linalg.norm(B.T, axis=0))[:j - i]   # model axes nearest it
            for k in sorted(near):
                a = B @ B[k]              # model axis k projected into the subspace
                for b in axes[i:]:
                    a = a - (a @ b) * b
                axes.append(a / np.linalg.norm(a))
        i = j
    return np.array(axes)


def search_along_axes(pose: np.ndarray, axes: np.ndarray, first_steps: Sequence[float],
                      score: Callable[[np.ndarray], float], gain: float, min_step: float,
                      max_shifts: Optional[Sequence[float]] = None
                      ) -> Tuple[np.ndarray, float, float]:
    """
    Pattern search of a pose's translation along model axes, by a score.

    Along each row of ``axes`` (model frame; turned by the pose's rotation) in turn: steps of
    ``first_steps[k]`` [m] in both senses, halved down to ``min_step`` [m] whenever neither
    raises ``score`` by more than ``gain``; a move that does is kept (and the same step tried
    again). ``max_shifts[k]`` [m] bounds the total shift along axis k (None: unbounded).

    :return: (pose, its score, the score of the given pose); the given pose object itself
        when no move was kept.
    """
    best = start = score(pose)
    for k, axis in enumerate(axes):
        direction = pose[:3, :3] @ axis
        delta, shift = float(first_steps[k]), 0.0
        while delta >= min_step:
            improved = False
            for sign in (1.0, -1.0):
                if max_shifts is not None and abs(shift + sign * delta) > max_shifts[k]:
                    continue
                T = pose.copy()
                T[:3, 3] += sign * delta * direction
                v = score(T)
                if v > best + gain:
                    best, pose, improved, shift = v, T, True, shift + sign * delta
                    break
            if not improved:
                delta /= 2.0
    return pose, best, start


def prepare_tracking_model(mesh: PolygonMesh, voxel_size: float = 0.003,
                           tracking_voxel: float = 0.002, seed: int = 0,
                           template: Optional[ModelTemplate] = None) -> TrackingModel:
    """
    Acquisition template at ``voxel_size`` [m] and dense samples at ``tracking_voxel`` [m].

    :param template: an existing template of the same mesh (``prepare_model``) to reuse.
    """
    if template is None:
        template = prepare_model(mesh, voxel_size, seed=seed)
    dense = sample_surface(mesh, 40000, seed).voxel_down_sample(tracking_voxel)
    P = np.asarray(dense.points).copy()
    N = np.asarray(dense.normals).copy()
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    centre = 0.5 * (P.min(axis=0) + P.max(axis=0))
    radius = float(np.max(np.linalg.norm(P - centre, axis=1)))
    probe = P[np.random.default_rng(seed).choice(len(P), min(len(P), 300), replace=False)]
    solid = o3d.t.geometry.RaycastingScene()
    solid.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, dtype=np.float32)),
                        o3d.core.Tensor(np.asarray(mesh.triangles(), dtype=np.uint32)))
    model = TrackingModel(mesh.name, template, P, N, centre, radius, probe, solid, mesh=mesh,
                          box_min=P.min(axis=0), box_max=P.max(axis=0))
    model.axes = principal_axes(P)
    along = P @ model.axes.T
    model.extents = along.max(axis=0) - along.min(axis=0)
    box = np.random.default_rng(seed).uniform(P.min(axis=0), P.max(axis=0), size=(4000, 3))
    model.interior = box[model.signed_distance(box) < 0][:400]
    # continuous symmetry axes only (6-60 ms on the shipped models, 3 mm samples)
    from object_localizer.verification import sample_model_surface
    samples = sample_model_surface(mesh, 0.003, max_samples=8000, seed=seed)
    model.symmetry_axes = find_symmetries(samples.points, samples.spacing,
                                          discrete=False).continuous_axes
    return model


def penetration(model: TrackingModel, pose: np.ndarray, other: TrackingModel,
                other_pose: np.ndarray, depth: float) -> float:
    """
    Share of ``model``'s interior points inside ``other``.

    Share of ``model``'s interior points at ``pose`` lying more than ``depth`` [m] inside
    ``other`` at ``other_pose`` (both 4x4 model -> sensor): the overlap of the two volumes.
    """
    centre = pose[:3, :3] @ model.centre + pose[:3, 3]
    other_centre = other_pose[:3, :3] @ other.centre + other_pose[:3, 3]
    if np.linalg.norm(centre - other_centre) > model.radius + other.radius:
        return 0.0
    rel = np.linalg.solve(other_pose, pose)
    if not len(model.interior):
        return 0.0
    local = model.interior @ rel[:3, :3].T + rel[:3, 3]
    return float(np.mean(other.signed_distance(local) < -depth))


def overlap(model: TrackingModel, pose: np.ndarray, other: TrackingModel,
            other_pose: np.ndarray, depth: float) -> float:
    """
    Overlap of two placed volumes: the larger of the two :func:`penetration` shares.

    The share of either model's interior points lying more than ``depth`` [m] inside the other
    (both poses 4x4 model -> sensor), the larger of the two: a small part sunk into a large
    one overlaps it fully even where the large one's share inside the small one is small.
    """
    return max(penetration(model, pose, other, other_pose, depth),
               penetration(other, other_pose, model, pose, depth))


def mean_displacement(model: TrackingModel, pose_a: np.ndarray, pose_b: np.ndarray) -> float:
    """Mean distance [m] between the model's probe points placed by two poses (ADD)."""
    d = model.probe @ (pose_a[:3, :3] - pose_b[:3, :3]).T + (pose_a[:3, 3] - pose_b[:3, 3])
    return float(np.mean(np.linalg.norm(d, axis=1)))


def symmetric_distance(model: TrackingModel, pose_a: np.ndarray, pose_b: np.ndarray) -> float:
    """
    Compute the ADD-S [m] between two poses of the model (its probe points).

    About 0 for poses that are equivalent under the model's symmetries.
    """
    from scipy.spatial import cKDTree

    A = model.probe @ pose_a[:3, :3].T + pose_a[:3, 3]
    B = model.points @ pose_b[:3, :3].T + pose_b[:3, 3]
    return float(np.mean(cKDTree(B).query(A)[0]))


def same_shape(a: TrackingModel, b: TrackingModel, tolerance: float = 0.001) -> bool:
    """
    Tell whether two models are the same part.

    Whether two models are the same part (sorted bounding-box extents equal within
    ``tolerance`` [m] and surface sample counts within 2 %): acquisition cannot tell them
    apart by geometry.
    """
    ea = np.sort(a.box_max - a.box_min)
    eb = np.sort(b.box_max - b.box_min)
    return bool(np.all(np.abs(ea - eb) <= tolerance)
                and abs(len(a.points) - len(b.points)) <= 0.02 * max(len(a.points), 1))


def predict_constant_velocity(model: TrackingModel, history: Tuple[Tuple[int, np.ndarray], ...],
                              stamp_ns: int, max_extrapolation: float = 3.0) -> np.ndarray:
    """
    Pose at ``stamp_ns`` from the last two ``(stamp_ns, pose)`` of ``history``.

    The model centre moves on at its last linear velocity and the object turns on at its last
    angular velocity. The extrapolation is capped at ``max_extrapolation`` times the last interval
    (a long gap in the stream is not a reason to fly away); one pose: that pose.
    """
    if not history:
        raise ValueError('no pose to predict from')
    t1, T1 = history[-1]
    if len(history) < 2:
        return T1.copy()
    t0, T0 = history[-2]
    if t1 <= t0:
        return T1.copy()
    s = min(max((stamp_ns - t1) / (t1 - t0), 0.0), max_extrapolation)
    c0 = T0[:3, :3] @ model.centre + T0[:3, 3]
    c1 = T1[:3, :3] @ model.centre + T1[:3, 3]
    w = rotation_log(T1[:3, :3] @ T0[:3, :3].T)
    angle = float(np.linalg.norm(w))
    R_step = rotation_about_axis(w, s * angle) if angle > 1e-12 else np.eye(3)
    R = R_step @ T1[:3, :3]
    c = c1 + s * (c1 - c0)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = c - R @ model.centre
    return T


def carried_motion(model: TrackingModel, motion: Tuple[Tuple[int, np.ndarray], ...],
                   pose: np.ndarray, stamp_ns: int) -> Optional[Tuple[int, np.ndarray]]:
    """
    Return a virtual earlier ``(stamp_ns, pose)`` giving ``pose`` the velocity of ``motion``.

    ``motion``: the last two verified ``(stamp_ns, 4x4 pose)`` of a track before it was lost;
    ``pose``: the re-acquired pose at ``stamp_ns``. The returned pose lies one interval of
    ``motion`` before ``stamp_ns``, with the model centre moved back by the centre's
    displacement over that interval and the object turned back by its rotation (sensor frame),
    so that :func:`predict_constant_velocity` from (it, ``pose``) moves on as the track did.
    Both are invariant under the model's symmetries (the centre lies on every symmetry axis):
    a re-acquired pose that is a symmetric twin of the lost one's continuation inherits the
    right motion, where a velocity between the pose before the loss and the re-acquired pose
    would carry the symmetry's turn. None when ``motion`` holds no interval.
    """
    if len(motion) < 2:
        return None
    (t0, T0), (t1, T1) = motion[-2], motion[-1]
    if t1 <= t0:
        return None
    w = rotation_log(T1[:3, :3] @ T0[:3, :3].T)
    angle = float(np.linalg.norm(w))
    R = np.asarray(pose, dtype=float)[:3, :3]
    R_prev = rotation_about_axis(w, -angle) @ R if angle > 1e-12 else R.copy()
    shift = (T1[:3, :3] - T0[:3, :3]) @ model.centre + T1[:3, 3] - T0[:3, 3]
    c_prev = R @ model.centre + pose[:3, 3] - shift
    T = np.eye(4)
    T[:3, :3] = R_prev
    T[:3, 3] = c_prev - R_prev @ model.centre
    return int(stamp_ns) - (int(t1) - int(t0)), T


class SceneCloud:
    """
    One scene cloud (N, 3) [m, sensor frame], shared by every object of a frame.

    Crops are computed on demand. Non-finite rows are allowed (organised clouds) and ignored.
    """

    def __init__(self, points: np.ndarray) -> None:
        P = np.asarray(points)
        if P.ndim != 2 or P.shape[1] != 3:
            raise ValueError(f'scene points must have shape (N, 3), got {P.shape}')
        self.points = P
        with np.errstate(invalid='ignore'):
            front = int(np.count_nonzero(P[:, 2] > 1e-6))
        if front < 10:
            raise ValueError(f'scene has only {front} finite points in front of the sensor')

    def cone(self, centre: np.ndarray, radius: float) -> np.ndarray:
        """
        Points (M, 3) on rays through a sphere, at any depth.

        Points (M, 3) float64 on rays through the sphere (``centre`` [m], ``radius`` [m]),
        at any depth: what the sensor sees in the direction of an object there.
        """
        cz = float(centre[2])
        if cz <= radius:
            return np.empty((0, 3))
        a0, b0 = float(centre[0]) / cz, float(centre[1]) / cz
        rho = radius / np.sqrt(max(cz * cz - radius * radius, 1e-12)) * \
            np.sqrt(1.0 + a0 * a0 + b0 * b0) * 1.05
        return crop_rays(self.points, a0, b0, rho)

    def in_box(self, pose: np.ndarray, model_points: np.ndarray, margin: float = 0.0
               ) -> np.ndarray:
        """
        Return the points inside the grown bounding box of the model, in the cloud's order.

        Points (M, 3) float64 inside the bounding box of ``model_points`` (model frame [m])
        grown by ``margin`` [m] on every side, at ``pose`` (4x4 model -> sensor): the object's
        own cloud (``objects/<name>/cloud``). One compiled pass over the cloud
        (:func:`object_localizer.crop.crop_near`; the box's circumscribed sphere first).
        """
        lo = np.min(model_points, axis=0) - margin
        hi = np.max(model_points, axis=0) + margin
        centre = pose[:3, :3] @ (0.5 * (lo + hi)) + pose[:3, 3]
        return crop_near(self.points, centre, 0.5 * float(np.linalg.norm(hi - lo)), pose, lo, hi)


@dataclass
class PoseQuality:
    """
    Result of :func:`check_pose` (see the module docstring).

    :ivar quality: summary in [0, 1]: the inlier fraction, reduced linearly by the residual, the
        free-space violations and the prediction error relative to their limits, and scaled by
        the silhouette edge support relative to twice its limit (capped at 1).
    :ivar edge_fraction: silhouette edge support in [0, 1] (NaN: too few silhouette pixels
        could be judged); see ``TrackerSettings.min_edge_fraction``.
    :ivar passed: every check passed; ``reason`` names the first failed one.
    """

    inlier_fraction: float = 0.0
    visible_residual: float = float('nan')
    free_space_fraction: float = 0.0
    prediction_error: float = 0.0
    visible_samples: int = 0
    penetration: float = 0.0
    edge_fraction: float = float('nan')
    quality: float = 0.0
    passed: bool = False
    reason: str = ''

    @property
    def support(self) -> float:
        """Inliers minus contradicted samples (:attr:`VisibleEvidence.support`) of the check."""
        return self.visible_samples * (2.0 * self.inlier_fraction - 1.0)


def _range_image(points: np.ndarray, pixel: float, lo: np.ndarray, shape: Tuple[int, int]
                 ) -> np.ndarray:
    """
    Nearest depth per pixel of a virtual pinhole image.

    Nearest depth per pixel of a virtual pinhole image in normalised coordinates (x/z, y/z)
    with pixel size ``pixel`` from ``lo``; NaN where nothing is observed.
    """
    return nearest_depth_image(points, pixel, lo, shape)


def _pixels(points: np.ndarray, pixel: float, lo: np.ndarray, shape: Tuple[int, int]
            ) -> Tuple[np.ndarray, np.ndarray]:
    u = np.floor((points[:, 0] / points[:, 2] - lo[0]) / pixel).astype(np.int64)
    v = np.floor((points[:, 1] / points[:, 2] - lo[1]) / pixel).astype(np.int64)
    ok = (u >= 0) & (u < shape[1]) & (v >= 0) & (v < shape[0])
    return v * shape[1] + u, ok


#: smallest distance [pixels of the check's image] between the model's outline and the outside
#: pixel judged by the edge test (see ``TrackerSettings.edge_gap``)
EDGE_GAP = 2


def silhouette_edge_fraction(model: TrackingModel, pose: np.ndarray, cone_points: np.ndarray,
                             pixel: float, settings: TrackerSettings) -> float:
    """
    Measure the share of the model's silhouette that shows a depth edge.

    Share of the model's silhouette (every sample facing the sensor, at ``pose``) where the
    observed depth ``settings.edge_gap`` outside (at least ``EDGE_GAP`` pixels) jumps behind
    it by more than
    ``settings.edge_threshold`` or is missing (:func:`~object_localizer.verification.
    silhouette_edges`), on a virtual pinhole image of ``pixel`` [normalised image units, i.e.
    radians] over the silhouette; NaN when fewer than ``settings.min_edge_samples`` pixels
    could be judged. Model and scene are drawn by the acquisition's verification
    (``render_model_depth``, ``observe_depth``).

    :param cone_points: (M, 3) scene points [m] on the rays through the object.
    """
    from object_localizer.verification import _zbuffer, PinholeCamera, render_model_depth, \
        silhouette_edges

    R, t = pose[:3, :3], pose[:3, 3]
    centres = model.points @ R.T + t
    front = centres[:, 2] > 1e-6
    if np.count_nonzero(front) < 3 or len(cone_points) < 3:
        return float('nan')
    a = centres[front, :2] / centres[front, 2:3]
    depth = float(np.median(centres[front, 2]))
    gap = max(EDGE_GAP, int(np.ceil(settings.edge_gap / (pixel * depth))))
    margin = (gap + 2) * pixel
    lo = a.min(axis=0) - margin
    hi = a.max(axis=0) + margin
    width, height = int((hi[0] - lo[0]) / pixel) + 1, int((hi[1] - lo[1]) / pixel) + 1
    if width * height > 4_000_000:
        return float('nan')
    camera = PinholeCamera(1.0 / pixel, 1.0 / pixel, -lo[0] / pixel - 0.5,
                           -lo[1] / pixel - 0.5, width, height)
    sil = render_model_depth(model.points, model.normals, pose, camera, 0.0)
    mask = np.isfinite(sil)
    if not mask.any():
        return float('nan')
    # samples about as far apart as pixels leave single-pixel holes: fill those with model
    # pixels on both sides (a hole would read as outline)
    holes = np.zeros_like(mask)
    holes[1:-1, :] |= mask[:-2, :] & mask[2:, :]
    holes[:, 1:-1] |= mask[:, :-2] & mask[:, 2:]
    sil[holes & ~mask] = np.nanmax(sil)
    # only the rays through the image (the others fall outside it): one compiled pass
    # (observe_depth's z-buffer, without its finiteness pass: the crop is finite)
    window = crop_window(cone_points, lo - pixel, hi + pixel)
    cam = camera.scaled(1)
    observed = _zbuffer(window, cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height, 0)
    observed[~np.isfinite(observed)] = np.nan
    sup, cont = silhouette_edges(sil, observed, settings.edge_threshold, gap)
    if sup + cont < settings.min_edge_samples:
        return float('nan')
    return sup / (sup + cont)


@dataclass
class VisibleEvidence:
    """
    What the scene says about the model samples a pose expects to be visible.

    :ivar expected: model samples facing both cameras, not hidden by the model itself, and
        not clearly occluded by something in front (the samples the sensor should measure).
    :ivar inliers: of those, the ones with an observed surface within ``inlier_distance``.
    :ivar behind: of those, the ones through which the sensor sees a surface behind the model.
    :ivar occluded: samples hidden by something clearly in front of them.
    :ivar residual: RMS normal distance [m] of the inliers (NaN without inliers).
    :ivar pixel: angular size of the virtual image's pixels [rad] (0: no image was built).
    :ivar reason: why nothing could be measured ('' when it could).
    """

    expected: int = 0
    inliers: int = 0
    behind: int = 0
    occluded: int = 0
    residual: float = float('nan')
    pixel: float = 0.0
    reason: str = ''

    @property
    def support(self) -> int:
        """Inliers minus the expected samples the scene contradicts (misfits)."""
        return 2 * self.inliers - self.expected


def visible_evidence(model: TrackingModel, pose: np.ndarray, cone_points: np.ndarray,
                     settings: TrackerSettings) -> VisibleEvidence:
    """
    Compare the model samples ``pose`` (4x4 model -> sensor) expects to see with the scene.

    :param cone_points: the scene points (M, 3) [m, sensor frame] on the rays through the
        object (``SceneCloud.cone``).
    """
    s = settings
    R, t = pose[:3, :3], pose[:3, 3]
    P = model.points @ R.T + t
    N = model.normals @ R.T
    cos = np.einsum('ij,ij->i', N, -P) / np.linalg.norm(P, axis=1)
    facing = (cos >= s.min_view_cos) & (P[:, 2] > 1e-6)
    if s.stereo_baseline > 0:   # stereo measures only what the second camera sees too
        to_right = np.array([s.stereo_baseline, 0.0, 0.0]) - P
        facing &= np.einsum('ij,ij->i', N, to_right) >= \
            s.min_view_cos * np.linalg.norm(to_right, axis=1)
    P, N, cos = P[facing], N[facing], cos[facing]
    if len(P) < s.min_visible_samples or len(cone_points) < s.min_visible_samples:
        return VisibleEvidence(reason=f'{len(P)} model samples face the sensor, '
                               f'{len(cone_points)} scene points on their rays: too few to '
                               'verify')
    # Virtual image over the model's silhouette, pixel ~ 1.5 x the scene's angular spacing.
    a = P[:, :2] / P[:, 2:3]
    lo, hi = a.min(axis=0), a.max(axis=0)
    inside = crop_window(cone_points, lo, hi)     # the scene on the rays of the silhouette
    area = float(np.prod(np.maximum(hi - lo, 1e-6)))
    pixel = 1.5 * np.sqrt(area / max(len(inside), 1))
    pixel = max(pixel, 1e-4)
    shape = (int((hi[1] - lo[1]) / pixel) + 1, int((hi[0] - lo[0]) / pixel) + 1)
    if shape[0] * shape[1] > 4_000_000:
        return VisibleEvidence(reason='scene too sparse on the object to verify')
    observed = _range_image(inside, pixel, lo, shape)
    own = _range_image(P, pixel, lo, shape)
    idx, ok = _pixels(P, pixel, lo, shape)
    idx = np.where(ok, idx, 0)
    # not hidden by the model itself (z-buffer of its own samples, one sample spacing deep)
    self_visible = ok & (P[:, 2] <= own[idx] + 2.0 * s.inlier_distance)
    z_obs = observed[idx]
    z_mod = P[:, 2]
    normal_dist = (z_obs - z_mod) * cos          # signed, > 0: observed behind the model
    with np.errstate(invalid='ignore'):
        seen = np.isfinite(z_obs)
        inlier = self_visible & seen & (np.abs(normal_dist) <= s.inlier_distance)
        # an occluder is clearly in front; a surface a few mm in front is more likely the
        # object itself, misplaced: it counts against the pose
        occluded = self_visible & seen & (z_obs < z_mod - 3.0 * s.inlier_distance)
        behind = self_visible & seen & (normal_dist > s.inlier_distance)
    misfit = self_visible & ~inlier & ~occluded
    n_in = int(np.count_nonzero(inlier))
    expected = n_in + int(np.count_nonzero(misfit))
    n_occ = int(np.count_nonzero(occluded))
    if expected < s.min_visible_samples:
        return VisibleEvidence(expected, n_in, occluded=n_occ, pixel=pixel, reason=(
            f'only {expected} model samples expected visible ({n_occ} occluded): too few to '
            'verify'))
    residual = float(np.sqrt(np.mean(normal_dist[inlier] ** 2))) if n_in else float('nan')
    return VisibleEvidence(expected, n_in, int(np.count_nonzero(behind)), n_occ, residual,
                           pixel)


def check_pose(model: TrackingModel, pose: np.ndarray, cone_points: np.ndarray,
               settings: TrackerSettings, prediction: Optional[np.ndarray] = None,
               others: Sequence[Tuple[TrackingModel, np.ndarray]] = (),
               acquisition: bool = False) -> PoseQuality:
    """
    Check ``pose`` against the scene points on the rays through the object.

    Visibility-aware check of ``pose`` against the scene points on the rays through the
    object (``SceneCloud.cone``), see the module docstring and :func:`visible_evidence`.

    :param prediction: the motion prediction (4x4) the pose is compared with; None: no check.
    :param others: other objects' verified (model, pose): the pose must not penetrate them.
    :param acquisition: the pose has no prediction (acquisition, hint): the stricter
        ``min_acquisition_inlier_fraction`` applies.
    """
    s = settings
    q = PoseQuality()
    if prediction is not None:
        q.prediction_error = mean_displacement(model, pose, prediction)
    ev = visible_evidence(model, pose, cone_points, s)
    q.visible_samples = ev.expected
    if ev.reason:
        q.reason = ev.reason
        return q
    expected = ev.expected
    q.inlier_fraction = ev.inliers / expected
    q.free_space_fraction = ev.behind / expected
    q.visible_residual = ev.residual
    min_inliers = max(s.min_inlier_fraction, s.min_acquisition_inlier_fraction) \
        if acquisition else s.min_inlier_fraction
    checks = [
        (q.inlier_fraction >= min_inliers,
         f'inlier fraction {q.inlier_fraction:.2f} < {min_inliers:.2f}'),
        (q.visible_residual <= s.max_visible_residual,
         f'visible residual {1e3 * q.visible_residual:.2f} mm > '
         f'{1e3 * s.max_visible_residual:.2f} mm'),
        (q.free_space_fraction <= s.max_free_space_fraction,
         f'free-space violations {q.free_space_fraction:.2f} > {s.max_free_space_fraction:.2f}'),
        (q.prediction_error <= s.max_prediction_error,
         f'{1e3 * q.prediction_error:.1f} mm from the prediction > '
         f'{1e3 * s.max_prediction_error:.1f} mm'),
    ]
    q.edge_fraction = silhouette_edge_fraction(model, pose, cone_points, ev.pixel, s)
    checks.append((not q.edge_fraction < s.min_edge_fraction,
                   f'silhouette edge support {q.edge_fraction:.2f} < {s.min_edge_fraction:.2f} '
                   "(the observed surface goes on past the model's outline: it lies inside a "
                   'larger surface)'))
    for other, other_pose in others:
        share = penetration(model, pose, other, other_pose, s.max_penetration)
        q.penetration = max(q.penetration, share)
        checks.append((share <= 0.1, f'{100 * share:.0f} % of the volume deeper than '
                                     f'{1e3 * s.max_penetration:.0f} mm inside {other.name}'))
    failed = [why for ok_, why in checks if not ok_]
    q.passed = not failed
    q.reason = '; '.join(failed)
    res = q.visible_residual if np.isfinite(q.visible_residual) else s.max_visible_residual
    edge = 1.0 if not np.isfinite(q.edge_fraction) or s.min_edge_fraction <= 0 else \
        min(q.edge_fraction / (2.0 * s.min_edge_fraction), 1.0)
    q.quality = float(np.clip(edge * q.inlier_fraction
                              * (1.0 - min(res / s.max_visible_residual, 1.0) / 2.0)
                              * (1.0 - min(q.free_space_fraction / s.max_free_space_fraction,
                                           1.0) / 2.0)
                              * (1.0 - min(q.prediction_error / s.max_prediction_error,
                                           1.0) / 2.0), 0.0, 1.0))
    return q


def _visible_target(model: TrackingModel, pose: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """
    Return the model samples facing the sensor at ``pose``.

    The model samples (M, 3) [m, sensor frame] facing the sensor at ``pose``, and their unit
    normals (M, 3).
    """
    R, t = pose[:3, :3], pose[:3, 3]
    P = model.points @ R.T + t
    N = model.normals @ R.T
    keep = np.einsum('ij,ij->i', N, -P) > 0
    return P[keep], N[keep]


def track_icp(model: TrackingModel, near_points: np.ndarray, start: np.ndarray,
              settings: TrackerSettings) -> np.ndarray:
    """
    Point-to-plane ICP with a Tukey M-estimator from ``start``.

    The scene points near the object (M, 3) [m] are aligned to the model samples facing the sensor
    (exact normals), in two stages (kernel 3k, radius 2 x max_distance; then k, max_distance);
    returns the pose. The iterations are :func:`object_localizer.point_to_plane.icp_point_to_plane`
    (Open3D's Tukey point-to-plane ICP, compiled, with its grid-based exact nearest neighbours).
    """
    s = settings
    S = np.asarray(near_points, dtype=np.float64)
    if s.scene_voxel > 0:
        S = np.asarray(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(S))
                       .voxel_down_sample(s.scene_voxel).points)
    if len(S) > s.max_icp_points:     # big objects: a fixed, even share of the crop
        step = len(S) / s.max_icp_points
        S = S[np.floor(np.arange(s.max_icp_points) * step).astype(int)]
    pose = np.asarray(start, dtype=float).copy()
    for scale, reach, min_step, min_residual in (
            (3.0 * s.loss_scale, 2.0 * s.max_distance, s.icp_coarse_min_step,
             s.icp_coarse_min_residual_step),
            (s.loss_scale, s.max_distance, s.icp_min_step, s.icp_min_residual_step)):
        P, N = _visible_target(model, pose)
        if len(P) < 3 or len(S) < 3:
            break
        # target frame = sensor; the scene is moved onto the model: T_scene->model_at_pose
        # never turned about its continuous symmetry axes (in the sensor frame at ``pose``)
        correction, _, _, _ = icp_point_to_plane(S, P, N, reach, scale, s.icp_iterations,
                                                 tolerance=1e-6, min_step=min_step,
                                                 min_residual_step=min_residual,
                                                 locked_rotations=model.symmetry_axes
                                                 @ pose[:3, :3].T)
        pose = np.linalg.solve(correction, pose)
    return pose


@dataclass
class TrackUpdate:
    """
    Outcome of one cloud for one object.

    :ivar pose: the verified pose (4x4), or None: nothing to publish for this cloud.
    :ivar state: the track state after this cloud.
    :ivar quality: the check of the best candidate (None: no candidate was found).
    :ivar reason: what happened, for the status message.
    :ivar cpu_seconds: process CPU time spent on this object for this cloud [s].
    :ivar acquired: the pose comes from the global acquisition.
    :ivar lost: the track was lost in this cloud (and, with a pose, re-acquired at once).
    """

    pose: Optional[np.ndarray]
    state: TrackState
    quality: Optional[PoseQuality]
    reason: str
    cpu_seconds: float = 0.0
    acquired: bool = False
    lost: bool = False


def refine_and_check(model: TrackingModel, scene: SceneCloud, start: np.ndarray,
                     settings: TrackerSettings, prediction: Optional[np.ndarray] = None,
                     others: Sequence[Tuple[TrackingModel, np.ndarray]] = (),
                     acquisition: bool = False, refine: bool = True
                     ) -> Tuple[np.ndarray, PoseQuality]:
    """
    Refine ``start`` (4x4 model -> sensor) by the tracking ICP and check the result.

    The ICP runs on the scene points near the pose (within reach of the model's centre and in
    its bounding box grown by the ICP reach); the check (:func:`check_pose`) on the points on
    the rays through the object. ``refine`` false: ``start`` itself is checked.

    :param others: verified (model, pose) of other objects: the pose must not penetrate them.
    :return: (pose, its check).
    """
    m, s = model, settings
    reach = m.radius + 2.0 * s.max_distance
    centre = start[:3, :3] @ m.centre + start[:3, 3]
    cone = scene.cone(centre, reach)
    if not refine:      # check ``start`` itself
        return start, check_pose(m, start, cone, s, prediction, others, acquisition)
    margin = 2.0 * s.max_distance
    near = crop_near(cone, centre, reach, start, m.box_min - margin, m.box_max + margin)
    if len(near) < 10:
        return start, PoseQuality(reason=f'only {len(near)} scene points near the pose')
    pose = track_icp(m, near, start, s)
    return pose, check_pose(m, pose, cone, s, prediction, others, acquisition)


def pose_support(model: TrackingModel, scene: SceneCloud, pose: np.ndarray,
                 settings: TrackerSettings) -> int:
    """
    Scene support of ``pose`` (4x4 model -> sensor) as :func:`refine_and_check` checks it.

    :attr:`VisibleEvidence.support` (inliers minus contradicted samples) on the scene points
    of the rays through the object (the check's cone), without the rest of the check: equal
    to :attr:`PoseQuality.support` of ``refine_and_check(..., refine=False)``.
    """
    m, s = model, settings
    cone = scene.cone(pose[:3, :3] @ m.centre + pose[:3, 3], m.radius + 2.0 * s.max_distance)
    return visible_evidence(m, pose, cone, s).support


def slide_along_axes(model: TrackingModel, scene: SceneCloud, pose: np.ndarray,
                     q: PoseQuality, settings: TrackerSettings,
                     others: Sequence[Tuple[TrackingModel, np.ndarray]] = (),
                     longest_only: bool = False) -> Tuple[np.ndarray, PoseQuality, str]:
    """
    Search a pose's position along the model's principal axes by scene support.

    Pattern search of the translation along each of ``model.axes`` (steps of a quarter of
    the model's extent along it, halved down to ``slide_min_step``; at most half the extent
    in all) keeping a move when the support (:attr:`VisibleEvidence.support`: inliers
    minus contradicted samples) grows by more than 2 % of the expected-visible samples (at
    least ``min_visible_samples``); a moved pose is refined by ICP and checked again (no
    prediction, :func:`refine_and_check`) and replaces ``pose`` only if it passes with that
    much more support.

    :param pose: the pose (4x4 model -> sensor), usually one that passed the acquisition check.
    :param q: its check.
    :param others: verified (model, pose) of other objects, for the check.
    :param longest_only: search along the model's longest axis only (a third of the work).
    :return: (pose, check, '' or how it moved).
    """
    s, m = settings, model
    if s.slide_min_step <= 0:
        return pose, q, ''
    centre = pose[:3, :3] @ m.centre + pose[:3, 3]
    cone = scene.cone(centre, m.radius + 2.0 * s.max_distance + 0.5 * float(max(m.extents)))
    gain = max(0.02 * q.visible_samples, s.min_visible_samples)
    pick = [int(np.argmax(m.extents))] if longest_only else slice(None)
    T0, _, start = search_along_axes(
        pose, m.axes[pick], 0.25 * m.extents[pick],
        lambda T: visible_evidence(m, T, cone, s).support, gain, s.slide_min_step,
        0.5 * m.extents[pick])
    if T0 is pose:
        return pose, q, ''
    pose2, q2 = refine_and_check(m, scene, T0, s, None, others, acquisition=True)
    after = visible_evidence(m, pose2, cone, s).support
    if not q2.passed or after <= start + gain:
        return pose, q, ''
    moved = float(np.linalg.norm(pose2[:3, 3] - pose[:3, 3]))
    return pose2, q2, (f'slid {1e3 * moved:.1f} mm along the model axes to a place the '
                       f'scene supports better ({start} -> {after} samples); ')


#: Global acquisition: (model, scene points (N, 3) [m], seed, explained) -> candidate poses
#: (best first). ``explained``: None, or (points (M, 3) [m, scene frame], radius [m]): the
#: surface samples of objects already verified in the cloud; scene points within the radius of
#: them are left out of the search (they only find those objects again).
Acquirer = Callable[[TrackingModel, np.ndarray, int, Optional[Tuple[np.ndarray, float]]], list]


def unexplained(points: np.ndarray, explained: Optional[np.ndarray], radius: float
                ) -> np.ndarray:
    """
    Return the mask of the points that no explained point is near.

    Mask (N,) of ``points`` (N, 3) farther than ``radius`` [m] from every row of ``explained``
    (M, 3) [m, same frame]: all True when ``explained`` is None or empty.
    """
    keep = np.ones(len(points), dtype=bool)
    if explained is None or not len(explained) or not len(points):
        return keep
    from scipy.spatial import cKDTree
    d = cKDTree(np.asarray(explained, dtype=float)).query(
        points, k=1, distance_upper_bound=radius)[0]
    return d > radius


def acquire_rough_fine(model: TrackingModel, points: np.ndarray, seed: int,
                       explained: Optional[Tuple[np.ndarray, float]] = None) -> list:
    """Global acquisition with ``localization.localize`` (FPFH + RANSAC, then ICP)."""
    P = np.asarray(points, dtype=float)
    P = P[np.all(np.isfinite(P), axis=1)]
    if explained is not None:
        P = P[unexplained(P, *explained)]
    return [localize(model.template, P, seed=seed).pose]


def make_acquirer(method: str, max_candidates: int = 6,
                  time_budget_s: float = 0.0,
                  camera: Optional[Callable[[], Any]] = None,
                  stereo_baseline: Optional[Callable[[], float]] = None) -> Acquirer:
    """
    Make the global acquisition of ``object_localizer.acquisition`` an Acquirer.

    The global acquisition of ``object_localizer.acquisition`` (``'ppf'``: point-pair-feature
    voting, ``'fpfh'``: FPFH + RANSAC, both with visibility verification) as an
    :data:`Acquirer`: its best ``max_candidates`` hypotheses, refined or not, best first (the
    tracker refines and checks each in turn); ``'rough_fine'``: :func:`acquire_rough_fine`.
    The acquisition model is built on first use and kept on the tracking model.

    :param camera: called at every acquisition: the intrinsics of the camera the clouds come
        from (``verification.as_camera`` forms, e.g. from the CameraInfo of the cloud's
        frame), or None (a virtual camera over the points).
    :param stereo_baseline: called at every acquisition: the stereo baseline [m] (second camera
        at +x of the cloud's optical frame) the visibility score reasons with; 0 or None: not
        stereo.

    The scene preparation (finite points, down-sampled clouds with normals, plane removal,
    observed depth: about 0.2 s of CPU per synthetic stereo cloud) is kept for the next call
    with the same points array and camera: the trackers of one cloud share it
    (:attr:`SceneCloud.points`). The array must not be changed in place meanwhile.
    """
    if method == 'rough_fine':
        return acquire_rough_fine
    from object_localizer import acquisition

    if method not in acquisition.METHODS:
        raise ValueError(f'acquisition method must be one of '
                         f'{("rough_fine",) + tuple(acquisition.METHODS)}, got {method!r}')

    last: list = [None, None, None]     # the last cloud's points array, (camera, baseline), scene

    def acquire(model: TrackingModel, points: np.ndarray, seed: int,
                explained: Optional[Tuple[np.ndarray, float]] = None) -> list:
        if model.acquisition is None:
            model.acquisition = acquisition.prepare_acquisition_model(model.mesh,
                                                                      check_model=model)
        view = (camera() if camera else None,
                float(stereo_baseline()) if stereo_baseline else 0.0)
        if last[0] is points and last[1] == view:
            scene = last[2]
        else:
            P = np.asarray(points, dtype=float)
            scene = acquisition.prepare_acquisition_scene(
                P[np.all(np.isfinite(P), axis=1)], camera=view[0], stereo_baseline=view[1])
            last[:] = [points, view, scene]
        exclude, radius = explained if explained is not None else (None, 0.0)
        hyps = acquisition.acquire_object(model.acquisition, scene, method=method, seed=seed,
                                          time_budget_s=time_budget_s, exclude_points=exclude,
                                          exclude_radius=radius, polish=False,
                                          tie_margin=0.0)
        return [h.pose for h in hyps[:max_candidates]]
    return acquire


@dataclass
class ObjectTracker:
    """Tracks one model through successive scene clouds (see the module docstring)."""

    model: TrackingModel
    settings: TrackerSettings = field(default_factory=TrackerSettings)
    acquirer: Acquirer = acquire_rough_fine
    state: TrackState = TrackState.ACQUIRING
    history: Deque[Tuple[int, np.ndarray]] = field(default_factory=deque)
    hint: Optional[np.ndarray] = None
    reference: Optional[np.ndarray] = None     # the last known pose (hint or before a loss)
    twins: list = field(default_factory=list)  # trackers of parts with the same shape
    #: the distinct places (pose, quality) that passed the check in the last global search
    places: list = field(default_factory=list)
    #: the track was named among identical parts by stale known poses, not decisively
    naming_uncertain: bool = False
    lost_count: int = 0
    acquisitions: int = 0
    _last_check_ns: Optional[int] = None
    _lost_ns: Optional[int] = None             # stamp of the cloud where the track was lost
    _reference_ns: Optional[int] = None        # stamp at which ``reference`` was verified
    _motion: tuple = ()                        # the last two verified (stamp, pose) before a loss
    _static_samples: list = field(default_factory=list)   # a static object's verified poses
    _last_quality: Optional[PoseQuality] = None
    _others: list = field(default_factory=list)
    _state_before: TrackState = TrackState.ACQUIRING   # the state before the last update

    def reset(self, pose: Optional[np.ndarray] = None) -> None:
        """
        Forget the track.

        ``pose`` (4x4 model -> sensor) is a hint for the next cloud, verified like any pose before
        it is published.
        """
        self.history.clear()
        self.hint = None if pose is None else np.asarray(pose, dtype=float).copy()
        self.reference = self.hint
        self.state = TrackState.ACQUIRING
        self.naming_uncertain = False
        self._last_check_ns = None
        self._lost_ns = None
        self._reference_ns = None
        self._motion = ()

    def _accept(self, stamp_ns: int, pose: np.ndarray) -> None:
        if self.history and stamp_ns <= self.history[-1][0]:
            self.history.clear()         # stamps went back (bag loop, restart): no velocity
        self.history.append((int(stamp_ns), pose))
        while len(self.history) > max(self.settings.max_history, 2):
            self.history.popleft()

    def _refine_and_check(self, scene: SceneCloud, start: np.ndarray,
                          prediction: Optional[np.ndarray], acquisition: bool = False,
                          refine: bool = True) -> Tuple[np.ndarray, PoseQuality]:
        # self._others: set by update() for the duration of one cloud
        return refine_and_check(self.model, scene, start, self.settings, prediction,
                                self._others, acquisition, refine)

    def update(self, points: np.ndarray | SceneCloud, stamp_ns: int,
               others: Sequence[Tuple[TrackingModel, np.ndarray]] = (),
               reacquire: bool = True, search: bool = True) -> TrackUpdate:
        """
        Process one cloud (N, 3) [m] (or a :class:`SceneCloud` shared by several trackers).

        :param others: the verified (model, pose) of other objects in this cloud; a pose that
            penetrates one of them fails the check.
        :param reacquire: a track lost in this cloud is searched for globally at once (in this
            cloud); False: it is only reported lost (state ``LOST``), and the next ``update``
            (in this cloud or the next) searches -- so a caller can first finish the objects
            that still track (their poses, and the twins they rule out, come first).
        :param search: the global search may run in this cloud; False: only the hint or the
            local re-acquisition around the last pose (a caller spreading the searches' CPU
            over clouds, see ``ObjectLocalizerNode``); the reason then says it was deferred.

        :raises ValueError: the cloud is unusable (shape, too few finite points).
        """
        t0 = time.process_time()
        scene = points if isinstance(points, SceneCloud) else SceneCloud(points)
        self._others = list(others)
        self._state_before = self.state
        result = self._update(scene, int(stamp_ns), reacquire, search)
        result.cpu_seconds = time.process_time() - t0
        if result.pose is not None:
            self._last_quality = result.quality
        return result

    def _update(self, scene: SceneCloud, stamp_ns: int, reacquire: bool = True,
                search: bool = True) -> TrackUpdate:
        s = self.settings
        if self.state == TrackState.STATIC and self.history:
            due = self._last_check_ns is None or \
                stamp_ns - self._last_check_ns >= s.static_recheck_period * 1e9 or \
                stamp_ns < self._last_check_ns
            held = self.history[-1][1]
            if not due:
                return TrackUpdate(held.copy(), TrackState.STATIC, self._last_quality,
                                   'static: pose held since the last check')
            # static_average > 1: refined by ICP from the held pose and, verified, averaged
            # with the earlier re-checks (:meth:`_static_mean`); the held pose itself is
            # checked only when that fails. static_average 1: the held pose is checked first
            # (one check, not ICP + check: hole_block about half) and refined only if it fails
            pose, q, how = None, None, ''
            if s.static_average > 1:    # refined and averaged: the held pose is a mean
                refined, q_refined = self._refine_and_check(scene, held, held)
                if q_refined.passed:
                    pose, q, how = self._static_mean(scene, refined, q_refined, held)
            if pose is None:
                pose, q = self._refine_and_check(scene, held, held, refine=False)
                how = 'static: re-checked (the held pose verified)'
                if not q.passed and s.static_average <= 1:
                    pose, q = self._refine_and_check(scene, held, held)
                    how = 'static: re-checked (refined)'
            if q.passed:
                self._accept(stamp_ns, pose)
                self._last_check_ns = stamp_ns
                return TrackUpdate(pose, TrackState.STATIC, q, how)
            return self._lose(q, f'static pose failed its re-check: {q.reason}', stamp_ns)
        if self.state == TrackState.TRACKING and self.history:
            gap = (stamp_ns - self.history[-1][0]) * 1e-9
            slid = ''
            if len(self.history) >= 2 and 0.0 < gap <= s.prediction_horizon:
                prediction = predict_constant_velocity(self.model, tuple(self.history)[-2:],
                                                       stamp_ns)
                pose, q = self._refine_and_check(scene, prediction, prediction)
            else:   # no velocity yet, or too long ago to extrapolate: no prediction to check
                pose, q = self._refine_and_check(scene, self.history[-1][1], None,
                                                 acquisition=True)
                if not q.passed and len(self.history) >= 2 and gap > 0.0:
                    # a slow graph (clouds 0.5 s apart): the extrapolated motion (capped at 3
                    # intervals) as a start only, checked without a prediction
                    start = predict_constant_velocity(self.model, tuple(self.history)[-2:],
                                                      stamp_ns)
                    pose2, q2 = self._refine_and_check(scene, start, None, acquisition=True)
                    if q2.passed:
                        pose, q = pose2, q2
                if q.passed:    # nothing to compare with: the part may have slid along itself
                    pose, q, slid = self.slide_along_axes(scene, pose, q)
            if not q.passed and len(self.history) >= 2:
                # a sudden stop or turn: from the last pose (no motion) before giving up
                last = self.history[-1][1]
                pose2, q2 = self._refine_and_check(scene, last, last)
                if q2.passed:
                    pose, q = pose2, q2
            if q.passed and self.twins:
                # an identical part not yet verified in this cloud does not stop the ICP from
                # sliding onto its place (the penetration check only knows verified poses):
                # the tracked pose must be clearly this part's (measured: link_base tracked
                # onto link_arm's place after the scene's loop jump, names swapped for 25
                # clouds, bench/localizer_reacquisition.py)
                ok, why = self._may_name(pose, stamp_ns)
                if not ok:
                    q = replace(q, passed=False, reason=f'identical part: {why}')
            if q.passed:
                self._accept(stamp_ns, pose)
                return TrackUpdate(pose, TrackState.TRACKING, q, f'{slid}tracking')
            lost = self._lose(q, f'track lost: {q.reason}', stamp_ns)
            if not reacquire:
                return lost
            # re-acquire at once, in this cloud (the next one may be far away in time)
            again = self._acquire(scene, stamp_ns, f'{lost.reason}; ', search)
            again.lost = True
            if again.quality is None:
                again.quality = q       # the failed check of the tracked pose
            return again
        return self._acquire(scene, stamp_ns, '', search)

    def _acquire(self, scene: SceneCloud, stamp_ns: int, prefix: str,
                 search: bool = True) -> TrackUpdate:
        """Try a hint or local re-acquisition first (verified), else the global search."""
        s = self.settings
        hint_reason = prefix
        self.places = []
        if self.hint is not None:
            hint, self.hint = self.hint, None
            pose, q = self._refine_and_check(scene, hint, None, acquisition=True)
            if q.passed:
                pose, q, slid = self.slide_along_axes(scene, pose, q)
                return self._start(stamp_ns, pose, q, f'{slid}initial pose verified')
            hint_reason = f'{prefix}initial pose rejected ({q.reason}); '
        elif self._relock_due(stamp_ns):
            pose, q, why = self._relock(scene, stamp_ns)
            if pose is not None:
                moved = mean_displacement(self.model, pose, self.reference)
                return self._start(stamp_ns, pose, q, hint_reason + (
                    f're-locked: {why} ({1e3 * moved:.1f} mm from the last verified pose) '
                    'passed the acquisition check'), acquired=True)
            hint_reason = f'{hint_reason}local re-acquisition failed ({why}); '
        if not search:
            state = TrackState.LOST if self.state == TrackState.LOST else TrackState.ACQUIRING
            return TrackUpdate(None, state, None, f'{hint_reason}global search deferred to a '
                               'later cloud (search CPU budget spent: the tracked objects keep '
                               'the camera rate)')
        self.acquisitions += 1
        best: Optional[Tuple[np.ndarray, PoseQuality]] = None
        passed: list = []
        for candidate in self.acquirer(self.model, scene.points, s.seed + self.acquisitions,
                                       self._explained()):
            pose, q = self._refine_and_check(scene, np.asarray(candidate, dtype=float), None,
                                             acquisition=True)
            if q.passed:
                passed.append((pose, q))
            elif best is None or q.quality > best[1].quality:
                best = (pose, q)
        state = TrackState.LOST if self.state == TrackState.LOST else TrackState.ACQUIRING
        if not passed:
            why = best[1].reason if best is not None else 'no candidate'
            return TrackUpdate(None, state, best[1] if best else None,
                               f'{hint_reason}acquisition failed: {why}')
        # distinct solutions (not equivalent under the model's symmetries: ADD-S > 5 mm),
        # each searched along the model's axes (a slid part with its end hidden passes too)
        distinct = self._distinct(passed)
        distinct = self._distinct([self.slide_along_axes(scene, pose, q)[:2]
                                   for pose, q in distinct])
        self.places = list(distinct)
        # a twin verified in this cloud already took its place (the penetration check keeps
        # this part out of it): only unverified twins make the acquisition ambiguous
        verified_models = [id(m) for m, _ in self._others]
        open_twins = [t for t in self.twins if id(t.model) not in verified_models]
        twins = [t.known_pose() for t in open_twins if t.known_pose() is not None]
        if open_twins:
            # an identical part elsewhere: only a known pose of this one tells which is which
            if self.reference is None:
                return TrackUpdate(None, state, distinct[0][1], hint_reason + (
                    f'ambiguous: the same shape as {", ".join(t.model.name for t in open_twins)}'
                    '; an initial pose (hint) is needed to tell them apart; not published'))
            assigned = self._assign_among_twins(distinct, twins)
            if assigned is not None:
                pose, q = assigned
                return self._start(stamp_ns, pose, q, hint_reason + (
                    f'acquired ({len(distinct)} places fit the shape of '
                    f'{", ".join([self.model.name] + [t.model.name for t in open_twins])}: '
                    'named by the assignment clearly nearest their known poses)'),
                    acquired=True)
            # clearly nearer its own known pose (or prediction) than any unverified twin's,
            # and near enough to it that the parts cannot have swapped places (radii growing
            # with the age of each known pose: naming.may_name)
            distinct = [d for d in distinct if self._may_name(d[0], stamp_ns)[0]]
            if not distinct:
                return TrackUpdate(None, state, passed[0][1], hint_reason + (
                    'ambiguous: every pose that fits is nearer the known pose of an identical '
                    'part; not published'))
        if len(distinct) == 1 and not open_twins:
            pose, q = distinct[0]
            return self._start(stamp_ns, pose, q, hint_reason + 'acquired', acquired=True)
        # several places fit (or an identical part exists): only a reference (the last
        # verified pose or the hint) may choose, and only when it is clearly nearer one
        if self.reference is not None:
            dist = [mean_displacement(self.model, d[0], self.reference) for d in distinct]
            order = np.argsort(dist)
            if len(distinct) == 1 or dist[order[0]] < 0.5 * dist[order[1]]:
                pose, q = distinct[order[0]]
                return self._start(stamp_ns, pose, q, hint_reason + (
                    f'acquired ({len(distinct)} distinct pose(s) fit; the one nearest the last '
                    'known pose)'), acquired=True)
        # ... or, without an identical part, overlapping places of which one explains clearly
        # more of the scene
        best = None if open_twins else self.best_supported(distinct)
        if best is not None:
            pose, q = best
            others = sorted((d[1].support for d in distinct if d is not best), reverse=True)
            return self._start(stamp_ns, pose, q, hint_reason + (
                f'acquired ({len(distinct)} overlapping places fit; the one the scene supports '
                f'clearly best: {q.support:.0f} samples, next {others[0]:.0f})'), acquired=True)
        gaps = [symmetric_distance(self.model, d[0], distinct[0][0]) for d in distinct[1:]]
        return TrackUpdate(None, state, distinct[0][1], f'{hint_reason}ambiguous: '
                           f'{len(distinct)} distinct poses fit the cloud '
                           f'({1e3 * min(gaps):.0f} mm or more apart) and no known pose tells '
                           'them apart; not published')

    def _explained(self) -> Optional[Tuple[np.ndarray, float]]:
        """
        Return what the identical parts verified in this cloud explain, for the global search.

        Their surface samples (M, 3) [m, scene frame] and ``explained_radius``; None when there
        are none or it is off. Only twins: another object's points would also remove the
        contact region of a part resting on it (the slider carriage on its rail: with the
        rail's points left out, the carriage's search lost the right place and a pose 13 mm off
        was the only one to pass, published where two distinct poses had left it ambiguous).
        """
        r = self.settings.explained_radius
        twins = {id(t.model) for t in self.twins}
        verified = [(m, T) for m, T in self._others if id(m) in twins]
        if r <= 0 or not verified:
            return None
        return np.vstack([m.points @ T[:3, :3].T + T[:3, 3] for m, T in verified]), r

    def _distinct(self, passed: list) -> list:
        """Return the (pose, quality) pairs not equivalent to a better one (ADD-S)."""
        distinct: list = []
        for pose, q in sorted(passed, key=lambda pq: -pq[1].quality):
            if all(symmetric_distance(self.model, pose, d[0]) > self.settings.ambiguity_distance
                   for d in distinct):
                distinct.append((pose, q))
        return distinct

    def best_supported(self, places: list) -> Optional[Tuple[np.ndarray, PoseQuality]]:
        """
        Return the place clearly best supported by the scene among overlapping ones, or None.

        ``places``: (pose, quality) pairs that passed the check. The one with the largest
        :attr:`PoseQuality.support` is returned when it has at least ``min_support_ratio``
        times the support of every other and every other overlaps it (more than 10 % of the
        volume deeper than ``max_penetration`` inside it: the same part cannot be in both);
        None otherwise (a place apart from it may be another part of the same shape).
        """
        s = self.settings
        if s.min_support_ratio <= 0 or len(places) < 2:
            return None
        ranked = sorted(places, key=lambda pq: -pq[1].support)
        best = ranked[0]
        for pose, q in ranked[1:]:
            if best[1].support < s.min_support_ratio * max(q.support, 0.0) or \
                    penetration(self.model, pose, self.model, best[0], s.max_penetration) <= 0.1:
                return None
        return best

    def _assign_among_twins(self, distinct: list, twins: List[np.ndarray]
                            ) -> Optional[Tuple[np.ndarray, PoseQuality]]:
        """
        Name one of several places that fit identical parts by their known poses.

        With one unverified twin whose known pose is ``twins[0]`` and at least two distinct
        places that fit, the places (i, j) for (this part, the twin) minimising the summed mean
        displacement from the two known poses are taken when that sum is less than half of the
        swapped assignment's (j, i): known poses that went stale as the parts moved (a hint of
        frame 0 for a free-running camera) still tell the parts apart while they have not
        swapped places. Return this part's (pose, quality), or None when it does not decide.
        """
        if self.reference is None or len(twins) != 1 or len(distinct) < 2:
            return None
        own = [mean_displacement(self.model, d[0], self.reference) for d in distinct]
        other = [mean_displacement(self.model, d[0], twins[0]) for d in distinct]
        pairs = [(own[i] + other[j], i, j) for i in range(len(distinct))
                 for j in range(len(distinct)) if i != j]
        cost, i, j = min(pairs)
        swapped = own[j] + other[i]
        return distinct[i] if cost < 0.5 * swapped else None

    def _relock_due(self, stamp_ns: int) -> bool:
        """Return whether a lost track is re-acquired locally first in this cloud."""
        return (self.state == TrackState.LOST and self.reference is not None
                and self._lost_ns is not None and self.settings.relock_window > 0
                and 0 <= stamp_ns - self._lost_ns <= self.settings.relock_window * 1e9)

    def expected_poses(self, stamp_ns: int) -> List[Tuple[np.ndarray, Optional[float]]]:
        """
        Return where this part is expected at ``stamp_ns``, with the age of that knowledge.

        ``(pose 4x4, age [s])``: the last verified pose (or, lost, the one before the loss;
        or the hint, age None: unknown) and, from the last two verified poses, the constant-
        velocity prediction (same age). Empty when nothing is known.
        """
        if self.history:
            last_ns, last = self.history[-1]
            motion = tuple(self.history)[-2:] if len(self.history) >= 2 else ()
        elif self.reference is not None:
            last_ns, last, motion = self._reference_ns, self.reference, self._motion
        else:
            return []
        age = None if last_ns is None else max(stamp_ns - last_ns, 0) * 1e-9
        out = [(last, age)]
        if len(motion) == 2:
            out.append((predict_constant_velocity(self.model, motion, stamp_ns), age))
        return out

    def _may_name(self, pose: np.ndarray, stamp_ns: int) -> Tuple[bool, str]:
        """Whether a verified ``pose`` may be named this part (identical twins: naming)."""
        if not self.twins:
            return True, ''
        from object_localizer.naming import may_name
        verified = {id(m) for m, _ in self._others}
        open_twins = [(t.model, t.expected_poses(stamp_ns)) for t in self.twins
                      if id(t.model) not in verified]
        return may_name(self.model, pose, self.expected_poses(stamp_ns), open_twins,
                        self.settings)

    def local_starts(self, stamp_ns: int) -> List[List[np.ndarray]]:
        """
        Return the start poses of the local re-acquisition, in two rings.

        First the motion prediction from the two poses before the loss (if any) and the last
        verified pose; then the first of those shifted by +-``relock_shift`` along each model
        axis and turned by +-``relock_turn`` about each model axis through the model's centre.
        """
        s = self.settings
        first = [T for T, _ in reversed(self.expected_poses(stamp_ns))]
        if not first:
            return []
        base = first[0]
        R, c = base[:3, :3], base[:3, :3] @ self.model.centre + base[:3, 3]
        ring = []
        for k in range(3):
            for sign in (1.0, -1.0):
                T = base.copy()
                T[:3, 3] += sign * s.relock_shift * R[:, k]
                ring.append(T)
                T = np.eye(4)
                T[:3, :3] = R @ rotation_about_axis(np.eye(3)[k], sign * s.relock_turn)
                T[:3, 3] = c - T[:3, :3] @ self.model.centre
                ring.append(T)
        return [first, ring]

    def _relock(self, scene: SceneCloud, stamp_ns: int
                ) -> Tuple[Optional[np.ndarray], Optional[PoseQuality], str]:
        """
        Local re-acquisition: tracking ICP from :meth:`local_starts`, verified.

        Return the best-quality pose of all starts' that pass the acquisition check and may be
        named this part (:meth:`_may_name`), its quality and how it was found; else (None,
        None, why). About 14 ICP + check, 0.2-0.4 s of CPU.
        """
        why, why_name = 'no start pose', ''
        tried = 0
        passing: list = []
        for ring, label in zip(self.local_starts(stamp_ns),
                               ('the predicted / last verified pose refined',
                                'a perturbed start near the prediction refined')):
            for start in ring:
                tried += 1
                pose, q = self._refine_and_check(scene, start, None, acquisition=True)
                if not q.passed:
                    why = q.reason
                    continue
                ok, why_not = self._may_name(pose, stamp_ns)
                if ok:
                    passing.append((pose, q, label))
                else:
                    why_name = why_not
        if passing:
            # every start is tried: the first ring's ICP may stop on the part slid along
            # itself (a brick 5 mm along its length passes the check), which a start beyond
            # it corrects with a better quality
            pose, q, label = max(passing, key=lambda pql: pql[1].quality)
            pose2, q2, slid = self.slide_along_axes(scene, pose, q)
            if slid and self._may_name(pose2, stamp_ns)[0]:
                pose, q, label = pose2, q2, f'{slid}{label}'
            return pose, q, f'{label} (best of {len(passing)} verified, {tried} starts)'
        if why_name:       # a verified place was found but may not carry this name
            return None, None, f'{tried} starts; a place fits but {why_name}'
        return None, None, f'{tried} starts; last: {why}'

    def slide_along_axes(self, scene: SceneCloud, pose: np.ndarray, q: PoseQuality
                         ) -> Tuple[np.ndarray, PoseQuality, str]:
        """:func:`slide_along_axes` with this tracker's model, settings and verified others."""
        return slide_along_axes(self.model, scene, pose, q, self.settings, self._others)

    def known_pose(self) -> Optional[np.ndarray]:
        """Return the last verified pose, else the last known one (hint, pose before a loss)."""
        return self.history[-1][1] if self.history else self.reference

    def withdraw(self, result: TrackUpdate, reason: str) -> TrackUpdate:
        """
        Take back the pose the last :meth:`update` found; return the outcome to report instead.

        For a pose found without a track (acquired, re-locked, a verified hint) that a caller
        rules out afterwards, e.g. because it overlaps a better pose of another object found in
        the same cloud (:func:`withdraw_overlapping`). The track goes back to the state it had
        before that update (``ACQUIRING``, or ``LOST`` for a track that had a pose): no pose,
        no places; the last known pose (``reference``) is kept, so the next cloud searches
        again with it.
        """
        self.history.clear()
        self.places = []
        self.state = TrackState.ACQUIRING if self._state_before == TrackState.ACQUIRING \
            else TrackState.LOST
        return TrackUpdate(None, self.state, result.quality, f'{result.reason}; {reason}',
                           cpu_seconds=result.cpu_seconds, lost=result.lost)

    def _start(self, stamp_ns: int, pose: np.ndarray, q: PoseQuality, reason: str,
               acquired: bool = False) -> TrackUpdate:
        self.history.clear()
        pose = self._equivalent_near_reference(pose)
        self._static_samples = [pose] if self.settings.static else []
        if (acquired and self._reference_ns is not None and 0 < stamp_ns - self._reference_ns
                <= self.settings.motion_memory * 1e9):
            earlier = carried_motion(self.model, self._motion, pose, stamp_ns)
            if earlier is not None:     # re-acquired after a loss: the velocity before it
                self.history.append(earlier)
        self._accept(stamp_ns, pose)
        self.state = TrackState.STATIC if self.settings.static else TrackState.TRACKING
        self._last_check_ns = stamp_ns
        return TrackUpdate(pose, self.state, q, reason, acquired=acquired)

    def _static_mean(self, scene: SceneCloud, refined: np.ndarray, q_refined: PoseQuality,
                     held: np.ndarray) -> Tuple[np.ndarray, PoseQuality, str]:
        """
        Return the mean of a static object's verified re-check poses, or ``refined``.

        ``refined`` (verified) joins the samples (restarting them when it is more than
        ``static_average_gate`` from their mean); their mean (translation; rotation: the
        nearest rotation to the sum of the matrices) is checked and returned when it passes,
        else ``refined``.
        """
        s = self.settings
        samples = self._static_samples
        if samples and mean_displacement(self.model, refined, held) > s.static_average_gate:
            samples.clear()
        samples.append(refined)
        del samples[:-s.static_average]
        if len(samples) < 2:
            return refined, q_refined, 'static: re-checked (refined)'
        stack = np.array(samples)
        mean = np.eye(4)
        mean[:3, :3] = nearest_rotation(stack[:, :3, :3].sum(axis=0))
        mean[:3, 3] = stack[:, :3, 3].mean(axis=0)
        pose, q = self._refine_and_check(scene, mean, held, refine=False)
        if not q.passed:
            return refined, q_refined, 'static: re-checked (refined; the mean failed the check)'
        return pose, q, f'static: re-checked (mean of {len(samples)} refined poses)'

    def _equivalent_near_reference(self, pose: np.ndarray) -> np.ndarray:
        """
        Return the pose equivalent to ``pose`` (model symmetries) nearest ``reference``.

        A search cannot tell a symmetric part's equivalent poses apart (the square peg upside
        down); the published frame keeps the orientation of the initial pose or of the pose
        before the loss (:func:`object_localizer.symmetry.nearest_equivalent_pose`). The
        symmetries turn by at least 45 deg (``find_symmetries`` looks for 2- to 8-fold
        turns): a pose within 22 deg of the reference is its own nearest equivalent and the
        symmetries are not looked for.
        """
        if self.reference is None:
            return pose
        if rotation_angle(self.reference[:3, :3].T @ pose[:3, :3]) < np.radians(22.0):
            return pose
        rotations, centre = self.model.discrete_symmetries()
        return nearest_equivalent_pose(pose, self.reference, rotations, centre)

    def _lose(self, q: PoseQuality, reason: str, stamp_ns: int) -> TrackUpdate:
        self.lost_count += 1
        self._lost_ns = stamp_ns
        if self.history:
            self.reference = self.history[-1][1]
            self._reference_ns = self.history[-1][0]
            self._motion = tuple(self.history)[-2:] if len(self.history) >= 2 else ()
        self.history.clear()
        self.state = TrackState.LOST
        return TrackUpdate(None, TrackState.LOST, q, reason, lost=True)


def withdraw_overlapping(found: Sequence[Tuple[ObjectTracker, TrackUpdate]],
                         verified: Sequence[Tuple[TrackingModel, np.ndarray]] = (),
                         max_share: float = 0.1) -> List[TrackUpdate]:
    """
    Withdraw the poses found in one cloud that overlap a better one.

    Withdraw, among the poses several trackers found in one cloud without a track (global
    searches, re-locks, verified hints: each checked against the poses verified before it,
    in the order searched), those whose volume overlaps (:func:`overlap` > ``max_share``, at
    each tracker's ``max_penetration`` depth) a pose of ``verified`` (tracked in this cloud)
    or a better pose found (higher ``quality``): two parts cannot be in one place. Each
    search's own check only sees the poses before it, one way (the share of the new part
    inside them): a wrong pose found first (ball_link sunk into socket_base, quality 0.28,
    half its volume inside the socket) did not stop the right pose found after it (the
    socket's share inside the ball link 6 %), and both were published.

    :param found: (tracker, its outcome of this cloud) pairs; outcomes without a pose are
        returned as they are.
    :param verified: (model, pose) of the objects tracked in this cloud (not withdrawn).
    :return: the outcomes in the order of ``found``, withdrawn ones replaced by
        :meth:`ObjectTracker.withdraw`'s.
    """
    out = [result for _, result in found]
    kept: List[Tuple[TrackingModel, np.ndarray, Optional[float]]] = \
        [(m, pose, None) for m, pose in verified]
    ranked = sorted((i for i, (_, r) in enumerate(found) if r.pose is not None),
                    key=lambda i: -(found[i][1].quality.quality if found[i][1].quality
                                    else 0.0))
    for i in ranked:
        tracker, result = found[i]
        depth = tracker.settings.max_penetration
        shares = [(overlap(tracker.model, result.pose, m, pose, depth), m, q)
                  for m, pose, q in kept]
        worst = max(shares, key=lambda smq: smq[0], default=None)
        if worst is not None and worst[0] > max_share:
            share, other, q = worst
            by = 'tracked in this cloud' if q is None else f'found in this cloud, quality ' \
                f'{q:.2f}'
            out[i] = tracker.withdraw(result, (
                f'withdrawn: {100 * share:.0f} % of the volume overlaps {other.name} '
                f'({by}) by more than {1e3 * depth:.0f} mm; not published'))
            continue
        kept.append((tracker.model, result.pose,
                     result.quality.quality if result.quality else 0.0))
    return out
