"""
Pose-hypothesis verification by the visible surface (pure core, no ROS).

A pose hypothesis is checked the way the camera would check it: the model's surface is rendered
into a depth image with the camera intrinsics (z-buffered splats of dense surface samples, so
self-occlusion is handled) and compared pixel by pixel with the observed depth of the scene.
Every model pixel is one of

* **inlier**: observed depth within ``inlier_threshold`` of the model depth;
* **violation** (free-space violation): the camera sees *behind* the model surface there
  (observed depth > model depth + threshold) -- the ray passes through where the model claims
  a surface, so the hypothesis is physically wrong at that pixel. On the model's silhouette
  (a pixel with a 4-neighbour off the model) such a pixel counts as unknown instead: stereo
  matching fattens and thins silhouettes by about half its window;
* **occluded**: something observed in front of the model (observed < model - threshold): the
  model may be hidden there, neither evidence for nor against it;
* **unknown**: no observed depth at that pixel, or (stereo camera: ``PinholeCamera.baseline``
  given) a model surface stereo cannot measure there -- hidden from the right camera by the
  model itself or by an observed surface, or too slanted for window matching
  (:data:`STEREO_MAX_DISPARITY_GRADIENT`): block matching gives such pixels the disparity of
  the background, which would otherwise read as a free-space violation.

The score is ``(inliers - violation_weight * violations) / max(inliers + violations,
min_support * model_pixels)`` clipped to [0, 1]: a pose explaining all of the visible surface
with nothing seen through it scores 1; violations lower it; occluded and unknown pixels are no
evidence either way, but with the default ``min_support`` 1 they still dilute the score (a
hypothesis mostly hidden has little support). This is the visibility reasoning of hypothesis
verification in the PPF literature (e.g. Vidal et al. 2018, Hinterstoisser et al. 2016) and of
depth-based tracking quality measures.

Frames and units: poses 4x4 model -> camera optical frame (z forward, x right, y down);
metres; pixels with integer centres. Images are coarsened by an integer ``stride`` (a
``stride``-times smaller camera) so a score costs well under a millisecond per hypothesis.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Mapping, Optional, Tuple, Union

import numba
import numpy as np

__all__ = [
    'PinholeCamera',
    'ObservedDepth',
    'SurfaceSamples',
    'VisibilityScore',
    'as_camera',
    'interior_hole_rate',
    'virtual_camera',
    'observe_depth',
    'render_model_depth',
    'sample_model_surface',
    'score_pose_visibility',
    'silhouette_edges',
    'unoccluded_mask',
]

#: Default ``min_support`` of :func:`score_pose_visibility`.
MIN_SUPPORT = 1.0
#: Largest share of single-pixel holes (empty pixels whose four neighbours are observed, per
#: observed pixel) an observed depth image may have; a cloud whose points are not on the
#: camera's pixel grid (an unorganised cloud, points scattered at random over the surfaces)
#: leaves holes by chance (Poisson: e^-2.25 = 11 % of the pixels at 2.25 points per pixel), which
#: would read as unobserved surface and lower the score of a right pose. The images of
#: :func:`observe_depth` and of the tracker's check are coarsened until they have fewer.
MAX_HOLE_RATE = 0.01
#: Largest disparity gradient (1 - ratio of a surface element's image areas in the right and
#: left cameras) at which window-based stereo matching is taken to measure a surface; the
#: disparity-gradient limit of stereo matching (Burt & Julesz 1980: 1 for human vision;
#: fixed-window block matching assumes near fronto-parallel surfaces).
STEREO_MAX_DISPARITY_GRADIENT = 0.4


@dataclass(frozen=True)
class PinholeCamera:
    """
    A pinhole camera at the origin of the optical frame.

    :ivar fx: focal lengths [px].
    :ivar cx: principal point [px] (pixel centres at integer coordinates).
    :ivar width: image size [px].
    :ivar baseline: stereo baseline [m] when the depth comes from a rectified stereo pair
        whose second (right) camera, with the same intrinsics, sits at (+baseline, 0, 0) of
        this optical frame; 0 = unknown / not stereo (no stereo-visibility reasoning).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    baseline: float = 0.0

    def scaled(self, stride: float) -> 'PinholeCamera':
        """
        Return the same camera with ``stride``-times fewer pixels per axis.

        The same camera with ``stride``-times fewer pixels per axis (pixel (u, v) of the
        result covers pixels ``stride*u .. stride*u + stride - 1`` of this one).
        """
        s = float(stride)
        return PinholeCamera(self.fx / s, self.fy / s, (self.cx + 0.5) / s - 0.5,
                             (self.cy + 0.5) / s - 0.5, int(np.ceil(self.width / s)),
                             int(np.ceil(self.height / s)), self.baseline)


