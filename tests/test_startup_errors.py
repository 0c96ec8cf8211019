"""
Bad start-up parameters end every node with one line on stderr and exit code 1.

Bad start-up parameters end every node with one line on stderr and exit code 1 (no rclpy
traceback): NaN, a missing model, out of range, wrong type (one case per node).
"""

import pytest

from stereo_manip_tools.testing import start_executable

NODES = [
    ('stereo_depth', 'stereo_depth_node', ['-p', 'sync_tolerance:=.nan']),
    ('object_localizer', 'object_localizer_node', ['-p', 'models:=[no_such_model]']),
    ('contact_correction', 'contact_correction_node', ['-p', 'tolerance:=.nan']),
    ('joint_estimator', 'joint_estimator_node', ['-p', 'window_size:=1']),
    ('ip_modeler', 'ip_modeler_node', ['-p', 'max_degree:=abc']),
]


@pytest.mark.process
@pytest.mark.parametrize('package, executable, ros_args', NODES,
                         ids=[f'{e}:{a[1]}' for _, e, a in NODES])
def test_bad_startup_parameter_gives_one_line_and_exit_1(package, executable, ros_args):
    with start_executable(package, executable, ros_args=ros_args) as proc:
        proc.process.wait(60)
        out = proc.output()
    assert proc.process.returncode == 1, out
    assert 'Traceback' not in out, out
    lines = [ln for ln in out.splitlines() if ln.strip() and '[INFO]' not in ln
             and 'Warning' not in ln and 'warnings.warn' not in ln]
    assert len(lines) == 1 and lines[0].startswith(f'{executable}: '), out
