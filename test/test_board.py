# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The simulated board's earth and mounting: a misaligned magnetometer, a location (the World
Magnetic Model's field there) and a disturbed place."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mag_calibrator_ros.calibration.fit.earth_field import earth_field
from mag_calibrator_ros.sim import motion
from mag_calibrator_ros.sim.board import BoardModel
from mag_calibrator_ros.sim.config import SimConfig

QUIET = dict(noise_ut=0.0, motion='poses')


def test_misaligned_magnetometer_reads_the_rotated_field():
    misalignment = np.array([2.0, -1.5, 3.0])
    board = BoardModel(SimConfig(mag_misalignment_deg=tuple(misalignment), **QUIET))
    rotation = Rotation.from_rotvec(np.radians(misalignment)).as_matrix()
    np.testing.assert_allclose(board.mag_misalignment, rotation)
    for t in (0.0, 1.9, 7.7):
        sensed, truth_t = board.magnetometer(t)
        np.testing.assert_allclose(rotation @ sensed, truth_t * 1e6, atol=1e-9)
        np.testing.assert_allclose(truth_t, board.true_field_tesla(t), atol=1e-15)
    aligned = BoardModel(SimConfig(**QUIET))
    np.testing.assert_allclose(aligned.magnetometer(1.0)[0], aligned.true_field_tesla(1.0) * 1e6)


def test_a_location_gives_the_world_magnetic_model_field_with_its_declination():
    board = BoardModel(SimConfig(latitude=52.52, longitude=13.40, altitude_m=34.0, **QUIET))
    expected = earth_field(52.52, 13.40, 34.0)
    assert board.location_field == expected
    np.testing.assert_allclose(
        board.earth_field_ut,
        motion.earth_field(expected.intensity_nt / 1000.0, expected.inclination_deg,
                           expected.declination_deg))
    east, north, _ = board.earth_field_ut
    assert math.degrees(math.atan2(east, north)) == pytest.approx(expected.declination_deg)
    assert BoardModel(SimConfig(**QUIET)).location_field is None


def test_a_disturbed_place_scales_and_dips_the_field():
    plain = BoardModel(SimConfig(field_ut=50.0, inclination_deg=60.0, **QUIET)).earth_field_ut
    disturbed = BoardModel(SimConfig(field_ut=50.0, inclination_deg=60.0, field_scale=1.2,
                                     inclination_offset_deg=8.0, **QUIET)).earth_field_ut
    assert np.linalg.norm(disturbed) == pytest.approx(1.2 * np.linalg.norm(plain))
    dip = math.degrees(math.asin(-disturbed[2] / np.linalg.norm(disturbed)))
    assert dip == pytest.approx(68.0)


@pytest.mark.parametrize(('kwargs', 'message'), [
    ({'mag_misalignment_deg': (1.0, 2.0)}, 'mag_misalignment_deg must be 3 finite numbers'),
    ({'mag_misalignment_deg': (200.0, 0.0, 0.0)}, 'at most 180 deg'),
    ({'latitude': 52.0}, 'location: longitude must be within'),
    ({'latitude': 95.0, 'longitude': 0.0}, 'location: latitude must be within'),
    ({'field_scale': 0.0}, 'field_scale must be in'),
    ({'inclination_offset_deg': math.inf}, 'inclination_offset_deg must be a finite number'),
])
def test_bad_earth_and_mounting_settings_are_named(kwargs, message):
    with pytest.raises(ValueError, match=message):
        SimConfig(**kwargs)


# -- the robot's own field: the battery current and the warming die (issue #26) ------------------

def driving_board(**kwargs) -> BoardModel:
    """A quiet cmd_vel robot standing 5 s, then driving straight at top speed."""
    board = BoardModel(SimConfig(noise_ut=0.0, motion='cmd_vel', seed=3, **kwargs))
    for t in np.arange(5.0, 30.0, 0.1):
        board.trajectory.command(0.0, float(t), speed=0.5)
    return board


def test_the_battery_current_adds_its_field_along_the_configured_axes():
    board = driving_board(current_field_ut_per_a=(1.6, 0.0, -0.4), temperature_rise_c=0.0)
    plain = driving_board(temperature_rise_c=0.0)
    for t, amperes in ((2.0, 0.5), (20.0, 5.0)):  # idle, then the full current at top speed
        assert board.battery_current_a(t) == pytest.approx(amperes)
        difference = board.magnetometer(t)[0] - plain.magnetometer(t)[0]
        np.testing.assert_allclose(difference, np.array([1.6, 0.0, -0.4]) * amperes, atol=1e-9)
    truth = board.interference_truth()
    np.testing.assert_allclose(truth.current_field, [1.6e-6, 0.0, -0.4e-6])
    np.testing.assert_array_equal(truth.temperature_drift, np.zeros(3))