CameraLike = Union[PinholeCamera, Mapping[str, Any], None]


def as_camera(camera: CameraLike) -> Optional[PinholeCamera]:
    """
    Make a :class:`PinholeCamera` of what describes one.

    A :class:`PinholeCamera` from one, from a mapping with ``fx fy cx cy width height``
    and optionally ``baseline`` [m] (e.g. the synthetic camera's ``truth['camera']``), or
    ``None``.

    :raises ValueError: a mapping lacks a key or has non-positive sizes/focal lengths or a
        negative baseline.
    """
    if camera is None or isinstance(camera, PinholeCamera):
        return camera
    try:
        cam = PinholeCamera(float(camera['fx']), float(camera['fy']), float(camera['cx']),
                            float(camera['cy']), int(camera['width']), int(camera['height']),
                            float(camera.get('baseline', 0.0)))
    except KeyError as exc:
        raise ValueError(f'camera mapping lacks {exc}; needs fx, fy, cx, cy, width, height') \
            from None
    if not (cam.fx > 0 and cam.fy > 0 and cam.width > 0 and cam.height > 0
            and cam.baseline >= 0):
        raise ValueError(f'camera needs positive focal lengths and size, got {cam}')
    return cam


def virtual_camera(points: np.ndarray, pixel_size: float = 0.002) -> PinholeCamera:
    """
    Make a pinhole camera at the origin that sees every point of ``points``.

    A pinhole camera at the origin that sees every point of ``points`` (N, 3) [m] with
    ``pixel_size`` [m] pixels at their median depth: visibility reasoning for clouds that come
    without intrinsics (any pinhole at the sensor centre gives the same visibility).

    :raises ValueError: no point in front of the origin.
    """
    P = np.asarray(points, dtype=float)
    P = P[np.all(np.isfinite(P), axis=1) & (P[:, 2] > 1e-6)] if len(P) else P
    if len(P) == 0:
        raise ValueError('virtual_camera: no finite point in front of the sensor (z > 0)')
    f = float(np.median(P[:, 2])) / pixel_size
    u = P[:, 0] / P[:, 2]
    v = P[:, 1] / P[:, 2]
    u0, u1, v0, v1 = u.min(), u.max(), v.min(), v.max()
    width = int(np.ceil((u1 - u0) * f)) + 3
    height = int(np.ceil((v1 - v0) * f)) + 3
    if width * height > 4_000_000:
        raise ValueError(f'virtual_camera: field of view too wide for {pixel_size} m pixels')
    return PinholeCamera(f, f, -u0 * f + 1.0, -v0 * f + 1.0, width, height)


@numba.njit(cache=True)
def _interior_holes(depth):  # pragma: no cover - numba
    holes = 0
    seen = 0
    H, W = depth.shape
    for y in range(H):
        for x in range(W):
            if np.isfinite(depth[y, x]):
                seen += 1
            elif 0 < y < H - 1 and 0 < x < W - 1 and np.isfinite(depth[y - 1, x]) \
                    and np.isfinite(depth[y + 1, x]) and np.isfinite(depth[y, x - 1]) \
                    and np.isfinite(depth[y, x + 1]):
                holes += 1
    return holes, seen


def interior_hole_rate(depth: np.ndarray) -> float:
    """
    Return the single-pixel holes of a depth image per observed pixel.

    A hole is an empty pixel (NaN or inf) whose four neighbours all hold a depth. A cloud on
    the camera's pixel grid rendered at a pixel coarser than its spacing has none (beyond the
    sensor's own isolated drop-outs); points scattered at random leave about
    ``exp(-points per pixel)`` of the pixels empty, most of them inside observed surfaces.

    :param depth: (H, W) depth image [m], non-finite = nothing observed.
    :return: holes / observed pixels (0 when nothing is observed).
    """
    holes, seen = _interior_holes(np.asarray(depth, dtype=np.float64))
    return float(holes) / seen if seen else 0.0


