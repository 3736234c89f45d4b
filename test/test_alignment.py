# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Magnetometer-to-IMU alignment from gravity: properties over random rotations, dips and noise;
the gates; gross mounting errors named; quasi-static stretches from a paired stream."""

from __future__ import annotations

import math
import re

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mag_calibrator_ros.calibration.fit.alignment import (
    ATTITUDE_WIDTH,
    MIN_STILL_S,
    AlignmentOptions,
    StaticAttitudes,
    describe_rotation,
    estimate_alignment,
    nearest_remap,
    rotation_angle_deg,
)
from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.sim import motion
from mag_calibrator_ros.sim.board import BoardModel
from mag_calibrator_ros.sim.config import SimConfig

GRAVITY = 9.80665
SOFT_IRON = np.array([[1.15, 0.10, -0.08], [0.10, 0.85, 0.12], [-0.08, 0.12, 1.00]])
HARD_IRON = np.array([120.0, -80.0, 60.0])
EXACT = Calibration(HARD_IRON, np.linalg.inv(SOFT_IRON), 50.0)


def attitudes(mounting: np.ndarray, count: int = 20, dip_deg: float = 60.0, noise: float = 0.05,
              accel_noise: float = 0.002, seed: int = 0, orientations=None) -> np.ndarray:
    """Rows of held attitudes: the magnetometer reads ``mounting @ body field`` (a misalignment
    is mounting = A^T; an axis remap is the remap itself), with hard and soft iron and noise."""
    rng = np.random.default_rng(seed)
    earth = motion.earth_field(50.0, dip_deg)
    if orientations is None:
        orientations = Rotation.random(count, random_state=rng).as_matrix()
    rows = []
    for world_from_body in orientations:
        body = world_from_body.T @ earth
        raw = SOFT_IRON @ (mounting @ body) + HARD_IRON + rng.normal(0.0, noise, 3)
        accel = world_from_body.T @ [0.0, 0.0, GRAVITY] + rng.normal(0.0, accel_noise, 3)
        rows.append([*raw, *accel, 100.0, 1.0])
    return np.array(rows)


@settings(max_examples=40, deadline=None, derandomize=True)
@given(rotvec=st.tuples(*[st.floats(-6.0, 6.0)] * 3),
       dip=st.floats(-75.0, 75.0).filter(lambda d: abs(d) > 12.0),
       noise=st.sampled_from([0.0, 0.02, 0.1]),
       seed=st.integers(0, 1000))
def test_a_small_misalignment_is_recovered(rotvec, dip, noise, seed):
    misalignment = Rotation.from_rotvec(np.radians(rotvec)).as_matrix()
    rows = attitudes(misalignment.T, 25, dip, noise, seed=seed)
    alignment = estimate_alignment(rows, EXACT, AlignmentOptions(expected_inclination_deg=dip))
    assert alignment.success, alignment.reason
    error = rotation_angle_deg(alignment.rotation @ misalignment.T)
    # 0.1 uT of 50 uT is 0.11 deg per attitude (accel noise 0.012 deg). Over 400 random cases
    # at 0.1 uT the worst were 0.18 deg (rotation), 0.10 deg (dip), 0.17 deg (dip scatter).
    assert error <= 0.03 + 2.5 * noise
    assert alignment.dip_deg == pytest.approx(dip, abs=0.03 + 1.5 * noise)
    assert alignment.dip_std_deg <= 0.03 + 2.0 * noise
    assert alignment.angle_deg == pytest.approx(rotation_angle_deg(misalignment), abs=error + 1e-6)
    assert alignment.handedness == 'right'
    corrected = EXACT.with_rotation(alignment.rotation)
    assert corrected.aligned


def test_alignment_makes_the_dip_constant_and_says_how_much_it_gained():
    misalignment = Rotation.from_rotvec(np.radians([3.0, -2.0, 1.0])).as_matrix()
    alignment = estimate_alignment(attitudes(misalignment.T), EXACT)
    assert alignment.dip_std_before_deg > 1.0 > 0.1 > alignment.dip_std_deg
    assert alignment.static_samples == 20 and alignment.outliers == 0
    assert alignment.rotation_std_deg < 0.1
    summary = alignment.summary()
    assert re.match(r'aligned to the IMU: rotation 3\.7\d deg, dip (59\.99|60\.0\d) deg', summary)
    assert set(alignment.as_dict()) >= {'rotation', 'angle_deg', 'dip_deg', 'dip_std_deg',
                                        'static_samples'}
    assert alignment.metadata()['static_samples'] == 20


def test_a_calibration_carrying_a_rotation_is_aligned_from_its_unrotated_field():
    misalignment = Rotation.from_rotvec(np.radians([2.0, 0.0, 0.0])).as_matrix()
    rows = attitudes(misalignment.T)
    carrying = EXACT.with_rotation(Rotation.from_rotvec([0.0, 0.0, 0.3]).as_matrix())
    again = estimate_alignment(rows, carrying)
    assert rotation_angle_deg(again.rotation @ misalignment.T) < 0.05


def test_spikes_and_accelerating_attitudes_are_left_out():
    misalignment = Rotation.from_rotvec(np.radians([1.0, 2.0, -1.0])).as_matrix()
    rows = attitudes(misalignment.T, 30)
    rows[3, :3] += [40.0, 0.0, 0.0]  # a spike: |field| far from F
    rows[7, 3:6] *= 1.2  # accelerating: |a| 20 % off
    rows[11, 3:6] = Rotation.from_rotvec([0.0, 0.1, 0.0]).apply(rows[11, 3:6])  # pushed sideways
    rows[12, :] = np.nan
    alignment = estimate_alignment(rows, EXACT)
    assert alignment.success
    # |a| and |field| screen the accelerating one and the NaN; the spike keeps its magnitude
    # (pointing elsewhere) and the sideways push keeps |a|: the robust fit leaves both out.
    assert alignment.static_samples == 26 and alignment.outliers == 2
    assert rotation_angle_deg(alignment.rotation @ misalignment.T) < 0.05


@pytest.mark.parametrize(('rows', 'message'), [
    (np.empty((0, ATTITUDE_WIDTH)), 'too few static attitudes .0 of 0'),
    (attitudes(np.eye(3), 4), 'too few static attitudes .4 of 4'),
    (attitudes(np.eye(3), orientations=[
        Rotation.from_euler('ZYX', [heading, 0.02 * k, 0.0]).as_matrix()
        for k, heading in enumerate(np.linspace(0.0, 6.0, 12))]),
     'gravity directions too close .the static attitudes spread'),
])
def test_gates_say_what_to_do(rows, message):
    alignment = estimate_alignment(rows, EXACT)
    assert not alignment.success
    assert alignment.reason.startswith(message.split(' .')[0])
    assert re.search(message, alignment.reason)
    assert 'hold' in alignment.reason or 'tilt' in alignment.reason


def test_scattered_dips_are_not_determined():
    rows = attitudes(np.eye(3), 30, accel_noise=0.0)
    rng = np.random.default_rng(3)
    for row in rows:  # each attitude's gravity tilted by ~10 deg at random: not static at all
        row[3:6] = Rotation.from_rotvec(rng.normal(0.0, 0.15, 3)).apply(row[3:6])
    alignment = estimate_alignment(rows, EXACT)
    assert not alignment.success
    assert ('dip not determined' in alignment.reason
            or 'rotation not determined' in alignment.reason)


@pytest.mark.parametrize(('rotvec_deg', 'remap', 'described'), [
    ((180.0, 0.0, 0.0), '(x, -y, -z)', '180 deg about x'),  # the AK09916's y/z inversion
    ((0.0, 0.0, 90.0), '(-y, x, z)', '90 deg about z'),
    ((0.0, 180.0, 0.0), '(-x, y, -z)', '180 deg about y'),
])
def test_a_gross_rotation_is_named_with_its_remap_and_not_applied(rotvec_deg, remap, described):
    mounting = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix().T
    alignment = estimate_alignment(attitudes(mounting), EXACT,
                                   AlignmentOptions(expected_inclination_deg=60.0))
    assert not alignment.success
    assert 'gross mounting error' in alignment.reason and described in alignment.reason
    assert alignment.remap == remap and remap in alignment.reason
    assert alignment.dip_std_before_deg > 10.0 > 0.1 > alignment.dip_std_deg
    fixed = _remapped(attitudes(mounting), remap)
    assert estimate_alignment(fixed, EXACT).angle_deg < 0.15  # the remap named does fix it


@pytest.mark.parametrize(('mounting', 'remap'), [
    (np.diag([1.0, 1.0, -1.0]), '(x, y, -z)'),
    (np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), '(y, x, z)'),
])
def test_a_left_handed_remap_is_detected_with_the_model_dip(mounting, remap):
    rows = attitudes(mounting)
    alignment = estimate_alignment(rows, EXACT, AlignmentOptions(expected_inclination_deg=60.0))
    assert not alignment.success and alignment.handedness == 'left'
    assert 'left-handed' in alignment.reason and alignment.remap == remap
    fixed = estimate_alignment(_remapped(rows, remap), EXACT,
                               AlignmentOptions(expected_inclination_deg=60.0))
    assert fixed.success and fixed.angle_deg < 0.15
    # Without the model, the reflection looks like the southern hemisphere: said, not guessed.
    unknown = estimate_alignment(rows, EXACT)
    assert unknown.handedness == 'unknown' and 'southern hemisphere' in unknown.note


def test_a_location_in_the_wrong_hemisphere_is_named_before_any_remap():
    """A right-handed board in the north given a southern location: the dip's sign disagrees
    with the model's exactly as a left-handed remap would make it, so both are named, the
    location first (it used to advise only a remap to (-x, -y, -z))."""
    alignment = estimate_alignment(attitudes(np.eye(3)), EXACT,
                                   AlignmentOptions(expected_inclination_deg=-60.0))
    assert not alignment.success and alignment.handedness == 'left'
    reason = alignment.reason
    assert reason.startswith('a wrong location or left-handed axes:')
    assert 'the location is wrong' in reason and 'latitude' in reason and 'gps/fix' in reason
    assert reason.index('location is wrong') < reason.index('remap the magnetometer')
    assert '(-x, -y, -z)' in reason


def test_southern_hemisphere_is_right_handed_with_the_model():
    rows = attitudes(np.eye(3), dip_deg=-55.0)
    alignment = estimate_alignment(rows, EXACT, AlignmentOptions(expected_inclination_deg=-55.0))
    assert alignment.success and alignment.handedness == 'right'
    assert alignment.dip_deg == pytest.approx(-55.0, abs=0.05)


def _remapped(rows: np.ndarray, remap: str) -> np.ndarray:
    """Apply a remap such as '(x, -y, -z)' to the raw field of the rows, about the hard iron:
    what a driver fixed that way would have published (with the remapped hard iron)."""
    names = remap.strip('()').split(', ')
    matrix = np.zeros((3, 3))
    for row, name in enumerate(names):
        matrix[row, 'xyz'.index(name[-1])] = -1.0 if name.startswith('-') else 1.0
    fixed = rows.copy()
    body = (rows[:, :3] - HARD_IRON) @ np.linalg.inv(SOFT_IRON).T  # the mounting's own reading
    fixed[:, :3] = (body @ matrix.T) @ SOFT_IRON.T + HARD_IRON
    return fixed


def test_remap_names_and_rotation_descriptions():
    assert nearest_remap(np.diag([1.0, -1.0, -1.0])) == ('(x, -y, -z)', 0.0)
    text, residual = nearest_remap(Rotation.from_rotvec([0.0, 0.0, math.radians(93.0)])
                                   .as_matrix())
    assert text == '(-y, x, z)' and residual == pytest.approx(3.0)
    assert describe_rotation(np.eye(3)) == '0 deg'
    assert 'about (' in describe_rotation(Rotation.from_rotvec([1.0, 1.0, 0.0]).as_matrix())


# -- quasi-static stretches ----------------------------------------------------------------------


def stream(trajectory_kind: str, gyro: bool, seconds: float = 40.0, rate_hz: float = 100.0,
           misalignment=(1.8, -1.9, 1.4), seed: int = 0):
    """A paired stream from the simulated board, fed to StaticAttitudes; returns it and the
    board."""
    board = BoardModel(SimConfig(mag_misalignment_deg=misalignment, hard_iron_ut=tuple(HARD_IRON),
                                 soft_iron=tuple(SOFT_IRON.reshape(9)), noise_ut=0.3,
                                 motion=trajectory_kind, seed=seed))
    collected = StaticAttitudes()
    collected.field_scale = 50.0 / np.linalg.det(EXACT.matrix) ** (1 / 3)
    for k in range(int(seconds * rate_hz)):
        t = k / rate_hz
        field, _ = board.magnetometer(t)
        accel, rate, _ = board.inertial(t, 57.0, 57.0)
        collected.add(t, field, accel, rate if gyro else None)
    collected.finish()
    return collected, board


@pytest.mark.parametrize('gyro', [True, False])
def test_held_poses_become_one_attitude_each_and_align_within_a_tenth_of_a_degree(gyro):
    collected, board = stream('poses', gyro)
    holds = int(40.0 / 2.0) + 1  # a pose every 0.8 s held + 1.2 s turning
    assert holds - 1 <= collected.fill <= holds + 3
    rows = collected.snapshot()
    assert np.all(rows[:, 6] >= MIN_STILL_S * 100.0)  # each averages a hold's readings
    alignment = estimate_alignment(rows, EXACT)
    assert alignment.success
    assert rotation_angle_deg(alignment.rotation @ board.mag_misalignment.T) < 0.1
    assert alignment.dip_std_deg < 0.1


@pytest.mark.parametrize('gyro', [True, False])
def test_a_tumbling_hand_is_never_still(gyro):
    collected, _ = stream('tumble', gyro, seconds=20.0)
    assert collected.fill == 0
    assert 'too few static attitudes' in estimate_alignment(collected.snapshot(), EXACT).reason


def test_a_slow_log_counts_lone_readings_and_a_fast_one_does_not():
    rows = attitudes(np.eye(3), 10)
    for rate, expected in ((3.0, 10), (100.0, 0)):
        collected = StaticAttitudes()
        for k, row in enumerate(rows):
            collected.add(k / rate, row[:3], row[3:6])
        collected.finish()
        assert collected.fill == expected, rate


def test_stretches_end_on_motion_gaps_and_bad_values():
    collected = StaticAttitudes()
    level = np.array([0.0, 0.0, GRAVITY])
    field = np.array([20.0, 0.0, -40.0])
    for k in range(50):  # 0.5 s held
        collected.add(k / 100, field, level, np.zeros(3))
    collected.add(0.50, field, level, np.array([0.0, 0.5, 0.0]))  # turning: ends it
    for k in range(10):  # 0.1 s: too short
        collected.add(0.6 + k / 100, field, level, np.zeros(3))
    collected.add(0.70, [math.nan, 0.0, 0.0], level, np.zeros(3))
    collected.add(0.71, field, [0.0, 0.0, 0.0], np.zeros(3))
    assert collected.refused == 2 and collected.fill == 1 and collected.readings == 63
    (row,) = collected.snapshot()
    assert row[6] == 50 and row[7] == pytest.approx(0.49)
    collected.clear()
    assert collected.fill == 0


def test_the_same_pose_held_twice_is_merged_and_a_full_store_stays_spread():
    collected = StaticAttitudes(capacity=8)
    collected.field_scale = 50.0
    rows = attitudes(np.eye(3), 30, noise=0.0, accel_noise=0.0, seed=5)
    time = 0.0
    for row in [*rows[:4], rows[0], *rows[4:]]:  # pose 0 twice
        for _ in range(30):
            collected.add(time, row[:3], row[3:6], np.zeros(3))
            time += 0.01
        time += 1.0  # a pause ends the stretch (gap)
    collected.finish()
    assert collected.stretches == 31 and collected.fill == 8
    gravity = collected.snapshot()[:, 3:6] / GRAVITY
    closest = min(np.degrees(np.arccos(np.clip(a @ b, -1, 1)))
                  for i, a in enumerate(gravity) for b in gravity[i + 1:])
    assert closest > 10.0  # the kept poses are spread, not the first eight


# -- without a clock (a log without time stamps) --------------------------------------------------


def test_without_a_clock_the_rows_decide_not_a_guessed_rate():
    """A slow log: every row is an attitude whatever time it is said to have been taken at."""
    rows = attitudes(np.eye(3), 10)
    snapshots = []
    for rate in (1.0, 3.0, 100.0, 1e4):
        collected = StaticAttitudes(clock=False)
        for k, row in enumerate(rows):
            collected.add(k / rate, row[:3], row[3:6])
        collected.finish()
        snapshots.append(collected.snapshot())
    assert len(snapshots[0]) == 10
    for snapshot in snapshots[1:]:
        np.testing.assert_array_equal(snapshot, snapshots[0])


def clockless(trajectory_kind: str, rate_hz: float, seconds: float = 40.0):
    """The simulated board's stream without its times or gyroscope (a log of six columns)."""
    board = BoardModel(SimConfig(mag_misalignment_deg=(1.8, -1.9, 1.4),
                                 hard_iron_ut=tuple(HARD_IRON),
                                 soft_iron=tuple(SOFT_IRON.reshape(9)), noise_ut=0.3,
                                 motion=trajectory_kind, seed=0))
    collected = StaticAttitudes(clock=False)
    collected.field_scale = 50.0 / np.linalg.det(EXACT.matrix) ** (1 / 3)
    for k in range(int(seconds * rate_hz)):
        field, _ = board.magnetometer(k / rate_hz)
        accel, _, _ = board.inertial(k / rate_hz, 57.0, 57.0)
        collected.add(0.0, field, accel)
    collected.finish()
    return collected, board


