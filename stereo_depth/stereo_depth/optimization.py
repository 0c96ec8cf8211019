"""
Step 3 of the four-step stereo pipeline (chapter Sec. 2.1): disparity computation.

Cost volumes are ``(H, W, D)`` arrays, ``C[y, x, d]`` the cost of disparity ``d`` (pixels) at left
pixel ``(x, y)``. Three optimisers:

* :func:`winner_take_all` - the local method: the lowest (aggregated) cost per pixel.
* :func:`semi_global_matching` - Hirschmueller's SGM: Eq. 1 approximated by 1-D dynamic
  programming along 4 or 8 image directions, smoothness ``P1`` for a 1-pixel disparity change
  and ``P2`` for larger jumps.
* :func:`belief_propagation` - hierarchical min-sum loopy belief propagation of Felzenszwalb &
  Huttenlocher (2006) on the 4-connected grid, minimising Eq. 1 with the truncated-linear
  smoothness ``C2(d_i, d_j) = min(lambda * |d_i - d_j|, tau)``; :func:`stereo_energy` evaluates
  that energy for a labelling.

The hot loops are numba-compiled with ``cache=True`` (the first call in a fresh environment
compiles, later processes load the cache).
"""

from __future__ import annotations

import threading
from typing import Callable, Optional

import numba
import numpy as np

from stereo_depth.matching_cost import _popcount8, census_planes, to_gray

__all__ = [
    'winner_take_all',
    'winner_take_all_both',
    'census_block_matching',
    'semi_global_matching',
    'sgm_disparities',
    'belief_propagation',
    'stereo_energy',
]

_U16_MAX = 65535
_U16 = np.uint16


# --------------------------------------------------------------------------------------------
# Winner-take-all
# --------------------------------------------------------------------------------------------

def winner_take_all(cost: np.ndarray) -> np.ndarray:
    """
    Lowest-cost disparity per pixel (ties go to the smaller disparity).

    :param cost: (H, W, D) cost volume.
    :return: (H, W) int32 disparities in [0, D-1] (pixels).
    """
    cost = np.asarray(cost)
    if cost.ndim != 3 or cost.shape[2] < 1:
        raise ValueError(f'cost volume must be (H, W, D) with D >= 1, got shape {cost.shape}')
    return np.argmin(cost, axis=2).astype(np.int32)


# --------------------------------------------------------------------------------------------
# Semi-global matching
# --------------------------------------------------------------------------------------------

@numba.njit(inline='always', fastmath=True, boundscheck=False)
def _path_update(c, prev, pmin, cur, acc, p1, p2, init=False):
    # Hirschmueller 2008, Eq. 13: L(p, d) = C(p, d) + min(L(p-r, d), L(p-r, d+-1) + P1,
    # min_k L(p-r, k) + P2) - min_k L(p-r, k). Written branch-free so that LLVM vectorises it.
    # Every sum is cast back to uint16 at once: numba widens small-integer arithmetic to 64
    # bits, and the casts let LLVM narrow it again to 32 x 16-bit SIMD lanes. init (a constant
    # at each call site): write the path cost to acc instead of adding it.
    nd = c.shape[0]
    mp = _U16(pmin + p2)
    if nd == 1:
        cur[0] = c[0]
        acc[0] = cur[0] if init else _U16(acc[0] + cur[0])
        return cur[0]
    v = min(prev[0], _U16(prev[1] + p1), mp)
    cur[0] = _U16(_U16(c[0]) + _U16(v - pmin))
    for d in range(1, nd - 1):
        m = _U16(min(prev[d - 1], prev[d + 1]) + p1)
        v = min(prev[d], m, mp)
        cur[d] = _U16(_U16(c[d]) + _U16(v - pmin))
    v = min(prev[nd - 1], _U16(prev[nd - 2] + p1), mp)
    cur[nd - 1] = _U16(_U16(c[nd - 1]) + _U16(v - pmin))
    best = cur[0]
    for d in range(nd):
        val = cur[d]
        acc[d] = val if init else _U16(acc[d] + val)
        best = min(best, val)
    return best


@numba.njit(inline='always', fastmath=True, boundscheck=False)
def _path_start(c, cur, acc, init=False):
    for d in range(c.shape[0]):
        cur[d] = c[d]
        acc[d] = c[d] if init else _U16(acc[d] + c[d])
    best = cur[0]
    for d in range(c.shape[0]):
        best = min(best, cur[d])
    return best


