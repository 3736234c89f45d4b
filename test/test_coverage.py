"""direction_coverage: equal-area cells after whitening, independent of N, and a useful hint."""

import numpy as np
import pytest

from mag_calibrator_ros.calibration import Calibration, Coverage, direction_coverage
from mag_calibrator_ros.calibration.coverage import (
    CELL_COUNT,
    cell_centres,
    cell_index,
    heading_coverage,
    whitened_directions,
)

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
