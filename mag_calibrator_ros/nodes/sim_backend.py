# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The driver node's simulated backend (``backend: sim``): the ``sim.*`` parameters, the
``SimConfig`` they make, and the ROS wiring of the simulated robot (``sim.motion: cmd_vel``).

Here so that ``nodes/icm20948_driver.py`` stays the chip's wiring: none of this exists on a real
board. The driver declares ``PARAMETERS`` with its own (every backend, so a launch file's
``sim.*`` values never break a hardware start) and builds ``SimRobotWiring`` only for the
cmd_vel robot; its module docstring lists every topic and parameter, these included. The robot
itself, pure, is ``sim/robot.py``.
"""

from __future__ import annotations

import math

from builtin_interfaces.msg import Time
from geometry_msgs.msg import Twist, TwistStamped
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.impl.implementation_singleton import rclpy_implementation
from rclpy.node import Node
from rclpy.qos import QoSProfile
from sensor_msgs.msg import BatteryState

from mag_calibrator_ros.nodes.parameters import descriptor
from mag_calibrator_ros.sim import motion
from mag_calibrator_ros.sim.config import (
    ACCEL_NOISE_DENSITY,
    GYRO_NOISE_DENSITY,
    IDENTITY,
    SimConfig,
)
from mag_calibrator_ros.sim.robot import SimulatedRobot

PARAMETERS: dict[str, tuple[object, ParameterDescriptor]] = {
    'sim.field_ut': (50.0, descriptor(
        'Simulator: earth field strength in microtesla.', float_range=(1.0, 4900.0))),
    'sim.inclination_deg': (60.0, descriptor(
        'Simulator: field inclination (dip) in degrees, positive pointing down.',
        float_range=(-90.0, 90.0))),
    'sim.hard_iron_ut': ([0.0, 0.0, 0.0], descriptor(
        'Simulator: hard-iron offset [x, y, z] in microtesla, chip frame.',
        constraints='3 finite doubles')),
    'sim.soft_iron': (list(IDENTITY), descriptor(
        'Simulator: soft-iron matrix, 9 doubles row-major, symmetric positive definite.',
        constraints='9 doubles, symmetric positive definite')),
    'sim.noise_ut': (0.3, descriptor(
        'Simulator: white noise per axis (1 sigma) in microtesla.', float_range=(0.0, 100.0))),
    'sim.motion': ('tumble', descriptor(
        'Simulator: how the board moves: tumble (hand), yaw (ground robot turning), still, or '
        'poses (held still at one tilt after another: what aligning to the IMU needs), or '
        'cmd_vel (a ground robot driving and turning only as commanded on cmd_vel).',
        constraints=' | '.join(motion.TRAJECTORY_KINDS))),
    'sim.i2c_error_rate': (0.0, descriptor(
        'Simulator: probability that an I2C transaction fails with EREMOTEIO.',
        float_range=(0.0, 0.99))),
    'sim.seed': (0, descriptor(
        'Simulator: random seed (motion, noise, faults).', integer_range=(0, 2**31 - 1))),
    'sim.accel_bias_mps2': ([0.0, 0.0, 0.0], descriptor(
        'Simulator: accelerometer bias [x, y, z] in m/s^2, chip frame.',
        constraints='3 finite doubles within ±156.9 (16 g)')),
    'sim.gyro_bias_dps': ([0.0, 0.0, 0.0], descriptor(
        'Simulator: gyroscope bias [x, y, z] in deg/s, chip frame.',
        constraints='3 finite doubles within ±2000')),
    'sim.accel_noise_density': (ACCEL_NOISE_DENSITY, descriptor(
        'Simulator: accelerometer noise density in (m/s^2)/sqrt(Hz).', float_range=(0.0, 1.0))),
    'sim.gyro_noise_density': (GYRO_NOISE_DENSITY, descriptor(
        'Simulator: gyroscope noise density in (rad/s)/sqrt(Hz).', float_range=(0.0, 1.0))),
    'sim.temperature_c': (25.0, descriptor(
        'Simulator: die temperature at power-on in degC.', float_range=(-40.0, 85.0))),
    'sim.temperature_rise_c': (2.0, descriptor(
        'Simulator: warm-up of the die after power-on in degC (sim.temperature_time_constant_s).',
        float_range=(-50.0, 50.0))),
    'sim.temperature_time_constant_s': (600.0, descriptor(
        "Simulator: time constant of the die's first-order warm-up, seconds.",
        float_range=(0.01, 86400.0))),
    'sim.hard_iron_drift_ut_per_c': ([0.0, 0.0, 0.0], descriptor(
        'Simulator: drift of the hard iron [x, y, z], uT per degC of die temperature above '
        'sim.temperature_c.', constraints='3 finite doubles, each within ±50')),
    'sim.current_field_ut_per_a': ([0.0, 0.0, 0.0], descriptor(
        'Simulator (motion cmd_vel): field of the battery current at the sensor [x, y, z], uT '
        'per ampere.', constraints='3 finite doubles, each within ±100')),
    'sim.mag_misalignment_deg': ([0.0, 0.0, 0.0], descriptor(
        'Simulator: rotation vector [x, y, z] in degrees of the magnetometer axes against the '
        'accel/gyro frame (what aligning to the IMU recovers).',
        constraints='3 finite doubles, at most 180 deg')),
    'sim.latitude': (math.nan, descriptor(
        'Simulator: latitude in degrees; with sim.longitude the field is the World Magnetic '
        "Model's there (sim.field_ut and sim.inclination_deg unused). NaN: no location.",
        constraints='-90..90 or NaN')),
    'sim.longitude': (math.nan, descriptor(
        'Simulator: longitude in degrees (-180..360) or NaN.', constraints='-180..360 or NaN')),
    'sim.altitude': (0.0, descriptor(
        'Simulator: altitude in metres above the WGS84 ellipsoid (with a location).',
        float_range=(-1000.0, 850000.0))),
    'sim.field_scale': (1.0, descriptor(
        'Simulator: a disturbed place: the field strength times this (against the model).',
        float_range=(0.01, 10.0))),
    'sim.inclination_offset_deg': (0.0, descriptor(
        'Simulator: a disturbed place: the dip moved by this many degrees.',
        float_range=(-90.0, 90.0))),
    # sim.motion cmd_vel: a ground robot following cmd_vel's linear x and angular z
    'sim.max_yaw_rate': (1.0, descriptor(
        'Simulator (motion cmd_vel): largest yaw rate the robot turns at, rad/s.',
        float_range=(0.01, 10.0))),
    'sim.max_yaw_acceleration': (1.0, descriptor(
        'Simulator (motion cmd_vel): largest yaw acceleration, rad/s^2.',
        float_range=(0.01, 100.0))),
    'sim.tilt_wobble_deg': (2.0, descriptor(
        'Simulator (motion cmd_vel): peak tilt while turning (an uneven floor: roll and pitch '
        'follow the heading), degrees.', float_range=(0.0, 20.0))),
    'sim.cmd_vel_timeout': (0.5, descriptor(
        'Simulator (motion cmd_vel): the robot stops by itself when no command came for this '
        "long, seconds (as a base controller's command timeout).", float_range=(0.01, 60.0))),
    'sim.max_speed': (0.5, descriptor(
        'Simulator (motion cmd_vel): top forward speed, m/s.', float_range=(0.01, 20.0))),
    'sim.max_linear_acceleration': (1.0, descriptor(
        'Simulator (motion cmd_vel): largest forward acceleration, m/s^2.',
        float_range=(0.01, 100.0))),
    'sim.track_width': (0.3, descriptor(
        'Simulator (motion cmd_vel): distance between the wheels, m (a turn in place spins '
        'them at yaw rate x half of it).', float_range=(0.01, 10.0))),
    'sim.idle_current_a': (0.5, descriptor(
        'Simulator (motion cmd_vel): battery current with the wheels still, A.',
        float_range=(0.0, 1000.0))),
    'sim.full_current_a': (5.0, descriptor(
        'Simulator (motion cmd_vel): battery current with both wheels at sim.max_speed, A '
        '(idle included).', float_range=(0.0, 1000.0))),
}
CMD_VEL_TOPIC = 'cmd_vel'
CMD_VEL_TYPES = {'geometry_msgs/msg/Twist': Twist, 'geometry_msgs/msg/TwistStamped': TwistStamped}
CMD_VEL_CHECK_S = 0.25
"""How often the sim's cmd_vel subscription checks which type the publishers use."""
BATTERY_TOPIC = 'battery_state'
RCLError = rclpy_implementation.RCLError


