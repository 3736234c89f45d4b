# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""SampleBuffer: the kNN uniqueness rule done right, its reference, merging and bookkeeping.

The buffer is given its reference; the session decides which (its own fits are tested in
test_session.py).
"""

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
import pytest

from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.calibration.fit.coverage import Coverage, direction_coverage
from mag_calibrator_ros.calibration.live.buffer import OUTCOMES, SampleBuffer

FIELD = 50.0  # µT


def sphere_samples(n, seed=0, offset=(30.0, -20.0, 10.0), noise=0.2):
    """Uniform directions on a 50 µT sphere with a hard-iron offset and a little noise."""
    rng = np.random.default_rng(seed)
    directions = rng.normal(size=(n, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return FIELD * directions + np.asarray(offset) + rng.normal(0.0, noise, (n, 3))


def true_calibration(offset=(30.0, -20.0, 10.0)):
    return Calibration(np.asarray(offset), np.eye(3), FIELD)


def brute_scores(points, k):
    """Mean distance of each point to its k nearest other points, the obvious way."""
    distances = np.linalg.norm(points[:, None, :] - points[None, :, :], axis=2)
    np.fill_diagonal(distances, np.inf)
    return np.sort(distances, axis=1)[:, :k].mean(axis=1)


class BruteForceBuffer:
    """mag-calibrator-rs's rule with consistent scoring, recomputed from scratch per sample."""

    def __init__(self, capacity, k):
        self.capacity, self.k, self.points = capacity, k, []

    def add(self, x):
        if any(np.array_equal(p, x) for p in self.points):
            return 'duplicate'
        if len(self.points) < self.capacity:
            self.points.append(x)
            return 'added'
        points = np.array(self.points)
        scores = brute_scores(points, self.k)
        weakest = int(np.argmin(scores))
        own = np.sort(np.linalg.norm(points - x, axis=1))[: self.k].mean()
        if own > scores[weakest]:
            self.points[weakest] = x
            return 'replaced'
        return 'not_unique'


def assert_bookkeeping_exact(buffer):
    """Incremental neighbour lists give the same scores as a full recomputation."""
    points = buffer.anchors
    if len(points) > buffer.k:
        np.testing.assert_allclose(buffer.scores, brute_scores(points, buffer.k), rtol=1e-12)


# -- the uniqueness rule --------------------------------------------------------------------------


def test_fills_first_then_replaces_the_most_crowded_sample():
    buffer = SampleBuffer(capacity=6, k=2)
    spread = [[50.0, 0, 0], [-50.0, 0, 0], [0, 50.0, 0], [0, -50.0, 0], [0, 0, 50.0]]
    crowded = [50.0, 1.0, 0.0]  # next to the first sample: the two most crowded ones
    for sample in [*spread, crowded]:
        assert buffer.add(sample) == 'added'
    assert buffer.fill == 6
    weakest_before = np.argsort(buffer.scores)[:2]
    assert set(weakest_before) == {0, 5}
    assert buffer.add([0.0, 0.0, -50.0]) == 'replaced'
    rows = {tuple(row) for row in buffer.samples}
    assert (0.0, 0.0, -50.0) in rows
    assert len(rows & {(50.0, 0.0, 0.0), (50.0, 1.0, 0.0)}) == 1  # one of the crowded pair left
    assert_bookkeeping_exact(buffer)


def test_a_crowded_new_sample_is_rejected():
    """mag-calibrator-rs scored buffered points with their zero self-distance, so every
    candidate looked more unique than the weakest buffered point and got in. Here it does not."""
    samples = sphere_samples(200, seed=1)
    buffer = SampleBuffer(capacity=50, k=5)
    buffer.add_many(samples)
    before = buffer.anchors
    # A candidate in the middle of the densest spot: right between a point and its nearest twin.
    scores = buffer.scores
    densest = int(np.argmin(scores))
    nearest = np.argsort(np.linalg.norm(before - before[densest], axis=1))[1]
    candidate = 0.5 * (before[densest] + before[nearest])
    assert buffer.add(candidate) == 'not_unique'
    np.testing.assert_array_equal(buffer.anchors, before)


