# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Input that no calibration can fix: a field in the wrong unit, or one already normalised.

Pure judgements on a handful of readings, each returning None (nothing wrong) or the reason in a
user's words, naming the likely cause and the fix. The live session (``live/sanity.py``) and
``mag_calibrator_fit`` call them; neither fits a field these refuse, because a fit would only
learn the mistake (a calibration of gauss read as tesla is off by 1e4 once the driver is fixed;
a fit of a normalised field learns nothing and may move it).

The bounds are the Earth's: its field is 22-67 µT everywhere on the surface (the World Magnetic
Model), and a magnetometer beside a robot's iron reads at most a few mT (the AK09916's full
scale is 4.9 mT). Gravity is 9.78-9.83 m/s^2; a moving robot's accelerometer reads around it.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from mag_calibrator_ros.calibration.fit.earth_field import TESLA_PER_UNIT
from mag_calibrator_ros.calibration.fit.robust import mad_sigma

MAX_TESLA = 1e-3
"""A median |B| above this is no field a magnetometer reads on Earth in tesla (the Earth's is
at most 67 µT; hard iron beside it a few hundred µT; chips saturate at a few mT)."""

MIN_TESLA = 1e-7
"""...nor below this: 0.1 µT, a few hundred times weaker than the Earth's weakest field (only
inside magnetic shielding)."""

EARTH_UT = (22.0, 67.0)
"""The Earth's field strength on its surface, µT (WMM2025: 22 µT off Brazil, 67 µT near the
south magnetic pole)."""

TESLA_PER = {'gauss': 1e-4, 'µT': 1e-6, 'mG': 1e-7, 'nT': 1e-9}
"""The units a field published as tesla is most often really in (sensor_msgs/MagneticField
requires tesla, REP-103; drivers publishing gauss or µT in it are a recurring bug)."""

NORMALISED_SPREAD = 1e-4
"""Largest relative spread (robust std over median) of |B| a field can have to count as
normalised or calibrated upstream. Raw magnetometers move |B| by several % as they turn (hard
and soft iron) and by their noise and quantisation when calibrated: the AK09916's step of
0.15 µT is 3e-3 of 50 µT, the finest MEMS parts' noise ~1e-3. A magnitude constant to 1e-4
over varied directions is no sensor's reading but a computed one."""

MIN_DIRECTION_SPREAD_DEG = 30.0
"""The readings' directions must spread this far (RMS angle from their mean) for a constant
magnitude to mean anything: a still sensor's magnitude is constant too."""

MIN_READINGS = 5
"""Fewer readings than this are not judged (one outlier would decide)."""

G = 9.80665
"""Standard gravity, m/s^2."""

ACCEL_RANGE_MPS2 = (4.0, 40.0)
"""Median |specific force| in m/s^2 of a robot's or a hand's accelerometer: g, give or take
what its motion adds. The g-units case reads 1, the milli-g 1000, raw counts thousands."""


def _magnitudes(rows: ArrayLike) -> np.ndarray:
    points = np.asarray(rows, dtype=float).reshape(-1, 3)
    with np.errstate(all='ignore'):
        norms = np.linalg.norm(points, axis=1)
    return norms[np.isfinite(norms) & (norms > 0.0)]


PUBLISH_TESLA = ("publish tesla (sensor_msgs/MagneticField, REP-103; 1 gauss = 1e-4 T, 1 µT = "
                 "1e-6 T, 1 mG = 1e-7 T) by fixing the driver's unit")
"""The fix for a ROS stream; ``mag_calibrator_fit`` names its own (``--units``, ``--scale``)."""


