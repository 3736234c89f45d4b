# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""fit_calibration: recovery of known hard and soft iron, model choice, every gate, bad input."""

import json
import math
import re
import warnings

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
import numpy as np
import pytest

from mag_calibrator_ros.calibration import (
    Calibration,
    FitMetrics,
    FitOptions,
    FitResult,
    fit_calibration,
)
from mag_calibrator_ros.calibration.fit.ellipsoid import axis_least_squares

FIELD = 50.0  # µT


def unit_vectors(rng, n):
    vectors = rng.normal(size=(n, 3))
    return vectors / np.linalg.norm(vectors, axis=1, keepdims=True)


def soft_iron(rng, off_diagonal=0.15, diagonal=0.1):
    """A symmetric positive-definite distortion with the given off-diagonal bound."""
    while True:
        matrix = np.diag(1.0 + rng.uniform(-diagonal, diagonal, 3))
        upper = rng.uniform(-off_diagonal, off_diagonal, 3)
        matrix[0, 1] = matrix[1, 0] = upper[0]
        matrix[0, 2] = matrix[2, 0] = upper[1]
        matrix[1, 2] = matrix[2, 1] = upper[2]
        if np.linalg.eigvalsh(matrix).min() > 0.3:
            return matrix


def yaw_directions(rng, n, inclination_deg=60.0):
    """A ground robot turning in place: the body field keeps its vertical component."""
    heading = rng.uniform(0.0, 2.0 * np.pi, n)
    inclination = np.radians(inclination_deg)
    return np.column_stack(
        [
            np.cos(inclination) * np.cos(heading),
            np.cos(inclination) * np.sin(heading),
            np.full(n, -np.sin(inclination)),
        ]
    )


def readings(directions, rng, soft, offset, noise=0.25, spikes=0.0, field=FIELD):
    """Raw readings (soft @ h + offset + noise) and the indices of injected spikes."""
    raw = field * directions @ soft.T + offset + rng.normal(0.0, noise, directions.shape)
    count = int(round(spikes * len(raw)))
    spiked = rng.choice(len(raw), count, replace=False)
    raw[spiked] += rng.choice([-1.0, 1.0], (count, 1)) * rng.uniform(1.0, 4.0, (count, 3)) * field
    return raw, spiked


def direction_error_deg(calibration, directions, soft, offset, field=FIELD):
    """RMS angle between corrected noise-free readings and the true field directions."""
    corrected = calibration.apply(field * directions @ soft.T + offset)
    corrected /= np.linalg.norm(corrected, axis=1, keepdims=True)
    cosine = np.clip(np.sum(corrected * directions, axis=1), -1.0, 1.0)
    return float(np.sqrt(np.mean(np.degrees(np.arccos(cosine)) ** 2)))


def assert_all_finite(result: FitResult):
    """The never-NaN/Inf promise, including a strict JSON round trip of the metrics."""
    json.dumps(result.metrics.as_dict(), allow_nan=False)
    if result.calibration is not None:
        assert np.all(np.isfinite(result.calibration.offset))
        assert np.all(np.isfinite(result.calibration.matrix))
        assert math.isfinite(result.calibration.field_strength)
    assert result.reason


# ----------------------------------------------------------------------------------------------
# recovery


def test_full_recovers_hard_and_soft_iron_with_spikes():
    rng = np.random.default_rng(11)
    soft, offset = soft_iron(rng), np.array([240.0, -180.0, 90.0])
    directions = unit_vectors(rng, 400)
    raw, spiked = readings(directions, rng, soft, offset, spikes=0.03)
    result = fit_calibration(raw, FitOptions(model='full'))
    assert result.success, result.reason
    assert result.metrics.model == 'full'
    calibration = result.calibration
    np.testing.assert_allclose(calibration.offset, offset, atol=0.1)
    # corrected = M (raw - b) = F M soft h: M soft must be a multiple of the identity
    product = calibration.matrix @ soft
    np.testing.assert_allclose(product / np.cbrt(np.linalg.det(product)), np.eye(3), atol=3e-3)
    assert direction_error_deg(calibration, directions, soft, offset) < 0.1
    assert set(spiked) <= set(np.flatnonzero(result.outliers))
    assert result.metrics.outlier_count <= len(spiked) + 2
    assert result.metrics.n_inliers == len(raw) - result.metrics.outlier_count


def test_parameter_std_is_reported_and_consistent_with_the_error():
    rng = np.random.default_rng(12)
    soft, offset = soft_iron(rng), np.array([-90.0, 30.0, 160.0])
    raw, _ = readings(unit_vectors(rng, 300), rng, soft, offset, noise=0.5)
    result = fit_calibration(raw, FitOptions(model='full'))
    std = result.metrics.parameter_std
    assert std is not None and len(std['offset']) == 3 and len(std['matrix']) == 9
    sigma = np.asarray(std['offset'])
    assert np.all(sigma > 0)
    assert np.all(np.abs(result.calibration.offset - offset) < 5 * sigma)
    assert np.all(sigma < 0.2)  # 0.5 µT noise, 300 samples: about 0.05 µT


def test_sphere_model_recovers_the_offset():
    rng = np.random.default_rng(13)
    offset = np.array([30.0, 260.0, -120.0])
    raw, _ = readings(unit_vectors(rng, 200), rng, np.eye(3), offset)
    result = fit_calibration(raw, FitOptions(model='sphere'))
    assert result.success, result.reason
    np.testing.assert_allclose(result.calibration.offset, offset, atol=0.15)
    matrix = result.calibration.matrix
    np.testing.assert_allclose(matrix, matrix[0, 0] * np.eye(3), atol=1e-12)


