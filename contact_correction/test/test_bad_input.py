"""Bad input never crashes: the pose is passed through unchanged with a flag and a reason."""

from contact_correction.contact_relation import ContactPair, EDGE, FACE, VERTEX
from contact_correction.correction import correct_pose
from contact_correction.polyhedron import polyhedron_from_mesh
from contact_correction.shapes import box_mesh
from contact_correction.trajectory import correct_trajectory
import numpy as np
import pytest
from stereo_manip_tools.mesh_io import PolygonMesh
from stereo_manip_tools.transforms import make_transform

I4 = np.eye(4)


def test_nan_pose_passed_through(configs):
    m, f, T, _ = configs['peg_in_hole']
    bad = T.copy()
    bad[0, 3] = np.nan
    r = correct_pose(m, f, bad, I4)
    assert not r.corrected and 'NaN' in r.status
    assert np.array_equal(r.T_moving, bad, equal_nan=True)
    r = correct_pose(m, f, T, np.full((4, 4), np.nan))
    assert not r.corrected and 'fixed pose' in r.status


def test_non_rotation_matrix_passed_through(configs):
    m, f, T, _ = configs['cube_on_table']
    bad = T.copy()
    bad[:3, :3] *= 1.1
    r = correct_pose(m, f, bad, I4)
    assert not r.corrected and 'orthonormal' in r.status
    assert np.array_equal(r.T_moving, bad)
    r = correct_pose(m, f, np.eye(3), I4)
    assert not r.corrected and 'shape' in r.status


def test_far_pose_passed_through(configs):
    m, f, T, _ = configs['peg_in_hole']
    far = T.copy()
    far[2, 3] += 0.5
    r = correct_pose(m, f, far, I4)        # detection: nothing within tolerance
    assert not r.corrected and 'no contact' in r.status
    assert np.array_equal(r.T_moving, far)
    # a given relation that is far from the pose: the correction would be too large
    m, f, T, _ = configs['cube_on_table']
    pairs = [ContactPair(VERTEX, v, FACE, int(np.argmax(f.face_normals[:, 2])))
             for v in (0, 1, 4, 5)]
    up = T.copy()
    up[2, 3] += 0.05
    r = correct_pose(m, f, up, I4, pairs)
    assert not r.corrected and 'far from the contact relation' in r.status
    assert np.array_equal(r.T_moving, up)
    assert r.geometry is not None and np.allclose(r.geometry.distances, 0.05)


def test_unsatisfiable_or_invalid_relation_passed_through(configs):
    m, f, T, _ = configs['cube_on_table']
    # a vertex on the table top and on the table bottom at once
    top, bottom = int(np.argmax(f.face_normals[:, 2])), int(np.argmin(f.face_normals[:, 2]))
    r = correct_pose(m, f, T, I4, [ContactPair(VERTEX, 0, FACE, top),
                                   ContactPair(VERTEX, 0, FACE, bottom)])
    assert not r.corrected and 'not satisfiable' in r.status
    r = correct_pose(m, f, T, I4, [ContactPair(EDGE, 0, FACE, top)])
    assert not r.corrected and 'unsupported contact pair kind' in r.status


def test_non_closed_model_is_a_clear_error():
    m = box_mesh((0.1, 0.1, 0.1))
    with pytest.raises(ValueError, match="model 'open' is not closed"):
        polyhedron_from_mesh(PolygonMesh(m.vertices, m.faces[1:], 'open'))


def test_trajectory_reports_each_frame(configs):
    m, f, T, _ = configs['peg_in_hole']
    poses = np.stack([T, T + 0.0, T])
    poses[1, 1, 3] = np.nan
    poses[2, 2, 3] = 0.5
    res = correct_trajectory(m, f, poses, I4)
    assert [r.corrected for r in res] == [True, False, False]
    assert res[0].rotation_rank == 3 and 'optimal' in res[0].method
    with pytest.raises(ValueError, match='fixed poses'):
        correct_trajectory(m, f, poses, np.stack([I4, I4]))


def test_penetrating_observation_is_corrected_out(configs):
    m, f, T, _ = configs['cube_on_table']
    down = make_transform(T[:3, :3], T[:3, 3] - [0, 0, 1.5e-3])
    r = correct_pose(m, f, down, I4, tolerance=1e-3, penetration_tolerance=3e-3)
    assert r.corrected and r.penetration_before == pytest.approx(1.5e-3, abs=1e-9)
    assert r.penetration_after < 1e-12 and r.max_residual < 1e-12
    assert np.allclose(r.T_moving[:3, 3], T[:3, 3], atol=1e-12)


def test_degenerate_configuration_is_recognised(configs):
    """
    A peg-in-hole relation with the peg at the rim is degenerate, inside the hole not.

    A peg-in-hole relation evaluated with the peg at the rim (all contacts at one height,
    the peg may tilt) is degenerate; inside the hole it is not.
    """
    from contact_correction.correction import _near_degenerate
    from contact_correction.optimal_correction import constraint_matrix
    from contact_correction.contact_relation import detect_contact_relation
    m, f, T, _ = configs['peg_in_hole']
    pairs = detect_contact_relation(m, f, T, I4, 1e-7)
    assert not _near_degenerate(constraint_matrix(m, f, T, pairs)[0], m.size)
    rim = make_transform(np.eye(3), [0.0, 0.0, -2e-7])
    assert _near_degenerate(constraint_matrix(m, f, rim, pairs)[0], m.size)
    # observed above the rim: the free depth kept as observed cannot realise the relation
    above = make_transform(np.eye(3), [0.0, 1e-3, 0.004])
    r = correct_pose(m, f, above, I4, pairs)
    assert not r.corrected and 'outside its elements' in r.status
