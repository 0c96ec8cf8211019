from setuptools import find_packages, setup

package_name = 'stereo_manip_tools'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    package_data={package_name: ['py.typed']},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    install_requires=['setuptools'],
    zip_safe=False,
    maintainer='stereo_manip maintainers',
    maintainer_email='maintainers@stereo-manip.org',
    description=('Shared tools for stereo_manip: message/array conversions, pose math, mesh I/O, '
                 'stamp synchroniser, rosbag2 record/replay, test harness.'),
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'record = stereo_manip_tools.bag_record:main',
            'replay = stereo_manip_tools.bag_replay:main',
        ],
    },
)
