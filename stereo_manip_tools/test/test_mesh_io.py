"""Pure tests of the shared OBJ loader: round trip, polygon faces, normals, errors."""

import numpy as np
import pytest

from stereo_manip_tools.mesh_io import find_model, load_obj, PolygonMesh, save_obj


def unit_cube() -> PolygonMesh:
    v = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], dtype=float)
    faces = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2],
             [1, 3, 7, 5]]
    return PolygonMesh(v, faces, 'cube')


def test_round_trip_keeps_polygons(tmp_path):
    cube = unit_cube()
    save_obj(cube, tmp_path / 'cube.obj', comment='unit cube')
    loaded = load_obj(tmp_path / 'cube.obj')
    assert loaded.name == 'cube'
    assert np.allclose(loaded.vertices, cube.vertices)
    assert [f.tolist() for f in loaded.faces] == [f.tolist() for f in cube.faces]
    assert len(loaded.triangles()) == 12


def test_normals_point_outward():
    cube = unit_cube()
    centre = cube.vertices.mean(axis=0)
    for f, n in zip(cube.faces, cube.face_normals()):
        assert np.dot(cube.vertices[f].mean(axis=0) - centre, n) > 0.49


def test_slash_and_negative_indices(tmp_path):
    p = tmp_path / 't.obj'
    p.write_text('v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\nf 1//1 2//1 3//1\nf -3 -2 -1\n')
    m = load_obj(p)
    assert [f.tolist() for f in m.faces] == [[0, 1, 2], [0, 1, 2]]


def test_malformed_record_names_line(tmp_path):
    p = tmp_path / 'bad.obj'
    p.write_text('v 0 0 0\nv 1 zero 0\n')
    with pytest.raises(ValueError, match=r'bad.obj:2'):
        load_obj(p)


def test_face_with_missing_vertex_rejected():
    with pytest.raises(ValueError, match='missing vertex'):
        PolygonMesh(np.zeros((3, 3)), [[0, 1, 5]])


def test_find_model_reports_search_path(tmp_path):
    with pytest.raises(FileNotFoundError, match='not found in'):
        find_model('no_such_model', [tmp_path])
    save_obj(unit_cube(), tmp_path / 'cube.obj')
    assert find_model('cube', [tmp_path]) == tmp_path / 'cube.obj'