@numba.njit(cache=True, nogil=True, fastmath=True, boundscheck=False)
def _sgm_half(cost, p1, p2, acc, reverse, eight, p2map, adaptive):
    # One raster sweep accumulating half of the paths into acc (uint16): the forward sweep
    # (rows top-down) runs the left-to-right path and the paths arriving from the row above
    # (up, and with eight paths up-left and up-right); the reverse sweep mirrors them. Each row
    # is processed direction by direction so that its cost and sum rows stay in cache; the
    # vertical paths keep the previous row's path costs in row buffers.
    # adaptive: intensity-adaptive P2 (Hirschmueller 2008, Sec. 3.1) from p2map, see
    # _adaptive_p2_maps.
    h, w, nd = cost.shape
    p1 = _U16(p1)
    p2 = _U16(p2)
    ndir = 3 if eight else 1
    prev = np.zeros((ndir, w, nd), np.uint16)
    cur = np.zeros((ndir, w, nd), np.uint16)
    pmin = np.zeros((ndir, w), np.uint16)
    cmin = np.zeros((ndir, w), np.uint16)
    hbuf = np.zeros((2, nd), np.uint16)
    for yi in range(h):
        y = h - 1 - yi if reverse else yi
        crow = cost[y]
        arow = acc[y]
        if reverse:
            hm = _path_start(crow[w - 1], hbuf[0], arow[w - 1], True)
            for i in range(1, w):
                x = w - 1 - i
                q2 = p2map[0, y, x + 1] if adaptive else p2
                hm = _path_update(crow[x], hbuf[(i - 1) & 1], hm, hbuf[i & 1], arow[x], p1,
                                  q2, True)
        else:
            hm = _path_start(crow[0], hbuf[0], arow[0], True)
            for x in range(1, w):
                q2 = p2map[0, y, x] if adaptive else p2
                hm = _path_update(crow[x], hbuf[(x - 1) & 1], hm, hbuf[x & 1], arow[x], p1,
                                  q2, True)
        for k in range(ndir):
            pk = prev[k]
            ck = cur[k]
            pmk = pmin[k]
            cmk = cmin[k]
            if yi == 0:
                for x in range(w):
                    cmk[x] = _path_start(crow[x], ck[x], arow[x])
                continue
            if k == 0:
                off = 0
            elif k == 1:
                off = 1 if reverse else -1
            else:
                off = -1 if reverse else 1
            x0 = 0
            x1 = w
            if off == -1:
                cmk[0] = _path_start(crow[0], ck[0], arow[0])
                x0 = 1
            elif off == 1:
                cmk[w - 1] = _path_start(crow[w - 1], ck[w - 1], arow[w - 1])
                x1 = w - 1
            py = y + 1 if reverse else y - 1
            for x in range(x0, x1):
                if adaptive:
                    q2 = p2map[k + 1, py, x + off] if reverse else p2map[k + 1, y, x]
                else:
                    q2 = p2
                cmk[x] = _path_update(crow[x], pk[x + off], pmk[x + off], ck[x], arow[x], p1, q2)
        prev, cur = cur, prev
        pmin, cmin = cmin, pmin
    return acc


@numba.njit(cache=True, parallel=True, nogil=True)
def _sgm_both(cost, p1, p2, eight, p2map, adaptive, accs):
    # accs: (2, H, W, D) uint16 output, any content: each sweep's first path (the horizontal
    # one) writes acc, the others add to it.
    for i in numba.prange(2):
        _sgm_half(cost, p1, p2, accs[i], i == 1, eight, p2map, adaptive)
    return accs


_SCRATCH = threading.local()


def _path_sum_buffers(shape: tuple) -> np.ndarray:
    """
    (2, H, W, D) uint16 scratch for the two sweeps' path sums, kept per thread.

    The buffers are tens of MB: allocating them per frame costs a page fault per 4 KiB page
    (several ms per frame), so each thread keeps its last one for the next frame of the same
    size. Only for results that do not escape (sgm_disparities).
    """
    buf = getattr(_SCRATCH, 'accs', None)
    if buf is None or buf.shape != (2,) + tuple(shape):
        _SCRATCH.accs = None     # release the old one first
        buf = np.empty((2,) + tuple(shape), np.uint16)
        _SCRATCH.accs = buf
    return buf


def _check_sgm_args(cost, p1, p2, paths):
    cost = np.asarray(cost)
    if cost.ndim != 3:
        raise ValueError(f'cost volume must be (H, W, D), got shape {cost.shape}')
    if cost.dtype != np.uint8:
        raise ValueError(f'SGM takes a uint8 cost volume (see quantize_cost), got {cost.dtype}')
    if paths not in (4, 8):
        raise ValueError(f'SGM paths must be 4 or 8, got {paths}')
    if not (0 <= p1 <= p2):
        raise ValueError(f'SGM penalties must satisfy 0 <= P1 <= P2, got P1={p1}, P2={p2}')
    if paths * (255 + int(p2)) > _U16_MAX:
        raise ValueError(f'P2={p2} too large for 16-bit path sums with {paths} paths')
    return np.ascontiguousarray(cost)


# Path step types of the P2 maps: the step from (y - dy, x - dx) to (y, x) of type t uses
# p2map[t, y, x]; the opposite step uses p2map[t, y - dy, x - dx]. The kernel's vertical
# buffers k = 0, 1, 2 are the types 1, 2, 3.
_P2_STEPS = ((0, 1), (1, 0), (1, 1), (1, -1))