def test_axis_model_is_the_brief_least_squares():
    """Same numbers as the brief's H = [x, y, z, -y², -z², 1] solve (direct, uncentred float64)."""
    rng = np.random.default_rng(14)
    soft, offset = np.diag([1.1, 0.9, 1.05]), np.array([12.0, -8.0, 5.0])
    raw, _ = readings(unit_vectors(rng, 200), rng, soft, offset)
    design = np.column_stack([raw, -(raw[:, 1] ** 2), -(raw[:, 2] ** 2), np.ones(len(raw))])
    x = np.linalg.solve(design.T @ design, design.T @ raw[:, 0] ** 2)
    brief_offset = np.array([x[0] / 2, x[1] / (2 * x[3]), x[2] / (2 * x[4])])
    temp = x[5] + brief_offset[0] ** 2 + x[3] * brief_offset[1] ** 2 + x[4] * brief_offset[2] ** 2
    brief_scale = np.sqrt([temp, temp / x[3], temp / x[4]])

    result = fit_calibration(raw, FitOptions(model='axis', field_strength=1.0))
    assert result.success, result.reason
    np.testing.assert_allclose(result.calibration.offset, brief_offset, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(np.diag(result.calibration.matrix), 1.0 / brief_scale, rtol=1e-9)
    matrix = result.calibration.matrix
    assert np.count_nonzero(matrix - np.diag(np.diag(matrix))) == 0


def test_axis_model_does_not_suffer_from_large_offsets():
    """The brief's float32 on raw data fails beyond ~5 F of offset; centred float64 does not."""
    rng = np.random.default_rng(41)
    soft = np.diag([1.1, 0.9, 1.05])
    raw, _ = readings(unit_vectors(rng, 200), rng, soft, np.zeros(3))
    near = fit_calibration(raw, FitOptions(model='axis'))
    far_offset = np.array([5.0, -5.0, 5.0]) * FIELD
    far = fit_calibration(raw + far_offset, FitOptions(model='axis'))
    np.testing.assert_allclose(far.calibration.offset - far_offset, near.calibration.offset,
                               atol=1e-9)  # fmt: skip
    np.testing.assert_allclose(far.calibration.matrix, near.calibration.matrix, rtol=1e-9)


def test_axis_model_has_no_cross_terms_so_full_beats_it_under_soft_iron():
    rng = np.random.default_rng(15)
    soft, offset = soft_iron(rng, off_diagonal=0.15), np.array([100.0, 50.0, -20.0])
    for _ in range(3):
        soft = soft_iron(rng, off_diagonal=0.15)
        if np.abs(soft - np.diag(np.diag(soft))).max() > 0.1:
            break
    directions = unit_vectors(rng, 300)
    raw, _ = readings(directions, rng, soft, offset)
    axis = fit_calibration(raw, FitOptions(model='axis')).calibration
    full = fit_calibration(raw, FitOptions(model='full')).calibration
    assert direction_error_deg(axis, directions, soft, offset) > 1.0
    assert direction_error_deg(full, directions, soft, offset) < 0.1


def test_axis_least_squares_rejects_a_non_ellipsoid():
    rng = np.random.default_rng(16)
    t, z = rng.uniform(0, 2 * np.pi, 300), rng.uniform(-1, 1, 300)
    radius = np.sqrt(1 + z**2)  # hyperboloid of one sheet
    assert axis_least_squares(np.column_stack([radius * np.cos(t), radius * np.sin(t), z])) is None


# ----------------------------------------------------------------------------------------------
# output scale


@pytest.mark.parametrize('field_strength', [None, 1.0, 48.5])
def test_corrected_magnitude_is_the_requested_field_strength(field_strength):
    rng = np.random.default_rng(17)
    soft, offset = soft_iron(rng), np.array([70.0, -20.0, 140.0])
    raw, _ = readings(unit_vectors(rng, 300), rng, soft, offset)
    result = fit_calibration(raw, FitOptions(model='full', field_strength=field_strength))
    magnitude = np.linalg.norm(result.calibration.apply(raw), axis=1)
    expected = field_strength or result.metrics.mean_radius
    assert result.calibration.field_strength == pytest.approx(expected)
    assert np.mean(magnitude) == pytest.approx(expected, rel=2e-3)
    if field_strength is None:  # volume preserved: the fitted radius of the raw ellipsoid
        assert expected == pytest.approx(FIELD * np.cbrt(np.linalg.det(soft)), rel=2e-3)


def test_unit_invariance_tesla_microtesla_counts():
    rng = np.random.default_rng(18)
    soft, offset = soft_iron(rng), np.array([-150.0, 80.0, 60.0])
    raw_ut, _ = readings(unit_vectors(rng, 250), rng, soft, offset, noise=0.5, spikes=0.02)
    results = {
        unit: fit_calibration(raw_ut * factor)
        for unit, factor in (('T', 1e-6), ('uT', 1.0), ('counts', 1 / 0.15))
    }
    reference = results['uT']
    for unit, factor in (('T', 1e-6), ('counts', 1 / 0.15)):
        result = results[unit]
        assert result.success == reference.success
        assert result.metrics.model == reference.metrics.model
        np.testing.assert_array_equal(result.outliers, reference.outliers)
        np.testing.assert_allclose(
            result.calibration.matrix, reference.calibration.matrix, rtol=1e-6
        )
        np.testing.assert_allclose(
            result.calibration.offset, reference.calibration.offset * factor, rtol=1e-6
        )
        assert result.metrics.mean_radius == pytest.approx(reference.metrics.mean_radius * factor)
        assert result.metrics.residual_rms_pct == pytest.approx(reference.metrics.residual_rms_pct)
        assert result.metrics.condition_number == pytest.approx(reference.metrics.condition_number)


# ----------------------------------------------------------------------------------------------
# automatic model choice


def test_auto_picks_sphere_for_a_clean_sphere():
    rng = np.random.default_rng(19)
    raw, _ = readings(unit_vectors(rng, 300), rng, np.eye(3), np.array([5.0, 6.0, 7.0]))
    result = fit_calibration(raw)
    assert result.success, result.reason
    assert result.metrics.model == 'sphere'
    assert result.calibration.model == 'sphere'


def test_auto_picks_full_under_soft_iron():
    rng = np.random.default_rng(20)
    raw, _ = readings(unit_vectors(rng, 300), rng, soft_iron(rng), np.array([5.0, 6.0, 7.0]))
    result = fit_calibration(raw)
    assert result.success, result.reason
    assert result.metrics.model == 'full'
    assert 'BIC' in result.reason


def test_auto_picks_planar_for_a_yawing_robot_even_with_spikes():
    rng = np.random.default_rng(21)
    raw, _ = readings(yaw_directions(rng, 400), rng, soft_iron(rng), np.array([60, -30, 90.0]),
                      spikes=0.02)  # fmt: skip
    result = fit_calibration(raw)
    assert result.success, result.reason
    assert result.metrics.model == 'planar'
    assert result.metrics.unobserved == ('offset_normal', 'matrix_normal')


def test_auto_never_fits_full_to_too_few_samples():
    rng = np.random.default_rng(22)
    raw, _ = readings(unit_vectors(rng, 15), rng, soft_iron(rng), np.zeros(3))
    result = fit_calibration(raw, FitOptions(min_samples=10, min_coverage=0.1))
    assert result.metrics.model == 'sphere'


# ----------------------------------------------------------------------------------------------
# planar


def test_planar_without_prior_gives_heading_and_reports_the_unobserved_terms():
    rng = np.random.default_rng(23)
    soft, offset = soft_iron(rng, off_diagonal=0.05), np.array([110.0, -70.0, 40.0])
    directions = yaw_directions(rng, 300)
    raw, _ = readings(directions, rng, soft, offset)
    result = fit_calibration(raw, FitOptions(model='planar'))
    assert result.success, result.reason
    assert result.metrics.unobserved == ('offset_normal', 'matrix_normal')
    assert result.calibration.metadata['plane_normal'][2] > 0.95
    corrected = result.calibration.apply(FIELD * directions @ soft.T + offset)
    heading_error = np.angle(
        np.exp(1j * (np.arctan2(corrected[:, 1], corrected[:, 0])
                     - np.arctan2(directions[:, 1], directions[:, 0])))
    )  # fmt: skip
    assert np.degrees(np.std(heading_error)) < 0.5
    assert result.metrics.coverage == 1.0  # heading sectors in the plane


@pytest.mark.parametrize('sweep_deg', [100.0, 150.0])
def test_a_short_turn_counts_the_headings_it_swept(sweep_deg):
    """Issue #46 item 9: a robot that turned 100 deg was told 330-340 deg of heading were not yet
    seen: the headings came from the planar fit's ellipse, which a short arc leaves anything
    (here a 7:1 axis ratio, every reading squeezed into a few sectors). The ring's circle
    counts them."""
    rng = np.random.default_rng(25)
    directions = yaw_directions(rng, 300)
    swept = np.radians(sweep_deg) * (rng.uniform(size=300) - 0.5)
    directions[:, 0], directions[:, 1] = (np.hypot(directions[:, 0], directions[:, 1])
                                          * np.array([np.cos(swept), np.sin(swept)]))
    raw, _ = readings(directions, rng, np.eye(3), np.array([55.0, -45.0, 25.0]))
    result = fit_calibration(raw, FitOptions(model='planar'))
    sectors = round(result.metrics.coverage * 36)
    assert abs(sectors * 10 - sweep_deg) <= 20, (sectors, result.metrics.coverage_hint)
    unseen = int(re.search(r'(\d+)° of heading not yet seen', result.metrics.coverage_hint)[1])
    assert abs(unseen - (360 - sweep_deg)) <= 20, result.metrics.coverage_hint


def test_planar_with_prior_keeps_the_vertical_and_corrects_heading():
    rng = np.random.default_rng(24)
    soft, offset = soft_iron(rng), np.array([110.0, -70.0, 40.0])
    directions = yaw_directions(rng, 300)
    raw, _ = readings(directions, rng, soft, offset)
    # a prior from an earlier full calibration, with the in-plane offset since drifted by 3 µT
    prior = Calibration(offset + [3.0, -2.0, 0.0], np.linalg.inv(soft), FIELD)
    result = fit_calibration(raw, FitOptions(model='planar', prior=prior, field_strength=FIELD))
    assert result.success, result.reason
    assert direction_error_deg(prior, directions, soft, offset) > 2.0
    assert direction_error_deg(result.calibration, directions, soft, offset) < 0.3


def test_planar_data_fail_3d_models_with_advice():
    rng = np.random.default_rng(25)
    raw, _ = readings(yaw_directions(rng, 300), rng, soft_iron(rng), np.zeros(3))
    for model in ('full', 'sphere', 'axis'):
        result = fit_calibration(raw, FitOptions(model=model))
        assert not result.success
        assert 'near one plane' in result.reason and 'planar' in result.reason
        assert 'roll axis (x)' in result.reason or 'pitch axis (y)' in result.reason
        assert_all_finite(result)


# ----------------------------------------------------------------------------------------------
# gates: each one fails on data made to trip it, with advice


def test_gate_too_few_samples():
    rng = np.random.default_rng(26)
    raw, _ = readings(unit_vectors(rng, 20), rng, np.eye(3), np.zeros(3))
    result = fit_calibration(raw, FitOptions(model='sphere', min_coverage=0.0))
    assert not result.success
    assert 'too few samples: 20, need at least 30' in result.reason
    assert result.calibration is not None  # best effort all the same
    assert fit_calibration(raw, FitOptions(model='sphere', min_samples=20, min_coverage=0)).success


def test_gate_fewer_samples_than_parameters_fits_nothing():
    result = fit_calibration(
        np.array([[1.0, 2, 3], [2, 3, 1], [3, 1, 2]]), FitOptions(model='full')
    )
    assert not result.success and result.calibration is None
    assert 'too few samples: 3' in result.reason
    assert_all_finite(result)


def test_gate_coverage_names_the_missing_rotation():
    rng = np.random.default_rng(27)
    directions = unit_vectors(rng, 3000)
    cap = directions[directions[:, 2] > 0.5][:300]
    result = fit_calibration(FIELD * cap + [20.0, 0, 0], FitOptions(model='sphere'))
    assert not result.success
    assert 'coverage' in result.reason
    assert 'keep rotating about the roll axis (x) and the pitch axis (y)' in result.reason
    assert '-z' in result.reason
    assert result.metrics.coverage < 0.5
    assert result.metrics.coverage_hint in result.reason


def test_gate_ill_conditioning():
    rng = np.random.default_rng(28)
    raw, _ = readings(unit_vectors(rng, 300), rng, soft_iron(rng), np.zeros(3))
    assert fit_calibration(raw, FitOptions(model='full')).success
    result = fit_calibration(raw, FitOptions(model='full', max_condition=1.5))
    assert not result.success
    assert 'ill-conditioned' in result.reason
    assert result.metrics.condition_number > 1.5


def test_gate_ill_conditioning_on_a_narrow_band():
    """A band of tilts within ±5° of one plane does not determine a full ellipsoid."""
    rng = np.random.default_rng(29)
    directions = yaw_directions(rng, 400)
    tilt = np.radians(rng.uniform(-5, 5, 400))
    directions[:, 2] += tilt
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    raw, _ = readings(directions, rng, soft_iron(rng), np.zeros(3))
    result = fit_calibration(raw, FitOptions(model='full', planar_thickness=0.0))
    assert not result.success
    assert 'ill-conditioned' in result.reason


def test_gate_axis_ratio():
    rng = np.random.default_rng(30)
    raw, _ = readings(unit_vectors(rng, 300), rng, np.diag([2.6, 1.0, 1.0]), np.zeros(3))
    result = fit_calibration(raw, FitOptions(model='full'))
    assert not result.success
    assert 'axis ratio 2.6 exceeds 2' in result.reason
    assert result.metrics.axis_ratio == pytest.approx(2.6, rel=0.01)
    assert fit_calibration(raw, FitOptions(model='full', max_axis_ratio=3.0)).success


def test_gate_residual():
    rng = np.random.default_rng(31)
    raw, _ = readings(unit_vectors(rng, 300), rng, np.eye(3), np.zeros(3), noise=5.0)
    result = fit_calibration(raw, FitOptions(model='full'))
    assert not result.success
    assert 'residual' in result.reason and 'exceeds 5.00 %' in result.reason
    assert result.metrics.residual_rms_pct > 5.0


def test_gate_not_an_ellipsoid():
    """Readings on a hyperboloid: never a calibration that passes, never an indefinite matrix."""
    rng = np.random.default_rng(32)
    t, z = rng.uniform(0, 2 * np.pi, 300), rng.uniform(-1, 1, 300)
    radius = np.sqrt(1 + z**2)
    raw = FIELD * np.column_stack([radius * np.cos(t), radius * np.sin(t), z]) + 100.0
    for model in ('full', 'axis', 'sphere', 'auto'):
        result = fit_calibration(raw, FitOptions(model=model))
        assert not result.success
        assert_all_finite(result)
        if result.calibration is not None:
            assert np.linalg.eigvalsh(result.calibration.matrix).min() > 0


def test_every_reason_is_joined_when_several_gates_fail():
    rng = np.random.default_rng(33)
    raw, _ = readings(yaw_directions(rng, 20), rng, np.eye(3), np.zeros(3), noise=4.0)
    result = fit_calibration(raw, FitOptions(model='full'))
    assert not result.success
    assert result.reason.count(';') >= 2
    assert 'too few samples' in result.reason and 'coverage' in result.reason


# ----------------------------------------------------------------------------------------------
# bad input never raises and never yields NaN/Inf


@pytest.mark.parametrize(
    ('samples', 'expected'),
    [
        (np.full((40, 3), np.nan), 'all 40 rows contain NaN or Inf'),
        (np.full((40, 3), np.inf), 'all 40 rows contain NaN or Inf'),
        (np.zeros((40, 3)), 'identical'),
        (np.tile([12.0, -3.0, 40.0], (40, 1)), 'identical'),
        ([], 'no samples'),
        (np.ones((10, 2)), 'shape (10, 2)'),
        ([['a', 'b', 'c']], 'not numbers'),
        (None, 'shape ()'),
        (np.outer(np.linspace(-1, 1, 100), [1.0, 2.0, 3.0]), 'rotate'),
    ],
)
def test_unusable_input(samples, expected):
    for model in ('auto', 'full', 'sphere', 'axis', 'planar'):
        result = fit_calibration(samples, FitOptions(model=model))
        assert not result.success
        assert expected in result.reason
        assert isinstance(result.metrics, FitMetrics)
        assert_all_finite(result)


def test_non_finite_rows_are_dropped_counted_and_marked():
    rng = np.random.default_rng(34)
    raw, _ = readings(unit_vectors(rng, 300), rng, soft_iron(rng), np.array([40.0, 0, 0]))
    clean = fit_calibration(raw, FitOptions(model='full'))
    dirty = np.vstack([raw, [[np.nan, 1, 2], [np.inf, 0, 0], [1, -np.inf, 3]]])
    result = fit_calibration(dirty, FitOptions(model='full'))
    assert result.success, result.reason
    assert result.metrics.n_non_finite == 3
    assert result.metrics.n_samples == 300
    assert '3 rows with NaN/Inf dropped' in result.reason
    assert result.outliers.shape == (303,) and result.outliers[-3:].all()
    np.testing.assert_allclose(result.calibration.offset, clean.calibration.offset)


def test_zero_components_are_legitimate_readings():
    rng = np.random.default_rng(35)
    raw, _ = readings(unit_vectors(rng, 300), rng, np.eye(3), np.zeros(3))
    raw[::10, 0] = 0.0
    raw[5::10, 2] = 0.0
    result = fit_calibration(raw, FitOptions(model='sphere', max_residual_pct=50))
    assert result.metrics.n_samples == 300


@pytest.mark.parametrize('scale', [1e-300, 1e-9, 1e9, 1e300])
def test_extreme_scales_fit_alike(scale):
    rng = np.random.default_rng(36)
    soft, offset = soft_iron(rng), np.array([100.0, 40.0, -60.0])
    raw, _ = readings(unit_vectors(rng, 200), rng, soft, offset)
    reference = fit_calibration(raw, FitOptions(model='full'))
    result = fit_calibration(raw / FIELD * scale, FitOptions(model='full'))
    assert result.success, result.reason
    np.testing.assert_allclose(result.calibration.matrix, reference.calibration.matrix, rtol=1e-6)
    assert_all_finite(result)


@pytest.mark.parametrize('model', ['auto', 'full', 'sphere', 'axis', 'planar'])
def test_values_beyond_any_unit_fail_with_that_reason_and_no_warning(model):
    rng = np.random.default_rng(37)
    raw, _ = readings(unit_vectors(rng, 200), rng, np.eye(3), np.zeros(3))
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        result = fit_calibration(raw / FIELD * 1.7e308, FitOptions(model=model))
    assert not result.success and result.calibration is None
    assert 'beyond' in result.reason and 'identical' not in result.reason
    assert_all_finite(result)


def test_invalid_options_are_rejected_with_every_problem():
    with pytest.raises(ValueError, match='model must be one of') as error:
        FitOptions(model='ellipse', field_strength=-1.0, min_coverage=2.0, max_axis_ratio=0.5)
    message = str(error.value)
    assert 'field_strength' in message and 'min_coverage' in message
    assert 'max_axis_ratio' in message


def test_metrics_as_dict_is_plain_json():
    rng = np.random.default_rng(37)
    raw, _ = readings(unit_vectors(rng, 200), rng, soft_iron(rng), np.zeros(3))
    result = fit_calibration(raw)
    data = json.loads(json.dumps(result.metrics.as_dict(), allow_nan=False))
    assert data['model'] == result.metrics.model
    assert isinstance(data['unobserved'], list)
    assert set(data) >= {
        'model', 'n_samples', 'n_inliers', 'residual_rms_pct', 'residual_max_pct', 'coverage',
        'condition_number', 'outlier_count', 'mean_radius', 'axis_ratio', 'parameter_std',
        'unobserved',
    }  # fmt: skip
    metadata = result.calibration.metadata
    assert metadata['residual_rms_pct'] == result.metrics.residual_rms_pct
    assert metadata['coverage'] == result.metrics.coverage
    assert metadata['samples'] == result.metrics.n_inliers


# ----------------------------------------------------------------------------------------------
# property: random ellipsoids, offsets up to ±5 F, soft iron with off-diagonals up to 0.15, noise
# and a few % of spikes, in any unit


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**32 - 1),
    offset_in_fields=st.lists(st.floats(-5.0, 5.0), min_size=3, max_size=3),
    off_diagonal=st.floats(0.0, 0.15),
    spikes=st.floats(0.0, 0.03),
    unit_exponent=st.integers(-7, 4),
)
def test_random_ellipsoids_are_recovered(
    seed, offset_in_fields, off_diagonal, spikes, unit_exponent
):
    rng = np.random.default_rng(seed)
    field = 10.0**unit_exponent * rng.uniform(1.0, 9.0)
    soft = soft_iron(rng, off_diagonal=off_diagonal)
    offset = np.asarray(offset_in_fields) * field
    directions = unit_vectors(rng, 300)
    raw, spiked = readings(
        directions, rng, soft, offset, noise=0.005 * field, spikes=spikes, field=field
    )
    result = fit_calibration(raw, FitOptions(model='full'))
    assert result.success, result.reason
    assert_all_finite(result)
    assert np.linalg.norm(result.calibration.offset - offset) < 0.01 * field
    assert direction_error_deg(result.calibration, directions, soft, offset, field) < 0.3
    assert set(spiked) <= set(np.flatnonzero(result.outliers))
    assert result.metrics.residual_rms_pct < 1.0


