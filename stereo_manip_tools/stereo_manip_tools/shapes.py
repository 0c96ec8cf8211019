"""
Parametric polygon meshes: the one home of the workspace's mesh builders (pure numpy).

Boxes, extruded profiles and the peg-in-hole blocks, in metres, closed 2-manifolds whose faces
are listed counter-clockwise seen from outside. ``stereo_depth.synthetic.make_models`` builds the
shipped models with them (the committed OBJ files are exactly their output) and
``contact_correction.shapes`` builds its test and fallback geometry with them.
"""

from __future__ import annotations

from typing import List, Sequence

import numpy as np

from stereo_manip_tools.mesh_io import PolygonMesh

__all__ = ['box_mesh', 'prism_mesh', 'hole_block_mesh', 'slot_block_mesh']


def box_mesh(lo: Sequence[float], hi: Sequence[float], name: str) -> PolygonMesh:
    """Axis-aligned box between corners ``lo`` and ``hi`` [m], six CCW quads."""
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    V = np.array([[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
                  [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]], dtype=float)
    F = [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]
    return PolygonMesh(V, F, name)


def prism_mesh(profile_yz: Sequence[Sequence[float]], length: float,
               name: str = 'prism') -> PolygonMesh:
    """
    Extrude a simple polygon of the y-z plane (counter-clockwise) along x, centred on x = 0.

    The two end faces are the polygon itself (concave if the profile is).

    :param profile_yz: polygon corners (y, z) [m], shape (K, 2), counter-clockwise.
    :param length: extrusion length along x [m].
    """
    P = np.asarray(profile_yz, dtype=float)
    k = len(P)
    x0, x1 = -length / 2.0, length / 2.0
    V = np.vstack([np.column_stack([np.full(k, x0), P]), np.column_stack([np.full(k, x1), P])])
    faces = [list(range(k, 2 * k)), list(range(k - 1, -1, -1))]
    for j in range(k):
        jn = (j + 1) % k
        faces.append([j, jn, k + jn, k + j])
    return PolygonMesh(V, faces, name)


def hole_block_mesh(size: float = 0.16, height: float = 0.08, hole: float = 0.04,
                    name: str = 'hole_block') -> PolygonMesh:
    """
    Build a square block with a square through hole along z.

    Block ``size`` x ``size`` x ``height`` [m] with a ``hole`` x ``hole`` hole; origin at the
    top-face centre, +z up. Vertices 0-3 outer top, 4-7 inner top, 8-11 outer bottom, 12-15
    inner bottom, each ring counter-clockwise seen from +z starting at (-,-); every face convex.
    """
    a, b = size / 2, hole / 2
    ring_o = [(-a, -a), (a, -a), (a, a), (-a, a)]
    ring_i = [(-b, -b), (b, -b), (b, b), (-b, b)]
    V = ([(x, y, 0.0) for x, y in ring_o] + [(x, y, 0.0) for x, y in ring_i]
         + [(x, y, -height) for x, y in ring_o] + [(x, y, -height) for x, y in ring_i])
    F: List[List[int]] = []
    for k in range(4):
        n = (k + 1) % 4
        F.append([k, n, 4 + n, 4 + k])                # top trapezoid, normal +z
        F.append([8 + k, 12 + k, 12 + n, 8 + n])       # bottom trapezoid, normal -z
        F.append([k, 8 + k, 8 + n, n])                 # outer wall, outward
        F.append([4 + k, 4 + n, 12 + n, 12 + k])       # hole wall, normal towards hole axis
    return PolygonMesh(np.array(V, dtype=float), F, name)


def slot_block_mesh(length: float = 0.16, width: float = 0.16, height: float = 0.08,
                    slot_width: float = 0.04, slot_depth: float = 0.04,
                    name: str = 'slot_block') -> PolygonMesh:
    """
    Build a block with a slot along x across its top.

    Block ``length`` (x) x ``width`` (y) x ``height`` (z) [m], slot ``slot_width`` (y) x
    ``slot_depth`` (z); origin at the top-face centre, +z up. The U-shaped cross-section (y, z)
    is extruded along x; each end face is split into three convex quads that use only the
    section's own vertices (no T-junctions).
    """
    a, b, w = length / 2, width / 2, slot_width / 2
    # Cross-section, counter-clockwise seen from +x: A B C D E F G H.
    sec = [(-b, -height), (b, -height), (b, 0.0), (w, 0.0), (w, -slot_depth), (-w, -slot_depth),
           (-w, 0.0), (-b, 0.0)]
    V = [(-a, y, z) for y, z in sec] + [(a, y, z) for y, z in sec]
    n = len(sec)
    F: List[List[int]] = []
    # End faces: x = +a seen from +x is CCW in (y, z); x = -a reversed.
    pieces = [[0, 1, 4, 5], [1, 2, 3, 4], [5, 6, 7, 0]]
    for p in pieces:
        F.append([n + i for i in p])
        F.append(list(reversed(p)))
    for i in range(n):
        j = (i + 1) % n
        F.append([i, j, n + j, n + i])  # side strip between section edges i -> j
    return PolygonMesh(np.array(V, dtype=float), F, name)
