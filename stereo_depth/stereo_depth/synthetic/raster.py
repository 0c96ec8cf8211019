"""
Exact per-pixel ray casting of triangle soups by z-buffered scan conversion (numba).

For every pixel (u, v) the ray from the optical centre with direction d = (x, y, 1),
x = (u - cx)/fx, y = (v - cy)/fy, is intersected with each candidate triangle analytically
(Moller-Trumbore rewritten with d-independent vectors): for a triangle (V0, V1, V2) in the
camera frame, e1 = V1 - V0, e2 = V2 - V0, and

    den = d . (e2 x e1),   w1 = d . (e2 x -V0) / den,   w2 = d . (-V0 x e1) / den,
    t = e2 . (-V0 x e1) / den,

so the hit is P = t d = V0 + w1 e1 + w2 e2 and, because d_z = 1, t is the depth Z. This is the
same exact ray/triangle intersection a ray tracer computes (here in float64), just visiting
only the pixels inside each triangle's projected bounding box. Triangles facing away from the
camera are culled (all models are closed, outward-oriented meshes). The result equals casting
one ray per pixel centre.
"""

from __future__ import annotations

from typing import Tuple

import numba as nb
import numpy as np

__all__ = ['triangle_setup', 'rasterize', 'shade', 'occlusion_mask', 'colorize', 'quantize']

if nb.config.THREADING_LAYER == 'default':
    # The TBB in this environment is too old for numba (it warns and falls back to OpenMP),
    # and OpenMP measured 3x slower here on a shared 2-core machine (spinning threads). The
    # kernels are only launched from one Python thread at a time, so the workqueue layer is
    # safe. NUMBA_THREADING_LAYER overrides this choice.
    nb.config.THREADING_LAYER = 'workqueue'


@nb.njit(cache=True, nogil=True)
def triangle_setup(V: np.ndarray, fx: float, fy: float, cx: float, cy: float, width: int,
                   height: int) -> np.ndarray:
    """
    Per-triangle constants for :func:`rasterize`, float64 (T, 17).

    :param V: triangle vertices in this camera's optical frame [m], (T, 3, 3).
    :returns: columns a(3) b(3) c(3) k, front flag, pixel bbox umin umax vmin vmax (inclusive,
        clipped to the image), unit normal n . (0, 0, 0) unused (2 spare columns); culled
        (facing away, degenerate) or off-image triangles have front flag 0. Triangles crossing
        the plane Z = 0 are scanned over the whole image (t > 0 then decides).
    """
    T = V.shape[0]
    out = np.zeros((T, 17))
    for i in range(T):
        v0x, v0y, v0z = V[i, 0, 0], V[i, 0, 1], V[i, 0, 2]
        e1x, e1y, e1z = V[i, 1, 0] - v0x, V[i, 1, 1] - v0y, V[i, 1, 2] - v0z
        e2x, e2y, e2z = V[i, 2, 0] - v0x, V[i, 2, 1] - v0y, V[i, 2, 2] - v0z
        # c = e2 x e1, a = e2 x (-V0), b = (-V0) x e1, k = e2 . b
        c0, c1, c2 = e2y * e1z - e2z * e1y, e2z * e1x - e2x * e1z, e2x * e1y - e2y * e1x
        a0, a1, a2 = -(e2y * v0z - e2z * v0y), -(e2z * v0x - e2x * v0z), -(e2x * v0y - e2y * v0x)
        b0, b1, b2 = -(v0y * e1z - v0z * e1y), -(v0z * e1x - v0x * e1z), -(v0x * e1y - v0y * e1x)
        k = e2x * b0 + e2y * b1 + e2z * b2
        out[i, 0], out[i, 1], out[i, 2] = a0, a1, a2
        out[i, 3], out[i, 4], out[i, 5] = b0, b1, b2
        out[i, 6], out[i, 7], out[i, 8] = c0, c1, c2
        out[i, 9] = k
        # Outward normal n = e1 x e2 = -c; front-facing iff n . V0 < 0.
        front = (-(c0 * v0x + c1 * v0y + c2 * v0z) < 0.0) and (c0 * c0 + c1 * c1 + c2 * c2 > 0)
        zmin = min(V[i, 0, 2], V[i, 1, 2], V[i, 2, 2])
        if zmin > 1e-6:
            umin, umax, vmin, vmax = np.inf, -np.inf, np.inf, -np.inf
            for j in range(3):
                u = fx * V[i, j, 0] / V[i, j, 2] + cx
                v = fy * V[i, j, 1] / V[i, j, 2] + cy
                umin, umax = min(umin, u), max(umax, u)
                vmin, vmax = min(vmin, v), max(vmax, v)
            umin, umax = np.floor(umin), np.ceil(umax)
            vmin, vmax = np.floor(vmin), np.ceil(vmax)
        else:
            umin, umax, vmin, vmax = 0.0, width - 1.0, 0.0, height - 1.0
        umin, umax = max(umin, 0.0), min(umax, width - 1.0)
        vmin, vmax = max(vmin, 0.0), min(vmax, height - 1.0)
        out[i, 11], out[i, 12], out[i, 13], out[i, 14] = umin, umax, vmin, vmax
        out[i, 10] = 1.0 if (front and umin <= umax and vmin <= vmax) else 0.0
    return out