@dataclass
class SurfaceSamples:
    """
    Dense samples of a model's surface for rendering it (model frame).

    :ivar points: (N, 3) surface points [m].
    :ivar normals: (N, 3) outward unit normals.
    :ivar spacing: typical distance between neighbouring samples [m].
    """

    points: np.ndarray
    normals: np.ndarray
    spacing: float


def sample_model_surface(mesh: Any, spacing: float = 0.0015,
                         max_samples: int = 30000, seed: int = 0) -> SurfaceSamples:
    """
    Sample the surface of a polygon mesh near-uniformly, with face normals.

    Near-uniform surface samples of a :class:`~stereo_manip_tools.mesh_io.PolygonMesh` about
    ``spacing`` [m] apart (coarser if that would exceed ``max_samples``), with face normals.

    :raises ValueError: spacing <= 0 or a mesh without area.
    """
    import open3d as o3d
    if not spacing > 0:
        raise ValueError(f'spacing must be > 0, got {spacing}')
    tm = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(mesh.vertices),
                                   o3d.utility.Vector3iVector(mesh.triangles()))
    area = float(tm.get_surface_area())
    if not area > 0:
        raise ValueError(f'mesh {getattr(mesh, "name", "?")} has no surface area')
    spacing = max(float(spacing), float(np.sqrt(area / max_samples)))
    tm.compute_triangle_normals()
    o3d.utility.random.seed(int(seed))
    pcd = tm.sample_points_uniformly(number_of_points=int(3.0 * area / spacing ** 2),
                                     use_triangle_normal=True).voxel_down_sample(spacing)
    normals = np.asarray(pcd.normals)
    normals = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    return SurfaceSamples(np.asarray(pcd.points).copy(), normals, spacing)


@dataclass
class ObservedDepth:
    """
    The observed depth image [m] (NaN = nothing observed) of a scene, on ``camera``.

    :ivar right: for a stereo camera (``camera.baseline`` > 0), the same scene points seen from
        the right camera: depth [m] on the right camera's (coarsened) pixels, NaN = none; a
        model point hidden there behind an observed surface cannot be matched by stereo.
        None otherwise.
    """

    depth: np.ndarray
    camera: PinholeCamera
    right: Optional[np.ndarray] = None


@dataclass
class VisibilityScore:
    """
    Outcome of :func:`score_pose_visibility`.

    :ivar score: ``(inliers - violation_weight * violations) / model_pixels`` in [0, 1].
    :ivar inlier_fraction: inliers / model pixels.
    :ivar violation_fraction: free-space violations / model pixels.
    :ivar occluded_fraction: pixels where the scene is in front of the model / model pixels.
    :ivar unknown_fraction: model pixels without observed depth / model pixels.
    :ivar visible_residual: RMS of observed - model depth over the inliers [m] (NaN if none).
    :ivar model_pixels: pixels the model covers in the (coarsened) image.
    :ivar edge_fraction: share of the model's silhouette (not occluded) where the observed
        depth two (coarse) pixels outside jumps behind the model by more than
        ``edge_threshold`` or is
        missing -- the depth edge a real object makes. A pose that sinks the model into a
        larger surface (a box face inside a table top) has a visible surface full of inliers
        but no edges: edge_fraction near 0. Objects resting on a support keep the edges of
        their contact side continuous, so real poses score about 0.4-0.9. NaN if no
        silhouette pixel could be judged.
    """

    score: float
    inlier_fraction: float
    violation_fraction: float
    occluded_fraction: float
    unknown_fraction: float
    visible_residual: float
    model_pixels: int
    edge_fraction: float = float('nan')

    @property
    def combined(self) -> float:
        """
        ``score * min(1, edge_fraction / 0.6)`` (a factor 0.625 when the edges are unknown).

        The ranking score of pose hypotheses in acquisition. The edge support saturates at
        0.5: an object resting on a support keeps the edges of its free sides only (about half
        its outline, measured 0.44-0.95 on right poses), so more edge is no better evidence,
        while a pose sunk into a larger surface (edge fraction near 0) is pushed down. A
        linear weight let a wrong pose with all its outline on depth edges outrank the right
        one: the slot block of ``peg_in_slot`` turned 90 deg onto its side (visible-surface
        score 0.55, edges 0.96) beat the truth (0.75, edges 0.51) in 4 of 14 trials.
        """
        e = 0.375 if not np.isfinite(self.edge_fraction) else self.edge_fraction
        return self.score * min(1.0, e / 0.6)


