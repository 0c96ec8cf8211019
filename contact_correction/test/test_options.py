"""
correct_trajectory options / node parameters of issue 13.

Recognised relations by default, explicit relation, units, plain CSV, defaults in --help; node
extras only with subscribers, NaN parameters and non-regular model files refused.
"""

import os

import contact_correction.contact_correction_node as node_module
from contact_correction.contact_correction_node import ContactCorrectionNode
from contact_correction.contact_relation import penetration_depth
from contact_correction.offline import main, read_csv
from contact_correction.shapes import t_peg_mesh, t_slot_block_mesh
from contact_correction.tracks import make_tracks, noisy_track, track_models
from geometry_msgs.msg import PoseStamped
import numpy as np
import pytest
from rclpy.parameter import Parameter
from std_msgs.msg import Header
from stereo_manip_tools.conversions import matrix_to_pose, ns_to_stamp
from stereo_manip_tools.mesh_io import PolygonMesh, save_obj
from stereo_manip_tools.testing import spin_until
from stereo_manip_tools.transforms import quaternion_from_matrix

I4 = np.eye(4)


@pytest.fixture(scope='module')
def t_track():
    tracks = {t.name: t for t in make_tracks(track_models())}
    return tracks['t_peg_slot_y']


def _write_models(tmp_path):
    peg, block = tmp_path / 't_peg.obj', tmp_path / 't_slot_block.obj'
    save_obj(t_peg_mesh(), peg)
    save_obj(t_slot_block_mesh(), block)
    return peg, block


def _write_csv(path, To, Tf):
    with open(path, 'w') as fh:
        fh.write('stamp_ns,x,y,z,qx,qy,qz,qw,fixed_x,fixed_y,fixed_z,fixed_qx,fixed_qy,'
                 'fixed_qz,fixed_qw\n')
        qf = quaternion_from_matrix(Tf[:3, :3])
        for k, T in enumerate(To):
            fh.write(','.join(str(v) for v in [k * 10**8, *T[:3, 3],
                                               *quaternion_from_matrix(T[:3, :3]),
                                               *Tf[:3, 3], *qf]) + '\n')


def test_offline_t_peg_flush_with_defaults(tmp_path, t_track):
    """
    The issue's scenario as a new user runs it.

    Every inserted (flush) frame corrected, the free translation (normal to the flush faces)
    unchanged, no penetration left anywhere.
    """
    peg_file, block_file = _write_models(tmp_path)
    Tf, Tt, To = noisy_track(t_track, np.random.default_rng(21), 1e-3, np.deg2rad(1.0))
    src, out = tmp_path / 'track.csv', tmp_path / 'out.csv'
    _write_csv(src, To, Tf)
    assert main([str(src), '-o', str(out), '--moving', str(peg_file), '--fixed',
                 str(block_file), '--sigma-translation', '0.001',
                 '--sigma-rotation-deg', '1']) == 0
    lines = out.read_text().splitlines()
    assert lines[0].startswith('stamp_ns,x,y,z,qx,qy,qz,qw,corrected,method')   # plain header
    _, Tc, _ = read_csv(out)
    cols = lines[0].split(',')
    rows = [dict(zip(cols, ln.split(',', len(cols) - 1))) for ln in lines[1:]]
    for k, phase in enumerate(t_track.phases):
        assert penetration_depth(t_track.moving, t_track.fixed, Tc[k], Tf, 0.002) < 1e-5, k
        if phase == 'inserted_flush':
            assert rows[k]['corrected'] == '1', rows[k]['status']
            y_obs = np.linalg.solve(Tf, To[k])[1, 3]
            y_cor = np.linalg.solve(Tf, Tc[k])[1, 3]
            assert abs(y_cor - y_obs) < 1e-6
    # --reference-point centroid: the T-peg's centroid keeps its free coordinate instead
    assert main([str(src), '-o', str(out), '--moving', str(peg_file), '--fixed',
                 str(block_file), '--reference-point', 'centroid']) == 0
    _, Tc, _ = read_csv(out)
    c = t_track.moving.centroid
    for k, phase in enumerate(t_track.phases):
        assert penetration_depth(t_track.moving, t_track.fixed, Tc[k], Tf, 0.002) < 1e-5, k
        if phase == 'inserted_flush':
            y_obs = (np.linalg.solve(Tf, To[k]) @ np.append(c, 1.0))[1]
            y_cor = (np.linalg.solve(Tf, Tc[k]) @ np.append(c, 1.0))[1]
            assert abs(y_cor - y_obs) < 1e-6


