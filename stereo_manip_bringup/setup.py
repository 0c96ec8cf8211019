from glob import glob

from setuptools import find_packages, setup

package_name = 'stereo_manip_bringup'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    package_data={package_name: ['py.typed']},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/launch', glob('launch/*.launch.py')),
        ('share/' + package_name + '/config', glob('config/*.yaml') + glob('config/*.xml')),
    ],
    install_requires=['setuptools'],
    zip_safe=False,
    maintainer='stereo_manip maintainers',
    maintainer_email='maintainers@stereo-manip.org',
    description='Launch file and demo pipeline runner of stereo_manip.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'demo = stereo_manip_bringup.demo:main',
        ],
    },
)
