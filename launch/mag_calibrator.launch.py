"""Start the ICM-20948 driver and the calibrator with the installed config/*.yaml.

    ros2 launch mag_calibrator_ros mag_calibrator.launch.py
    ros2 launch mag_calibrator_ros mag_calibrator.launch.py backend:=sim
    ros2 launch mag_calibrator_ros mag_calibrator.launch.py \
        calibration_file:=/home/robot/.ros/mag_calibrator/calibration.yaml namespace:=robot1

Relative topics (imu/mag -> imu/mag_corrected): ``namespace`` moves both nodes together.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from launch import LaunchDescription

PACKAGE = 'mag_calibrator_ros'


def generate_launch_description() -> LaunchDescription:
    config = os.path.join(get_package_share_directory(PACKAGE), 'config')
    backend = LaunchConfiguration('backend')
    calibration_file = LaunchConfiguration('calibration_file')
    namespace = LaunchConfiguration('namespace')
    return LaunchDescription([
        DeclareLaunchArgument(
            'backend', default_value='smbus2',
            description='Driver backend: smbus2 (the real ICM-20948 on I2C) or sim (simulated).'),
        DeclareLaunchArgument(
            'calibration_file', default_value='~/.ros/mag_calibrator/calibration.yaml',
            description='Calibration YAML loaded at start-up and written by ~/save.'),
        DeclareLaunchArgument(
            'namespace', default_value='',
            description='Namespace for both nodes and their topics.'),
        Node(
            package=PACKAGE,
            executable='icm20948_driver',
            name='icm20948_driver',
            namespace=namespace,
            output='screen',
            parameters=[os.path.join(config, 'icm20948_driver.yaml'), {'backend': backend}],
        ),
        Node(
            package=PACKAGE,
            executable='mag_calibrator',
            name='mag_calibrator',
            namespace=namespace,
            output='screen',
            parameters=[
                os.path.join(config, 'mag_calibrator.yaml'),
                {'calibration_file': calibration_file},
            ],
        ),
    ])
