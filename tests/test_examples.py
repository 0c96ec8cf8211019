"""
The examples/ scripts against the installed nodes.

The examples/ scripts run against the installed nodes (each its own process) and report what
a controller needs: the corrected pose in the controller's TF frame, the joint estimate, and a
service answer checked against the simulated truth.
"""

import json
import os
from pathlib import Path
import subprocess
import sys

from geometry_msgs.msg import PoseStamped
from joint_estimator.common import JointType
from joint_estimator.synthetic import random_joint_motion
import numpy as np
import pytest
from std_msgs.msg import Header
from stereo_manip_msgs.msg import JointEstimate
from stereo_manip_tools.conversions import matrix_to_pose, ns_to_stamp, \
    pose_stamped_to_transform_stamped, pose_to_matrix
from stereo_manip_tools.testing import spin_until, start_executable, wait_for_subscribers
from stereo_manip_tools.tf import StaticTransformBroadcaster
from stereo_manip_tools.transforms import make_transform, rotation_about_axis

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / 'examples'


def run_example(name, *args, timeout=90):
    return subprocess.Popen([sys.executable, str(EXAMPLES / name), *args], cwd=ROOT,
                            env=dict(os.environ), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


@pytest.mark.process
def test_controller_view_sees_corrected_pose_in_world_and_joint_estimate(ros_node):
    node = ros_node
    hole = make_transform(np.eye(3), [0.0, 0.0, 0.5])           # in the camera frame
    mount = make_transform(rotation_about_axis([1, 0, 0], -np.pi / 2), [0.2, 0.0, 1.0])
    with start_executable('contact_correction', 'contact_correction_node', ros_args=[
            '-p', 'fixed_pose_static:=[0.0,0.0,0.5,0.0,0.0,0.0,1.0]',
            '-r', 'moving_pose:=/objects/peg/pose',
            '-r', 'corrected_pose:=/objects/peg/pose_corrected'],
            observer=node, wait_for_node='contact_correction'), \
        start_executable('joint_estimator', 'joint_estimator_node', ros_args=[
            '-p', 'min_poses:=10', '-p', 'estimate_every:=5',
            '-p', 'link_a_frame:=link_arm', '-p', 'link_b_frame:=link_base',
            '-r', 'link_a_pose:=/objects/link_arm/pose',
            '-r', 'link_b_pose:=/objects/link_base/pose'],
            observer=node, wait_for_node='joint_estimator'):
        # what the stereo node and the localizer would broadcast: mount and the hole block
        static = StaticTransformBroadcaster(node)
        cam = 'stereo_left_optical'
        static.send_transform([
            pose_stamped_to_transform_stamped(
                PoseStamped(header=Header(frame_id='world'), pose=matrix_to_pose(mount)), cam),
            pose_stamped_to_transform_stamped(
                PoseStamped(header=Header(frame_id=cam), pose=matrix_to_pose(hole)),
                'hole_block')])
        view = run_example('controller_view.py', '--count', '8', '--json', '--timeout', '60',
                           '--target-frame', 'world')
        peg_pub = node.create_publisher(PoseStamped, '/objects/peg/pose', 10)
        a_pub = node.create_publisher(PoseStamped, '/objects/link_arm/pose', 10)
        b_pub = node.create_publisher(PoseStamped, '/objects/link_base/pose', 10)
        corrected = []
        node.create_subscription(PoseStamped, '/objects/peg/pose_corrected', corrected.append,
                                 10)
        assert wait_for_subscribers(node, [peg_pub, a_pub, b_pub])
        assert spin_until(node, lambda: node.count_subscribers(
            '/objects/peg/pose_corrected') >= 2, 30), 'controller_view did not subscribe'
        spin_until(node, lambda: False, 1.0)
        rng = np.random.default_rng(4)
        motion = random_joint_motion(JointType.REVOLUTE, 40, rng)
        base = make_transform(np.eye(3), [0.1, 0.0, 0.6])
        estimates = []
        node.create_subscription(JointEstimate, '/joint_estimate', estimates.append, 10)
        for k in range(40):                 # two links' tracks: the joint node estimates
            header = Header(stamp=ns_to_stamp((k + 1) * 100_000_000), frame_id=cam)
            b_pub.publish(PoseStamped(header=header, pose=matrix_to_pose(base)))
            a_pub.publish(PoseStamped(header=header,
                                      pose=matrix_to_pose(base @ motion.poses[k])))
            spin_until(node, lambda: False, 0.02)
        assert spin_until(node, lambda: len(estimates) >= 1, 30)
        peg = make_transform(np.eye(3), [0.02, 0.0, 0.45])        # above the block: no contact
        for k in range(400):                # then the peg, until the view has seen 8 poses
            header = Header(stamp=ns_to_stamp((k + 41) * 100_000_000), frame_id=cam)
            peg_pub.publish(PoseStamped(header=header, pose=matrix_to_pose(peg)))
            spin_until(node, lambda: False, 0.05)
            if view.poll() is not None:
                break
        out, err = view.communicate(timeout=90)
    assert view.returncode == 0, f'controller_view failed:\n{out}\n{err}'
    records = [json.loads(line) for line in out.splitlines() if line.startswith('{')]
    poses = [r for r in records if r['event'] == 'corrected_pose']
    joints = [r for r in records if r['event'] == 'joint_estimate']
    assert len(poses) >= 8
    # the corrected pose looked up through TF in `world` = mount @ the corrected pose message
    by_stamp = {m.header.stamp.sec * 10**9 + m.header.stamp.nanosec: pose_to_matrix(m.pose)
                for m in corrected}
    in_tf = [r for r in poses if 'tf_position_m' in r and r['tf_stamp_ns'] == r['stamp_ns']]
    assert len(in_tf) >= 6, poses       # each pose waited for the transform of its own stamp
    for r in in_tf:
        expected = (mount @ by_stamp[r['stamp_ns']])[:3, 3]
        assert np.allclose(r['tf_position_m'], expected, atol=2e-6), (r, expected)
    # the joint estimate arrived and is the simulated revolute joint (axis in link B)
    assert joints and joints[-1]['type'] == 'revolute' and joints[-1]['frame'] == 'link_base'
    axis = np.array(joints[-1]['axis_in_b'])
    assert abs(axis @ motion.axis_in_b) > np.cos(np.deg2rad(2.0))


@pytest.mark.process
def test_estimate_joint_client_gets_the_hinge(ros_node):
    with start_executable('joint_estimator', 'joint_estimator_node', observer=ros_node,
                          wait_for_node='joint_estimator'):
        client = run_example('estimate_joint_client.py', '--noise-deg', '1.0',
                             '--max-axis-error-deg', '3.0')
        out, err = client.communicate(timeout=120)
    assert client.returncode == 0, f'estimate_joint_client failed:\n{out}\n{err}'
    assert 'joint type: REVOLUTE' in out and 'corrected track: 40 poses' in out
