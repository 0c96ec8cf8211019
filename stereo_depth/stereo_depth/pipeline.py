"""
The four-step stereo pipeline as named methods, and disparity -> depth -> 3-D points.

A *method* turns a rectified pair into a left-view disparity map: (H, W) float32, pixels,
``x_right = x_left - d``, NaN where there is no estimate. Methods and their parameters:

================  ===========================================================================
``sgm``           census (``census_window``) -> SGM (``p1``, ``p2``, ``paths`` 8,
                  intensity-adaptive P2 ``p2_gamma``) -> WTA with parabola subpixel ->
                  refinement (hole filling ``fill_mode`` 'directional').
``sgm4``          the same with 4 paths (faster).
``block_matching``  the chapter's local method: ``cost`` ('ad', 'bt', 'census', 'zncc') ->
                  box aggregation (``window``) -> WTA -> subpixel -> refinement.
``bp``            hierarchical loopy BP (Felzenszwalb & Huttenlocher 2006) of Eq. 1 on a
                  truncated census (or 'ad') data cost (``cost``, ``census_window``,
                  ``data_weight``, ``data_truncation``, ``smoothness``, ``truncation``,
                  ``iterations``, ``levels``) -> refinement.
``opencv_bm``     OpenCV ``StereoBM`` (``block_size``), the hardware-like real-time path.
``opencv_sgbm``   OpenCV ``StereoSGBM`` (``block_size``, ``mode`` 'sgbm' | '3way' | 'hh' |
                  'hh4'; P1 = 8 bs^2, P2 = 32 bs^2 unless ``p1``/``p2`` are given).
================  ===========================================================================

Refinement parameters shared by the own methods: ``lr_check`` (bool), ``lr_max_diff`` (px),
``speckle_size`` (px, 0 = off), ``speckle_diff`` (px), ``median`` (odd window, 1 = off),
``fill`` (bool: fill missing pixels from the background, so the map is dense); ``sgm`` and
``sgm4`` also take ``fill_mode`` ('row' | 'directional', see ``refinement.fill_invalid``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, NamedTuple, Optional

import numba
import numpy as np

from stereo_depth.aggregation import box_aggregate, box_sum_u16
from stereo_depth.matching_cost import (absolute_difference_cost, census_cost, check_pair,
                                        to_gray, zncc_cost)
from stereo_depth.optimization import (belief_propagation, census_block_matching, sgm_disparities,
                                       winner_take_all_both)
from stereo_depth.refinement import (fill_invalid, left_right_check, median_filter,
                                     remove_speckles, subpixel_refine)

__all__ = [
    'StereoMethod',
    'METHODS',
    'available_methods',
    'method_defaults',
    'compute_disparity',
    'disparity_to_depth',
    'depth_to_points',
    'disparity_to_points',
    'cloud_points',
    'PackedCloud',
    'cloud_message_data',
]

_REFINE_DEFAULTS = {
    'lr_check': True,
    'lr_max_diff': 1.0,
    'speckle_size': 100,
    'speckle_diff': 1.0,
    'median': 3,
    'fill': True,
}


# SGM: intensity-adaptive P2 (p2_gamma, Hirschmueller 2008 Sec. 3.1) with a larger base P2,
# and the 8-direction background fill (fill_mode 'directional', Sec. 3.5). Chosen on both
# benchmark sets (bench/stereo_middlebury.py): against constant P2 = 60 and row fill they
# lower bad-2 on Middlebury Motorcycle and on the synthetic peg_in_hole frames alike.
_SGM_DEFAULTS = {'census_window': (9, 7), 'p1': 10, 'p2': 90, 'p2_gamma': 30.0,
                 'uniqueness': 0.0, **_REFINE_DEFAULTS, 'fill_mode': 'directional'}


@dataclass(frozen=True)
class StereoMethod:
    """A named disparity method: ``function(left, right, max_disparity, **params)``."""

    name: str
    function: Callable[..., np.ndarray]
    defaults: dict = field(default_factory=dict)
    description: str = ''


def _refine(dl: np.ndarray, dr: np.ndarray | None, p: dict) -> np.ndarray:
    d = dl
    if p['lr_check'] and dr is not None:
        d = left_right_check(d, dr, p['lr_max_diff'])
    if p['speckle_size'] > 0:
        d = remove_speckles(d, int(p['speckle_size']), float(p['speckle_diff']))
    if p['median'] > 1:
        d = median_filter(d, int(p['median']))
    if p['fill']:
        d = fill_invalid(d, p.get('fill_mode', 'row'))
    return d.astype(np.float32, copy=False)


def _sgm(left, right, max_disparity, census_window=(9, 7), p1=10, p2=90, paths=8,
         uniqueness=0.0, p2_gamma=30.0, **refine):
    cost = census_cost(left, right, max_disparity, tuple(census_window))
    dl, dr = sgm_disparities(cost, int(p1), int(p2), int(paths), float(uniqueness), left,
                             float(p2_gamma))
    return _refine(dl, dr, refine)


def _sgm4(left, right, max_disparity, **params):
    params['paths'] = 4
    return _sgm(left, right, max_disparity, **params)


def _cost_volume(kind, left, right, max_disparity, census_window=(9, 7), zncc_window=(7, 7),
                 ad_truncation=255.0):
    if kind == 'ad':
        return absolute_difference_cost(left, right, max_disparity, ad_truncation)
    if kind == 'bt':
        return absolute_difference_cost(left, right, max_disparity, ad_truncation, True)
    if kind == 'census':
        return census_cost(left, right, max_disparity, tuple(census_window))
    if kind == 'zncc':
        return zncc_cost(left, right, max_disparity, tuple(zncc_window))
    raise ValueError(f"unknown matching cost '{kind}' (use 'ad', 'bt', 'census' or 'zncc')")


def _block_matching(left, right, max_disparity, cost='census', window=(7, 7),
                    census_window=(5, 5), zncc_window=(7, 7), ad_truncation=255.0, **refine):
    if cost == 'census' and tuple(window)[0] * tuple(window)[1] * 255 <= 65535:
        dl, dr = census_block_matching(left, right, max_disparity, tuple(census_window),
                                       tuple(window))
        return _refine(dl, dr, refine)
    c = _cost_volume(cost, left, right, max_disparity, census_window, zncc_window, ad_truncation)
    if cost != 'zncc':
        window = tuple(window)
        if c.dtype == np.uint8 and window[0] * window[1] * 255 <= 65535:
            c = box_sum_u16(c, window)
        else:
            c = box_aggregate(c, window, normalize=False)
    dl, dr = winner_take_all_both(c)
    return _refine(dl, dr, refine)


def _bp(left, right, max_disparity, cost='census', census_window=(7, 7), data_weight=0.15,
        data_truncation=30.0, smoothness=1.0, truncation=3.0, iterations=5, levels=5,
        **refine):
    # FH 2006 data term lambda_d * min(C, tau_d) on a census (or absolute difference) cost.
    def data_cost(a, b):
        if cost == 'census':
            c = census_cost(a, b, max_disparity, tuple(census_window))
        elif cost == 'ad':
            c = absolute_difference_cost(a, b, max_disparity)
        else:
            raise ValueError(f"bp data cost must be 'census' or 'ad', got '{cost}'")
        return np.minimum(c.astype(np.float32), np.float32(data_truncation)) * \
            np.float32(data_weight)

    data = data_cost(left, right)
    labels = belief_propagation(data, smoothness, truncation, int(iterations), int(levels))
    dl = subpixel_refine(labels, data)
    dr = None
    if refine['lr_check']:
        # BP of the right view: mirror the pair (the flipped right image becomes the left one).
        flip_l = np.ascontiguousarray(np.asarray(right)[:, ::-1])
        flip_r = np.ascontiguousarray(np.asarray(left)[:, ::-1])
        lab_r = belief_propagation(data_cost(flip_l, flip_r), smoothness, truncation,
                                   int(iterations), int(levels))
        dr = np.ascontiguousarray(lab_r[:, ::-1]).astype(np.float32)
    return _refine(dl, dr, refine)


def _to_cv_input(img):
    arr = np.asarray(img)
    if arr.dtype != np.uint8:
        arr = np.clip(np.rint(arr), 0, 255).astype(np.uint8)
    return arr


def _opencv_bm(left, right, max_disparity, block_size=15, uniqueness_ratio=10,
               speckle_window=100, speckle_range=2, texture_threshold=10):
    import cv2

    nd = int(np.ceil(max_disparity / 16.0) * 16)
    bm = cv2.StereoBM_create(numDisparities=nd, blockSize=int(block_size))
    bm.setUniquenessRatio(int(uniqueness_ratio))
    bm.setSpeckleWindowSize(int(speckle_window))
    bm.setSpeckleRange(int(speckle_range))
    bm.setTextureThreshold(int(texture_threshold))
    gl = _to_cv_input(to_gray(left))
    gr = _to_cv_input(to_gray(right))
    raw = bm.compute(gl, gr)
    d = raw.astype(np.float32) / 16.0
    d[(raw < 0) | (d >= max_disparity)] = np.nan
    return d


_SGBM_MODES = {'sgbm': 0, '3way': 2, 'hh': 1, 'hh4': 3}


def _opencv_sgbm(left, right, max_disparity, block_size=5, mode='3way', p1=None, p2=None,
                 uniqueness_ratio=0, speckle_window=0, speckle_range=0, disp12_max_diff=0,
                 pre_filter_cap=0):
    import cv2

    if mode not in _SGBM_MODES:
        raise ValueError(f"unknown SGBM mode '{mode}' (use {sorted(_SGBM_MODES)})")
    bs = int(block_size)
    nd = int(np.ceil(max_disparity / 16.0) * 16)
    sgbm = cv2.StereoSGBM_create(
        minDisparity=0, numDisparities=nd, blockSize=bs,
        P1=int(8 * bs * bs if p1 is None else p1), P2=int(32 * bs * bs if p2 is None else p2),
        disp12MaxDiff=int(disp12_max_diff), preFilterCap=int(pre_filter_cap),
        uniquenessRatio=int(uniqueness_ratio), speckleWindowSize=int(speckle_window),
        speckleRange=int(speckle_range), mode=_SGBM_MODES[mode])
    raw = sgbm.compute(_to_cv_input(left), _to_cv_input(right))
    d = raw.astype(np.float32) / 16.0
    d[(raw < 0) | (d >= max_disparity)] = np.nan
    return d


METHODS: dict[str, StereoMethod] = {
    'sgm': StereoMethod('sgm', _sgm, {**_SGM_DEFAULTS, 'paths': 8},
                        'census + semi-global matching (8 paths) + refinement'),
    'sgm4': StereoMethod('sgm4', _sgm4, dict(_SGM_DEFAULTS),
                         'census + semi-global matching (4 paths) + refinement'),
    'block_matching': StereoMethod(
        'block_matching', _block_matching,
        {'cost': 'census', 'window': (7, 7), 'census_window': (5, 5), 'zncc_window': (7, 7),
         'ad_truncation': 255.0, **_REFINE_DEFAULTS},
        'local method: matching cost + box aggregation + winner-take-all + refinement'),
    'bp': StereoMethod(
        'bp', _bp,
        {'cost': 'census', 'census_window': (7, 7), 'data_weight': 0.15,
         'data_truncation': 30.0, 'smoothness': 1.0, 'truncation': 3.0, 'iterations': 5,
         'levels': 5, **_REFINE_DEFAULTS},
        'hierarchical loopy belief propagation of Eq. 1 (Felzenszwalb & Huttenlocher 2006)'),
    'opencv_bm': StereoMethod(
        'opencv_bm', _opencv_bm,
        {'block_size': 15, 'uniqueness_ratio': 10, 'speckle_window': 100, 'speckle_range': 2,
         'texture_threshold': 10},
        'OpenCV StereoBM (real time, sparse)'),
    'opencv_sgbm': StereoMethod(
        'opencv_sgbm', _opencv_sgbm,
        {'block_size': 5, 'mode': '3way', 'p1': None, 'p2': None, 'uniqueness_ratio': 0,
         'speckle_window': 0, 'speckle_range': 0, 'disp12_max_diff': 0, 'pre_filter_cap': 0},
        'OpenCV StereoSGBM'),
}


def available_methods() -> list[str]:
    """Names accepted by :func:`compute_disparity`."""
    return sorted(METHODS)


def method_defaults(method: str) -> dict:
    """Return a copy of the default parameters of ``method``."""
    if method not in METHODS:
        raise ValueError(f"unknown stereo method '{method}'; available: {available_methods()}")
    return dict(METHODS[method].defaults)


def compute_disparity(left: np.ndarray, right: np.ndarray, method: str = 'sgm',
                      max_disparity: int = 64, min_disparity: int = 0,
                      **params: Any) -> np.ndarray:
    """
    Left-view disparity of a rectified pair with a named method.

    :param left: left rectified image, (H, W) grey or (H, W, 3) RGB.
    :param right: right rectified image, same shape.
    :param method: one of :func:`available_methods`.
    :param max_disparity: number of disparity candidates D (min_disparity .. min_disparity +
        D - 1 pixels); ``stereo_image_proc`` calls it ``disparity_range``.
    :param min_disparity: smallest disparity searched [px] (>= 0). The pair is cropped to
        ``left[:, m:]`` and ``right[:, :W - m]`` and matched over 0 .. D-1, so a scene whose
        disparities lie in a band costs D, not m + D, candidates; columns x < m of the result
        are NaN (their match would lie outside the right image). In a band (m > 0) a match at
        either end of it (within half a pixel of m or of m + D - 1) is NaN too: its cost was
        still falling at the band's limit, so it says only that the surface lies beyond the
        band; kept, every pixel farther than the band (the background) would become one flat
        fake surface at depth ``f B / m``, and every nearer one a surface at ``f B / (m+D-1)``.
    :param params: method parameters overriding :func:`method_defaults`; unknown names raise.
    :return: (H, W) float32 disparities in pixels, NaN where unknown.
    """
    p = method_defaults(method)
    unknown = set(params) - set(p)
    if unknown:
        raise ValueError(f"unknown parameter(s) {sorted(unknown)} for method '{method}'; "
                         f'known: {sorted(p)}')
    p.update(params)
    left, right = np.asarray(left), np.asarray(right)
    m = int(min_disparity)
    if m < 0:
        raise ValueError(f'min_disparity must be >= 0 px, got {m}')
    if m == 0:
        check_pair(left, right, max_disparity)
        return METHODS[method].function(left, right, int(max_disparity), **p)
    w = left.shape[1]
    if m + int(max_disparity) > w:
        raise ValueError(f'min_disparity {m} + max_disparity {max_disparity} exceeds the image '
                         f'width {w}')
    lc, rc = np.ascontiguousarray(left[:, m:]), np.ascontiguousarray(right[:, :w - m])
    check_pair(lc, rc, max_disparity)
    d = METHODS[method].function(lc, rc, int(max_disparity), **p)
    return _place_band(d, m, float(int(max_disparity) - 1.5), w)


@numba.njit(cache=True, nogil=True, boundscheck=False)
def _place_band(d, m, hi, w):
    # The band's disparities d (H, W - m) into the full-width map: d + m in columns m.., NaN
    # left of m and where d was clamped at an end of the band (d < 0.5 or d > D - 1.5).
    h = d.shape[0]
    out = np.empty((h, w), np.float32)
    fm = np.float32(m)
    for y in range(h):
        for x in range(m):
            out[y, x] = np.nan
        for x in range(w - m):
            v = d[y, x]
            out[y, m + x] = np.float32(np.nan) if (v < 0.5 or v > hi) else v + fm
    return out


def disparity_to_depth(disparity: np.ndarray, focal_length: float, baseline: float,
                       doffs: float = 0.0) -> np.ndarray:
    """
    Depth along the optical axis ``Z = f B / (d + doffs)`` (metres, NaN where unknown).

    :param disparity: (H, W) disparities in pixels.
    :param focal_length: horizontal focal length ``fx`` in pixels (rectified).
    :param baseline: distance between the optical centres in metres (> 0).
    :param doffs: ``cx_right - cx_left`` in pixels (0 for the usual rectification).
    :return: (H, W) float32 depth; NaN where ``d + doffs <= 0`` or the disparity is NaN.
    """
    if not np.isfinite(baseline) or baseline <= 0:
        raise ValueError(f'baseline must be a positive number of metres, got {baseline}')
    if not np.isfinite(focal_length) or focal_length <= 0:
        raise ValueError(f'focal length must be a positive number of pixels, got {focal_length}')
    d = np.asarray(disparity, dtype=np.float32) + np.float32(doffs)
    with np.errstate(divide='ignore', invalid='ignore'):
        z = np.float32(focal_length * baseline) / d
    z[~(d > 0)] = np.nan
    return z


def depth_to_points(depth: np.ndarray, fx: float, fy: float, cx: float,
                    cy: float) -> np.ndarray:
    """
    Back-project a depth image into the optical frame (z forward, x right, y down).

    :param depth: (H, W) depth in metres, NaN where unknown.
    :param fx: focal lengths and principal point of the (rectified) camera, pixels.
    :return: (H, W, 3) float32 points in metres, NaN where the depth is unknown.
    """
    z = np.asarray(depth, dtype=np.float32)
    h, w = z.shape
    u = np.arange(w, dtype=np.float32)[None, :]
    v = np.arange(h, dtype=np.float32)[:, None]
    x = (u - np.float32(cx)) * z / np.float32(fx)
    y = (v - np.float32(cy)) * z / np.float32(fy)
    return np.stack([x, y, z], axis=-1)


def disparity_to_points(disparity: np.ndarray, fx: float, fy: float, cx: float, cy: float,
                        baseline: float, doffs: float = 0.0) -> np.ndarray:
    """Disparity -> (H, W, 3) points in the left optical frame (metres, NaN where unknown)."""
    return depth_to_points(disparity_to_depth(disparity, fx, baseline, doffs), fx, fy, cx, cy)


def cloud_points(depth: np.ndarray, fx: float, fy: float, cx: float, cy: float,
                 decimation: int = 1, organized: bool = False,
                 colours: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray | None]:
    """
    Select the points of a depth image for a point cloud, every ``decimation``-th pixel.

    Pixel (u, v) with ``u % s == 0`` and ``v % s == 0`` (s = ``decimation``) is kept, exactly
    back-projected (no averaging: a mean across a depth edge would invent points between
    surfaces).

    :param depth: (H, W) metres along the optical axis, NaN where unknown.
    :param decimation: keep every s-th pixel in both directions (>= 1).
    :param organized: True: return the (ceil(H/s), ceil(W/s), 3) grid with NaN where unknown
        (an organised cloud); False: only the finite points, (N, 3).
    :param colours: optional (H, W, 3) uint8 colours of the left image.
    :return: (points float32 [m] in the optical frame, colours of those points or None).
    """
    s = int(decimation)
    if s < 1:
        raise ValueError(f'decimation must be >= 1, got {s}')
    z = np.asarray(depth, dtype=np.float32)[::s, ::s]
    hs, ws = z.shape
    u = (np.arange(ws, dtype=np.float32) * s)[None, :]
    v = (np.arange(hs, dtype=np.float32) * s)[:, None]
    pts = np.stack([(u - np.float32(cx)) * z / np.float32(fx),
                    (v - np.float32(cy)) * z / np.float32(fy), z], axis=-1)
    rgb = None if colours is None else np.asarray(colours)[::s, ::s]
    if organized:
        return pts, rgb
    ok = np.isfinite(z)
    return pts[ok], (None if rgb is None else rgb[ok])


class PackedCloud(NamedTuple):
    """
    A point cloud laid out as ``sensor_msgs/PointCloud2`` data, ready to be sent as is.

    :ivar buffer: (height, width, k) float32, C-contiguous; each point is k consecutive
        float32 of the ``fields`` (``rgb``: the colour bits ``r << 16 | g << 8 | b`` of a
        uint32 stored in the float32). An unorganised cloud has height 1.
    :ivar fields: names of the k float32 fields, in order (offsets 0, 4, 8, ...).
    :ivar is_dense: True when no point is NaN.
    """

    buffer: np.ndarray
    fields: tuple
    is_dense: bool


@numba.njit(cache=True, nogil=True, boundscheck=False)
def _pack_cloud(z, s, fx, fy, cx, cy, colours, use_rgb, organized, out, out_u32,
                from_disparity, fb, doffs):
    # One pass over the decimated grid: x, y, z (+ rgb bits) written into the message layout.
    # The float32 arithmetic is the one of cloud_points ((u - cx) * z / fx), so the points are
    # bit-identical. Unorganised: only finite depths, compacted in raster order.
    # from_disparity: z holds disparities, the depth is disparity_to_depth's float32
    # fb / (d + doffs) (NaN unless d + doffs > 0), computed at the kept pixels only.
    h, w = z.shape
    n = 0
    for i in range((h + s - 1) // s):
        v = np.float32(i * s)
        for j in range((w + s - 1) // s):
            zz = z[i * s, j * s]
            if from_disparity:
                dd = zz + doffs
                zz = fb / dd if dd > 0 else np.float32(np.nan)
            if not organized and not np.isfinite(zz):
                continue
            u = np.float32(j * s)
            out[n, 0] = (u - cx) * zz / fx
            out[n, 1] = (v - cy) * zz / fy
            out[n, 2] = zz
            if use_rgb:
                c = colours[i * s, j * s]
                out_u32[n, 3] = (np.uint32(c[0]) << np.uint32(16)) | \
                    (np.uint32(c[1]) << np.uint32(8)) | np.uint32(c[2])
            n += 1
    return n


def cloud_message_data(depth: Optional[np.ndarray], fx: float, fy: float, cx: float, cy: float,
                       decimation: int = 1, organized: bool = False,
                       colours: Optional[np.ndarray] = None, *,
                       disparity: Optional[np.ndarray] = None, baseline: float = 0.0,
                       doffs: float = 0.0) -> PackedCloud:
    """
    Pack the points of :func:`cloud_points` into PointCloud2 data in one pass.

    Same selection and bit-identical coordinates as :func:`cloud_points` followed by
    ``stereo_manip_tools.conversions.xyz_to_pointcloud2``, without per-field copies or float64
    intermediates: one float32 buffer of x, y, z (and rgb) per point, written by one compiled
    pass over the decimated grid (~1 ms at 640x480, decimation 2, against ~4 ms).

    :param depth: (H, W) metres along the optical axis, NaN where unknown.
    :param fx: focal lengths and principal point of the (rectified) left camera, pixels.
    :param decimation: keep every s-th pixel in both directions (>= 1).
    :param organized: True: the (ceil(H/s), ceil(W/s)) grid with NaN points where unknown;
        False: only the finite points, height 1.
    :param colours: optional (H, W, 3) uint8 RGB of the left image (adds an ``rgb`` field).
    :param disparity: instead of ``depth`` (pass None): (H, W) disparities [px]; the depth of
        the kept pixels is :func:`disparity_to_depth`'s (``baseline`` [m], ``doffs`` [px]),
        bit for bit, computed for those pixels only (no full-size depth image).
    :return: :class:`PackedCloud`.
    """
    s = int(decimation)
    if s < 1:
        raise ValueError(f'decimation must be >= 1, got {s}')
    from_disparity = disparity is not None
    if from_disparity == (depth is not None):
        raise ValueError('give either depth or disparity')
    if from_disparity and (not np.isfinite(baseline) or baseline <= 0):
        raise ValueError(f'baseline must be a positive number of metres, got {baseline}')
    if from_disparity and (not np.isfinite(fx) or fx <= 0):
        raise ValueError(f'focal length must be a positive number of pixels, got {fx}')
    z = np.asarray(disparity if from_disparity else depth, dtype=np.float32)
    if z.ndim != 2:
        raise ValueError(f'depth must be (H, W), got shape {z.shape}')
    h, w = z.shape
    hs, ws = (h + s - 1) // s, (w + s - 1) // s
    use_rgb = colours is not None
    if use_rgb:
        col = np.asarray(colours)
        if col.shape != (h, w, 3):
            raise ValueError(f'colours must be (H, W, 3) = {(h, w, 3)}, got {col.shape}')
        col = col.astype(np.uint8, copy=False)
    else:
        col = np.zeros((1, 1, 3), np.uint8)
    k = 4 if use_rgb else 3
    out = np.empty((hs * ws, k), np.float32)
    n = _pack_cloud(z, s, np.float32(fx), np.float32(fy), np.float32(cx), np.float32(cy), col,
                    use_rgb, bool(organized), out, out.view(np.uint32), from_disparity,
                    np.float32(fx * baseline), np.float32(doffs))
    fields = ('x', 'y', 'z', 'rgb') if use_rgb else ('x', 'y', 'z')
    if organized:
        return PackedCloud(out.reshape(hs, ws, k), fields, n == 0 or
                           bool(np.isfinite(out[:, 2]).all()))
    return PackedCloud(out[:n].reshape(1, n, k), fields, True)