def field_unit_problem(readings: ArrayLike, claimed: str = 'T', fix: str = PUBLISH_TESLA,
                       full_scale_t: float | None = None) -> str | None:
    """Why readings said to be in ``claimed`` (tesla on a ROS topic; a unit of TESLA_PER_UNIT)
    cannot be (their median |B| names the likely unit), or None. Needs MIN_READINGS usable rows;
    fewer are not judged, nor an unknown ``claimed``. Up to the magnetometer's full scale
    (``full_scale_t``) when it is beyond MAX_TESLA: a hard iron of 2 mT beside an AK09916
    (4.9 mT) was called a wrong unit for good (issue #47), and no unit mistake puts the Earth's
    field there (gauss, µT, mG and nT make it 0.5, 50, 500 or 5e4 "T")."""
    norms = _magnitudes(readings)
    per_unit = TESLA_PER_UNIT.get(claimed)
    if len(norms) < MIN_READINGS or per_unit is None:
        return None
    median = float(np.median(norms))
    if MIN_TESLA <= median * per_unit <= max(MAX_TESLA, full_scale_t or 0.0):
        return None
    points = np.asarray(readings, dtype=float).reshape(-1, 3)
    finite = points[np.all(np.isfinite(points), axis=1)]
    integral = bool(len(finite) and np.all(finite == np.round(finite)))
    likely = likely_field_unit(median, integral)
    where = 'beyond' if median * per_unit > MAX_TESLA else 'far below'
    what = 'the magnetometer input' if claimed == 'T' else 'the readings'
    iron = ('' if where != 'beyond' or full_scale_t else '; if a magnet beside the sensor '
            "really makes it read that much, give the magnetometer's full scale (full_scale, "
            '--full-scale) and fields up to it are taken')
    return (f'{what} cannot be {"tesla" if claimed == "T" else claimed}: |B| {median:.4g} '
            f'"{claimed}" is {where} any field on Earth ({EARTH_UT[0]:.0f}-{EARTH_UT[1]:.0f} '
            f'µT); it looks like {likely}: {fix}; not calibrating it{iron}')


def likely_field_unit(median: float, integral: bool = False) -> str:
    """The units a median |B| published as tesla is likely in: those that put it within the
    Earth's field and ten times it (hard iron beside the sensor), joined by 'or'; raw counts
    too when the readings are whole numbers (``integral``) or no unit fits."""
    if not math.isfinite(median) or median <= 0.0:
        return 'an unknown unit'
    if median < MIN_TESLA:
        return 'tesla scaled twice (e.g. µT converted to T twice)'
    low, high = EARTH_UT[0] * 1e-6, EARTH_UT[1] * 1e-6 * 10.0
    names = {'gauss': 'gauss', 'µT': 'µT', 'mG': 'milligauss', 'nT': 'nT'}
    likely = [names[unit] for unit, tesla in TESLA_PER.items()
              if low <= median * tesla <= high]
    if integral or not likely:
        likely.append("raw counts (scale them by the sensor's tesla per count)")
    return ' or '.join(likely)


def magnitude_spread(readings: ArrayLike) -> float:
    """The relative spread of |B| (robust std over median; NaN for fewer than MIN_READINGS)."""
    norms = _magnitudes(readings)
    if len(norms) < MIN_READINGS:
        return math.nan
    median = float(np.median(norms))
    return mad_sigma(norms) / median


def normalised_problem(readings: ArrayLike) -> str | None:
    """Why a field cannot be calibrated because it already is (its |B| constant to far below
    any sensor's noise over varied directions: normalised or calibrated upstream), or None.
    Distinct readings only: one message repeated would make any magnitude look constant."""
    points = np.asarray(readings, dtype=float).reshape(-1, 3)
    with np.errstate(all='ignore'):
        points = np.unique(points, axis=0)  # a message repeated tells nothing more
        norms = np.linalg.norm(points, axis=1)
        usable = np.isfinite(norms) & (norms > 0.0)
        points, norms = points[usable], norms[usable]
        if len(norms) < MIN_READINGS:
            return None
        median = float(np.median(norms))
        spread = mad_sigma(norms) / median
        units = points / norms[:, None]
        mean = units.mean(axis=0)
        mean /= np.linalg.norm(mean) or 1.0
        angles = np.degrees(np.arccos(np.clip(units @ mean, -1.0, 1.0)))
    directions = float(np.sqrt(np.mean(angles ** 2)))
    if not (spread <= NORMALISED_SPREAD and directions >= MIN_DIRECTION_SPREAD_DEG):
        return None
    return (f'the magnetometer input is already normalised or calibrated upstream: |B| stays '
            f'{median:.6g} to a relative {spread:.1g} while its direction turns {directions:.0f} '
            "deg (RMS), far steadier than any sensor's noise: there is nothing to learn, and "
            "nothing is fitted; calibrate the raw field instead (turn off the driver's or "
            "filter's normalisation/calibration), or use it as it is (publish_uncalibrated)")


