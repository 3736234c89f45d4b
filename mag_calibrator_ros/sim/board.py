# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""What the sensors on a moving board measure: physics and sensor errors, in SI units, chip frame.

The register-level simulator asks this model for a sample at a sample time and only encodes the
answer into registers (scale, saturation, quantisation), so physics and register protocol stay
apart. A motion is any ``motion.Trajectory``; the world is ENU with the earth's field from
``motion.earth_field`` and gravity straight down.

- magnetometer: ``soft_iron @ (A.T @ R.T @ earth) + hard_iron + noise`` (µT), ``A`` the
  magnetometer's misalignment against the accel/gyro frame (``mag_misalignment_deg``, a rotation
  vector; identity by default): a calibration's rotation must recover ``A``;
- the earth's field: ``field_ut`` / ``inclination_deg``, or with a location (``latitude``,
  ``longitude``, ``altitude_m``) the World Magnetic Model's field there today (declination
  included), in either case scaled by ``field_scale`` and dipped by ``inclination_offset_deg``
  (a disturbed place, against the model);
- accelerometer: specific force ``R.T @ (a_world - g_world) + bias + noise`` (m/s^2), so a board
  lying level reads +g on z;
- gyroscope: body angular rate ``+ bias + noise`` (rad/s);
- die temperature: ``temperature_c + temperature_rise_c * (1 - exp(-t / tau))``, a
  first-order warm-up after power-on towards ``temperature_c + temperature_rise_c`` with the
  time constant ``tau = temperature_time_constant_s`` (600 s by default);
