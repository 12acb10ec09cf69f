from setuptools import find_packages, setup

package_name = 'tissue_testing'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='SPH tissue simulator maintainers',
    maintainer_email='maintainers@sph-tissue-sim.org',
    description='Test support of the haptic tissue simulator workspace.',
    license='Apache-2.0',
    tests_require=['pytest'],
)
