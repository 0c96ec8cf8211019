"""Bad input gets a clear message, never a crash or a silent answer."""

from joint_estimator.common import check_unit_quaternion, compose_track, JointType, \
    relative_track, validate_track
from joint_estimator.revolute import estimate_revolute_joint
from joint_estimator.selection import estimate_joint
from joint_estimator.synthetic import random_joint_motion
import numpy as np
import pytest


@pytest.fixture
def track():
    return random_joint_motion(JointType.REVOLUTE, 20, np.random.default_rng(0)).poses


def test_too_few_poses(track):
    with pytest.raises(ValueError, match='1 poses given, at least 2 needed'):
        estimate_revolute_joint(track[:1])
    with pytest.raises(ValueError, match='2 poses given, at least 3 needed'):
        estimate_joint(track[:2], joint_type=JointType.SPHERICAL)
    with pytest.raises(ValueError, match='0 poses given'):
        estimate_joint(track[:0])


def test_nan_pose_is_named(track):
    track[7, 1, 3] = np.nan
    with pytest.raises(ValueError, match='pose 7 contains NaN'):
        estimate_joint(track)
    with pytest.raises(ValueError, match='pose 7 contains NaN'):
        estimate_revolute_joint(track)


def test_non_orthonormal_rotation_is_named(track):
    track[3, :3, :3] *= 1.01
    with pytest.raises(ValueError, match='rotation of pose 3 is not orthonormal'):
        estimate_joint(track)
    track[3, :3, :3] = np.diag([1.0, 1.0, -1.0])          # a reflection
    with pytest.raises(ValueError, match='rotation of pose 3 .*det'):
        estimate_joint(track)


def test_stamps_out_of_order(track):
    stamps = np.arange(20) * 10 ** 8
    stamps[[5, 6]] = stamps[[6, 5]]
    with pytest.raises(ValueError, match='stamps out of order or repeated at pose 6'):
        estimate_joint(track, stamps_ns=stamps)
    with pytest.raises(ValueError, match='19 stamps for 20 poses'):
        estimate_joint(track, stamps_ns=stamps[:19])


def test_wrong_shapes_and_parameters(track):
    with pytest.raises(ValueError, match=r'expected an \(N, 4, 4\) array'):
        estimate_joint(track[:, :3, :])
    with pytest.raises(ValueError, match='last row'):
        bad = track.copy()
        bad[2, 3, 0] = 1.0
        validate_track(bad)
    with pytest.raises(ValueError, match='sigma_position must be positive'):
        estimate_joint(track, sigma_position=0.0)
    with pytest.raises(ValueError):
        estimate_joint(track, joint_type=9)
    with pytest.raises(ValueError, match="correction must be 'chapter' or 'ml'"):
        estimate_joint(track, correction='magic')
    with pytest.raises(ValueError, match='link tracks differ in shape'):
        relative_track(track, track[:5])


def test_all_types_degenerate_gives_one_clear_message():
    still = compose_track(np.tile(np.eye(3), (3, 1, 1)), np.zeros((3, 3)))
    with pytest.raises(ValueError, match='prismatic: .*does not define a sliding direction'):
        estimate_joint(still, candidates=[JointType.PRISMATIC, JointType.REVOLUTE])


def test_non_unit_quaternion_of_a_message_is_refused():
    """The node's check: a norm of 2, 1e12, 1e-12 or NaN is a malformed pose, not a rotation."""
    for q in ((0.0, 0.0, 0.0, 2.0), (0.0, 0.0, 0.0, 1e12), (0.0, 0.0, 0.0, 1e-12),
              (0.0, 0.0, 0.0, 0.0), (np.nan, 0.0, 0.0, 1.0), (1.0, 1.0, 0.0, 0.0)):
        with pytest.raises(ValueError, match='quaternion norm'):
            check_unit_quaternion(q)
    # unit, and float32 round-off of a unit quaternion, pass
    check_unit_quaternion((0.0, 0.0, 0.0, 1.0))
    q = np.float32([0.1, -0.7, 0.3, 0.64]).astype(float)
    check_unit_quaternion(q / np.linalg.norm(q) * (1.0 + 1e-6))
