"""Session-wide test isolation: a random ROS domain and localhost-only discovery.

Set before any rclpy context exists, so every in-process node and every executable started by
``stereo_manip_tools.testing`` joins only this session's graph.
"""

import importlib
import os
from pathlib import Path
import random
import sys

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


#: the Noble-pinned job's test, collected last of the pure-core group (tests/noble_job.py)
NOBLE_TEST = 'tests/test_noble_pinned.py::test_pure_core_tests_pass_with_noble_versions'
_uses_ros: dict = {}


def _pure_core(item: pytest.Item) -> bool:
    """Tell whether a test is of the pure-core tier: no rclpy, no executables, no timing."""
    if any(item.get_closest_marker(m) for m in ('ros', 'process')):
        return False
    path = Path(str(item.fspath))
    if path not in _uses_ros:
        _uses_ros[path] = 'rclpy' in path.read_text(errors='replace')
    return not _uses_ros[path]


def pytest_collection_modifyitems(session, config, items):
    """
    Overlap the Noble-pinned job with this venv's pure-core tests.

    Both are single-threaded runs of the same tests: on two cores they take the time of one.
    The job starts now (``make test`` started it before the bootstrap already: it is attached to,
    tests/noble_job.py); the pure-core tests run first, the job's test next (it waits for the
    job), the rclpy and process tiers last, alone. Only in a run that collects the job's test
    with the rest (``make test``); STEREO_MANIP_NOBLE_BACKGROUND=0 turns it off.
    """
    noble = [i for i in items if i.nodeid == NOBLE_TEST]
    if (not noble or len(items) < 50 or config.getoption('collectonly')
            or os.environ.get('STEREO_MANIP_NOBLE_BACKGROUND', '1') == '0'):
        return
    sys.path.insert(0, str(Path(__file__).resolve().parent / 'tests'))
    import noble_job
    if noble_job.unavailable_reason() is not None:
        return
    # the job make test started before the bootstrap (scripts/make_test.sh), else one now
    noble_job.background = noble_job.attach() or noble_job.BackgroundJob()
    config.add_cleanup(noble_job.background.cancel)
    core = [i for i in items if i is not noble[0] and _pure_core(i)]
    rest = [i for i in items if i is not noble[0] and not _pure_core(i)]
    items[:] = core + noble + rest
