"""
Analytic test shapes sampled with exact outward normals (benchmarks and tests; pure numpy).

Each sampler returns ``(points (N, 3) [m], normals (N, 3) unit, outward)`` for a shape centred
at the origin. ``size`` is the object's largest extent [m] (edge of the cube, diameter of the
sphere, ...), the reference for noise levels and accuracy goals.
"""

from __future__ import annotations

from typing import Callable, Dict, Optional, Tuple

import numpy as np

__all__ = [
    'SHAPES',
    'sample_shape',
    'sample_sphere',
    'sample_ellipsoid',
    'sample_cube',
    'sample_cylinder',
    'sample_torus',
    'sample_superquadric',
    'visible_half',
    'add_noise',
]

Sample = Tuple[np.ndarray, np.ndarray]


def _unit_vectors(n: int, rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def sample_sphere(n: int, size: float = 0.08, rng: Optional[np.random.Generator] = None
                  ) -> Sample:
    """Sphere of diameter ``size``."""
    rng = rng or np.random.default_rng(0)
    u = _unit_vectors(n, rng)
    return 0.5 * size * u, u


def sample_ellipsoid(n: int, size: float = 0.08, ratios=(1.0, 0.7, 0.5),
                     rng: Optional[np.random.Generator] = None) -> Sample:
    """Ellipsoid with semi-axes ``size / 2 * ratios`` (area-weighted by rejection)."""
    rng = rng or np.random.default_rng(0)
    axes = 0.5 * size * np.asarray(ratios, dtype=float)
    pts, nrm = [], []
    while sum(len(p) for p in pts) < n:
        u = _unit_vectors(2 * n, rng)
        p = u * axes
        g = p / axes ** 2
        # area element of p = axes * u is prod(axes) * |u / axes| times the sphere's
        keep = rng.random(len(u)) < np.linalg.norm(u / axes, axis=1) * axes.min()
        pts.append(p[keep])
        nrm.append(g[keep] / np.linalg.norm(g[keep], axis=1, keepdims=True))
    return np.vstack(pts)[:n], np.vstack(nrm)[:n]


def sample_cube(n: int, size: float = 0.08, rng: Optional[np.random.Generator] = None
                ) -> Sample:
    """Axis-aligned cube of edge ``size`` (uniform over the six faces)."""
    rng = rng or np.random.default_rng(0)
    h = 0.5 * size
    face = rng.integers(0, 6, n)
    axis, sign = face // 2, np.where(face % 2 == 0, 1.0, -1.0)
    p = rng.uniform(-h, h, size=(n, 3))
    p[np.arange(n), axis] = sign * h
    nrm = np.zeros((n, 3))
    nrm[np.arange(n), axis] = sign
    return p, nrm


def sample_cylinder(n: int, size: float = 0.08, rng: Optional[np.random.Generator] = None
                    ) -> Sample:
    """Sample a closed cylinder (with caps) along z, diameter = height = ``size``."""
    rng = rng or np.random.default_rng(0)
    r = h = 0.5 * size
    side_area, cap_area = 2 * np.pi * r * 2 * h, 2 * np.pi * r * r
    on_side = rng.random(n) < side_area / (side_area + cap_area)
    theta = rng.uniform(0, 2 * np.pi, n)
    p = np.empty((n, 3))
    nrm = np.zeros((n, 3))
    p[:, 0], p[:, 1] = r * np.cos(theta), r * np.sin(theta)
    p[:, 2] = rng.uniform(-h, h, n)
    nrm[:, 0], nrm[:, 1] = np.cos(theta), np.sin(theta)
    caps = ~on_side
    rho = r * np.sqrt(rng.random(caps.sum()))
    p[caps, 0], p[caps, 1] = rho * np.cos(theta[caps]), rho * np.sin(theta[caps])
    sign = np.where(rng.random(caps.sum()) < 0.5, 1.0, -1.0)
    p[caps, 2] = sign * h
    nrm[caps] = 0.0
    nrm[caps, 2] = sign
    return p, nrm


def sample_torus(n: int, size: float = 0.08, tube_ratio: float = 0.3,
                 rng: Optional[np.random.Generator] = None) -> Sample:
    """Torus around z of outer diameter ``size``; tube radius = ``tube_ratio`` * major."""
    rng = rng or np.random.default_rng(0)
    R = 0.5 * size / (1.0 + tube_ratio)
    r = tube_ratio * R
    pts, nrm = [], []
    while sum(len(p) for p in pts) < n:
        u = rng.uniform(0, 2 * np.pi, 2 * n)
        v = rng.uniform(0, 2 * np.pi, 2 * n)
        keep = rng.random(2 * n) < (R + r * np.cos(v)) / (R + r)  # area weighting
        u, v = u[keep], v[keep]
        nn = np.stack([np.cos(v) * np.cos(u), np.cos(v) * np.sin(u), np.sin(v)], axis=1)
        c = np.stack([R * np.cos(u), R * np.sin(u), np.zeros_like(u)], axis=1)
        pts.append(c + r * nn)
        nrm.append(nn)
    return np.vstack(pts)[:n], np.vstack(nrm)[:n]


def sample_superquadric(n: int, size: float = 0.08, exponent: float = 3.0,
                        rng: Optional[np.random.Generator] = None) -> Sample:
    """
    Superellipsoid ``|x/h|^e + |y/h|^e + |z/h|^e = 1``, h = size/2 (e = 3: rounded cube).

    Points come from radially projected random directions (not area-uniform).
    """
    rng = rng or np.random.default_rng(0)
    h = 0.5 * size
    u = _unit_vectors(n, rng)
    F = np.sum(np.abs(u) ** exponent, axis=1)
    p = h * u / F[:, None] ** (1.0 / exponent)
    g = np.sign(p) * np.abs(p / h) ** (exponent - 1)
    return p, g / np.linalg.norm(g, axis=1, keepdims=True)


SHAPES: Dict[str, Callable[..., Sample]] = {
    'sphere': sample_sphere,
    'ellipsoid': sample_ellipsoid,
    'cube': sample_cube,
    'cylinder': sample_cylinder,
    'torus': sample_torus,
    'superquadric': sample_superquadric,
}


def sample_shape(name: str, n: int, size: float = 0.08,
                 rng: Optional[np.random.Generator] = None) -> Sample:
    """Sample one of :data:`SHAPES` by name."""
    if name not in SHAPES:
        raise ValueError(f'unknown shape {name!r}; choose from {sorted(SHAPES)}')
    return SHAPES[name](n, size=size, rng=rng)


def visible_half(points: np.ndarray, normals: np.ndarray,
                 view_direction=(0.3, -0.4, 0.866)) -> Sample:
    """
    Keep the points whose outward normal faces the viewer (a one-sided, half view).

    :param view_direction: direction from the object toward the sensor.
    """
    v = np.asarray(view_direction, dtype=float)
    keep = normals @ (v / np.linalg.norm(v)) > 0.0
    return points[keep], normals[keep]


def add_noise(points: np.ndarray, sigma: float,
              rng: Optional[np.random.Generator] = None) -> np.ndarray:
    """Isotropic Gaussian noise of standard deviation ``sigma`` [m] per coordinate."""
    rng = rng or np.random.default_rng(0)
    return points + rng.normal(scale=sigma, size=points.shape)
