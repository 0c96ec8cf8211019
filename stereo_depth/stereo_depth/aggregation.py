"""
Step 2 of the four-step stereo pipeline (chapter Sec. 2.1): cost (support) aggregation.

The chapter's "first method": estimate a correspondence from a small region around the pixel,
i.e. sum (or average) the matching cost of every disparity over a window. Cost volumes are
``(H, W, D)``; aggregation acts on each disparity slice independently (fronto-parallel windows).
"""

from __future__ import annotations

import cv2
import numba
import numpy as np

__all__ = ['box_aggregate', 'box_sum_u16']


def box_aggregate(cost: np.ndarray, window: tuple[int, int] = (5, 5),
                  normalize: bool = True) -> np.ndarray:
    """
    Average (or sum) the cost of every disparity over a ``window`` (width, height) box.

    Borders are reflected (OpenCV ``BORDER_REFLECT_101``). Implemented with OpenCV's separable
    running-sum box filter, all disparities at once (costs are the channels).

    :param cost: (H, W, D) cost volume, uint8 or float.
    :param window: odd (width, height) in pixels.
    :param normalize: True: window mean with the input's dtype (uint8 mean is rounded);
        False: window sum as float32 (exact for integer costs).
    :return: (H, W, D) aggregated cost volume.
    """
    cost = np.asarray(cost)
    if cost.ndim != 3:
        raise ValueError(f'cost volume must be (H, W, D), got shape {cost.shape}')
    ww, wh = int(window[0]), int(window[1])
    if ww < 1 or wh < 1 or ww % 2 == 0 or wh % 2 == 0:
        raise ValueError(f'aggregation window must be odd and positive, got {window}')
    if cost.shape[2] > 512:
        raise ValueError(f'at most 512 disparities supported, got {cost.shape[2]}')
    if ww == 1 and wh == 1:
        return cost.astype(np.float32) if not normalize else cost.copy()
    if normalize:
        out = cv2.boxFilter(cost, -1, (ww, wh), normalize=True)
    else:
        out = cv2.boxFilter(cost.astype(np.float32), -1, (ww, wh), normalize=False)
    return out.reshape(cost.shape)


@numba.njit(cache=True, parallel=True, nogil=True, fastmath=True, boundscheck=False)
def _box_sum_u16(cost, rw, rh, nchunks):
    # Separable running sums, borders replicated. Rows are split into chunks (one per thread);
    # each chunk keeps a running vertical sum of (W, D) and slides it down its rows.
    h, w, nd = cost.shape
    out = np.empty((h, w, nd), np.uint16)
    for ci in numba.prange(nchunks):
        y0 = ci * h // nchunks
        y1 = (ci + 1) * h // nchunks
        if y0 >= y1:
            continue
        vs = np.zeros((w, nd), np.uint16)
        for dy in range(-rh, rh + 1):
            yy = min(max(y0 + dy, 0), h - 1)
            row = cost[yy]
            for x in range(w):
                for d in range(nd):
                    vs[x, d] = np.uint16(vs[x, d] + row[x, d])
        hs = np.zeros(nd, np.uint16)
        for y in range(y0, y1):
            if y > y0:
                add = cost[min(y + rh, h - 1)]
                sub = cost[max(y - rh - 1, 0)]
                for x in range(w):
                    for d in range(nd):
                        vs[x, d] = np.uint16(vs[x, d] + add[x, d] - sub[x, d])
            orow = out[y]
            hs[:] = 0
            for dx in range(-rw, rw + 1):
                xx = min(max(dx, 0), w - 1)
                for d in range(nd):
                    hs[d] = np.uint16(hs[d] + vs[xx, d])
            for d in range(nd):
                orow[0, d] = hs[d]
            for x in range(1, w):
                xa = min(x + rw, w - 1)
                xs = max(x - rw - 1, 0)
                for d in range(nd):
                    hs[d] = np.uint16(hs[d] + vs[xa, d] - vs[xs, d])
                    orow[x, d] = hs[d]
    return out


def box_sum_u16(cost: np.ndarray, window: tuple[int, int] = (5, 5)) -> np.ndarray:
    """
    Window sum of a uint8 cost volume into uint16 (exact), borders replicated.

    The fast path of :func:`box_aggregate` for integer costs (numba, separable running sums).

    :param cost: (H, W, D) uint8 cost volume.
    :param window: odd (width, height); ``width * height * max(cost)`` must fit in 16 bits.
    :return: (H, W, D) uint16 window sums.
    """
    cost = np.ascontiguousarray(cost)
    if cost.ndim != 3 or cost.dtype != np.uint8:
        raise ValueError(f'box_sum_u16 takes an (H, W, D) uint8 volume, got {cost.dtype} '
                         f'{cost.shape}')
    ww, wh = int(window[0]), int(window[1])
    if ww < 1 or wh < 1 or ww % 2 == 0 or wh % 2 == 0:
        raise ValueError(f'aggregation window must be odd and positive, got {window}')
    if ww * wh * 255 > 65535 and ww * wh * int(cost.max()) > 65535:
        raise ValueError(f'window {window} sums may overflow 16 bits')
    return _box_sum_u16(cost, ww // 2, wh // 2, max(1, numba.get_num_threads()))
