"""Automatic joint type selection (BIC) and outlier-frame rejection (MSAC + refit)."""

from joint_estimator.common import compose_track, JointType
from joint_estimator.selection import ALL_TYPES, bic_score, estimate_joint
from joint_estimator.synthetic import add_noise, add_outliers, random_joint_motion
import numpy as np
import pytest

SP, SR = 0.001, np.deg2rad(1.0)


@pytest.mark.slow
@pytest.mark.parametrize('jt', list(JointType))
def test_selection_picks_the_right_type_on_clean_data(jt):
    for seed in range(3):
        rng = np.random.default_rng(100 * int(jt) + seed)
        g = random_joint_motion(jt, 60, rng)
        # noiseless track
        res = estimate_joint(g.poses, sigma_position=SP, sigma_rotation=SR)
        assert res.best.joint_type == jt, res.status
        # slightly noisy track
        res = estimate_joint(add_noise(g.poses, SP, SR, rng), sigma_position=SP,
                             sigma_rotation=SR)
        assert res.best.joint_type == jt, res.status
        assert res.best.outlier_indices.size <= 1
        assert set(res.scores) | set(res.failures) == set(ALL_TYPES)
        assert res.best.score == min(res.scores.values())


def test_scores_follow_the_bic_formula():
    rng = np.random.default_rng(1)
    g = random_joint_motion(JointType.REVOLUTE, 50, rng)
    res = estimate_joint(add_noise(g.poses, SP, SR, rng), sigma_position=SP, sigma_rotation=SR,
                         robust=False)
    fit = res.candidates[JointType.REVOLUTE]
    assert not fit.scale_estimated and fit.sigma_position == SP and fit.sigma_rotation == SR
    expected = fit.chi2.sum() + 50 * 6 * np.log(2 * np.pi * SP * SR) + (9 + 50) * np.log(300)
    assert fit.score == pytest.approx(expected, rel=1e-12)
    assert bic_score(fit, 1e9) == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize('jt', [JointType.REVOLUTE, JointType.PRISMATIC, JointType.PLANAR,
                                JointType.SPHERICAL])
def test_outlier_frames_are_rejected_and_reported(jt):
    rng = np.random.default_rng(40 + int(jt))
    g = random_joint_motion(jt, 100, rng)
    noisy, mask = add_outliers(add_noise(g.poses, SP, SR, rng), 0.2, rng)
    res = estimate_joint(noisy, sigma_position=SP, sigma_rotation=SR)
    assert res.best.joint_type == jt, res.status
    np.testing.assert_array_equal(res.best.outlier_indices, np.flatnonzero(mask))
    assert '20 of 100 frames rejected' in res.status
    # the robust estimate is as good as the one on the clean frames alone
    clean = estimate_joint(noisy[~mask], joint_type=jt, sigma_position=SP, sigma_rotation=SR,
                           robust=False).best
    # (equal up to the refinement's convergence tolerance: the robust fit refines in rounds)
    np.testing.assert_allclose(res.best.corrected[~mask], clean.corrected, atol=1e-6)
    # without rejection the outliers pull the fit away
    naive = estimate_joint(noisy, joint_type=jt, sigma_position=SP, sigma_rotation=SR,
                           robust=False).best
    err_naive = np.abs(naive.corrected[~mask] - g.poses[~mask]).max()
    err_robust = np.abs(res.best.corrected[~mask] - g.poses[~mask]).max()
    assert err_robust < err_naive


def test_degenerate_motion_is_reported_not_answered_with_a_random_axis():
    rng = np.random.default_rng(3)
    still = add_noise(compose_track(np.tile(np.eye(3), (30, 1, 1)), np.zeros((30, 3))),
                      SP, SR, rng)
    res = estimate_joint(still, sigma_position=SP, sigma_rotation=SR)
    assert res.best.joint_type == JointType.FIXED
    assert JointType.REVOLUTE in res.failures
    assert 'does not define a revolute axis' in res.failures[JointType.REVOLUTE]
    assert 'revolute not scored' in res.status
    with pytest.raises(ValueError, match='does not define a revolute axis'):
        estimate_joint(still, joint_type=JointType.REVOLUTE, sigma_position=SP,
                       sigma_rotation=SR)


def test_requested_type_fits_only_that_type():
    rng = np.random.default_rng(4)
    g = random_joint_motion(JointType.CYLINDRICAL, 40, rng)
    res = estimate_joint(g.poses, joint_type=int(JointType.REVOLUTE))
    assert list(res.candidates) == [JointType.REVOLUTE]
    auto = estimate_joint(g.poses, joint_type=255)
    assert auto.best.joint_type == JointType.CYLINDRICAL
