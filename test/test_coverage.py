# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""direction_coverage: equal-area cells after whitening, independent of N, and a useful hint."""

from pathlib import Path
import sys
from typing import NamedTuple

from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mag_calibrator_ros.calibration import (
    Calibration,
    Coverage,
    FitOptions,
    direction_coverage,
    fit_calibration,
)
from mag_calibrator_ros.calibration.fit.coverage import (
    CELL_COUNT,
    NOT_A_SHELL_HINT,
    STILL_HINT,
    cell_centres,
    cell_index,
    heading_coverage,
    missing_rotation_hint,
    whitened_directions,
)
from mag_calibrator_ros.calibration.fit.heading import TURN_STILL_HINT
from mag_calibrator_ros.calibration.live.hints import UNDECIDED_STILL_HINT
from mag_calibrator_ros.calibration.live.offline import calibrate_now, feed
from mag_calibrator_ros.calibration.live.session import CalibrationSession
from mag_calibrator_ros.calibration.live.settings import SessionSettings
from mag_calibrator_ros.sim.motion import body_field_samples

sys.path.insert(0, str(Path(__file__).parent))
from test_fit_recordings import PUBLISHED  # noqa: E402  (the authors' calibrations, one place)

FIELD = 50.0
OFFSET = np.array([210.0, -140.0, 75.0])
SOFT = np.array([[1.10, 0.12, -0.05], [0.12, 0.92, 0.08], [-0.05, 0.08, 1.02]])


def unit_vectors(rng, n):
    vectors = rng.normal(size=(n, 3))
    return vectors / np.linalg.norm(vectors, axis=1, keepdims=True)


def distorted(directions, rng, noise=0.25):
    """Raw readings of a sensor with hard and soft iron seeing these field directions."""
    return FIELD * directions @ SOFT.T + OFFSET + rng.normal(0.0, noise, directions.shape)


def rotation_about(axis, angles):
    """Directions of a field swept by turning the body about one body axis (a cone round it)."""
    field = np.array([0.55, 0.30, -0.78])
    field /= np.linalg.norm(field)
    c, s = np.cos(angles), np.sin(angles)
    i, j = [k for k in range(3) if k != axis]
    out = np.empty((len(angles), 3))
    out[:, axis] = field[axis]
    out[:, i] = c * field[i] - s * field[j]
    out[:, j] = s * field[i] + c * field[j]
    return out


def test_cells_are_equal_area_and_at_least_80():
    assert CELL_COUNT >= 80
    rng = np.random.default_rng(1)
    counts = np.bincount(cell_index(unit_vectors(rng, 400_000)), minlength=CELL_COUNT)
    assert counts.min() > 0.95 * counts.mean()
    assert counts.max() < 1.05 * counts.mean()


def test_each_cell_centre_lies_in_its_own_cell():
    np.testing.assert_array_equal(cell_index(cell_centres()), np.arange(CELL_COUNT))


def test_full_tumble_with_hard_and_soft_iron_is_complete():
    rng = np.random.default_rng(2)
    coverage = direction_coverage(distorted(unit_vectors(rng, 3000), rng))
    assert isinstance(coverage, Coverage)
    assert coverage.cells == CELL_COUNT
    assert coverage.occupied == CELL_COUNT
    assert coverage.fraction == 1.0
    assert coverage.hint == ''


def test_does_not_depend_on_sample_count():
    """Repeating samples, or more samples on the same directions, changes nothing."""
    rng = np.random.default_rng(3)
    directions = unit_vectors(rng, 60)
    raw = distorted(directions, rng, noise=0.0)
    once = direction_coverage(raw)
    tripled = direction_coverage(np.vstack([raw, raw, raw]))
    assert once == tripled
    cells = np.unique(cell_index(directions)).size
    assert abs(once.occupied - cells) <= 3  # the whitening recovers the true directions


