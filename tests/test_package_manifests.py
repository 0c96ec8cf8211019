"""
package.xml declares what each package imports, with rosdep keys for Noble.

package.xml declares what each package imports, with rosdep keys that resolve on Ubuntu 24.04
(Noble) for ROS 2 Jazzy, so `rosdep install --from-paths . -i` + `colcon build` work on a stock
install. Imports are read from the sources (every import statement, lazy ones too).
"""

import ast
from pathlib import Path
import sys
import xml.etree.ElementTree as ET

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {'stereo_manip_tools': 'stereo_manip_tools', 'stereo_depth': 'stereo_depth',
            'object_localizer': 'object_localizer', 'contact_correction': 'contact_correction',
            'joint_estimator': 'joint_estimator', 'ip_modeler': 'ip_modeler',
            'stereo_manip_bringup': 'stereo_manip_bringup'}
WORKSPACE = set(PACKAGES) | {'stereo_manip_msgs'}
# Python module -> rosdep key (rosdistro rosdep/base.yaml, python.yaml; checked for noble)
SYSTEM_KEYS = {'numpy': 'python3-numpy', 'scipy': 'python3-scipy', 'cv2': 'python3-opencv',
               'skimage': 'python3-skimage', 'matplotlib': 'python3-matplotlib',
               'mpl_toolkits': 'python3-matplotlib', 'open3d': 'python3-open3d-pip',
               'pytest': 'python3-pytest', 'hypothesis': 'python3-hypothesis',
               'yaml': 'python3-yaml'}
# modules with no rosdep key on noble: the manifest must say so in a comment naming pip
PIP_ONLY = {'numba', 'rosbags'}
# test helpers imported by name from their own folder
LOCAL_MODULES = {p.stem for p in ROOT.glob('*/test/*.py')} | {'conftest'}
ROS_PACKAGES = {'rclpy', 'launch', 'launch_ros', 'ament_index_python', 'rcl_interfaces',
                'builtin_interfaces', 'ament_flake8', 'ament_pep257'}


def imported_modules(folder: Path) -> set:
    mods = set()
    for path in folder.rglob('*.py'):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                mods |= {a.name.split('.')[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                mods.add(node.module.split('.')[0])
    return mods


def required_key(module: str):
    """
    Return the rosdep key of an imported top-level module.

    None: needs none (standard library, a module of the same folder, or pip-only and checked
    separately).
    """
    if module in SYSTEM_KEYS:
        return SYSTEM_KEYS[module]
    if module in WORKSPACE or module in ROS_PACKAGES or module.endswith('_msgs'):
        return module
    if module in sys.stdlib_module_names or module in PIP_ONLY or module in LOCAL_MODULES:
        return None
    return f'<no key known for {module!r}: add it to SYSTEM_KEYS>'


def manifest(package: str):
    root = ET.parse(ROOT / PACKAGES[package] / 'package.xml').getroot()
    run = {e.text for e in root if e.tag in ('exec_depend', 'depend')}
    test = {e.text for e in root if e.tag in ('test_depend', 'depend')}
    comments = (ROOT / PACKAGES[package] / 'package.xml').read_text()
    return run, test, comments


@pytest.mark.parametrize('package', sorted(PACKAGES))
def test_every_import_is_declared(package):
    run, test, text = manifest(package)
    src = ROOT / PACKAGES[package]
    launch = imported_modules(src / 'launch') if (src / 'launch').is_dir() else set()
    runtime = imported_modules(src / package) | launch
    missing = sorted({required_key(m) for m in runtime if required_key(m)} - run - {package})
    assert not missing, f'{package}/package.xml lacks exec_depend {missing}'
    tests = imported_modules(src / 'test') if (src / 'test').is_dir() else set()
    missing = sorted({required_key(m) for m in tests if required_key(m)} - run - test
                     - {package})
    assert not missing, f'{package}/package.xml lacks test_depend {missing}'
    for module in sorted((runtime | tests) & PIP_ONLY):
        assert f'{module}' in text and 'pip' in text, \
            f'{package} imports {module} (no rosdep key on noble): say so in package.xml'


@pytest.mark.parametrize('package', sorted(PACKAGES))
def test_no_stale_or_unresolvable_keys(package):
    run, test, _ = manifest(package)
    src = ROOT / PACKAGES[package]
    used = {required_key(m) for m in imported_modules(src)} - {None}
    # declared but never imported: only runtime dependencies of other kinds
    allowed_unused = {'python3-pytest', 'python3-hypothesis', 'stereo_manip_msgs', 'std_msgs',
                      'geometry_msgs', 'nav_msgs', 'sensor_msgs', 'python3-skimage',
                      'stereo_depth', 'object_localizer', 'contact_correction',
                      'joint_estimator', 'ip_modeler', 'python3-matplotlib',
                      'python3-open3d-pip', 'stereo_manip_models'}
    stale = sorted((run | test) - used - allowed_unused)
    assert not stale, f'{package}/package.xml declares keys nothing imports: {stale}'
    # python3-numba has no noble definition in rosdep: declaring it breaks rosdep install
    assert 'python3-numba' not in run | test


@pytest.mark.parametrize('package', sorted(PACKAGES))
def test_model_readers_depend_on_the_model_package(package):
    """Code that loads shipped models by name needs the data package installed with it."""
    run, _, _ = manifest(package)
    src = ROOT / PACKAGES[package]
    readers = [p for p in (src / package).rglob('*.py') if 'find_model' in p.read_text()]
    if readers:
        assert 'stereo_manip_models' in run, \
            f'{package} loads models ({readers[0].name}) without exec_depend stereo_manip_models'


def test_every_package_has_a_readme():
    """Every ament package of the workspace (each folder with a package.xml) documents itself."""
    folders = sorted(p.parent for p in ROOT.glob('*/package.xml')) + \
        sorted(p.parent for p in ROOT.glob('ros_compat/*/package.xml'))
    assert len(folders) >= 9, folders
    missing = [str(f.relative_to(ROOT)) for f in folders
               if not (f / 'README.md').is_file() or len((f / 'README.md').read_text()) < 300]
    assert not missing, f'packages without a README: {missing}'
