# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The Earth's field expected where the robot is: the World Magnetic Model, and checks against it.

A calibration made next to a steel structure looks perfect to every self-consistency check: the
disturbed field is a sphere too. Only an outside reference shows it. The World Magnetic Model
(WMM2025, NOAA NCEI and BGS; Chulliat et al., "The US/UK World Magnetic Model for 2025-2030",
NOAA Technical Report, 2024) gives the main field's intensity, inclination (dip) and declination
anywhere on Earth, evaluated here with NOAA's own ``wmm-calculator`` package
(https://github.com/CIRES-Geomagnetism/wmm). ArduPilot compares the fitted radius with the
model's intensity and takes its declination; the inclination separates a disturbed field from a
good one better still (``check_against_model``).

The model covers 2024-11-13 to 2030-01-01, latitudes -90..90, altitudes -1..850 km above the WGS84
ellipsoid (what ``sensor_msgs/NavSatFix.altitude`` gives). Intensities are in nT from the model;
``EarthField.intensity_in`` converts to the caller's units when they are known.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import datetime
import math
import warnings

MODEL_NAME = 'WMM2025'
MIN_ALTITUDE_M = -1000.0
MAX_ALTITUDE_M = 850_000.0
FIRST_DAY = datetime.date(2024, 11, 13)
LAST_DAY = datetime.date(2029, 12, 31)

MAX_FIELD_ERROR_PCT = 15.0
"""Largest accepted difference between the fitted field radius and the model's intensity, in %.
A magnetometer's gain is typically within a few % (datasheet sensitivity tolerance) and local
anomalies away from steel are small; ArduPilot refuses beyond about 30 %. A field 20 % off the
model is a disturbed place (or a wrong location)."""

MAX_DIP_ERROR_DEG = 5.0
"""Largest accepted difference between the measured dip and the model's inclination. The model's
own uncertainty is 0.2 deg (its error model); crustal anomalies away from structures stay within
a degree or two, while steel nearby bends the field by several."""

DISTURBED_HINT = ('the field here is disturbed (steel structure, rebar, vehicle?) or the '
                  'location is wrong (check latitude and longitude, or the gps/fix)')

TESLA_PER_UNIT = {
    'T': 1.0, 'mT': 1e-3, 'uT': 1e-6, '\u00b5T': 1e-6, '\u03bcT': 1e-6, 'nT': 1e-9,
    'G': 1e-4, 'gauss': 1e-4, 'Gauss': 1e-4, 'mG': 1e-7, 'mgauss': 1e-7,
}
"""Unit labels a field may be expressed in; anything else (counts, 'input') is unknown."""


class EarthFieldError(ValueError):
    """A location or date the model cannot evaluate; the message says which and why."""


@dataclass(frozen=True)
class EarthField:
    """The model's field at one place and day: intensity (nT), inclination (positive down,
    northern hemisphere) and declination (east of true north), in degrees."""

    intensity_nt: float
    inclination_deg: float
    declination_deg: float
    latitude_deg: float
    longitude_deg: float
    altitude_m: float
    date: str
    model: str = MODEL_NAME
    notes: tuple[str, ...] = field(default_factory=tuple)

    def intensity_in(self, units: str) -> float | None:
        """The intensity in ``units`` ('T', 'uT', 'nT', 'G', 'mG' ...); None when unknown."""
        per_unit = TESLA_PER_UNIT.get(units)
        return None if per_unit is None else self.intensity_nt * 1e-9 / per_unit

    def describe(self) -> str:
        """One line for a log: '49.97 uT, inclination 67.72 deg, declination 5.14 deg (...)'."""
        return (f'{self.intensity_nt / 1000.0:.2f} uT, inclination {self.inclination_deg:.2f} '
                f'deg, declination {self.declination_deg:.2f} deg ({self.model} at '
                f'{self.latitude_deg:.4f}, {self.longitude_deg:.4f}, {self.altitude_m:.0f} m, '
                f'{self.date})')


def location_problems(latitude: float, longitude: float, altitude_m: float = 0.0) -> list[str]:
    """Everything that keeps the model from being evaluated at this location."""
    problems = []
    for name, value, low, high, unit in (
        ('latitude', latitude, -90.0, 90.0, 'deg'),
        ('longitude', longitude, -180.0, 360.0, 'deg'),
        ('altitude', altitude_m, MIN_ALTITUDE_M, MAX_ALTITUDE_M, 'm above the WGS84 ellipsoid'),
    ):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not (
                math.isfinite(value) and low <= value <= high):
            problems.append(f'{name} must be within [{low:g}, {high:g}] {unit}, got {value!r}')
    return problems


def as_date(when: datetime.date | datetime.datetime | str | None) -> datetime.date:
    """A date from a date, datetime, ISO text ('2026-11-23') or None (today, UTC)."""
    if when is None:
        return datetime.datetime.now(datetime.UTC).date()
    if isinstance(when, datetime.datetime):
        return when.date()
    if isinstance(when, datetime.date):
        return when
    try:
        return datetime.date.fromisoformat(str(when).strip())
    except ValueError:
        raise EarthFieldError(f'date must be YYYY-MM-DD, got {when!r}') from None


def import_model() -> bool:
    """Import the model package and what its first evaluation imports, by evaluating it once;
    False when it is not installed (``earth_field`` then says so). A node calls this at
    start-up: an import on another thread still holds the interpreter lock its messages need."""
    try:
        from wmm import wmm_calc
    except ImportError:
        return False
    model = wmm_calc()
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')
        model.setup_time(FIRST_DAY.year, FIRST_DAY.month, FIRST_DAY.day)
        model.setup_env(0.0, 0.0, 0.0)
        model.get_all()
    return True


def earth_field(latitude: float, longitude: float, altitude_m: float = 0.0,
                when: datetime.date | datetime.datetime | str | None = None) -> EarthField:
    """The World Magnetic Model's field at a location (degrees, metres above the WGS84
    ellipsoid) on a day (default today). Raises :class:`EarthFieldError`. It evaluates a
    spherical-harmonic model (the first call also imports it): call it off the message path."""
    problems = location_problems(latitude, longitude, altitude_m)
    day = as_date(when)
    if day < FIRST_DAY:
        problems.append(f'{day} is before the validity of {MODEL_NAME} ({FIRST_DAY} to '
                        f'{LAST_DAY}): the model does not describe the field then')
    elif day > LAST_DAY:
        problems.append(f'{MODEL_NAME} covers {FIRST_DAY} to {LAST_DAY}, not {day} (a newer '
                        'model package is needed)')
    if problems:
        raise EarthFieldError('; '.join(problems))
    try:
        from wmm import wmm_calc  # NOAA's package; a node imports it first (import_model)
    except ImportError:
        raise EarthFieldError('the World Magnetic Model package is not installed: pip install '
                              'wmm-calculator==1.4.4') from None

    model = wmm_calc()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter('always')
        model.setup_time(day.year, day.month, day.day)
        model.setup_env(float(latitude), float(longitude), float(altitude_m) / 1000.0)
        values = model.get_all()
    notes = tuple(' '.join(str(w.message).split()) for w in caught)
    intensity = float(values['f'][0])
    inclination = float(values['inc'][0])
    declination = float(values['dec'][0])
    if not all(math.isfinite(v) for v in (intensity, inclination, declination)):
        raise EarthFieldError(f'{MODEL_NAME} gave no finite field at {latitude}, {longitude}')
    return EarthField(intensity, inclination, declination, float(latitude), float(longitude),
                      float(altitude_m), day.isoformat(), MODEL_NAME, notes)


@dataclass(frozen=True)
class EarthCheck:
    """A calibration judged against the model: ``radius_ratio`` = fitted field / model intensity
    (None when the units are unknown), ``dip_error_deg`` = measured dip - model inclination (None
    without an accelerometer); ``problems`` says what is beyond the tolerances."""

    intensity: float | None
    """The model's intensity in the caller's units (None when they are unknown)."""
    inclination_deg: float
    declination_deg: float
    radius_ratio: float | None = None
    dip_error_deg: float | None = None
    problems: tuple[str, ...] = ()

    def as_dict(self) -> dict[str, float | None]:
        return {'intensity': self.intensity, 'inclination_deg': self.inclination_deg,
                'declination_deg': self.declination_deg, 'radius_ratio': self.radius_ratio,
                'dip_error_deg': self.dip_error_deg}


def check_against_model(
    expected: EarthField, units: str, fitted_radius: float | None = None,
    dip_deg: float | None = None, max_field_error_pct: float = MAX_FIELD_ERROR_PCT,
    max_dip_error_deg: float = MAX_DIP_ERROR_DEG,
) -> EarthCheck:
    """Compare a fitted field radius (in ``units``) and a measured dip with the model."""
    intensity = expected.intensity_in(units)
    problems = []
    ratio = None
    if intensity is not None and fitted_radius is not None and math.isfinite(fitted_radius):
        ratio = float(fitted_radius) / intensity
        if abs(ratio - 1.0) * 100.0 > max_field_error_pct:
            problems.append(
                f'field strength {100.0 * (ratio - 1.0):+.0f} % against the model '
                f'({expected.intensity_nt / 1000.0:.1f} uT, tolerance {max_field_error_pct:g} %)')
    dip_error = None
    if dip_deg is not None and math.isfinite(dip_deg):
        dip_error = float(dip_deg) - expected.inclination_deg
        if abs(dip_error) > max_dip_error_deg:
            flipped = (dip_deg > 0.0) != (expected.inclination_deg > 0.0)
            problems.append(
                f"dip {dip_deg:.1f} deg against the model's {expected.inclination_deg:.1f} deg "
                f'({dip_error:+.1f} deg, tolerance {max_dip_error_deg:g} deg'
                + ('; the other sign: the other hemisphere, or left-handed magnetometer axes)'
                   if flipped else ')'))
    return EarthCheck(intensity, expected.inclination_deg, expected.declination_deg, ratio,
                      dip_error, tuple(problems))


@dataclass(frozen=True)
class EarthReference:
    """The model's field where the robot is, in the units of the readings, with the tolerances
    a fit is judged by; ``gate``: a fit beyond them fails (else it is only warned about)."""

    field: EarthField
    units: str
    max_field_error_pct: float = MAX_FIELD_ERROR_PCT
    max_dip_error_deg: float = MAX_DIP_ERROR_DEG
    gate: bool = True

    def check(self, fitted_radius: float | None, dip_deg: float | None = None) -> EarthCheck:
        return check_against_model(self.field, self.units, fitted_radius, dip_deg,
                                   self.max_field_error_pct, self.max_dip_error_deg)


def disturbance_text(check: EarthCheck) -> str:
    """'field strength +20 % against the model (...): the field here is disturbed (...)'."""
    return f"{'; '.join(check.problems)}: {DISTURBED_HINT}" if check.problems else ''


__all__ = [
    'DISTURBED_HINT',
    'MAX_DIP_ERROR_DEG',
    'MAX_FIELD_ERROR_PCT',
    'MODEL_NAME',
    'TESLA_PER_UNIT',
    'EarthCheck',
    'EarthField',
    'EarthFieldError',
    'EarthReference',
    'as_date',
    'check_against_model',
    'disturbance_text',
    'earth_field',
    'location_problems',
]
