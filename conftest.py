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
