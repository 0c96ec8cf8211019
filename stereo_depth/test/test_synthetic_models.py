"""Shipped object models: reproducible, closed, outward, convex planar faces, exact sizes."""

import numpy as np
import pytest
from stereo_depth.synthetic.make_models import (
    build_models, check_closed_manifold, MODEL_NAMES, PRIMITIVES, write_models)
from stereo_manip_tools.mesh_io import find_model, load_obj


def _volume(mesh):
    V, T = mesh.vertices, mesh.triangles()
    return np.einsum('ij,ij->i', V[T[:, 0]], np.cross(V[T[:, 1]], V[T[:, 2]])).sum() / 6


@pytest.mark.parametrize('name', MODEL_NAMES)
def test_shipped_model_matches_generator_and_is_closed(name):
    shipped = load_obj(find_model(name))
    mesh, _ = build_models()[name]
    np.testing.assert_allclose(shipped.vertices, mesh.vertices, atol=1e-8)
    assert [list(f) for f in shipped.faces] == [list(f) for f in mesh.faces]
    check_closed_manifold(shipped, planarity_tol=1e-8)


def test_write_models_round_trip(tmp_path):
    paths = write_models(tmp_path)
    assert sorted(p.stem for p in paths) == sorted(MODEL_NAMES)


def test_check_rejects_inward_and_open_meshes():
    mesh, _ = build_models()['cube']
    flipped = type(mesh)(mesh.vertices, [f[::-1] for f in mesh.faces], 'flipped')
    with pytest.raises(ValueError, match='volume'):
        check_closed_manifold(flipped)
    opened = type(mesh)(mesh.vertices, mesh.faces[:-1], 'open')
    with pytest.raises(ValueError, match='edge'):
        check_closed_manifold(opened)


def test_box_dimensions_and_frames():
    m = build_models()
    peg = m['peg'][0].vertices
    np.testing.assert_allclose(peg.min(0), [-0.02, -0.02, 0.0])
    np.testing.assert_allclose(peg.max(0), [0.02, 0.02, 0.12])
    for name in ('hole_block', 'slot_block'):
        V = m[name][0].vertices
        np.testing.assert_allclose(V.min(0), [-0.08, -0.08, -0.08])
        np.testing.assert_allclose(V.max(0), [0.08, 0.08, 0.0])
    tab = m['table'][0].vertices
    np.testing.assert_allclose(tab.min(0), [-0.5, -0.5, -0.02])
    np.testing.assert_allclose(tab.max(0), [0.5, 0.5, 0.0])
    cube = m['cube'][0].vertices
    np.testing.assert_allclose(cube.max(0) - cube.min(0), [0.08] * 3)


def test_hole_and_slot_volumes_and_walls():
    m = build_models()
    assert _volume(m['hole_block'][0]) == pytest.approx(0.16 ** 2 * 0.08 - 0.04 ** 2 * 0.08)
    assert _volume(m['slot_block'][0]) == pytest.approx(0.16 ** 2 * 0.08 - 0.04 * 0.04 * 0.16)
    # The zero-clearance hole: four wall faces on the planes |x| = 0.02 or |y| = 0.02, their
    # normals pointing into the hole (towards the axis), spanning the full height.
    hb = m['hole_block'][0]
    normals = hb.face_normals()
    walls = 0
    for f, n in zip(hb.faces, normals):
        P = hb.vertices[f]
        c = P.mean(0)
        if abs(n[2]) < 1e-12 and max(abs(c[0]), abs(c[1])) < 0.03:
            walls += 1
            assert np.dot(n, -c) > 0
            assert P[:, 2].min() == pytest.approx(-0.08) and P[:, 2].max() == pytest.approx(0.0)
    assert walls == 4
    # Peg volume and a zero-clearance fit: peg cross-section equals the hole.
    assert _volume(m['peg'][0]) == pytest.approx(0.04 * 0.04 * 0.12)


@pytest.mark.parametrize('name', ['sphere', 'torus', 'superquadric'])
def test_primitive_vertices_lie_on_analytic_surface(name):
    V = build_models()[name][0].vertices
    p = PRIMITIVES[name]
    if name == 'sphere':
        res = np.linalg.norm(V, axis=1) - p['radius']
    elif name == 'torus':
        res = (np.hypot(V[:, 0], V[:, 1]) - p['major_radius']) ** 2 + V[:, 2] ** 2 \
            - p['minor_radius'] ** 2
    else:
        a1, a2, a3, e1, e2 = p['a1'], p['a2'], p['a3'], p['eps1'], p['eps2']
        res = (np.abs(V[:, 0] / a1) ** (2 / e2) + np.abs(V[:, 1] / a2) ** (2 / e2)) ** (e2 / e1) \
            + np.abs(V[:, 2] / a3) ** (2 / e1) - 1
    np.testing.assert_allclose(res, 0.0, atol=1e-9)
    assert len(build_models()[name][0].faces) <= 3000
