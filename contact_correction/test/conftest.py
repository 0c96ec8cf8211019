"""Hand-built contact configurations with analytic answers (all poses in the fixed frame)."""

from contact_correction.polyhedron import polyhedron_from_mesh
from contact_correction.shapes import (
    block_with_hole_mesh, block_with_slot_mesh, box_mesh, prism_mesh)
import numpy as np
import pytest
from stereo_manip_tools.transforms import make_transform, rotation_about_axis


def rot(axis, angle):
    return rotation_about_axis(np.asarray(axis, dtype=float), angle)


def about_point(R, p):
    """Pose rotating by R about the point p (4x4)."""
    p = np.asarray(p, dtype=float)
    return make_transform(R, p - R @ p)


@pytest.fixture(scope='session')
def shapes():
    return {
        'peg': polyhedron_from_mesh(box_mesh((0.04, 0.04, 0.12), (0, 0, 0.06), 'peg')),
        'cube': polyhedron_from_mesh(box_mesh((0.04, 0.04, 0.04), (0, 0, 0.02), 'cube')),
        'table': polyhedron_from_mesh(box_mesh((0.5, 0.5, 0.05), (0, 0, -0.025), 'table')),
        'hole_block': polyhedron_from_mesh(block_with_hole_mesh()),
        'slot_block': polyhedron_from_mesh(block_with_slot_mesh()),
        # triangular ridge along x, apex edge at z = 0
        'ridge': polyhedron_from_mesh(prism_mesh([(-0.05, -0.05), (0.05, -0.05), (0.0, 0.0)],
                                                 0.3, 'ridge')),
    }


@pytest.fixture(scope='session')
def configs(shapes):
    """Map a name to (moving, fixed, true relative pose, expected rotation rank)."""
    out = {}
    out['cube_on_table'] = (shapes['cube'], shapes['table'],
                            make_transform(rot([0, 0, 1], 0.3), [0.01, 0.02, 0.0]), 2)
    # peg rolled 0.5 rad about its bottom edge y = -0.02 (edge along x) onto the table
    out['edge_on_face'] = (shapes['peg'], shapes['table'],
                           about_point(rot([1, 0, 0], 0.5), [0, -0.02, 0]), 1)
    # cube tipped onto its corner (0.02, 0.02, 0)
    T = about_point(rot([1, -1, 0], 0.4), [0.02, 0.02, 0.0])
    T[2, 3] -= shapes['cube'].transformed_vertices(T)[:, 2].min()
    out['vertex_on_face'] = (shapes['cube'], shapes['table'], T, 0)
    out['peg_in_hole'] = (shapes['peg'], shapes['hole_block'],
                          make_transform(np.eye(3), [0, 0, -0.03]), 3)
    out['peg_in_slot'] = (shapes['peg'], shapes['slot_block'],
                          make_transform(np.eye(3), [0.01, 0, -0.04]), 3)
    # peg lying across the ridge (peg length along y), its -z side face (after rotation) on
    # the apex edge: face of the moving object on an edge of the fixed object
    R = rot([1, 0, 0], -np.pi / 2)          # peg +z -> +y
    T = make_transform(R, [0.0, -0.06, 0.02])
    out['face_on_edge'] = (shapes['peg'], shapes['ridge'], T, 1)
    return out
