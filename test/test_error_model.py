"""The error model behind every corrected message's covariance (issue #45): seeded by the fit's
residual, measuring what the readings depart from F by, and marking a gross departure on the
message that shows it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.calibration.live.error_model import (
    GROSS_SIGMAS,
    UNKNOWN_RESIDUAL,
    WINDOW,
    ErrorModel,
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