def _adaptive_p2_maps(cost, image, p1, p2, gamma, paths=8):
    """
    (4, H, W) uint16 P2 per path step (see _P2_STEPS), or a dummy when gamma == 0.

    With 4 paths only the horizontal and vertical maps (types 0 and 1) are filled.

    The step between neighbours q and p costs ``max(P1, P2 * gamma / (gamma + |I(p) - I(q)|))``
    for a larger disparity jump (Hirschmueller 2008, Sec. 3.1): an intensity edge is where a
    depth edge is likely, so a jump there is cheaper; in uniform regions the full P2 keeps the
    surface smooth.
    """
    if gamma < 0:
        raise ValueError(f'adaptive P2 gamma must be >= 0 (0 = constant P2), got {gamma}')
    if gamma == 0:
        return np.zeros((4, 1, 1), np.uint16)
    if image is None:
        raise ValueError('adaptive P2 (gamma > 0) needs the left image')
    img = to_gray(image)
    h, w = cost.shape[:2]
    if img.shape != (h, w):
        raise ValueError(f'image {img.shape} does not match the cost volume {(h, w)}')
    maps = np.empty((4 if paths == 8 else 2, h, w), np.uint16)
    g = np.float32(gamma)
    for t, (dy, dx) in enumerate(_P2_STEPS[:maps.shape[0]]):
        # pixels without a predecessor of this type (first row / column) keep P2
        maps[t, :dy, :] = p2
        if dx > 0:
            maps[t, :, :dx] = p2
        elif dx < 0:
            maps[t, :, w + dx:] = p2
        ys = slice(dy, h)
        xs = slice(dx, w) if dx >= 0 else slice(0, w + dx)
        qs = slice(0, w - dx) if dx >= 0 else slice(-dx, w)
        di = np.abs(img[ys, xs] - img[0:h - dy, qs])
        q = np.maximum(np.float32(p1), np.float32(p2) * g / (g + di))
        maps[t, ys, xs] = np.rint(q).astype(np.uint16)
    return maps


def semi_global_matching(cost: np.ndarray, p1: int = 7, p2: int = 100, paths: int = 8,
                         image: Optional[np.ndarray] = None,
                         gamma: float = 0.0) -> np.ndarray:
    """
    Aggregate a cost volume along 4 or 8 directions (semi-global matching).

    :param cost: (H, W, D) uint8 cost volume.
    :param p1: penalty for a disparity change of one pixel between neighbours.
    :param p2: penalty for larger changes (P2 >= P1).
    :param paths: 4 (horizontal + vertical) or 8 (plus diagonals).
    :param image: the left image (H, W) or (H, W, 3); needed only when ``gamma > 0``.
    :param gamma: intensity-adaptive P2 (Hirschmueller 2008, Sec. 3.1): the step from pixel
        q to p along a path uses ``max(P1, P2 * gamma / (gamma + |I(p) - I(q)|))`` (intensity
        units of 0..255), so depth jumps are cheaper at intensity edges; 0 keeps P2 constant.
    :return: (H, W, D) uint16 summed path costs ``S``; ``argmin_d S`` is the SGM disparity.
    """
    cost = _check_sgm_args(cost, p1, p2, paths)
    maps = _adaptive_p2_maps(cost, image, int(p1), int(p2), float(gamma), paths)
    accs = _sgm_both(cost, int(p1), int(p2), paths == 8, maps, gamma > 0,
                     np.empty((2,) + cost.shape, np.uint16))
    return accs[0] + accs[1]


@numba.njit(inline='always', fastmath=True, boundscheck=False)
def _wta_pixel(s, x, w, rmin_rev, rarg_rev, uniqueness, packed):
    # Left disparity (parabola subpixel, NaN if not unique) of one pixel's cost vector s, and
    # the running right-view minimum: right pixel x - d sees cost s[d] at disparity d. The
    # right buffers are indexed reversed (k = w - 1 - xr) so that the update is a forward,
    # vectorisable slice. packed: integer costs < 2^24 and at most 256 disparities.
    nd = s.shape[0]
    if packed:
        # (cost << 8 | d): one vectorised minimum gives the cost and its smallest index
        pk = np.uint32(0xFFFFFFFF)
        for d in range(nd):
            pk = min(pk, (np.uint32(s[d]) << np.uint32(8)) | np.uint32(d))
        bd = np.int64(pk & np.uint32(255))
        best = s[bd]
    else:
        best = s[0]
        for d in range(1, nd):
            best = min(best, s[d])
        bd = np.int64(0)
        while s[bd] != best:
            bd += 1
    k0 = w - 1 - x
    n = min(nd, x + 1)
    rm = rmin_rev[k0:k0 + n]
    ra = rarg_rev[k0:k0 + n]
    for d in range(n):
        v = s[d]
        m = rm[d]
        ra[d] = np.int32(d) if v < m else ra[d]
        rm[d] = min(v, m)
    if uniqueness > 0.0:
        second = best
        found = False
        for d in range(nd):
            if d < bd - 1 or d > bd + 1:
                if not found or s[d] < second:
                    second = s[d]
                    found = True
        if found and best * (1.0 + uniqueness) > second:
            return np.float32(np.nan)
    if 0 < bd < nd - 1:
        cm = np.float32(s[bd - 1])
        cp = np.float32(s[bd + 1])
        den = cm - np.float32(2.0) * np.float32(best) + cp
        if den > 0:
            return np.float32(bd + 0.5 * (cm - cp) / den)
    return np.float32(bd)


@numba.njit(inline='always', boundscheck=False)
def _right_row(rarg_rev, out_row):
    w = out_row.shape[0]
    for xr in range(w):
        a = rarg_rev[w - 1 - xr]
        out_row[xr] = np.float32(a) if a >= 0 else np.float32(np.nan)