def test_same_answer_in_any_unit():
    rng = np.random.default_rng(4)
    raw_ut = distorted(unit_vectors(rng, 150), rng)
    in_tesla = direction_coverage(raw_ut * 1e-6)
    in_counts = direction_coverage(np.round(raw_ut / 0.15))
    assert direction_coverage(raw_ut).occupied == in_tesla.occupied
    assert abs(in_counts.occupied - in_tesla.occupied) <= 2  # rounding to counts moves a few


def test_yaw_only_asks_for_roll_or_pitch():
    rng = np.random.default_rng(5)
    raw = distorted(rotation_about(2, rng.uniform(0, 2 * np.pi, 500)), rng)
    coverage = direction_coverage(raw)
    assert coverage.fraction < 0.35
    assert 'yaw' not in coverage.hint
    assert 'roll axis (x)' in coverage.hint and 'pitch axis (y)' in coverage.hint
    assert '+z and -z' in coverage.hint


def test_pitch_only_asks_for_roll_or_yaw():
    rng = np.random.default_rng(6)
    raw = distorted(rotation_about(1, rng.uniform(0, 2 * np.pi, 500)), rng)
    coverage = direction_coverage(raw)
    assert coverage.fraction < 0.35
    assert 'pitch' not in coverage.hint
    assert 'roll axis (x)' in coverage.hint and 'yaw axis (z)' in coverage.hint


def test_missing_hemisphere_names_the_unseen_direction():
    rng = np.random.default_rng(7)
    directions = unit_vectors(rng, 2000)
    upper = directions[directions[:, 2] > 0.1]
    coverage = direction_coverage(distorted(upper, rng))
    assert 0.3 < coverage.fraction < 0.7
    assert '-z' in coverage.hint
    assert 'keep rotating about the' in coverage.hint


def test_calibration_is_used_for_the_directions():
    rng = np.random.default_rng(8)
    raw = distorted(unit_vectors(rng, 2000), rng)
    good = Calibration(OFFSET, np.linalg.inv(SOFT), FIELD)
    assert direction_coverage(raw, good).fraction == 1.0
    # without the offset every reading points the same way: almost nothing is covered
    assert direction_coverage(raw, Calibration.identity(FIELD)).fraction < 0.1


def test_whitened_directions_are_unit_vectors_close_to_the_truth():
    rng = np.random.default_rng(9)
    directions = unit_vectors(rng, 400)
    found = whitened_directions(distorted(directions, rng, noise=0.0))
    np.testing.assert_allclose(np.linalg.norm(found, axis=1), 1.0)
    assert np.degrees(np.arccos(np.min(np.sum(found * directions, axis=1)))) < 5.0


@pytest.mark.parametrize(
    'samples',
    [
        [],
        np.empty((0, 3)),
        np.full((10, 3), np.nan),
        np.full((10, 3), np.inf),
        np.zeros((10, 3)),
        [['a', 'b', 'c']],
        np.ones((5, 2)),
        None,
    ],
)
def test_unusable_input_gives_zero_coverage_and_advice(samples):
    coverage = direction_coverage(samples)
    assert coverage.fraction == 0.0
    assert coverage.occupied == 0
    assert 'rotate' in coverage.hint


def test_non_finite_rows_are_ignored():
    rng = np.random.default_rng(10)
    raw = distorted(unit_vectors(rng, 3000), rng)
    raw[::7] = np.nan
    raw[1::9, 0] = np.inf
    assert direction_coverage(raw).fraction == 1.0


def test_heading_coverage_counts_sectors_and_names_the_turn():
    half = np.linspace(0.0, np.pi, 200, endpoint=False)
    coverage = heading_coverage(half, np.array([0.0, 0.1, 0.99]))
    assert coverage.fraction == pytest.approx(0.5)
    assert 'yaw axis (z)' in coverage.hint and '180°' in coverage.hint
    complete = heading_coverage(np.linspace(-np.pi, np.pi, 400), np.array([0.0, 0.0, 1.0]))
    assert complete.fraction == 1.0 and complete.hint == ''


