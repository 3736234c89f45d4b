# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""ROS 2 node ``icm20948_driver``: the whole ICM-20948, one owner of the chip and its bus.

Wiring only: parameters -> ``Icm20948Supervisor`` (bring-up, polling, fault recovery, rates;
``icm20948/supervisor.py``) on its own thread -> publishers and diagnostics. With
``backend: sim`` the bus is the register-level ``SimulatedIcm20948Bus`` (tests, demo, no hardware)
and ``nodes/sim_backend.py`` holds what only it needs: the ``sim.*`` parameters, the
``SimConfig`` they make and, with ``sim.motion: cmd_vel``, the simulated robot's wiring
(``sim/robot.py``).

Why a thread and not a timer: at kHz poll rates the executor's per-tick overhead alone would take
a large share of a core (docs/ARCHITECTURE.md, "Threads and processes"); the
supervisor's loop sleeps until its next poll. Publishers are thread-safe.

Published topics (relative, REP-145; reliable, volatile, depth 10, as REP-2003 asks of drivers;
one frame for all three, the ICM-20948 accel/gyro frame, with the magnetometer axes already
remapped into it; every stamp from the node's clock, when read, but imu/data_raw's and
imu/temperature's with ``imu_fifo``: when the chip sampled it):

- ``imu/mag`` (sensor_msgs/MagneticField): the field, tesla, at ``rate_hz``.
- ``imu/data_raw`` (sensor_msgs/Imu), with ``publish_imu``: m/s^2 and rad/s, no orientation
  (orientation_covariance[0] = -1).
- ``imu/temperature`` (sensor_msgs/Temperature), with ``publish_temperature``: degC, at most
  10 Hz.
- ``/diagnostics`` (diagnostic_msgs/DiagnosticArray): one status per stream, once a second;
  ``resyncs``: IMU reads so slow a newer sample may have landed (data-ready re-armed; bus busy?).

With ``sim.motion: cmd_vel`` (the simulated ground robot; ``nodes/sim_backend.py``), also:

- ``battery_state`` (sensor_msgs/BatteryState), at most 20 Hz, with an imu/mag reading's
  stamp: the battery current the robot draws (``current``, negative: discharging, as the
  message defines it), the pack's voltage; the rest NaN (unmeasured).

Subscribed topics (only with ``sim.motion: cmd_vel``): ``cmd_vel`` (geometry_msgs/Twist, or
TwistStamped when only that is published): the simulated robot drives at its linear x and turns
at its angular z.

Services: none. Timers: diagnostics every second; with ``sim.motion: cmd_vel``, the check of
cmd_vel's message type every ``sim_backend.CMD_VEL_CHECK_S``.

Parameters, ``name`` (default): meaning; read-only but for frame_id and the noise figures.
The chip:

- ``backend`` (smbus2): smbus2 (Linux /dev/i2c-N) or sim (the register-level simulator).
- ``i2c_bus`` (1): N of /dev/i2c-N; ``address`` (0x69): 0x68 (AD0 low) or 0x69 (AD0 high).
- ``rate_hz`` (100): magnetometer rate, one of 10, 20, 50, 100.
- ``imu_rate_hz`` (200): accelerometer/gyroscope rate at least (the chip's 1125/(1+n) Hz).
- ``accel_range_g`` (4), ``gyro_range_dps`` (1000): full scales.
- ``dlpf`` (3): the digital low-pass filter DLPFCFG of both, 1 to 6.
- ``publish_imu`` (true), ``publish_temperature`` (true): the optional topics.
- ``imu_fifo`` (true): accelerometer, gyroscope and temperature from the chip's FIFO, each
  sample stamped when the chip took it; false: polled on data-ready, stamped when read.

The messages (settable while running):

- ``frame_id`` (imu_link): header.frame_id of all three topics: a tf2 frame name of at most
  128 characters, letters, digits and underscores, single slashes between names
  (robot1/imu_link), none leading; a name does not start with a digit.
- ``magnetic_field_stddev`` (0.0): tesla per axis for the covariance; 0: unknown.
- ``accel_noise_density``, ``gyro_noise_density`` (0.0): per sqrt(Hz) for the covariances.

The simulator (``backend: sim`` only; declared with every backend, in ``nodes/sim_backend.py``):

- ``sim.field_ut`` (50.0), ``sim.inclination_deg`` (60.0): the earth field.
- ``sim.latitude``, ``sim.longitude`` (NaN), ``sim.altitude`` (0.0): or the World Magnetic
  Model's field there; ``sim.field_scale`` (1.0), ``sim.inclination_offset_deg`` (0.0): a
  disturbed place.
- ``sim.hard_iron_ut`` ([0, 0, 0]), ``sim.soft_iron`` (identity): the distortion to calibrate.
- ``sim.mag_misalignment_deg`` ([0, 0, 0]): magnetometer axes against the accel/gyro frame.
- ``sim.noise_ut`` (0.3): magnetometer white noise, 1 sigma.
- ``sim.accel_bias_mps2``, ``sim.gyro_bias_dps`` ([0, 0, 0]): inertial biases, within the
  largest full scale (±16 g, ±2000 deg/s).
- ``sim.accel_noise_density`` (2.26e-3), ``sim.gyro_noise_density`` (2.62e-4): inertial noise,
  at most 1.0 per sqrt(Hz).
- A magnetometer distortion beyond the AK09916's ±4912 µT reads as its overflow (ST2 HOFL):
  the sample is dropped and counted, as on the chip.
- ``sim.temperature_c`` (25.0), ``sim.temperature_rise_c`` (2.0),
  ``sim.temperature_time_constant_s`` (600.0): the die and its first-order warm-up.
- ``sim.hard_iron_drift_ut_per_c`` ([0, 0, 0]): the hard iron's drift, µT per degC of die
  temperature above ``sim.temperature_c``; ``sim.current_field_ut_per_a`` ([0, 0, 0]): the
  field of the battery current at the sensor, µT per ampere (``sim.motion: cmd_vel`` only).
- ``sim.motion`` (tumble): tumble, yaw, still, poses, or cmd_vel (a robot following cmd_vel).
- ``sim.i2c_error_rate`` (0.0): share of failing I2C transactions; ``sim.seed`` (0).
- ``sim.max_yaw_rate`` (1.0), ``sim.max_yaw_acceleration`` (1.0), ``sim.tilt_wobble_deg``
  (2.0), ``sim.cmd_vel_timeout`` (0.5): the cmd_vel robot's limits, tilt and command timeout;
  ``sim.max_speed`` (0.5), ``sim.max_linear_acceleration`` (1.0): its driving limits.
- ``sim.track_width`` (0.3), ``sim.idle_current_a`` (0.5), ``sim.full_current_a`` (5.0): the
  cmd_vel robot's battery current, idle plus a share of the full current by the wheels' mean
  speed against ``sim.max_speed`` (``motion.DriveCurrent``).
"""

from __future__ import annotations

from dataclasses import dataclass
import gc
import math
import re
import sys
import threading

from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.duration import Duration
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Imu, MagneticField, Temperature

from mag_calibrator_ros.icm20948 import registers as reg
from mag_calibrator_ros.icm20948.driver import ImuSettings
from mag_calibrator_ros.icm20948.supervisor import (
    ERROR,
    OK,
    WARN,
    Icm20948Supervisor,
    ImuSample,
    MagSample,
    Sample,
    TemperatureSample,
)
from mag_calibrator_ros.nodes import diagnostics, sim_backend
from mag_calibrator_ros.nodes.parameters import descriptor as _descriptor
from mag_calibrator_ros.nodes.runtime import spin_node
from mag_calibrator_ros.sim import motion
from mag_calibrator_ros.sim.config import SimConfig
from mag_calibrator_ros.sim.robot import SimulatedRobot
from mag_calibrator_ros.sim.simulator import SimulatedIcm20948Bus

NODE_NAME = 'icm20948_driver'
TOPIC = 'imu/mag'
IMU_TOPIC = 'imu/data_raw'
TEMPERATURE_TOPIC = 'imu/temperature'
BACKENDS = ('smbus2', 'sim')
LEVELS = {OK: diagnostics.OK, WARN: diagnostics.WARN, ERROR: diagnostics.ERROR}

# Publisher QoS: reliable, volatile, keep-last 10 (REP-2003 system-default reliability; the
# explicit depth keeps a momentarily slow reliable subscriber from losing samples).
DRIVER_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=10,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)


class DriverConfigurationError(ValueError):
    """A parameter value the driver refuses; the message lists every problem."""


@dataclass(frozen=True)
class DriverSettings:
    backend: str
    i2c_bus: int
    address: int
    rate_hz: int
    frame_id: str
    magnetic_field_stddev: float
    imu: ImuSettings
    publish_imu: bool
    publish_temperature: bool
    imu_fifo: bool
    accel_noise_density: float
    gyro_noise_density: float
    sim: SimConfig | None
    cmd_vel: motion.CmdVelTrajectory | None = None
    """The simulated robot following cmd_vel (sim.motion cmd_vel), else None."""


_IMU = ImuSettings()
PARAMETERS: dict[str, tuple[object, ParameterDescriptor]] = {
    'backend': ('smbus2', _descriptor(
        'Where the chip is: smbus2 (Linux /dev/i2c-N) or sim (register-level simulator).',
        constraints='smbus2 | sim')),
    'i2c_bus': (1, _descriptor(
        'I2C bus number N of /dev/i2c-N (Raspberry Pi header: 1).', integer_range=(0, 255))),
    'address': (reg.ICM20948_DEFAULT_ADDRESS, _descriptor(
        'ICM-20948 I2C address: 104 (0x68, AD0 low) or 105 (0x69, AD0 high; SparkFun and '
        'Adafruit boards).', integer_range=(0x68, 0x69))),
    'rate_hz': (100, _descriptor(
        'AK09916 magnetometer continuous-measurement rate in Hz.', integer_range=(10, 100),
        constraints='one of 10, 20, 50, 100')),
    'imu_rate_hz': (_IMU.rate_hz, _descriptor(
        'Accelerometer/gyroscope output rate in Hz, at least: the chip runs at 1125/(1+n) Hz, '
        'the nearest at or above this (200 -> 225, 1000 -> 1125).', integer_range=(5, 1125))),
    'accel_range_g': (_IMU.accel_range_g, _descriptor(
        'Accelerometer full scale in g.', integer_range=(2, 16), constraints='2 | 4 | 8 | 16')),
    'gyro_range_dps': (_IMU.gyro_range_dps, _descriptor(
        'Gyroscope full scale in deg/s.', integer_range=(250, 2000),
        constraints='250 | 500 | 1000 | 2000')),
    'dlpf': (_IMU.dlpf, _descriptor(
        'Digital low-pass filter DLPFCFG for both sensors; 3 dB bandwidth accel/gyro in Hz: '
        '1: 246/152, 2: 111/120, 3: 50/51, 4: 24/24, 5: 12/12, 6: 6/6.',
        integer_range=(1, 6))),
    'publish_imu': (True, _descriptor('Publish imu/data_raw (accelerometer and gyroscope).')),
    'publish_temperature': (True, _descriptor(
        'Publish imu/temperature (die temperature, at most 10 Hz).')),
    'imu_fifo': (True, _descriptor(
        "Read the accelerometer, gyroscope and temperature from the chip's FIFO in bursts, "
        'each sample stamped when the chip took it (needed towards 1125 Hz); false: poll '
        'data-ready and stamp each sample when read.')),
    'frame_id': ('imu_link', _descriptor(
        'header.frame_id of imu/mag, imu/data_raw and imu/temperature: the ICM-20948 '
        'accel/gyro frame (REP-145).', read_only=False,
        constraints='at most 128 characters: letters, digits, underscores; a name does not '
                    'start with a digit; single slashes between names, none leading')),
    'magnetic_field_stddev': (0.0, _descriptor(
        'Per-axis noise standard deviation in tesla for the covariance diagonal; 0 = unknown '
        '(all-zero covariance).', read_only=False, float_range=(0.0, 1e-3))),
    'accel_noise_density': (0.0, _descriptor(
        'Accelerometer noise density in (m/s^2)/sqrt(Hz) for the covariance diagonal (variance '
        '= density^2 x DLPF noise bandwidth); 0 = unknown. ICM-20948 typical: 2.26e-3.',
        read_only=False, float_range=(0.0, 1.0))),
    'gyro_noise_density': (0.0, _descriptor(
        'Gyroscope noise density in (rad/s)/sqrt(Hz) for the covariance diagonal; 0 = unknown. '
        'ICM-20948 typical: 2.6e-4.', read_only=False, float_range=(0.0, 1.0))),
    **sim_backend.PARAMETERS,  # declared on every backend
}
FRAME_ID_MAX_LENGTH = 128
FRAME_ID_PATTERN = re.compile(r'[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*')


def settings_problems(values: dict[str, object]) -> list[str]:
    """Cross-checks beyond the descriptors' ranges; empty when the settings are usable."""
    problems = []
    if values['backend'] not in BACKENDS:
        problems.append(f"backend must be one of {', '.join(BACKENDS)}, got {values['backend']!r}")
    if values['rate_hz'] not in reg.CONTINUOUS_MODES:
        problems.append(
            f"rate_hz must be one of {sorted(reg.CONTINUOUS_MODES)}, got {values['rate_hz']}"
        )
    problems += imu_settings(values).problems()
    problems += frame_id_problems(values['frame_id'])
    for name in ('magnetic_field_stddev', 'accel_noise_density', 'gyro_noise_density'):
        problems += non_negative_problems(name, values[name])
    return problems + sim_backend.problems(values)


def imu_settings(values: dict[str, object]) -> ImuSettings:
    return ImuSettings(rate_hz=values['imu_rate_hz'], accel_range_g=values['accel_range_g'],
                       gyro_range_dps=values['gyro_range_dps'], dlpf=values['dlpf'])


def frame_id_problems(frame_id: object) -> list[str]:
    """A tf2 frame name: one or more tokens of letters, digits and underscores, none starting
    with a digit, joined by single slashes (imu_link, robot1/imu_link), at most
    FRAME_ID_MAX_LENGTH characters: the tokens of ROS names
    (design.ros2.org/articles/topic_and_service_names.html) without the leading slash tf2
    refuses. Every message carries the frame, so a 100 kB or multi-line one is a mistake."""
    if not isinstance(frame_id, str):
        return [f'frame_id must be a non-empty string, got {frame_id!r}']
    shown = repr(frame_id) if len(frame_id) <= 40 else f'{frame_id[:40]!r}...'
    if not frame_id.strip():
        return [f'frame_id must be a non-empty string, got {shown}']
    if frame_id.startswith('/'):
        return [f'frame_id must not start with a slash (tf2 frame names), got {shown}']
    if len(frame_id) > FRAME_ID_MAX_LENGTH:
        return [f'frame_id must be at most {FRAME_ID_MAX_LENGTH} characters (a tf2 frame name), '
                f'got {len(frame_id)}: {shown}']
    if not FRAME_ID_PATTERN.fullmatch(frame_id):
        return [f'frame_id must be letters, digits and underscores, not starting with a digit, '
                f'with single slashes between such names (imu_link, robot1/imu_link), got {shown}']
    return []


def non_negative_problems(name: str, value: object) -> list[str]:
    if not isinstance(value, float) or not math.isfinite(value) or value < 0.0:
        return [f'{name} must be a finite double >= 0, got {value!r}']
    return []


def diagonal_covariance(variance: float) -> list[float]:
    """Row-major 3x3 with ``variance`` on the diagonal: all zeros (= unknown, REP-145) for 0."""
    return [variance, 0.0, 0.0, 0.0, variance, 0.0, 0.0, 0.0, variance]


def covariance_from_stddev(stddev: float) -> list[float]:
    return diagonal_covariance(stddev * stddev)


def covariance_from_density(density: float, noise_bandwidth_hz: float) -> list[float]:
    """White noise of ``density`` per sqrt(Hz) through a filter of this noise bandwidth."""
    return diagonal_covariance(density * density * noise_bandwidth_hz)


class Icm20948DriverNode(Node):
    """Publishes imu/mag, imu/data_raw and imu/temperature from an ICM-20948 or its simulator."""

    def __init__(self, **node_kwargs) -> None:
        super().__init__(NODE_NAME, **node_kwargs)
        self.settings = self._read_settings()
        s = self.settings
        self.simulator: SimulatedIcm20948Bus | None = None
        if s.sim is not None:
            self.simulator = SimulatedIcm20948Bus(s.sim, trajectory=s.cmd_vel)
        self.bus_name = 'sim' if s.backend == 'sim' else f'/dev/i2c-{s.i2c_bus}'
        self.hardware_id = f'icm20948@{self.bus_name}:{s.address:#04x}'
        self._frame_id = s.frame_id
        self._mag_covariance = covariance_from_stddev(s.magnetic_field_stddev)
        self._accel_covariance = covariance_from_density(
            s.accel_noise_density, s.imu.accel_noise_bandwidth_hz)
        self._gyro_covariance = covariance_from_density(
            s.gyro_noise_density, s.imu.gyro_noise_bandwidth_hz)
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self.published = 0  # imu/mag messages
        self.published_imu = 0
        self._publisher = self.create_publisher(MagneticField, TOPIC, DRIVER_QOS)
        self._imu_publisher = (self.create_publisher(Imu, IMU_TOPIC, DRIVER_QOS)
                               if s.publish_imu else None)
        self._temperature_publisher = (
            self.create_publisher(Temperature, TEMPERATURE_TOPIC, DRIVER_QOS)
            if s.publish_temperature else None)
        self._zero_stamp_said = False  # 'stamped 0' (sim time without /clock) is said once
        self._sim_robot: sim_backend.SimRobotWiring | None = None  # set last: the pump reads it
        self._diagnostics = diagnostics.DiagnosticsPublisher(self)
        clock = self.get_clock()
        inertial = s.publish_imu or s.publish_temperature
        self.supervisor = Icm20948Supervisor(
            self._open_bus, address=s.address, bus_name=self.bus_name, mag_rate_hz=s.rate_hz,
            imu=s.imu if inertial else None, publish_imu=s.publish_imu,
            publish_temperature=s.publish_temperature, imu_fifo=s.imu_fifo,
            stamp=lambda: clock.now().to_msg(),
            stamp_ago=lambda age: (clock.now() - Duration(nanoseconds=round(age * 1e9))).to_msg(),
            log=self._log,
        )
        self._diagnostics_timer = self.create_timer(1.0, self._publish_diagnostics)
        topics = [self.resolve_topic_name(TOPIC) + f' {s.rate_hz} Hz']
        if s.publish_imu:
            topics.append(f'{self.resolve_topic_name(IMU_TOPIC)} {s.imu.odr_hz:.1f} Hz '
                          f'(imu_rate_hz {s.imu.rate_hz}; chip rates are 1125/(1+n) Hz), '
                          f'±{s.imu.accel_range_g} g, ±{s.imu.gyro_range_dps} deg/s, '
                          f'dlpf {s.imu.dlpf}')
        if s.publish_temperature:
            topics.append(self.resolve_topic_name(TEMPERATURE_TOPIC))
        self.get_logger().info(
            f'{s.backend} backend, ICM-20948 {s.address:#04x} on {self.bus_name}, publishing '
            + '; '.join(topics) + f' in frame {s.frame_id}'
        )
        self._stop = threading.Event()
        self._pump = threading.Thread(target=self.supervisor.run, args=(self._stop, self._deliver),
                                      daemon=True, name=f'{NODE_NAME} I2C')
        self._pump.start()
        if s.cmd_vel is not None:  # the simulated robot: cmd_vel in, battery_state out
            self._sim_robot = sim_backend.SimRobotWiring(
                self, SimulatedRobot(s.cmd_vel, lambda: self.simulator.sim_time_s), DRIVER_QOS)

    # --- counters the tests, the demo and the benchmark read -------------------------------------

    @property
    def i2c_errors(self) -> int:
        return self.supervisor.i2c_errors

    @property
    def reinitialisations(self) -> int:
        return self.supervisor.reinitialisations

    @property
    def overflows(self) -> int:
        return self.supervisor.overflows

    @property
    def overruns(self) -> int:
        return self.supervisor.overruns

    @property
    def last_recovery_s(self) -> float | None:
        return self.supervisor.last_recovery_s

    # --- parameters ------------------------------------------------------------------------------

    def _read_settings(self) -> DriverSettings:
        problems = []
        values: dict[str, object] = {}
        for name, (default, descriptor) in PARAMETERS.items():
            try:
                values[name] = self.declare_parameter(name, default, descriptor).value
            except (InvalidParameterValueException, InvalidParameterTypeException) as error:
                expected = type(default).__name__ if not isinstance(default, list) else (
                    f'list of {len(default)} doubles'
                )
                problems.append(f'{name}: {error} (expected {expected}: {descriptor.description})')
                # Declare it anyway (default) so the node stays introspectable while it reports.
                values[name] = self.declare_parameter(
                    name, default, descriptor, ignore_override=True
                ).value
        problems += settings_problems(values)
        sim = None
        if values['backend'] == 'sim':
            try:
                sim = sim_backend.sim_config(values)
            except ValueError as error:
                problems.append(f'sim.*: {error}')
        cmd_vel = None
        if sim is not None and not problems:
            cmd_vel = sim_backend.cmd_vel_trajectory(sim, values)
        if problems:
            message = 'refusing to start, invalid parameters:\n  ' + '\n  '.join(problems)
            self.get_logger().fatal(message)
            Node.destroy_node(self)  # nothing else was created yet
            raise DriverConfigurationError(message)
        return DriverSettings(
            backend=values['backend'],
            i2c_bus=values['i2c_bus'],
            address=values['address'],
            rate_hz=values['rate_hz'],
            frame_id=values['frame_id'],
            magnetic_field_stddev=values['magnetic_field_stddev'],
            imu=imu_settings(values),
            publish_imu=values['publish_imu'],
            publish_temperature=values['publish_temperature'],
            imu_fifo=values['imu_fifo'],
            accel_noise_density=values['accel_noise_density'],
            gyro_noise_density=values['gyro_noise_density'],
            sim=sim,
            cmd_vel=cmd_vel,
        )

    def _on_set_parameters(self, parameters) -> SetParametersResult:
        problems = []
        for parameter in parameters:
            if parameter.name == 'frame_id':
                problems += frame_id_problems(parameter.value)
            elif parameter.name in ('magnetic_field_stddev', 'accel_noise_density',
                                    'gyro_noise_density'):
                problems += non_negative_problems(parameter.name, parameter.value)
        if problems:
            return SetParametersResult(successful=False, reason='; '.join(problems))
        imu = self.settings.imu
        for parameter in parameters:
            if parameter.name == 'frame_id':
                self._frame_id = parameter.value
            elif parameter.name == 'magnetic_field_stddev':
                self._mag_covariance = covariance_from_stddev(parameter.value)
            elif parameter.name == 'accel_noise_density':
                self._accel_covariance = covariance_from_density(
                    parameter.value, imu.accel_noise_bandwidth_hz)
            elif parameter.name == 'gyro_noise_density':
                self._gyro_covariance = covariance_from_density(
                    parameter.value, imu.gyro_noise_bandwidth_hz)
        return SetParametersResult(successful=True)

    # --- wiring ----------------------------------------------------------------------------------

    def _open_bus(self):
        if self.simulator is not None:
            return self.simulator
        import smbus2  # only the hardware backend needs it

        try:
            return smbus2.SMBus(self.settings.i2c_bus)
        except OSError as error:
            raise OSError(
                error.errno,
                f'cannot open {self.bus_name}: {error.strerror or error} (is I2C enabled, and is '
                f'this user in the i2c group?)',
            ) from error

    def _log(self, level: str, message: str) -> None:
        # One call site per severity: rclpy refuses a severity change at the same call site.
        logger = self.get_logger()
        if level == 'error':
            logger.error(message)
        elif level == 'warning':
            logger.warning(message)
        else:
            logger.info(message)

    def _deliver(self, samples: list[Sample]) -> bool:
        """Publish the supervisor's samples (on its thread); False stops it after shutdown."""
        try:
            for sample in samples:
                if isinstance(sample, MagSample):
                    self._publish_mag(sample)
                elif isinstance(sample, ImuSample):
                    self._publish_imu(sample)
                else:
                    self._publish_temperature(sample)
        except Exception as error:  # a publish after shutdown, or a defect
            if not self.context.ok():
                return False
            self.get_logger().error(f'publishing failed: {error!r}', throttle_duration_sec=10.0)
        return True

    def _publish_mag(self, sample: MagSample) -> None:
        if not self._zero_stamp_said and sample.stamp.sec == 0 and sample.stamp.nanosec == 0:
            self._zero_stamp_said = True
            self.get_logger().warning(
                'messages are stamped 0: use_sim_time is true and no /clock has come (play the '
                'bag with --clock, or set use_sim_time false)'
                if self.get_parameter('use_sim_time').value else
                'messages are stamped 0: the node clock reads 0')
        message = MagneticField()
        message.header.stamp = sample.stamp
        message.header.frame_id = self._frame_id
        x, y, z = (float(v) for v in sample.reading.field_tesla)
        message.magnetic_field.x, message.magnetic_field.y, message.magnetic_field.z = x, y, z
        message.magnetic_field_covariance = self._mag_covariance
        self._publisher.publish(message)
        self.published += 1
        if self._sim_robot is not None:
            self._sim_robot.publish_battery(sample.stamp, self._frame_id)

    def _publish_imu(self, sample: ImuSample) -> None:
        reading = sample.reading
        message = Imu()
        message.header.stamp = sample.stamp
        message.header.frame_id = self._frame_id
        message.orientation_covariance[0] = -1.0  # no orientation (REP-145)
        acceleration, rate = message.linear_acceleration, message.angular_velocity
        acceleration.x, acceleration.y, acceleration.z = (
            float(v) for v in reading.linear_acceleration)
        rate.x, rate.y, rate.z = (float(v) for v in reading.angular_velocity)
        message.linear_acceleration_covariance = self._accel_covariance
        message.angular_velocity_covariance = self._gyro_covariance
        self._imu_publisher.publish(message)
        self.published_imu += 1

    def _publish_temperature(self, sample: TemperatureSample) -> None:
        message = Temperature()
        message.header.stamp = sample.stamp
        message.header.frame_id = self._frame_id
        message.temperature = float(sample.celsius)
        message.variance = 0.0  # unknown
        self._temperature_publisher.publish(message)

    def _publish_diagnostics(self) -> None:
        backend = {'backend': self.settings.backend}
        self._diagnostics.publish([
            diagnostics.diagnostic_status(
                f'{self.get_fully_qualified_name()}: {status.stream}', self.hardware_id,
                LEVELS[status.level],
                status.message, {**backend, **status.values},
            )
            for status in self.supervisor.status()
        ])

    def destroy_node(self) -> None:
        self._stop.set()
        self._pump.join(timeout=5.0)
        self.supervisor.close()
        super().destroy_node()


def started_node() -> Icm20948DriverNode:
    """The node, with everything allocated at start-up exempt from the garbage collector: a full
    collection over rclpy's, numpy's and scipy's objects pauses every thread long enough to lose
    samples at high rates; what the running node allocates is still collected."""
    node = Icm20948DriverNode()
    gc.freeze()
    return node


def main(args: list[str] | None = None) -> int:
    """Console script ``icm20948_driver``: exit 0 on a normal stop, 2 on invalid parameters."""
    try:
        return spin_node(started_node, args)
    except DriverConfigurationError:
        return 2  # already logged as FATAL with every problem


if __name__ == '__main__':
    sys.exit(main(sys.argv))
