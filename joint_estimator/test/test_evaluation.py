"""The evaluation metrics against hand-computed values (pure core)."""

from joint_estimator.evaluation import axis_angle_deg, line_distance_over_segment, \
    point_line_distance
import numpy as np
import pytest


def test_axis_angle_ignores_the_sign_and_measures_the_angle():
    u = np.array([0.0, 0.0, 1.0])
    tilted = np.array([np.sin(np.deg2rad(3.0)), 0.0, np.cos(np.deg2rad(3.0))])
    assert axis_angle_deg(tilted, u) == pytest.approx(3.0, abs=1e-9)
    assert axis_angle_deg(-tilted, u) == pytest.approx(3.0, abs=1e-9)
    assert axis_angle_deg(u, u) == 0.0
    assert axis_angle_deg(np.array([1.0, 0.0, 0.0]), u) == pytest.approx(90.0)


def test_point_line_distance():
    assert point_line_distance([0.3, 0.4, 7.0], [0.0, 0.0, -2.0], [0.0, 0.0, 1.0]) == \
        pytest.approx(0.5)


def test_line_distance_over_segment_of_a_shifted_and_a_tilted_line():
    u = np.array([0.0, 0.0, 1.0])
    c = np.array([0.1, 0.0, 0.0])
    # parallel, 2 mm away: 2 mm everywhere, wherever the anchor is
    assert line_distance_over_segment(c, u, [5.0, 5.0, 3.0], c + [0.002, 0.0, 0.0], u) == \
        pytest.approx(0.002)
    # through the anchor's foot (z = 0.5), tilted by 0.01 rad: 0.1 m away it is 1 mm off
    tilted = np.array([np.sin(0.01), 0.0, np.cos(0.01)])
    foot = c + [0.0, 0.0, 0.5]
    d = line_distance_over_segment(c, u, [0.0, 0.0, 0.5], foot, tilted)
    assert d == pytest.approx(0.1 * np.sin(0.01), rel=1e-9)
