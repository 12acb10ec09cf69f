from glob import glob

from setuptools import find_packages, setup

package_name = 'sph_tissue_sim'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*')),
        ('share/' + package_name + '/launch', glob('launch/*.launch.py')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='SPH tissue simulator maintainers',
    maintainer_email='maintainers@sph-tissue-sim.org',
    description='Real-time viscoelastic SPH soft-tissue simulation (paper, TLSPH and mass-spring schemes, dynamic local interaction area) with haptic contact force, as a ROS 2 node.',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'sim_node = sph_tissue_sim.sim_node:main',
        ],
    },
)
