# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""OnlineTracker: the notebook's gradient descent on the full model, safe and bounded."""

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
import pytest

from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.calibration.live.tracker import OnlineTracker, TrackerHealth
from mag_calibrator_ros.sim.motion import body_field_samples

FIELD = 50.0  # µT
SOFT_IRON = np.array([[1.08, 0.12, -0.05], [0.12, 0.93, 0.04], [-0.05, 0.04, 1.02]])
RULES = [False, True]  # normalise_input: the notebook's raw rule and its normalised one


def hand_tumble(hard_iron, seed=0, n=3000, noise=0.5):
    """(raw, noise-free reading, true field): a minute of smooth hand rotation at 50 Hz."""
    truth = body_field_samples('tumble', n, 50.0, FIELD, 60.0, seed)
    reading = truth @ SOFT_IRON.T + np.asarray(hard_iron)
    raw = reading + np.random.default_rng(seed).normal(0.0, noise, truth.shape)
    return raw, reading, truth


def direction_error_rms_deg(calibration, reading, truth):
    corrected = calibration.apply(reading)
    cross = np.linalg.norm(np.cross(corrected, truth), axis=1)
    dot = np.einsum('ij,ij->i', corrected, truth)
    return float(np.sqrt(np.mean(np.degrees(np.arctan2(cross, dot)) ** 2)))


def ideal_calibration(hard_iron):
    return Calibration(np.asarray(hard_iron), np.linalg.inv(SOFT_IRON), FIELD)


def assert_valid_state(tracker):
    calibration = tracker.calibration
    assert np.all(np.isfinite(calibration.offset)) and np.all(np.isfinite(calibration.matrix))
    np.testing.assert_allclose(calibration.matrix, calibration.matrix.T, atol=1e-12)
    assert np.linalg.eigvalsh(calibration.matrix).min() > 0.0


# -- convergence ----------------------------------------------------------------------------------


@pytest.mark.parametrize('normalise_input', RULES)
@pytest.mark.parametrize('hard_iron', [[20.0, -15.0, 10.0], [250.0, -150.0, 60.0]])
def test_converges_from_identity(normalise_input, hard_iron):
    """Offsets up to six fields, soft iron with cross terms, from no calibration at all."""
    raw, reading, truth = hand_tumble(hard_iron, seed=1)
    tracker = OnlineTracker(Calibration.identity(FIELD), normalise_input=normalise_input)
    start_error = direction_error_rms_deg(tracker.calibration, reading, truth)
    for _ in range(3):
        assert tracker.update_many(raw) == len(raw)
    assert start_error > 10.0
    assert direction_error_rms_deg(tracker.calibration, reading, truth) < 0.3
    np.testing.assert_allclose(tracker.calibration.offset, hard_iron, atol=1.0)
    health = tracker.health
    assert isinstance(health, TrackerHealth)
    assert health.converged and health.rms_error < 0.02
    assert (health.steps, health.skipped, health.refused_steps) == (9000, 0, 0)
    assert tracker.calibration.model == 'full'
    assert_valid_state(tracker)


@pytest.mark.parametrize('normalise_input', RULES)
def test_converges_from_a_perturbed_calibration(normalise_input):
    hard_iron = np.array([120.0, 40.0, -80.0])
    raw, reading, truth = hand_tumble(hard_iron, seed=2)
    ideal = ideal_calibration(hard_iron)
    tilt = np.array([[0.0, 0.08, 0.0], [0.08, 0.0, -0.05], [0.0, -0.05, 0.1]])
    warp = np.eye(3) + tilt  # symmetric: a rotation would be invisible to a magnitude loss
    start = Calibration(hard_iron + [12.0, -10.0, 8.0], warp @ ideal.matrix @ warp, FIELD)
    tracker = OnlineTracker(start, normalise_input=normalise_input)
    start_error = direction_error_rms_deg(start, reading, truth)
    tracker.update_many(raw)
    tracker.update_many(raw)
    final_error = direction_error_rms_deg(tracker.calibration, reading, truth)
    assert start_error > 3.0 and final_error < 0.3
    assert np.linalg.norm(tracker.calibration.offset - hard_iron) < 1.0
    assert tracker.health.converged


def test_starting_from_a_good_fit_it_stays_good():
    hard_iron = [60.0, -30.0, 15.0]
    raw, reading, truth = hand_tumble(hard_iron, seed=3)
    tracker = OnlineTracker(ideal_calibration(hard_iron))
    tracker.update_many(raw)
    assert direction_error_rms_deg(tracker.calibration, reading, truth) < 0.2
    assert tracker.health.converged


def test_follows_slow_hard_iron_drift():
    """A tenth of the field of offset drift over two minutes (a warming motor mount, say)."""
    start_offset = np.array([60.0, -30.0, 15.0])
    raw, _, truth = hand_tumble(start_offset, seed=4, n=6000)
    drift = np.linspace(0.0, 1.0, len(raw))[:, None] * np.array([5.0, -3.0, 2.0])
    tracker = OnlineTracker(ideal_calibration(start_offset))
    tracker.update_many(raw + drift)
    np.testing.assert_allclose(tracker.calibration.offset, start_offset + drift[-1], atol=0.6)


