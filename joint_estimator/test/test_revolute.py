"""Revolute joint exactly as Section 4 derives it (Eqs. 10-18): ground truth and identities."""

from hypothesis import given, settings, strategies as st
from joint_estimator.common import (
    compose_track, DegenerateMotionError, perpendicular_basis, rotations_about_axis, split_track)
from joint_estimator.common import JointType
from joint_estimator.revolute import (
    correct_orientations, eq17_objective, estimate_revolute_joint, fit_axis_directions,
    fit_axis_directions_iterative, fit_revolute, ml_angles, solve_axis_points)
from joint_estimator.synthetic import add_noise, random_joint_motion
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from stereo_manip_tools.transforms import rotation_about_axis, skew


def _aligned(est, true):
    """Estimated direction with the sign of the true one."""
    return est * np.sign(est @ true)


def _line_distance(point, true_point, direction):
    d = point - true_point
    return np.linalg.norm(d - direction * (d @ direction))


@pytest.mark.parametrize('seed', range(5))
def test_noiseless_track_recovers_the_joint_to_1e9(seed):
    rng = np.random.default_rng(seed)
    g = random_joint_motion(JointType.REVOLUTE, 30, rng, rotation_range=np.deg2rad(60))
    fit = estimate_revolute_joint(g.poses)
    sign = np.sign(fit.axis_in_b @ g.axis_in_b)
    np.testing.assert_allclose(sign * fit.axis_in_a, g.axis_in_a, atol=1e-9)
    np.testing.assert_allclose(sign * fit.axis_in_b, g.axis_in_b, atol=1e-9)
    assert _line_distance(fit.point_in_a, g.point_in_a, g.axis_in_a) < 1e-9
    assert _line_distance(fit.point_in_b, g.point_in_b, g.axis_in_b) < 1e-9
    np.testing.assert_allclose(fit.corrected, g.poses, atol=1e-9)
    # the joint angle differs from the truth by a constant (the choice of zero), sign-aware
    offset = np.angle(np.exp(1j * (fit.coordinates[:, 0] - sign * g.coordinates[:, 0])))
    assert np.ptp(np.unwrap(offset)) < 1e-9
    assert fit.rotation_rms < 1e-9 and fit.position_rms < 1e-9


@settings(max_examples=60, deadline=None)
@given(st.floats(-np.pi, np.pi), st.floats(0.0, 2 * np.pi), st.integers(0, 2 ** 31))
def test_eq16_trace_identities(theta, phi, seed):
    rng = np.random.default_rng(seed)
    lb = rng.normal(size=3)
    lb /= np.linalg.norm(lb)
    e1, e2 = perpendicular_basis(lb)
    l_t = np.cos(phi) * e1 + np.sin(phi) * e2            # any l(t) with  ^B l . l(t) = 0
    P = np.outer(lb, lb)
    assert np.trace(P) == pytest.approx(1.0, abs=1e-12)
    assert np.trace(skew(l_t) @ P) == pytest.approx(0.0, abs=1e-12)
    assert np.trace(skew(l_t) @ skew(l_t) @ P) == pytest.approx(-1.0, abs=1e-12)
    # Eq. (16): Tr(R(-l(t), theta) ^B l ^B l^T) = cos theta
    lhs = np.trace(rotation_about_axis(-l_t, theta) @ P)
    assert lhs == pytest.approx(np.cos(theta), abs=1e-12)


def test_eq17_objective_is_the_sum_of_one_minus_cos_of_the_axis_misalignment():
    rng = np.random.default_rng(3)
    R = Rotation.random(20, random_state=rng).as_matrix()
    a, b = rng.normal(size=3), rng.normal(size=3)
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    cos = np.clip((R @ a) @ b, -1, 1)
    assert eq17_objective(R, a, b) == pytest.approx(np.sum(1 - np.cos(np.arccos(cos))),
                                                    abs=1e-12)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2 ** 31))
