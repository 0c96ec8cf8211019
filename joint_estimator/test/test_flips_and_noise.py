"""Square-marker flips, estimated noise scales and the honest outputs, against ground truth."""

import cv2
from joint_estimator.ambiguity import marker_twins, relative_candidates, two_link_candidates
from joint_estimator.common import compose_track, JointType, rotations_about_axis
from joint_estimator.evaluation import axis_angle_deg, point_line_distance
from joint_estimator.robust import line_of_sight_ratio
from joint_estimator.selection import estimate_joint, unwrap_angles
from joint_estimator.synthetic import add_noise, random_joint_motion
import numpy as np
import pytest
from scipy.spatial.transform import Rotation


def _door_in_camera(n, rng, motion_deg=100.0, distance=1.0):
    """Track a door seen by a camera (B = camera, optical frame), marker (A) z to the camera."""
    axis = np.array([0.0, 1.0, 0.0])
    hinge = np.array([-0.2, 0.0, distance])
    R0 = np.column_stack([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
    t0 = hinge + np.array([0.35, 0.05, 0.0])
    q = np.deg2rad(np.linspace(-motion_deg / 2, motion_deg / 2, n)) + rng.normal(0, 1e-3, n)
    Rq = rotations_about_axis(axis, q)
    T = compose_track(Rq @ R0, hinge + np.einsum('nij,j->ni', Rq, t0 - hinge))
    return T, axis, hinge, R0.T @ axis, R0.T @ (hinge - t0)


def test_twin_reproduces_opencv_second_ippe_solution():
    rng = np.random.default_rng(0)
    K = np.array([[800.0, 0, 320], [0, 800.0, 240], [0, 0, 1]])
    h = 0.025
    corners = np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]])
    worst = 0.0
    for _ in range(30):
        R = Rotation.from_euler('xyz', [180 + rng.uniform(-40, 40), rng.uniform(-40, 40),
                                        rng.uniform(-180, 180)], degrees=True).as_matrix()
        t = np.array([rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1), rng.uniform(0.6, 1.2)])
        img = (corners @ R.T + t) @ K.T
        img = img[:, :2] / img[:, 2:] + rng.normal(0, 0.3, (4, 2))
        _, rvecs, tvecs, _ = cv2.solvePnPGeneric(corners, img, K, None,
                                                 flags=cv2.SOLVEPNP_IPPE_SQUARE)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = cv2.Rodrigues(rvecs[0])[0], tvecs[0].ravel()
        twin = marker_twins(T[None])[0]
        R2 = cv2.Rodrigues(rvecs[1])[0]
        worst = max(worst, np.degrees(np.linalg.norm(
            Rotation.from_matrix(twin[:3, :3] @ R2.T).as_rotvec())))
        np.testing.assert_array_equal(twin[:3, 3], T[:3, 3])
    assert worst < 0.5, worst
    # the twin of the twin is the pose again; a marker facing the camera is its own twin
    T = _door_in_camera(5, rng)[0]
    np.testing.assert_allclose(marker_twins(marker_twins(T)), T, atol=1e-12)
    facing = compose_track(np.diag([1.0, -1.0, -1.0])[None], np.array([[0.0, 0.0, 1.0]]))
    np.testing.assert_allclose(marker_twins(facing), facing, atol=1e-12)


def test_candidate_sets_have_the_measured_pose_first():
    rng = np.random.default_rng(1)
    T, *_ = _door_in_camera(6, rng)
    C = relative_candidates(T)
    assert C.shape == (6, 2, 4, 4)
    np.testing.assert_array_equal(C[:, 0], T)
    B = compose_track(np.tile(np.eye(3), (6, 1, 1)), np.tile([0.0, 0.0, 0.5], (6, 1)))
    C2 = two_link_candidates(T, B)
    assert C2.shape == (6, 4, 4, 4)
    np.testing.assert_allclose(C2[:, 0, :3, 3], T[:, :3, 3] - [0.0, 0.0, 0.5], atol=1e-12)


@pytest.mark.parametrize('flip_fraction', [0.1, 0.3, 0.55])
def test_flipped_poses_are_repaired_not_dropped(flip_fraction):
    rng = np.random.default_rng(int(flip_fraction * 100))
    n = 150
    T, axis_b, hinge, axis_a, point_a = _door_in_camera(n, rng)
    noisy = add_noise(T, 0.001, np.deg2rad(1.0), rng)
    # flips in runs, as a marker detector produces them
    flipped = np.zeros(n, bool)
    while flipped.mean() < flip_fraction:
        s = int(rng.integers(0, n - 8))
        flipped[s:s + int(rng.integers(3, 9))] = True
    data = noisy.copy()
    data[flipped] = marker_twins(noisy[flipped])
    angles = np.degrees(np.linalg.norm(Rotation.from_matrix(
        data[flipped, :3, :3] @ np.transpose(noisy[flipped, :3, :3], (0, 2, 1))).as_rotvec(),
        axis=1))
    assert np.median(angles) > 10.0          # the flips are gross orientation errors
    est = estimate_joint(data)
    b = est.best
    assert b.joint_type == JointType.REVOLUTE, est.status
    rep = np.zeros(n, bool)
    rep[b.repaired_indices] = True
    # repaired = flipped, up to flips too small to matter (twin within the noise)
    big = np.zeros(n, bool)
    big[flipped] = angles > 5.0
    # every gross flip repaired, or (rarely, with its twin still off by the noise) rejected
    assert np.all(rep[big] | ~b.inliers[big]) and not np.any(rep & ~flipped)
    assert rep[big].mean() > 0.95
    assert b.outlier_indices.size <= 0.05 * n
    assert axis_angle_deg(b.axis_in_b, axis_b) < 0.5
    assert point_line_distance(b.point_in_b, hinge, axis_b) < 0.003
    assert 'flipped poses repaired' in est.status and not b.warnings
    # without the repair the flipped frames are lost (rejected)
    plain = estimate_joint(data, flip_repair=False)
    assert plain.best.outlier_indices.size >= 0.8 * big.sum()


