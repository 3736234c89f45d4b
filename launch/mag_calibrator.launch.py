"""Start the ICM-20948 driver and the calibrator with the installed config/*.yaml.

    ros2 launch mag_calibrator_ros mag_calibrator.launch.py
    ros2 launch mag_calibrator_ros mag_calibrator.launch.py backend:=sim
    ros2 launch mag_calibrator_ros mag_calibrator.launch.py namespace:=robot1
    ros2 launch mag_calibrator_ros mag_calibrator.launch.py calibration_file:=/data/mag.yaml

Relative topics (imu/mag -> imu/mag_corrected): ``namespace`` moves both nodes together. Without
calibration_file each calibrator uses its own file, named after its namespace and name
($ROS_HOME/mag_calibrator/robot1__mag_calibrator.yaml), so robots on one host never share one.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.launch_context import LaunchContext
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from launch import LaunchDescription

PACKAGE = 'mag_calibrator_ros'


def calibrator(context: LaunchContext, config: str) -> list[Node]:
    """The calibrator, given calibration_file only when the user named one."""
    parameters: list = [os.path.join(config, 'mag_calibrator.yaml')]
    calibration_file = LaunchConfiguration('calibration_file').perform(context)
    if calibration_file:
        parameters.append({'calibration_file': calibration_file})
    return [Node(
        package=PACKAGE,
        executable='mag_calibrator',
        name='mag_calibrator',
        namespace=LaunchConfiguration('namespace'),
        output='screen',
        parameters=parameters,
    )]


def generate_launch_description() -> LaunchDescription:
    config = os.path.join(get_package_share_directory(PACKAGE), 'config')
    return LaunchDescription([
        DeclareLaunchArgument(
            'backend', default_value='smbus2',
            description='Driver backend: smbus2 (the real ICM-20948 on I2C) or sim (simulated).'),
        DeclareLaunchArgument(
            'calibration_file', default_value='',
            description='Calibration YAML loaded at start-up and written by ~/save (default: '
                        'one per node, $ROS_HOME/mag_calibrator/<namespace>__<name>.yaml).'),
        DeclareLaunchArgument(
            'namespace', default_value='',
            description='Namespace for both nodes and their topics.'),
        Node(
            package=PACKAGE,
            executable='icm20948_driver',
            name='icm20948_driver',
            namespace=LaunchConfiguration('namespace'),
            output='screen',
            parameters=[os.path.join(config, 'icm20948_driver.yaml'),
                        {'backend': LaunchConfiguration('backend')}],
        ),
        OpaqueFunction(function=calibrator, args=[config]),
    ])