_EPS = 1e-12


@nb.njit(cache=True, fastmath=False, nogil=True)
def _hit(tri: np.ndarray, x: float, y: float) -> Tuple[float, float, float]:
    den = x * tri[6] + y * tri[7] + tri[8]
    if den == 0.0:
        return np.inf, 0.0, 0.0
    w1 = (x * tri[0] + y * tri[1] + tri[2]) / den
    w2 = (x * tri[3] + y * tri[4] + tri[5]) / den
    if w1 < -_EPS or w2 < -_EPS or w1 + w2 > 1.0 + _EPS:
        return np.inf, 0.0, 0.0
    t = tri[9] / den
    if t <= 0.0:
        return np.inf, 0.0, 0.0
    return t, w1, w2


@nb.njit(parallel=True, cache=True, nogil=True)
def rasterize(tris: np.ndarray, fx: float, fy: float, cx: float, cy: float, n_bands: int,
              depth: np.ndarray, tid: np.ndarray, w1s: np.ndarray, w2s: np.ndarray) -> None:
    """
    Z-buffer ``tris`` (prepared by :func:`triangle_setup`) over ``depth``, in place.

    :param depth: (H, W) float64 z-buffer [m], updated in place: inf where nothing was hit
        yet, or the depth of an already rendered (e.g. cached static) layer.
    :param tid: (H, W) int32 output: index of the nearest triangle of ``tris`` where one of
        them won the depth test, -1 elsewhere (reset here).
    :param w1s: (H, W) float64 output: barycentric w1 (meaningful where tid >= 0).
    :param w2s: (H, W) float64 output: barycentric w2.
    """
    height, width = depth.shape
    rows_per = (height + n_bands - 1) // n_bands
    for band in nb.prange(n_bands):
        r0 = band * rows_per
        r1 = min(height, r0 + rows_per)
        tid[r0:r1, :] = -1
        for i in range(tris.shape[0]):
            tri = tris[i]
            if tri[10] == 0.0:
                continue
            v0 = max(r0, int(tri[13]))
            v1 = min(r1 - 1, int(tri[14]))
            u0 = int(tri[11])
            u1 = int(tri[12])
            # Front-facing triangles are hit (t > 0) exactly where den > 0; the inside test
            # needs no division: A >= 0, B >= 0, A + B <= den (relative tolerance _EPS).
            for v in range(v0, v1 + 1):
                y = (v - cy) / fy
                den0 = y * tri[7] + tri[8]
                A0 = y * tri[1] + tri[2]
                B0 = y * tri[4] + tri[5]
                for u in range(u0, u1 + 1):
                    x = (u - cx) / fx
                    den = x * tri[6] + den0
                    A = x * tri[0] + A0
                    B = x * tri[3] + B0
                    tol = _EPS * den
                    if den <= 0.0 or A < -tol or B < -tol or A + B > den + tol:
                        continue
                    t = tri[9] / den
                    if t < depth[v, u] and t > 0.0:
                        depth[v, u] = t
                        tid[v, u] = i
                        w1s[v, u] = A / den
                        w2s[v, u] = B / den


