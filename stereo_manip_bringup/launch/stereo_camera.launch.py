r"""
Launch stereo_manip on a real stereo camera (ROS 2 Jazzy install; no synthetic scene).

    ros2 launch stereo_manip_bringup stereo_camera.launch.py \
        camera_namespace:=/stereo params_file:=/path/to/my_stereo_camera.yaml
    ros2 launch stereo_manip_bringup stereo_camera.launch.py namespace:=cell_1 \
        use_contact:=true use_joint:=false

The camera driver (started separately: it owns the hardware) publishes rectified images and
camera infos under ``camera_namespace``: ``left/image_rect``, ``right/image_rect``,
``left/camera_info``, ``right/camera_info`` (what image_proc's rectify nodes give). This file
starts, in ``namespace``:

- ``stereo_depth_node``: disparity, depth, ``points2``; static TF of the camera mount;
- ``object_localizer``: ``objects/<model>/pose`` (+ TF ``<model>``), tracks, segmented clouds;
- ``contact_correction`` (``use_contact``): ``objects/<moving>/pose_corrected``
  (+ TF ``<moving>_corrected``) and ``contact_state``;
- ``joint_estimator`` (``use_joint``): ``joint_estimate`` and the corrected link pose
  (+ TF ``<link_a>_corrected``).

Every parameter comes from ``params_file`` (default: this package's
``config/stereo_camera.yaml``, a template to copy and edit: models, camera frame and mount, the
moving/fixed objects and link names). The synthetic demo graph is ``pipeline.launch.py``.
With the camera on another machine, ``multihost:=true`` gives every node the multi-host
environment (``stereo_manip_bringup.deployment``: SUBNET discovery, the shipped Fast DDS
profile ``config/fastdds_multihost.xml``); start the driver with the same two variables.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from stereo_manip_bringup.deployment import multihost_environment


def _nodes(context):
    import yaml

    params_file = LaunchConfiguration('params_file').perform(context)
    if not os.path.isfile(params_file):
        raise RuntimeError(f'params_file {params_file!r} does not exist')
    camera = LaunchConfiguration('camera_namespace').perform(context).rstrip('/') or ''
    with open(params_file) as f:
        params = yaml.safe_load(f) or {}

    def node_params(name):
        for key, value in params.items():
            if key.split('/')[-1] == name:
                return (value or {}).get('ros__parameters', {})
        return {}
    contact = node_params('contact_correction')
    joint = node_params('joint_estimator')
    moving = contact.get('moving_object', 'peg')
    fixed = contact.get('fixed_object', 'hole_block')
    link_a = joint.get('link_a_frame', 'link_a')
    link_b = joint.get('link_b_frame', 'link_b')
    multihost = LaunchConfiguration('multihost').perform(context).lower() == 'true'
    common = {'namespace': LaunchConfiguration('namespace'), 'parameters': [params_file],
              'additional_env': multihost_environment() if multihost else {},
              'output': 'screen'}
    return [
        Node(package='stereo_depth', executable='stereo_depth_node', name='stereo_depth_node',
             remappings=[(f'{side}/{topic}', f'{camera}/{side}/{topic}')
                         for side in ('left', 'right')
                         for topic in ('image_rect', 'camera_info')], **common),
        Node(package='object_localizer', executable='object_localizer_node',
             name='object_localizer', **common),
        Node(package='contact_correction', executable='contact_correction_node',
             name='contact_correction',
             condition=IfCondition(LaunchConfiguration('use_contact')),
             remappings=[('moving_pose', f'objects/{moving}/pose'),
                         ('fixed_pose', f'objects/{fixed}/pose'),
                         ('corrected_pose', f'objects/{moving}/pose_corrected'),
                         ('corrected_pose_smoothed',
                          f'objects/{moving}/pose_corrected_smoothed')], **common),
        Node(package='joint_estimator', executable='joint_estimator_node',
             name='joint_estimator', condition=IfCondition(LaunchConfiguration('use_joint')),
             remappings=[('link_a_pose', f'objects/{link_a}/pose'),
                         ('link_b_pose', f'objects/{link_b}/pose')], **common),
    ]


def generate_launch_description():
    default_params = os.path.join(get_package_share_directory('stereo_manip_bringup'),
                                  'config', 'stereo_camera.yaml')
    return LaunchDescription([
        DeclareLaunchArgument('namespace', default_value='',
                              description='namespace of the stereo_manip nodes'),
        DeclareLaunchArgument('camera_namespace', default_value='/stereo',
                              description='where the driver publishes left/ and right/ '
                                          'image_rect and camera_info'),
        DeclareLaunchArgument('params_file', default_value=default_params,
                              description='ROS parameters file of every node'),
        DeclareLaunchArgument('use_contact', default_value='true',
                              description='start contact_correction_node'),
        DeclareLaunchArgument('use_joint', default_value='false',
                              description='start joint_estimator_node'),
        DeclareLaunchArgument('multihost', default_value='false',
                              description='camera, perception and controller on different '
                                          'machines: SUBNET discovery and the Fast DDS profile '
                                          'config/fastdds_multihost.xml'),
        OpaqueFunction(function=_nodes),
    ])