@numba.njit(cache=True)
def _zbuffer(P, fx, fy, cx, cy, width, height, radius):  # pragma: no cover - numba
    depth = np.full((height, width), np.inf)
    for i in range(P.shape[0]):
        z = P[i, 2]
        if not (z > 1e-6):
            continue
        u = fx * P[i, 0] / z + cx
        v = fy * P[i, 1] / z + cy
        ui = int(np.floor(u + 0.5))
        vi = int(np.floor(v + 0.5))
        for dv in range(-radius, radius + 1):
            y = vi + dv
            if y < 0 or y >= height:
                continue
            for du in range(-radius, radius + 1):
                x = ui + du
                if x < 0 or x >= width:
                    continue
                if z < depth[y, x]:
                    depth[y, x] = z
    return depth


def observe_depth(scene_points: np.ndarray, camera: CameraLike = None, *, stride: int = 4,
                  pixel_size: float = 0.002, stereo_baseline: float = 0.0,
                  max_hole_rate: float = MAX_HOLE_RATE) -> ObservedDepth:
    """
    Render the depth image observed in a scene cloud (see :func:`score_pose_visibility`).

    The image is coarsened further (stride x 1.25, up to three times) while more than
    ``max_hole_rate`` of its observed pixels have single-pixel holes next to them
    (:func:`interior_hole_rate`): an unorganised cloud, whose points do not fall on the camera's
    pixel grid, then gets an image as free of chance holes as an organised one, so a right
    pose scores the same on both (the holes would read as unobserved surface). Organised
    camera clouds keep ``stride``.

    :param scene_points: the scene [m, optical frame]: (N, 3), or an organised (H, W, 3) cloud
        (NaN = no measurement); non-finite points are ignored.
    :param camera: the camera that produced the cloud (:func:`as_camera` forms); ``None`` builds
        :func:`virtual_camera` over the points (``pixel_size`` [m] at their median depth).
    :param stride: coarsening of the camera image (nearest observed depth per coarse pixel).
    :param stereo_baseline: the stereo baseline [m] (second camera at +x of the optical frame)
        when ``camera`` is None or carries none (0: not stereo): the virtual camera sits at the
        origin of the optical frame with its axes, so the stereo visibility reasoning of
        :func:`score_pose_visibility` holds for it too.
    :param max_hole_rate: see above (``inf``: keep ``stride``).
    :raises ValueError: wrong shape, no finite point, stride < 1, negative baseline.
    """
    if stride < 1:
        raise ValueError(f'stride must be >= 1, got {stride}')
    if not stereo_baseline >= 0:
        raise ValueError(f'stereo_baseline must be >= 0, got {stereo_baseline}')
    P = np.asarray(scene_points, dtype=float)
    if P.ndim == 3 and P.shape[2] == 3:
        P = P.reshape(-1, 3)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f'scene points must have shape (N, 3) or (H, W, 3), got {P.shape}')
    P = P[np.all(np.isfinite(P), axis=1)]
    if len(P) == 0:
        raise ValueError('observe_depth: the scene has no finite point')
    base = as_camera(camera)
    if base is not None and base.baseline == 0 and stereo_baseline > 0:
        base = replace(base, baseline=float(stereo_baseline))
    scale = float(stride)
    for attempt in range(4):
        if base is None:
            cam = replace(virtual_camera(P, pixel_size * scale), baseline=float(stereo_baseline))
        else:
            cam = base.scaled(scale)
        depth = _zbuffer(P, cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height, 0)
        if attempt == 3 or interior_hole_rate(depth) <= max_hole_rate:
            break
        scale *= 1.25
    depth[~np.isfinite(depth)] = np.nan
    right = None
    if cam.baseline > 0:
        right = _zbuffer(P - np.array([cam.baseline, 0.0, 0.0]), cam.fx, cam.fy, cam.cx, cam.cy,
                         cam.width, cam.height, 0)
        right[~np.isfinite(right)] = np.nan
    return ObservedDepth(depth, cam, right)


def render_model_depth(surface_points: np.ndarray, surface_normals: np.ndarray,
                       pose: np.ndarray, camera: PinholeCamera,
                       spacing: float) -> np.ndarray:
    """
    Depth image [m] (NaN = model absent) of a model at ``pose`` on ``camera``.

    Z-buffered splats of the surface samples that face the camera; each splat covers the
    pixels within the sample spacing so the rendered surface has no holes.

    :param surface_points: (N, 3) dense surface samples in the model frame [m].
    :param surface_normals: (N, 3) their outward unit normals.
    :param pose: 4x4 model -> optical frame.
    :param spacing: the samples' spacing [m].
    """
    return _render(surface_points, surface_normals, pose, camera, spacing)[0]