# ----------------------------------------------------------------------------------------------
# harder data


def test_planar_with_prior_explains_tilts_taken_while_turning():
    """±5° of tilt at 60° inclination changes the horizontal field by ~±9 %; not an error."""
    rng = np.random.default_rng(38)
    soft, offset = soft_iron(rng), np.array([-40.0, 90.0, 20.0])
    heading = rng.uniform(0, 2 * np.pi, 400)
    inclination = np.radians(60.0 + rng.uniform(-5.0, 5.0, 400))
    directions = np.column_stack(
        [np.cos(inclination) * np.cos(heading), np.cos(inclination) * np.sin(heading),
         -np.sin(inclination)]
    )  # fmt: skip
    raw, _ = readings(directions, rng, soft, offset)
    prior = Calibration(offset + [2.0, 3.0, 0.0], np.linalg.inv(soft) * 1e3, FIELD * 1e3)
    result = fit_calibration(raw, FitOptions(model='planar', prior=prior))
    assert result.success, result.reason
    assert result.metrics.residual_rms_pct < 1.0  # the noise, not the tilts
    assert direction_error_deg(result.calibration, directions, soft, offset) < 0.3
    flat = fit_calibration(raw, FitOptions(model='planar'))
    # without a prior the tilts determine the offset along the normal: no longer counted as error
    assert flat.success, flat.reason
    assert flat.metrics.residual_rms_pct < 1.0
    assert flat.metrics.unobserved == ('matrix_normal',)
    corrected = flat.calibration.apply(FIELD * directions @ soft.T + offset)
    vertical_error = corrected[:, 2] / np.linalg.norm(corrected, axis=1) - directions[:, 2]
    assert np.sqrt(np.mean(vertical_error**2)) < 0.15  # at the held normal scale


