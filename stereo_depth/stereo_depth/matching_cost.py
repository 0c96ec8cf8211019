"""
Step 1 of the four-step stereo pipeline (chapter Sec. 2.1): matching cost computation.

Every function takes a rectified pair (left/right images of the same shape, epipolar lines are
image rows) and returns a cost volume ``C`` of shape ``(H, W, D)`` where ``C[y, x, d]`` is the
cost of matching left pixel ``(x, y)`` with right pixel ``(x - d, y)``; ``D = max_disparity``
candidates ``d = 0 .. D-1`` (pixels). Lower is better. Candidates that fall outside the right
image (``x - d < 0``) get the largest cost the measure can produce, so that they never win
unless nothing else is available.

Costs that feed the integer optimisers (SGM, BP) are ``uint8``: census (Hamming distance),
absolute difference and quantised ZNCC.
"""

from __future__ import annotations

import numba
from numba import types
from numba.extending import intrinsic
import numpy as np

__all__ = [
    'to_gray',
    'census_transform',
    'census_planes',
    'census_cost',
    'absolute_difference_cost',
    'zncc_cost',
    'quantize_cost',
    'check_pair',
]


def check_pair(left: np.ndarray, right: np.ndarray, max_disparity: int) -> None:
    """
    Raise ValueError naming the problem if the pair or the disparity range is unusable.

    :param left: left image, (H, W) or (H, W, 3).
    :param right: right image, same shape as ``left``.
    :param max_disparity: number of disparity candidates, 1 <= D <= W.
    """
    left = np.asarray(left)
    right = np.asarray(right)
    if left.ndim not in (2, 3) or (left.ndim == 3 and left.shape[2] not in (1, 3)):
        raise ValueError(f'left image must be (H, W) or (H, W, 3), got shape {left.shape}')
    if left.shape != right.shape:
        raise ValueError(f'left and right images differ in shape: {left.shape} vs {right.shape}')
    if int(max_disparity) < 1 or int(max_disparity) > left.shape[1]:
        raise ValueError(
            f'max_disparity must be in [1, image width {left.shape[1]}], got {max_disparity}')


def to_gray(image: np.ndarray) -> np.ndarray:
    """
    Return a float32 (H, W) intensity image (ITU-R 601 luma for RGB input, 0..255 scale).

    :param image: (H, W), (H, W, 1) or (H, W, 3) RGB image of any real dtype.
    """
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim == 2:
        return img.astype(np.float32, copy=False)
    if img.ndim == 3 and img.shape[2] == 3:
        f = img.astype(np.float32)
        return 0.299 * f[:, :, 0] + 0.587 * f[:, :, 1] + 0.114 * f[:, :, 2]
    raise ValueError(f'expected an (H, W) or (H, W, 3) image, got shape {img.shape}')


@numba.njit(cache=True, parallel=True, nogil=True, fastmath=True, boundscheck=False)
def _census_kernel(padded, h, w, hw, hh):
    # padded: (h + 2 hh, w + 2 hw) replicate-padded image. Bits are appended in raster order of
    # the window (row-major, centre skipped); the loop over x vectorises.
    out = np.empty((h, w), dtype=np.uint64)
    for y in numba.prange(h):
        code = np.zeros(w, np.uint64)
        centre = padded[y + hh, hw:hw + w]
        for dy in range(2 * hh + 1):
            row = padded[y + dy]
            for dx in range(2 * hw + 1):
                if dy == hh and dx == hw:
                    continue
                for x in range(w):
                    code[x] = (code[x] << np.uint64(1)) | np.uint64(row[x + dx] < centre[x])
        out[y] = code
    return out