def problems(values: dict[str, object]) -> list[str]:
    """The ``sim.*`` cross-checks beyond the descriptors' ranges (every backend: a bad value is
    a mistake in the file either way); empty when usable."""
    found = []
    if values['sim.motion'] not in motion.TRAJECTORY_KINDS:
        found.append(
            f"sim.motion must be one of {', '.join(motion.TRAJECTORY_KINDS)}, "
            f"got {values['sim.motion']!r}"
        )
    found += [f'sim.{problem}' for problem in motion.cmd_vel_problems(*cmd_vel_limits(values))]
    return found


def cmd_vel_limits(values: dict[str, object]) -> tuple:
    """(max rate, max acceleration, wobble, command timeout, max speed, max linear
    acceleration, drive current) of a sim cmd_vel robot."""
    drive = motion.DriveCurrent(values['sim.idle_current_a'], values['sim.full_current_a'],
                                values['sim.track_width'])
    return (values['sim.max_yaw_rate'], values['sim.max_yaw_acceleration'],
            values['sim.tilt_wobble_deg'], values['sim.cmd_vel_timeout'],
            values['sim.max_speed'], values['sim.max_linear_acceleration'], drive)


def sim_config(values: dict[str, object]) -> SimConfig:
    """The simulated board the ``sim.*`` values (and ``address``) describe; ValueError names
    what ``SimConfig`` refuses."""
    return SimConfig(
        field_ut=values['sim.field_ut'],
        inclination_deg=values['sim.inclination_deg'],
        hard_iron_ut=tuple(values['sim.hard_iron_ut']),
        soft_iron=tuple(values['sim.soft_iron']),
        noise_ut=values['sim.noise_ut'],
        motion=values['sim.motion'],
        i2c_error_rate=values['sim.i2c_error_rate'],
        seed=values['sim.seed'],
        address=values['address'],
        accel_bias_mps2=tuple(values['sim.accel_bias_mps2']),
        gyro_bias_dps=tuple(values['sim.gyro_bias_dps']),
        accel_noise_density=values['sim.accel_noise_density'],
        gyro_noise_density=values['sim.gyro_noise_density'],
        temperature_c=values['sim.temperature_c'],
        temperature_rise_c=values['sim.temperature_rise_c'],
        temperature_time_constant_s=values['sim.temperature_time_constant_s'],
        current_field_ut_per_a=tuple(values['sim.current_field_ut_per_a']),
        hard_iron_drift_ut_per_c=tuple(values['sim.hard_iron_drift_ut_per_c']),
        mag_misalignment_deg=tuple(values['sim.mag_misalignment_deg']),
        latitude=values['sim.latitude'],
        longitude=values['sim.longitude'],
        altitude_m=values['sim.altitude'],
        field_scale=values['sim.field_scale'],
        inclination_offset_deg=values['sim.inclination_offset_deg'],
    )