def test_spikes_do_not_count_as_directions():
    """A yawing sensor with a fifth of its samples spiked still lacks roll and pitch."""
    rng = np.random.default_rng(11)
    raw = distorted(rotation_about(2, rng.uniform(0, 2 * np.pi, 400)), rng)
    spiked = rng.choice(len(raw), 80, replace=False)
    kicks = rng.normal(size=(80, 3))
    raw[spiked] += kicks / np.linalg.norm(kicks, axis=1, keepdims=True) * FIELD * 1.5
    clean = direction_coverage(np.delete(raw, spiked, axis=0))
    coverage = direction_coverage(raw)
    # a few spikes land back on the sphere and look like field readings; the rest must not count
    assert coverage.occupied <= clean.occupied + 8
    assert coverage.fraction < 0.35
    assert 'roll axis (x)' in coverage.hint and 'yaw' not in coverage.hint


# --- degenerate data: a still sensor, a small wobble, yaw only ---------------------------------

UNITS = {'uT': 1.0, 'T': 1e-6, 'counts': 1.0 / 0.15}
"""Per-unit factors from microtesla; counts are rounded to integers (0.15 uT per count)."""


def in_unit(raw_ut, unit):
    scaled = raw_ut * UNITS[unit]
    return np.round(scaled) if unit == 'counts' else scaled


def still(rng, n, offset_fields, noise):
    """A sensor lying still: one field direction plus noise, offset a multiple of the field."""
    direction = np.tile(unit_vectors(rng, 1), (n, 1))
    offset = np.array([0.6, -0.5, 0.62]) / np.linalg.norm([0.6, -0.5, 0.62])
    return (
        FIELD * direction @ SOFT.T
        + offset_fields * FIELD * offset
        + rng.normal(0.0, noise, (n, 3))
    )


def wobbled(rng, n, degrees):
    """Field directions of a body rocked by up to ``degrees`` about random axes."""
    field = np.array([0.55, 0.30, -0.78])
    field /= np.linalg.norm(field)
    axes = unit_vectors(rng, n) * rng.uniform(0.0, np.radians(degrees), (n, 1))
    return Rotation.from_rotvec(axes).apply(field)


@pytest.mark.parametrize('unit', sorted(UNITS))
@pytest.mark.parametrize('offset_fields', [0.0, 1.0, 5.0])
@pytest.mark.parametrize('noise', [0.02, 0.1, 0.5, 2.0])
def test_still_sensor_covers_nothing_and_says_rotate(unit, offset_fields, noise):
    """Centred and whitened by a fit to itself, a noise blob looks like a sphere: it must not."""
    rng = np.random.default_rng(int(100 * noise + 10 * offset_fields))
    coverage = direction_coverage(in_unit(still(rng, 300, offset_fields, noise), unit))
    assert coverage.fraction < 0.1
    assert coverage.hint == STILL_HINT
    assert 'rotate the sensor' in coverage.hint


def test_still_sensor_through_a_good_calibration_is_one_cell_and_says_rotate():
    rng = np.random.default_rng(20)
    good = Calibration(OFFSET, np.linalg.inv(SOFT), FIELD)
    raw = FIELD * np.tile(unit_vectors(rng, 1), (300, 1)) @ SOFT.T + OFFSET
    coverage = direction_coverage(raw + rng.normal(0.0, 0.25, raw.shape), good)
    assert coverage.occupied <= 2
    assert coverage.hint == STILL_HINT


def test_still_sensor_read_in_a_few_counts_covers_nothing():
    """Noise below one count: a handful of distinct readings, which any sphere fits exactly."""
    rng = np.random.default_rng(21)
    for noise_counts in (0.2, 0.35, 0.6):
        raw = np.round(still(rng, 500, 1.0, 0.0) / 0.15 + rng.normal(0.0, noise_counts, (500, 3)))
        coverage = direction_coverage(raw)
        assert coverage.occupied == 0, noise_counts
        assert coverage.hint == STILL_HINT


