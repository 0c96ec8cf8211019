"""Every joint type on hand-built motions: parameters, corrected track and joint coordinates."""

from joint_estimator.common import (
    compose_track, JointType, relative_track, rotations_about_axis, split_track)
from joint_estimator.selection import estimate_joint
from joint_estimator.synthetic import add_noise
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

N = 40
Z = np.array([0.0, 0.0, 1.0])


def _fit(T, jt, **kw):
    kw.setdefault('robust', False)
    return estimate_joint(T, joint_type=jt, sigma_position=0.001,
                          sigma_rotation=np.deg2rad(1.0), **kw).best


def _dir_close(est, true, atol=1e-9):
    np.testing.assert_allclose(est * np.sign(est @ true), true, atol=atol)


def _on_line(point, line_point, direction, atol=1e-9):
    d = point - line_point
    assert np.linalg.norm(d - direction * (d @ direction)) < atol


def door():
    """Door hinged about B's z axis through (0.5, 0, 0); A's origin at the handle."""
    q = np.linspace(0.0, np.deg2rad(80.0), N)
    hinge = np.array([0.5, 0.0, 0.0])
    handle = np.array([0.5, 0.8, 0.9])
    R = rotations_about_axis(Z, q)
    return compose_track(R, hinge + (R @ (handle - hinge))), q, hinge, handle


def test_revolute_door():
    T, q, hinge, handle = door()
    fit = _fit(T, JointType.REVOLUTE)
    _dir_close(fit.axis_in_b, Z)
    _dir_close(fit.axis_in_a, Z)
    _on_line(fit.point_in_b, hinge, Z)
    _on_line(fit.point_in_a, hinge - handle, Z)
    np.testing.assert_allclose(fit.corrected, T, atol=1e-9)
    dq = np.sign(fit.axis_in_b @ Z) * fit.coordinates[:, 0] - q
    assert np.ptp(dq) < 1e-9


def test_prismatic_drawer():
    s = np.linspace(0.0, 0.3, N)
    R = Rotation.from_euler('xyz', [0.3, -0.2, 1.0]).as_matrix()
    d = np.array([1.0, 0.0, 0.0])
    T = compose_track(np.tile(R, (N, 1, 1)), np.array([0.1, 0.2, 0.3]) + np.outer(s, d))
    fit = _fit(T, JointType.PRISMATIC)
    _dir_close(fit.axis_in_b, d)
    _dir_close(fit.axis_in_a, R.T @ d)
    _on_line(fit.point_in_b, np.array([0.1, 0.2, 0.3]), d)
    np.testing.assert_allclose(fit.corrected, T, atol=1e-9)
    slope = np.polyfit(s, fit.coordinates[:, 0], 1)[0]
    assert abs(abs(slope) - 1.0) < 1e-9


def test_spherical_ball_joint():
    rng = np.random.default_rng(4)
    centre_b, centre_a = np.array([0.1, 0.0, 0.5]), np.array([0.0, 0.0, -0.3])
    R = Rotation.from_rotvec(rng.uniform(-0.5, 0.5, (N, 3))).as_matrix()
    T = compose_track(R, centre_b - R @ centre_a)
    fit = _fit(T, JointType.SPHERICAL)
    np.testing.assert_allclose(fit.point_in_b, centre_b, atol=1e-9)
    np.testing.assert_allclose(fit.point_in_a, centre_a, atol=1e-9)
    np.testing.assert_allclose(fit.corrected, T, atol=1e-9)
    np.testing.assert_allclose(Rotation.from_rotvec(fit.coordinates).as_matrix(), R, atol=1e-9)


def test_cylindrical_screw():
    q = np.linspace(0.0, 2.0, N)
    s = np.linspace(0.0, 0.1, N)
    y = np.array([0.0, 1.0, 0.0])
    axis_point = np.array([0.0, 0.0, 0.2])
    offset = np.array([0.3, 0.0, 0.0])          # A's origin relative to the axis point at q=0
    R = rotations_about_axis(y, q)
    T = compose_track(R, axis_point + R @ offset + np.outer(s, y))
    fit = _fit(T, JointType.CYLINDRICAL)
    _dir_close(fit.axis_in_b, y)
    _dir_close(fit.axis_in_a, y)
    _on_line(fit.point_in_b, axis_point, y)
    _on_line(fit.point_in_a, -offset, y)
    np.testing.assert_allclose(fit.corrected, T, atol=1e-9)
    sign = np.sign(fit.axis_in_b @ y)
    assert np.ptp(sign * fit.coordinates[:, 0] - q) < 1e-9
    assert np.ptp(sign * fit.coordinates[:, 1] - s) < 1e-9


def test_planar_object_sliding_on_a_table():
    rng = np.random.default_rng(6)
    q = rng.uniform(-1.0, 1.0, N)
    xy = rng.uniform(-0.2, 0.2, (N, 2))
    R = rotations_about_axis(Z, q) @ Rotation.from_euler('x', np.pi).as_matrix()
    T = compose_track(R, np.column_stack([xy, np.full(N, 0.05)]))
    fit = _fit(T, JointType.PLANAR)
    _dir_close(fit.axis_in_b, Z)
    _dir_close(fit.axis_in_a, -Z)
    np.testing.assert_allclose(abs(fit.point_in_b @ Z), 0.05, atol=1e-9)
    np.testing.assert_allclose(fit.corrected, T, atol=1e-9)
    e1, e2 = fit.model.plane_basis
    np.testing.assert_allclose(fit.coordinates[:, 1:], T[:, :3, 3] @ np.column_stack([e1, e2]),
                               atol=1e-9)


def test_fixed_from_two_link_tracks():
    rng = np.random.default_rng(7)
    link_b = compose_track(Rotation.random(N, random_state=rng).as_matrix(),
                           rng.uniform(-1, 1, (N, 3)))
    rel = compose_track(np.tile(Rotation.random(random_state=rng).as_matrix(), (N, 1, 1)),
                        np.tile([0.1, -0.2, 0.05], (N, 1)))
    link_a = link_b @ rel
    fit = _fit(relative_track(link_a, link_b), JointType.FIXED)
    np.testing.assert_allclose(fit.corrected, rel, atol=1e-9)
    assert fit.coordinates.shape == (N, 0)


@pytest.mark.parametrize('jt', list(JointType))
def test_every_corrected_track_is_closer_to_the_truth_than_the_noisy_one(jt):
    from joint_estimator.synthetic import random_joint_motion
    rng = np.random.default_rng(int(jt) + 30)
    g = random_joint_motion(jt, 100, rng)
    noisy = add_noise(g.poses, 0.002, np.deg2rad(2.0), rng)
    fit = _fit(noisy, jt)
    Rt, pt = split_track(g.poses)
    raw_pos = np.linalg.norm(noisy[:, :3, 3] - pt, axis=1).mean()
    cor_pos = np.linalg.norm(fit.corrected[:, :3, 3] - pt, axis=1).mean()
    raw_rot = np.linalg.norm(Rotation.from_matrix(
        noisy[:, :3, :3] @ np.transpose(Rt, (0, 2, 1))).as_rotvec(), axis=1).mean()
    cor_rot = np.linalg.norm(Rotation.from_matrix(
        fit.corrected[:, :3, :3] @ np.transpose(Rt, (0, 2, 1))).as_rotvec(), axis=1).mean()
    assert cor_pos < raw_pos
    assert cor_rot <= raw_rot * 1.05
