from setuptools import find_packages, setup

package_name = 'contact_correction'

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
    description=('Vision error correction with contact relations between polyhedra (non-linear '
                 'step, then the linear optimum of Eqs. 2-9).'),
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'contact_correction_node = contact_correction.contact_correction_node:main',
            'correct_trajectory = contact_correction.offline:main',
        ],
    },
)
