from setuptools import find_packages, setup

package_name = 'stereo_depth'

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
    description=('Stereo pairs to disparity, depth and point clouds (matching cost, aggregation, '
                 'optimisation of Eq. 1, refinement) and the synthetic stereo camera.'),
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'synthetic_camera = stereo_depth.synthetic_camera_node:main',
            'stereo_depth_node = stereo_depth.stereo_depth_node:main',
            'evaluate_disparity = stereo_depth.evaluation:main',
        ],
    },
)
