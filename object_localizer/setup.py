from setuptools import find_packages, setup

package_name = 'object_localizer'

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
    description=('Known 3D models localised in point clouds: descriptors + RANSAC, then ICP with '
                 'an M-estimator; 6-DOF pose tracking.'),
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'object_localizer_node = object_localizer.localizer_node:main',
        ],
    },
)