- the robot's own field, added to the hard iron in the magnetometer's axes (``raw - b - K u -
  c (T - T0)`` of issue #26 undoes it): ``K * I`` with ``K = current_field_ut_per_a`` and
  ``I`` the battery current of a ``cmd_vel`` robot (``motion.DriveCurrent``), and ``c * (T -
  T0)`` with ``c = hard_iron_drift_ut_per_c``, ``T`` the die temperature and ``T0 =
  temperature_c`` (the hard iron is ``hard_iron_ut`` at power-on). ``interference_truth`` gives
  K, c and T0 in SI units for tests and benchmarks;
- a magnet stuck on the board (``attached_magnet_ut``): a body-fixed hard-iron step, added to
  the hard iron from ``magnet_attached_s`` until ``magnet_removed_s`` (``hard_iron_ut``);
- a magnet in the room (``zone_field_ut``): fixed in the world frame, added to the earth's
  field before the board's rotation, scaled by ``(1 - (d / r)^2)^2`` with ``d`` the distance
  from the motion's ``position(t)`` to ``zone_center_m`` and ``r = zone_radius_m``: all of it
  at the centre, none from the edge out (``zone_weight``). The truth ``magnetometer`` returns
  stays the earth's field alone: what a heading needs.

Noise per sample is the noise density times the square root of the DLPF's noise bandwidth, the
way DS-000189 specifies it; the DLPF's delay is not modelled.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import TYPE_CHECKING

import numpy as np

from mag_calibrator_ros.calibration.fit.earth_field import EarthField, earth_field
from mag_calibrator_ros.icm20948 import registers as reg
from mag_calibrator_ros.sim import motion

if TYPE_CHECKING:
    from mag_calibrator_ros.sim.config import SimConfig

GRAVITY_WORLD = np.array([0.0, 0.0, -reg.STANDARD_GRAVITY])  # ENU: down


@dataclass(frozen=True)
class ImuTruth:
    """The error-free values behind one inertial sample (chip frame, SI).

    ``sample_time``: seconds since the simulated chip powered on; ``rotation``: world<-body;
    ``specific_force`` (m/s^2) and ``angular_velocity`` (rad/s) without bias or noise.
    """

    sample_time: float
    rotation: np.ndarray
    specific_force: np.ndarray
    angular_velocity: np.ndarray
    temperature_c: float


@dataclass(frozen=True)
class InterferenceTruth:
    """The robot's own field as simulated, SI units, magnetometer axes (chip frame): the reading
    is ``S (earth) + hard_iron + current_field * I + temperature_drift * (T - T0)``.

    ``current_field``: (3,) tesla per ampere of battery current; ``temperature_drift``: (3,)
    tesla per degC; ``reference_temperature_c``: T0, where the hard iron is ``hard_iron`` (3,)
    tesla.
    """

    current_field: np.ndarray
    temperature_drift: np.ndarray
    reference_temperature_c: float
    hard_iron: np.ndarray


class BoardModel:
    """The simulated board: a trajectory, the earth's field and gravity, and sensor errors."""

    def __init__(self, config: SimConfig, trajectory: motion.Trajectory | None = None) -> None:
        self.config = config
        self.trajectory = (trajectory if trajectory is not None
                           else motion.make_trajectory(config.motion, config.seed))
        self.location_field: EarthField | None = None
        """The World Magnetic Model's field at the configured location (None without one)."""
        strength, inclination, declination = config.field_ut, config.inclination_deg, 0.0
        if config.has_location:
            self.location_field = earth_field(config.latitude, config.longitude,
                                              config.altitude_m)
            strength = self.location_field.intensity_nt / 1000.0
            inclination = self.location_field.inclination_deg
            declination = self.location_field.declination_deg
        inclination = min(90.0, max(-90.0, inclination + config.inclination_offset_deg))
        self._earth_ut = motion.earth_field(strength * config.field_scale, inclination,
                                            declination)
        self.mag_misalignment = motion.Rotation.from_rotvec(
            np.radians(np.asarray(config.mag_misalignment_deg, dtype=float))).as_matrix()
        """A: the magnetometer's axes in the accel/gyro frame; it reads A^T @ field."""
        self._sensing = config.soft_iron_matrix @ self.mag_misalignment.T
        self._mag_rng = np.random.default_rng([config.seed, 10])
        self._imu_rng = np.random.default_rng([config.seed, 12])
        self._accel_bias = np.asarray(config.accel_bias_mps2, dtype=float)
        self._gyro_bias = np.radians(np.asarray(config.gyro_bias_dps, dtype=float))
        self._draws_current = bool(np.any(config.current_field != 0.0))
        self._drifts = bool(np.any(config.hard_iron_drift != 0.0))
        if self._draws_current and not callable(getattr(self.trajectory, 'battery_current',
                                                        None)):
            raise ValueError(f'current_field_ut_per_a needs a motion that draws a battery '
                             f'current (cmd_vel), got a {type(self.trajectory).__name__}')
        self._magnet = bool(np.any(config.attached_magnet != 0.0))
        self._zoned = config.zone_radius_m > 0.0 and bool(np.any(config.zone_field != 0.0))
        if self._zoned and not callable(getattr(self.trajectory, 'position', None)):
            raise ValueError(f'zone_field_ut needs a motion with a position (a '
                             f'motion.CarriedTrajectory), got a {type(self.trajectory).__name__}')

    @property
    def earth_field_ut(self) -> np.ndarray:
        """The world-frame (ENU) field the board is in, µT."""
        return self._earth_ut.copy()

    def true_field_tesla(self, t: float) -> np.ndarray:
        """True chip-frame earth field (T) at time ``t``."""
        return self.trajectory.orientation(max(t, 0.0)).T @ self._earth_ut * 1e-6

    def magnetometer(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(sensed field in µT with distortion and noise, true earth field in T), chip frame."""
        rotation = self.trajectory.state(max(t, 0.0)).rotation
        earth_chip_ut = rotation.T @ self._earth_ut
        around_ut = earth_chip_ut
        if self._zoned:
            around_ut = earth_chip_ut + rotation.T @ self.zone_field_ut(t)
        # An absurd distortion may leave the doubles (inf, NaN): the chip reads that as an
        # overflow, the simulator's business, not a warning on every sample.
        with np.errstate(over='ignore', invalid='ignore'):
            sensed = self._sensing @ around_ut + self.hard_iron_ut(t)
            if self.config.noise_ut > 0.0:
                sensed = sensed + self._mag_rng.normal(0.0, self.config.noise_ut, 3)
        return sensed, earth_chip_ut * 1e-6

    def inertial(
        self, t: float, accel_noise_bandwidth_hz: float, gyro_noise_bandwidth_hz: float
    ) -> tuple[np.ndarray, np.ndarray, ImuTruth]:
        """(specific force m/s^2, angular rate rad/s) as sensed, and the truth behind them."""
        state = self.trajectory.state(max(t, 0.0))
        rotation = state.rotation
        specific_force = rotation.T @ (state.linear_acceleration - GRAVITY_WORLD)
        truth = ImuTruth(t, rotation, specific_force, state.angular_velocity,
                         self.temperature_c(t))
        accel_sigma = self.config.accel_noise_density * math.sqrt(accel_noise_bandwidth_hz)
        gyro_sigma = self.config.gyro_noise_density * math.sqrt(gyro_noise_bandwidth_hz)
        noise = self._imu_rng.standard_normal(6)
        accel = specific_force + self._accel_bias + accel_sigma * noise[:3]
        gyro = state.angular_velocity + self._gyro_bias + gyro_sigma * noise[3:]
        return accel, gyro, truth

    def temperature_c(self, t: float) -> float:
        """First-order warm-up from ``temperature_c`` by ``temperature_rise_c``."""
        warm = 1.0 - math.exp(-max(t, 0.0) / self.config.temperature_time_constant_s)
        return self.config.temperature_c + self.config.temperature_rise_c * warm

    def battery_current_a(self, t: float) -> float | None:
        """The battery current (A) the robot draws at ``t``; None for a motion without one."""
        current = getattr(self.trajectory, 'battery_current', None)
        return float(current(max(t, 0.0))) if callable(current) else None

    def hard_iron_ut(self, t: float) -> np.ndarray:
        """The offset the magnetometer reads at ``t`` (µT): the hard iron, the current's field
        and the hard iron's drift with the die temperature."""
        offset = self.config.hard_iron
        if self._draws_current:
            offset = offset + self.config.current_field * self.trajectory.battery_current(
                max(t, 0.0))
        if self._drifts:
            offset = offset + self.config.hard_iron_drift * (
                self.temperature_c(t) - self.config.temperature_c)
        if self._magnet and self.magnet_attached(t):
            offset = offset + self.config.attached_magnet
        return offset

    def magnet_attached(self, t: float) -> bool:
        """Whether the magnet of ``attached_magnet_ut`` is on the board at ``t``."""
        return self.config.magnet_attached_s <= t < self.config.magnet_removed_s

    def zone_weight(self, t: float) -> float:
        """How much of the zone's field the board is in at ``t``: 1 at its centre, 0 outside."""
        if not self._zoned:
            return 0.0
        offset = self.trajectory.position(max(t, 0.0)) - self.config.zone_center
        inside = 1.0 - float(offset @ offset) / self.config.zone_radius_m**2
        return inside * inside if inside > 0.0 else 0.0

    def zone_field_ut(self, t: float) -> np.ndarray:
        """The world-fixed zone's field (µT, world frame ENU) where the board is at ``t``."""
        return self.config.zone_field * self.zone_weight(t)

    def interference_truth(self) -> InterferenceTruth:
        """K, c and T0 as simulated (SI), for tests and benchmarks to judge a learned model."""
        return InterferenceTruth(self.config.current_field * 1e-6,
                                 self.config.hard_iron_drift * 1e-6,
                                 float(self.config.temperature_c), self.config.hard_iron * 1e-6)


def board_readings(board: BoardModel, seconds: float, rate_hz: float,
                   remap: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(magnetometer T, accelerometer m/s^2, gyroscope rad/s) rows at ``rate_hz`` from t=0 over
    ``seconds`` of a simulated board, each row read at one instant (what pairing by stamp
    gives), the inertial noise at 57 Hz bandwidth; ``remap`` turns the magnetometer's axes (a
    driver publishing them wrongly)."""
    mag, accel, gyro = [], [], []
    for k in range(int(seconds * rate_hz)):
        t = k / rate_hz
        field, _ = board.magnetometer(t)
        force, rate, _ = board.inertial(t, 57.0, 57.0)
        mag.append((field if remap is None else remap @ field) * 1e-6)
        accel.append(force)
        gyro.append(rate)
    return np.array(mag), np.array(accel), np.array(gyro)


@dataclass(frozen=True)
class CourseRecording:
    """A driven course as a robot's sensors recorded it, one row per magnetometer sample.

    ``times`` (s since power-on); ``mag`` (T, with distortion, the robot's own field and noise),
    ``truth`` (T, the earth's field in the chip frame), ``accel`` (m/s^2), ``gyro`` (rad/s), all
    (n, 3) and read at the same instant (what pairing by stamp gives); ``temperature_c`` (the
    die), ``current_a`` (the battery current the robot draws, positive), ``speed`` (m/s) and
    ``yaw_rate`` (rad/s), all (n,).
    """

    times: np.ndarray
    mag: np.ndarray
    truth: np.ndarray
    accel: np.ndarray
    gyro: np.ndarray
    temperature_c: np.ndarray
    current_a: np.ndarray
    speed: np.ndarray
    yaw_rate: np.ndarray

    @property
    def moving(self) -> np.ndarray:
        """Which rows the robot was driving or turning in (not standing still)."""
        return (np.abs(self.speed) > 1e-3) | (np.abs(self.yaw_rate) > 1e-3)


def course_recording(board: BoardModel, course: motion.CourseDriver | None = None,
                     rate_hz: float = 100.0, command_period_s: float = 0.1,
                     start_s: float = 0.0) -> CourseRecording:
    """Drive a ``cmd_vel`` board's robot over ``course`` (``motion.GROUND_COURSE`` by default)
    from ``start_s``, its commands re-sent every ``command_period_s`` as a teleop does, and
    record its sensors at ``rate_hz``; the inertial noise at 57 Hz bandwidth."""
    trajectory = board.trajectory
    if not isinstance(trajectory, motion.CmdVelTrajectory):
        raise ValueError(f'a course needs a board whose motion is cmd_vel, got a '
                         f'{type(trajectory).__name__}')
    course = course or motion.CourseDriver()
    rows: dict[str, list] = {name: [] for name in CourseRecording.__dataclass_fields__}
    next_command = 0.0
    for k in range(int(round(course.duration_s * rate_hz))):
        into = k / rate_hz
        while next_command <= into:
            speed, yaw_rate = course.command_at(next_command)
            trajectory.command(yaw_rate, start_s + next_command, speed=speed)
            next_command += command_period_s
        t = start_s + into
        field, truth = board.magnetometer(t)
        accel, gyro, _ = board.inertial(t, 57.0, 57.0)
        _, rate = trajectory.yaw_and_rate(t)
        for name, value in (('times', t), ('mag', field * 1e-6), ('truth', truth),
                            ('accel', accel), ('gyro', gyro),
                            ('temperature_c', board.temperature_c(t)),
                            ('current_a', trajectory.battery_current(t)),
                            ('speed', trajectory.speed(t)), ('yaw_rate', rate)):
            rows[name].append(value)
    return CourseRecording(**{name: np.array(values) for name, values in rows.items()})