def test_real_still_start_of_a_recording_covers_nothing(shared_data):
    """The fxos8700 recording's first 24 rows are the sensor lying still (PROVENANCE.md)."""
    raw = np.loadtxt(shared_data / 'fxos8700-mwrona' / 'mag-readings.txt', ndmin=2)
    coverage = direction_coverage(raw[:24])
    assert coverage.fraction == 0.0
    assert coverage.hint == STILL_HINT
    assert direction_coverage(raw).fraction > 0.8  # the whole recording is a tumble


@pytest.mark.parametrize('folder', sorted(PUBLISHED))
def test_recordings_cover_as_much_as_with_the_authors_calibration(shared_data, folder):
    """The authors counted 67-69 of 72 equal-area bins occupied; the quick whitening must give
    what the published calibration gives."""
    name, delimiter, offset, matrix = PUBLISHED[folder]
    raw = np.loadtxt(shared_data / folder / name, delimiter=delimiter, ndmin=2)
    published = Calibration(np.asarray(offset), np.asarray(matrix), 1.0)
    quick = direction_coverage(raw)
    assert quick.fraction > 0.8
    assert abs(quick.occupied - direction_coverage(raw, published).occupied) <= 2


@pytest.mark.parametrize('unit', sorted(UNITS))
def test_small_wobble_covers_little(unit):
    rng = np.random.default_rng(22)
    coverage = direction_coverage(in_unit(distorted(wobbled(rng, 300, 5.0), rng), unit))
    assert coverage.fraction < 0.1
    assert 'rotate' in coverage.hint


def test_coverage_grows_with_the_rotation():
    """Still, rocked by 5, 60, 120 degrees, tumbled: honest partial coverage in between."""
    rng = np.random.default_rng(23)
    fractions = []
    for degrees in (0.0, 5.0, 60.0, 120.0):
        fractions.append(direction_coverage(distorted(wobbled(rng, 400, degrees), rng)).fraction)
    fractions.append(direction_coverage(distorted(unit_vectors(rng, 3000), rng)).fraction)
    assert fractions[0] < 0.1 and fractions[1] < 0.1
    assert 0.1 < fractions[2] < 0.5 < fractions[3] < fractions[4] == 1.0
    assert fractions == sorted(fractions)


@pytest.mark.parametrize('unit', sorted(UNITS))
@pytest.mark.parametrize('offset', [OFFSET, np.array([0.0, 0.0, -250.0]), np.full(3, 150.0)])
def test_yaw_only_covers_a_ring(unit, offset):
    """A ring of directions, not a sphere and not nothing; the hint asks for roll or pitch.

    Without a calibration the ring's tilt (the field's inclination) is unknown, so it is centred
    as a great circle: at most about 20 cells (16 on the equator). A calibration places it.
    """
    rng = np.random.default_rng(24)
    directions = rotation_about(2, rng.uniform(0, 2 * np.pi, 500))
    raw_ut = distorted(directions, rng) - OFFSET + offset  # the ring is far smaller than F
    coverage = direction_coverage(in_unit(raw_ut, unit))
    assert 10 <= coverage.occupied <= 20
    assert 'roll axis (x)' in coverage.hint and 'pitch axis (y)' in coverage.hint
    ring = np.unique(cell_index(rotation_about(2, np.linspace(0, 2 * np.pi, 2000)))).size
    good = Calibration(offset, np.linalg.inv(SOFT), FIELD)
    assert abs(direction_coverage(raw_ut, good).occupied - ring) <= 2


def test_readings_off_any_shell_cover_nothing_and_say_why():
    """Tumbling in a field that changes by tens of percent: no trustworthy directions."""
    rng = np.random.default_rng(25)
    directions = unit_vectors(rng, 1000)
    raw = distorted(directions * rng.uniform(0.4, 1.6, (1000, 1)), rng)
    coverage = direction_coverage(raw)
    assert coverage.fraction == 0.0
    assert coverage.hint == NOT_A_SHELL_HINT