@pytest.mark.slow
@pytest.mark.parametrize('sp, sr_deg', [(0.0005, 0.5), (0.002, 1.5), (0.005, 3.0)])
def test_noise_scales_are_estimated_and_the_type_follows_over_a_10x_range(sp, sr_deg):
    sr = np.deg2rad(sr_deg)
    for jt in (JointType.REVOLUTE, JointType.PRISMATIC, JointType.CYLINDRICAL):
        for seed in range(2):
            rng = np.random.default_rng([seed, int(jt), int(sp * 1e4)])
            g = random_joint_motion(jt, 100, rng)
            est = estimate_joint(add_noise(g.poses, sp, sr, rng))
            b = est.best
            assert b.joint_type == jt and b.scale_estimated, est.status
            assert b.sigma_position == pytest.approx(sp, rel=0.2), est.status
            assert b.sigma_rotation == pytest.approx(sr, rel=0.2), est.status


def test_line_of_sight_noise_ratio():
    rng = np.random.default_rng(3)
    T, *_ = _door_in_camera(300, rng)
    p = T[:, :3, 3]
    v = p / np.linalg.norm(p, axis=1)[:, None]
    e = rng.normal(0.0, 0.0005, p.shape)
    e += v * rng.normal(0.0, 0.005, (300, 1))         # 10x the noise along the line of sight
    assert line_of_sight_ratio(p + e) == pytest.approx(10.0, rel=0.2)
    assert line_of_sight_ratio(p + rng.normal(0.0, 0.001, p.shape)) == pytest.approx(
        1.0, abs=0.25)
    # a sparse track with isotropic noise claims no anisotropy either
    g = random_joint_motion(JointType.REVOLUTE, 20, rng)
    assert line_of_sight_ratio(add_noise(g.poses, 0.001, 0.01, rng)[:, :3, 3]) < 1.5


def test_coordinates_unwrapped_and_coverage_warns_about_a_partial_fit():
    rng = np.random.default_rng(7)
    n = 120
    T, axis_b, hinge, *_ = _door_in_camera(n, rng, motion_deg=100.0)
    # a reference that puts the motion across +-180 deg
    noisy = add_noise(T, 0.001, np.deg2rad(1.0), rng)
    est = estimate_joint(noisy, joint_type=JointType.REVOLUTE)
    q = est.best.coordinates[:, 0]
    assert np.degrees(np.ptp(q)) == pytest.approx(100.0, abs=3.0)
    assert np.all(np.diff(q) * np.sign(q[-1] - q[0]) > -np.deg2rad(5.0))
    assert est.best.coverage > 0.95 and not est.best.warnings
    # unwrap_angles: inliers across the cut, a rejected frame on the far branch
    truth = np.deg2rad(np.linspace(150.0, 250.0, 11))
    wrapped = np.angle(np.exp(1j * truth))
    inl = np.ones(11, bool)
    inl[5] = False
    wrapped[5] = np.angle(np.exp(1j * (truth[5] + 2.9)))     # garbage, ~166 deg off
    out = unwrap_angles(wrapped, inl)
    np.testing.assert_allclose(out[inl] - out[0], truth[inl] - truth[0], atol=1e-12)
    assert abs(out[5] - out[4]) < np.pi + 0.1
    # the first 60 % of the motion destroyed (gross pose jumps): warned, coverage < 0.5
    bad = noisy.copy()
    k = int(0.6 * n)
    bad[:k, :3, :3] = Rotation.random(k, random_state=rng).as_matrix()
    bad[:k, :3, 3] += rng.uniform(-0.3, 0.3, (k, 3))
    est = estimate_joint(bad, joint_type=JointType.REVOLUTE)
    b = est.best
    assert b.coverage < 0.5
    assert any('more than a third' in w for w in b.warnings), b.warnings
    assert any('cover only' in w for w in b.warnings), b.warnings
    assert 'WARNING' in est.status


@pytest.mark.slow
def test_axis_point_nearest_the_data_and_calibrated_uncertainty():
    ratios = []
    for seed in range(25):
        rng = np.random.default_rng(100 + seed)
        g = random_joint_motion(JointType.REVOLUTE, 60, rng)
        noisy = add_noise(g.poses, 0.002, np.deg2rad(1.0), rng)
        b = estimate_joint(noisy, joint_type=JointType.REVOLUTE).best
        # on the axis, at the foot of the positions' centre
        c = noisy[b.inliers, :3, 3].mean(axis=0)
        assert abs((c - b.point_in_b) @ b.axis_in_b) < 1e-9
        assert point_line_distance(b.point_in_b, g.point_in_b, g.axis_in_b) < 0.01
        R, p = b.corrected[:, :3, :3], b.corrected[:, :3, 3]
        np.testing.assert_allclose(np.einsum('nij,j->ni', R, b.point_in_a) + p,
                                   np.tile(b.point_in_b, (60, 1)), atol=1e-9)
        mn = b.extra['minimum_norm_point_in_b']
        assert point_line_distance(mn, b.point_in_b, b.axis_in_b) < 1e-9
        ratios.append(np.deg2rad(axis_angle_deg(b.axis_in_b, g.axis_in_b)) / b.axis_angle_std_in_b)
        assert b.axis_point_std > 0
    # the axis error (a 2-d tangent error: Rayleigh distributed, median 1.18 std) is of the
    # size the reported std says
    assert 0.5 < np.median(ratios) < 2.0, np.median(ratios)
    assert np.max(ratios) < 4.0, np.max(ratios)