def _render(surface_points: np.ndarray, surface_normals: np.ndarray, pose: np.ndarray,
            camera: PinholeCamera, spacing: float, right: Optional[np.ndarray] = None,
            tolerance: float = 0.0) -> Tuple[np.ndarray, np.ndarray]:
    """
    Render the model depth and whether stereo can measure each model pixel.

    :func:`render_model_depth` plus a (H, W) uint8 image, 1 where the model's front surface is
    measurable by stereo: always when ``right`` (the observed depth seen from the right camera,
    :class:`ObservedDepth`) is None; else the front sample must also face the right camera
    (``camera.baseline`` along +x), not be hidden there behind an observed surface by more
    than ``tolerance`` [m], and not be so slanted that its images differ in size by more than
    :data:`STEREO_MAX_DISPARITY_GRADIENT` (window matching assumes a surface about parallel to
    the image). A surface the left camera sees but stereo cannot match (a side face turned
    away from the right camera or seen edge-on by it, a part hidden from it by the rim of a
    hole) gets the disparity of the background from block matching: measured, the peg's side
    face at 69 / 80 deg incidence (left / right camera) read 19 % of the true peg's pixels
    as free-space violations.
    """
    R = np.ascontiguousarray(pose[:3, :3], dtype=np.float64)
    t = np.ascontiguousarray(pose[:3, 3], dtype=np.float64)
    stereo = right is not None
    return _render_kernel(np.ascontiguousarray(surface_points, dtype=np.float64),
                          np.ascontiguousarray(surface_normals, dtype=np.float64), R, t,
                          camera.fx, camera.fy, camera.cx, camera.cy, camera.width,
                          camera.height, float(spacing), stereo, float(camera.baseline),
                          right if stereo else np.zeros((1, 1)), float(tolerance),
                          STEREO_MAX_DISPARITY_GRADIENT)


@numba.njit(cache=True)
def _render_kernel(Pm, Nm, R, t, fx, fy, cx, cy, width, height, spacing, stereo, baseline,
                   right, tolerance, max_gradient):  # pragma: no cover - numba
    n = Pm.shape[0]
    P = np.empty((n, 3))
    F = np.zeros(n, np.uint8)
    keep = np.zeros(n, np.bool_)
    z_min = np.inf
    for i in range(n):
        for a in range(3):
            P[i, a] = R[a, 0] * Pm[i, 0] + R[a, 1] * Pm[i, 1] + R[a, 2] * Pm[i, 2] + t[a]
        n0 = R[0, 0] * Nm[i, 0] + R[0, 1] * Nm[i, 1] + R[0, 2] * Nm[i, 2]
        n1 = R[1, 0] * Nm[i, 0] + R[1, 1] * Nm[i, 1] + R[1, 2] * Nm[i, 2]
        n2 = R[2, 0] * Nm[i, 0] + R[2, 1] * Nm[i, 1] + R[2, 2] * Nm[i, 2]
        if n0 * P[i, 0] + n1 * P[i, 1] + n2 * P[i, 2] >= 0:
            continue                         # faces away from the camera
        keep[i] = True
        if P[i, 2] < z_min:
            z_min = P[i, 2]
        if not stereo:
            F[i] = 1
            continue
        x = P[i, 0] - baseline
        z = P[i, 2]
        dot_r = n0 * x + n1 * P[i, 1] + n2 * z
        if dot_r >= 0 or not (z > 1e-6):
            continue                         # faces away from the right camera
        # image area of a surface element in the right camera over that in the left one
        # (cos / distance^2): 1 - the disparity gradient along the surface
        dot_l = n0 * P[i, 0] + n1 * P[i, 1] + n2 * P[i, 2]
        r2 = x * x + P[i, 1] * P[i, 1] + z * z
        l2 = P[i, 0] * P[i, 0] + P[i, 1] * P[i, 1] + z * z
        ratio = (dot_r / (r2 * np.sqrt(r2))) / (dot_l / (l2 * np.sqrt(l2)))
        if ratio < 1.0 - max_gradient or ratio * (1.0 - max_gradient) > 1.0:
            continue                         # too slanted for window matching
        u = np.floor(fx * x / z + cx + 0.5)
        v = np.floor(fy * P[i, 1] / z + cy + 0.5)
        if u < 0 or u >= width or v < 0 or v >= height:
            continue
        d = right[int(v), int(u)]
        if d < z - tolerance:
            continue                         # hidden behind an observed surface (NaN: not)
        F[i] = 1
    depth = np.full((height, width), np.inf)
    flag = np.zeros((height, width), np.uint8)
    if not np.isfinite(z_min):
        return np.full((height, width), np.nan), flag
    radius = int(min(3.0, np.floor(0.5 * spacing * fx / max(z_min, 1e-3))))
    for i in range(n):
        if not keep[i]:
            continue
        z = P[i, 2]
        if not (z > 1e-6):
            continue
        ui = int(np.floor(fx * P[i, 0] / z + cx + 0.5))
        vi = int(np.floor(fy * P[i, 1] / z + cy + 0.5))
        for dv in range(-radius, radius + 1):
            y = vi + dv
            if y < 0 or y >= height:
                continue
            for du in range(-radius, radius + 1):
                xx = ui + du
                if xx < 0 or xx >= width:
                    continue
                if z < depth[y, xx]:
                    depth[y, xx] = z
                    flag[y, xx] = F[i]
    for y in range(height):
        for xx in range(width):
            if not np.isfinite(depth[y, xx]):
                depth[y, xx] = np.nan
    return depth, flag