def test_closed_form_eq17_is_the_global_minimum(seed):
    rng = np.random.default_rng(seed)
    g = random_joint_motion(JointType.REVOLUTE, 15, rng, rotation_range=np.deg2rad(45))
    R = add_noise(g.poses, 0.0, np.deg2rad(5.0), rng)[:, :3, :3]
    a, b, _ = fit_axis_directions(R)
    best = eq17_objective(R, a, b)
    for _ in range(50):
        u, v = rng.normal(size=3), rng.normal(size=3)
        assert best <= eq17_objective(R, u / np.linalg.norm(u), v / np.linalg.norm(v)) + 1e-12
        # small perturbations too
        ap = a + 1e-3 * rng.normal(size=3)
        bp = b + 1e-3 * rng.normal(size=3)
        assert best <= eq17_objective(R, ap / np.linalg.norm(ap), bp / np.linalg.norm(bp)) + 1e-12


def test_iterative_eq17_agrees_with_the_closed_form():
    rng = np.random.default_rng(11)
    g = random_joint_motion(JointType.REVOLUTE, 50, rng, rotation_range=np.deg2rad(90))
    R = add_noise(g.poses, 0.001, np.deg2rad(2.0), rng)[:, :3, :3]
    a, b, _ = fit_axis_directions(R)
    ai, bi, nfev = fit_axis_directions_iterative(R)
    assert nfev > 10
    assert np.degrees(np.arccos(min(1.0, abs(a @ ai)))) < 1e-3
    assert np.degrees(np.arccos(min(1.0, abs(b @ bi)))) < 1e-3


def test_eq18_matrix_is_rank_5_and_the_solution_has_minimum_norm():
    rng = np.random.default_rng(5)
    g = random_joint_motion(JointType.REVOLUTE, 40, rng)
    R, p = split_track(add_noise(g.poses, 0.002, np.deg2rad(1.0), rng))
    a, b, _ = fit_axis_directions(R)
    R_hat = correct_orientations(R, a, b)
    ca, cb, rank, S = solve_axis_points(R_hat, p)
    assert rank == 5 and S[-1] < 1e-9 * S[0]
    null = np.concatenate([a, b]) / np.sqrt(2)
    # minimum norm: no component along the null space (the axis) ...
    assert abs(np.concatenate([ca, cb]) @ null) < 1e-9
    # ... and moving along the axis keeps the least-squares residual unchanged

    def residual(x_a, x_b):
        return np.sum((x_b - R_hat @ x_a - p) ** 2)
    assert residual(ca + 0.3 * a, cb + 0.3 * b) == pytest.approx(residual(ca, cb), rel=1e-9)
    assert residual(ca + 1e-3 * rng.normal(size=3), cb) > residual(ca, cb)


def test_corrected_track_satisfies_eqs_10_and_11_exactly_on_noisy_data():
    rng = np.random.default_rng(8)
    g = random_joint_motion(JointType.REVOLUTE, 60, rng)
    noisy = add_noise(g.poses, 0.005, np.deg2rad(3.0), rng)
    for correction in ('chapter', 'ml'):
        fit = estimate_revolute_joint(noisy, correction=correction)
        R_hat, p_hat = split_track(fit.corrected)
        np.testing.assert_allclose(R_hat @ fit.axis_in_a, np.tile(fit.axis_in_b, (60, 1)),
                                   atol=1e-12)                                    # Eq. (10)
        np.testing.assert_allclose(R_hat @ fit.point_in_a + p_hat,
                                   np.tile(fit.point_in_b, (60, 1)), atol=1e-12)  # Eq. (11)
        np.testing.assert_allclose(np.einsum('nji,njk->nik', R_hat, R_hat),
                                   np.tile(np.eye(3), (60, 1, 1)), atol=1e-12)