CALIBRATION_FIELD_T = (1e-6, 1e-3)
"""A calibration's field strength F in tesla lies within 1-1000 µT: the Earth's field, or the
field a magnetometer beside iron reads; F = 1 is a normalised calibration, 50 one in µT."""

STATED_UNIT_FIELD_UT = (10.0, 100.0)
"""A field strength a stated unit makes outside this (µT) is worth a word: the Earth's is
22-67 µT, a little more or less beside iron; a tenfold one is another unit."""

MAX_OFFSET_T = 0.01
"""No magnetometer reads an offset beyond 10 mT (the AK09916's full scale is 4.9 mT, the
LIS3MDL's 1.6 mT): a larger one is in another unit."""


def calibration_unit_problem(offset_t: ArrayLike, field_strength_t: float,
                             full_scale_t: float | None = None) -> str | None:
    """Why a calibration said to be in tesla cannot be (its F outside CALIBRATION_FIELD_T, an
    offset component beyond ``full_scale_t`` or MAX_OFFSET_T), naming the likely unit; None when
    it can. Every entry of a calibration asks (a file, ``~/load``, ``--params-file``, the CLI's
    output): one in µT read as tesla publishes 10^6 times the field (issue #46)."""
    offset = np.asarray(offset_t, dtype=float).reshape(-1)
    strength = float(field_strength_t)
    low, high = CALIBRATION_FIELD_T
    if not (low <= strength <= high):
        likely = ('a normalised calibration (F = 1: unit vectors, not tesla)' if strength == 1.0
                  else likely_field_unit(strength))
        where = 'beyond' if strength > high else 'far below'
        return (f'field_strength {strength:.6g} T is {where} any field a magnetometer reads '
                f'({low * 1e6:g}-{high * 1e6:g} µT): it looks like {likely}; a calibration '
                'for the node is in tesla or names its unit (calibration.units: "uT")')
    limit = MAX_OFFSET_T if full_scale_t is None or full_scale_t <= 0.0 else full_scale_t
    largest = float(np.max(np.abs(offset))) if offset.size else 0.0
    if largest > limit:
        return (f'offset {largest:.6g} T is beyond what the magnetometer reads '
                f'({limit * 1e3:g} mT{" full scale" if limit != MAX_OFFSET_T else ""}): it '
                f'looks like {likely_field_unit(largest)} next to field_strength '
                f'{strength * 1e6:.4g} µT; a calibration for the node is in tesla or names its '
                'unit (calibration.units: "uT")')
    return None


TEMPERATURE_RANGE_C = (-60.0, 200.0)
"""A die or board temperature in degrees Celsius lies within this (the ICM-20948 works from
-40 to 85 degC, datasheet DS-000189 Table 1; a kelvin or Fahrenheit reading of a warm robot
does not)."""

FIELD_PER_EARTH = 200.0
"""With no full scale given, a field beyond this many field strengths is none a magnetometer
reads (MAX_OFFSET_T, 10 mT, against the Earth's 50 µT)."""


def field_limit(full_scale: float | None, field_strength: float) -> float:
    """The largest field, in the calibration's units, any term or corrected reading may have:
    the magnetometer's full scale, or FIELD_PER_EARTH field strengths without one."""
    return full_scale if full_scale else FIELD_PER_EARTH * field_strength


