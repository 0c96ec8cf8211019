"""
Procedural surface texture fixed to each object (pure numpy + OpenCV).

Every polygon face gets a 2D chart: an orthonormal in-plane basis (e1, e2) and a random texel
offset. A surface point X (object frame, metres) of face f has texture coordinates

    (s, t) = ((X - o_f) . e1, (X - o_f) . e2) / texel_size + offset_f      [texels],

an affine function of X on the face, so the texture moves with the object and is identical
in both views (view-independent, Lambertian). The intensity is a bilinear lookup of a seeded,
wrap-around multi-scale noise tile (done per pixel in :func:`stereo_depth.synthetic.raster.shade`).
"""

from __future__ import annotations

from functools import lru_cache
from typing import Tuple

import numpy as np

from stereo_manip_tools.mesh_io import PolygonMesh
from stereo_manip_tools.transforms import perpendicular_basis

__all__ = ['make_noise_tile', 'face_charts', 'triangle_corner_texcoords']


@lru_cache(maxsize=8)
def make_noise_tile(seed: int, size: int = 1024,
                    sigmas: Tuple[float, ...] = (1.5, 4.0, 12.0),
                    weights: Tuple[float, ...] = (0.45, 0.35, 0.2)) -> np.ndarray:
    """
    Seamless (wrap-around) band-limited noise tile with values in [0, 1], float32 (size, size).

    Cached per arguments (treat the result as read-only). Sum of Gaussian-blurred white noise
    at several scales (sigmas in texels), each normalised to
    unit standard deviation, then mapped to [0, 1] by a clipped affine map (mean 0.5, 3 sd).
    """
    if size < 16 or size & (size - 1):
        raise ValueError(f'texture tile size must be a power of two >= 16, got {size}')
    rng = np.random.default_rng(seed)
    acc = np.zeros((size, size), np.float64)
    f = np.fft.fftfreq(size)
    f2 = f[:, None] ** 2 + f[None, :] ** 2
    for s, w in zip(sigmas, weights):
        spec = np.fft.fft2(rng.standard_normal((size, size)))
        b = np.fft.ifft2(spec * np.exp(-2.0 * np.pi ** 2 * s ** 2 * f2)).real  # periodic blur
        acc += w * b / max(float(b.std()), 1e-12)
    acc /= float(acc.std())
    return np.clip(0.5 + acc / 6.0, 0.0, 1.0).astype(np.float32)


def face_charts(mesh: PolygonMesh, rng: np.random.Generator, tile_size: int,
                texel_size: float) -> Tuple[np.ndarray, np.ndarray]:
    """
    Per-face affine chart: matrix A_f (2, 3) and offset b_f (2,) with (s, t) = A_f X + b_f.

    :param texel_size: size of one texel on the surface [m].
    """
    normals = mesh.face_normals()
    A = np.zeros((len(mesh.faces), 2, 3))
    b = np.zeros((len(mesh.faces), 2))
    for i, (f, n) in enumerate(zip(mesh.faces, normals)):
        e1, e2 = perpendicular_basis(n)
        o = mesh.vertices[f[0]]
        A[i, 0], A[i, 1] = e1 / texel_size, e2 / texel_size
        b[i] = -A[i] @ o + rng.uniform(0, tile_size, 2)
    return A, b


def triangle_corner_texcoords(mesh: PolygonMesh, A: np.ndarray, b: np.ndarray
                              ) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fan triangles of ``mesh``, their polygon face index, and corner texcoords (T, 3, 2)."""
    tris, face_of = [], []
    for fi, f in enumerate(mesh.faces):
        for k in range(1, len(f) - 1):
            tris.append((f[0], f[k], f[k + 1]))
            face_of.append(fi)
    tris = np.asarray(tris, dtype=np.int64).reshape(-1, 3)
    face_of = np.asarray(face_of, dtype=np.int64)
    V = mesh.vertices[tris]                                  # (T, 3, 3)
    st = np.einsum('tij,tkj->tki', A[face_of], V) + b[face_of][:, None, :]
    return tris, face_of, st
