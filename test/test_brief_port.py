# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The benchmark yardstick (benchmarks/brief_port.py) must behave as the brief's Rust library.

Each test pins one documented behaviour or quirk of mag-calibrator-rs, so the comparisons in
benchmarks/bench_engine.py are against the real design and not a strawman or an improved copy.
"""

import importlib.util
from pathlib import Path
import sys

import numpy as np
import pytest

_PATH = Path(__file__).resolve().parents[1] / 'benchmarks' / 'brief_port.py'
_SPEC = importlib.util.spec_from_file_location('brief_port', _PATH)
brief_port = importlib.util.module_from_spec(_SPEC)
sys.modules['brief_port'] = brief_port
_SPEC.loader.exec_module(brief_port)
BriefMagCalibrator = brief_port.BriefMagCalibrator

FIELD = 50.0


def fibonacci_sphere(n: int) -> np.ndarray:
    """Unit vectors spread evenly over the sphere (deterministic)."""
    i = np.arange(n)
    y = 1.0 - 2.0 * i / (n - 1)
    r = np.sqrt(1.0 - y * y)
    theta = np.pi * (3.0 - np.sqrt(5.0)) * i
    return np.column_stack([np.cos(theta) * r, y, np.sin(theta) * r])


def axis_ellipsoid(offset, radii, n=200) -> np.ndarray:
    return np.asarray(offset) + fibonacci_sphere(n) * np.asarray(radii)


def stream(calibrator, samples) -> list[str]:
    return [calibrator.evaluate_sample(x) for x in samples]


def test_recovers_clean_axis_aligned_ellipsoid_with_small_offset():
    offset, radii = np.array([12.0, -8.0, 5.0]), np.array([55.0, 45.0, 50.0])
    calibrator = BriefMagCalibrator(50, k=2, pre_scaler=FIELD)
    stream(calibrator, axis_ellipsoid(offset, radii))
    result = calibrator.perform_calibration()
    assert result is not None
    off, scale = result
    # Quirk 8: results are in pre-scaled units (raw / pre_scaler).
    np.testing.assert_allclose(off * FIELD, offset, atol=0.01)
    np.testing.assert_allclose(scale * FIELD, radii, rtol=1e-4)
    calibration = calibrator.to_calibration(off, scale)
    corrected = calibration.apply(axis_ellipsoid(offset, radii, 500))
    np.testing.assert_allclose(np.linalg.norm(corrected, axis=1), 1.0, atol=1e-4)


def test_drops_samples_with_any_zero_or_non_normal_component():
    calibrator = BriefMagCalibrator(4)
    assert calibrator.evaluate_sample([0.0, 30.0, 40.0]) == 'dropped'  # a legitimate reading
    assert calibrator.evaluate_sample([20.0, -0.0, 40.0]) == 'dropped'
    assert calibrator.evaluate_sample([np.nan, 30.0, 40.0]) == 'dropped'
    assert calibrator.evaluate_sample([np.inf, 30.0, 40.0]) == 'dropped'
    assert calibrator.evaluate_sample([1e-40, 30.0, 40.0]) == 'dropped'  # float32 subnormal
    assert calibrator.matrix_filled == 0
    assert calibrator.evaluate_sample([-20.0, 30.0, 40.0]) == 'added'
    assert calibrator.matrix_filled == 1


def test_scores_buffered_points_on_k_and_the_candidate_on_k_plus_one_neighbours():
    # Points on a line at 0, 1, 3, 7 with k = 1: a buffered point's score is (0 + nearest) / N,
    # the self-distance counting as one of its k + 1; the candidate's is (two nearest) / N.
    calibrator = BriefMagCalibrator(4, k=1)
    stream(calibrator, [[x, 1.0, 1.0] for x in (0.5, 1.5, 3.5, 7.5)])
    np.testing.assert_allclose(calibrator.mean_distance_from_all(), [0.25, 0.25, 0.5, 1.0])
    assert calibrator.mean_distance_from_single([5.5, 1.0, 1.0]) == pytest.approx(1.0)
    assert calibrator.evaluate_sample([5.5, 1.0, 1.0]) == 'replaced'
    # The first of the tied lowest rows goes; mean_distance is the mean score, divided by N.
    np.testing.assert_allclose(calibrator.matrix[:, 0], [5.5, 1.5, 3.5, 7.5])
    assert calibrator.mean_distance == pytest.approx(0.5)


def test_accepts_crowded_samples_and_duplicates():
    samples = axis_ellipsoid([3.0, 2.0, -4.0], [50.0, 50.0, 50.0], 60)
    calibrator = BriefMagCalibrator(60, k=2)
    stream(calibrator, samples)
    scores = calibrator.mean_distance_from_all()
    sparse = int(np.argmax(scores))
    # An exact duplicate of a buffered point scores exactly as that point does, so it beats the
    # most crowded row and gets in.
    assert calibrator.evaluate_sample(samples[sparse]) == 'replaced'
    rows = calibrator.matrix[:, :3]
    assert np.sum(np.all(rows == rows[sparse], axis=1)) == 2
    # A point squeezed between two buffered neighbours is accepted too.
    crowded = samples[sparse] + 1e-3
    assert calibrator.evaluate_sample(crowded) == 'replaced'


def test_pre_scaler_makes_every_candidate_look_unique():
    # Buffered rows are raw / pre_scaler but the candidate is scored in raw units.
    samples = axis_ellipsoid([3.0, 2.0, -4.0], [50.0, 50.0, 50.0], 40)
    calibrator = BriefMagCalibrator(40, k=2, pre_scaler=FIELD)
    stream(calibrator, samples)
    outcomes = stream(calibrator, np.repeat(samples[:1], 10, axis=0))
    assert outcomes == ['replaced'] * 10


def test_half_filled_buffer_fits_the_dummy_rows():
    samples = axis_ellipsoid([3.0, 2.0, -4.0], [55.0, 45.0, 50.0], 30)
    full = BriefMagCalibrator(30, pre_scaler=FIELD)
    half = BriefMagCalibrator(60, pre_scaler=FIELD)
    stream(full, samples)
    stream(half, samples)
    assert half.matrix_filled == 30
    np.testing.assert_array_equal(half.matrix[30:, :3], 1.0)
    full_off, _ = full.perform_calibration()
    half_result = half.perform_calibration()
    # The 30 dummy rows at (1, 1, 1) (pre-scaled) drag the fit away from the true ellipsoid.
    assert half_result is None or np.max(np.abs(half_result[0] - full_off)) > 0.01


def test_float32_uncentred_fit_degrades_with_large_offset():
    radii = np.array([55.0, 45.0, 50.0])
    direction = np.array([0.6, -0.5, 0.62]) / np.linalg.norm([0.6, -0.5, 0.62])
    errors = {}
    for multiple in (1, 10, 20):
        offset = direction * FIELD * multiple
        calibrator = BriefMagCalibrator(50, pre_scaler=1.0)
        stream(calibrator, axis_ellipsoid(offset, radii))
        result = calibrator.perform_calibration()
        errors[multiple] = None if result is None else np.max(np.abs(result[1] / radii - 1.0))
    assert errors[1] < 1e-5
    assert errors[10] > 0.01  # exact data, yet >1 % scale error
    assert errors[20] is None or errors[20] > 0.1


def test_identical_samples_give_no_calibration():
    calibrator = BriefMagCalibrator(8)
    stream(calibrator, [[30.0, -20.0, 10.0]] * 8)
    assert calibrator.perform_calibration() is None


def test_brief_calibrate_streams_and_returns_a_raw_unit_calibration():
    offset, radii = np.array([12.0, -8.0, 5.0]), np.array([55.0, 45.0, 50.0])
    calibration, calibrator = brief_port.brief_calibrate(
        axis_ellipsoid(offset, radii, 300), capacity=50, pre_scaler=FIELD
    )
    assert calibrator.matrix_filled == 50
    assert calibration.model == 'axis'
    np.testing.assert_allclose(calibration.offset, offset, atol=0.01)
    np.testing.assert_allclose(1.0 / np.diag(calibration.matrix), radii, rtol=1e-4)
    np.testing.assert_allclose(calibrator.samples.shape, (50, 3))
