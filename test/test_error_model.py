# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The error model behind every corrected message's covariance (issue #45): seeded by the fit's
residual, measuring what the readings depart from F by, and marking a gross departure on the
message that shows it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mag_calibrator_ros.calibration.fit.calibration import Calibration, with_uncertainty
from mag_calibrator_ros.calibration.live.error_model import (
    DIP_MIN_READINGS,
    GROSS_SIGMAS,
    STATUS_BOUNDS_DEG,
    UNKNOWN_RESIDUAL,
    WINDOW,
    ErrorModel,
    accuracy,
    calibration_accuracy,
    dip_of,
    heading_sigma_deg,
)

FIELD = 50e-6


def calibration(residual_pct: float | None = 0.5) -> Calibration:
    metadata = {} if residual_pct is None else {'residual_rms_pct': residual_pct}
    return Calibration(np.zeros(3), np.eye(3), FIELD, 'full', metadata)


def noisy_magnitudes(sigma: float, count: int, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    directions = rng.normal(size=(count, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    errors = rng.normal(scale=sigma, size=(count, 3))
    return errors, np.linalg.norm(FIELD * directions + errors, axis=1), directions


def test_without_a_calibration_there_is_nothing_to_say():
    model = ErrorModel()
    assert model.sigma(FIELD) == 0.0
    model.restart(calibration())
    model.restart(None)
    assert model.sigma(FIELD) == 0.0


@pytest.mark.parametrize('residual_pct, share', [(0.5, 0.005), (None, UNKNOWN_RESIDUAL)])
def test_the_first_message_carries_the_fits_own_residual(residual_pct, share):
    model = ErrorModel()
    model.restart(calibration(residual_pct))
    assert model.sigma(FIELD) == pytest.approx(share * FIELD)


@pytest.mark.parametrize('noise', [0.2e-6, 2e-6])
def test_the_measured_sigma_covers_the_component_errors_as_a_1_sigma_should(noise):
    """Isotropic noise of 0.2 or 2 uT per component on a right calibration seeded at 0.5 %
    (0.25 uT): after a window the model's sigma is the noise's, and each component error is
    within it about 68 % of the time."""
    model = ErrorModel()
    model.restart(calibration(0.5))
    errors, magnitudes, _ = noisy_magnitudes(noise, 4 * WINDOW)
    sigmas = np.array([model.sigma(magnitude) for magnitude in magnitudes])
    settled = slice(2 * WINDOW, None)
    assert np.median(sigmas[settled]) == pytest.approx(noise, rel=0.2)
    inside = np.abs(errors[settled]) <= sigmas[settled, None]
    assert 0.6 < inside.mean() < 0.76


def test_a_gross_departure_is_marked_on_its_own_message_and_does_not_widen_the_rest():
    model = ErrorModel()
    model.restart(calibration(0.5))
    _, magnitudes, _ = noisy_magnitudes(0.25e-6, WINDOW)
    quiet = [model.sigma(magnitude) for magnitude in magnitudes][-1]
    magnet = model.sigma(3 * FIELD)  # a magnet passing: 100 uT off
    assert magnet >= 2 * FIELD
    after = model.sigma(FIELD)
    assert after < 1.2 * quiet  # clipped at GROSS_SIGMAS: one reading moves the mean little
    assert after < GROSS_SIGMAS * quiet


def test_a_non_finite_reading_has_no_trust():
    model = ErrorModel()
    model.restart(calibration())
    assert model.sigma(math.inf) == math.inf
    assert math.isfinite(model.sigma(FIELD))


def test_a_new_calibration_forgets_what_the_old_one_departed_by():
    model = ErrorModel()
    model.restart(calibration(0.5))
    for _ in range(WINDOW):
        model.sigma(1.2 * FIELD)  # a wrong calibration, 20 % long: a steady error
    assert model.sigma(1.2 * FIELD) > 0.1 * FIELD
    model.restart(calibration(0.5))
    assert model.sigma(FIELD) == pytest.approx(0.005 * FIELD)


def test_a_gyro_fits_direction_uncertainty_stays_when_the_magnitudes_agree():
    """A direction wrong by the fit's jackknife sigma leaves |corrected| = F: the magnitude
    cannot see it, so it stays in the sigma however long the readings agree."""
    direction = Calibration(np.zeros(3), np.eye(3), FIELD, 'full',
                            {'residual_rms_pct': 0.5, 'direction_std_deg': 1.0})
    model = ErrorModel()
    model.restart(direction)
    for _ in range(2 * WINDOW):
        sigma = model.sigma(FIELD)
    assert sigma == pytest.approx(FIELD * math.radians(1.0), rel=0.01)


# -- heading accuracy and status (issue #45, scope 3-5) -------------------------------------


def test_the_heading_sigma_is_the_component_sigma_across_the_horizontal_field():
    """0.5 uT on 50 uT at a dip of 60 deg: across a 25 uT horizontal field, atan(0.02)."""
    assert heading_sigma_deg(0.5e-6, FIELD, 60.0) == pytest.approx(
        math.degrees(math.atan(0.02)))
    assert heading_sigma_deg(0.5e-6, FIELD, 90.0) == math.inf  # at a magnetic pole
    assert heading_sigma_deg(math.inf, FIELD, 60.0) == math.inf


@pytest.mark.parametrize('sigma_ut, status', [
    (0.5, 'high'), (1.5, 'medium'), (5.0, 'low'), (10.0, 'unreliable')])
def test_the_status_follows_the_heading_sigma_bounds(sigma_ut, status):
    """At a dip of 60 deg (25 uT horizontal): 1.1, 3.4, 11.3 and 21.8 deg."""
    told = accuracy(sigma_ut * 1e-6, FIELD, (60.0, 'model'))
    assert told.status == status
    bounds = dict(STATUS_BOUNDS_DEG)
    if status in bounds:
        assert told.heading_sigma_deg <= bounds[status]
    assert f'accuracy {status}: heading sigma' in told.text()


def test_without_a_dip_the_status_is_judged_from_the_direction_a_lower_bound():
    told = accuracy(1.5e-6, FIELD, (None, ''))  # 1.7 deg of direction: 'high' at the equator
    assert told.heading_sigma_deg is None and told.direction_sigma_deg == pytest.approx(1.72,
                                                                                      abs=0.01)
    assert told.status == 'low' and 'dip unknown' in told.text()  # at best, unbounded above
    assert accuracy(1.5e-6, FIELD, (60.0, 'model')).status == 'medium'
    assert accuracy(15e-6, FIELD, (None, '')).status == 'unreliable'  # 16.7 deg: no better


def test_the_dip_measured_comes_before_the_streams_and_the_models():
    aligned = Calibration(np.zeros(3), np.eye(3), FIELD, 'full', {'dip_deg': 64.0})
    assert dip_of(aligned, 67.0, 65.0) == (64.0, 'measured')
    assert dip_of(calibration(), 67.0, 65.0) == (65.0, 'stream')
    assert dip_of(calibration(), 67.0) == (67.0, 'model')
    assert dip_of(None) == (None, '')


def test_the_stream_shows_the_dip_when_it_scatters_no_more_than_the_alignment_accepts():
    model = ErrorModel()
    model.restart(calibration())
    rng = np.random.default_rng(3)
    dip = math.radians(60.0)
    for _ in range(DIP_MIN_READINGS - 1):
        model.observe_dip((math.cos(dip), 0.0, -math.sin(dip)), (0.0, 0.0, 1.0))
    assert model.stream_dip() is None  # too few to say
    model.observe_dip((math.cos(dip), 0.0, -math.sin(dip)), (0.0, 0.0, 1.0))
    assert model.stream_dip() == pytest.approx(60.0)
    assert model.accuracy(calibration(), None).dip_source == 'stream'
    for _ in range(2 * DIP_MIN_READINGS):  # a frame the field does not sit still in
        tilt = rng.uniform(-0.5, 0.5)
        model.observe_dip((math.cos(dip + tilt), 0.0, -math.sin(dip + tilt)), (0.0, 0.0, 1.0))
    assert model.stream_dip() is None


def test_a_disturbed_window_or_a_confirmed_misfit_is_unreliable_whatever_the_sigma():
    model = ErrorModel()
    model.restart(calibration(0.5))
    for _ in range(WINDOW):
        model.sigma(FIELD)
    assert model.accuracy(calibration(0.5), 60.0).status == 'high'
    assert model.accuracy(calibration(0.5), 60.0, misfit='does not fit').status == 'unreliable'
    for _ in range(WINDOW // 2):
        model.sigma(2 * FIELD)  # a magnet held near for half the window
    disturbed = model.accuracy(calibration(0.5), 60.0)
    assert disturbed.status == 'unreliable' and 'departed' in disturbed.reason
    assert model.accuracy(None, 60.0).status == 'uncalibrated'


def test_a_calibration_by_its_own_numbers():
    told = calibration_accuracy(calibration(1.0), 60.0)  # 0.5 uT across 25 uT
    assert told.status == 'high'
    assert told.heading_sigma_deg == pytest.approx(math.degrees(math.atan(0.02)))
    assert calibration_accuracy(None).status == 'uncalibrated'
    assert set(told.values()) >= {'calibration_status', 'heading_sigma_deg'}


def field_at_dip(dip_deg: float) -> tuple[float, float, float]:
    dip = math.radians(dip_deg)
    return (FIELD * math.cos(dip), 0.0, -FIELD * math.sin(dip))


def test_a_dip_wrong_by_what_the_magnitude_cannot_see_is_added_across_the_field():
    """A planar calibration 2.5 deg off in dip keeps |corrected| = F: against the model's
    inclination (60 deg) the stream shows it, across the field in its vertical plane."""
    model = ErrorModel()
    model.restart(calibration())
    corrected = field_at_dip(62.5)
    for _ in range(DIP_MIN_READINGS):
        model.observe_dip(corrected, (0.0, 0.0, 1.0))
    assert model.along(corrected) == (0.0, 0.0, 0.0)  # nothing to measure it against
    model.expect_dip(60.0)
    along = np.array(model.along(corrected))
    assert np.linalg.norm(along) == pytest.approx(FIELD * math.radians(2.5), rel=1e-6)
    assert abs(along @ corrected) < 1e-9 * FIELD ** 2  # across the field
    assert along[1] == 0.0  # in its vertical plane: no heading error
    model.expect_dip(62.5)
    assert np.linalg.norm(model.along(corrected)) < 1e-12  # the dip it should be
    model.restart(calibration())
    assert model.along(corrected) == (0.0, 0.0, 0.0)  # a new calibration measures anew


def test_the_covariance_adds_the_sigma_and_the_one_direction():
    along = (3e-7, 0.0, -4e-7)
    covariance = with_uncertainty([0.0] * 9, 1e-7, along).reshape(3, 3)
    np.testing.assert_allclose(covariance, 1e-14 * np.eye(3) + np.outer(along, along))
    unreported = with_uncertainty([-1.0] + [0.0] * 8, 1e-7, (math.nan, 0.0, 0.0))
    np.testing.assert_allclose(unreported.reshape(3, 3), 1e-14 * np.eye(3))
    # the driver's stated noise is in sigma already (measured on the readings): not twice
    stated = np.diag([0.25e-14, 0.5e-14, 0.75e-14])  # a mean variance of half sigma^2
    raised = with_uncertainty(stated.reshape(9), 1e-7).reshape(3, 3)
    np.testing.assert_allclose(raised, stated + 0.5e-14 * np.eye(3), rtol=1e-12)
    noisier = np.diag([4e-14, 4e-14, 4e-14])  # stated noisier than measured: kept as stated
    np.testing.assert_allclose(with_uncertainty(noisier.reshape(9), 1e-7).reshape(3, 3), noisier)


def test_a_disturbed_field_widens_every_reading_not_only_the_ones_that_show_it():
    """A magnet near: a quarter of the readings show it in their magnitude, the others are off
    as much in a direction the magnitude does not see; once the window is disturbed, each
    reading carries what the gross ones departed by."""
    model = ErrorModel()
    model.restart(calibration(0.5))
    for _ in range(WINDOW):
        model.sigma(FIELD)
    quiet = model.sigma(FIELD)
    for index in range(WINDOW):
        sigma = model.sigma(1.4 * FIELD if index % 3 == 0 else FIELD)  # 20 uT off, 1 in 3
    assert quiet < 0.01 * FIELD
    assert sigma >= 0.4 * FIELD  # a reading of |B| = F, in the disturbed window
