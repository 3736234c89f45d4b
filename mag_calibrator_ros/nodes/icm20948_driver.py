"""ROS 2 node ``icm20948_driver``: publishes the ICM-20948's AK09916 as sensor_msgs/MagneticField.

A thin shell over ``icm20948.driver``: parameters, a poll timer in step with the sensor's
data-ready, fault recovery (back off, re-initialise, resume) and diagnostics. With
``backend: sim`` the bus is the register-level ``SimulatedIcm20948Bus`` (tests, demo, no hardware).

Topic: relative ``imu/mag`` (REP-145), reliable QoS as REP-2003 asks of drivers; field in tesla in
the ICM-20948 accel/gyro frame so it shares ``imu_link`` with imu/data_raw from the same chip.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
import sys
import time

from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import MagneticField

from mag_calibrator_ros import motion
from mag_calibrator_ros.icm20948 import registers as reg
from mag_calibrator_ros.icm20948.driver import (
    Icm20948Magnetometer,
    MagReading,
    WrongDeviceError,
)
from mag_calibrator_ros.icm20948.simulator import (
    IDENTITY,
    SimConfig,
    SimulatedIcm20948Bus,
)
from mag_calibrator_ros.nodes import diagnostics
from mag_calibrator_ros.nodes.runtime import spin_node

NODE_NAME = 'icm20948_driver'
TOPIC = 'imu/mag'
BACKENDS = ('smbus2', 'sim')

# Poll the data-ready flag this many times per sample period (at least MIN_POLL_HZ): late enough
# reads never exceed half a period, so no sample is overrun while the executor keeps up.
POLL_PER_SAMPLE = 2.5
MIN_POLL_HZ = 50.0
# A read error this many times in a row means the device is gone or reset: re-initialise.
ERRORS_BEFORE_REINIT = 3
# No DRDY for this many sample periods (and at least STUCK_MIN_S) means the AK09916 stopped.
STUCK_PERIODS = 5
STUCK_MIN_S = 0.25
BACKOFF_INITIAL_S = 0.1
BACKOFF_MAX_S = 0.5  # cheap to retry (a dozen register accesses); recover fast
# Diagnostics: WARN when the measured rate is below this share of the requested one.
RATE_WARN_FRACTION = 0.8

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
    sim: SimConfig | None


def _descriptor(
    description: str,
    *,
    read_only: bool = True,
    integer_range: tuple[int, int] | None = None,
    float_range: tuple[float, float] | None = None,
    constraints: str = '',
) -> ParameterDescriptor:
    descriptor = ParameterDescriptor(
        description=description, read_only=read_only, additional_constraints=constraints
    )
    if integer_range is not None:
        descriptor.integer_range = [
            IntegerRange(from_value=integer_range[0], to_value=integer_range[1], step=0)
        ]
    if float_range is not None:
        descriptor.floating_point_range = [
            FloatingPointRange(from_value=float_range[0], to_value=float_range[1], step=0.0)
        ]
    return descriptor


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
        'AK09916 continuous-measurement rate in Hz.', integer_range=(10, 100),
        constraints='one of 10, 20, 50, 100')),
    'frame_id': ('imu_link', _descriptor(
        'header.frame_id of imu/mag: the ICM-20948 accel/gyro frame (REP-145).',
        read_only=False, constraints='non-empty, no leading slash')),
    'magnetic_field_stddev': (0.0, _descriptor(
        'Per-axis noise standard deviation in tesla for the covariance diagonal; 0 = unknown '
        '(all-zero covariance).', read_only=False, float_range=(0.0, 1e-3))),
    'sim.field_ut': (50.0, _descriptor(
        'Simulator: earth field strength in microtesla.', float_range=(1.0, 4900.0))),
    'sim.inclination_deg': (60.0, _descriptor(
        'Simulator: field inclination (dip) in degrees, positive pointing down.',
        float_range=(-90.0, 90.0))),
    'sim.hard_iron_ut': ([0.0, 0.0, 0.0], _descriptor(
        'Simulator: hard-iron offset [x, y, z] in microtesla, chip frame.',
        constraints='3 finite doubles')),
    'sim.soft_iron': (list(IDENTITY), _descriptor(
        'Simulator: soft-iron matrix, 9 doubles row-major, symmetric positive definite.',
        constraints='9 doubles, symmetric positive definite')),
    'sim.noise_ut': (0.3, _descriptor(
        'Simulator: white noise per axis (1 sigma) in microtesla.', float_range=(0.0, 100.0))),
    'sim.motion': ('tumble', _descriptor(
        'Simulator: how the board moves: tumble (hand), yaw (ground robot turning) or still.',
        constraints='tumble | yaw | still')),
    'sim.i2c_error_rate': (0.0, _descriptor(
        'Simulator: probability that an I2C transaction fails with EREMOTEIO.',
        float_range=(0.0, 0.99))),
    'sim.seed': (0, _descriptor(
        'Simulator: random seed (motion, noise, faults).', integer_range=(0, 2**31 - 1))),
}


def settings_problems(values: dict[str, object]) -> list[str]:
    """Cross-checks beyond the descriptors' ranges; empty when the settings are usable."""
    problems = []
    if values['backend'] not in BACKENDS:
        problems.append(f"backend must be one of {', '.join(BACKENDS)}, got {values['backend']!r}")
    if values['rate_hz'] not in reg.CONTINUOUS_MODES:
        problems.append(
            f"rate_hz must be one of {sorted(reg.CONTINUOUS_MODES)}, got {values['rate_hz']}"
        )
    problems += frame_id_problems(values['frame_id'])
    problems += stddev_problems(values['magnetic_field_stddev'])
    if values['sim.motion'] not in motion.TRAJECTORY_KINDS:
        problems.append(
            f"sim.motion must be one of {', '.join(motion.TRAJECTORY_KINDS)}, "
            f"got {values['sim.motion']!r}"
        )
    return problems