@pytest.mark.parametrize('unit', sorted(UNITS))
@pytest.mark.parametrize('offset_fields', [0.0, 5.0])
def test_fitting_still_data_fails_with_the_rotate_reason(unit, offset_fields):
    rng = np.random.default_rng(26)
    result = fit_calibration(in_unit(still(rng, 300, offset_fields, 0.5), unit))
    assert not result.success
    assert result.metrics.coverage == 0.0
    assert result.reason == f'coverage 0 % is below 50 %: {STILL_HINT}'
    assert result.metrics.coverage_hint == STILL_HINT


def test_fitting_still_data_fails_even_without_the_coverage_gate():
    rng = np.random.default_rng(27)
    result = fit_calibration(still(rng, 300, 1.0, 0.5), FitOptions(min_coverage=0.0))
    assert not result.success


class StreamedBuffer(NamedTuple):
    """The live session's buffer as a fit of it gets it (the job ``~/calibrate`` runs)."""

    samples: np.ndarray
    counts: np.ndarray
    readings: np.ndarray
    reference: Calibration | None

    def coverage(self) -> Coverage:
        """As SampleBuffer.coverage: through the buffer's reference, the shell checked against
        the readings."""
        return direction_coverage(self.samples, self.reference, self.readings)


def streamed_buffer(raw, capacity=100):
    """The buffer as the live session keeps it: its own reference fits, merging, held-out
    readings (the session never calibrates here, so the buffer is all there is). Its units are
    not tesla's: nothing refuses the request that shows the buffer (only fits that could go in
    force are refused for a unit, so the buffer learns the same in any)."""
    settings = SessionSettings(buffer_size=capacity, auto_calibrate=False, full_scale=0.0)
    session = CalibrationSession(settings, metadata={'units': 'x'})
    feed(session, raw, rate_hz=50.0)
    reported = session.report(measure_coverage=True).coverage
    job = calibrate_now(session).outcome.job
    buffer = StreamedBuffer(job.samples, job.weights, job.readings, job.reference)
    if reported.cells == CELL_COUNT:  # the session reports this coverage (with its own hint)
        assert reported.fraction == buffer.coverage().fraction
    return buffer


@pytest.mark.parametrize('unit', sorted(UNITS))
@pytest.mark.parametrize('capacity', [50, 100, 200])
def test_buffer_fed_a_still_sensor_reports_no_coverage(unit, capacity):
    """The reported failure: the kNN buffer keeps the rim of the noise blob, a thin shell of a
    few noise sigmas that centring and whitening (and the buffer's own provisional fit) turn into
    70-99 % "coverage"."""
    rng = np.random.default_rng(capacity)
    buffer = streamed_buffer(in_unit(still(rng, 4000, 1.0, 0.5), unit), capacity)
    coverage = buffer.coverage()
    assert coverage.fraction < 0.1
    assert coverage.hint == STILL_HINT
    result = fit_calibration(buffer.samples, weights=buffer.counts, readings=buffer.readings)
    assert not result.success
    assert STILL_HINT in result.reason and 'residual' not in result.reason


def test_buffer_fed_a_tumble_after_lying_still_covers_the_sphere():
    rng = np.random.default_rng(28)
    buffer = streamed_buffer(np.vstack([still(rng, 2000, 1.0, 0.5),
                                        distorted(unit_vectors(rng, 3000), rng)]))
    assert buffer.coverage().fraction > 0.8


def test_fitting_a_flat_still_blob_fails_with_the_rotate_reason():
    """One quiet axis makes a still sensor's noise flat: the planar model's headings of a flat
    blob go all round, but it is still no rotation (and the planar model says to turn)."""
    rng = np.random.default_rng(29)
    raw = np.array([20.0, -30.0, 40.0]) + rng.normal(0.0, 0.5, (600, 3)) * [1.0, 1.0, 0.02]
    result = fit_calibration(raw)
    assert result.metrics.model == 'planar'
    assert not result.success
    assert result.reason == f'coverage 0 % is below 50 %: {TURN_STILL_HINT}'