def test_a_quarter_of_spikes_is_survived():
    """A buffer that keeps far-out samples can hold this many spikes (0.3-2 F, any direction)."""
    rng = np.random.default_rng(39)
    soft, offset = soft_iron(rng), np.array([280.0, -120.0, 60.0])
    directions = unit_vectors(rng, 100)
    raw, _ = readings(directions, rng, soft, offset, noise=0.5)
    spiked = rng.choice(100, 25, replace=False)
    kicks = rng.normal(size=(25, 3))
    kicks *= rng.uniform(0.3, 2.0, (25, 1)) * FIELD / np.linalg.norm(kicks, axis=1, keepdims=True)
    raw[spiked] += kicks
    result = fit_calibration(raw, FitOptions(model='full'))
    assert result.success, result.reason
    assert direction_error_deg(result.calibration, directions, soft, offset) < 0.6
    # a spike along the sphere's surface is invisible (and harmless); any 10 sigma off it is caught
    radial = np.abs(np.linalg.norm((raw - offset) @ np.linalg.inv(soft).T, axis=1) / FIELD - 1)
    assert set(np.flatnonzero(radial > 0.1)) <= set(np.flatnonzero(result.outliers))
    assert result.metrics.outlier_count <= 25


def test_a_hemisphere_does_not_determine_a_full_ellipsoid():
    rng = np.random.default_rng(40)
    directions = unit_vectors(rng, 3000)
    upper = directions[directions[:, 2] > 0.0][:300]
    raw, _ = readings(upper, rng, soft_iron(rng), np.array([50.0, 0.0, 0.0]))
    full = fit_calibration(raw, FitOptions(model='full'))
    assert not full.success
    assert 'ill-conditioned' in full.reason
    assert fit_calibration(raw).metrics.model != 'full'


