from glob import glob

from setuptools import find_packages, setup

package_name = 'haptic_omni_driver'

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
    description='ROS 2 driver for PHANTOM Omni / Geomagic Touch haptic devices with OpenHaptics, rosbag2 replay and scripted backends, force safety and a recorder.',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'omni_driver = haptic_omni_driver.driver_node:main',
            'omni_record = haptic_omni_driver.recorder_node:main',
            'omni_bag_recover = haptic_omni_driver.recover:main',
        ],
    },
)