def compensation_bound_problems(compensation: object, limit: float,
                                units: str = 'T') -> list[str]:
    """Everything in a compensation (``fit.calibration.Compensation``) no robot can have,
    naming the term and the bound: an input or one degree Celsius moving the field by more than
    ``limit`` (the magnetometer's full scale: the chip would saturate at a unit of the input),
    or T0 outside TEMPERATURE_RANGE_C. A file edited by hand with K = 1e300 T/A published fields
    of 2e300 T (issue #47)."""
    problems = []
    for name, column in zip(compensation.inputs, compensation.interference.T, strict=True):
        size = float(np.max(np.abs(column)))
        if not size <= limit:
            problems.append(f"interference for '{name}' is {size:.3g} {units} per unit of the "
                            f'input, beyond the {limit:.3g} {units} the magnetometer reads')
    drift = float(np.max(np.abs(compensation.temperature_coefficient)))
    if not drift <= limit:
        problems.append(f'temperature_coefficient is {drift:.3g} {units} per degC, beyond the '
                        f'{limit:.3g} {units} the magnetometer reads')
    t0, (low, high) = compensation.reference_temperature, TEMPERATURE_RANGE_C
    if t0 is not None and not low <= t0 <= high:
        problems.append(f'reference_temperature {t0:.6g} degC is outside {low:g} to {high:g} '
                        'degC (a kelvin or Fahrenheit value?)')
    return problems


def stated_unit_note(field_strength_t: float, units: str) -> str | None:
    """A word when the unit a user stated makes the field strength unlike the Earth's
    (outside STATED_UNIT_FIELD_UT), or None."""
    field_ut = field_strength_t * 1e6
    low, high = STATED_UNIT_FIELD_UT
    if not math.isfinite(field_ut) or low <= field_ut <= high:
        return None
    return (f'--units {units} makes the field {field_ut:.3g} µT, outside {low:g}-{high:g} µT '
            f"(the Earth's is {EARTH_UT[0]:.0f}-{EARTH_UT[1]:.0f} µT): check the unit the "
            'numbers are in')


def accel_unit_problem(samples: ArrayLike) -> str | None:
    """Why accelerometer samples published as m/s^2 are in another unit (g, milli-g, counts),
    from their median |a|, or None. Needs MIN_READINGS usable rows."""
    norms = _magnitudes(samples)
    if len(norms) < MIN_READINGS:
        return None
    median = float(np.median(norms))
    low, high = ACCEL_RANGE_MPS2
    if low <= median <= high:
        return None
    if 0.4 <= median <= 4.0:
        likely = f'g (multiply by {G})'
    elif 400.0 <= median <= 4000.0:
        likely = f'milli-g (multiply by {G / 1000.0:g})'
    elif median > 4000.0:
        likely = ('raw counts (multiply by g over the counts per g of the full scale, e.g. '
                  f'{G}/16384 at ±2 g)')
    else:
        likely = 'an unknown unit'
    return (f"imu/data_raw's accelerometer cannot be m/s^2: |a| {median:.4g} where gravity "
            f'alone is {G:.2f} m/s^2; it looks like {likely}: publish m/s^2 (sensor_msgs/Imu, '
            'REP-103); its samples are not used (no alignment to the IMU)')


__all__ = [
    'ACCEL_RANGE_MPS2',
    'EARTH_UT',
    'FIELD_PER_EARTH',
    'TEMPERATURE_RANGE_C',
    'compensation_bound_problems',
    'field_limit',
    'MAX_TESLA',
    'MIN_DIRECTION_SPREAD_DEG',
    'MIN_READINGS',
    'MIN_TESLA',
    'NORMALISED_SPREAD',
    'PUBLISH_TESLA',
    'CALIBRATION_FIELD_T',
    'MAX_OFFSET_T',
    'STATED_UNIT_FIELD_UT',
    'accel_unit_problem',
    'calibration_unit_problem',
    'field_unit_problem',
    'likely_field_unit',
    'magnitude_spread',
    'normalised_problem',
    'stated_unit_note',
]
