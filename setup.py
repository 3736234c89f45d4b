# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""ament_python build for mag_calibrator_ros (colcon, or pip in a venv)."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'mag_calibrator_ros'

setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*', 'benchmarks']),
    data_files=[
        ('share/ament_index/resource_index/packages', [f'resource/{PACKAGE}']),
        (f'share/{PACKAGE}', ['package.xml', 'LICENSE', 'CHANGELOG.rst']),
        (f'share/{PACKAGE}/config', glob('config/*.yaml') + glob('config/*.rviz')),
        (f'share/{PACKAGE}/launch', glob('launch/*.launch.py')),
    ],
    install_requires=[
        'setuptools',
        'numpy',
        'scipy',
        'matplotlib',
        'PyYAML',
        'smbus2',
        'rosbags',
        'wmm-calculator',
    ],
    zip_safe=True,
    maintainer='mag_calibrator_ros maintainers',
    maintainer_email='maintainers@mag-calibrator-ros.dev',
    description='Live magnetometer calibration (ICM-20948 driver, kNN sample buffer, robust '
    'ellipsoid fits) for ROS 2 Jazzy.',
    license='MIT',
    tests_require=['pytest', 'pytest-xdist'],
    entry_points={
        'console_scripts': [
            f'icm20948_driver = {PACKAGE}.nodes.entry:icm20948_driver',
            f'mag_calibrator = {PACKAGE}.nodes.entry:mag_calibrator',
            f'mag_calibrator_fit = {PACKAGE}.tools.fit:main',
            f'mag_calibrator_demo = {PACKAGE}.tools.demo:main',
        ],
    },
)
