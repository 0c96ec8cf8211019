"""Pinhole stereo camera model: projections, ROS conventions, non-default cameras."""

from hypothesis import given, settings, strategies as st
import numpy as np
import pytest
from stereo_depth.synthetic import render, StereoCamera


@settings(max_examples=60, deadline=None)
@given(fx=st.floats(100, 2000), B=st.floats(0.01, 0.5), X=st.floats(-0.5, 0.5),
       Y=st.floats(-0.5, 0.5), Z=st.floats(0.2, 5.0))
def test_projection_round_trip_and_disparity(fx, B, X, Y, Z):
    cam = StereoCamera.create(fx=fx, baseline=B)
    P = np.array([[X, Y, Z]])
    ul = cam.project(P)[0]
    ur = cam.project(P, right=True)[0]
    assert ur[1] == pytest.approx(ul[1])                         # rectified: same row
    assert ul[0] - ur[0] == pytest.approx(fx * B / Z, rel=1e-12)  # d = fx B / Z
    back = cam.back_project(ul[0], ul[1], Z)
    np.testing.assert_allclose(back, P[0], atol=1e-12)
    assert cam.depth_from_disparity(cam.disparity_from_depth(Z)) == pytest.approx(Z)


def test_ros_projection_conventions():
    cam = StereoCamera.create(width=800, height=600, fx=700.0, baseline=0.12)
    assert cam.cx == 399.5 and cam.cy == 299.5
    assert cam.P_right[0, 3] == pytest.approx(-700.0 * 0.12)
    assert -cam.P_right[0, 3] / cam.P_right[0, 0] == pytest.approx(0.12)
    np.testing.assert_array_equal(cam.P_left[:, :3], cam.K)
    np.testing.assert_array_equal(cam.right_center, [0.12, 0.0, 0.0])
    # A point on the right camera's optical axis projects to its principal point.
    assert cam.project(np.array([[0.12, 0.0, 1.0]]), right=True)[0] == pytest.approx(
        [cam.cx, cam.cy])


def test_non_default_camera_geometry_is_exact():
    cam = StereoCamera.create(width=320, height=240, fx=280.0, baseline=0.06, cx=150.0,
                              cy=130.0)
    _, _, truth = render('peg_in_hole', 120, seed=3, camera=cam)
    assert truth['depth'].shape == (240, 320)
    vs, us = np.nonzero(truth['valid'] & ~truth['occlusion'])
    rng = np.random.default_rng(0)
    checked = 0
    for i in rng.permutation(len(us))[:3000]:
        u, v = us[i], vs[i]
        ur = u - truth['disparity'][v, u]
        u0 = int(np.floor(ur))
        if u0 < 1 or u0 + 2 >= 320 or v < 1 or v + 1 >= 240:
            continue
        cols, rows = np.arange(u0 - 1, u0 + 3), np.arange(v - 1, v + 2)
        same = (truth['object_id_right'][np.ix_(rows, cols)] == truth['object_id'][v, u]) & \
            (truth['face_id_right'][np.ix_(rows, cols)] == truth['face_id'][v, u])
        if not same.all():
            continue
        gu, gv = np.meshgrid(cols, rows)
        A = np.column_stack([gu.ravel(), gv.ravel(), np.ones(gu.size)])
        tc = truth['texcoords_right'][np.ix_(rows, cols)].reshape(-1, 2).astype(float)
        c, *_ = np.linalg.lstsq(A, tc, rcond=None)
        q = np.linalg.solve(c[:2].T, truth['texcoords'][v, u].astype(float) - c[2])
        assert np.hypot(q[0] - ur, q[1] - v) < 0.05
        checked += 1
        if checked >= 150:
            break
    assert checked >= 100
