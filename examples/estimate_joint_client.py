#!/usr/bin/env python3
"""
A controller asks joint_estimator_node which joint links a door to its frame.

    source scripts/env.sh
    scripts/ros2run joint_estimator joint_estimator_node &      # the server
    python examples/estimate_joint_client.py --noise-deg 1.0

The controller has recorded a track of the door leaf (link A) in the frame's coordinates
(link B) -- here simulated: a revolute motion about a known hinge plus noise -- and calls the
``estimate_joint`` service (stereo_manip_msgs/srv/EstimateJoint) with it. It prints the joint
type, hinge axis and point, and their errors against the simulated truth; exit status 0 when the
service answered with a revolute joint within ``--max-axis-error-deg``.
"""

import argparse
import math
import sys

from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
import numpy as np
import rclpy
from stereo_manip_msgs.msg import JointEstimate
from stereo_manip_msgs.srv import EstimateJoint

from stereo_manip_tools.conversions import matrix_to_pose, ns_to_stamp
from stereo_manip_tools.transforms import make_transform, rotation_about_axis


def door_track(n: int, noise_deg: float, noise_m: float, seed: int):
    """Poses of a door leaf swinging 80 degrees about a hinge (axis, point) in link B."""
    rng = np.random.default_rng(seed)
    axis = np.array([0.1, 0.05, 1.0])
    axis /= np.linalg.norm(axis)
    point = np.array([0.3, -0.1, 0.5])
    leaf = make_transform(np.eye(3), [0.4, 0.0, 0.0])          # leaf origin 0.4 m off the hinge
    poses = []
    for angle in np.linspace(0.0, np.deg2rad(80.0), n):
        R = rotation_about_axis(axis, angle)
        hinge = make_transform(R, point - R @ point)
        T = hinge @ make_transform(np.eye(3), point) @ leaf
        noise = make_transform(rotation_about_axis(rng.normal(size=3),
                                                   np.deg2rad(noise_deg) * rng.normal()),
                               noise_m * rng.normal(size=3))
        poses.append(T @ noise)
    return np.array(poses), axis, point


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--service', default='/estimate_joint')
    parser.add_argument('--poses', type=int, default=40)
    parser.add_argument('--noise-deg', type=float, default=1.0)
    parser.add_argument('--noise-mm', type=float, default=1.0)
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--timeout', type=float, default=30.0)
    parser.add_argument('--max-axis-error-deg', type=float, default=5.0)
    opts = parser.parse_args(argv)

    poses, axis, point = door_track(opts.poses, opts.noise_deg, opts.noise_mm / 1000, opts.seed)
    request = EstimateJoint.Request(joint_type=EstimateJoint.Request.AUTO)
    request.link_a = Path()
    request.link_a.header.frame_id = 'door_frame'
    for k, T in enumerate(poses):
        p = PoseStamped(pose=matrix_to_pose(T))
        p.header.frame_id = 'door_frame'
        p.header.stamp = ns_to_stamp((k + 1) * 100_000_000)
        request.link_a.poses.append(p)

    rclpy.init()
    node = rclpy.create_node('estimate_joint_client')
    try:
        client = node.create_client(EstimateJoint, opts.service)
        if not client.wait_for_service(timeout_sec=opts.timeout):
            print(f'{opts.service} not available within {opts.timeout} s', file=sys.stderr)
            return 1
        future = client.call_async(request)
        rclpy.spin_until_future_complete(node, future, timeout_sec=opts.timeout)
        if not future.done():
            print(f'{opts.service} did not answer within {opts.timeout} s', file=sys.stderr)
            return 1
        response = future.result()
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    if not response.success:
        print(f'estimate_joint failed: {response.message}', file=sys.stderr)
        return 1
    est = response.estimate
    got_axis = np.array([est.axis_in_b.x, est.axis_in_b.y, est.axis_in_b.z])
    got_point = np.array([est.point_in_b.x, est.point_in_b.y, est.point_in_b.z])
    axis_error = math.degrees(math.acos(min(1.0, abs(float(got_axis @ axis)))))
    # distance of the true hinge point from the estimated axis line
    d = point - got_point
    line_error = float(np.linalg.norm(d - (d @ got_axis) * got_axis))
    kind = {v: k for k, v in vars(JointEstimate).items() if k.isupper()
            and isinstance(v, int)}.get(est.joint_type, str(est.joint_type))
    print(f'joint type: {kind} (frame {est.header.frame_id}, {est.sample_count} poses, '
          f'{est.outlier_count} outliers)')
    print(f'axis in link B: {np.round(got_axis, 4).tolist()}  error {axis_error:.2f} deg')
    print(f'hinge line: error {line_error * 1000:.1f} mm; residuals '
          f'{math.degrees(est.rotation_residual):.2f} deg, {est.position_residual * 1000:.1f} mm')
    print(f'corrected track: {len(response.corrected_track.poses)} poses')
    ok = est.joint_type == JointEstimate.REVOLUTE and axis_error <= opts.max_axis_error_deg
    return 0 if ok else 1


if __name__ == '__main__':
    sys.exit(main())
