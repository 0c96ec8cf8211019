"""Offline command ``estimate_joint``: CSV and bag input, JSON/figure/CSV output, bad input."""

import csv
import json
import subprocess

from joint_estimator.common import JointType
from joint_estimator.offline import main, read_csv_track
from joint_estimator.synthetic import add_noise, add_outliers, random_joint_motion
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from stereo_manip_tools.testing import executable_path
from stereo_manip_tools.transforms import quaternion_from_matrix

SP, SR = 0.001, np.deg2rad(1.0)


def _rows(T):
    return [list(t[:3, 3]) + list(quaternion_from_matrix(t[:3, :3])) for t in T]


def _write_csv(path, header, rows):
    with open(path, 'w', newline='') as f:
        w = csv.writer(f)
        w.writerow(header)
        w.writerows(rows)


@pytest.fixture
def hinge(tmp_path):
    rng = np.random.default_rng(2)
    g = random_joint_motion(JointType.REVOLUTE, 60, rng)
    noisy, mask = add_outliers(add_noise(g.poses, SP, SR, rng), 0.1, rng)
    path = tmp_path / 'hinge.csv'
    stamps = np.arange(60) * 0.05
    _write_csv(path, ['stamp', 'x', 'y', 'z', 'qx', 'qy', 'qz', 'qw'],
               [[s] + r for s, r in zip(stamps, _rows(noisy))])
    return g, noisy, mask, path


def test_csv_relative_track_to_json_figure_and_corrected_csv(hinge, tmp_path, capsys):
    g, noisy, mask, path = hinge
    out, fig, cor = tmp_path / 'est.json', tmp_path / 'fig.png', tmp_path / 'corrected.csv'
    code = main(['--csv', str(path), '--sigma-position', '0.001', '--sigma-rotation-deg', '1',
                 '--output', str(out), '--figure', str(fig), '--corrected-csv', str(cor)])
    assert code == 0
    assert 'revolute selected' in capsys.readouterr().out
    est = json.loads(out.read_text())
    assert est['joint_type'] == 'revolute'
    assert est['outlier_indices'] == np.flatnonzero(mask).tolist()
    axis = np.array(est['axis_in_b'])
    assert np.degrees(np.arccos(min(1.0, abs(axis @ g.axis_in_b)))) < 1.0
    assert set(est['candidate_bic']) | set(est['not_scored']) == {
        t.name.lower() for t in JointType}
    assert fig.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n' and fig.stat().st_size > 20000
    T_c, stamps = read_csv_track(cor)
    np.testing.assert_array_equal(stamps, np.round(np.arange(60) * 0.05 * 1e9))
    inl = ~mask
    assert (np.linalg.norm(T_c[inl, :3, 3] - g.poses[inl, :3, 3], axis=1).mean()
            < np.linalg.norm(noisy[inl, :3, 3] - g.poses[inl, :3, 3], axis=1).mean())


def test_csv_two_link_tracks(tmp_path):
    rng = np.random.default_rng(5)
    g = random_joint_motion(JointType.PRISMATIC, 40, rng)
    from scipy.spatial.transform import Rotation
    link_b = np.tile(np.eye(4), (40, 1, 1))
    link_b[:, :3, :3] = Rotation.random(40, random_state=rng).as_matrix()
    link_a = link_b @ g.poses
    path = tmp_path / 'two.csv'
    header = [f'{k}_{c}' for k in 'ab' for c in ('x', 'y', 'z', 'qx', 'qy', 'qz', 'qw')]
    _write_csv(path, header, [a + b for a, b in zip(_rows(link_a), _rows(link_b))])
    out = tmp_path / 'est.json'
    assert main(['--csv', str(path), '--output', str(out)]) == 0
    assert json.loads(out.read_text())['joint_type'] == 'prismatic'


def test_bag_input(tmp_path):
    from geometry_msgs.msg import PoseStamped
    from rclpy.serialization import serialize_message
    from std_msgs.msg import Header
    from stereo_manip_tools.bag_io import BagWriter
    from stereo_manip_tools.conversions import matrix_to_pose, ns_to_stamp

    rng = np.random.default_rng(8)
    g = random_joint_motion(JointType.REVOLUTE, 40, rng)
    noisy = add_noise(g.poses, SP, SR, rng)
    bag = tmp_path / 'bag'
    with BagWriter(bag) as w:
        w.add_topic('/rel', 'geometry_msgs/msg/PoseStamped')
        for i, T in enumerate(noisy):
            stamp = (i + 1) * 10 ** 8
            msg = PoseStamped(header=Header(stamp=ns_to_stamp(stamp), frame_id='b'),
                              pose=matrix_to_pose(T))
            w.write('/rel', stamp, serialize_message(msg))
    out = tmp_path / 'est.json'
    assert main(['--bag', str(bag), '--topic-relative', '/rel', '--sigma-position', '0.001',
                 '--sigma-rotation-deg', '1', '--output', str(out)]) == 0
    est = json.loads(out.read_text())
    assert est['joint_type'] == 'revolute' and est['sample_count'] == 40
    assert main(['--bag', str(bag), '--topic-relative', '/missing']) == 2