def test_identity_in_the_wrong_units_is_rescaled_from_the_first_sample():
    """Identity with F = 1 on µT data: the notebook's norm-from-the-first-sample trick."""
    hard_iron = [20.0, -15.0, 10.0]
    raw, reading, truth = hand_tumble(hard_iron, seed=5)
    tracker = OnlineTracker(Calibration.identity(1.0))
    for _ in range(3):
        tracker.update_many(raw)
    assert tracker.health.rescaled
    assert direction_error_rms_deg(tracker.calibration, reading, truth) < 0.3
    magnitudes = np.linalg.norm(tracker.calibration.apply(reading), axis=1)
    assert magnitudes.mean() == pytest.approx(1.0, rel=0.01)  # normalised, as F = 1 asks


@pytest.mark.parametrize('normalise_input', RULES)
def test_the_rate_is_unit_free(normalise_input):
    raw, _, _ = hand_tumble([40.0, 10.0, -25.0], seed=6, n=1000)
    in_microtesla = OnlineTracker(Calibration.identity(FIELD), normalise_input=normalise_input)
    in_tesla = OnlineTracker(Calibration.identity(FIELD * 1e-6), normalise_input=normalise_input)
    in_microtesla.update_many(raw)
    in_tesla.update_many(raw * 1e-6)
    np.testing.assert_allclose(
        in_tesla.calibration.offset, in_microtesla.calibration.offset * 1e-6, rtol=1e-9
    )
    np.testing.assert_allclose(
        in_tesla.calibration.matrix, in_microtesla.calibration.matrix, rtol=1e-9
    )


def test_real_recording_from_identity(shared_data):
    """LSM303DLHC counts (jremington): the author's Magneto fit leaves ~0.6 % magnitude spread."""
    samples = np.loadtxt(shared_data / 'lsm303dlhc-altimu10v3' / 'mag_2.csv', delimiter=',')
    tracker = OnlineTracker(Calibration.identity(600.0))
    for _ in range(10):  # 301 rows: the notebook's epochs
        tracker.update_many(samples)
    magnitudes = np.linalg.norm(tracker.calibration.apply(samples), axis=1)
    assert 100.0 * magnitudes.std() / magnitudes.mean() < 1.0
    np.testing.assert_allclose(
        tracker.calibration.offset, [53.6, -43.7, 43.9], atol=3.0  # the author's Magneto offset
    )


# -- safety ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    'bad',
    [[np.nan, 1.0, 2.0], [np.inf, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 2.0], 'garbage', None],
)
def test_bad_samples_are_skipped_without_touching_the_state(bad):
    hard_iron = [60.0, -30.0, 15.0]
    tracker = OnlineTracker(ideal_calibration(hard_iron))
    tracker.update_many(hand_tumble(hard_iron, n=300)[0])
    before = tracker.calibration
    health = tracker.health
    assert tracker.update(bad) is False
    after = tracker.calibration
    np.testing.assert_array_equal(after.offset, before.offset)
    np.testing.assert_array_equal(after.matrix, before.matrix)
    assert tracker.health.skipped == health.skipped + 1
    assert tracker.health.steps == health.steps


def test_a_sample_at_the_corrected_origin_is_skipped():
    tracker = OnlineTracker(ideal_calibration([60.0, -30.0, 15.0]))
    assert tracker.update([60.0, -30.0, 15.0]) is False


@pytest.mark.parametrize('normalise_input', RULES)
def test_every_step_is_bounded(normalise_input):
    hard_iron = np.array([60.0, -30.0, 15.0])
    max_step = 0.01
    tracker = OnlineTracker(
        ideal_calibration(hard_iron), learning_rate=0.5, normalise_input=normalise_input,
        max_step=max_step,
    )
    scale = FIELD / np.linalg.det(np.linalg.inv(SOFT_IRON)) ** (1.0 / 3.0)  # radius, input units
    spikes = hard_iron + np.random.default_rng(7).normal(size=(200, 3)) * 20.0 * FIELD
    for spike in spikes:
        before = tracker.calibration
        tracker.update(spike)
        after = tracker.calibration
        assert np.linalg.norm(after.offset - before.offset) <= max_step * scale * (1 + 1e-9)
        internal_before = before.matrix * scale / FIELD
        internal_after = after.matrix * scale / FIELD
        assert np.linalg.norm(internal_after - internal_before) <= max_step * (1 + 1e-9)
        assert tracker.health.last_step <= np.sqrt(2.0) * max_step * (1 + 1e-9)
    assert_valid_state(tracker)