@settings(max_examples=20, deadline=None)  # each streams 1500 readings through a buffer
@given(
    offset=arrays(float, 3, elements=st.floats(-15.0, 15.0)),
    noise=st.floats(0.001, 0.03),
    unit_scale=st.sampled_from([1e-6, 1.0, 1e-2, 1.0 / 0.15]),
    seed=st.integers(0, 2**32 - 1),
)
def test_property_still_sensor_never_looks_rotated(offset, noise, unit_scale, seed):
    """Any offset up to 15 F, noise 0.1-3 % of F, any unit: raw or through the buffer, < 10 %."""
    rng = np.random.default_rng(seed)
    direction = unit_vectors(rng, 1)
    raw = (direction + offset + rng.normal(0.0, noise, (1500, 3))) * FIELD * unit_scale
    assert direction_coverage(raw).fraction < 0.1
    buffer = streamed_buffer(raw, capacity=60)
    assert buffer.coverage().fraction < 0.1


# --- weak and strong fields with large hard-iron offsets (issue #2, parts 2 and 3) --------------

STRONG_OFFSETS = {
    # (field uT, offset uT): the weakest field (South Atlantic) under the AK09916's whole
    # zero-field tolerance (13.6 F), the strongest (near the poles) at 5 F, and 15 F
    'weak field, 300 uT offset': (22.0, 300.0),
    'strong field, 5 F offset': (65.0, 325.0),
    'mid field, 15 F offset': (40.0, 600.0),
}
OFFSET_DIRECTION = np.array([0.6, -0.5, 0.62]) / np.linalg.norm([0.6, -0.5, 0.62])


def sensor_readings(kind, field_ut, offset_ut, noise_share=0.01, n=3000, seed=3):
    """Raw uT readings of a board moving along a motion.body_field_samples trajectory."""
    rng = np.random.default_rng(seed)
    truth = body_field_samples(kind, n, 50.0, field_ut, 60.0, seed)
    raw = truth @ SOFT.T + offset_ut * OFFSET_DIRECTION
    return raw + rng.normal(0.0, noise_share * field_ut, raw.shape)


@pytest.mark.parametrize('unit', sorted(UNITS))
@pytest.mark.parametrize('case', sorted(STRONG_OFFSETS))
def test_tumble_with_a_large_offset_covers_the_sphere_and_calibrates(case, unit):
    """Offsets of several times the field are normal; they used to be taken for a still sensor
    (coverage 0, 'rotate') and could never be calibrated."""
    field, offset = STRONG_OFFSETS[case]
    raw = in_unit(sensor_readings('tumble', field, offset), unit)
    coverage = direction_coverage(raw)
    assert coverage.fraction > 0.95, coverage
    result = fit_calibration(raw)
    assert result.success, result.reason
    recovered = result.calibration.offset / UNITS[unit]
    assert np.linalg.norm(recovered - offset * OFFSET_DIRECTION) < 0.02 * field

    buffer = streamed_buffer(raw)
    assert buffer.coverage().fraction > 0.75, buffer.coverage()
    weights = buffer.counts
    with_readings = fit_calibration(buffer.samples, weights=weights, readings=buffer.readings)
    assert with_readings.success, with_readings.reason
    alone = fit_calibration(buffer.samples, weights=weights)  # what ~/calibrate fits today
    assert alone.success, alone.reason


@pytest.mark.parametrize('unit', sorted(UNITS))
@pytest.mark.parametrize('case', sorted(STRONG_OFFSETS))
@pytest.mark.parametrize('noise_share', [0.005, 0.03])
def test_still_sensor_with_a_large_offset_covers_nothing(case, unit, noise_share):
    field, offset = STRONG_OFFSETS[case]
    raw = in_unit(sensor_readings('still', field, offset, noise_share), unit)
    coverage = direction_coverage(raw)
    assert coverage.fraction == 0.0 and coverage.hint == STILL_HINT
    assert not fit_calibration(raw).success
    buffer = streamed_buffer(raw)
    coverage = buffer.coverage()
    assert coverage.fraction < 0.1 and coverage.hint == STILL_HINT
    fitted = fit_calibration(buffer.samples, weights=buffer.counts, readings=buffer.readings)
    assert not fitted.success
    assert STILL_HINT in fitted.reason
    assert not fit_calibration(buffer.samples, weights=buffer.counts).success