def test_chapter_correction_is_the_minimal_rotation():
    rng = np.random.default_rng(9)
    g = random_joint_motion(JointType.REVOLUTE, 30, rng)
    R, p = split_track(add_noise(g.poses, 0.0, np.deg2rad(4.0), rng))
    fit = estimate_revolute_joint(compose_track(R, p), correction='chapter')
    a, b = fit.axis_in_a, fit.axis_in_b
    D = fit.corrected[:, :3, :3] @ np.transpose(R, (0, 2, 1))   # Delta Theta(t)^-1
    for Dt, Rt in zip(D, R):
        w = Rotation.from_matrix(Dt).as_rotvec()
        v = Rt @ a
        # rotation about v x b by the angle between v and b: the smallest one mapping v onto b
        assert np.linalg.norm(w) == pytest.approx(np.arccos(np.clip(v @ b, -1, 1)), abs=1e-9)
        assert abs(w @ b) < 1e-9 and abs(w @ v) < 1e-9


def test_joint_angle_per_frame_and_ml_projection_are_exact_optima():
    rng = np.random.default_rng(12)
    g = random_joint_motion(JointType.REVOLUTE, 25, rng)
    R, p = split_track(add_noise(g.poses, 0.003, np.deg2rad(2.0), rng))
    m = fit_revolute(R, p)
    sp, sr = 0.003, np.deg2rad(2.0)
    q = ml_angles(R, p, m.axis_in_b, m.reference, m.point_in_a, m.point_in_b, sp, sr, False)
    grid = np.linspace(-np.pi, np.pi, 20001)
    for i in range(0, 25, 6):
        Rg = rotations_about_axis(m.axis_in_b, grid) @ m.reference
        cost = ((3 - np.einsum('nij,ij->n', Rg, R[i])) / sr ** 2
                + np.sum((m.point_in_b - Rg @ m.point_in_a - p[i]) ** 2, 1) / sp ** 2)
        assert abs(np.angle(np.exp(1j * (grid[np.argmin(cost)] - q[i])))) < 1e-3


def test_noisy_estimate_is_accurate():
    rng = np.random.default_rng(21)
    errs = []
    for _ in range(10):
        g = random_joint_motion(JointType.REVOLUTE, 100, rng)
        fit = estimate_revolute_joint(add_noise(g.poses, 0.001, np.deg2rad(1.0), rng))
        errs.append(np.degrees(np.arccos(min(1.0, abs(fit.axis_in_b @ g.axis_in_b)))))
        assert _line_distance(fit.point_in_b, g.point_in_b, g.axis_in_b) < 0.005
    assert np.mean(errs) < 0.5


def test_too_small_a_rotation_is_reported_as_degenerate():
    rng = np.random.default_rng(2)
    g = random_joint_motion(JointType.REVOLUTE, 50, rng, rotation_range=np.deg2rad(2.0))
    with pytest.raises(DegenerateMotionError, match='rotation range .* does not define'):
        estimate_revolute_joint(add_noise(g.poses, 0.001, np.deg2rad(1.0), rng))
    still = compose_track(np.tile(np.eye(3), (10, 1, 1)), np.zeros((10, 3)))
    with pytest.raises(DegenerateMotionError):
        estimate_revolute_joint(still)


def test_estimate_joint_without_refinement_is_exactly_the_chapter_estimator():
    from joint_estimator.selection import estimate_joint
    rng = np.random.default_rng(31)
    g = random_joint_motion(JointType.REVOLUTE, 40, rng)
    noisy = add_noise(g.poses, 0.002, np.deg2rad(2.0), rng)
    chapter = estimate_revolute_joint(noisy, correction='chapter')
    same = estimate_joint(noisy, joint_type=JointType.REVOLUTE, robust=False, refine=False,
                          correction='chapter').best
    for name in ('axis_in_a', 'axis_in_b', 'point_in_a', 'point_in_b', 'corrected',
                 'coordinates'):
        np.testing.assert_array_equal(getattr(same, name), getattr(chapter, name))
    refined = estimate_joint(noisy, joint_type=JointType.REVOLUTE, robust=False).best
    assert not np.allclose(refined.axis_in_b, chapter.axis_in_b, atol=1e-9)