# ----------------------------------------------------------------------------------------------
# weights (SampleBuffer's counts: a point that averages n readings)


def averaged_points(rng, soft, offset, n=120, noise=0.5, max_count=60):
    """Points that each average 1 or ``max_count`` readings: noise shrinks by sqrt(count)."""
    directions = unit_vectors(rng, n)
    counts = rng.choice([1.0, float(max_count)], n)
    raw = FIELD * directions @ soft.T + offset
    raw += rng.normal(0.0, noise, raw.shape) / np.sqrt(counts)[:, None]
    return raw, counts, directions


@pytest.mark.parametrize('model', ['sphere', 'axis', 'full', 'planar', 'auto'])
def test_unit_weights_change_nothing(model):
    rng = np.random.default_rng(41)
    soft, offset = soft_iron(rng), np.array([80.0, -20.0, 140.0])
    directions = yaw_directions(rng, 200) if model == 'planar' else unit_vectors(rng, 200)
    # the axis model is the brief's plain least squares: spikes would leave nothing to compare
    raw, _ = readings(directions, rng, soft, offset, spikes=0.0 if model == 'axis' else 0.02)
    plain = fit_calibration(raw, FitOptions(model=model))
    weighted = fit_calibration(raw, FitOptions(model=model), weights=np.ones(len(raw)))
    assert weighted.success == plain.success and weighted.reason == plain.reason
    np.testing.assert_allclose(weighted.calibration.offset, plain.calibration.offset, rtol=1e-9)
    np.testing.assert_allclose(weighted.calibration.matrix, plain.calibration.matrix, rtol=1e-9)
    np.testing.assert_array_equal(weighted.outliers, plain.outliers)


