"""object_localizer_node as its own process: a cloud in, the object's pose out."""

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

from object_localizer.evaluation import add_s, sample_visible_surface
from object_localizer.localization import prepare_model
from stereo_manip_tools.conversions import ns_to_stamp, pointcloud2_to_array, pose_to_matrix, \
    xyz_to_pointcloud2
from stereo_manip_tools.mesh_io import find_model, load_obj
from stereo_manip_tools.testing import spin_until, start_executable, wait_for_subscribers
from stereo_manip_tools.transforms import make_transform, rotation_about_axis


@pytest.mark.process
def test_node_publishes_pose_of_object_in_cloud(ros_node):
    arm = load_obj(find_model('link_arm'))
    T = make_transform(rotation_about_axis([0.2, 1.0, 0.1], 0.9), [0.03, -0.02, 0.7])
    points = sample_visible_surface(arm, T, 8000, seed=7)
    points += np.random.default_rng(7).normal(scale=0.0005, size=points.shape)
    header = Header(frame_id='stereo_left_optical', stamp=ns_to_stamp(1_234_000_000))
    cloud = xyz_to_pointcloud2(points, header)
    poses, clouds = [], []
    ros_node.create_subscription(PoseStamped, '/objects/link_arm/pose', poses.append, 10)
    ros_node.create_subscription(PointCloud2, '/objects/link_arm/cloud', clouds.append, 10)
    bad = PointCloud2(header=header, height=1, width=10, point_step=12,
                      fields=[PointField(name='x', offset=0, datatype=7, count=1)],
                      data=b'\0' * 120)
    pub = ros_node.create_publisher(PointCloud2, '/points2', 10)
    with start_executable('object_localizer', 'object_localizer_node',
                          ros_args=['-p', 'models:=[link_arm]'], observer=ros_node,
                          wait_for_node='object_localizer') as proc:
        assert wait_for_subscribers(ros_node, [pub])
        pub.publish(bad)  # no y/z fields: rejected with a warning, node keeps going
        assert spin_until(ros_node, lambda: 'points2 rejected' in proc.output(), 20), \
            proc.output()
        pub.publish(cloud)
        assert spin_until(ros_node, lambda: len(poses) > 0 and len(clouds) > 0, 30), \
            proc.output()
        assert proc.running()
    got = poses[0]
    assert got.header.stamp == header.stamp and got.header.frame_id == 'stereo_left_optical'
    assert add_s(pose_to_matrix(got.pose), T, prepare_model(arm).points) < 0.0015
    # the segmented cloud is the object's points (all of them; nothing else was in the scene)
    assert abs(len(pointcloud2_to_array(clouds[0])) - len(points)) <= 0.01 * len(points)


@pytest.mark.process
def test_node_refuses_malformed_initial_poses():
    with start_executable('object_localizer', 'object_localizer_node',
                          ros_args=['-p', 'models:=[link_arm]',
                                    '-p', 'initial_poses:=[0.0, 0.0, 1.0]']) as proc:
        proc.process.wait(60)
        out = proc.output()
    assert proc.process.returncode != 0
    assert 'initial_poses has 3 numbers; expected 7 per model' in out
    assert 'Traceback' not in out
