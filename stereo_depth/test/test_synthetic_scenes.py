"""
Scene trajectories.

Contact phases are geometrically true, nothing interpenetrates, and the joint pairs obey their
joint constraints exactly.
"""

import numpy as np
import pytest
from stereo_depth.synthetic import make_scene, SCENES
from stereo_manip_tools.mesh_io import find_model, load_obj
from stereo_manip_tools.transforms import invert_transform, is_rotation_matrix


def _peg_samples():
    g = np.linspace(-0.02, 0.02, 7)
    z = np.linspace(0.0, 0.12, 25)
    X, Y, Z = np.meshgrid(g, g, z, indexing='ij')
    return np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1)


def _inside_hole_block(P, tol=1e-9):
    x, y, z = np.abs(P[:, 0]), np.abs(P[:, 1]), P[:, 2]
    solid = (x < 0.08 - tol) & (y < 0.08 - tol) & (z < -tol) & (z > -0.08 + tol)
    hole = (x < 0.02 + tol) & (y < 0.02 + tol)
    return solid & ~hole


def _inside_slot_block(P, tol=1e-9):
    x, y, z = np.abs(P[:, 0]), np.abs(P[:, 1]), P[:, 2]
    solid = (x < 0.08 - tol) & (y < 0.08 - tol) & (z < -tol) & (z > -0.08 + tol)
    slot = (y < 0.02 + tol) & (z > -0.04 - tol)
    return solid & ~slot


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_peg_in_hole_phases_are_geometrically_true(seed):
    scene = make_scene('peg_in_hole', seed)
    peg = load_obj(find_model('peg')).vertices
    samples = _peg_samples()
    seen = set()
    for k in range(scene.n_frames):
        ex = scene.extras(k)
        T = ex['T_block_peg']
        assert is_rotation_matrix(T[:3, :3], 1e-9)
        # Consistency with the world poses.
        W = scene.world_poses(k)
        np.testing.assert_allclose(invert_transform(W['hole_block']) @ W['peg'], T, atol=1e-12)
        P = samples @ T[:3, :3].T + T[:3, 3]
        assert not _inside_hole_block(P).any(), f'frame {k}: peg penetrates the block'
        V = peg @ T[:3, :3].T + T[:3, 3]
        on_top = np.abs(V[:, 2]) < 1e-9
        phase = ex['contact_phase']
        seen.add(phase)
        if phase == 'none':
            assert V[:, 2].min() > 1e-6
        elif phase == 'vertex_face':
            assert on_top.sum() == 1 and V[:, 2].min() > -1e-9
            v = V[on_top][0]
            assert max(abs(v[0]), abs(v[1])) > 0.02 and max(abs(v[0]), abs(v[1])) < 0.08
        elif phase == 'edge_face':
            assert on_top.sum() == 2 and V[:, 2].min() > -1e-9
        elif phase in ('face_face', 'aligned'):
            assert on_top.sum() == 4
        elif phase == 'inserted':
            assert V[:, 2].min() < 0
            np.testing.assert_allclose(np.sort(np.unique(np.round(V[:, 0], 12))), [-0.02, 0.02],
                                       atol=1e-12)
    assert {'none', 'vertex_face', 'edge_face', 'face_face', 'inserted'} <= seen


def test_peg_in_hole_insertion_is_a_straight_line():
    scene = make_scene('peg_in_hole', 4)
    pts = np.array([scene.extras(k)['T_block_peg'][:3, 3] for k in range(scene.n_frames)
                    if scene.extras(k)['contact_phase'] == 'inserted'])
    assert len(pts) > 10
    np.testing.assert_allclose(pts[:, :2], 0.0, atol=1e-12)
    assert np.all(np.diff(pts[:, 2]) <= 0)


def test_peg_in_slot_never_penetrates():
    scene = make_scene('peg_in_slot', 3)
    samples = _peg_samples()
    for k in range(scene.n_frames):
        T = scene.extras(k)['T_block_peg']
        assert not _inside_slot_block(samples @ T[:3, :3].T + T[:3, 3]).any(), k


@pytest.mark.parametrize('name', ['revolute_pair', 'prismatic_pair', 'spherical_pair'])
def test_joint_pairs_satisfy_their_constraints(name):
    scene = make_scene(name, 11)
    qs = []
    for k in range(0, scene.n_frames, 7):
        W = scene.world_poses(k)
        j = scene.extras(k)['joint']
        T = invert_transform(W[j['base']]) @ W[j['child']]
        np.testing.assert_allclose(T, j['T_base_child'], atol=1e-12)
        R, t = T[:3, :3], T[:3, 3]
        if j['type'] == 'revolute':
            np.testing.assert_allclose(R @ j['axis_child'], j['axis_base'], atol=1e-12)
            np.testing.assert_allclose(T[:3, :3] @ j['point_child'] + t, j['point_base'],
                                       atol=1e-12)
            qs.append(j['q'])
        elif j['type'] == 'prismatic':
            np.testing.assert_allclose(R, np.eye(3), atol=1e-12)
            np.testing.assert_allclose(np.cross(t, j['axis_base']), 0.0, atol=1e-12)
            qs.append(j['q'])
        else:
            np.testing.assert_allclose(R @ j['center_child'] + t, j['center_base'], atol=1e-12)
            qs.append(np.linalg.norm(j['rotation_vector']))
    assert np.ptp(qs) > 0.05, 'the joint hardly moves'


@pytest.mark.parametrize('name', SCENES)
def test_scenes_are_deterministic_and_in_working_range(name):
    a, b = make_scene(name, 5), make_scene(name, 5)
    for k in (0, 17, a.n_frames + 3):
        for n in a.objects:
            np.testing.assert_array_equal(a.poses(k)[n], b.poses(k)[n])
    # Objects other than the table stay 0.25-1.5 m in front of the camera.
    for k in range(0, a.n_frames, 10):
        for n, T in a.poses(k).items():
            if n != 'table':
                assert 0.25 < T[2, 3] < 1.5, (n, k, T[2, 3])


def test_unknown_scene_is_refused():
    with pytest.raises(ValueError, match='unknown scene'):
        make_scene('kitchen')
