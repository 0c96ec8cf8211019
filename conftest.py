"""Session-wide test isolation: a random ROS domain and localhost-only discovery.

Set before any rclpy context exists, so every in-process node and every executable started by
``stereo_manip_tools.testing`` joins only this session's graph.
"""

import os
import random

os.environ['ROS_DOMAIN_ID'] = os.environ.get('STEREO_MANIP_TEST_DOMAIN') or str(
    random.SystemRandom().randint(1, 101))
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'

pytest_plugins = ['stereo_manip_tools.testing']

# pytest's importlib mode names test modules after their path (object_localizer.test.test_x)
# and would otherwise bind the bare source folder `object_localizer/` (no __init__.py) as the
# package; importing the installed packages first keeps the real ones in sys.modules.
import importlib  # noqa: E402

for _pkg in ('stereo_manip_tools', 'stereo_depth', 'object_localizer', 'contact_correction',
             'joint_estimator', 'ip_modeler', 'stereo_manip_bringup'):
    importlib.import_module(_pkg)
