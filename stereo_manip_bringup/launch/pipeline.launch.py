"""
Launch the stereo_manip graph on a ROS 2 Jazzy install.

Launch the stereo_manip graph on a ROS 2 Jazzy install (``ros2 launch`` is not on PyPI; in
this repository's own environment use ``scripts/ros2run stereo_manip_bringup demo``).

    ros2 launch stereo_manip_bringup pipeline.launch.py scene:=peg_in_hole
    ros2 launch stereo_manip_bringup pipeline.launch.py scene:=revolute_pair rate:=5.0
    ros2 launch stereo_manip_bringup pipeline.launch.py scene:=peg_in_hole use_camera:=false
    ros2 launch stereo_manip_bringup pipeline.launch.py use_camera:=false multihost:=true

The nodes, parameters and remappings are the demo's (``stereo_manip_bringup.demo.STAGES``), so
the launched graph is the one the demo scores; here the synthetic camera free-runs at ``rate``
instead of waiting for a software trigger, with the free-running settings of
``LIVE_PARAMETERS`` (one stereo thread; IP modellers and joint estimator at bounded rates, which
would otherwise take the pose path's CPU). ``use_camera:=false`` leaves the camera out, for a
real stereo driver publishing ``left/image_rect``, ``right/image_rect`` and camera infos.
``multihost:=true`` gives every node the multi-host environment
(``stereo_manip_bringup.deployment``: SUBNET discovery, the shipped Fast DDS profile).
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from stereo_manip_bringup.demo import LIVE_PARAMETERS, STAGES
from stereo_manip_bringup.deployment import multihost_environment


def _nodes(context):
    scene = LaunchConfiguration('scene').perform(context)
    if scene not in STAGES:
        raise RuntimeError(f'unknown scene {scene!r}; choose one of: {", ".join(STAGES)}')
    rate = float(LaunchConfiguration('rate').perform(context))
    use_camera = LaunchConfiguration('use_camera').perform(context).lower() == 'true'
    multihost = LaunchConfiguration('multihost').perform(context).lower() == 'true'
    actions = []
    for spec in STAGES[scene]().nodes:
        params = dict(spec.parameters)
        remappings = dict(spec.remappings)
        if spec.executable == 'synthetic_camera':
            if not use_camera:
                continue
            params.update(trigger=False, rate=rate)
            remappings.pop('trigger', None)
        params.update(LIVE_PARAMETERS.get(spec.executable, {}))   # free-running: bounded rates
        actions.append(Node(package=spec.package, executable=spec.executable,
                            name=spec.node_name, parameters=[params],
                            remappings=list(remappings.items()),
                            additional_env={**spec.env, **(multihost_environment()
                                                           if multihost else {})},
                            output='screen'))
    return actions


def generate_launch_description():
    return LaunchDescription([
        DeclareLaunchArgument('scene', default_value='peg_in_hole',
                              description='demo graph: ' + ', '.join(STAGES)),
        DeclareLaunchArgument('rate', default_value='2.0',
                              description='synthetic camera rate [Hz]'),
        DeclareLaunchArgument('use_camera', default_value='true',
                              description='start the synthetic camera'),
        DeclareLaunchArgument('multihost', default_value='false',
                              description='nodes on several machines: SUBNET discovery and '
                                          'the Fast DDS profile config/fastdds_multihost.xml'),
        OpaqueFunction(function=_nodes),
    ])