def test_integer_weights_equal_repeated_rows():
    rng = np.random.default_rng(42)
    soft, offset = soft_iron(rng), np.array([-150.0, 60.0, 30.0])
    raw, _ = readings(unit_vectors(rng, 150), rng, soft, offset, noise=0.2)
    counts = rng.integers(1, 8, len(raw))
    weighted = fit_calibration(raw, FitOptions(model='full'), weights=counts)
    repeated = fit_calibration(np.repeat(raw, counts, axis=0), FitOptions(model='full'))
    assert weighted.success and repeated.success
    assert weighted.metrics.outlier_count == repeated.metrics.outlier_count == 0
    np.testing.assert_allclose(weighted.calibration.offset, repeated.calibration.offset,
                               rtol=1e-6)
    np.testing.assert_allclose(weighted.calibration.matrix, repeated.calibration.matrix,
                               rtol=1e-6)


def test_weights_make_averaged_points_count():
    """Points of very different precision: weighting by counts is markedly more accurate."""
    errors = {'plain': [], 'weighted': []}
    for seed in range(6):
        rng = np.random.default_rng(100 + seed)
        soft, offset = soft_iron(rng), rng.uniform(-200.0, 200.0, 3)
        raw, counts, directions = averaged_points(rng, soft, offset, noise=1.0)
        plain = fit_calibration(raw, FitOptions(model='full'))
        weighted = fit_calibration(raw, FitOptions(model='full'), weights=counts)
        assert weighted.success, weighted.reason
        errors['plain'].append(direction_error_deg(plain.calibration, directions, soft, offset))
        errors['weighted'].append(
            direction_error_deg(weighted.calibration, directions, soft, offset)
        )
    assert np.mean(errors['weighted']) < 0.7 * np.mean(errors['plain'])