def cmd_vel_trajectory(config: SimConfig, values: dict[str, object]
                       ) -> motion.CmdVelTrajectory | None:
    """The robot's motion with ``sim.motion: cmd_vel`` (seeded as the board), else None."""
    if config.motion != 'cmd_vel':
        return None
    return motion.CmdVelTrajectory(config.seed, *cmd_vel_limits(values))


class SimRobotWiring:
    """The simulated robot on the graph: ``cmd_vel`` in (the type its publishers use: Twist, or
    TwistStamped when only that is published, as one topic has one type in DDS), checked every
    CMD_VEL_CHECK_S; ``battery_state`` out with the imu/mag readings (``publish_battery``)."""

    def __init__(self, node: Node, robot: SimulatedRobot, qos: QoSProfile) -> None:
        self._node = node
        self.robot = robot
        self._subscription = None
        self._type: str | None = None
        self._follow_type()
        node.create_timer(CMD_VEL_CHECK_S, self._follow_type)
        self._message = message = BatteryState()
        message.temperature = message.charge = message.capacity = math.nan  # unmeasured
        message.design_capacity = message.percentage = math.nan
        message.power_supply_status = BatteryState.POWER_SUPPLY_STATUS_DISCHARGING
        message.present = True
        self._publisher = node.create_publisher(BatteryState, BATTERY_TOPIC, qos)

    def _follow_type(self) -> None:
        node = self._node
        topic = node.resolve_topic_name(CMD_VEL_TOPIC)
        offered = {info.topic_type for info in node.get_publishers_info_by_topic(topic)}
        wanted = ('geometry_msgs/msg/TwistStamped'
                  if offered == {'geometry_msgs/msg/TwistStamped'} else 'geometry_msgs/msg/Twist')
        if wanted == self._type:
            return
        if self._subscription is not None:
            # the old type's topic goes with its last user: subscribe anew at the next check
            node.destroy_subscription(self._subscription)
            self._subscription = self._type = None
            return
        try:
            self._subscription = node.create_subscription(
                CMD_VEL_TYPES[wanted], CMD_VEL_TOPIC, self._on_cmd_vel, QoSProfile(depth=10))
        except RCLError as error:  # the old type still held by DDS: the next check retries
            node.get_logger().debug(f'subscribing {topic} as {wanted} failed: {error}')
            return
        self._type = wanted

    def _on_cmd_vel(self, message: Twist | TwistStamped) -> None:
        twist = message.twist if isinstance(message, TwistStamped) else message
        self.robot.drive(twist.linear.x, twist.angular.z)

    def publish_battery(self, stamp: Time, frame_id: str) -> None:
        """The battery with the imu/mag reading just published (on the supervisor's thread;
        one message, refilled), when one is due at its stamp."""
        battery = self.robot.battery_due(stamp.sec * 1_000_000_000 + stamp.nanosec)
        if battery is None:
            return
        message = self._message
        message.header.stamp = stamp
        message.header.frame_id = frame_id
        message.voltage = battery.voltage
        message.current = -battery.current_a  # negative when discharging (BatteryState.msg)
        self._publisher.publish(message)