@numba.njit(cache=True, parallel=True, nogil=True, fastmath=True, boundscheck=False)
def _wta_two(acc_a, acc_b, uniqueness):
    # S = acc_a + acc_b fits in uint16 (checked by the caller).
    h, w, nd = acc_a.shape
    dl = np.empty((h, w), np.float32)
    dr = np.empty((h, w), np.float32)
    for y in numba.prange(h):
        s = np.empty(nd, np.uint16)
        rmin = np.full(w, _U16_MAX, np.uint16)
        rarg = np.full(w, -1, np.int32)
        for x in range(w):
            aa = acc_a[y, x]
            bb = acc_b[y, x]
            for d in range(nd):
                s[d] = _U16(aa[d] + bb[d])
            dl[y, x] = _wta_pixel(s, x, w, rmin, rarg, uniqueness, nd <= 256)
        _right_row(rarg, dr[y])
    return dl, dr


@numba.njit(cache=True, parallel=True, nogil=True, fastmath=True, boundscheck=False)
def _wta_one(cost, uniqueness, big, packed):
    h, w, nd = cost.shape
    dl = np.empty((h, w), np.float32)
    dr = np.empty((h, w), np.float32)
    for y in numba.prange(h):
        rmin = np.full(w, big, cost.dtype)
        rarg = np.full(w, -1, np.int32)
        for x in range(w):
            dl[y, x] = _wta_pixel(cost[y, x], x, w, rmin, rarg, uniqueness, packed)
        _right_row(rarg, dr[y])
    return dl, dr