def test_weighted_outliers_are_judged_against_one_readings_noise():
    """A lone spike is flagged; a heavily averaged point off by less than one reading's noise
    allows is not (its weight says how well it is known, not that the model must fit it)."""
    rng = np.random.default_rng(43)
    soft, offset = soft_iron(rng), np.array([20.0, 50.0, -90.0])
    raw, counts, _ = averaged_points(rng, soft, offset, noise=0.5, max_count=1)
    radius = FIELD * soft @ unit_vectors(rng, 2).T  # two more points, 2 % and 25 % off
    heavy = offset + 1.02 * radius[:, 0]
    spike = offset + 1.25 * radius[:, 1]
    samples = np.vstack([raw, heavy, spike])
    weights = np.append(counts, [50.0, 1.0])
    result = fit_calibration(samples, FitOptions(model='full'), weights=weights)
    assert result.success, result.reason
    assert result.outliers[-1] and not result.outliers[-2]
    assert result.metrics.outlier_count == 1


@pytest.mark.parametrize(
    ('weights', 'message'),
    [
        (np.ones(5), 'shape'),
        (-np.ones(60), '> 0'),
        (np.zeros(60), '> 0'),
        (np.full(60, np.nan), 'finite'),
        (['a'] * 60, 'not numbers'),
    ],
)
def test_bad_weights_fail_clearly_without_raising(weights, message):
    rng = np.random.default_rng(44)
    raw, _ = readings(unit_vectors(rng, 60), rng, np.eye(3), np.zeros(3))
    result = fit_calibration(raw, FitOptions(model='full'), weights=weights)
    assert not result.success and result.calibration is None
    assert 'weights' in result.reason and message in result.reason
    assert_all_finite(result)


def test_weights_of_non_finite_rows_are_dropped_with_them():
    rng = np.random.default_rng(45)
    soft, offset = soft_iron(rng), np.array([10.0, 20.0, 30.0])
    raw, counts, _ = averaged_points(rng, soft, offset)
    raw[[3, 7]] = np.nan
    result = fit_calibration(raw, FitOptions(model='full'), weights=counts)
    assert result.success, result.reason
    assert result.metrics.n_non_finite == 2 and result.outliers[3] and result.outliers[7]


def test_too_simple_model_fails_on_residual_not_on_coverage():
    # Rotated soft iron that the axis-aligned model cannot represent: the data cover the sphere,
    # so the honest reason is the residual (model error), never "rotate the sensor".
    from mag_calibrator_ros.sim.motion import body_field_samples

    truth = body_field_samples('tumble', 3000, 50.0, 50.0, 60.0, seed=3)
    soft_iron = np.array([[1.1, 0.15, -0.15], [0.15, 0.9, 0.15], [-0.15, 0.15, 1.05]])
    noise = np.random.default_rng(0).normal(0.0, 0.5, truth.shape)
    raw = truth @ soft_iron.T + np.array([200.0, -150.0, 90.0]) + noise
    result = fit_calibration(raw, FitOptions(model='axis'))
    assert not result.success
    assert 'residual' in result.reason
    assert 'rotat' not in result.reason
    assert result.metrics.coverage > 0.8


# ----------------------------------------------------------------------------------------------
# planar on a robot that tilts while turning (every real floor tilts it a few degrees)


def tilted_yaw_directions(rng, n, inclination_deg, tilt_deg=(2.0, 4.0)):
    """Body-frame field of a robot at random headings tilted 2-4° in a random direction."""
    from scipy.spatial.transform import Rotation

    inclination = np.radians(inclination_deg)
    world = np.array([np.cos(inclination), 0.0, -np.sin(inclination)])
    tilt = np.radians(rng.uniform(*tilt_deg, n))
    direction = rng.uniform(0.0, 2.0 * np.pi, n)
    attitude = Rotation.from_euler(
        'ZYX', np.column_stack([rng.uniform(0, 2 * np.pi, n), tilt * np.cos(direction),
                                tilt * np.sin(direction)])
    )  # fmt: skip
    return attitude.inv().apply(world)


def heading_errors_deg(calibration, directions, soft, offset):
    """Heading (angle in the body x-y plane) of corrected noise-free readings minus the truth's."""
    corrected = calibration.apply(FIELD * directions @ soft.T + offset)
    return np.degrees(np.angle(np.exp(1j * (
        np.arctan2(corrected[:, 1], corrected[:, 0])
        - np.arctan2(directions[:, 1], directions[:, 0])
    ))))  # fmt: skip


