"""Hand-built polygon meshes with known geometry (boxes, prisms, a block with a through hole).

Used by the tests for configurations with analytic answers and as a fallback when the shipped
models are not installed. The shipped models are loaded with
:func:`contact_correction.polyhedron.load_polyhedron` (``stereo_manip_tools.mesh_io``).
All sizes in metres; faces counter-clockwise seen from outside.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from stereo_manip_tools.mesh_io import PolygonMesh

__all__ = ['box_mesh', 'prism_mesh', 'block_with_hole_mesh', 'block_with_slot_mesh']


def prism_mesh(profile_yz: Sequence[Sequence[float]], length: float,
               name: str = 'prism') -> PolygonMesh:
    """Extrude a simple polygon of the y-z plane (counter-clockwise) along x, centred on x = 0.

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


def box_mesh(size: Sequence[float], center: Sequence[float] = (0.0, 0.0, 0.0),
             name: str = 'box') -> PolygonMesh:
    """Axis-aligned box of ``size`` (sx, sy, sz) [m] centred on ``center`` [m]: 8 vertices,
    6 quadrilateral faces."""
    sx, sy, sz = (float(s) for s in size)
    profile = [(-sy / 2, -sz / 2), (sy / 2, -sz / 2), (sy / 2, sz / 2), (-sy / 2, sz / 2)]
    m = prism_mesh(profile, sx, name)
    return PolygonMesh(m.vertices + np.asarray(center, dtype=float), m.faces, name)


def block_with_hole_mesh(outer: float = 0.16, hole: float = 0.04, height: float = 0.08,
                         name: str = 'hole_block') -> PolygonMesh:
    """Square block ``outer`` x ``outer`` x ``height`` [m] with a square ``hole`` x ``hole``
    through hole along z; origin at the centre of the top face, +z up (the top face is one
    merged face with a hole once loaded as a polyhedron)."""
    A, a, h = outer / 2.0, hole / 2.0, float(height)
    sq = [(-1, -1), (1, -1), (1, 1), (-1, 1)]
    V = []
    for s, z in ((A, 0.0), (a, 0.0), (A, -h), (a, -h)):   # O, I, O', I'
        V.extend([(s * u, s * v, z) for u, v in sq])
    O, In, Ob, Ib = 0, 4, 8, 12
    faces = []
    for k in range(4):
        kn = (k + 1) % 4
        faces.append([O + k, O + kn, In + kn, In + k])          # top ring, +z
        faces.append([Ob + kn, Ob + k, Ib + k, Ib + kn])        # bottom ring, -z
        faces.append([Ob + k, Ob + kn, O + kn, O + k])          # outer wall
        faces.append([In + k, In + kn, Ib + kn, Ib + k])        # hole wall (normal into hole)
    return PolygonMesh(np.asarray(V, dtype=float), faces, name)


def block_with_slot_mesh(length: float = 0.16, width: float = 0.16, height: float = 0.08,
                         slot_width: float = 0.04, slot_depth: float = 0.04,
                         name: str = 'slot_block') -> PolygonMesh:
    """Block ``length`` (x) x ``width`` (y) x ``height`` (z) [m] with a slot along x across the
    top (``slot_width`` in y, ``slot_depth`` in z); origin at the centre of the top face."""
    W, H, w, s = width / 2.0, float(height), slot_width / 2.0, float(slot_depth)
    profile = [(-W, -H), (W, -H), (W, 0.0), (w, 0.0), (w, -s), (-w, -s), (-w, 0.0), (-W, 0.0)]
    return prism_mesh(profile, length, name)