@pytest.mark.parametrize('rate_hz', [100.0, 25.0])
def test_without_a_clock_a_fast_log_uses_its_holds_not_its_turns(rate_hz):
    collected, board = clockless('poses', rate_hz)
    rows = collected.snapshot()
    assert 19 <= len(rows) <= 24  # the holds (a pose every 2 s), not the hundreds of turns
    assert collected.stretches > 10 * len(rows)
    alignment = estimate_alignment(rows, EXACT)
    assert alignment.success, alignment.reason
    assert rotation_angle_deg(alignment.rotation @ board.mag_misalignment.T) < 0.15


def test_without_a_clock_a_tumble_is_refused_not_aligned_wrong():
    collected, _ = clockless('tumble', 100.0, seconds=20.0)
    alignment = estimate_alignment(collected.snapshot(), EXACT)
    assert not alignment.success
    assert 'too few static attitudes' in alignment.reason


def test_without_a_clock_a_full_store_keeps_its_holds():
    collected = StaticAttitudes(capacity=4, clock=False)
    collected.field_scale = 50.0
    rows = attitudes(np.eye(3), 12, noise=0.0, accel_noise=0.0, seed=5)
    for row in rows[:4]:  # four holds of 50 readings ...
        for _ in range(50):
            collected.add(0.0, row[:3], row[3:6])
        collected.add(0.0, [math.nan] * 3, row[3:6])
    for row in rows[4:]:  # ... then eight poses passed through
        collected.add(0.0, row[:3], row[3:6])
        collected.add(0.0, [math.nan] * 3, row[3:6])
    collected.finish()
    assert sorted(collected.snapshot()[:, 7]) == [50, 50, 50, 50]
