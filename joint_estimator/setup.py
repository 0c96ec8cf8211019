from setuptools import find_packages, setup

package_name = 'joint_estimator'

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
    description=('Joint parameters and corrected trajectories from two links pose tracks (Eqs. '
                 '10-18), with automatic joint type selection.'),
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'joint_estimator_node = joint_estimator.joint_estimator_node:main',
            'estimate_joint = joint_estimator.offline:main',
        ],
    },
)