@numba.njit(cache=True)
def _compare(model, measurable, observed, thr):  # pragma: no cover - numba
    n = 0
    inl = 0
    vio = 0
    occ = 0
    unk = 0
    ss = 0.0
    H, W = model.shape
    for y in range(H):
        for x in range(W):
            m = model[y, x]
            if not np.isfinite(m):
                continue
            n += 1
            o = observed[y, x]
            border = False
            if y == 0 or y == H - 1 or x == 0 or x == W - 1:
                border = True
            elif not (np.isfinite(model[y - 1, x]) and np.isfinite(model[y + 1, x])
                      and np.isfinite(model[y, x - 1]) and np.isfinite(model[y, x + 1])):
                border = True
            if not np.isfinite(o):
                unk += 1
            elif o > m + thr:
                if border or measurable[y, x] == 0:
                    # stereo fattens/thins silhouettes, and cannot match a surface the
                    # second camera does not see: no evidence there
                    unk += 1
                else:
                    vio += 1
            elif o < m - thr:
                occ += 1
            else:
                inl += 1
                ss += (o - m) * (o - m)
    return n, inl, vio, occ, unk, ss


@numba.njit(cache=True)
def _edges(model, observed, thr, gap):  # pragma: no cover - numba
    sup = 0
    cont = 0
    H, W = model.shape
    for y in range(H):
        for x in range(W):
            m = model[y, x]
            if not np.isfinite(m):
                continue
            for k in range(4):
                dy = gap if k == 0 else (-gap if k == 1 else 0)
                dx = gap if k == 2 else (-gap if k == 3 else 0)
                yy = y + dy
                xx = x + dx
                if yy < 0 or yy >= H or xx < 0 or xx >= W:
                    continue
                if np.isfinite(model[yy, xx]):
                    continue
                # (y, x) is on the silhouette, (yy, xx) just outside it
                o = observed[yy, xx]
                if not np.isfinite(o) or o > m + thr:
                    sup += 1
                elif o >= m - thr:
                    cont += 1
    return sup, cont


