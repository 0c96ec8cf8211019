"""Pure tests of stereo_manip_tools.transforms: round trips and known answers."""

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
import pytest

from stereo_manip_tools.transforms import (
    check_transform, invert_transform, is_rotation_matrix, make_transform,
    matrix_from_quaternion, minimal_rotation_between, nearest_rotation, quaternion_from_matrix,
    rotation_about_axis, rotation_angle, rotation_log, skew, transform_points)

unit = st.floats(-1.0, 1.0, allow_nan=False)
angles = st.floats(0.0, np.pi, allow_nan=False)


def axis_of(x, y, z):
    v = np.array([x, y, z])
    return v / np.linalg.norm(v) if np.linalg.norm(v) > 1e-3 else np.array([0.0, 0.0, 1.0])


def test_skew_is_cross_product():
    a, b = np.array([1.0, -2.0, 0.5]), np.array([0.3, 4.0, -1.0])
    assert np.allclose(skew(a) @ b, np.cross(a, b))


def test_rotation_about_z_quarter_turn():
    R = rotation_about_axis([0, 0, 2.0], np.pi / 2)
    assert np.allclose(R @ [1, 0, 0], [0, 1, 0])


@settings(max_examples=200, deadline=None)
@given(unit, unit, unit, angles)
def test_log_recovers_axis_angle(x, y, z, theta):
    axis = axis_of(x, y, z)
    R = rotation_about_axis(axis, theta)
    w = rotation_log(R)
    assert np.allclose(rotation_about_axis(w, np.linalg.norm(w)) if np.linalg.norm(w) > 0
                       else np.eye(3), R, atol=1e-6)
    assert abs(rotation_angle(R) - theta) < 1e-6


@settings(max_examples=200, deadline=None)
@given(unit, unit, unit, angles)
def test_quaternion_round_trip(x, y, z, theta):
    R = rotation_about_axis(axis_of(x, y, z), theta)
    q = quaternion_from_matrix(R)
    assert q[3] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
    assert np.allclose(matrix_from_quaternion(q), R, atol=1e-12)


def test_quaternion_known_value():
    q = quaternion_from_matrix(rotation_about_axis([1, 0, 0], np.pi / 2))
    assert np.allclose(q, [np.sin(np.pi / 4), 0, 0, np.cos(np.pi / 4)])


def test_zero_quaternion_rejected():
    with pytest.raises(ValueError, match='zero or not finite'):
        matrix_from_quaternion([0, 0, 0, 0])


def test_inverse_and_points():
    T = make_transform(rotation_about_axis([1, 2, 3], 0.7), [0.1, -0.2, 0.3])
    P = np.random.default_rng(0).normal(size=(10, 3))
    assert np.allclose(transform_points(invert_transform(T), transform_points(T, P)), P)
    assert np.allclose(invert_transform(T) @ T, np.eye(4))


def test_nearest_rotation_projects_noisy_matrix():
    R = rotation_about_axis([0.3, -1, 0.2], 1.1)
    noisy = R + 1e-3 * np.random.default_rng(1).normal(size=(3, 3))
    Rn = nearest_rotation(noisy)
    assert is_rotation_matrix(Rn) and np.allclose(Rn, R, atol=5e-3)
    assert not is_rotation_matrix(noisy)


@settings(max_examples=100, deadline=None)
@given(unit, unit, unit, unit, unit, unit)
def test_minimal_rotation_maps_a_to_b(a1, a2, a3, b1, b2, b3):
    a, b = axis_of(a1, a2, a3), axis_of(b1, b2, b3)
    R = minimal_rotation_between(a, b)
    assert is_rotation_matrix(R)
    assert np.allclose(R @ a, b, atol=1e-9)
    # minimal: the rotation angle equals the angle between the vectors
    assert abs(rotation_angle(R) - np.arccos(np.clip(a @ b, -1, 1))) < 1e-6


def test_check_transform_names_the_problem():
    T = np.eye(4)
    check_transform(T)
    bad = T.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match='NaN'):
        check_transform(bad, 'peg pose')
    bad = T.copy()
    bad[:3, :3] *= 2
    with pytest.raises(ValueError, match='orthonormal'):
        check_transform(bad)
    with pytest.raises(ValueError, match='4x4'):
        check_transform(np.eye(3))


def test_is_rotation_matrix_equals_the_allclose_test():
    """The rotation test decides as np.allclose(R^T R, I, atol=tol) and |det R - 1| < tol."""
    rng = np.random.default_rng(4)
    decided = []
    for k in range(3000):
        R = rotation_about_axis(rng.normal(size=3), rng.uniform(0, np.pi))
        R = R + rng.normal(0.0, 10 ** rng.uniform(-9, -5), (3, 3))
        ref = bool(np.allclose(R.T @ R, np.eye(3), atol=1e-6)
                   and abs(np.linalg.det(R) - 1.0) < 1e-6)
        assert is_rotation_matrix(R) == ref
        decided.append(ref)
    assert 0.1 < np.mean(decided) < 0.9      # both outcomes are exercised