@pytest.mark.parametrize('case', sorted(STRONG_OFFSETS))
def test_session_calibrates_a_tumble_with_a_large_offset(case):
    """The node's logic (tesla): auto-calibration starts and succeeds."""
    field, offset = STRONG_OFFSETS[case]
    session = CalibrationSession()
    feed(session, sensor_readings('tumble', field, offset) * 1e-6, rate_hz=50.0)
    report = session.report(measure_coverage=True)
    assert 'rotate' not in report.progress
    assert report.counts.adoptions.get('auto') == 1, [e.message for e in session.take_events()]
    assert report.state.startswith('calibrated')
    np.testing.assert_allclose(
        session.calibration.offset, offset * 1e-6 * OFFSET_DIRECTION, atol=0.02 * field * 1e-6
    )


@pytest.mark.parametrize('case', sorted(STRONG_OFFSETS))
def test_session_fed_a_still_sensor_says_rotate_and_does_not_calibrate(case):
    field, offset = STRONG_OFFSETS[case]
    session = CalibrationSession()
    feed(session, sensor_readings('still', field, offset) * 1e-6, rate_hz=50.0)
    # still, a robot or a hand alike: said, with no rotation a robot could not make (issue 24)
    assert UNDECIDED_STILL_HINT in session.report(measure_coverage=True).progress
    assert session.calibration is None
    assert not calibrate_now(session).success
    assert session.report().state == 'collecting'


@pytest.mark.parametrize('offset_fields', [0.0, 5.0, 15.0])
def test_buffer_fed_a_small_wobble_covers_little(offset_fields):
    rng = np.random.default_rng(30)
    directions = wobbled(rng, 3000, 5.0)
    raw = FIELD * directions @ SOFT.T + offset_fields * FIELD * OFFSET_DIRECTION
    buffer = streamed_buffer(raw + rng.normal(0.0, 0.25, raw.shape))
    coverage = buffer.coverage()
    assert coverage.fraction < 0.1
    assert 'rotate' in coverage.hint


def test_a_noise_rim_is_told_apart_by_the_readings_behind_it():
    """The rim a buffer can keep of a still sensor's noise (merged means placed on a fitted
    surface: a thin, smooth shell a few sigmas across) passes for a sphere when judged alone; the
    readings it was drawn from fill its inside."""
    rng = np.random.default_rng(6)
    readings = still(rng, 3000, 0.0, 1.0)
    centre, sigma = readings.mean(axis=0), readings.std(axis=0).mean()
    rim = centre + 2.5 * sigma * unit_vectors(rng, 50)
    assert direction_coverage(rim).fraction > 0.3  # alone: only the loose offset guard
    judged = direction_coverage(rim, None, readings)
    assert judged.fraction == 0.0 and judged.hint == STILL_HINT
    tumble = distorted(unit_vectors(rng, 3000), rng)
    assert direction_coverage(tumble[::30], readings=tumble).fraction > 0.6


def test_scattered_holes_do_not_name_every_axis():
    # A few holes spread over an almost full sphere: every rotation reaches some of them, so the
    # hint asks for new orientations and names the unseen direction, not all three axes at once.
    occupied = np.ones(CELL_COUNT, dtype=bool)
    occupied[[3, 17, 40, 58, 71]] = False
    hint = missing_rotation_hint(occupied)
    assert hint.startswith('keep rotating through new orientations')
    assert 'roll axis' not in hint and 'the field has not yet pointed along' in hint
    assert missing_rotation_hint(np.ones(CELL_COUNT, dtype=bool)) == ''