def test_a_candidate_as_unique_as_the_weakest_does_not_churn():
    buffer = SampleBuffer(capacity=4, k=1)
    for sample in ([1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0], [0, -1.0, 0]):
        buffer.add(sample)
    # Every buffered point has nearest-neighbour distance sqrt(2); so does this candidate.
    assert buffer.add([0.0, 0.0, 1.0]) == 'not_unique'


def test_spread_improves_as_more_samples_stream_through():
    samples = sphere_samples(3000, seed=2)
    buffer = SampleBuffer(capacity=100, k=6)
    buffer.add_many(samples[:100])
    crowding_first = buffer.scores.min()
    assert buffer.merged == 0  # nothing merges without a reference that may merge
    counts = buffer.add_many(samples[100:])
    assert counts['replaced'] > 0 and counts['not_unique'] > 0
    assert buffer.scores.min() > 1.5 * crowding_first
    assert buffer.seen == 3000
    assert_bookkeeping_exact(buffer)


# -- bookkeeping: incremental equals brute force --------------------------------------------------


@settings(max_examples=40, deadline=None)
@given(
    capacity=st.integers(2, 30),
    k_fraction=st.floats(0.0, 1.0),
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(1, 300),
    duplicate_share=st.floats(0.0, 0.3),
    scale_exponent=st.integers(-8, 4),
)
def test_incremental_bookkeeping_equals_brute_force(
    capacity, k_fraction, seed, n, duplicate_share, scale_exponent
):
    k = 1 + int(k_fraction * (capacity - 2))
    rng = np.random.default_rng(seed)
    samples = rng.normal(size=(n, 3)) * 10.0**scale_exponent
    repeats = rng.random(n) < duplicate_share
    for i in np.flatnonzero(repeats):
        samples[i] = samples[rng.integers(0, i + 1)]
    buffer = SampleBuffer(capacity, k)  # the rule alone: nothing merged
    reference = BruteForceBuffer(capacity, k)
    for sample in samples:
        assert buffer.add(sample) == reference.add(sample)
    np.testing.assert_array_equal(buffer.samples, np.array(reference.points))
    np.testing.assert_array_equal(buffer.anchors, buffer.samples)
    assert_bookkeeping_exact(buffer)


@settings(max_examples=20, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1), capacity=st.integers(3, 40), new_capacity=st.integers(3, 40)
)
def test_resize_keeps_exact_bookkeeping_and_the_most_unique_samples(seed, capacity, new_capacity):
    samples = np.random.default_rng(seed).normal(size=(200, 3))
    buffer = SampleBuffer(capacity, k=2)
    buffer.add_many(samples)
    before = {tuple(row) for row in buffer.samples}
    buffer.resize(capacity=new_capacity, k=1)
    assert (buffer.capacity, buffer.k) == (new_capacity, 1)
    assert buffer.fill == min(new_capacity, len(before))
    assert {tuple(row) for row in buffer.samples} <= before
    assert_bookkeeping_exact(buffer)
    # Still a working buffer: new samples follow the rule.
    reference = BruteForceBuffer(new_capacity, 1)
    reference.points = list(buffer.samples)
    for sample in np.random.default_rng(seed + 1).normal(size=(50, 3)):
        assert buffer.add(sample) == reference.add(sample)
    assert_bookkeeping_exact(buffer)


def test_shrinking_drops_the_most_crowded_first():
    buffer = SampleBuffer(capacity=5, k=1)
    for sample in ([0.0, 0, 1], [10.0, 0, 1], [0, 10.0, 1], [-10.0, 0, 1], [0.1, 0, 1]):
        buffer.add(sample)
    buffer.resize(capacity=4)
    rows = {tuple(row) for row in buffer.samples}
    assert len(rows & {(0.0, 0.0, 1.0), (0.1, 0.0, 1.0)}) == 1


# -- scale invariance -----------------------------------------------------------------------------


def outcomes_and_samples(samples, scale):
    buffer = SampleBuffer(capacity=60, k=6)
    outcomes = [buffer.add(sample * scale) for sample in samples]
    return outcomes, buffer.samples / scale, buffer.relative_knn_distance


