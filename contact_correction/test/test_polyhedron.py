"""Polyhedron construction: merged faces, edges, convexity, closedness, file formats."""

from contact_correction.polyhedron import load_polyhedron, polyhedron_from_mesh
from contact_correction.shapes import block_with_hole_mesh, block_with_slot_mesh, box_mesh
import numpy as np
import pytest
from stereo_manip_tools.mesh_io import PolygonMesh, save_obj


def test_box_elements():
    p = polyhedron_from_mesh(box_mesh((0.1, 0.2, 0.3)))
    assert (len(p.feature_vertices), p.n_edges, p.n_faces) == (8, 12, 6)
    assert p.edge_convex.all()
    # outward normals: the centre is behind every face plane by half the size
    assert np.allclose(np.sort(-p.face_offsets), -np.array([0.15, 0.15, 0.1, 0.1, 0.05, 0.05]))
    assert np.allclose(np.abs(p.face_normals).sum(1), 1.0)
    # every edge joins two faces with perpendicular normals
    n = p.face_normals[p.edge_faces]
    assert np.allclose(np.einsum('ij,ij->i', n[:, 0], n[:, 1]), 0.0)


def test_triangulated_box_merges_coplanar_triangles():
    m = box_mesh((0.1, 0.1, 0.1))
    tri = PolygonMesh(m.vertices, list(m.triangles()), 'tri_box')
    p = polyhedron_from_mesh(tri)
    assert p.n_faces == 6 and p.n_edges == 12 and p.edge_convex.all()


def test_block_with_hole_is_non_convex():
    p = polyhedron_from_mesh(block_with_hole_mesh(0.16, 0.04, 0.08))
    assert p.n_faces == 10          # top and bottom rings are single faces with a hole
    assert p.n_edges == 24
    assert (~p.edge_convex).sum() == 4      # the four vertical edges of the hole
    concave = p.edge_vertices[~p.edge_convex]
    d = p.vertices[concave[:, 1]] - p.vertices[concave[:, 0]]
    assert np.allclose(np.abs(d[:, 2]), 0.08) and np.allclose(d[:, :2], 0.0)
    w = p.contains(np.array([[0.0, 0.0, -0.04], [0.05, 0.0, -0.04], [0.0, 0.0, 0.01]]))
    assert np.allclose(w, [0.0, 1.0, 0.0], atol=1e-9)
    # a point in the hole is 0.02 from the walls, not inside the top face's region
    assert p.distance_to_surface(np.array([[0.0, 0.0, -0.04]]))[0] == pytest.approx(0.02)
    top = int(np.argmax(p.face_normals[:, 2]))
    assert p.face_distance(top, np.array([[0.0, 0.0, 0.0]]))[0] == pytest.approx(0.02)


def test_slot_block_concave_edges_and_nonconvex_end_faces():
    p = polyhedron_from_mesh(block_with_slot_mesh())
    assert p.n_faces == 10 and (~p.edge_convex).sum() == 2
    area = sum(0.5 * np.linalg.norm(np.cross(t[1] - t[0], t[2] - t[0]))
               for t in p.tri_corners[p.face_triangles[0]])
    assert area == pytest.approx(0.16 * 0.08 - 0.04 * 0.04)


def test_open_mesh_is_rejected_with_a_clear_message():
    m = box_mesh((0.1, 0.1, 0.1))
    with pytest.raises(ValueError, match='not closed'):
        polyhedron_from_mesh(PolygonMesh(m.vertices, m.faces[:-1], 'open_box'))


def test_inconsistent_orientation_is_rejected():
    m = box_mesh((0.1, 0.1, 0.1))
    faces = [f.copy() for f in m.faces]
    faces[0] = faces[0][::-1]
    with pytest.raises(ValueError, match='same direction|not closed'):
        polyhedron_from_mesh(PolygonMesh(m.vertices, faces, 'flipped'))


def test_load_obj_and_stl(tmp_path):
    m = block_with_hole_mesh()
    save_obj(m, tmp_path / 'hole.obj')
    p = load_polyhedron(tmp_path / 'hole.obj')
    assert p.n_faces == 10 and p.name == 'hole'
    o3d = pytest.importorskip('open3d')
    tm = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(m.vertices),
                                   o3d.utility.Vector3iVector(m.triangles()))
    tm.compute_triangle_normals()
    o3d.io.write_triangle_mesh(str(tmp_path / 'hole.stl'), tm)
    q = load_polyhedron(tmp_path / 'hole.stl')
    assert q.n_faces == 10 and q.n_edges == 24 and (~q.edge_convex).sum() == 4


def test_unknown_model_name():
    with pytest.raises(FileNotFoundError):
        load_polyhedron('no_such_model_xyz')
