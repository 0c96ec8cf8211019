"""
stereo_camera.launch.py (real stereo camera).

The launch file builds the graph from its arguments and params file alone (run here against
stand-ins of `launch`/`launch_ros`, which are not on PyPI), and the shipped params file is valid
for every node it names.
"""

import ast
from pathlib import Path
import sys
import types

import numpy as np
import pytest
from stereo_manip_tools.testing import make_node, shutdown_node, spin_until, start_executable
from stereo_manip_tools.tf import TransformListener
from stereo_manip_tools.transforms import pose_from_xyz_quaternion
import yaml

ROOT = Path(__file__).resolve().parents[1]
LAUNCH = ROOT / 'stereo_manip_bringup' / 'launch' / 'stereo_camera.launch.py'
PARAMS = ROOT / 'stereo_manip_bringup' / 'config' / 'stereo_camera.yaml'


class _Recorded:
    def __init__(self, *args, **kwargs):
        self.args, self.kwargs = args, kwargs


def _stub_launch(monkeypatch, values):
    """Minimal `launch` / `launch_ros` whose actions record their arguments."""
    class LaunchConfiguration:
        def __init__(self, name):
            self.name = name

        def perform(self, context):
            return context[self.name]

    mods = {
        'launch': {'LaunchDescription': lambda actions: actions},
        'launch.actions': {'DeclareLaunchArgument': _Recorded, 'OpaqueFunction': _Recorded},
        'launch.conditions': {'IfCondition': lambda cfg: ('if', cfg.name)},
        'launch.substitutions': {'LaunchConfiguration': LaunchConfiguration},
        'launch_ros': {}, 'launch_ros.actions': {'Node': _Recorded}}
    for name, attrs in mods.items():
        module = types.ModuleType(name)
        module.__dict__.update(attrs)
        monkeypatch.setitem(sys.modules, name, module)


def test_launch_file_has_no_synthetic_dependency():
    tree = ast.parse(LAUNCH.read_text())
    names = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)} | {
        a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    assert not {m for m in names if m and ('synthetic' in m or 'demo' in m or
                                           m.startswith('stereo_depth'))}, names
    assert 'synthetic' not in LAUNCH.read_text().split('"""', 2)[2]


def test_launch_builds_the_graph_from_arguments_and_params(monkeypatch):
    _stub_launch(monkeypatch, {})
    namespace = {}
    exec(compile(LAUNCH.read_text(), str(LAUNCH), 'exec'), namespace)
    description = namespace['generate_launch_description']()
    declared = {a.args[0]: a.kwargs['default_value'] for a in description
                if isinstance(a, _Recorded) and 'default_value' in a.kwargs}
    assert {'namespace', 'camera_namespace', 'params_file', 'use_contact',
            'use_joint'} <= set(declared)
    assert declared['params_file'].endswith('config/stereo_camera.yaml')
    opaque = [a for a in description if isinstance(a, _Recorded) and 'function' in a.kwargs]
    context = {'params_file': str(PARAMS), 'camera_namespace': '/my_cam/', 'namespace': 'c1',
               'multihost': 'false'}
    nodes = {n.kwargs['name']: n.kwargs for n in opaque[0].kwargs['function'](context)}
    assert all(kw['additional_env'] == {} for kw in nodes.values())
    # multihost:=true: every node gets SUBNET discovery and the shipped Fast DDS profile
    multi = opaque[0].kwargs['function']({**context, 'multihost': 'true'})
    for n in multi:
        env = n.kwargs['additional_env']
        assert env['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'SUBNET'
        assert Path(env['FASTRTPS_DEFAULT_PROFILES_FILE']).is_file()
    assert set(nodes) == {'stereo_depth_node', 'object_localizer', 'contact_correction',
                          'joint_estimator'}
    for kw in nodes.values():
        assert kw['parameters'] == [str(PARAMS)] and kw['namespace'].name == 'namespace'
    assert dict(nodes['stereo_depth_node']['remappings'])['left/image_rect'] == \
        '/my_cam/left/image_rect'
    assert dict(nodes['contact_correction']['remappings']) == {
        'moving_pose': 'objects/peg/pose', 'fixed_pose': 'objects/hole_block/pose',
        'corrected_pose': 'objects/peg/pose_corrected',
        'corrected_pose_smoothed': 'objects/peg/pose_corrected_smoothed'}
    assert dict(nodes['joint_estimator']['remappings'])['link_b_pose'] == \
        'objects/link_base/pose'
    assert nodes['joint_estimator']['condition'] == ('if', 'use_joint')
    context['params_file'] = '/nonexistent.yaml'
    with pytest.raises(RuntimeError, match='does not exist'):
        opaque[0].kwargs['function'](context)


@pytest.mark.ros
def test_params_file_names_only_declared_parameters():
    from contact_correction.contact_correction_node import ContactCorrectionNode
    from joint_estimator.joint_estimator_node import JointEstimatorNode
    from object_localizer.localizer_node import ObjectLocalizerNode
    from rclpy.parameter import Parameter
    from stereo_depth.stereo_depth_node import StereoDepthNode
    classes = {'stereo_depth_node': StereoDepthNode, 'object_localizer': ObjectLocalizerNode,
               'contact_correction': ContactCorrectionNode,
               'joint_estimator': JointEstimatorNode}
    params = yaml.safe_load(PARAMS.read_text())
    assert {k.split('/')[-1] for k in params} == set(classes)
    for key, section in params.items():
        name = key.split('/')[-1]
        values = section['ros__parameters']
        anchor = make_node()
        try:
            node = classes[name](context=anchor.context, parameter_overrides=[
                Parameter(k, value=v) for k, v in values.items()])
            try:
                for k, v in values.items():
                    assert node.has_parameter(k), f'{name} declares no parameter {k!r}'
                    assert node.get_parameter(k).value == v or np.allclose(
                        node.get_parameter(k).value, v), (name, k)
            finally:
                node.destroy_node()
        finally:
            shutdown_node(anchor)


@pytest.mark.process
def test_params_file_gives_the_camera_mount_on_tf_static(ros_node):
    listener = TransformListener(ros_node)
    with start_executable('stereo_depth', 'stereo_depth_node',
                          ros_args=['--params-file', str(PARAMS)], observer=ros_node,
                          wait_for_node='stereo_depth_node'):
        assert spin_until(ros_node, lambda: listener.can_transform('base_link',
                                                                   'stereo_left_optical'), 20)
    T, stamp = listener.lookup('base_link', 'stereo_left_optical')
    mount = yaml.safe_load(PARAMS.read_text())['/**/stereo_depth_node']['ros__parameters']
    assert np.allclose(T, pose_from_xyz_quaternion(mount['camera_mount_pose']), atol=1e-9)
    assert stamp == 0                                   # static: no dynamic stamp in the chain
    # the camera looks along base_link's +x: optical z (forward) = base x
    assert np.allclose(T[:3, 2], [1, 0, 0], atol=1e-9)