def census_transform(image: np.ndarray, window: tuple[int, int] = (9, 7)) -> np.ndarray:
    """
    Census transform (Zabih & Woodfill 1994): one bit per neighbour, ``neighbour < centre``.

    Borders are replicated. At most 64 bits: ``window_w * window_h - 1 <= 64``.

    :param image: (H, W) or (H, W, 3) image.
    :param window: odd (width, height) of the census window in pixels.
    :return: (H, W) uint64 bit strings.
    """
    ww, wh = int(window[0]), int(window[1])
    if ww < 1 or wh < 1 or ww % 2 == 0 or wh % 2 == 0:
        raise ValueError(f'census window must be odd and positive, got {window}')
    if ww * wh - 1 > 64:
        raise ValueError(f'census window {window} needs {ww * wh - 1} bits, at most 64 fit')
    import cv2

    gray = to_gray(image)
    h, w = gray.shape
    padded = cv2.copyMakeBorder(gray, wh // 2, wh // 2, ww // 2, ww // 2, cv2.BORDER_REPLICATE)
    return _census_kernel(padded, h, w, ww // 2, wh // 2)


@numba.njit(cache=True, nogil=True, fastmath=True, boundscheck=False)
def _census_planes_kernel(padded, h, w, hw, hh, nbits, out):
    # Bit k of the census code (raster order of the window, centre skipped; the first neighbour
    # is the highest bit, as _census_kernel) goes to plane (nbits - 1 - k) // 8. The loop over
    # x compares in the image's own type (uint8: 32 lanes per AVX2 instruction).
    for y in range(h):
        centre = padded[y + hh, hw:hw + w]
        k = 0
        for dy in range(2 * hh + 1):
            for dx in range(2 * hw + 1):
                if dy == hh and dx == hw:
                    continue
                bit = nbits - 1 - k
                o = out[bit // 8, y]
                bv = np.uint8(1 << (bit % 8))
                row = padded[y + dy, dx:dx + w]
                for x in range(w):
                    # a select, not a shifted bool: numba widens the latter to 64 bits
                    o[x] = np.uint8(o[x] | bv) if row[x] < centre[x] else o[x]
                k += 1
    return out


def census_planes(image: np.ndarray, window: tuple[int, int] = (5, 5)) -> np.ndarray:
    """
    Return the census codes of :func:`census_transform` as byte planes (plane p: bits 8p..8p+7).

    ``planes[p] == (census_transform(image, window) >> 8 p) & 255`` for every p; the Hamming
    distance of two codes is the sum over the planes of the byte popcounts, which vectorise
    32 lanes wide (AVX2), against 8 lanes for 32-bit codes. uint8 images are compared as
    they are (the same comparisons as their float32 grey values), others through
    :func:`to_gray`.

    :param image: (H, W) or (H, W, 3) image.
    :param window: odd (width, height) of the census window in pixels (at most 64 bits).
    :return: (ceil(bits / 8), H, W) uint8, C-contiguous.
    """
    ww, wh = int(window[0]), int(window[1])
    if ww < 1 or wh < 1 or ww % 2 == 0 or wh % 2 == 0:
        raise ValueError(f'census window must be odd and positive, got {window}')
    nbits = ww * wh - 1
    if nbits > 64:
        raise ValueError(f'census window {window} needs {nbits} bits, at most 64 fit')
    import cv2

    img = np.asarray(image)
    gray = img if img.ndim == 2 and img.dtype == np.uint8 else to_gray(img)
    h, w = gray.shape
    padded = cv2.copyMakeBorder(np.ascontiguousarray(gray), wh // 2, wh // 2, ww // 2, ww // 2,
                                cv2.BORDER_REPLICATE)
    out = np.zeros((max(1, (nbits + 7) // 8), h, w), np.uint8)
    return _census_planes_kernel(padded, h, w, ww // 2, wh // 2, nbits, out)


@intrinsic
def _popcount8(typingctx, value):
    # popcount of the low byte of ``value`` as uint8: LLVM's ctpop on i8 vectorises to the
    # nibble-table VPSHUFB sequence, 32 lanes per AVX2 instruction.
    if not isinstance(value, types.Integer):
        return None
    sig = types.uint8(value)

    def codegen(context, builder, signature, args):
        v = args[0]
        ty = context.get_value_type(types.uint8)
        if v.type.width > 8:
            v = builder.trunc(v, ty)
        return builder.ctpop(v)

    return sig, codegen


@intrinsic
def _popcount64(typingctx, value):
    # LLVM's ctpop: a single POPCNT (or a vector VPOPCNTQ) instruction.
    if not isinstance(value, types.Integer):
        return None
    sig = types.uint64(types.uint64)

    def codegen(context, builder, signature, args):
        return builder.ctpop(args[0])

    return sig, codegen


@intrinsic
def _popcount_like(typingctx, value, like):
    # popcount of ``value`` at the width of ``like``'s type (uint32 or uint64): numba widens
    # uint32 ^ uint32 to 64 bits, and a 64-bit popcount does not vectorise on AVX2, a 32-bit
    # one does (census codes of at most 32 bits: 5x5 windows).
    if not isinstance(value, types.Integer) or not isinstance(like, types.Integer):
        return None
    sig = like(value, like)

    def codegen(context, builder, signature, args):
        v = args[0]
        ty = context.get_value_type(signature.return_type)
        if v.type.width > ty.width:
            v = builder.trunc(v, ty)
        elif v.type.width < ty.width:
            v = builder.zext(v, ty)
        return builder.ctpop(v)

    return sig, codegen


@numba.njit(cache=True, parallel=True, nogil=True, fastmath=True, boundscheck=False)
def _hamming_volume(cl, cr, ndisp, invalid):
    h, w = cl.shape
    out = np.empty((h, w, ndisp), dtype=np.uint8)
    for y in numba.prange(h):
        crr = np.empty(w, cr.dtype)
        _reverse_row(cr[y], crr)
        _hamming_row(cl[y], crr, ndisp, invalid, out[y])
    return out


def census_cost(left: np.ndarray, right: np.ndarray, max_disparity: int,
                window: tuple[int, int] = (9, 7)) -> np.ndarray:
    """
    Census matching cost: Hamming distance between census codes of left and right pixels.

    Robust to gain/offset differences between the cameras; the usual partner of SGM.

    :param left: left rectified image, (H, W) or (H, W, 3).
    :param right: right rectified image, same shape.
    :param max_disparity: number D of disparity candidates (pixels, 0..D-1).
    :param window: odd (width, height) of the census window.
    :return: (H, W, D) uint8 costs in [0, window_w * window_h - 1].
    """
    check_pair(left, right, max_disparity)
    cl = census_transform(left, window)
    cr = census_transform(right, window)
    nbits = int(window[0]) * int(window[1]) - 1
    return _hamming_volume(cl, cr, int(max_disparity), np.uint8(nbits))


@numba.njit(cache=True, parallel=True, nogil=True)
def _ad_volume(gl, gr, ndisp, trunc):
    h, w = gl.shape
    out = np.empty((h, w, ndisp), dtype=np.uint8)
    for y in numba.prange(h):
        for x in range(w):
            a = gl[y, x]
            dmax = min(ndisp, x + 1)
            for d in range(dmax):
                out[y, x, d] = np.uint8(min(abs(a - gr[y, x - d]), trunc) + np.float32(0.5))
            for d in range(dmax, ndisp):
                out[y, x, d] = np.uint8(trunc + np.float32(0.5))
    return out


@numba.njit(cache=True, parallel=True, nogil=True)
def _bt_volume(gl, gr, ndisp, trunc):
    # Birchfield-Tomasi: distance of a pixel to the linearly interpolated half-pixel
    # neighbourhood of its partner, symmetrised.
    h, w = gl.shape
    out = np.empty((h, w, ndisp), dtype=np.uint8)
    for y in numba.prange(h):
        lmin = np.empty(w, np.float32)
        lmax = np.empty(w, np.float32)
        rmin = np.empty(w, np.float32)
        rmax = np.empty(w, np.float32)
        for x in range(w):
            a = gl[y, x]
            al = 0.5 * (a + gl[y, max(x - 1, 0)])
            ar = 0.5 * (a + gl[y, min(x + 1, w - 1)])
            lmin[x] = min(a, al, ar)
            lmax[x] = max(a, al, ar)
            b = gr[y, x]
            bl = 0.5 * (b + gr[y, max(x - 1, 0)])
            br = 0.5 * (b + gr[y, min(x + 1, w - 1)])
            rmin[x] = min(b, bl, br)
            rmax[x] = max(b, bl, br)
        for x in range(w):
            a = gl[y, x]
            dmax = min(ndisp, x + 1)
            for d in range(dmax):
                xr = x - d
                b = gr[y, xr]
                c1 = max(np.float32(0.0), a - rmax[xr], rmin[xr] - a)
                c2 = max(np.float32(0.0), b - lmax[x], lmin[x] - b)
                out[y, x, d] = np.uint8(min(min(c1, c2), trunc) + np.float32(0.5))
            for d in range(dmax, ndisp):
                out[y, x, d] = np.uint8(trunc + np.float32(0.5))
    return out


def absolute_difference_cost(left: np.ndarray, right: np.ndarray, max_disparity: int,
                             truncation: float = 255.0,
                             birchfield_tomasi: bool = False) -> np.ndarray:
    """
    Absolute intensity difference ``min(|I_L(x, y) - I_R(x - d, y)|, truncation)``.

    :param left: left rectified image, (H, W) or (H, W, 3) (colour is converted to luma).
    :param right: right rectified image, same shape.
    :param max_disparity: number D of disparity candidates.
    :param truncation: upper bound of the cost (intensity levels, <= 255).
    :param birchfield_tomasi: use the sampling-insensitive measure of Birchfield & Tomasi 1998.
    :return: (H, W, D) uint8 costs.
    """
    check_pair(left, right, max_disparity)
    if not 0.0 < truncation <= 255.0:
        raise ValueError(f'truncation must be in (0, 255], got {truncation}')
    gl, gr = to_gray(left), to_gray(right)
    kernel = _bt_volume if birchfield_tomasi else _ad_volume
    return kernel(gl, gr, int(max_disparity), np.float32(truncation))


def zncc_cost(left: np.ndarray, right: np.ndarray, max_disparity: int,
              window: tuple[int, int] = (7, 7)) -> np.ndarray:
    """
    Zero-mean normalised cross-correlation cost ``1 - ZNCC`` over a window, in [0, 2].

    Window sums use OpenCV box filters (the aggregation is part of the measure here).
    Textureless windows (zero variance) get cost 1 (uncorrelated).

    :param left: left rectified image, (H, W) or (H, W, 3).
    :param right: right rectified image, same shape.
    :param max_disparity: number D of disparity candidates.
    :param window: odd (width, height) of the correlation window.
    :return: (H, W, D) float32 costs; 2 for candidates outside the right image.
    """
    import cv2

    check_pair(left, right, max_disparity)
    ww, wh = int(window[0]), int(window[1])
    if ww < 1 or wh < 1 or ww % 2 == 0 or wh % 2 == 0:
        raise ValueError(f'zncc window must be odd and positive, got {window}')
    gl = to_gray(left).astype(np.float64)
    gr = to_gray(right).astype(np.float64)
    h, w = gl.shape
    ndisp = int(max_disparity)

    def box(a):
        return cv2.boxFilter(a, -1, (ww, wh), normalize=True, borderType=cv2.BORDER_REFLECT)

    ml, mr = box(gl), box(gr)
    vl = np.maximum(box(gl * gl) - ml * ml, 0.0)
    vr = np.maximum(box(gr * gr) - mr * mr, 0.0)
    out = np.full((h, w, ndisp), 2.0, dtype=np.float32)
    eps = 1e-6
    for d in range(ndisp):
        shifted = np.empty_like(gr)
        shifted[:, d:] = gr[:, :w - d]
        shifted[:, :d] = gr[:, :1]
        mrs = np.empty_like(mr)
        mrs[:, d:] = mr[:, :w - d]
        mrs[:, :d] = mr[:, :1]
        vrs = np.empty_like(vr)
        vrs[:, d:] = vr[:, :w - d]
        vrs[:, :d] = vr[:, :1]
        cov = box(gl * shifted) - ml * mrs
        den = np.sqrt(vl * vrs)
        zncc = np.where(den > eps, cov / np.maximum(den, eps), 0.0)
        out[:, d:, d] = (1.0 - np.clip(zncc[:, d:], -1.0, 1.0)).astype(np.float32)
    return out


def quantize_cost(cost: np.ndarray, scale: float) -> np.ndarray:
    """
    Scale a real-valued cost volume to uint8 (``round(cost * scale)`` clipped to 255).

    The integer optimisers (SGM, BP) take uint8 volumes; use this for ZNCC (``scale`` ~ 30).

    :param cost: (H, W, D) real costs, non-negative.
    :param scale: factor applied before rounding.
    """
    if scale <= 0:
        raise ValueError(f'scale must be positive, got {scale}')
    return np.clip(np.rint(np.asarray(cost, dtype=np.float32) * scale), 0, 255).astype(np.uint8)


@numba.njit(inline='always', fastmath=True, boundscheck=False)
def _reverse_row(row, out):
    w = row.shape[0]
    for k in range(w):
        out[k] = row[w - 1 - k]


@numba.njit(inline='always', fastmath=True, boundscheck=False)
def _hamming_row(cl_row, cr_reversed, ndisp, invalid, out):
    # out[x, d] = popcount(cl[x] ^ cr[x - d]); the right row is given reversed so that the
    # candidates of one pixel are a forward slice (the loop then vectorises, VPOPCNTQ).
    w = cl_row.shape[0]
    for x in range(w):
        a = cl_row[x]
        k0 = w - 1 - x
        n = min(ndisp, x + 1)
        src = cr_reversed[k0:k0 + n]
        o = out[x]
        for d in range(n):
            o[d] = np.uint8(_popcount_like(a ^ src[d], a))
        for d in range(n, ndisp):
            o[d] = invalid
