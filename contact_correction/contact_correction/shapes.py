"""
Polygon meshes with known geometry (boxes, prisms, blocks with a hole, a slot, a T-slot).

Built with the workspace's mesh builders (:mod:`stereo_manip_tools.shapes`), in this package's
parameter forms. Used by the tests for configurations with analytic answers and as a fallback
when the shipped models are not installed. The shipped models are loaded with
:func:`contact_correction.polyhedron.load_polyhedron` (``stereo_manip_tools.mesh_io``). All
sizes in metres; faces counter-clockwise seen from outside.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from stereo_manip_tools.mesh_io import PolygonMesh
from stereo_manip_tools.shapes import hole_block_mesh, prism_mesh, slot_block_mesh

__all__ = ['box_mesh', 'prism_mesh', 'block_with_hole_mesh', 'block_with_slot_mesh', 't_peg_mesh',
           't_slot_block_mesh']


def box_mesh(size: Sequence[float], center: Sequence[float] = (0.0, 0.0, 0.0),
             name: str = 'box') -> PolygonMesh:
    """
    Axis-aligned box of ``size`` (sx, sy, sz) [m] centred on ``center`` [m].

    8 vertices, 6 quadrilateral faces: a square profile extruded along x (the vertex order the
    tests' contact relations refer to).
    """
    sx, sy, sz = (float(s) for s in size)
    profile = [(-sy / 2, -sz / 2), (sy / 2, -sz / 2), (sy / 2, sz / 2), (-sy / 2, sz / 2)]
    m = prism_mesh(profile, sx, name)
    return PolygonMesh(m.vertices + np.asarray(center, dtype=float), m.faces, name)


def block_with_hole_mesh(outer: float = 0.16, hole: float = 0.04, height: float = 0.08,
                         name: str = 'hole_block') -> PolygonMesh:
    """
    Build a square block with a square through hole along z.

    Square block ``outer`` x ``outer`` x ``height`` [m] with a square ``hole`` x ``hole``
    through hole along z; origin at the centre of the top face, +z up (the top face is one
    merged face with a hole once loaded as a polyhedron).
    """
    return hole_block_mesh(outer, height, hole, name)


def block_with_slot_mesh(length: float = 0.16, width: float = 0.16, height: float = 0.08,
                         slot_width: float = 0.04, slot_depth: float = 0.04,
                         name: str = 'slot_block') -> PolygonMesh:
    """
    Build a block with a slot along x across its top.

    Block ``length`` (x) x ``width`` (y) x ``height`` (z) [m] with a slot along x across the
    top (``slot_width`` in y, ``slot_depth`` in z); origin at the centre of the top face.
    """
    return slot_block_mesh(length, width, height, slot_width, slot_depth, name)


def _prism_along_y(profile_xz: Sequence[Sequence[float]], thickness: float,
                   name: str) -> PolygonMesh:
    """
    Extrude a simple polygon of the x-z plane along y.

    Extrude a simple polygon of the x-z plane along y (``|y| <= thickness / 2``) with
    :func:`prism_mesh`, turned by +90 deg about z; the corners may be given in either winding
    order (the faces are oriented outwards).
    """
    P = np.asarray(profile_xz, dtype=float)
    area = 0.5 * np.sum(P[:, 0] * np.roll(P[:, 1], -1) - np.roll(P[:, 0], -1) * P[:, 1])
    # prism_mesh wants (y', z) counter-clockwise; the turn maps y' -> -x, so y' = -x
    yz = np.column_stack([-P[:, 0], P[:, 1]])
    if area > 0:        # counter-clockwise in (x, z) is clockwise in (-x, z)
        yz = yz[::-1]
    m = prism_mesh(yz, thickness, name)
    Rz = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    return PolygonMesh(m.vertices @ Rz.T, m.faces, name)


def t_peg_mesh(bar_width: float = 0.06, bar_height: float = 0.015, stem_width: float = 0.02,
               stem_length: float = 0.035, thickness: float = 0.02,
               name: str = 't_peg') -> PolygonMesh:
    """
    T-shaped plate.

    a bar ``bar_width`` (x) x ``bar_height`` (z) on a stem ``stem_width`` x ``stem_length`` below
    it, ``thickness`` along y [m]. Origin at the centre of the bar's underside (where the stem
    meets the bar), +z from the stem towards the bar; the two large faces are ``y = +-thickness /
    2``.
    """
    B, h, s, L = bar_width / 2.0, float(bar_height), stem_width / 2.0, float(stem_length)
    profile = [(-s, -L), (s, -L), (s, 0.0), (B, 0.0), (B, h), (-B, h), (-B, 0.0), (-s, 0.0)]
    return _prism_along_y(profile, thickness, name)


def t_slot_block_mesh(width: float = 0.10, height: float = 0.075, thickness: float = 0.02,
                      bar_slot_width: float = 0.064, bar_slot_depth: float = 0.015,
                      stem_slot_width: float = 0.02, stem_slot_depth: float = 0.04,
                      name: str = 't_slot_block') -> PolygonMesh:
    """
    Build a block with a T-shaped slot through it along y, open at the top.

    Block ``width`` (x) x ``height`` (z) x ``thickness`` (y) [m] with a T-shaped slot
    through it along y, open at the top: a wide part ``bar_slot_width`` x ``bar_slot_depth``
    under the top face and a narrow part ``stem_slot_width`` x ``stem_slot_depth`` below.
    Origin at the centre of the shoulders (the bottom of the wide part), so that
    :func:`t_peg_mesh` with the defaults sits inserted at the identity pose: shoulders under
    the bar, stem walls tight (zero clearance), 1 mm bar clearance each side, 5 mm under the
    stem, and the peg's large faces and top flush with the block's.
    """
    W, Bs, s = width / 2.0, bar_slot_width / 2.0, stem_slot_width / 2.0
    top, bottom, D = float(bar_slot_depth), bar_slot_depth - height, float(stem_slot_depth)
    profile = [(-W, bottom), (W, bottom), (W, top), (Bs, top), (Bs, 0.0), (s, 0.0), (s, -D),
               (-s, -D), (-s, 0.0), (-Bs, 0.0), (-Bs, top), (-W, top)]
    return _prism_along_y(profile, thickness, name)
