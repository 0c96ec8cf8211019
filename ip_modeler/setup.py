from setuptools import find_packages, setup

package_name = 'ip_modeler'

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
    description=('Implicit-polynomial surface fitting with adaptive degree by incremental QR '
                 '(Eqs. 19-22).'),
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'ip_modeler_node = ip_modeler.ip_modeler_node:main',
            'fit_ip = ip_modeler.offline:main',
        ],
    },
)