def winner_take_all_both(cost: np.ndarray,
                         uniqueness: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """
    Winner-take-all for both views from the left view's cost volume, in one pass.

    :param cost: (H, W, D) cost volume (uint8, uint16 or float32).
    :param uniqueness: reject (NaN) a pixel whose best cost times ``1 + uniqueness`` exceeds the
        best cost outside ``best +- 1``; 0 disables the test.
    :return: ``(disp_left, disp_right)`` (H, W) float32 pixels: left disparities with parabola
        subpixel refinement, integer right-view disparities ``argmin_d C(y, xr + d, d)``.
    """
    cost = np.ascontiguousarray(cost)
    if cost.ndim != 3 or cost.shape[2] < 1:
        raise ValueError(f'cost volume must be (H, W, D) with D >= 1, got shape {cost.shape}')
    if uniqueness < 0:
        raise ValueError(f'uniqueness must be >= 0, got {uniqueness}')
    if cost.dtype == np.float64:
        cost = cost.astype(np.float32)
    big = (np.finfo(cost.dtype).max if np.issubdtype(cost.dtype, np.floating)
           else np.iinfo(cost.dtype).max)
    packed = bool(np.issubdtype(cost.dtype, np.integer) and cost.dtype.itemsize <= 2
                  and cost.shape[2] <= 256)
    return _wta_one(cost, float(uniqueness), cost.dtype.type(big), packed)


def sgm_disparities(cost: np.ndarray, p1: int = 7, p2: int = 100, paths: int = 8,
                    uniqueness: float = 0.0, image: Optional[np.ndarray] = None,
                    gamma: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """
    SGM followed by winner-take-all for both views, fused for speed.

    :param cost: (H, W, D) uint8 cost volume of the left view.
    :param p1: small-jump penalty.
    :param p2: large-jump penalty.
    :param paths: 4 or 8.
    :param uniqueness: reject a pixel (NaN) whose best sum is not lower than ``1 + uniqueness``
        times the best sum outside ``best +- 1``; 0 disables the test.
    :param image: the left image, needed only when ``gamma > 0``.
    :param gamma: intensity-adaptive P2, see :func:`semi_global_matching`; 0 = constant P2.
    :return: ``(disp_left, disp_right)``, (H, W) float32 in pixels: the left disparity with
        parabola subpixel refinement (NaN where not unique), and the integer right-view
        disparity (``x_left = x_right + d``) for the left-right check.
    """
    cost = _check_sgm_args(cost, p1, p2, paths)
    if uniqueness < 0:
        raise ValueError(f'uniqueness must be >= 0, got {uniqueness}')
    maps = _adaptive_p2_maps(cost, image, int(p1), int(p2), float(gamma), paths)
    accs = _sgm_both(cost, int(p1), int(p2), paths == 8, maps, gamma > 0,
                     _path_sum_buffers(cost.shape))
    return _wta_two(accs[0], accs[1], float(uniqueness))


# --------------------------------------------------------------------------------------------
# Belief propagation (Felzenszwalb & Huttenlocher 2006)
# --------------------------------------------------------------------------------------------

@numba.njit(inline='always', fastmath=True)
def _bp_message(h, out, lam, tau):
    # m(d) = min_d' ( h(d') + min(lam |d - d'|, tau) ), by the two-pass distance transform of
    # the truncated linear model (FH 2006, Sec. 2.1), then normalised to zero mean.
    nd = h.shape[0]
    for d in range(nd):
        out[d] = h[d]
    for d in range(1, nd):
        out[d] = min(out[d], out[d - 1] + lam)
    for d in range(nd - 2, -1, -1):
        out[d] = min(out[d], out[d + 1] + lam)
    mn = h[0]
    for d in range(1, nd):
        mn = min(mn, h[d])
    mn = mn + tau
    s = 0.0
    for d in range(nd):
        out[d] = min(out[d], mn)
        s += out[d]
    s /= nd
    for d in range(nd):
        out[d] -= s


@numba.njit(inline='always', fastmath=True)
def _bp_row(data, mu, md, ml, mr, lam, tau, parity, y, hb, out):
    # One checkerboard half-update of row y. mu[y, x] is the message pixel (x, y) received
    # from its upper neighbour, md from below, ml from the left, mr from the right. Pixels of
    # one colour only read messages sent to them and write messages to the other colour, each
    # to a distinct slot, so rows can be updated in parallel.
    h, w, nd = data.shape
    x0 = (y + parity) & 1
    for x in range(x0, w, 2):
        if y > 0:
            for d in range(nd):
                hb[d] = data[y, x, d] + mu[y, x, d] + ml[y, x, d] + mr[y, x, d]
            _bp_message(hb, out, lam, tau)
            md[y - 1, x, :] = out
        if y < h - 1:
            for d in range(nd):
                hb[d] = data[y, x, d] + md[y, x, d] + ml[y, x, d] + mr[y, x, d]
            _bp_message(hb, out, lam, tau)
            mu[y + 1, x, :] = out
        if x > 0:
            for d in range(nd):
                hb[d] = data[y, x, d] + mu[y, x, d] + md[y, x, d] + ml[y, x, d]
            _bp_message(hb, out, lam, tau)
            mr[y, x - 1, :] = out
        if x < w - 1:
            for d in range(nd):
                hb[d] = data[y, x, d] + mu[y, x, d] + md[y, x, d] + mr[y, x, d]
            _bp_message(hb, out, lam, tau)
            ml[y, x + 1, :] = out


@numba.njit(cache=True, parallel=True, nogil=True, fastmath=True)
def _bp_iterate_parallel(data, mu, md, ml, mr, lam, tau, parity):
    h, w, nd = data.shape
    for y in numba.prange(h):
        hb = np.empty(nd, np.float32)
        out = np.empty(nd, np.float32)
        _bp_row(data, mu, md, ml, mr, lam, tau, parity, y, hb, out)


@numba.njit(cache=True, nogil=True, fastmath=True)
def _bp_iterate_serial(data, mu, md, ml, mr, lam, tau, parity):
    h, w, nd = data.shape
    hb = np.empty(nd, np.float32)
    out = np.empty(nd, np.float32)
    for y in range(h):
        _bp_row(data, mu, md, ml, mr, lam, tau, parity, y, hb, out)


# Parallel over rows for large grids; small grids run serially, where the per-call thread
# barrier would cost more than it saves (and much more on a loaded machine).
_BP_PARALLEL_MIN_CELLS = 4_000_000


def _bp_iterate(data, mu, md, ml, mr, lam, tau, parity):
    kernel = _bp_iterate_parallel if data.size >= _BP_PARALLEL_MIN_CELLS else _bp_iterate_serial
    kernel(data, mu, md, ml, mr, lam, tau, parity)


@numba.njit(cache=True, parallel=True, nogil=True)
def _bp_decode(data, mu, md, ml, mr):
    h, w, nd = data.shape
    lab = np.empty((h, w), np.int32)
    for y in numba.prange(h):
        for x in range(w):
            best = np.inf
            bd = 0
            for d in range(nd):
                b = data[y, x, d] + mu[y, x, d] + md[y, x, d] + ml[y, x, d] + mr[y, x, d]
                if b < best:
                    best = b
                    bd = d
            lab[y, x] = bd
    return lab


@numba.njit(cache=True, nogil=True)
def _energy(cost, labels, lam, tau):
    h, w, _ = cost.shape
    e = 0.0
    for y in range(h):
        for x in range(w):
            d = labels[y, x]
            e += cost[y, x, d]
            if x + 1 < w:
                e += min(lam * abs(d - labels[y, x + 1]), tau)
            if y + 1 < h:
                e += min(lam * abs(d - labels[y + 1, x]), tau)
    return e


def stereo_energy(cost: np.ndarray, labels: np.ndarray, smoothness: float,
                  truncation: float) -> float:
    """
    Eq. 1 of the chapter for a labelling on the 4-connected grid.

    ``E(d) = sum_i C1(i, d_i) + sum_{(i, j) neighbours} min(smoothness * |d_i - d_j|,
    truncation)``, each unordered neighbour pair counted once.

    :param cost: (H, W, D) data cost ``C1``.
    :param labels: (H, W) integer disparities in [0, D-1].
    :param smoothness: slope ``lambda`` of the truncated-linear term (cost per pixel of jump).
    :param truncation: ``tau``, the maximum smoothness cost of a pair.
    """
    cost = np.asarray(cost, dtype=np.float64)
    labels = np.asarray(labels)
    if labels.shape != cost.shape[:2]:
        raise ValueError(f'labels {labels.shape} do not match cost volume {cost.shape}')
    if labels.min() < 0 or labels.max() >= cost.shape[2]:
        raise ValueError('labels out of the disparity range of the cost volume')
    return float(_energy(cost, labels.astype(np.int64), float(smoothness), float(truncation)))


def _downsample_data(data: np.ndarray) -> np.ndarray:
    # FH 2006 Sec. 3: the data cost of a coarse node is the sum over its 2x2 block.
    h, w, nd = data.shape
    h2, w2 = (h + 1) // 2, (w + 1) // 2
    pad = np.zeros((2 * h2, 2 * w2, nd), np.float32)
    pad[:h, :w] = data
    return (pad[0::2, 0::2] + pad[1::2, 0::2] + pad[0::2, 1::2] + pad[1::2, 1::2])


def belief_propagation(cost: np.ndarray, smoothness: float = 1.0, truncation: float = 4.0,
                       iterations: int = 5, levels: int = 4,
                       callback: Optional[Callable[[int, int, np.ndarray], None]] = None
                       ) -> np.ndarray:
    """
    Hierarchical min-sum loopy BP (Felzenszwalb & Huttenlocher 2006) minimising Eq. 1.

    Messages are computed in O(D) with the truncated-linear distance transform, updated on a
    checkerboard (each iteration updates both colours once), and initialised coarse-to-fine: the
    data cost of a level is the 2x2 block sum of the finer level, and every fine node starts
    from its parent's messages.

    :param cost: (H, W, D) data cost ``C1`` (any real dtype; float32 internally).
    :param smoothness: slope ``lambda`` of ``C2 = min(lambda |d_i - d_j|, tau)``.
    :param truncation: ``tau`` (same units as the cost).
    :param iterations: message-passing iterations per level.
    :param levels: number of pyramid levels (1 = flat BP).
    :param callback: called as ``callback(level, iteration, labels)`` after every iteration of
        every level (level 0 is the finest), e.g. to record the energy.
    :return: (H, W) int32 disparities (pixels): of the labellings decoded after each
        finest-level iteration, the one with the lowest Eq. 1 energy.
    """
    cost = np.asarray(cost)
    if cost.ndim != 3 or cost.shape[2] < 2:
        raise ValueError(f'cost volume must be (H, W, D) with D >= 2, got shape {cost.shape}')
    if smoothness < 0 or truncation < 0:
        raise ValueError('smoothness and truncation must be non-negative')
    if iterations < 1 or levels < 1:
        raise ValueError('iterations and levels must be >= 1')
    pyramid = [np.ascontiguousarray(cost, dtype=np.float32)]
    for _ in range(levels - 1):
        if min(pyramid[-1].shape[:2]) < 2:
            break
        pyramid.append(_downsample_data(pyramid[-1]))
    lam = np.float32(smoothness)
    tau = np.float32(truncation)
    msgs = None
    best_labels = None
    best_energy = np.inf
    for level in range(len(pyramid) - 1, -1, -1):
        data = pyramid[level]
        h, w, nd = data.shape
        if msgs is None:
            msgs = [np.zeros((h, w, nd), np.float32) for _ in range(4)]
        else:
            msgs = [np.ascontiguousarray(np.repeat(np.repeat(m, 2, axis=0), 2, axis=1)[:h, :w])
                    for m in msgs]
        mu, md, ml, mr = msgs
        for it in range(iterations):
            _bp_iterate(data, mu, md, ml, mr, lam, tau, 0)
            _bp_iterate(data, mu, md, ml, mr, lam, tau, 1)
            if callback is not None or level == 0:
                labels = _bp_decode(data, mu, md, ml, mr)
                if callback is not None:
                    callback(level, it, labels)
                if level == 0:
                    # Loopy BP is not guaranteed to lower the energy at every iteration; keep
                    # the best labelling decoded so far.
                    e = _energy(data, labels.astype(np.int64), float(lam), float(tau))
                    if e < best_energy:
                        best_energy = e
                        best_labels = labels
    return best_labels


@numba.njit(inline='always', fastmath=True, boundscheck=False)
def _hamming_pixel(pl, y, x, crr, ndp, out):
    # out[d] = Hamming distance of left pixel (x, y) and right pixel x - d of the row held
    # reversed in crr (index w - 1 - (x - d)), summed over the byte planes; d < ndp.
    k0 = crr.shape[1] - ndp - 1 - x
    if pl.shape[0] == 3:
        # the 5x5 census (24 bits): all three planes in one pass, one store per candidate
        a0 = pl[0, y, x]
        a1 = pl[1, y, x]
        a2 = pl[2, y, x]
        s0 = crr[0, k0:k0 + ndp]
        s1 = crr[1, k0:k0 + ndp]
        s2 = crr[2, k0:k0 + ndp]
        for d in range(ndp):
            out[d] = np.uint8(_popcount8(np.uint8(a0 ^ s0[d])) + _popcount8(np.uint8(a1 ^ s1[d]))
                              + _popcount8(np.uint8(a2 ^ s2[d])))
        return
    a = pl[0, y, x]
    src = crr[0, k0:k0 + ndp]
    for d in range(ndp):
        out[d] = _popcount8(np.uint8(a ^ src[d]))
    for p in range(1, pl.shape[0]):
        a = pl[p, y, x]
        src = crr[p, k0:k0 + ndp]
        for d in range(ndp):
            out[d] = np.uint8(out[d] + _popcount8(np.uint8(a ^ src[d])))


@numba.njit(inline='always', fastmath=True, boundscheck=False)
def _reversed_right_row(pr, y, crr):
    # the right planes' row y, reversed, into crr[:, :w] (crr[:, w:] stays 0: candidates
    # left of the right image, overwritten with the invalid cost)
    w = pr.shape[2]
    for p in range(pr.shape[0]):
        for k in range(w):
            crr[p, k] = pr[p, y, w - 1 - k]


@numba.njit(inline='always', fastmath=True, boundscheck=False)
def _hamming_full_row(pl, pr, y, crr, ndp, invalid, out):
    _reversed_right_row(pr, y, crr)
    for x in range(pl.shape[2]):
        o = out[x]
        _hamming_pixel(pl, y, x, crr, ndp, o)
        for d in range(x + 1, ndp):
            o[d] = invalid


@numba.njit(inline='always', fastmath=True, boundscheck=False)
def _box_wta_pixel(hs, va, vb, rp, dcode):
    # Slide the horizontal window sum hs one pixel (+ column va, - column vb) and take the
    # packed minimum (sum << 16 | dcode[d]) for the left view (returned) and, per candidate,
    # for the right pixel x - d (rp, indexed reversed). Every value is cast back to 16/32 bits
    # at once: numba widens small integers to 64 bits, the casts let LLVM keep 16 / 8 lanes.
    pk = np.uint32(0xFFFFFFFF)
    for d in range(hs.shape[0]):
        s = _U16(hs[d] + va[d] - vb[d])
        hs[d] = s
        p = np.uint32(np.uint32(np.uint32(s) << np.uint32(16)) | dcode[d])
        pk = np.uint32(min(pk, p))
        rp[d] = np.uint32(min(rp[d], p))
    return pk


@numba.njit(inline='always', fastmath=True, boundscheck=False)
def _left_disparity(hs, pk, nd, uniqueness):
    # Parabola subpixel of the packed minimum pk (NaN if not unique), as _wta_pixel.
    bd = np.int64(pk & np.uint32(0xFFFF))
    best = hs[bd]
    if uniqueness > 0.0:
        second = best
        found = False
        for d in range(nd):
            if d < bd - 1 or d > bd + 1:
                if not found or hs[d] < second:
                    second = hs[d]
                    found = True
        if found and best * (1.0 + uniqueness) > second:
            return np.float32(np.nan)
    if 0 < bd < nd - 1:
        return _parabola_vertex(bd, best, hs[bd - 1], hs[bd + 1], nd)
    return np.float32(bd)


@numba.njit(inline='always', fastmath=True, boundscheck=False)
def _parabola_vertex(bd, best, cmi, cpi, nd):
    # Subpixel disparity of the integer winner bd (cost best) from the costs cmi, cpi at
    # bd - 1 and bd + 1 (as _wta_pixel): the vertex of the parabola through the three.
    if 0 < bd < nd - 1:
        cm = np.float32(cmi)
        cp = np.float32(cpi)
        den = cm - np.float32(2.0) * np.float32(best) + cp
        if den > 0:
            return np.float32(bd + 0.5 * (cm - cp) / den)
    return np.float32(bd)


@numba.njit(cache=True, parallel=True, nogil=True, fastmath=True, boundscheck=False)
def _census_box_wta(pl, pr, nd, rw, rh, invalid, nchunks, uniqueness):
    # Fused census-Hamming cost -> box sum (borders replicated) -> WTA of both views, row by
    # row, without materialising the cost volumes. Same result as the step-by-step path.
    # pl, pr: (P, H, W) census byte planes. Candidates are padded to ndp, a multiple of 32:
    # the loops over them then have no scalar remainder (112 = 3 x 32 + 16 ran its last 16
    # candidates scalar); the padding never wins (dcode sets its packed cost to 0xFFFF....).
    # Per row: the Hamming row entering the vertical window is computed into a ring of rows
    # and the vertical sums vs updated (+ entering - leaving row) pixel by pixel; then the
    # horizontal running sum and both views' minima in one pass over the candidates.
    _, h, w = pl.shape
    ndp = (nd + 31) // 32 * 32
    dl = np.empty((h, w), np.float32)
    dr = np.empty((h, w), np.float32)
    dcode = np.empty(ndp, np.uint32)
    for d in range(ndp):
        dcode[d] = np.uint32(d) if d < nd else np.uint32(0xFFFF0000) | np.uint32(d)
    for ci in numba.prange(nchunks):
        y0 = ci * h // nchunks
        y1 = (ci + 1) * h // nchunks
        if y0 >= y1:
            continue
        # ring of Hamming rows: row r lives in slot r % nring until it leaves the window
        nring = 2 * rh + 2
        ring = np.empty((nring, w, ndp), np.uint8)
        vs = np.zeros((w, ndp), np.uint16)
        crr = np.zeros((pl.shape[0], w + ndp), np.uint8)
        hs = np.empty(ndp, np.uint16)
        rpk = np.empty(w + ndp, np.uint32)
        pkrow = np.empty(w, np.uint32)      # the row's left winners and their neighbours'
        cmrow = np.empty(w, np.uint16)      # costs, for the subpixel pass after the row
        cprow = np.empty(w, np.uint16)
        for r in range(max(y0 - rh, 0), min(y0 + rh, h - 1) + 1):
            _hamming_full_row(pl, pr, r, crr, ndp, invalid, ring[r % nring])
        for dy in range(-rh, rh + 1):
            hadd = ring[min(max(y0 + dy, 0), h - 1) % nring]
            for x in range(w):
                vrow = vs[x]
                arow = hadd[x]
                for d in range(ndp):
                    vrow[d] = _U16(vrow[d] + arow[d])
        for y in range(y0, y1):
            if y > y0:
                ya = min(y + rh, h - 1)
                ys = max(y - rh - 1, 0)
                if ya != ys:
                    hadd = ring[ya % nring]
                    hsub = ring[ys % nring]
                    fresh = y + rh <= h - 1
                    if fresh:
                        _reversed_right_row(pr, ya, crr)
                    for x in range(w):
                        arow = hadd[x]
                        if fresh:
                            _hamming_pixel(pl, ya, x, crr, ndp, arow)
                            for d in range(x + 1, ndp):
                                arow[d] = invalid
                        vrow = vs[x]
                        srow = hsub[x]
                        for d in range(ndp):
                            vrow[d] = _U16(vrow[d] + arow[d] - srow[d])
            # hs starts as the sum of columns -rw-1 .. rw-1 (replicated), so that the step to
            # x = 0 (+ column rw, - column -rw-1 = 0) gives the window of x = 0
            hs[:] = 0
            for dx in range(-rw - 1, rw):
                vrow = vs[min(max(dx, 0), w - 1)]
                for d in range(ndp):
                    hs[d] = _U16(hs[d] + vrow[d])
            rpk[:] = np.uint32(0xFFFFFFFF)
            dly = dl[y]
            for x in range(w):
                k0 = w - 1 - x
                pk = _box_wta_pixel(hs, vs[min(x + rw, w - 1)], vs[max(x - rw - 1, 0)],
                                    rpk[k0:k0 + ndp], dcode)
                if uniqueness > 0.0:
                    dly[x] = _left_disparity(hs, pk, nd, uniqueness)
                else:
                    bd = np.int64(pk & np.uint32(0xFFFF))
                    pkrow[x] = pk
                    cmrow[x] = hs[max(bd - 1, 0)]
                    cprow[x] = hs[min(bd + 1, ndp - 1)]
            if uniqueness <= 0.0:
                # the subpixel step as a pass of its own: inside the candidate loop its
                # dependent loads and the division stalled every pixel (~2 ms per frame)
                for x in range(w):
                    pk = pkrow[x]
                    dly[x] = _parabola_vertex(np.int64(pk & np.uint32(0xFFFF)),
                                              pk >> np.uint32(16), cmrow[x], cprow[x], nd)
            dry = dr[y]
            for xr in range(w):
                v = rpk[w - 1 - xr]
                dry[xr] = np.float32(v & np.uint32(0xFFFF)) if v < np.uint32(0xFFFF0000) \
                    else np.float32(np.nan)
    return dl, dr


def census_block_matching(left: np.ndarray, right: np.ndarray, max_disparity: int,
                          census_window: tuple[int, int] = (5, 5),
                          window: tuple[int, int] = (7, 7),
                          uniqueness: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """
    Run the local method fused for speed: census cost, box aggregation, WTA for both views.

    Identical to ``winner_take_all_both(box_sum_u16(census_cost(...), window))`` but computed
    row by row, so no (H, W, D) volume is stored: the census codes as byte planes
    (:func:`matching_cost.census_planes`), their Hamming distances one row at a time into a
    ring of the rows in the vertical window, running vertical and horizontal box sums, and
    both views' winners from one packed minimum (``sum << 16 | d``) per candidate (640x480,
    112 disparities, one thread: ~20 ms CPU against ~31 ms for the 32-bit-code kernel).

    :param left: left rectified image, (H, W) or (H, W, 3).
    :param right: right rectified image, same shape.
    :param max_disparity: number D of disparity candidates.
    :param census_window: odd (width, height) of the census transform.
    :param window: odd (width, height) of the aggregation box.
    :param uniqueness: as in :func:`winner_take_all_both`.
    :return: ``(disp_left, disp_right)`` (H, W) float32 pixels, as winner_take_all_both.
    """
    from stereo_depth.matching_cost import check_pair

    check_pair(left, right, max_disparity)
    ww, wh = int(window[0]), int(window[1])
    if ww < 1 or wh < 1 or ww % 2 == 0 or wh % 2 == 0:
        raise ValueError(f'aggregation window must be odd and positive, got {window}')
    nbits = int(census_window[0]) * int(census_window[1]) - 1
    if ww * wh * nbits > _U16_MAX:
        raise ValueError(f'window {window} with census {census_window} overflows 16 bits')
    if uniqueness < 0:
        raise ValueError(f'uniqueness must be >= 0, got {uniqueness}')
    if int(max_disparity) > _U16_MAX:
        raise ValueError(f'at most {_U16_MAX} disparities, got {max_disparity}')
    pl = census_planes(left, census_window)
    pr = census_planes(right, census_window)
    nchunks = max(1, min(numba.get_num_threads(), pl.shape[1]))
    return _census_box_wta(pl, pr, int(max_disparity), ww // 2, wh // 2, np.uint8(nbits),
                           nchunks, float(uniqueness))
