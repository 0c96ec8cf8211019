from glob import glob

from setuptools import setup

package_name = 'stereo_manip_bringup'

# The rest of the metadata is in setup.cfg; data_files stay here for the launch/config globs.
setup(data_files=[
    ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
    ('share/' + package_name, ['package.xml']),
    ('share/' + package_name + '/launch', glob('launch/*.launch.py')),
    ('share/' + package_name + '/config', glob('config/*.yaml') + glob('config/*.xml')),
])