def test_spikes_do_not_derail_it():
    hard_iron = np.array([60.0, -30.0, 15.0])
    raw, reading, truth = hand_tumble(hard_iron, seed=8)
    rng = np.random.default_rng(8)
    where = rng.choice(len(raw), 60, replace=False)  # 2 % spikes of 0.5-3 fields
    directions = rng.normal(size=(60, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    raw[where] += directions * rng.uniform(0.5, 3.0, (60, 1)) * FIELD
    tracker = OnlineTracker(ideal_calibration(hard_iron))
    converged = []
    for sample in raw:
        tracker.update(sample)
        converged.append(tracker.health.converged)
    assert direction_error_rms_deg(tracker.calibration, reading, truth) < 0.5
    assert all(converged[200:])  # spikes do not make the health flicker
    assert tracker.health.rms_error > 0.05  # while the plain loss does see them


@settings(max_examples=60, deadline=None)
@given(
    samples=st.lists(
        st.tuples(*[st.floats(allow_nan=True, allow_infinity=True, width=64)] * 3),
        min_size=1, max_size=60,
    ),
    normalise_input=st.booleans(),
    learning_rate=st.floats(1e-4, 10.0),
)
def test_any_input_leaves_a_valid_calibration(samples, normalise_input, learning_rate):
    tracker = OnlineTracker(
        ideal_calibration([60.0, -30.0, 15.0]), learning_rate=learning_rate,
        normalise_input=normalise_input,
    )
    for sample in samples:
        tracker.update(sample)
    assert_valid_state(tracker)
    health = tracker.health
    assert health.steps + health.skipped + health.refused_steps == len(samples)


@pytest.mark.parametrize(
    'kwargs', [{'learning_rate': 0.0}, {'learning_rate': np.nan}, {'max_step': -1.0}]
)
def test_bad_settings_are_refused(kwargs):
    with pytest.raises(ValueError):
        OnlineTracker(Calibration.identity(FIELD), **kwargs)


def test_an_extremely_anisotropic_start_is_tracked_not_refused():
    """A valid calibration is never refused; it just never gets more anisotropic."""
    start = Calibration(np.zeros(3), np.diag([1.0, 1.0, 1e-3]), FIELD)
    tracker = OnlineTracker(start)
    rng = np.random.default_rng(10)
    tracker.update_many(rng.normal(size=(200, 3)) * FIELD)
    eigenvalues = np.linalg.eigvalsh(tracker.calibration.matrix)
    assert eigenvalues[-1] / eigenvalues[0] <= 1000.0 * (1 + 1e-9)
    assert_valid_state(tracker)


def test_a_rotation_in_the_start_matrix_is_kept():
    """M = R P: the magnitude loss cannot see R, so the tracker keeps it and learns P."""
    hard_iron = np.array([60.0, -30.0, 15.0])
    raw, reading, truth = hand_tumble(hard_iron, seed=11)
    angle = np.radians(10.0)
    rotation = np.array(
        [[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0, 0, 1.0]]
    )
    start = Calibration(hard_iron, rotation @ np.linalg.inv(SOFT_IRON), FIELD)
    tracker = OnlineTracker(start)
    tracker.update_many(raw)
    corrected = tracker.calibration.apply(reading)
    expected = truth @ rotation.T  # the start's convention: truth rotated by R
    cross = np.linalg.norm(np.cross(corrected, expected), axis=1)
    angles = np.degrees(np.arctan2(cross, np.einsum('ij,ij->i', corrected, expected)))
    assert np.sqrt(np.mean(angles**2)) < 0.2


def test_health_before_any_sample():
    health = OnlineTracker(Calibration.identity(FIELD)).health
    assert (health.steps, health.skipped, health.converged) == (0, 0, False)
    assert health.loss == np.inf


def test_the_normalised_rule_takes_the_input_magnitude_out_of_the_matrix_step():
    """One step from the same state: the raw rule's matrix step is |x - b| / radius times the
    normalised rule's (the notebook's x versus x / |x|)."""
    hard_iron = np.array([60.0, -30.0, 15.0])
    raw, _, _ = hand_tumble(hard_iron, n=200)
    for distance in (1.2, 3.0):  # in fields from the offset, along the corrected z axis
        sample = hard_iron + SOFT_IRON @ np.array([0.0, 0.0, distance * FIELD])
        steps = {}
        for normalise_input in RULES:
            tracker = OnlineTracker(
                ideal_calibration(hard_iron), learning_rate=1e-3, normalise_input=normalise_input
            )
            tracker.update_many(raw)  # past the warm-up
            before = tracker.calibration.matrix
            assert tracker.update(sample)
            steps[normalise_input] = np.linalg.norm(tracker.calibration.matrix - before)
        assert steps[False] / steps[True] == pytest.approx(distance, rel=0.05)


def test_the_matrix_never_becomes_unphysically_anisotropic():
    """Data from a 200:1 ellipsoid pulls towards it; steps past 100:1 are refused."""
    rng = np.random.default_rng(9)
    directions = rng.normal(size=(3000, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    squashed = FIELD * directions * [1.0, 1.0, 1.0 / 200.0]
    start = Calibration(np.zeros(3), np.diag([1.0, 1.0, 99.0]), FIELD)
    tracker = OnlineTracker(start, learning_rate=0.05)
    tracker.update_many(squashed)
    eigenvalues = np.linalg.eigvalsh(tracker.calibration.matrix)
    assert eigenvalues[-1] / eigenvalues[0] <= 100.0
    assert tracker.health.refused_steps > 0
    assert_valid_state(tracker)
