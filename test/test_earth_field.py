# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The World Magnetic Model through earth_field, and calibrations judged against it."""

from __future__ import annotations

import datetime
import math

import pytest

from mag_calibrator_ros.calibration.fit.earth_field import (
    MAX_DIP_ERROR_DEG,
    EarthField,
    EarthFieldError,
    as_date,
    check_against_model,
    disturbance_text,
    earth_field,
    location_problems,
)

# Rows of NOAA's WMM2025 test value table (WMM2025_FINAL_TEST_VALUES.txt, published with the
# model; also in the WMM2025 technical report): decimal year, altitude km, latitude, longitude,
# declination deg, inclination deg, F nT. Printed to 0.01 deg and 1 nT.
WMM2025_TEST_VALUES = [
    (2025.0, 65, 43, 93, 0.50, 64.10, 55627),
    (2025.0, 51, -33, 109, -5.49, -67.50, 57055),
    (2025.5, 69, 38, -144, 12.93, 56.97, 42374),
    (2026.0, 62, -14, 99, -1.43, -44.70, 47058),
    (2026.5, 14, 0, 80, -3.10, -17.15, 41327),
    (2027.0, 54, 54, 178, 0.63, 65.46, 49634),
]


def _day(decimal_year: float) -> datetime.date:
    """2025.0 -> 2025-01-01, 2025.5 -> 2025-07-02 (day 182.5 of 365, as the model counts)."""
    year = int(decimal_year)
    start = datetime.date(year, 1, 1)
    days = (datetime.date(year + 1, 1, 1) - start).days
    return start + datetime.timedelta(days=round((decimal_year - year) * days))


@pytest.mark.parametrize(('year', 'altitude_km', 'lat', 'lon', 'dec', 'inc', 'intensity'),
                         WMM2025_TEST_VALUES)
def test_model_matches_noaa_test_values(year, altitude_km, lat, lon, dec, inc, intensity):
    field = earth_field(lat, lon, altitude_km * 1000.0, _day(year))
    # One day of secular variation (< 0.01 deg, < 1 nT) and rounding of the printed table.
    assert field.declination_deg == pytest.approx(dec, abs=0.011)
    assert field.inclination_deg == pytest.approx(inc, abs=0.011)
    assert field.intensity_nt == pytest.approx(intensity, abs=1.0)
    assert field.model == 'WMM2025'


def test_intensity_in_known_units_and_none_for_counts():
    field = EarthField(50_000.0, 60.0, 2.0, 0.0, 0.0, 0.0, '2026-11-23')
    assert field.intensity_in('T') == pytest.approx(50e-6)
    assert field.intensity_in('uT') == pytest.approx(50.0)
    assert field.intensity_in('\u00b5T') == pytest.approx(50.0)
    assert field.intensity_in('nT') == pytest.approx(50_000.0)
    assert field.intensity_in('G') == pytest.approx(0.5)
    assert field.intensity_in('mG') == pytest.approx(500.0)
    assert field.intensity_in('input') is None
    assert field.intensity_in('counts') is None


@pytest.mark.parametrize(
    ('args', 'message'),
    [((91.0, 0.0), 'latitude must be within'),
     ((math.nan, 0.0), 'latitude must be within'),
     ((0.0, 400.0), 'longitude must be within'),
     ((0.0, 0.0, 1e7), 'altitude must be within'),
     ((0.0, math.inf), 'longitude must be within'),
     (('52', 13.0), 'latitude must be within')],
)
def test_bad_locations_are_refused_with_the_reason(args, message):
    assert any(message in problem for problem in location_problems(*args))
    with pytest.raises(EarthFieldError, match=message):
        earth_field(*args)


def test_dates_outside_the_model_are_refused():
    with pytest.raises(EarthFieldError, match='WMM2025 covers 2024-11-13 to 2029-12-31'):
        earth_field(52.0, 13.0, 0.0, '2031-01-01')
    with pytest.raises(EarthFieldError, match='date must be YYYY-MM-DD'):
        earth_field(52.0, 13.0, 0.0, 'yesterday')
    assert as_date('2026-11-23') == datetime.date(2026, 11, 23)
    assert as_date(datetime.datetime(2026, 11, 23, 12)) == datetime.date(2026, 11, 23)


def test_today_is_covered():
    """The package must ship coefficients for the day the robot runs (today, UTC)."""
    field = earth_field(52.52, 13.40, 34.0)
    assert field.date == as_date(None).isoformat()
    assert 45_000 < field.intensity_nt < 55_000 and 60 < field.inclination_deg < 75


def test_the_pole_blackout_zone_is_noted_not_raised():
    assert any('blackout' in note for note in earth_field(89.0, -121.0, 28_000.0).notes)


def test_check_against_model_says_what_is_off():
    expected = EarthField(50_000.0, 60.0, 2.0, 0.0, 0.0, 0.0, '2026-11-23')
    good = check_against_model(expected, 'T', 51e-6, 61.0)
    assert good.problems == () and good.radius_ratio == pytest.approx(1.02)
    assert good.dip_error_deg == pytest.approx(1.0)
    assert disturbance_text(good) == ''
    strong = check_against_model(expected, 'T', 60e-6, 60.0)
    assert strong.radius_ratio == pytest.approx(1.2)
    assert 'field strength +20 %' in disturbance_text(strong)
    assert 'steel structure' in disturbance_text(strong)
    steep = check_against_model(expected, 'uT', 50.0, 60.0 + MAX_DIP_ERROR_DEG + 3.0)
    assert 'dip 68.0 deg' in steep.problems[0]
    for disagreeing in (strong, steep):  # either may be a wrong location, not the place
        text = disturbance_text(disagreeing)
        assert 'location is wrong' in text and 'latitude and longitude' in text
    unknown_units = check_against_model(expected, 'input', 700.0, 59.0)
    assert unknown_units.radius_ratio is None and unknown_units.intensity is None
    assert unknown_units.problems == ()
    assert set(unknown_units.as_dict()) == {'intensity', 'inclination_deg', 'declination_deg',
                                            'radius_ratio', 'dip_error_deg'}
