# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""What the simulated board sees and how it misbehaves: ``SimConfig`` and its checks."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
import math

import numpy as np

from mag_calibrator_ros.calibration.fit.earth_field import location_problems
from mag_calibrator_ros.icm20948 import registers as reg
from mag_calibrator_ros.sim import motion

IDENTITY = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
# Datasheet typicals (DS-000189), rounded: 230 ug/sqrt(Hz) and 0.015 dps/sqrt(Hz).
ACCEL_NOISE_DENSITY = 2.26e-3  # (m/s^2)/sqrt(Hz)
GYRO_NOISE_DENSITY = 2.62e-4  # (rad/s)/sqrt(Hz)
# What the simulated chip can express: a bias beyond the largest full scale (DS-000189: ±16 g,
# ±2000 dps) would read the rails on every range, and a density beyond MAX_NOISE_DENSITY (over
# 400 times the datasheet's typical) is no accelerometer or gyroscope; unbounded, 1e308 made
# every sample infinite and the simulated chip raised on each one.
MAX_ACCEL_BIAS_MPS2 = max(reg.ACCEL_RANGES_G) * reg.STANDARD_GRAVITY
MAX_GYRO_BIAS_DPS = float(max(reg.GYRO_RANGES_DPS))
MAX_NOISE_DENSITY = 1.0  # (m/s^2)/sqrt(Hz) and (rad/s)/sqrt(Hz)
# The robot's own field: beyond these a sensor would sit on the wire or the magnet itself
# (100 uT/A: a wire 2 mm away; 50 uT/degC: 2.5 mT over a 50 degC warm-up).
MAX_CURRENT_FIELD_UT_PER_A = 100.0
MAX_DRIFT_UT_PER_C = 50.0


@dataclass(frozen=True)
class SimConfig:
    """What the simulated board sees and how it misbehaves.

    Magnetometer: ``soft_iron`` is a symmetric positive-definite 3x3 matrix, row-major;
    ``hard_iron_ut`` an offset in the chip frame; ``noise_ut`` white noise per axis (1 sigma).
    Accel/gyro: constant biases (chip frame) and white-noise densities (per sample: density x
    sqrt(DLPF noise bandwidth)); die temperature starts at ``temperature_c`` and warms by
    ``temperature_rise_c``, first order with ``temperature_time_constant_s``. ``who_am_i`` and
    ``ak09916_id`` let tests model a wrong chip.
    The robot's own field (``board.BoardModel``): ``current_field_ut_per_a`` (µT per ampere of
    battery current, per chip axis: wires and motors near the sensor; ``motion`` cmd_vel only,
    the one simulated robot that draws a current) and ``hard_iron_drift_ut_per_c`` (µT per degC
    of die temperature from ``temperature_c``, the power-on temperature the hard iron is
    given at). Both zero by default: a board without them.
    Earth and mounting (``board.BoardModel``): ``mag_misalignment_deg``, a location, and a
    disturbance (``field_scale``, ``inclination_offset_deg``).
    Disturbances of ordinary use (issue #44), off by default: a magnet attached to the board
    (``attached_magnet_ut``, magnetometer axes, added to the hard iron from
    ``magnet_attached_s`` until ``magnet_removed_s``, seconds since power-on) and a world-fixed
    magnet zone (``zone_field_ut``, world frame ENU, added to the earth's field while the board
    is within ``zone_radius_m`` of ``zone_center_m``, tapering smoothly to nothing at its edge;
    a motion with a ``position``: ``motion.CarriedTrajectory``).
    """

    @property
    def has_location(self) -> bool:
        return not (math.isnan(self.latitude) and math.isnan(self.longitude))

    field_ut: float = 50.0
    inclination_deg: float = 60.0
    hard_iron_ut: Sequence[float] = (0.0, 0.0, 0.0)
    soft_iron: Sequence[float] = IDENTITY
    noise_ut: float = 0.3
    motion: str = 'tumble'
    i2c_error_rate: float = 0.0
    seed: int = 0
    address: int = reg.ICM20948_DEFAULT_ADDRESS
    who_am_i: int = reg.WHO_AM_I_VALUE
    ak09916_id: tuple[int, int] = (reg.WIA1_VALUE, reg.WIA2_VALUE)
    accel_bias_mps2: Sequence[float] = (0.0, 0.0, 0.0)
    gyro_bias_dps: Sequence[float] = (0.0, 0.0, 0.0)
    accel_noise_density: float = ACCEL_NOISE_DENSITY
    gyro_noise_density: float = GYRO_NOISE_DENSITY
    temperature_c: float = 25.0
    temperature_rise_c: float = 2.0
    temperature_time_constant_s: float = 600.0
    current_field_ut_per_a: Sequence[float] = (0.0, 0.0, 0.0)
    hard_iron_drift_ut_per_c: Sequence[float] = (0.0, 0.0, 0.0)
    mag_misalignment_deg: Sequence[float] = (0.0, 0.0, 0.0)
    """Rotation vector (deg) of the magnetometer's axes against the accel/gyro frame."""
    latitude: float = math.nan
    longitude: float = math.nan
    altitude_m: float = 0.0
    """A location (deg, m above WGS84): the field is then the World Magnetic Model's there
    (``field_ut`` and ``inclination_deg`` unused). NaN: no location."""
    field_scale: float = 1.0
    inclination_offset_deg: float = 0.0
    """A disturbed place: the field scaled and dipped against the model (or field_ut/incl.)."""
    attached_magnet_ut: Sequence[float] = (0.0, 0.0, 0.0)
    """A magnet stuck on the board: a body-fixed hard-iron step (uT, magnetometer axes)."""
    magnet_attached_s: float = math.inf
    magnet_removed_s: float = math.inf
    """When it is attached and removed (s since power-on; inf: never)."""
    zone_field_ut: Sequence[float] = (0.0, 0.0, 0.0)
    """A magnet in the room: the field (uT, world frame ENU) it adds at its zone's centre."""
    zone_center_m: Sequence[float] = (0.0, 0.0, 0.0)
    zone_radius_m: float = 0.0
    """Where it is (world, m) and how far it reaches (m; 0: no zone)."""
    # Derived, validated copies (filled in __post_init__).
    hard_iron: np.ndarray = field(init=False, repr=False, compare=False)
    soft_iron_matrix: np.ndarray = field(init=False, repr=False, compare=False)
    current_field: np.ndarray = field(init=False, repr=False, compare=False)
    hard_iron_drift: np.ndarray = field(init=False, repr=False, compare=False)
    attached_magnet: np.ndarray = field(init=False, repr=False, compare=False)
    zone_field: np.ndarray = field(init=False, repr=False, compare=False)
    zone_center: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        problems = config_problems(self)
        if problems:
            raise ValueError('invalid simulator configuration: ' + '; '.join(problems))
        object.__setattr__(self, 'hard_iron', np.asarray(self.hard_iron_ut, dtype=float))
        matrix = np.asarray(self.soft_iron, dtype=float).reshape(3, 3)
        object.__setattr__(self, 'soft_iron_matrix', matrix)
        object.__setattr__(self, 'current_field',
                           np.asarray(self.current_field_ut_per_a, dtype=float))
        object.__setattr__(self, 'hard_iron_drift',
                           np.asarray(self.hard_iron_drift_ut_per_c, dtype=float))
        for name, given in (('attached_magnet', self.attached_magnet_ut),
                            ('zone_field', self.zone_field_ut),
                            ('zone_center', self.zone_center_m)):
            object.__setattr__(self, name, np.asarray(given, dtype=float))


