"""The demo runner's pieces, the launch file, and one short demo run as separate processes."""

import importlib.util
from pathlib import Path
import sys
import types

import numpy as np
import pytest

from stereo_manip_bringup import demo
from stereo_manip_tools.processes import executable_path


def test_ros_args_format_parameters_and_remappings():
    spec = demo.NodeSpec('pkg', 'exe', 'name', {'a': True, 'b': [1.5, 2.0], 'c': 'x'},
                         {'in': '/out'})
    assert spec.ros_args() == ['-r', '__node:=name', '-p', 'a:=true', '-p', 'b:=[1.5,2.0]',
                               '-p', 'c:=x', '-r', 'in:=/out']


def test_line_errors():
    angle, dist = demo._line_errors(np.array([0, 0, 2.0]), np.zeros(3),
                                    np.array([0, 0.01, -1.0]), np.array([0.003, 0.0, 5.0]))
    assert angle == pytest.approx(np.degrees(np.arctan(0.01)), rel=1e-6)
    assert dist == pytest.approx(0.003)


@pytest.mark.parametrize('name', list(demo.STAGES))
def test_every_stage_names_installed_executables(name):
    stage = demo.STAGES[name]()
    assert stage.stamp_topic in stage.topics
    assert stage.done_topics and set(stage.done_topics) <= set(stage.topics)
    for spec in stage.nodes:
        assert executable_path(spec.package, spec.executable).is_file()


def test_launch_file_builds_the_demo_graph(monkeypatch):
    """launch/launch_ros are not on PyPI: stand-ins record what the launch file asks for."""
    made = []

    class Config:
        values = {'scene': 'revolute_pair', 'rate': '5.0', 'use_camera': 'true'}

        def __init__(self, name):
            self.name = name

        def perform(self, context):
            return self.values[self.name]

    def node(**kwargs):
        made.append(kwargs)
        return kwargs

    fake = {'launch': types.SimpleNamespace(LaunchDescription=list),
            'launch.actions': types.SimpleNamespace(
                DeclareLaunchArgument=lambda *a, **k: ('arg', a[0]),
                OpaqueFunction=lambda function: ('opaque', function)),
            'launch.substitutions': types.SimpleNamespace(LaunchConfiguration=Config),
            'launch_ros.actions': types.SimpleNamespace(Node=node)}
    for mod, ns in fake.items():
        monkeypatch.setitem(sys.modules, mod, ns)
    path = Path(__file__).resolve().parents[1] / 'launch' / 'pipeline.launch.py'
    spec = importlib.util.spec_from_file_location('pipeline_launch', path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    description = module.generate_launch_description()
    assert [a[1] for a in description if a[0] == 'arg'] == ['scene', 'rate', 'use_camera']
    opaque = [a[1] for a in description if a[0] == 'opaque'][0]
    opaque(None)
    names = [n['name'] for n in made]
    assert names == [s.node_name for s in demo.STAGES['revolute_pair']().nodes]
    camera = made[0]
    assert camera['parameters'][0]['trigger'] is False and camera['parameters'][0]['rate'] == 5.0
    assert all(n['additional_env']['OPENBLAS_NUM_THREADS'] == '1' for n in made)
    for n in made:
        assert executable_path(n['package'], n['executable']).is_file()


@pytest.mark.process
def test_short_demo_run_scores_a_stage(tmp_path):
    """End to end: camera -> stereo -> localiser -> IP modeller as separate processes."""
    from stereo_manip_tools.processes import ExecutableProcess
    proc = ExecutableProcess('stereo_manip_bringup', 'demo',
                             ['--out', str(tmp_path), '--stages', 'primitives', '--frames',
                              '0.5'])
    proc.process.wait(400)
    out = proc.output()
    assert proc.process.returncode == 0, out
    report = (tmp_path / 'report.md').read_text()
    assert 'cube: degree' in report and 'torus: degree' in report, report
    assert (tmp_path / 'primitives.object_localizer.log').is_file()
