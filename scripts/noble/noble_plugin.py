"""
pytest plugin of the Noble-pinned job (tests/test_noble_pinned.py).

The job runs the package tests with Noble's library versions and without ROS (its venv has no
rclpy or message packages). A test module whose import fails only because a ROS module is
missing is an rclpy-tier test: it is reported as skipped with that reason. Any other import
error (a library API missing from the pinned version, e.g. scipy.linalg.lapack.dtrcon) fails.
"""

import importlib
import re

import pytest

# top-level modules that come with ROS, not with the Python libraries the job pins
ROS_MODULE = re.compile(r'^(rclpy|rosidl_\w+|rpyutils|ament_\w+|launch\w*|\w+_msgs|'
                        r'\w+_interfaces|rosbags)$')
MISSING = re.compile(r"No module named '([\w.]+)'")

for _pkg in ('stereo_manip_tools', 'stereo_depth', 'object_localizer', 'contact_correction',
             'joint_estimator', 'ip_modeler', 'stereo_manip_bringup'):
    try:    # bind the real packages before pytest's importlib mode sees the source folders
        importlib.import_module(_pkg)
    except ImportError:
        pass


@pytest.hookimpl(hookwrapper=True)
def pytest_make_collect_report(collector):
    outcome = yield
    report = outcome.get_result()
    if not report.failed or not isinstance(collector, pytest.Module):
        return
    found = MISSING.search(str(report.longrepr))
    if found and ROS_MODULE.match(found.group(1).split('.')[0]):
        report.outcome = 'skipped'
        report.longrepr = (str(collector.path), 0,
                           f'Skipped: needs ROS ({found.group(1)}), not in the Noble-pinned venv')