def silhouette_edges(model_depth: np.ndarray, observed_depth: np.ndarray, threshold: float,
                     gap: int = 2) -> Tuple[int, int]:
    """
    Count depth-edge evidence along a rendered model's silhouette.

    Depth-edge evidence along a rendered model's silhouette: the check that the model is an
    object of its own and not a piece of a larger observed surface.

    For every model pixel with a 4-neighbour ``gap`` pixels away that is off the model, the
    observed depth at that outside pixel is

    * **supported** (an edge): missing, or behind the model's depth there by more than
      ``threshold`` -- the depth discontinuity an object's silhouette makes;
    * **continuous**: within ``threshold`` of the model's depth -- the observed surface goes on
      past the silhouette as if the model were painted onto it (a model sunk into a table,
      a wall, or a larger part);
    * neither: in front of the model (an occluder hides the silhouette).

    Shared by :func:`score_pose_visibility` (``edge_fraction``, acquisition ranking) and
    ``object_localizer.tracking.check_pose`` (acceptance of every published pose).

    :param model_depth: (H, W) rendered model depth [m], NaN off the model; interior holes
        must be filled (a hole reads as silhouette).
    :param observed_depth: (H, W) observed depth [m] on the same pixels, NaN = nothing seen.
    :param threshold: depth jump [m] that counts as an edge.
    :param gap: distance [px] of the outside pixel (stereo matching fattens silhouettes by
        about half its window: the pixel right next to the silhouette is unreliable).
    :return: (supported, continuous) silhouette-pixel/direction counts.
    """
    sup, cont = _edges(np.asarray(model_depth, dtype=float),
                       np.asarray(observed_depth, dtype=float), float(threshold), int(gap))
    return int(sup), int(cont)


def score_pose_visibility(surface: SurfaceSamples, pose: np.ndarray, observed: ObservedDepth,
                          *, inlier_threshold: float = 0.004,
                          violation_weight: float = 1.0,
                          edge_threshold: float = 0.01,
                          min_support: float = MIN_SUPPORT) -> VisibilityScore:
    """
    Visible-surface score of a pose hypothesis against the observed depth (module doc).

    :param surface: dense model-surface samples (:func:`sample_model_surface`; an
        :class:`~object_localizer.acquisition.AcquisitionModel` carries them as ``surface``).
    :param pose: 4x4 model -> optical frame.
    :param observed: :func:`observe_depth` of the scene (build it once per cloud).
    :param inlier_threshold: |observed - model| depth tolerance [m] of an inlier pixel.
    :param violation_weight: weight of a free-space violation against an inlier.
    :param edge_threshold: depth jump [m] that counts as a silhouette edge.
    :param min_support: the score's denominator is the model pixels with evidence (inliers +
        violations) but at least this share of all model pixels: occluded and unknown pixels
        are no evidence against a pose, but a pose whose surface is mostly unseen keeps little
        support (1.0: every model pixel counts, occluded or not).
    """
    pose = np.asarray(pose, dtype=float)
    if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
        raise ValueError(f'pose must be a finite 4x4 transform, got shape {pose.shape}')
    if not 0.0 < min_support <= 1.0:
        raise ValueError(f'min_support must be in (0, 1], got {min_support}')
    model, measurable = _render(surface.points, surface.normals, pose, observed.camera,
                                surface.spacing, observed.right, float(inlier_threshold))
    n, inl, vio, occ, unk, ss = _compare(model, measurable, observed.depth,
                                         float(inlier_threshold))
    if n == 0:
        return VisibilityScore(0.0, 0.0, 0.0, 0.0, 0.0, float('nan'), 0)
    score = (inl - violation_weight * vio) / max(inl + vio, min_support * n)
    sup, cont = silhouette_edges(model, observed.depth, edge_threshold, 2)
    edge = sup / (sup + cont) if sup + cont else float('nan')
    return VisibilityScore(float(min(1.0, max(0.0, score))), inl / n, vio / n, occ / n,
                           unk / n, float(np.sqrt(ss / inl)) if inl else float('nan'), int(n),
                           float(edge))


def unoccluded_mask(points: np.ndarray, normals: np.ndarray, observed: ObservedDepth,
                    tolerance: float) -> np.ndarray:
    """
    Mask (N,) of model points [m, optical frame] the camera can see.

    Normal facing the sensor, and at their pixel the observed depth is not in front of them by more
    than ``tolerance`` [m] (not hidden behind another object) and is known.

    ICP restricted to these points is not pulled by the surfaces of an occluder.
    """
    P = np.asarray(points, dtype=float)
    facing = np.einsum('ij,ij->i', normals, P) < 0
    cam = observed.camera
    z = P[:, 2]
    ok = facing & (z > 1e-6)
    u = np.full(len(P), -1)
    v = np.full(len(P), -1)
    u[ok] = np.floor(cam.fx * P[ok, 0] / z[ok] + cam.cx + 0.5).astype(int)
    v[ok] = np.floor(cam.fy * P[ok, 1] / z[ok] + cam.cy + 0.5).astype(int)
    ok &= (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
    d = np.full(len(P), np.nan)
    d[ok] = observed.depth[v[ok], u[ok]]
    return ok & np.isfinite(d) & (d >= z - tolerance)