@pytest.mark.parametrize('scale', [1e-6, 1e-2, 1.0 / 0.15, 1024.0])  # T, gauss, counts, other
def test_same_decisions_in_any_unit_synthetic(scale):
    samples = sphere_samples(2000, seed=3)  # µT
    outcomes, kept, relative = outcomes_and_samples(samples, 1.0)
    scaled_outcomes, scaled_kept, scaled_relative = outcomes_and_samples(samples, scale)
    assert scaled_outcomes == outcomes
    np.testing.assert_allclose(scaled_kept, kept, rtol=1e-12, atol=1e-12)
    assert scaled_relative == pytest.approx(relative, rel=1e-9)


@pytest.mark.parametrize(
    ('recording', 'delimiter'),
    [('gd-notebook/mag_raw_data_long.txt', '\t'), ('lsm303dlhc-altimu10v3/mag_2.csv', ',')],
)
def test_same_decisions_in_any_unit_on_real_recordings(shared_data, recording, delimiter):
    samples = np.loadtxt(shared_data / recording, delimiter=delimiter)
    outcomes, kept, _ = outcomes_and_samples(samples, 1.0)
    assert outcomes.count('replaced') > 0
    for scale in (1e-6, 1e-2, 1.0 / 1100.0):
        scaled_outcomes, scaled_kept, _ = outcomes_and_samples(samples, scale)
        assert scaled_outcomes == outcomes
        np.testing.assert_allclose(scaled_kept, kept, rtol=1e-9)


def test_relative_knn_distance_is_scale_free_and_radius_is_right():
    buffer = SampleBuffer(capacity=100, k=6)
    buffer.add_many(sphere_samples(2000, seed=4))
    assert buffer.field_radius() == pytest.approx(FIELD, rel=0.01)
    assert 0.0 < buffer.relative_knn_distance < 1.0
    relative = buffer.mean_knn_distance / FIELD
    assert buffer.relative_knn_distance == pytest.approx(relative, rel=0.01)
    buffer.set_reference(true_calibration())
    assert buffer.field_radius() == pytest.approx(FIELD)


def test_radius_of_a_planar_ring_is_the_ring_radius():
    angle = np.linspace(0.0, 2.0 * np.pi, 200, endpoint=False)
    ring = np.column_stack([FIELD * np.cos(angle), FIELD * np.sin(angle), np.full(200, 7.0)])
    buffer = SampleBuffer(capacity=50, k=4)
    buffer.add_many(ring)
    assert buffer.field_radius() == pytest.approx(FIELD, rel=0.01)


# -- what it refuses ----------------------------------------------------------------------------


def test_duplicates_and_magnitude_outliers_are_refused():
    buffer = SampleBuffer(capacity=10, k=3)
    assert buffer.add([30.0, 40.0, 0.0]) == 'added'
    assert buffer.add([30.0, 40.0, 0.0]) == 'duplicate'
    buffer.set_reference(Calibration(np.zeros(3), np.eye(3), FIELD))
    assert buffer.add([300.0, 400.0, 0.0]) == 'magnitude_outlier'  # 10 F
    assert buffer.add([3.0, 4.0, 0.0]) == 'magnitude_outlier'  # F / 10
    assert buffer.reference_checks == (2, 2)
    assert buffer.add([0.0, 0.0, 50.0]) == 'added'
    assert buffer.reference_checks == (3, 2)
    assert buffer.fill == 2 and buffer.seen == 5


@pytest.mark.parametrize('bad', [[np.nan, 1.0, 2.0], [np.inf, 1.0, 2.0], [0.0, 0.0, 0.0],
                                 [-0.0, 0.0, -0.0]])
def test_unscreened_readings_are_a_programming_error(bad):
    """Screening (non-finite, all-zero, saturated) happens once, before the buffer."""
    buffer = SampleBuffer(capacity=10, k=3)
    with pytest.raises(ValueError, match='screen'):
        buffer.add(bad)
    assert buffer.seen == 0 and buffer.fill == 0


