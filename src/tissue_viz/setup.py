from glob import glob

from setuptools import find_packages, setup

package_name = 'tissue_viz'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*')),
        ('share/' + package_name + '/launch', glob('launch/*.launch.py')),
        ('share/' + package_name + '/rviz', glob('rviz/*.rviz')),
        ('share/' + package_name + '/foxglove', glob('foxglove/*.json')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='SPH tissue simulator maintainers',
    maintainer_email='maintainers@sph-tissue-sim.org',
    description='Live metrics, ROS diagnostics, markers and reports for the SPH soft-tissue simulator.',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'viz_node = tissue_viz.viz_node:main',
            'tissue_report = tissue_viz.report:main',
        ],
    },
)