def config_problems(config: SimConfig) -> list[str]:
    """Every problem with a simulator configuration, spelled out (empty when valid)."""
    problems = []

    def finite(name: str, value: object) -> bool:
        try:
            ok = math.isfinite(float(value))
        except (TypeError, ValueError):
            ok = False
        if not ok:
            problems.append(f'{name} must be a finite number, got {value!r}')
        return ok

    def vector(name: str, values: object, unit: str, bound: float = math.inf,
               why: str = 'the largest full scale') -> None:
        array = np.asarray(values, dtype=float) if _numeric(values) else None
        if array is None or array.shape != (3,) or not np.all(np.isfinite(array)):
            problems.append(f'{name} must be 3 finite numbers ({unit}), got {values!r}')
        elif np.any(np.abs(array) > bound):
            problems.append(f'{name} must be within ±{bound:g} {unit} ({why}), got '
                            f'{values!r}')

    if finite('field_ut', config.field_ut) and not 0.0 < config.field_ut <= 4900.0:
        problems.append(f'field_ut must be in (0, 4900] uT (AK09916 range), got {config.field_ut}')
    if finite('inclination_deg', config.inclination_deg) and abs(config.inclination_deg) > 90.0:
        problems.append(f'inclination_deg must be within [-90, 90], got {config.inclination_deg}')
    if finite('noise_ut', config.noise_ut) and config.noise_ut < 0.0:
        problems.append(f'noise_ut must be >= 0, got {config.noise_ut}')
    if finite('i2c_error_rate', config.i2c_error_rate) and not (
        0.0 <= config.i2c_error_rate < 1.0
    ):
        problems.append(f'i2c_error_rate must be in [0, 1), got {config.i2c_error_rate}')
    if config.motion not in motion.TRAJECTORY_KINDS:
        problems.append(
            f"motion must be one of {', '.join(motion.TRAJECTORY_KINDS)}, got {config.motion!r}"
        )
    if config.address not in reg.ICM20948_ADDRESSES:
        problems.append(f'address must be 0x68 or 0x69, got {config.address!r}')
    vector('hard_iron_ut', config.hard_iron_ut, 'uT')
    soft = np.asarray(config.soft_iron, dtype=float) if _numeric(config.soft_iron) else None
    if soft is None or soft.shape != (9,) or not np.all(np.isfinite(soft)):
        problems.append(
            f'soft_iron must be 9 finite numbers (row-major 3x3), got {config.soft_iron!r}'
        )
    else:
        matrix = soft.reshape(3, 3)
        if not np.allclose(matrix, matrix.T, atol=1e-9):
            problems.append('soft_iron must be symmetric')
        elif np.linalg.eigvalsh(matrix).min() <= 0.0:
            problems.append('soft_iron must be positive definite')
    vector('accel_bias_mps2', config.accel_bias_mps2, 'm/s^2', MAX_ACCEL_BIAS_MPS2)
    vector('gyro_bias_dps', config.gyro_bias_dps, 'deg/s', MAX_GYRO_BIAS_DPS)
    vector('mag_misalignment_deg', config.mag_misalignment_deg, 'deg, a rotation vector')
    if _numeric(config.mag_misalignment_deg) and np.asarray(
            config.mag_misalignment_deg, dtype=float).shape == (3,) and np.linalg.norm(
            np.asarray(config.mag_misalignment_deg, dtype=float)) > 180.0:
        problems.append('mag_misalignment_deg must be a rotation of at most 180 deg')
    if not (_nan(config.latitude) and _nan(config.longitude)):
        problems += [f'location: {problem}' for problem in location_problems(
            config.latitude, config.longitude, config.altitude_m)]
    if finite('field_scale', config.field_scale) and not 0.0 < config.field_scale <= 10.0:
        problems.append(f'field_scale must be in (0, 10], got {config.field_scale}')
    if finite('inclination_offset_deg', config.inclination_offset_deg) and abs(
            config.inclination_offset_deg) > 90.0:
        problems.append(f'inclination_offset_deg must be within [-90, 90], got '
                        f'{config.inclination_offset_deg}')
    for name in ('accel_noise_density', 'gyro_noise_density'):
        value = getattr(config, name)
        if finite(name, value) and not 0.0 <= value <= MAX_NOISE_DENSITY:
            problems.append(f'{name} must be >= 0 and <= {MAX_NOISE_DENSITY} per sqrt(Hz), '
                            f'got {value}')
    if not isinstance(config.seed, int) or config.seed < 0:
        problems.append(f'seed must be an integer >= 0, got {config.seed!r}')
    if finite('temperature_c', config.temperature_c) and not -40.0 <= config.temperature_c <= 85.0:
        problems.append(f'temperature_c must be within the operating range [-40, 85] degC, '
                        f'got {config.temperature_c}')
    if finite('temperature_rise_c', config.temperature_rise_c) and (
        abs(config.temperature_rise_c) > 50.0
    ):
        problems.append(f'temperature_rise_c must be within [-50, 50] degC, '
                        f'got {config.temperature_rise_c}')
    if finite('temperature_time_constant_s', config.temperature_time_constant_s) and not (
            0.0 < config.temperature_time_constant_s <= 86400.0):
        problems.append(f'temperature_time_constant_s must be in (0, 86400] s, got '
                        f'{config.temperature_time_constant_s}')
    vector('current_field_ut_per_a', config.current_field_ut_per_a, 'uT per A',
           MAX_CURRENT_FIELD_UT_PER_A, 'a wire 2 mm from the sensor')
    vector('hard_iron_drift_ut_per_c', config.hard_iron_drift_ut_per_c, 'uT per degC',
           MAX_DRIFT_UT_PER_C, 'a magnet, not a drift')
    if (config.motion != 'cmd_vel' and _numeric(config.current_field_ut_per_a)
            and np.any(np.asarray(config.current_field_ut_per_a, dtype=float) != 0.0)):
        problems.append(f'current_field_ut_per_a needs motion cmd_vel (the simulated ground '
                        f'robot, the only motion that draws a battery current), got motion '
                        f'{config.motion!r}: set motion to cmd_vel or the field to zero')
    _check_disturbances(config, vector, problems)
    return problems