def test_one_exact_zero_component_is_a_legitimate_reading():
    buffer = SampleBuffer(capacity=10, k=3)
    for sample in ([0.0, 30.0, 40.0], [30.0, 0.0, -40.0], [-50.0, 0.0, 0.0]):
        assert buffer.add(sample) == 'added'
    assert buffer.fill == 3


def test_duplicates_are_refused_when_full_too():
    samples = sphere_samples(300, seed=5)
    buffer = SampleBuffer(capacity=40, k=4)
    buffer.add_many(samples)
    for row in buffer.anchors:
        assert buffer.add(row) == 'duplicate'


def test_add_many_counts_every_outcome():
    buffer = SampleBuffer(capacity=10, k=3)
    counts = buffer.add_many([[1.0, 2.0, 3.0], [1.0, 2.0, 3.0], [2.0, 2.0, 3.0]])
    assert set(counts) == set(OUTCOMES)
    assert [counts[key] for key in ('added', 'duplicate')] == [2, 1]
    assert buffer.add_many(np.empty((0, 3)))['added'] == 0


@pytest.mark.parametrize('bad', [[1.0, 2.0], [[1.0, 2.0, 3.0, 4.0]], 'abc'])
def test_malformed_samples_raise_a_clear_error(bad):
    with pytest.raises(ValueError):
        SampleBuffer().add(bad)


def test_add_many_rejects_wrong_shapes():
    with pytest.raises(ValueError, match=r'\(n, 3\)'):
        SampleBuffer().add_many(np.zeros((4, 2)))


@pytest.mark.parametrize(
    'kwargs',
    [
        {'capacity': 1},
        {'capacity': 10, 'k': 10},
        {'capacity': 10, 'k': 0},
        {'capacity': 10.5},
        {'capacity': True},
    ],
)
def test_bad_configuration_is_refused(kwargs):
    with pytest.raises(ValueError):
        SampleBuffer(**kwargs)


@pytest.mark.parametrize('tolerance', [0.0, -0.1, float('nan'), float('inf')])
def test_a_bad_tolerance_is_refused(tolerance):
    with pytest.raises(ValueError, match='tolerance'):
        SampleBuffer().set_reference(true_calibration(), tolerance)


# -- outliers -------------------------------------------------------------------------------------


