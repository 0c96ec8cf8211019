"""Session-wide test isolation: a random ROS domain and localhost-only discovery.

Set before any rclpy context exists, so every in-process node and every executable started by
``stereo_manip_tools.testing`` joins only this session's graph.
"""

import importlib
import os
import random

import pytest

os.environ['ROS_DOMAIN_ID'] = os.environ.get('STEREO_MANIP_TEST_DOMAIN') or str(
    random.SystemRandom().randint(1, 101))
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'

pytest_plugins = ['stereo_manip_tools.testing']

# pytest's importlib mode names test modules after their path (object_localizer.test.test_x)
# and would otherwise bind the bare source folder `object_localizer/` (no __init__.py) as the
# package; importing the installed packages first keeps the real ones in sys.modules.
for _pkg in ('stereo_manip_tools', 'stereo_depth', 'object_localizer', 'contact_correction',
             'joint_estimator', 'ip_modeler', 'stereo_manip_bringup'):
    importlib.import_module(_pkg)


@pytest.fixture(autouse=True)
def _linter_in_package_folder(request, monkeypatch):
    """Run an ament linter test in its package folder, as ``colcon test`` does.

    The ament linters check the current folder; this suite runs from the workspace root.
    """
    if request.node.get_closest_marker('linter'):
        monkeypatch.chdir(request.path.parents[1])
