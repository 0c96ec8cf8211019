"""
Middlebury-style evaluation of disparity maps, and the ``evaluate_disparity`` executable.

Metrics follow the Middlebury stereo SDK: over the evaluated pixels (ground truth known and
inside the optional mask), ``bad-t`` is the fraction whose estimate is missing or differs from
the truth by more than ``t`` pixels; missing estimates are *counted as errors* and also reported
separately (``invalid``); ``avgerr`` and ``rms`` are computed over the pixels that have an
estimate; ``bad-t_valid`` is the error rate over those pixels only.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
import sys
from typing import Optional, Sequence

import numba
import numpy as np

__all__ = [
    'evaluate_disparity',
    'nonoccluded_mask',
    'read_pfm',
    'write_pfm',
    'load_disparity',
    'main',
]


def evaluate_disparity(disparity: np.ndarray, truth: np.ndarray,
                       mask: Optional[np.ndarray] = None,
                       thresholds: Sequence[float] = (1.0, 2.0, 4.0)) -> dict:
    """
    Middlebury metrics of an estimated disparity map against ground truth.

    :param disparity: (H, W) estimate in pixels; NaN, inf or negative values are "missing".
    :param truth: (H, W) ground truth in pixels; non-finite values are "unknown" (not scored).
    :param mask: optional (H, W) bool, True where the pixel is evaluated (e.g. non-occluded).
    :param thresholds: error thresholds t in pixels.
    :return: dict with ``bad-t`` (fractions in [0, 1], missing counted as errors),
        ``bad-t_valid``, ``invalid`` (fraction missing), ``avgerr``, ``rms`` (pixels, over
        estimated pixels), ``n_evaluated``.
    """
    est = np.asarray(disparity, dtype=np.float64)
    gt = np.asarray(truth, dtype=np.float64)
    if est.shape != gt.shape or est.ndim != 2:
        raise ValueError(f'estimate {est.shape} and truth {gt.shape} must be equal (H, W) arrays')
    sel = np.isfinite(gt)
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != gt.shape:
            raise ValueError(f'mask {mask.shape} does not match the truth {gt.shape}')
        sel &= mask
    n = int(sel.sum())
    if n == 0:
        raise ValueError('no pixel to evaluate (truth unknown everywhere inside the mask)')
    e = est[sel]
    g = gt[sel]
    missing = ~np.isfinite(e) | (e < 0)
    err = np.abs(np.where(missing, 0.0, e) - g)
    have = ~missing
    out = {'n_evaluated': n, 'invalid': float(missing.mean())}
    for t in thresholds:
        key = f'bad-{float(t):.1f}'
        out[key] = float(((err > t) | missing).mean())
        out[key + '_valid'] = float((err[have] > t).mean()) if have.any() else float('nan')
    out['avgerr'] = float(err[have].mean()) if have.any() else float('nan')
    out['rms'] = float(np.sqrt((err[have] ** 2).mean())) if have.any() else float('nan')
    return out


@numba.njit(cache=True)
def _zbuffer_visible(gt, tol):
    h, w = gt.shape
    vis = np.zeros((h, w), np.bool_)
    zb = np.empty(w, np.float64)
    for y in range(h):
        zb[:] = -np.inf
        for x in range(w):
            d = gt[y, x]
            if np.isfinite(d):
                b = int(np.floor(x - d + 0.5))
                if 0 <= b < w and d > zb[b]:
                    zb[b] = d
        for x in range(w):
            d = gt[y, x]
            if np.isfinite(d):
                b = int(np.floor(x - d + 0.5))
                vis[y, x] = 0 <= b < w and d >= zb[b] - tol
    return vis


def nonoccluded_mask(truth: np.ndarray, tolerance: float = 1.0) -> np.ndarray:
    """
    Pixels of the left image visible in the right one, from the left ground truth.

    Rule (forward warping with a z-buffer): every left pixel ``x`` with known disparity ``d``
    lands at ``xr = x - d`` in the right image and is splatted to the nearest right-image column
    ``round(xr)``; each column keeps the largest disparity (the nearest surface) it receives.
    A left pixel is non-occluded when ``round(xr)`` lies inside the right image and its
    disparity is within ``tolerance`` pixels of that column's z-buffer value, i.e. nothing
    nearer covers it in the right view. Pixels with unknown truth are False.

    :param truth: (H, W) left-view ground-truth disparity (pixels, non-finite = unknown).
    :param tolerance: pixels; absorbs the sampling of slanted surfaces.
    :return: (H, W) bool mask.
    """
    gt = np.asarray(truth, dtype=np.float64)
    if gt.ndim != 2:
        raise ValueError(f'truth must be (H, W), got shape {gt.shape}')
    return _zbuffer_visible(gt, float(tolerance))


def read_pfm(path: str | Path) -> np.ndarray:
    """Read a PFM image (Middlebury's disparity format) as float32, top row first; inf kept."""
    with open(path, 'rb') as f:
        header = f.readline().decode('latin-1').strip()
        if header not in ('Pf', 'PF'):
            raise ValueError(f'{path}: not a PFM file (header {header!r})')
        dims = f.readline().decode('latin-1').split()
        while not dims:
            dims = f.readline().decode('latin-1').split()
        w, h = int(dims[0]), int(dims[1])
        scale = float(f.readline().decode('latin-1').strip())
        dtype = '<f4' if scale < 0 else '>f4'
        ch = 3 if header == 'PF' else 1
        data = np.frombuffer(f.read(w * h * ch * 4), dtype=dtype)
    if data.size != w * h * ch:
        raise ValueError(f'{path}: truncated PFM data')
    img = data.reshape(h, w, ch) if ch == 3 else data.reshape(h, w)
    return np.ascontiguousarray(img[::-1]).astype(np.float32)


def write_pfm(path: str | Path, image: np.ndarray) -> None:
    """Write a (H, W) float image as little-endian greyscale PFM."""
    img = np.asarray(image, dtype='<f4')
    if img.ndim != 2:
        raise ValueError(f'write_pfm takes an (H, W) image, got shape {img.shape}')
    with open(path, 'wb') as f:
        f.write(b'Pf\n%d %d\n-1.0\n' % (img.shape[1], img.shape[0]))
        f.write(np.ascontiguousarray(img[::-1]).tobytes())


def load_disparity(path: str | Path, scale: float = 1.0) -> np.ndarray:
    """
    Load a disparity map from .pfm, .npy or an 8/16-bit image (value / scale; 0 = missing).

    :param path: file name.
    :param scale: divisor for integer image formats (e.g. 16 for OpenCV fixed point, 256 KITTI).
    """
    p = Path(path)
    if not p.is_file():
        raise ValueError(f'{p}: no such file')
    suffix = p.suffix.lower()
    if suffix == '.pfm':
        return read_pfm(p)
    if suffix == '.npy':
        arr = np.load(p)
        if arr.ndim != 2:
            raise ValueError(f'{p}: expected an (H, W) array, got shape {arr.shape}')
        return arr.astype(np.float32)
    import cv2

    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    if img is None or img.ndim != 2:
        raise ValueError(f'{p}: cannot read a single-channel disparity image')
    d = img.astype(np.float32) / float(scale)
    d[img == 0] = np.nan
    return d


def main(argv: Optional[Sequence[str]] = None) -> int:
    """``evaluate_disparity ESTIMATE TRUTH [--mask M | --nonoccluded] [--json]``."""
    ap = argparse.ArgumentParser(
        prog='evaluate_disparity',
        description='Middlebury-style metrics (bad-1/2/4 with missing counted as errors, '
                    'invalid fraction, average error) of a disparity map against ground truth.')
    ap.add_argument('estimate', help='estimated disparity (.pfm, .npy, .png)')
    ap.add_argument('truth', help='ground-truth disparity (.pfm, .npy, .png)')
    ap.add_argument('--mask', help='mask image/array, non-zero = evaluate')
    ap.add_argument('--nonoccluded', action='store_true',
                    help='evaluate only pixels visible in the right view (z-buffer warping '
                         'of the truth, see nonoccluded_mask)')
    ap.add_argument('--scale', type=float, default=1.0,
                    help='divisor for integer disparity images (default 1)')
    ap.add_argument('--thresholds', type=float, nargs='+', default=[1.0, 2.0, 4.0])
    ap.add_argument('--json', action='store_true', help='print the metrics as JSON')
    args = ap.parse_args(argv)
    try:
        est = load_disparity(args.estimate, args.scale)
        gt = load_disparity(args.truth, args.scale)
        mask = None
        if args.mask:
            mp = Path(args.mask)
            if mp.suffix.lower() == '.npy':
                mask = np.load(mp).astype(bool)
            else:
                import cv2

                m = cv2.imread(str(mp), cv2.IMREAD_GRAYSCALE)
                if m is None:
                    raise ValueError(f'{mp}: cannot read the mask')
                mask = m > 0
        if args.nonoccluded:
            nonocc = nonoccluded_mask(gt)
            mask = nonocc if mask is None else (mask & nonocc)
        metrics = evaluate_disparity(est, gt, mask, args.thresholds)
    except ValueError as exc:
        print(f'evaluate_disparity: error: {exc}', file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(metrics, indent=2))
    else:
        for k, v in metrics.items():
            print(f'{k:>16s}: {v:.4f}' if isinstance(v, float) else f'{k:>16s}: {v}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