def test_the_hard_iron_drifts_with_the_warming_die_from_the_power_on_temperature():
    config = dict(temperature_c=20.0, temperature_rise_c=20.0, temperature_time_constant_s=60.0,
                  hard_iron_ut=(10.0, -5.0, 3.0))
    board = BoardModel(SimConfig(hard_iron_drift_ut_per_c=(0.2, 0.0, 0.1), **QUIET, **config))
    plain = BoardModel(SimConfig(**QUIET, **config))
    assert board.temperature_c(0.0) == 20.0
    assert board.temperature_c(60.0) == pytest.approx(20.0 + 20.0 * (1.0 - math.exp(-1.0)))
    assert board.temperature_c(1e5) == pytest.approx(40.0)
    for t in (0.0, 60.0, 600.0):
        rise = board.temperature_c(t) - 20.0
        difference = board.magnetometer(t)[0] - plain.magnetometer(t)[0]
        np.testing.assert_allclose(difference, np.array([0.2, 0.0, 0.1]) * rise, atol=1e-9)
    truth = board.interference_truth()
    assert truth.reference_temperature_c == 20.0
    np.testing.assert_allclose(truth.temperature_drift, [0.2e-6, 0.0, 0.1e-6])
    np.testing.assert_allclose(truth.hard_iron, [10e-6, -5e-6, 3e-6])
    assert board.battery_current_a(1.0) is None  # a hand-held board draws no motor current


def test_without_the_robots_field_the_board_reads_as_before():
    board = driving_board()
    for t in (0.0, 12.0, 25.0):
        sensed, truth = board.magnetometer(t)
        np.testing.assert_allclose(sensed, truth * 1e6, atol=1e-12)


@pytest.mark.parametrize(('kwargs', 'message'), [
    ({'current_field_ut_per_a': (8.0, 0.0, 0.0)}, 'needs motion cmd_vel'),
    ({'motion': 'cmd_vel', 'current_field_ut_per_a': (500.0, 0.0, 0.0)}, 'a wire 2 mm'),
    ({'hard_iron_drift_ut_per_c': (0.2, math.nan, 0.0)}, 'hard_iron_drift_ut_per_c must be 3'),
    ({'temperature_time_constant_s': 0.0}, 'temperature_time_constant_s must be in'),
])
def test_bad_robot_field_settings_are_named(kwargs, message):
    with pytest.raises(ValueError, match=message):
        SimConfig(**kwargs)


def test_a_recorded_course_logs_the_current_and_temperature_each_reading_saw():
    from mag_calibrator_ros.sim.board import course_recording

    board = BoardModel(SimConfig(noise_ut=0.0, motion='cmd_vel', seed=2, temperature_c=30.0,
                                 temperature_rise_c=10.0, temperature_time_constant_s=5.0,
                                 current_field_ut_per_a=(2.0, 0.0, 0.0),
                                 hard_iron_drift_ut_per_c=(0.0, 0.5, 0.0)))
    course = motion.CourseDriver((motion.Leg(2.0), motion.Leg(4.0, speed=0.5),
                                  motion.Leg(2.0, yaw_rate=0.8)))
    recording = course_recording(board, course, rate_hz=50.0)
    assert len(recording.times) == 400 and recording.times[-1] == pytest.approx(7.98)
    offset = (recording.mag - recording.truth) * 1e6
    expected = np.column_stack([2.0 * recording.current_a, 0.5 * (recording.temperature_c - 30.0),
                                np.zeros(400)])
    np.testing.assert_allclose(offset, expected, atol=1e-9)
    assert recording.current_a[:100].max() == 0.5 and recording.current_a.max() == 5.0
    assert not recording.moving[:100].any() and recording.moving[150:].all()
    warmed = 30.0 + 10.0 * (1.0 - math.exp(-7.98 / 5.0))
    assert recording.temperature_c[-1] == pytest.approx(warmed)
    with pytest.raises(ValueError, match='motion is cmd_vel'):
        course_recording(BoardModel(SimConfig(**QUIET)), course)
