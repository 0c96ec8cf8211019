"""
Ray-cast stereo renderer with exact ground truth (CPU, headless).

Both views are cast from their own optical centre (no warping), so occlusions are real. A ray
through pixel (u, v) has direction ((u - cx)/fx, (v - cy)/fy, 1): its hit parameter is the depth
Z [m] directly. The ray/triangle intersections are computed exactly in float64 by the numba
kernels of :mod:`stereo_depth.synthetic.raster`, which visit only the pixels in each triangle's
bounding box (the same result as casting every ray through Open3D's ``RaycastingScene``, which
the tests check, at a fraction of the cost). Surfaces carry the object-fixed procedural texture of
:mod:`stereo_depth.synthetic.texture`, shaded by a Lambertian directional light fixed in the left
optical frame (view independent, so corresponding points have the same intensity in both views
up to the optional photometric gain, blur and noise).

Ground truth of one pair (``truth`` dict; arrays (H, W) unless stated, left view unless the key
ends in ``_right``):

* ``depth`` / ``depth_right``: Z [m] in each camera's optical frame, float32, NaN background.
* ``disparity``: ``fx B / depth`` [px], float32, NaN background (x_right = x_left - d).
* ``occlusion``: bool, True for foreground left pixels whose surface point is not visible from
  the right camera (hidden by a surface the right image sees at the pixels bracketing the
  projection, on a face turned away from the right camera, or left of the right image; see
  :func:`stereo_depth.synthetic.raster.occlusion_mask`). Background pixels are False (use
  ``valid``).
* ``valid``: bool, foreground (a surface was hit) in the left view.
* ``object_id`` / ``object_id_right``: int16 index into ``object_names``, -1 background.
* ``face_id`` / ``face_id_right``: int32 polygon face of that object's model (OBJ face order), -1.
* ``texcoords`` / ``texcoords_right``: (H, W, 2) float32 texture chart coordinates [texels] of the
  surface point (affine in the object-frame point on each face; fixed to the object), NaN
  background. A surface point has the same (object_id, face_id, texcoords) in both views.
* ``poses``: ``{name: 4x4}`` object pose in the left optical frame (T_left_object, float64).
* ``object_names``: list of names in ``object_id`` order.
* ``camera``: :meth:`StereoCamera.as_dict` (K, baseline, P_left, P_right, ...).

Not in ``truth`` but on the renderer: :attr:`StereoRenderer.charts`, ``{name: (A (F, 2, 3),
b (F, 2))}`` per-face texture charts, (s, t) = A X + b for an object-frame point X [m] on face
F, so texcoords can be mapped back to the surface.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, List, Mapping, Optional, Sequence, Tuple

import cv2
import numba
import numpy as np

from stereo_manip_tools.mesh_io import PolygonMesh
from stereo_manip_tools.transforms import check_transform

from .camera import StereoCamera
from .raster import colorize, occlusion_mask, quantize, rasterize, shade, triangle_setup
from .texture import face_charts, make_noise_tile, triangle_corner_texcoords

__all__ = ['RenderOptions', 'StereoRenderer', 'reprojection_errors']


@dataclass(frozen=True)
class RenderOptions:
    """
    Photometric options.

    :ivar color: True for rgb8 images (H, W, 3), False for mono8 (H, W).
    :ivar noise_sigma: std of additive Gaussian noise [grey levels 0-255] (>= 0).
    :ivar blur_sigma: Gaussian blur std [px] applied to both images (>= 0; 0 = none).
    :ivar gain_right: multiplicative gain of the right camera (> 0); 1 = identical cameras.
    :ivar ambient: ambient fraction of the Lambertian shading, in [0, 1].
    :ivar background: grey level of pixels that hit nothing, in [0, 1].
    :ivar texel_size: texture texel size on the surfaces [m] (> 0).
    :ivar light_dir: direction towards the light in the left optical frame (normalised).
    """

    color: bool = False
    noise_sigma: float = 0.0
    blur_sigma: float = 0.0
    gain_right: float = 1.0
    ambient: float = 0.45
    background: float = 0.08
    texel_size: float = 0.0005
    light_dir: Tuple[float, float, float] = (-0.25, -0.35, -1.0)

    def __post_init__(self) -> None:
        checks = [('noise_sigma', self.noise_sigma >= 0), ('blur_sigma', self.blur_sigma >= 0),
                  ('gain_right', self.gain_right > 0), ('ambient', 0 <= self.ambient <= 1),
                  ('background', 0 <= self.background <= 1), ('texel_size', self.texel_size > 0)]
        for name, ok in checks:
            if not ok or not np.isfinite(getattr(self, name)):
                raise ValueError(f'render option {name} out of range: {getattr(self, name)!r}')
        if np.linalg.norm(self.light_dir) == 0:
            raise ValueError('render option light_dir must be non-zero')


#: Albedo of named models; others cycle through ``_PALETTE``.
_NAMED_COLORS = {'table': (0.75, 0.68, 0.60)}
_PALETTE = np.array([[0.95, 0.85, 0.70], [0.70, 0.85, 1.00], [1.00, 0.70, 0.65],
                     [0.75, 1.00, 0.75], [1.00, 0.95, 0.60], [0.85, 0.75, 1.00],
                     [0.65, 0.95, 0.95], [1.00, 0.80, 0.95]], dtype=np.float32)


class _Model:
    def __init__(self, mesh: PolygonMesh, rng: np.random.Generator, tile: int, texel: float,
                 color: np.ndarray) -> None:
        self.name = mesh.name
        self.mesh = mesh
        A, b = face_charts(mesh, rng, tile, texel)
        self.charts = (A, b)
        tris, face_of, st = triangle_corner_texcoords(mesh, A, b)
        self.tris = tris
        self.face_of = face_of.astype(np.int32)
        self.st0 = st[:, 0]
        self.d1 = st[:, 1] - st[:, 0]
        self.d2 = st[:, 2] - st[:, 0]
        self.vertices = mesh.vertices.astype(np.float64)
        self.color = color.astype(np.float32)


class StereoRenderer:
    """
    Renders stereo pairs of a fixed set of object models at given poses.

    Not thread-safe: one renderer reuses its working buffers; use one per thread.

    :param camera: the stereo camera.
    :param meshes: object models (names must be unique); ``object_id`` follows this order.
    :param seed: seed of the texture tile and the per-face texture offsets.
    :param options: photometric options.
    """

    def __init__(self, camera: StereoCamera, meshes: Sequence[PolygonMesh], seed: int = 0,
                 options: RenderOptions = RenderOptions()) -> None:
        names = [m.name for m in meshes]
        if len(set(names)) != len(names):
            raise ValueError(f'object names must be unique, got {names}')
        if not names:
            raise ValueError('a renderer needs at least one model')
        self.camera = camera
        self.options = options
        self.seed = int(seed)
        rng = np.random.default_rng(self.seed)
        self.tile = make_noise_tile(self.seed)
        n_tile = self.tile.shape[0]
        self.models: List[_Model] = [
            _Model(m, rng, n_tile, options.texel_size,
                   np.array(_NAMED_COLORS.get(m.name, _PALETTE[i % len(_PALETTE)])))
            for i, m in enumerate(meshes)]
        self.names = names
        self._index = {n: i for i, n in enumerate(names)}
        L = np.asarray(options.light_dir, dtype=float)
        self._light = L / np.linalg.norm(L)
        self._bands = max(1, 4 * numba.get_num_threads())
        self._static: Optional[dict] = None
        H, W = camera.height, camera.width
        self._work = [{'z': np.empty((H, W)), 'tid': np.empty((H, W), np.int32),
                       'img': np.empty((H, W), np.float32),
                       'tid_d': np.empty((H, W), np.int32), 'w1': np.empty((H, W)),
                       'w2': np.empty((H, W))} for _ in range(2)]
        self._noise = (np.random.default_rng([self.seed, 7]).standard_normal(1 << 22)
                       .astype(np.float32) if options.noise_sigma > 0 else np.zeros(1, np.float32))
        self._palette = np.concatenate([np.array([[1.0, 1.0, 1.0]], np.float32),
                                        np.stack([m.color for m in self.models])])

    @property
    def charts(self) -> Dict[str, Tuple[np.ndarray, np.ndarray]]:
        """Per-object face texture charts ``{name: (A (F,2,3), b (F,2))}``."""
        return {m.name: m.charts for m in self.models}

    def _triangles(self, poses: Mapping[str, np.ndarray]) -> Dict[str, np.ndarray]:
        """Posed triangle soup (left optical frame) with per-triangle attributes."""
        Vs, obj, face, st0, d1, d2, grey = [], [], [], [], [], [], []
        for name, T in poses.items():
            if name not in self._index:
                raise KeyError(f'no model named {name!r}; known: {self.names}')
            T = np.asarray(T, dtype=float)
            check_transform(T, f'pose of {name}')
            i = self._index[name]
            m = self.models[i]
            V = m.vertices @ T[:3, :3].T + T[:3, 3]
            Vs.append(V[m.tris])
            obj.append(np.full(len(m.tris), i, np.int16))
            grey.append(np.full(len(m.tris), float(np.mean(m.color))))
            face.append(m.face_of)
            st0.append(m.st0)
            d1.append(m.d1)
            d2.append(m.d2)
        if not Vs:
            z = np.zeros((0, 2))
            out = {'V': np.zeros((0, 3, 3)), 'obj': np.zeros(0, np.int16),
                   'face': np.zeros(0, np.int32), 'st0': z, 'd1': z, 'd2': z,
                   'lam': np.zeros(0, np.float32)}
        else:
            out = {'V': np.concatenate(Vs), 'obj': np.concatenate(obj),
                   'face': np.concatenate(face), 'st0': np.concatenate(st0),
                   'd1': np.concatenate(d1), 'd2': np.concatenate(d2)}
            V = out['V']
            n = np.cross(V[:, 1] - V[:, 0], V[:, 2] - V[:, 0])
            nn = np.linalg.norm(n, axis=1)
            n = n / np.where(nn > 0, nn, 1.0)[:, None]
            opt = self.options
            lam = opt.ambient + (1.0 - opt.ambient) * np.abs(n @ self._light)
            if not opt.color:
                lam = lam * np.concatenate(grey)
            out['lam'] = lam.astype(np.float32)
        return out

    def _empty_view(self) -> Dict[str, np.ndarray]:
        H, W = self.camera.height, self.camera.width
        return {'z': np.full((H, W), np.inf), 'tid': np.full((H, W), -1, np.int32),
                'img': np.full((H, W), self.options.background, np.float32),
                'tc': np.full((H, W, 2), np.nan, np.float32),
                'z32': np.full((H, W), np.nan, np.float32),
                'oid': np.full((H, W), -1, np.int16), 'fid': np.full((H, W), -1, np.int32)}

    def _draw(self, tris: Dict[str, np.ndarray], base: Dict[str, np.ndarray], right: bool,
              id_offset: int, reuse: bool = False) -> Tuple[Dict[str, np.ndarray], np.ndarray]:
        """
        Render ``tris`` over a copy of the view buffers ``base``; returns (view, setup).

        ``reuse``: the truth buffers too are working buffers, overwritten by the next call.
        """
        cam = self.camera
        V = tris['V']
        if right:
            V = V.copy()
            V[:, :, 0] -= cam.baseline
        args = (cam.fx, cam.fy, cam.cx, cam.cy)
        setup = triangle_setup(V, *args, cam.width, cam.height)
        # Working buffers (z, tid, img and the rasterizer's scratch) are reused between calls
        # (no allocation, no page faults); the returned truth arrays are fresh copies.
        work = self._work[1 if right else 0]
        view = {}
        for k, a in base.items():
            if k in ('z', 'tid', 'img') or reuse:
                if k not in work:
                    work[k] = np.empty_like(a)
                np.copyto(work[k], a)
                view[k] = work[k]
            else:
                view[k] = a.copy()
        rasterize(setup, *args, self._bands, view['z'], work['tid_d'], work['w1'], work['w2'])
        shade(view['z'], work['tid_d'], work['w1'], work['w2'], tris['st0'], tris['d1'],
              tris['d2'], tris['lam'], tris['obj'], tris['face'], self.tile, id_offset,
              view['img'], view['tc'], view['z32'], view['oid'], view['fid'], view['tid'])
        return view, setup

    def _static_layer(self, poses: Mapping[str, np.ndarray]) -> dict:
        """Render the buffers of the static objects (cached while their poses do not change)."""
        key = tuple((n, np.asarray(T, dtype=float).tobytes()) for n, T in sorted(poses.items()))
        if self._static is not None and self._static['key'] == key:
            return self._static
        tris = self._triangles(poses)
        empty = self._empty_view()
        left, _ = self._draw(tris, empty, False, 0)
        left = {k: a.copy() for k, a in left.items()}
        right, setup_r = self._draw(tris, empty, True, 0)
        right = {k: a.copy() for k, a in right.items()}
        self._static = {'key': key, 'left': left, 'right': right, 'setup_r': setup_r,
                        'count': len(tris['V'])}
        return self._static

    def _photometric(self, img: np.ndarray, gain: float, rng: np.random.Generator) -> np.ndarray:
        """
        Blur, gain, additive noise and quantisation to uint8 of a [0, 1] float image.

        The noise samples are drawn from a per-renderer bank of 2^22 standard normals at a
        random offset per image (drawn from ``rng``), which is much faster than fresh samples.
        """
        opt = self.options
        if opt.blur_sigma > 0:
            img = cv2.GaussianBlur(img, (0, 0), opt.blur_sigma)
        # A window that fits in the bank keeps the noise reads contiguous (fast).
        offset = int(rng.integers(0, max(1, self._noise.size - img.size + 1)))
        return quantize(img, 255.0 * gain, self._noise, offset, float(opt.noise_sigma))

    def render(self, poses: Mapping[str, np.ndarray], noise_key: Sequence[int] = (0,),
               static: Sequence[str] = (), images_only: bool = False
               ) -> Tuple[np.ndarray, np.ndarray, dict]:
        """
        Render one stereo pair.

        :param poses: ``{object name: T_left_object (4x4)}``; objects not listed are absent.
        :param noise_key: integers seeding the photometric noise of this pair (with the seed).
        :param static: names of objects whose poses stay fixed from frame to frame (e.g. the
            table): their layer is rendered once and reused while their poses are unchanged
            (checked exactly), so only the moving objects are drawn per frame. The result is
            identical to rendering everything (static objects come first in the z-buffer).
        :param images_only: skip the truth images (no occlusion mask, no fresh truth buffers):
            the same images, bit for bit, and a truth dict with ``poses``, ``object_names`` and
            ``camera`` only (a live camera whose truth images nobody reads: ~4 ms less per
            pair).
        :returns: (left, right, truth): uint8 images (H, W) mono or (H, W, 3) rgb, and the truth
            dict documented in the module docstring.
        :raises KeyError: for a pose of an unknown object.
        :raises ValueError: for a malformed pose (shape, NaN, non-orthonormal rotation).
        """
        cam, opt = self.camera, self.options
        static_poses = {n: poses[n] for n in static if n in poses}
        moving = {n: T for n, T in poses.items() if n not in static_poses}
        layer = self._static_layer(static_poses)
        tris = self._triangles(moving)
        n_static = layer['count']
        left, _ = self._draw(tris, layer['left'], False, n_static, images_only)
        right, setup_r = self._draw(tris, layer['right'], True, n_static, images_only)
        if not images_only:
            tris_r = np.concatenate([layer['setup_r'], setup_r])
            occ = occlusion_mask(left['z'], left['tid'], right['tid'], tris_r, cam.fx, cam.fy,
                                 cam.cx, cam.cy, cam.baseline)
        img_l, img_r = left['img'], right['img']
        if opt.color:
            img_l = colorize(img_l, left['oid'], self._palette)
            img_r = colorize(img_r, right['oid'], self._palette)
        rng = np.random.default_rng([self.seed, *[int(k) for k in noise_key]])
        left_img = self._photometric(img_l, 1.0, rng)
        right_img = self._photometric(img_r, opt.gain_right, rng)
        if images_only:
            return left_img, right_img, {
                'poses': {name: np.array(T, dtype=float) for name, T in poses.items()},
                'object_names': list(self.names), 'camera': cam.as_dict()}
        depth_l = left['z32']
        truth = {
            'depth': depth_l,
            'disparity': (np.float32(cam.fx * cam.baseline) / depth_l).astype(np.float32),
            'occlusion': occ,
            'valid': left['tid'] >= 0,
            'object_id': left['oid'], 'face_id': left['fid'], 'texcoords': left['tc'],
            'depth_right': right['z32'], 'object_id_right': right['oid'],
            'face_id_right': right['fid'], 'texcoords_right': right['tc'],
            'poses': {name: np.array(T, dtype=float) for name, T in poses.items()},
            'object_names': list(self.names),
            'camera': cam.as_dict(),
        }
        return left_img, right_img, truth


def reprojection_errors(truth: dict, n: int = 400, seed: int = 0) -> np.ndarray:
    """
    Reprojection distances [px] of the left depth into the right image.

    Distance [px] between the projection into the right camera of the back-projected left
    depth and the right-image location whose texture coordinates equal the left pixel's, for
    up to ``n`` random valid, unoccluded left pixels (``seed``) of a rendered ``truth``; the
    geometry check of the acceptance test and of ``bench/camera_render_rate.py``.
    """
    cam = truth['camera']
    K, P_r = cam['K'], cam['P_right']
    H, W = truth['depth'].shape
    ok = truth['valid'] & ~truth['occlusion']
    vs, us = np.nonzero(ok)
    rng = np.random.default_rng(seed)
    pick = rng.permutation(len(us))
    errs = []
    for i in pick:
        u, v = us[i], vs[i]
        Z = float(truth['depth'][v, u])
        X = Z * np.linalg.solve(K, [u, v, 1.0])
        x = P_r @ np.append(X, 1.0)
        ur, vr = x[0] / x[2], x[1] / x[2]
        u0, v0 = int(np.floor(ur)), int(round(vr))
        cols, rows = np.arange(u0 - 1, u0 + 3), np.arange(v0 - 1, v0 + 2)
        if cols[0] < 0 or cols[-1] >= W or rows[0] < 0 or rows[-1] >= H:
            continue
        oid = truth['object_id_right'][np.ix_(rows, cols)]
        fid = truth['face_id_right'][np.ix_(rows, cols)]
        if np.any(oid != truth['object_id'][v, u]) or np.any(fid != truth['face_id'][v, u]):
            continue  # the neighbourhood crosses a face boundary: no local affine model
        # Texture coordinates are a smooth (projective) function of the pixel on a face: fit
        # it locally and solve for the right pixel carrying the left pixel's coordinates.
        gu, gv = np.meshgrid(cols, rows)
        A = np.column_stack([gu.ravel(), gv.ravel(), np.ones(gu.size)])
        tc = truth['texcoords_right'][np.ix_(rows, cols)].reshape(-1, 2).astype(np.float64)
        coef, *_ = np.linalg.lstsq(A, tc, rcond=None)
        q = np.linalg.solve(coef[:2].T, truth['texcoords'][v, u].astype(np.float64) - coef[2])
        errs.append(np.hypot(q[0] - ur, q[1] - vr))
        if len(errs) >= n:
            break
    return np.array(errs)