def test_offline_explicit_relation_units_and_help(tmp_path, t_track, capsys):
    peg_file, block_file = _write_models(tmp_path)
    Tf, _, To = noisy_track(t_track, np.random.default_rng(22), 1e-3, np.deg2rad(1.0))
    k0 = t_track.phases.index('inserted_flush')
    src, out = tmp_path / 'track.csv', tmp_path / 'out.csv'
    _write_csv(src, To[k0:k0 + 4], Tf)
    relation = 'vertex 0 - face 4; vertex 1 - face 4; vertex 4 - face 8; vertex 5 - face 7; ' \
               'vertex 6 - face 7; vertex 7 - face 5; vertex 8 - face 4; vertex 12 - face 8'
    assert main([str(src), '-o', str(out), '--moving', str(peg_file), '--fixed',
                 str(block_file), '--relation', relation]) == 0
    text = out.read_text()
    assert text.count(',given,') == 4
    # a model in millimetres is refused with a clear message
    mm = tmp_path / 'peg_mm.obj'
    m = t_peg_mesh()
    save_obj(PolygonMesh(m.vertices * 1000.0, m.faces, 'peg_mm'), mm)
    assert main([str(src), '-o', str(out), '--moving', str(mm), '--fixed',
                 str(block_file)]) == 2
    assert 'millimetres' in capsys.readouterr().err
    # bad relation text, NaN option
    assert main([str(src), '-o', str(out), '--moving', str(peg_file), '--fixed',
                 str(block_file), '--relation', 'vertex 0 face 4']) == 2
    with pytest.raises(SystemExit):
        main([str(src), '-o', str(out), '--sigma-translation', 'nan'])
    with pytest.raises(SystemExit):     # an AR(1) correlation must be in [0, 1)
        main([str(src), '-o', str(out), '--noise-correlation', '1.0'])
    # defaults are shown in --help; a missing --moving is announced
    with pytest.raises(SystemExit):
        main(['--help'])
    help_text = capsys.readouterr().out
    assert '(default: 0.002)' in help_text and '(default: 20.0)' in help_text
    assert '--reference-point {origin,centroid}' in help_text and \
        '(default: origin)' in help_text
    with pytest.raises(SystemExit):
        main([str(src), '-o', str(out), '--reference-point', 'middle'])
    main([str(src), '-o', str(out)])
    assert "no --moving given; using the shipped model 'peg'" in capsys.readouterr().err


def _pose_msg(T, stamp_ns):
    return PoseStamped(header=Header(stamp=ns_to_stamp(int(stamp_ns)), frame_id='world'),
                       pose=matrix_to_pose(T))


@pytest.mark.ros
def test_node_extras_only_with_subscribers_and_bounded(ros_node, monkeypatch):
    built = []
    real = node_module.matrices_to_path
    monkeypatch.setattr(node_module, 'matrices_to_path',
                        lambda *a, **k: built.append(1) or real(*a, **k))
    node = ContactCorrectionNode(context=ros_node.context, parameter_overrides=[
        Parameter('fixed_pose_static', value=[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]),
        Parameter('track_length', value=3)])
    try:
        poses = []
        ros_node.create_subscription(PoseStamped, 'corrected_pose', poses.append, 10)
        pub = ros_node.create_publisher(PoseStamped, 'moving_pose', 10)
        assert spin_until([ros_node, node], lambda: pub.get_subscription_count() > 0, 10)
        T = np.eye(4)
        T[2, 3] = -0.03
        for k in range(5):
            pub.publish(_pose_msg(T, (k + 1) * 10**7))
            assert spin_until([ros_node, node], lambda: len(poses) > k, 10)
        assert built == []                 # nobody listens to corrected_track
        assert len(node.track) == 3        # bounded by track_length
        assert node.state_pub.get_subscription_count() == 0
    finally:
        node.destroy_node()


@pytest.mark.ros
def test_node_refuses_nan_parameters_and_fifo_models(ros_node, tmp_path):
    node = ContactCorrectionNode(context=ros_node.context, parameter_overrides=[
        Parameter('fixed_pose_static', value=[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])])
    try:
        for name in ('sigma_translation', 'tolerance', 'switch_cost'):
            r = node.set_parameters([Parameter(name, value=float('nan'))])[0]
            assert not r.successful and ('finite' in r.reason or 'range' in r.reason), name
        r = node.set_parameters([Parameter('relation', value='vertex 1 face 2')])[0]
        assert not r.successful and 'relation entry' in r.reason
        r = node.set_parameters([Parameter('reference_point', value='middle')])[0]
        assert not r.successful and 'origin, centroid' in r.reason
        assert node.set_parameters([Parameter('reference_point', value='centroid')])[0] \
            .successful
        np.testing.assert_allclose(node._options()['reference_point'], node.moving.centroid)
        assert node.set_parameters([Parameter('switch_cost', value=5.0)])[0].successful
    finally:
        node.destroy_node()
    if not hasattr(os, 'mkfifo'):
        return
    fifo = tmp_path / 'model.obj'
    os.mkfifo(fifo)
    node = ContactCorrectionNode(context=ros_node.context, parameter_overrides=[
        Parameter('moving_object', value=str(fifo)),
        Parameter('fixed_pose_static', value=[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])])
    try:
        assert 'not a regular file' in node.model_error
    finally:
        node.destroy_node()