@nb.njit(parallel=True, cache=True, nogil=True)
def shade(depth: np.ndarray, tid: np.ndarray, w1s: np.ndarray, w2s: np.ndarray,
          st0: np.ndarray, d1: np.ndarray, d2: np.ndarray, lambert: np.ndarray,
          tri_obj: np.ndarray, tri_face: np.ndarray, tile: np.ndarray, id_offset: int,
          img: np.ndarray, tc: np.ndarray, z32: np.ndarray, oid: np.ndarray, fid: np.ndarray,
          tid_all: np.ndarray) -> None:
    """
    Write the per-pixel outputs of the pixels a triangle won (``tid >= 0``), in place.

    (s, t) = st0 + w1 d1 + w2 d2 per triangle [texels]; intensity = bilinear wrap-around lookup
    of ``tile`` (square, power-of-two side) at (s, t) times the per-triangle factor ``lambert``.
    Outputs (left untouched where ``tid < 0``): intensity ``img`` (H, W) float32 in [0, 1],
    texcoords ``tc`` (H, W, 2) float32, depth ``z32`` (H, W) float32, object id ``oid`` int16,
    face id ``fid`` int32 and ``tid_all`` = tid + id_offset (index in the combined triangle
    list of all layers).
    """
    H, W = tid.shape
    mask = tile.shape[0] - 1
    for v in nb.prange(H):
        for u in range(W):
            i = tid[v, u]
            if i < 0:
                continue
            a = w1s[v, u]
            b = w2s[v, u]
            s = st0[i, 0] + a * d1[i, 0] + b * d2[i, 0]
            t = st0[i, 1] + a * d1[i, 1] + b * d2[i, 1]
            tc[v, u, 0] = s
            tc[v, u, 1] = t
            z32[v, u] = depth[v, u]
            oid[v, u] = tri_obj[i]
            fid[v, u] = tri_face[i]
            tid_all[v, u] = i + id_offset
            fs = np.floor(s)
            ft = np.floor(t)
            ax = np.float32(s - fs)
            ay = np.float32(t - ft)
            x0 = np.int64(fs) & mask
            y0 = np.int64(ft) & mask
            x1 = (x0 + 1) & mask
            y1 = (y0 + 1) & mask
            val = ((1 - ay) * ((1 - ax) * tile[y0, x0] + ax * tile[y0, x1])
                   + ay * ((1 - ax) * tile[y1, x0] + ax * tile[y1, x1]))
            img[v, u] = val * lambert[i]


@nb.njit(parallel=True, cache=True, nogil=True)
def occlusion_mask(depth_l: np.ndarray, tid_l: np.ndarray, tid_r: np.ndarray,
                   tris_r: np.ndarray, fx: float, fy: float, cx: float, cy: float,
                   baseline: float) -> np.ndarray:
    """
    Left foreground pixels whose surface point the right camera does not see.

    For a left pixel with depth Z the point projects to the right at (u - fx B / Z, v). It is
    occluded if that lies left of the right image (u_r < -0.5), if its own triangle faces away
    from the right camera, or if a triangle seen by the right image at either pixel bracketing
    u_r, intersected exactly with the right ray through (u_r, v), lies in front of it.
    """
    H, W = depth_l.shape
    occ = np.zeros((H, W), np.bool_)
    for v in nb.prange(H):
        y = (v - cy) / fy
        for u in range(W):
            own = tid_l[v, u]
            if own < 0:
                continue
            Z = depth_l[v, u]
            ur = u - fx * baseline / Z
            if ur < -0.5:
                occ[v, u] = True
                continue
            if tris_r[own, 10] == 0.0:
                # Back-facing for the right camera (or outside its view): not visible.
                occ[v, u] = True
                continue
            x = (ur - cx) / fx
            ua = int(np.floor(ur))
            for cu in range(ua, ua + 2):
                if cu < 0 or cu >= W:
                    continue
                c = tid_r[v, cu]
                if c < 0 or c == own:
                    continue
                t, a, b = _hit(tris_r[c], x, y)
                if t < Z * (1.0 - 1e-9):
                    occ[v, u] = True
    return occ


@nb.njit(parallel=True, cache=True, nogil=True)
def colorize(img: np.ndarray, oid: np.ndarray, palette: np.ndarray) -> np.ndarray:
    """RGB (H, W, 3) float32 = intensity (H, W) times ``palette[oid + 1]`` (row 0: background)."""
    H, W = img.shape
    out = np.empty((H, W, 3), np.float32)
    for v in nb.prange(H):
        for u in range(W):
            k = oid[v, u] + 1
            for c in range(3):
                out[v, u, c] = img[v, u] * palette[k, c]
    return out


@nb.njit(parallel=True, cache=True, nogil=True)
def quantize(img: np.ndarray, scale: float, noise: np.ndarray, offset: int,
             sigma: float) -> np.ndarray:
    """
    Quantise an image to uint8 with noise from a bank.

    uint8 image = clip(round(scale * img + sigma * noise[(offset + i) % len(noise)]), 0, 255)
    for the flat pixel/channel index i (``noise``: a bank of standard normal samples).
    """
    flat = np.ascontiguousarray(img).reshape(-1)
    out = np.empty(flat.size, np.uint8)
    n = noise.size
    contiguous = offset + flat.size <= n
    for i in nb.prange(flat.size):
        x = scale * flat[i]
        if sigma > 0.0:
            x += sigma * (noise[offset + i] if contiguous else noise[(offset + i) % n])
        x = np.floor(x + 0.5)
        out[i] = 0 if x < 0.0 else (255 if x > 255.0 else np.uint8(x))
    return out.reshape(img.shape)