@pytest.mark.parametrize('inclination', [30.0, 60.0, 70.0])
@pytest.mark.parametrize('offset', [[110.0, -70.0, 40.0], [-150.0, 220.0, -180.0]])
def test_planar_calibrates_a_tilting_robot_at_any_inclination(inclination, offset):
    """A 2-D fit sees the tilts as 2-9 % radius changes (tan(inclination) x tilt); in 3-D they are
    no error, and the offset along the normal becomes observable."""
    rng = np.random.default_rng(int(inclination) + abs(int(offset[0])))
    soft, offset = soft_iron(rng), np.array(offset)
    directions = tilted_yaw_directions(rng, 200, inclination)
    raw, _ = readings(directions, rng, soft, offset)
    result = fit_calibration(raw, FitOptions(model='planar', field_strength=FIELD))
    assert result.success, result.reason
    assert result.metrics.residual_rms_pct < 1.5  # noise 0.25 µT is 0.5 %
    assert result.metrics.unobserved == ('matrix_normal',)
    assert result.metrics.parameter_std['offset_normal'][0] < 0.05 * FIELD
    errors = heading_errors_deg(result.calibration, directions, soft, offset)
    assert np.sqrt(np.mean(errors**2)) < 1.0 and np.max(np.abs(errors)) < 2.5
    corrected = result.calibration.apply(FIELD * directions @ soft.T + offset)
    vertical_error = corrected[:, 2] - FIELD * directions[:, 2]
    assert np.sqrt(np.mean(vertical_error**2)) < 0.15 * FIELD  # at the held normal scale


def test_planar_recovers_the_normal_offset_when_the_held_terms_are_right():
    """Soft iron with the normal scale equal to the in-plane one and no cross terms (what the
    fit holds): the tilts then give the offset along the normal to a few % of the field."""
    rng = np.random.default_rng(61)
    soft = np.diag([1.1, 0.9, np.sqrt(0.99)])
    soft[0, 1] = soft[1, 0] = 0.08
    soft[2, 2] = np.sqrt(np.linalg.det(soft[:2, :2]))
    offset = np.array([90.0, -140.0, 160.0])
    for inclination in (30.0, 70.0):
        directions = tilted_yaw_directions(rng, 200, inclination)
        raw, _ = readings(directions, rng, soft, offset)
        flat = fit_calibration(raw, FitOptions(model='planar', planar_thickness=0.0))
        result = fit_calibration(raw, FitOptions(model='planar', field_strength=FIELD))
        assert result.success, result.reason
        assert result.metrics.unobserved == ('matrix_normal',)
        assert abs(result.calibration.offset[2] - offset[2]) < 0.03 * FIELD, inclination
        assert flat.metrics.model == 'planar'


@pytest.mark.parametrize('seed', range(5))
def test_a_level_ring_never_frees_the_normal_offset(seed):
    """Without tilts the normal reading is noise: regressing on it would 'determine' an offset
    from nothing, so the fit keeps the 2-D ellipse and reports the offset unobserved."""
    rng = np.random.default_rng(70 + seed)
    soft, offset = soft_iron(rng), np.array([60.0, -30.0, 90.0])
    directions = yaw_directions(rng, 200, inclination_deg=rng.uniform(20.0, 75.0))
    raw, _ = readings(directions, rng, soft, offset, noise=0.5)
    result = fit_calibration(raw, FitOptions(model='planar'))
    assert result.success, result.reason
    assert result.metrics.unobserved == ('offset_normal', 'matrix_normal')
    assert 'offset_normal' not in result.metrics.parameter_std


def test_a_still_sensor_fails_planar_with_the_rotate_reason():
    rng = np.random.default_rng(62)
    raw = np.array([20.0, -30.0, 40.0]) + rng.normal(0.0, 0.3, (200, 3))
    result = fit_calibration(raw, FitOptions(model='planar'))
    assert not result.success
    assert 'rotate' in result.reason or 'turn' in result.reason
    assert 'tilts while turning' not in result.reason


def test_an_unexplained_tilt_is_named_as_the_cause(monkeypatch):
    """When the offset along the normal is not fitted, tilts at 70° leave a residual that follows
    the normal reading: the reason says so instead of blaming disturbance or noise."""
    from mag_calibrator_ros.calibration.fit import ellipsoid

    monkeypatch.setattr(ellipsoid, 'TILT_EVIDENCE', np.inf)  # the 2-D fit, as before
    rng = np.random.default_rng(63)
    soft, offset = soft_iron(rng), np.array([110.0, -70.0, 40.0])
    directions = tilted_yaw_directions(rng, 200, 70.0, tilt_deg=(3.0, 5.0))
    raw, _ = readings(directions, rng, soft, offset)
    result = fit_calibration(raw, FitOptions(model='planar'))
    assert not result.success
    assert result.metrics.unobserved == ('offset_normal', 'matrix_normal')
    assert 'tilts while turning' in result.reason
    assert 'disturbed' not in result.reason


def test_a_disturbed_planar_fit_still_blames_the_disturbance():
    rng = np.random.default_rng(64)
    soft, offset = soft_iron(rng), np.array([110.0, -70.0, 40.0])
    directions = yaw_directions(rng, 300)
    raw, _ = readings(directions, rng, soft, offset)
    raw[:, :2] += 3.0 * np.sin(np.linspace(0.0, 12.0, len(raw)))[:, None]  # passing iron
    result = fit_calibration(raw, FitOptions(model='planar'))
    assert not result.success
    assert 'disturbed' in result.reason and 'tilts while turning' not in result.reason
