"""
Still real stereo pairs.

The Middlebury 2014 Motorcycle pair shipped by scikit-image, or a pair of image files with user
calibration (pure numpy/OpenCV).

Middlebury calibration (quarter resolution, as shipped by ``skimage.data.stereo_motorcycle``):
f = 994.978 px, cx = 311.193 px, cy = 254.877 px, doffs = 31.086 px (x-difference of the
principal points, cx_right = cx_left + doffs), baseline 193.001 mm. Disparity d: x_right =
x_left - d; depth Z = f B / (d + doffs). In ROS terms the right camera has
``P = [f 0 cx+doffs -f B; 0 f cy 0; 0 0 1 0]``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math
import os
from typing import Optional

import cv2
import numpy as np

__all__ = ['RealStereoPair', 'load_motorcycle', 'load_stereo_files', 'MOTORCYCLE_CALIBRATION']

MOTORCYCLE_CALIBRATION = {'f': 994.978, 'cx': 311.193, 'cy': 254.877, 'doffs': 31.086,
                          'baseline': 0.193001}


@dataclass
class RealStereoPair:
    """
    A rectified still pair with calibration.

    :ivar left: left image, uint8 (H, W) or (H, W, 3) RGB.
    :ivar right: right image, same shape.
    :ivar fx: focal length [px] (both cameras; fy = fx).
    :ivar cx: left principal point x [px].
    :ivar cy: principal point y [px].
    :ivar doffs: cx_right - cx_left [px].
    :ivar baseline: [m].
    :ivar disparity: ground-truth left disparity [px] or None; NaN where unknown.
    :ivar name: label.
    """

    left: np.ndarray
    right: np.ndarray
    fx: float
    cx: float
    cy: float
    doffs: float
    baseline: float
    disparity: Optional[np.ndarray] = None
    name: str = ''
    extra: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.left.shape != self.right.shape:
            raise ValueError(f'left {self.left.shape} and right {self.right.shape} image shapes '
                             'differ')
        if self.left.dtype != np.uint8 or self.left.ndim not in (2, 3):
            raise ValueError('images must be uint8 (H, W) or (H, W, 3)')
        for name in ('fx', 'baseline'):
            v = getattr(self, name)
            if not math.isfinite(v) or v <= 0:
                raise ValueError(f'{name} must be finite and > 0, got {v!r}')

    @property
    def K_left(self) -> np.ndarray:
        """3x3 left intrinsics."""
        return np.array([[self.fx, 0, self.cx], [0, self.fx, self.cy], [0, 0, 1.0]])

    @property
    def K_right(self) -> np.ndarray:
        """3x3 right intrinsics (principal point shifted by ``doffs``)."""
        K = self.K_left
        K[0, 2] += self.doffs
        return K

    @property
    def P_left(self) -> np.ndarray:
        """3x4 left projection."""
        return np.hstack([self.K_left, np.zeros((3, 1))])

    @property
    def P_right(self) -> np.ndarray:
        """3x4 right projection, P[0, 3] = -fx B."""
        P = np.hstack([self.K_right, np.zeros((3, 1))])
        P[0, 3] = -self.fx * self.baseline
        return P

    def depth(self) -> Optional[np.ndarray]:
        """Ground-truth depth Z = f B / (d + doffs) [m], NaN where unknown; None without GT."""
        if self.disparity is None:
            return None
        with np.errstate(divide='ignore', invalid='ignore'):
            z = self.fx * self.baseline / (self.disparity + self.doffs)
        return np.where(np.isfinite(z) & (z > 0), z, np.nan).astype(np.float32)

    def as_gray(self) -> 'RealStereoPair':
        """Copy with mono8 images."""
        def g(im: np.ndarray) -> np.ndarray:
            return im if im.ndim == 2 else cv2.cvtColor(im, cv2.COLOR_RGB2GRAY)
        return RealStereoPair(g(self.left), g(self.right), self.fx, self.cx, self.cy,
                              self.doffs, self.baseline, self.disparity, self.name, self.extra)


def load_motorcycle() -> RealStereoPair:
    """
    Load the Middlebury 2014 Motorcycle pair from scikit-image (741 x 500, RGB, offline).

    Ground truth disparity is float32 with non-finite values (NaN or +inf, depending on the
    scikit-image version) converted to NaN.
    """
    from skimage import data
    left, right, disp = data.stereo_motorcycle()
    disp = np.asarray(disp, dtype=np.float32)
    disp = np.where(np.isfinite(disp), disp, np.nan).astype(np.float32)
    c = MOTORCYCLE_CALIBRATION
    return RealStereoPair(np.ascontiguousarray(left), np.ascontiguousarray(right), c['f'],
                          c['cx'], c['cy'], c['doffs'], c['baseline'], disp, 'motorcycle')


def load_stereo_files(left_path: str, right_path: str, fx: float, baseline: float,
                      cx: Optional[float] = None, cy: Optional[float] = None,
                      doffs: float = 0.0, disparity_path: Optional[str] = None
                      ) -> RealStereoPair:
    """
    Load a rectified pair from image files (any format OpenCV reads; colour -> RGB).

    :param fx: focal length [px] (> 0).
    :param baseline: [m] (> 0).
    :param cx: left principal point x [px] (default image centre).
    :param cy: principal point y [px] (default image centre).
    :param doffs: cx_right - cx_left [px].
    :param disparity_path: optional ground-truth disparity (.npy, or .pfm read by OpenCV).
    :raises FileNotFoundError: naming the missing file.
    :raises ValueError: for unreadable images or bad calibration.
    """
    imgs = []
    for p in (left_path, right_path):
        if not os.path.isfile(p):
            raise FileNotFoundError(f'stereo image file not found: {p}')
        im = cv2.imread(p, cv2.IMREAD_UNCHANGED)
        if im is None:
            raise ValueError(f'cannot read image {p}')
        if im.dtype != np.uint8:
            im = cv2.convertScaleAbs(im, alpha=255.0 / max(float(im.max()), 1.0))
        if im.ndim == 3:
            im = cv2.cvtColor(im, cv2.COLOR_BGRA2RGB if im.shape[2] == 4 else cv2.COLOR_BGR2RGB)
        imgs.append(im)
    h, w = imgs[0].shape[:2]
    disp = None
    if disparity_path:
        if not os.path.isfile(disparity_path):
            raise FileNotFoundError(f'disparity file not found: {disparity_path}')
        if disparity_path.endswith('.npy'):
            disp = np.load(disparity_path).astype(np.float32)
        else:
            disp = cv2.imread(disparity_path, cv2.IMREAD_UNCHANGED)
            if disp is None:
                raise ValueError(f'cannot read disparity {disparity_path}')
            disp = disp.astype(np.float32)
        disp = np.where(np.isfinite(disp), disp, np.nan).astype(np.float32)
    return RealStereoPair(imgs[0], imgs[1], float(fx), float((w - 1) / 2 if cx is None else cx),
                          float((h - 1) / 2 if cy is None else cy), float(doffs),
                          float(baseline), disp, os.path.basename(left_path))