def _check_disturbances(config: SimConfig, vector, problems: list[str]) -> None:
    """Append the attached magnet's and the world-fixed zone's problems (``vector``: the check
    of a 3-vector, appending to the same list)."""
    vector('attached_magnet_ut', config.attached_magnet_ut, 'uT', 4900.0, 'the AK09916 range')
    attached, removed = config.magnet_attached_s, config.magnet_removed_s
    if not all(isinstance(v, (int, float)) and not math.isnan(v) and v >= 0.0
               for v in (attached, removed)):
        problems.append(f'magnet_attached_s and magnet_removed_s must be >= 0 s (inf: never), '
                        f'got {attached!r} and {removed!r}')
    elif removed < attached:
        problems.append(f'magnet_removed_s ({removed}) must not come before magnet_attached_s '
                        f'({attached})')
    vector('zone_field_ut', config.zone_field_ut, 'uT', 4900.0, 'the AK09916 range')
    vector('zone_center_m', config.zone_center_m, 'm')
    radius = config.zone_radius_m
    if not (isinstance(radius, (int, float)) and math.isfinite(radius) and radius >= 0.0):
        problems.append(f'zone_radius_m must be a finite number >= 0 m, got {radius!r}')


def _nan(value: object) -> bool:
    return isinstance(value, float) and math.isnan(value)


def _numeric(values: object) -> bool:
    try:
        np.asarray(values, dtype=float)
    except (TypeError, ValueError):
        return False
    return True