@pytest.mark.parametrize('content, message', [
    ('x,y,z\n1,2,3\n', 'header must have columns'),
    ('x,y,z,qx,qy,qz,qw\n0,0,0,0,0,0,1\n0,0,nan,0,0,0,1\n', 'row 2 has a missing'),
    ('x,y,z,qx,qy,qz,qw\n0,0,0,0,0,0,0\n', 'quaternion'),
    ('x,y,z,qx,qy,qz,qw\n0,0,0,0,0,0,1\n', '1 poses given'),
    ('stamp,x,y,z,qx,qy,qz,qw\n1,0,0,0,0,0,0,1\n0.5,0,0,0,0,0,0,1\n', 'out of order'),
    ('x,y,z,qx,qy,qz,qw\n0,0,zero,0,0,0,1\n', 'non-numeric'),
])
def test_bad_csv_exits_2_with_a_message(tmp_path, capsys, content, message):
    path = tmp_path / 'bad.csv'
    path.write_text(content)
    assert main(['--csv', str(path)]) == 2
    assert message in capsys.readouterr().err


def test_missing_file(tmp_path, capsys):
    assert main(['--csv', str(tmp_path / 'nope.csv')]) == 2
    assert 'cannot read' in capsys.readouterr().err


@pytest.mark.process
def test_installed_command(hinge, tmp_path):
    _, _, _, path = hinge
    out = tmp_path / 'est.json'
    run = subprocess.run([str(executable_path('joint_estimator', 'estimate_joint')), '--csv',
                          str(path), '--joint-type', 'revolute', '--output', str(out)],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert json.loads(out.read_text())['joint_type'] == 'revolute'
    bad = subprocess.run([str(executable_path('joint_estimator', 'estimate_joint')), '--csv',
                          str(tmp_path / 'nope.csv')], capture_output=True, text=True,
                         timeout=120)
    assert bad.returncode == 2 and 'cannot read' in bad.stderr


def test_defaults_repair_flips_estimate_noise_and_report_coverage(tmp_path, capsys):
    """
    A door marker seen by a camera, 25 % of the poses flipped (IPPE twin), no noise levels given.

    The JSON reports the repaired frames, the estimated noise, the inliers' coverage, the axis
    uncertainty and unwrapped coordinates crossing +-180 deg.
    """
    from joint_estimator.ambiguity import marker_twins
    from joint_estimator.common import compose_track, rotations_about_axis
    rng = np.random.default_rng(11)
    n = 120
    axis, hinge = np.array([0.0, 1.0, 0.0]), np.array([-0.2, 0.0, 1.0])
    R0 = np.diag([1.0, -1.0, -1.0])
    q = np.deg2rad(np.linspace(130.0, 230.0, n))          # crosses 180 deg
    Rq = rotations_about_axis(axis, q - np.pi)
    truth = compose_track(rotations_about_axis(axis, q) @ R0,
                          hinge + np.einsum('nij,j->ni', Rq, [0.35, 0.05, 0.0]))
    noisy = add_noise(truth, SP, SR, rng)
    flipped = np.zeros(n, bool)
    flipped[rng.choice(n, n // 4, replace=False)] = True
    noisy[flipped] = marker_twins(noisy[flipped])
    path, out = tmp_path / 'door.csv', tmp_path / 'door.json'
    _write_csv(path, ['x', 'y', 'z', 'qx', 'qy', 'qz', 'qw'], _rows(noisy))
    assert main(['--csv', str(path), '--output', str(out)]) == 0
    est = json.loads(out.read_text())
    assert est['joint_type'] == 'revolute', est['status']
    twin_angle = np.degrees(np.linalg.norm(Rotation.from_matrix(
        marker_twins(noisy[flipped])[:, :3, :3] @ np.transpose(noisy[flipped, :3, :3], (0, 2, 1))
    ).as_rotvec(), axis=1))
    assert set(np.flatnonzero(flipped)[twin_angle > 5.0]) <= set(est['repaired_indices'])
    assert set(est['repaired_indices']) <= set(np.flatnonzero(flipped))
    assert est['noise']['estimated']
    assert est['noise']['sigma_position_m'] == pytest.approx(SP, rel=0.3)
    assert est['coverage']['fraction'] > 0.95 and est['warnings'] == []
    coords = np.degrees(np.array(est['coordinates'])[:, 0])
    assert np.ptp(coords) == pytest.approx(100.0, abs=3.0)         # unwrapped: not 359 deg
    assert 0 < est['axis_uncertainty']['axis_angle_std_in_b_rad'] < np.deg2rad(1.0)
    # the reported point lies by the data, the minimum-norm one need not
    centre = noisy[:, :3, 3].mean(axis=0)
    assert np.linalg.norm(np.array(est['point_in_b']) - centre) < 0.4
    assert 'flipped poses repaired' in capsys.readouterr().out