def with_spikes(samples, share, seed):
    """Transients of 2-5 F in random directions: gross outliers."""
    rng = np.random.default_rng(seed)
    spiky = samples.copy()
    where = rng.choice(len(samples), int(share * len(samples)), replace=False)
    directions = rng.normal(size=(len(where), 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    spiky[where] += directions * rng.uniform(2.0, 5.0, (len(where), 1)) * FIELD
    return spiky, set(map(tuple, spiky[where]))


def test_spikes_get_in_without_a_reference_and_never_survive_once_one_is_set():
    samples, spikes = with_spikes(sphere_samples(5000, seed=6), 0.002, seed=6)
    buffer = SampleBuffer(capacity=50, k=5)
    buffer.add_many(samples[:2500])
    assert {tuple(row) for row in buffer.samples} & spikes  # the uniqueness rule loves spikes
    evicted = buffer.set_reference(true_calibration())
    assert evicted > 0 and buffer.evicted == evicted
    assert not {tuple(row) for row in buffer.samples} & spikes
    assert_bookkeeping_exact(buffer)
    counts = buffer.add_many(samples[2500:])
    assert not {tuple(row) for row in buffer.samples} & spikes
    assert counts['magnitude_outlier'] == len(spikes & set(map(tuple, samples[2500:])))


def test_good_data_is_never_a_magnitude_outlier():
    """Soft iron of 10 % and 2 µT noise under a rough hard-iron-only reference: all kept."""
    rng = np.random.default_rng(7)
    directions = rng.normal(size=(5000, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    soft = np.array([[1.1, 0.05, 0.0], [0.05, 0.92, 0.03], [0.0, 0.03, 1.0]])
    offset = np.array([150.0, -80.0, 40.0])
    samples = FIELD * directions @ soft.T + offset + rng.normal(0.0, 2.0, (5000, 3))
    buffer = SampleBuffer(capacity=100, k=6)
    buffer.set_reference(Calibration(offset, np.eye(3), FIELD))
    assert buffer.add_many(samples)['magnitude_outlier'] == 0


def test_a_stale_reference_refuses_and_counts_so_its_owner_can_tell():
    """A calibration file from another mounting: every reading is refused, and counted."""
    buffer = SampleBuffer(capacity=50, k=5)
    buffer.set_reference(Calibration(np.zeros(3), np.eye(3), 3.0 * FIELD))
    counts = buffer.add_many(sphere_samples(200, seed=8))
    assert counts['magnitude_outlier'] == 200 and buffer.fill == 0
    assert buffer.reference_checks == (200, 200)


def test_a_reference_most_of_the_buffer_disagrees_with_evicts_nothing():
    """A file from another mounting must not wipe a buffer full of good, current data."""
    buffer = SampleBuffer(capacity=50, k=5)
    buffer.add_many(sphere_samples(500, seed=13))
    assert buffer.set_reference(Calibration(np.zeros(3), np.eye(3), 3.0 * FIELD)) == 0
    assert buffer.fill == 50 and buffer.evicted == 0


def test_set_reference_none_stops_screening():
    buffer = SampleBuffer(capacity=10, k=3)
    buffer.set_reference(true_calibration())
    buffer.set_reference(None)
    assert buffer.add([500.0, 0.0, 0.0]) == 'added'
    assert buffer.reference is None and buffer.reference_checks == (0, 0)


# -- progress, reset ------------------------------------------------------------------------------


def test_coverage_grows_with_rotation_and_is_independent_of_capacity():
    samples = sphere_samples(3000, seed=9)
    small, large = SampleBuffer(capacity=100, k=6), SampleBuffer(capacity=300, k=6)
    small.add_many(samples)
    large.add_many(samples)
    assert isinstance(small.coverage(), Coverage)
    # 100 random samples of the same stream fill about 70 % of the 80 cells; well spread, more.
    random_subset = samples[np.random.default_rng(9).choice(3000, 100, replace=False)]
    assert small.coverage().fraction > direction_coverage(random_subset).fraction + 0.1
    assert large.coverage().fraction > 0.95
    cap = SampleBuffer(capacity=100, k=6)
    cap.add_many(samples[samples[:, 2] > 10.0 + 25.0])  # only the top of the sphere
    assert cap.coverage().fraction < 0.5
    assert cap.coverage().hint


def test_clear_forgets_samples_counters_and_the_reference():
    buffer = SampleBuffer(capacity=20, k=3)
    buffer.set_reference(true_calibration(), 0.1, merge=True)
    buffer.add_many(sphere_samples(100, seed=10))
    assert buffer.merged > 0
    buffer.clear()
    assert (buffer.fill, buffer.seen, buffer.mean_knn_distance) == (0, 0, 0.0)
    assert (buffer.merged, buffer.evicted) == (0, 0)
    assert buffer.reference is None and buffer.counts.size == 0
    assert buffer.relative_knn_distance == 0.0
    buffer.add_many(sphere_samples(100, seed=11))
    assert buffer.fill == 20
    assert_bookkeeping_exact(buffer)


# -- merging ------------------------------------------------------------------------------------


SOFT = np.array([[1.08, 0.12, -0.03], [0.12, 0.95, 0.06], [-0.03, 0.06, 1.02]])
OFFSET = np.array([180.0, -90.0, 60.0])
TRUE = Calibration(OFFSET, np.linalg.inv(SOFT), FIELD)


def tumble_stream(n=3000, seed=21, noise=0.5, spike_share=0.0, small_spikes=False):
    """A hand tumble at 50 Hz through hard and soft iron, as the node sees it, plus spikes.

    Returns (raw, truth reading without noise and spikes, spike mask).
    """
    from mag_calibrator_ros.sim.motion import body_field_samples

    rng = np.random.default_rng(seed)
    reading = body_field_samples('tumble', n, 50.0, FIELD, 55.0, seed) @ SOFT.T + OFFSET
    raw = reading + rng.normal(0.0, noise, reading.shape)
    spikes = np.zeros(n, dtype=bool)
    spikes[rng.choice(n, int(round(spike_share * n)), replace=False)] = True
    directions = rng.normal(size=(int(spikes.sum()), 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    low, high = (0.3, 2.0) if small_spikes else (2.0, 5.0)
    raw[spikes] += directions * rng.uniform(low, high, (len(directions), 1)) * FIELD
    return raw, reading, spikes


def true_relative_magnitude(points):
    """|S^-1 (x - h)| / F: 1 on the true ellipsoid."""
    return np.linalg.norm((points - OFFSET) @ np.linalg.inv(SOFT).T, axis=1) / FIELD


def test_without_a_reference_the_spikes_stay():
    """The uniqueness rule alone keeps spikes: they are the most unique samples of all (the
    session gives the buffer its own fit as reference to refuse them, see test_session.py)."""
    raw, _, spikes = tumble_stream(spike_share=0.03)
    buffer = SampleBuffer(capacity=100, k=6)
    buffer.add_many(raw)
    assert buffer.merged == 0
    assert len({tuple(row) for row in buffer.anchors} & set(map(tuple, raw[spikes]))) > 30


def test_only_a_reference_that_may_merge_merges():
    raw, _, _ = tumble_stream(n=1000, seed=31)
    screening = SampleBuffer(capacity=50, k=6)
    screening.set_reference(TRUE, 0.1)
    screening.add_many(raw)
    assert screening.merged == 0 and np.all(screening.counts == 1.0)
    merging = SampleBuffer(capacity=50, k=6)
    merging.set_reference(TRUE, 0.1, merge=True)
    merging.add_many(raw)
    assert merging.merged > 500 and merging.counts.sum() > 500


def replay_groups(buffer, stream, groups=None):
    """Feed ``stream`` and track, the obvious way, which readings each buffered point stands for.

    A merge goes to the nearest anchor; a replaced anchor's readings go to its nearest other
    anchor while the buffer merges (else the rule drops the sample).
    """
    groups = {} if groups is None else groups
    for x in stream:
        before = buffer.anchors
        folding = buffer.merging
        merged = buffer.merged
        outcome = buffer.add(x)
        after = {tuple(row) for row in buffer.anchors}
        if outcome == 'added':
            groups[tuple(x)] = [x]
        elif outcome == 'replaced':
            (gone,) = [row for row in before if tuple(row) not in after]
            readings = groups.pop(tuple(gone))
            if folding:
                others = np.array([row for row in before if tuple(row) != tuple(gone)])
                nearest = others[np.argmin(np.linalg.norm(others - gone, axis=1))]
                groups[tuple(nearest)].extend(readings)
            groups[tuple(x)] = [x]
        elif buffer.merged > merged:
            groups[tuple(before[np.argmin(np.linalg.norm(before - x, axis=1))])].append(x)
        for anchor in list(groups):  # evicted by a new reference
            if anchor not in after:
                del groups[anchor]
    return groups


def on_surface(readings, reference):
    """Mean direction, mean radius to second order (the buffer's rule, from the raw readings)."""
    matrix = reference.matrix / reference.field_strength
    readings = np.asarray(readings)
    u = (readings.mean(axis=0) - reference.offset) @ matrix.T
    covariance = matrix @ np.cov(readings, rowvar=False, bias=True) @ matrix.T
    radius = np.linalg.norm(u)
    direction = u / radius
    surface = radius + (np.trace(covariance) - direction @ covariance @ direction) / (2 * radius)
    return reference.offset + np.linalg.solve(matrix, surface * direction)


def rough_reference():
    """A calibration a little off the truth, as a fit of part of the stream would be."""
    return Calibration(OFFSET + [0.5, -0.3, 0.2], 1.01 * TRUE.matrix, FIELD)


def test_counts_and_means_equal_a_brute_force_replay():
    """Counts, sums and second moments (kept about each anchor, moved exactly when a replaced
    point's readings join a neighbour) give what the readings themselves give."""
    raw, _, _ = tumble_stream(n=2000, seed=22)
    buffer = SampleBuffer(capacity=60, k=6)
    groups = replay_groups(buffer, raw[:300])  # the rule alone first
    reference = rough_reference()
    buffer.set_reference(reference, 0.1, merge=True)
    replay_groups(buffer, raw[300:], groups)
    assert buffer.evicted == 0 and buffer.merged > 1000
    counts, samples = buffer.counts, buffer.samples
    assert counts.max() > 20
    for anchor, count, sample in zip(buffer.anchors, counts, samples, strict=True):
        readings = groups[tuple(anchor)]
        assert count == len(readings)
        expected = readings[0] if count == 1 else on_surface(readings, reference)
        np.testing.assert_allclose(sample, expected, rtol=1e-9)
    assert counts.sum() == sum(len(readings) for readings in groups.values())


def test_merged_means_stay_on_the_surface_and_lose_noise():
    """Noise-free: every mean lies on the ellipsoid, where a plain mean of the readings spread
    over a patch sinks inside it. Noisy: means are far closer to it than single readings."""
    _, reading, _ = tumble_stream(seed=23, noise=0.0)
    clean = SampleBuffer(capacity=100, k=6)
    clean.set_reference(TRUE, 0.05, merge=True)
    groups = replay_groups(clean, reading)
    assert clean.merged > 1000
    on_surface_error = np.abs(true_relative_magnitude(clean.samples) - 1.0)
    plain = np.array([np.mean(groups[tuple(a)], axis=0) for a in clean.anchors])
    plain_error = np.abs(true_relative_magnitude(plain) - 1.0)
    assert plain_error.max() > 2e-3  # the sagitta of the larger patches
    assert on_surface_error.max() < 0.1 * plain_error.max()

    raw, _, _ = tumble_stream(seed=23, noise=0.5)
    noisy = SampleBuffer(capacity=100, k=6)
    noisy.set_reference(rough_reference(), 0.1, merge=True)
    noisy.add_many(raw)
    heavy = noisy.counts >= 10
    assert heavy.sum() > 20
    merged_error = np.std(true_relative_magnitude(noisy.samples[heavy]) - 1.0)
    single_error = np.std(true_relative_magnitude(raw) - 1.0)
    assert merged_error < 0.4 * single_error


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), capacity=st.integers(20, 80), k=st.integers(1, 8),
       spike_share=st.floats(0.0, 0.05), start=st.integers(0, 1000))
def test_bookkeeping_stays_exact_with_merges_evictions_and_replacements(
    seed, capacity, k, spike_share, start
):
    raw, _, _ = tumble_stream(n=1500, seed=seed % 1000, spike_share=spike_share)
    buffer = SampleBuffer(capacity, k)
    buffer.add_many(raw[:start])  # spikes get in before the reference, then get evicted
    buffer.set_reference(rough_reference(), 0.1, merge=True)
    buffer.add_many(raw[start:])
    assert_bookkeeping_exact(buffer)
    assert {tuple(row) for row in buffer.anchors} <= set(map(tuple, raw))
    assert buffer.counts.min() >= 1.0


def test_merging_decisions_are_the_same_in_any_unit():
    raw, _, _ = tumble_stream(seed=26, spike_share=0.02, small_spikes=True)
    runs = []
    for scale in (1.0, 1e-6, 1.0 / 0.15):
        buffer = SampleBuffer(capacity=60, k=6)
        buffer.set_reference(rough_reference().scaled(scale), 0.1, merge=True)
        outcomes = [buffer.add(sample * scale) for sample in raw]
        runs.append((outcomes, buffer.samples / scale, buffer.counts, buffer.merged))
    assert runs[0][3] > 0
    for outcomes, samples, counts, merged in runs[1:]:
        assert outcomes == runs[0][0] and merged == runs[0][3]
        np.testing.assert_array_equal(counts, runs[0][2])
        np.testing.assert_allclose(samples, runs[0][1], rtol=1e-9)


def test_resize_keeps_counts_and_means():
    raw, _, _ = tumble_stream(seed=29)
    buffer = SampleBuffer(capacity=100, k=6)
    buffer.set_reference(rough_reference(), 0.1, merge=True)
    buffer.add_many(raw)
    pairs = {tuple(a): (tuple(m), c)
             for a, m, c in zip(buffer.anchors, buffer.samples, buffer.counts, strict=True)}
    buffer.resize(capacity=60)
    assert buffer.fill == 60
    for a, m, c in zip(buffer.anchors, buffer.samples, buffer.counts, strict=True):
        assert pairs[tuple(a)] == (tuple(m), c)
    assert_bookkeeping_exact(buffer)


def test_readings_are_a_bounded_draw_of_recent_readings():
    """The evidence coverage() checks the shell against: where the readings really lie."""
    from mag_calibrator_ros.calibration.live.buffer import READING_HORIZON, READING_SAMPLE_SIZE

    rng = np.random.default_rng(40)
    buffer = SampleBuffer(capacity=30)
    first = rng.normal(0.0, 1.0, (10, 3)) + [100.0, 0.0, 0.0]
    buffer.add_many(first)
    np.testing.assert_array_equal(buffer.readings, first)
    buffer.set_reference(Calibration([100.0, 0.0, 0.0], np.eye(3), 1.0), 0.1)
    buffer.add([400.0, 1.0, 2.0])  # a magnitude outlier: refused, never evidence
    assert len(buffer.readings) == 10
    buffer.set_reference(None)
    buffer.add_many(rng.normal(0.0, 1.0, (5000, 3)) + [100.0, 0.0, 0.0])
    assert len(buffer.readings) == READING_SAMPLE_SIZE
    # after a change (a moved magnet) the draw soon describes the new situation
    buffer.add_many(rng.normal(0.0, 1.0, (3 * READING_HORIZON, 3)) + [0.0, 300.0, 0.0])
    assert np.mean(buffer.readings[:, 1] > 150.0) > 0.9
    again = SampleBuffer(capacity=30)
    again.add_many(first)
    np.testing.assert_array_equal(again.readings, first)  # deterministic
    buffer.clear()
    assert buffer.readings.shape == (0, 3)


def test_shift_moves_each_point_by_its_readings_mean_state_and_forgets_unknown_ones():
    """What was taken off the readings changed (a compensation put in force): each point
    moves by the change at the mean of its merged readings' states, its neighbours rebuilt;
    a point or reading whose state is unknown cannot move and is forgotten."""
    raw, _, _ = tumble_stream(seed=31)
    buffer = SampleBuffer(capacity=60, k=4)
    buffer.forget_states(1)
    buffer.set_reference(rough_reference(), 0.1, merge=True)
    for reading in raw:
        buffer.add(reading, state=[reading[0]])  # a state whose mean is the mean's x
    assert buffer.merged > 0
    before, anchors, counts = buffer.samples, buffer.anchors, buffer.counts
    draw = buffer.readings

    def change(states):
        return 0.01 * states * [[1.0, 0.0, 0.0]]

    assert buffer.shift(change) == 0  # the anchor moves as the mean (its readings with it)
    moved = buffer.anchors - anchors  # by 0.01 x of the readings' mean: ``samples`` but for
    np.testing.assert_allclose(moved, change(before[:, :1]), atol=0.02)  # its placing
    assert np.ptp(moved[:, 0]) > 1.0
    np.testing.assert_array_equal(buffer.counts, counts)
    np.testing.assert_allclose(buffer.readings - draw, change(draw[:, :1]), atol=1e-12)
    assert_bookkeeping_exact(buffer)
    buffer.set_reference(None)
    buffer.clear()
    buffer.add_many(raw[:40])  # no state: unknown
    for reading in raw[40:50]:
        buffer.add(reading, state=[1.0])
    assert buffer.shift(change) == 40
    assert buffer.fill == 10 and len(buffer.readings) == 10
    np.testing.assert_allclose(buffer.samples, raw[40:50] + change(np.ones((10, 1))))
    assert_bookkeeping_exact(buffer)
    with pytest.raises(ValueError, match='a state has 1 values here, got 2'):
        buffer.add([1.0, 2.0, 3.0], state=[1.0, 2.0])
