# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Start the ICM-20948 driver and the calibrator (and RViz), with the installed config/*.yaml.

    ros2 launch mag_calibrator_ros mag_calibrator.launch.py
    ros2 launch mag_calibrator_ros mag_calibrator.launch.py backend:=sim namespace:=robot1 \\
        rviz:=true
    ros2 launch mag_calibrator_ros mag_calibrator.launch.py backend:=sim \\
        sim.hard_iron_ut:="[120.0, -80.0, 60.0]" sim.noise_ut:=0.5 sim.motion:=yaw
    ros2 launch mag_calibrator_ros mag_calibrator.launch.py driver_params_file:=/data/imu.yaml
    ros2 launch mag_calibrator_ros mag_calibrator.launch.py calibration_file:=/data/mag.yaml

Arguments (``ros2 launch ... --show-args``):

- ``namespace`` (none): both nodes and their topics, relative (imu/mag -> imu/mag_corrected),
  move together; robots on one host each get their own.
- ``backend`` (the driver params file's, smbus2 as shipped): smbus2 (the real ICM-20948 on
  I2C) or sim (the register-level simulator).
- ``driver_params_file``, ``calibrator_params_file`` (the installed config/icm20948_driver.yaml
  and config/mag_calibrator.yaml): params files keyed ``/**``, so they apply in a namespace.
- ``sim.hard_iron_ut`` ([x, y, z] µT), ``sim.soft_iron`` (9 values, row-major, symmetric
  positive definite), ``sim.noise_ut`` (µT, 1 sigma), ``sim.motion`` (tumble | yaw | still |
  poses | cmd_vel): the simulator's distortion and motion, over the driver params file; unset:
  the file's. Integers are taken as doubles (120 -> 120.0).
- ``use_sim_time`` (false): both nodes take their time from /clock (a bag played with --clock).
- ``calibration_file`` (one per node, $ROS_HOME/mag_calibrator/<namespace>__<name>.yaml, e.g.
  robot1__mag_calibrator.yaml): the calibration loaded at start-up and written by ~/save.
- ``rviz`` (false): also start rviz2 with config/mag_calibrator.rviz, its topics moved into the
  namespace (the shipped file shows /mag_calibrator/view/...); where rviz2 is not installed, a
  line says so and the nodes run without it.

Each node is told this launch's pid and stops when it is gone, however it ended.
"""

import os
import tempfile

from ament_index_python.packages import (
    PackageNotFoundError,
    get_package_prefix,
    get_package_share_directory,
)
from launch.actions import DeclareLaunchArgument, LogInfo, OpaqueFunction
from launch.launch_context import LaunchContext
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
import yaml

from launch import LaunchDescription

PACKAGE = 'mag_calibrator_ros'
SIM_ARGUMENTS = {
    # name: (parameter type, description)
    'sim.hard_iron_ut': ('doubles', 'Simulator hard-iron offset [x, y, z] in microtesla.'),
    'sim.soft_iron': ('doubles', 'Simulator soft iron: 9 values, row-major, symmetric positive '
                                 'definite.'),
    'sim.noise_ut': ('double', 'Simulator white noise per axis (1 sigma) in microtesla.'),
    'sim.motion': ('string', 'Simulator motion: tumble | yaw | still | poses | cmd_vel.'),
}
RVIZ_TOPIC_PREFIX = 'Value: /mag_calibrator/view/'
LAUNCH_PID_ENV = 'MAG_CALIBRATOR_ROS_LAUNCH_PID'
"""mag_calibrator_ros.nodes.runtime.LAUNCH_PID_ENV: each node stops when this launch is gone."""


def argument(context: LaunchContext, name: str) -> str:
    return LaunchConfiguration(name).perform(context)


def parameter_value(text: str, kind: str) -> object:
    """A launch argument as the driver's parameter type: YAML, with integers (and what YAML 1.1
    leaves a string, such as 5e-5) taken as doubles where the parameter is a double."""
    if kind == 'string':
        return text
    value = yaml.safe_load(text)
    if kind == 'doubles' and isinstance(value, list):
        return [_double(item) for item in value]
    return _double(value)


def _double(value: object) -> object:
    if isinstance(value, bool):
        return value  # refused by the node with its reason
    try:
        return float(value)
    except (TypeError, ValueError):
        return value  # refused by the node with its reason


def driver(context: LaunchContext, config: str) -> list[Node]:
    """The driver with its params file, then what the user gave on the command line."""
    parameters: list = [argument(context, 'driver_params_file') or
                        os.path.join(config, 'icm20948_driver.yaml')]
    given: dict[str, object] = {'use_sim_time': _use_sim_time(context)}
    backend = argument(context, 'backend')
    if backend:
        given['backend'] = backend
    for name, (kind, _) in SIM_ARGUMENTS.items():
        text = argument(context, name)
        if text:
            given[name] = parameter_value(text, kind)
    parameters.append(given)
    return [_node(context, 'icm20948_driver', parameters)]


def calibrator(context: LaunchContext, config: str) -> list[Node]:
    """The calibrator, given calibration_file only when the user named one."""
    parameters: list = [argument(context, 'calibrator_params_file') or
                        os.path.join(config, 'mag_calibrator.yaml')]
    given: dict[str, object] = {'use_sim_time': _use_sim_time(context)}
    calibration_file = argument(context, 'calibration_file')
    if calibration_file:
        given['calibration_file'] = calibration_file
    parameters.append(given)
    return [_node(context, 'mag_calibrator', parameters)]


def _node(context: LaunchContext, executable: str, parameters: list) -> Node:
    """One of the package's nodes, named as its executable, in the launch's namespace."""
    return Node(package=PACKAGE, executable=executable, name=executable,
                namespace=argument(context, 'namespace'), output='screen', parameters=parameters,
                additional_env={LAUNCH_PID_ENV: str(os.getpid())})


def _use_sim_time(context: LaunchContext) -> bool:
    return argument(context, 'use_sim_time') == 'true'  # true | false: the argument's choices


def namespaced_rviz_config(text: str, namespace: str) -> str:
    """The shipped RViz config with its topics in ``namespace`` (rviz2 takes only absolute
    topics from a config file)."""
    prefix = '/' + namespace.strip('/') if namespace.strip('/') else ''
    return text.replace(RVIZ_TOPIC_PREFIX, f'Value: {prefix}/mag_calibrator/view/')


def rviz(context: LaunchContext, config: str) -> list[Node | LogInfo]:
    """rviz2 with the config written for the namespace, when asked for; one line instead when
    rviz2 is not installed (launch would stop on it, after the nodes had started)."""
    if argument(context, 'rviz') != 'true':  # true | false: the argument's choices
        return []
    if not rviz2_installed():
        return [LogInfo(msg='rviz:=true, but rviz2 is not installed (sudo apt install '
                            'ros-jazzy-rviz2): the driver and calibrator run without it')]
    namespace = argument(context, 'namespace')
    with open(os.path.join(config, 'mag_calibrator.rviz'), encoding='utf-8') as shipped:
        text = namespaced_rviz_config(shipped.read(), namespace)
    handle, path = tempfile.mkstemp(prefix='mag_calibrator_', suffix='.rviz')
    with os.fdopen(handle, 'w', encoding='utf-8') as written:
        written.write(text)
    return [Node(package='rviz2', executable='rviz2', name='rviz2', namespace=namespace,
                 output='screen', arguments=['-d', path])]


def rviz2_installed() -> bool:
    try:
        get_package_prefix('rviz2')
    except PackageNotFoundError:
        return False
    return True


def generate_launch_description() -> LaunchDescription:
    config = os.path.join(get_package_share_directory(PACKAGE), 'config')
    arguments = [
        DeclareLaunchArgument(
            'namespace', default_value='',
            description='Namespace for both nodes and their topics.'),
        DeclareLaunchArgument(
            'backend', default_value='',
            description='Driver backend: smbus2 (the real ICM-20948 on I2C) or sim (simulated); '
                        "empty: the driver params file's (smbus2 as shipped)."),
        DeclareLaunchArgument(
            'driver_params_file', default_value=os.path.join(config, 'icm20948_driver.yaml'),
            description='Params file of the driver (keyed /** to apply in a namespace).'),
        DeclareLaunchArgument(
            'calibrator_params_file', default_value=os.path.join(config, 'mag_calibrator.yaml'),
            description='Params file of the calibrator (keyed /** to apply in a namespace).'),
        *[DeclareLaunchArgument(name, default_value='',
                                description=f"{text} Empty: the driver params file's.")
          for name, (_, text) in SIM_ARGUMENTS.items()],
        DeclareLaunchArgument(
            'use_sim_time', default_value='false', choices=['true', 'false'],
            description='Both nodes take their time from /clock (a bag played with --clock).'),
        DeclareLaunchArgument(
            'calibration_file', default_value='',
            description='Calibration YAML loaded at start-up and written by ~/save (default: '
                        'one per node, $ROS_HOME/mag_calibrator/<namespace>__<name>.yaml).'),
        DeclareLaunchArgument(
            'rviz', default_value='false', choices=['true', 'false'],
            description='Also start rviz2 with config/mag_calibrator.rviz, its topics moved '
                        'into the namespace.'),
    ]
    return LaunchDescription([
        *arguments,
        OpaqueFunction(function=driver, args=[config]),
        OpaqueFunction(function=calibrator, args=[config]),
        OpaqueFunction(function=rviz, args=[config]),
    ])
