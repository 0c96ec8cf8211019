"""
Rectified pinhole stereo camera model (pure numpy).

Conventions (REP 103 / ROS stereo): both cameras share the intrinsic matrix K; the left optical
frame is the reference (z forward, x right, y down, metres); the right camera centre sits at
(B, 0, 0) in the left optical frame, so a point (X, Y, Z) projects to

    u_left  = fx X / Z + cx,        u_right = fx (X - B) / Z + cx = u_left - d,
    v       = fy Y / Z + cy,        d = fx B / Z  (disparity, pixels).

Pixel centres are at integer coordinates (OpenCV / ROS: pixel (0, 0) covers [-0.5, 0.5]^2).
``P_right[0, 3] = -fx B`` as in ``sensor_msgs/CameraInfo``.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Tuple

import numpy as np

__all__ = ['StereoCamera', 'look_at']


@dataclass(frozen=True)
class StereoCamera:
    """
    Rectified stereo pair with identical intrinsics.

    :ivar width: image width [px] (> 0).
    :ivar height: image height [px] (> 0).
    :ivar fx: focal length along x [px] (> 0).
    :ivar fy: focal length along y [px] (> 0).
    :ivar cx: principal point x [px]; default (width - 1) / 2 when built by :meth:`create`.
    :ivar cy: principal point y [px].
    :ivar baseline: distance between the optical centres [m] (> 0), along +x of the left frame.
    """

    width: int = 640
    height: int = 480
    fx: float = 600.0
    fy: float = 600.0
    cx: float = 319.5
    cy: float = 239.5
    baseline: float = 0.10

    def __post_init__(self) -> None:
        for name in ('width', 'height'):
            val = getattr(self, name)
            if int(val) != val or val <= 0:
                raise ValueError(f'camera {name} must be a positive integer, got {val!r}')
        for name in ('fx', 'fy', 'baseline'):
            val = getattr(self, name)
            if not math.isfinite(val) or val <= 0:
                raise ValueError(f'camera {name} must be finite and > 0, got {val!r}')
        for name in ('cx', 'cy'):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f'camera {name} must be finite, got {getattr(self, name)!r}')

    @classmethod
    def create(cls, width: int = 640, height: int = 480, fx: float = 600.0,
               fy: float | None = None, baseline: float = 0.10, cx: float | None = None,
               cy: float | None = None) -> 'StereoCamera':
        """
        Camera with square pixels and centred principal point unless given.

        The defaults (fx = 600 px, B = 0.10 m) give disparities 120 px at 0.5 m and 40 px at
        1.5 m, the chapter's working range.
        """
        return cls(int(width), int(height), float(fx), float(fx if fy is None else fy),
                   float((width - 1) / 2 if cx is None else cx),
                   float((height - 1) / 2 if cy is None else cy), float(baseline))

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix (shared by both cameras)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def P_left(self) -> np.ndarray:
        """3x4 projection matrix of the left camera, ``K [I | 0]``."""
        return np.hstack([self.K, np.zeros((3, 1))])

    @property
    def P_right(self) -> np.ndarray:
        """3x4 projection matrix of the right camera, ``K [I | (-B, 0, 0)]``; P[0, 3] = -fx B."""
        P = self.P_left
        P[0, 3] = -self.fx * self.baseline
        return P

    @property
    def right_center(self) -> np.ndarray:
        """Right optical centre in the left optical frame [m], shape (3,)."""
        return np.array([self.baseline, 0.0, 0.0])

    def ray_directions(self) -> np.ndarray:
        """
        Per-pixel ray directions with unit z, ``((u - cx)/fx, (v - cy)/fy, 1)``, (H, W, 3).

        Because the z component is 1, the ray parameter of a hit equals its depth Z [m].
        """
        u = (np.arange(self.width, dtype=np.float64) - self.cx) / self.fx
        v = (np.arange(self.height, dtype=np.float64) - self.cy) / self.fy
        d = np.empty((self.height, self.width, 3))
        d[..., 0] = u[None, :]
        d[..., 1] = v[:, None]
        d[..., 2] = 1.0
        return d

    def disparity_from_depth(self, depth: np.ndarray) -> np.ndarray:
        """Disparity ``fx B / Z`` [px] of depth Z [m]; NaN stays NaN."""
        return (self.fx * self.baseline) / np.asarray(depth)

    def depth_from_disparity(self, disparity: np.ndarray) -> np.ndarray:
        """Depth ``fx B / d`` [m] of disparity d [px]."""
        return (self.fx * self.baseline) / np.asarray(disparity)

    def project(self, points: np.ndarray, right: bool = False) -> np.ndarray:
        """Pixel coordinates (N, 2) of points (N, 3) given in the left optical frame [m]."""
        P = self.P_right if right else self.P_left
        X = np.asarray(points, dtype=float).reshape(-1, 3)
        x = X @ P[:, :3].T + P[:, 3]
        return x[:, :2] / x[:, 2:3]

    def back_project(self, u: np.ndarray, v: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Left-frame points (..., 3) [m] of left pixels (u, v) with depth Z [m]."""
        Z = np.asarray(depth, dtype=float)
        X = (np.asarray(u, dtype=float) - self.cx) / self.fx * Z
        Y = (np.asarray(v, dtype=float) - self.cy) / self.fy * Z
        return np.stack([X, Y, Z], axis=-1)

    def as_dict(self) -> dict:
        """Parameters plus K, P_left, P_right as numpy arrays (for ground truth)."""
        return {'width': self.width, 'height': self.height, 'fx': self.fx, 'fy': self.fy,
                'cx': self.cx, 'cy': self.cy, 'baseline': self.baseline, 'K': self.K,
                'P_left': self.P_left, 'P_right': self.P_right}

    @property
    def shape(self) -> Tuple[int, int]:
        """Return (height, width) of the images."""
        return (self.height, self.width)


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, 0.0, 1.0)) -> np.ndarray:
    """
    4x4 pose of an optical frame (z forward, x right, y down) at ``eye`` looking at ``target``.

    :param eye: camera centre in the world frame [m], (3,).
    :param target: point looked at [m], (3,).
    :param up: world up direction; the image y axis points along its negative projection.
    :returns: T_world_camera (maps camera-frame points to world points).
    :raises ValueError: if eye == target or the view direction is parallel to ``up``.
    """
    eye, target, up = (np.asarray(a, dtype=float) for a in (eye, target, up))
    z = target - eye
    n = np.linalg.norm(z)
    if n == 0:
        raise ValueError('look_at: eye and target coincide')
    z /= n
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError('look_at: view direction parallel to up vector')
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, eye
    return T
