"""The colcon build produced what `ros2 run` and the ament index need, for every package."""

import configparser
import os
from pathlib import Path

from ament_index_python.packages import get_package_prefix, get_package_share_directory, \
    get_packages_with_prefixes
import pytest

ROOT = Path(__file__).resolve().parents[1]
PYTHON_PACKAGES = ['stereo_manip_tools', 'stereo_depth', 'object_localizer',
                   'contact_correction', 'joint_estimator', 'ip_modeler', 'stereo_manip_bringup']


def console_scripts(package: str):
    """List the executable names declared in the package's setup.cfg entry_points."""
    cfg = configparser.ConfigParser(interpolation=None)
    cfg.read(ROOT / package / 'setup.cfg')
    lines = cfg['options.entry_points']['console_scripts'].strip().splitlines()
    return [line.split('=')[0].strip() for line in lines]


def test_ament_index_finds_every_package():
    found = get_packages_with_prefixes()
    for pkg in PYTHON_PACKAGES + ['stereo_manip_msgs', 'stereo_manip_models']:
        assert pkg in found, f'{pkg} missing from the ament index'
        assert (Path(get_package_share_directory(pkg)) / 'package.xml').is_file()


def test_models_are_installed_by_their_data_package():
    shipped = sorted(p.name for p in (ROOT / 'stereo_manip_models' / 'models').glob('*.obj'))
    installed = Path(get_package_share_directory('stereo_manip_models')) / 'models'
    assert shipped and sorted(p.name for p in installed.glob('*.obj')) == shipped


@pytest.mark.parametrize('package', PYTHON_PACKAGES)
def test_executables_installed_where_ros2_run_looks(package):
    lib = Path(get_package_prefix(package)) / 'lib' / package
    for exe in console_scripts(package):
        path = lib / exe
        assert path.is_file() and os.access(path, os.X_OK), f'{package}/{exe} not installed'


def test_interface_package_ships_definitions():
    share = Path(get_package_share_directory('stereo_manip_msgs'))
    for name in ['ContactElement', 'ContactPair', 'ContactState', 'JointEstimate',
                 'ImplicitPolynomial', 'TrackStatus']:
        assert (share / 'msg' / f'{name}.msg').is_file()
    for name in ['CorrectTrajectory', 'EstimateJoint', 'FitImplicitPolynomial']:
        assert (share / 'srv' / f'{name}.srv').is_file()