def frame_id_problems(frame_id: object) -> list[str]:
    if not isinstance(frame_id, str) or not frame_id.strip():
        return [f'frame_id must be a non-empty string, got {frame_id!r}']
    if frame_id.startswith('/'):
        return [f'frame_id must not start with a slash (tf2 frame names), got {frame_id!r}']
    return []


def stddev_problems(stddev: object) -> list[str]:
    if not isinstance(stddev, float) or not math.isfinite(stddev) or stddev < 0.0:
        return [f'magnetic_field_stddev must be a finite double >= 0 (tesla), got {stddev!r}']
    return []


def covariance_from_stddev(stddev: float) -> list[float]:
    """Row-major 3x3: stddev^2 on the diagonal, or all zeros (= unknown, REP-145) for 0."""
    variance = stddev * stddev
    return [variance, 0.0, 0.0, 0.0, variance, 0.0, 0.0, 0.0, variance]


class Icm20948DriverNode(Node):
    """Publishes imu/mag from an ICM-20948 (smbus2) or its simulator, surviving bus faults."""

    def __init__(self, **node_kwargs) -> None:
        super().__init__(NODE_NAME, **node_kwargs)
        self.settings = self._read_settings()
        s = self.settings
        self.simulator: SimulatedIcm20948Bus | None = None
        if s.sim is not None:
            self.simulator = SimulatedIcm20948Bus(s.sim)
        self.bus_name = 'sim' if s.backend == 'sim' else f'/dev/i2c-{s.i2c_bus}'
        self.hardware_id = f'icm20948@{self.bus_name}:{s.address:#04x}'
        self._frame_id = s.frame_id
        self._covariance = covariance_from_stddev(s.magnetic_field_stddev)
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self._bus = None
        self._driver: Icm20948Magnetometer | None = None
        self._running = False
        self._next_attempt = 0.0
        self._backoff = BACKOFF_INITIAL_S
        self._episode_start: float | None = None
        self._episode_logged = False
        self._last_error = ''
        self._consecutive_errors = 0
        self._last_drdy = 0.0
        self._last_overflows = 0
        self._period = 1.0 / s.rate_hz
        self._stuck_after = max(STUCK_PERIODS * self._period, STUCK_MIN_S)

        # Counters (diagnostics, tests, benchmark).
        self.published = 0
        self.i2c_errors = 0
        self.reinitialisations = 0
        self.overflows = 0
        self.overruns = 0
        self.last_recovery_s: float | None = None
        self._window_start = time.monotonic()
        self._window_published = 0
        self._window_counters = (0, 0)  # i2c_errors, overflows at the window start
        self.measured_rate_hz = 0.0

        self._publisher = self.create_publisher(MagneticField, TOPIC, DRIVER_QOS)
        self._diagnostics = diagnostics.DiagnosticsPublisher(self)
        poll_hz = max(POLL_PER_SAMPLE * s.rate_hz, MIN_POLL_HZ)
        self._poll_timer = self.create_timer(1.0 / poll_hz, self._poll)
        self._diagnostics_timer = self.create_timer(1.0, self._publish_diagnostics)
        self.get_logger().info(
            f'{s.backend} backend, ICM-20948 {s.address:#04x} on {self.bus_name}, '
            f'{s.rate_hz} Hz, publishing {self.resolve_topic_name(TOPIC)} in frame {s.frame_id}'
        )
        self._try_initialise()

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
                sim = SimConfig(
                    field_ut=values['sim.field_ut'],
                    inclination_deg=values['sim.inclination_deg'],
                    hard_iron_ut=tuple(values['sim.hard_iron_ut']),
                    soft_iron=tuple(values['sim.soft_iron']),
                    noise_ut=values['sim.noise_ut'],
                    motion=values['sim.motion'],
                    i2c_error_rate=values['sim.i2c_error_rate'],
                    seed=values['sim.seed'],
                    address=values['address'],
                )
            except ValueError as error:
                problems.append(f'sim.*: {error}')
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
            sim=sim,
        )

    def _on_set_parameters(self, parameters) -> SetParametersResult:
        problems = []
        for parameter in parameters:
            if parameter.name == 'frame_id':
                problems += frame_id_problems(parameter.value)
            elif parameter.name == 'magnetic_field_stddev':
                problems += stddev_problems(parameter.value)
        if problems:
            return SetParametersResult(successful=False, reason='; '.join(problems))
        for parameter in parameters:
            if parameter.name == 'frame_id':
                self._frame_id = parameter.value
            elif parameter.name == 'magnetic_field_stddev':
                self._covariance = covariance_from_stddev(parameter.value)
        return SetParametersResult(successful=True)

    # --- device life cycle -----------------------------------------------------------------------

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

    def _try_initialise(self) -> None:
        now = time.monotonic()
        try:
            if self._bus is None:
                self._bus = self._open_bus()
            driver = Icm20948Magnetometer(self._bus, self.settings.address, self.bus_name)
            driver.initialise(self.settings.rate_hz)
        except (OSError, WrongDeviceError) as error:
            self._fault(f'initialisation failed: {error}', now)
            self._close_bus()  # a USB adapter may come back as a new device: reopen next time
            self._next_attempt = now + self._backoff
            self._backoff = min(2.0 * self._backoff, BACKOFF_MAX_S)
            return
        self._driver = driver
        self._last_overflows = 0
        self._running = True
        self._consecutive_errors = 0
        self._backoff = BACKOFF_INITIAL_S
        self._last_drdy = time.monotonic()
        if self._episode_start is not None:
            self.last_recovery_s = self._last_drdy - self._episode_start
            self.reinitialisations += 1
            self.get_logger().info(
                f'magnetometer back after {self.last_recovery_s:.2f} s; publishing again'
            )
            self._episode_start = None
            self._episode_logged = False

    def _fault(self, message: str, now: float) -> None:
        """Enter (or stay in) a fault episode; the first message of an episode is logged."""
        self._last_error = message
        self._running = False
        if self._episode_start is None:
            self._episode_start = now
        if not self._episode_logged:
            self._episode_logged = True
            self.get_logger().error(
                f'{self.hardware_id}: {message}; retrying with back-off up to {BACKOFF_MAX_S:g} s '
                f'(logged once until it recovers)'
            )
        self._next_attempt = now + self._backoff

    # --- reading ---------------------------------------------------------------------------------

    def _poll(self) -> None:
        now = time.monotonic()
        if not self._running:
            if now >= self._next_attempt:
                self._try_initialise()
            return
        stamp = self.get_clock().now()
        try:
            reading = self._driver.read()
        except OSError as error:
            self._read_error(error, now)
            return
        self._consecutive_errors = 0
        if self._driver.overflows != self._last_overflows:
            self.overflows += self._driver.overflows - self._last_overflows
            self._last_overflows = self._driver.overflows
            self._last_drdy = now  # a sample arrived, it was just unusable
            self.get_logger().warning(
                'AK09916 magnetic overflow (ST2 HOFL): sample discarded; a magnet or motor '
                'too close?', throttle_duration_sec=10.0,
            )
        if reading is None:
            if now - self._last_drdy > self._stuck_after:
                self._check_stuck(now)
            return
        self._last_drdy = now
        self._publish(reading, stamp)

    def _read_error(self, error: OSError, now: float) -> None:
        self.i2c_errors += 1
        self._consecutive_errors += 1
        self._last_error = f'I2C read failed: {error}'
        if self._consecutive_errors >= ERRORS_BEFORE_REINIT:
            self._fault(
                f'{self._consecutive_errors} I2C reads failed in a row (last: {error}); device '
                f'gone or reset, re-initialising', now,
            )
        else:
            self.get_logger().warning(
                f'{self.hardware_id}: I2C read failed ({error}); retrying',
                throttle_duration_sec=10.0,
            )

    def _check_stuck(self, now: float) -> None:
        """No data-ready for too long: find out whether the AK09916 left continuous mode."""
        try:
            mode = self._driver.measurement_mode()
        except OSError as error:
            self.i2c_errors += 1
            self._fault(f'no data-ready for {now - self._last_drdy:.2f} s and the AK09916 does '
                        f'not answer ({error})', now)
            return
        expected = reg.CONTINUOUS_MODES[self.settings.rate_hz]
        reason = (f'AK09916 left continuous mode (CNTL2 expected {expected:#04x}, found '
                  f'{mode:#04x}): chip reset?' if mode != expected
                  else 'AK09916 data-ready stuck although in continuous mode')
        self._fault(f'no data-ready for {now - self._last_drdy:.2f} s; {reason}', now)

    def _publish(self, reading: MagReading, stamp) -> None:
        if reading.overrun:
            self.overruns += 1
        message = MagneticField()
        message.header.stamp = stamp.to_msg()
        message.header.frame_id = self._frame_id
        x, y, z = (float(v) for v in reading.field_tesla)
        message.magnetic_field.x, message.magnetic_field.y, message.magnetic_field.z = x, y, z
        message.magnetic_field_covariance = self._covariance
        self._publisher.publish(message)
        self.published += 1
        self._window_published += 1

    # --- diagnostics -----------------------------------------------------------------------------

    def _publish_diagnostics(self) -> None:
        now = time.monotonic()
        elapsed = now - self._window_start
        if elapsed > 0.0:
            self.measured_rate_hz = self._window_published / elapsed
        errors = self.i2c_errors - self._window_counters[0]
        overflows = self.overflows - self._window_counters[1]
        self._window_start, self._window_published = now, 0
        self._window_counters = (self.i2c_errors, self.overflows)
        requested = self.settings.rate_hz
        warnings = []
        if self.measured_rate_hz < RATE_WARN_FRACTION * requested:
            warnings.append(f'{self.measured_rate_hz:.1f} Hz of {requested} Hz requested')
        if errors:
            warnings.append(f'{errors} I2C errors in the last {elapsed:.1f} s (wiring?)')
        if overflows:
            warnings.append(f'{overflows} overflowed samples discarded (magnet nearby?)')
        if not self._running:
            level, message = diagnostics.ERROR, self._last_error or 'not initialised'
        elif warnings:
            level, message = diagnostics.WARN, '; '.join(warnings)
        else:
            level, message = diagnostics.OK, f'publishing {self.measured_rate_hz:.1f} Hz'
        values = {
            'backend': self.settings.backend,
            'bus': self.bus_name,
            'address': f'{self.settings.address:#04x}',
            'requested rate (Hz)': requested,
            'measured rate (Hz)': self.measured_rate_hz,
            'published': self.published,
            'i2c errors': self.i2c_errors,
            'reinitialisations': self.reinitialisations,
            'overflows (HOFL)': self.overflows,
            'overruns (DOR)': self.overruns,
            'last error': self._last_error,
        }
        self._diagnostics.publish([diagnostics.diagnostic_status(
            f'{self.get_name()}: magnetometer', self.hardware_id, level, message, values
        )])

    def _close_bus(self) -> None:
        bus, self._bus = self._bus, None
        if bus is not None and bus is not self.simulator:
            try:
                bus.close()
            except OSError:
                pass

    def destroy_node(self) -> None:
        self._close_bus()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """Console script ``icm20948_driver``: exit 0 on a normal stop, 2 on invalid parameters."""
    try:
        return spin_node(Icm20948DriverNode, args)
    except DriverConfigurationError:
        return 2  # already logged as FATAL with every problem


if __name__ == '__main__':
    sys.exit(main(sys.argv))
