# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Gravity's direction from the accelerometer only while it measures gravity: the gyroscope
tells a ground robot's tilt from its drive's acceleration (``live/gravity.py``), so a planar fit
levelled after straight legs is not tilted by them."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from mag_calibrator_ros.calibration.live.gravity import (
    GRAVITY_DEG,
    MAX_STEP_S,
    RATE_DISAGREE,
    RESTART_S,
    SETTLE_S,
    GravityTracker,
    RateCheck,
)
from mag_calibrator_ros.calibration.live.offline import calibrate_now, feed
from mag_calibrator_ros.calibration.live.session import CalibrationSession
from mag_calibrator_ros.calibration.live.settings import SessionSettings
from mag_calibrator_ros.sim import motion
from mag_calibrator_ros.sim.board import BoardModel, course_recording
from mag_calibrator_ros.sim.config import SimConfig
from mag_calibrator_ros.tools.fit import gravity_directions
from mag_calibrator_ros.tools.recordings import read_recording

RATE_HZ = 100.0
RAZOR = Path(__file__).resolve().parent / 'data' / 'imu_tools' / 'sparkfun_razor.bag'
"""A real SparkFun 9DoF Razor turned by hand (imu_tools' sample, GPL-3.0-or-later)."""
HARD_IRON_UT = (55.0, -45.0, 25.0)
SOFT_IRON = (1.1, 0.08, 0.0, 0.08, 0.9, 0.05, 0.0, 0.05, 1.0)
TURN_AND_DRIVE = motion.GROUND_COURSE[:4]
"""Standing, a turn in place on a 2° wobbly floor, 15 s straight at 0.5 m/s (starting and
stopping at 1 m/s^2: the accelerometer tilts 5.8° in each), standing."""


def robot(seed: int = 1, gyro_bias_dps: tuple[float, float, float] = (0.0, 0.0, 0.0),
          noise_ut: float = 0.3) -> BoardModel:
    trajectory = motion.CmdVelTrajectory(seed=seed, wobble_deg=2.0)
    config = SimConfig(field_ut=50.0, inclination_deg=60.0, hard_iron_ut=HARD_IRON_UT,
                       soft_iron=SOFT_IRON, noise_ut=noise_ut, motion='cmd_vel', seed=seed,
                       gyro_bias_dps=gyro_bias_dps)
    return BoardModel(config, trajectory)


def angle_deg(a, b) -> float:
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    cosine = a @ b / (np.linalg.norm(a) * np.linalg.norm(b))
    return math.degrees(math.acos(min(1.0, cosine)))


def handheld(seconds: float = 30.0, seed: int = 1, with_field: bool = False) -> tuple:
    """(stamps ns, specific force, rates) of an IMU turned and shaken by hand (``tumble``), and
    its magnetometer's readings (uT) ``with_field``."""
    config = SimConfig(field_ut=50.0, inclination_deg=60.0, hard_iron_ut=HARD_IRON_UT,
                       noise_ut=0.3, motion='tumble', seed=seed)
    board = BoardModel(config, motion.make_trajectory('tumble', seed))
    times = np.arange(0.0, seconds, 1.0 / RATE_HZ)
    rows = [board.inertial(t, 57.0, 57.0) for t in times]
    found = (np.round(times * 1e9).astype(np.int64), np.array([row[0] for row in rows]),
             np.array([row[1] for row in rows]))
    if not with_field:
        return found
    return (*found, np.array([board.magnetometer(t)[0] for t in times]))


def rates_over(stamps, accel, gyro) -> RateCheck:
    tracker = GravityTracker()
    for stamp, force, rate in zip(stamps.tolist(), accel.tolist(), gyro.tolist(), strict=True):
        tracker.update(stamp, tuple(force), tuple(rate))
    return tracker.rates


@pytest.mark.parametrize('bias_dps, bound_deg', [((0.0, 0.0, 0.0), 0.4),
                                                 ((2.0, -2.0, 1.0), GRAVITY_DEG)])
def test_gravity_follows_the_tilts_and_not_the_drive(bias_dps, bound_deg):
    board = robot(gyro_bias_dps=bias_dps)
    recording = course_recording(board, motion.CourseDriver(TURN_AND_DRIVE), rate_hz=RATE_HZ)
    tracker = GravityTracker()
    measured, tracked = [], []
    for t, accel, gyro in zip(recording.times, recording.accel, recording.gyro, strict=True):
        truth = board.trajectory.state(t).rotation.T @ (0.0, 0.0, 1.0)  # up in the chip frame
        measured.append(angle_deg(accel, truth))
        up = tracker.update(round(t * 1e9), tuple(accel), tuple(gyro), 'imu_link')
        tracked.append(math.nan if up is None else angle_deg(up, truth))
    measured, tracked = np.array(measured), np.array(tracked)
    assert measured.max() > 5.0  # the drive's starts and stops: the accelerometer is fooled
    given = np.isfinite(tracked)
    assert given.mean() > 0.9
    assert tracked[given].max() < bound_deg  # a lag of bias x CORRECTION_S at most
    assert tracker.rejected > 0.5 * RATE_HZ  # the starts and stops, not a few noisy samples
    tilt_axes = np.array(bias_dps[:2])  # the floor barely tilts: x, y are the tilt axes
    assert np.allclose(np.degrees(tracker.bias[:2]), tilt_axes, atol=0.3)


def test_without_a_gyroscope_the_specific_force_is_taken_as_it_is():
    """Nothing tells an acceleration from a tilt then: what every reading was levelled by."""
    tracker = GravityTracker()
    assert tracker.update(0, (0.0, 3.0, 4.0), None) == (0.0, 0.6, 0.8)
    assert tracker.update(10_000_000, (0.0, 0.0, 2.0), None) == (0.0, 0.0, 1.0)
    assert tracker.rejected == 0


def test_a_sample_without_its_rate_is_skipped_once_a_gyroscope_came():
    """A log whose gyroscope cells are missing now and then (sensors logged at other rates)
    keeps its gravity: each such sample is skipped, not a restart and a second of settling."""
    tracker = GravityTracker()
    step = round(1e9 / RATE_HZ)
    given = []
    for k in range(round(5.0 * RATE_HZ)):
        gyro = None if k % 10 == 9 else (0.0, 0.0, 0.0)
        given.append(tracker.update(k * step, (0.0, 0.0, 9.81), gyro, 'imu_link'))
    assert all(up is None for up in given[9::10])
    settled = [up for k, up in enumerate(given) if k % 10 != 9 and k >= 2 * RATE_HZ]
    assert all(up == pytest.approx((0.0, 0.0, 1.0)) for up in settled)
    tracker.restart()  # a new sensor: it may have no gyroscope
    assert tracker.update(6_000_000_000, (0.0, 0.0, 9.81), None) == (0.0, 0.0, 1.0)


def steady(tracker: GravityTracker, start_ns: int, seconds: float, force=(0.0, 0.0, 9.81),
           gyro=(0.0, 0.0, 0.0), frame_id: str = 'imu_link') -> list:
    step = round(1e9 / RATE_HZ)
    return [tracker.update(start_ns + k * step, force, gyro, frame_id)
            for k in range(round(seconds * RATE_HZ))]


def test_it_settles_before_it_says_and_restarts_where_the_gyroscope_cannot_carry_it():
    tracker = GravityTracker()
    ups = steady(tracker, 0, 2.0)
    settled = round(SETTLE_S * RATE_HZ)
    assert all(up is None for up in ups[:settled - 1])
    assert all(up == pytest.approx((0.0, 0.0, 1.0)) for up in ups[settled + 1:])
    last_ns = round(1.99e9)
    again = tracker.update(last_ns, (0.0, 0.0, 9.81), (0.0, 0.0, 0.0), 'imu_link')
    assert again is not None and again == ups[-1]  # the same instant again: the same answer
    restarts = {
        'a gap': last_ns + round((MAX_STEP_S + 0.01) * 1e9),
        'a stamp going back': last_ns - 5_000_000_000,
    }
    for why, stamp_ns in restarts.items():
        assert tracker.update(stamp_ns, (0.0, 0.0, 9.81), (0.0, 0.0, 0.0), 'imu_link') is None, why
        ups = steady(tracker, stamp_ns + 10_000_000, 2.0)
        assert ups[0] is None and ups[-1] is not None, why
        last_ns = stamp_ns + 10_000_000 + round(1.99e9)
    assert tracker.update(last_ns + 10_000_000, (0.0, 0.0, 9.81), (0.0, 0.0, 0.0),
                          'base_link') is None  # another frame: another sensor
    ups = steady(tracker, last_ns + 20_000_000, 2.0, frame_id='base_link')
    assert ups[-1] is not None
    # a rate beyond any gyroscope's (its norm overflows) restarts it instead of raising
    huge_ns = last_ns + 20_000_000 + round(2e9)
    assert tracker.update(huge_ns, (0.0, 0.0, 9.81), (1.7e308,) * 3, 'base_link') is None
    assert tracker.update(huge_ns + 10_000_000, (0.0, 0.0, 9.81), (0.0, 0.0, 0.0),
                          'base_link') is None  # settling again


def test_an_acceleration_is_no_gravity_until_it_lasts_too_long_to_be_one():
    tracker = GravityTracker()
    steady(tracker, 0, 2.0)
    pushed = (1.0, 0.0, 9.81)  # 1 m/s^2 forward with no rotation: 5.8° of false tilt
    ups = steady(tracker, 2_000_000_000, RESTART_S + SETTLE_S + 1.0, force=pushed)
    within = round(0.1 * RATE_HZ)
    assert all(up is None for up in ups[within:round(RESTART_S * RATE_HZ)])
    assert ups[-1] is not None  # restarted on the accelerometer: a slope it was started on
    assert angle_deg(ups[-1], pushed) < 0.1
    assert tracker.rejected >= (RESTART_S - 0.1) * RATE_HZ


def test_a_planar_fit_after_a_straight_leg_is_not_tilted_by_its_start_and_stop():
    """Until gravity was tracked, the levelled fit took the 5.8° of the drive's starts and stops
    for tilts: here y's offset 1.1 µT off and 0.97° RMS of heading error (now 0.35 µT, 0.27°)."""
    board = robot()
    recording = course_recording(board, motion.CourseDriver(TURN_AND_DRIVE), rate_hz=RATE_HZ)
    session = CalibrationSession(SessionSettings())
    feed(session, recording.mag, RATE_HZ, frame_id='imu_link', accel=recording.accel,
         gyro=recording.gyro)
    attempt = calibrate_now(session)
    assert attempt.success, attempt.message
    assert 'levelled by gravity' in attempt.message
    calibration = session.calibration
    assert np.allclose(np.asarray(calibration.offset[:2]) * 1e6, HARD_IRON_UT[:2], atol=1.0)
    clean = robot(noise_ut=0.0)
    turn = course_recording(clean, motion.CourseDriver(motion.GROUND_COURSE[:2]),
                            rate_hz=RATE_HZ)
    corrected = calibration.apply(turn.mag)
    moving = turn.times >= 5.0
    error = (np.arctan2(corrected[moving, 1], corrected[moving, 0])
             - np.arctan2(turn.truth[moving, 1], turn.truth[moving, 0]))
    error = np.degrees(np.mod(error + math.pi, 2.0 * math.pi) - math.pi)
    heading_rms = float(np.sqrt(np.mean(error**2)))
    assert heading_rms < 0.5, heading_rms


def test_the_whole_recording_fit_levels_by_the_same_gravity():
    """``mag_calibrator_fit --all`` takes gravity's directions as the node's pairing does."""
    board = robot()
    recording = course_recording(board, motion.CourseDriver(TURN_AND_DRIVE), rate_hz=RATE_HZ)
    stamps = np.round(recording.times * 1e9).astype(np.int64)
    ups, _ = gravity_directions(recording.accel, recording.gyro, stamps)
    accelerating = np.abs(np.gradient(recording.speed, recording.times)) > 0.5
    assert accelerating.sum() > 50
    assert np.isnan(ups[accelerating]).all(axis=1).mean() > 0.9
    without_gyro, _ = gravity_directions(recording.accel, None, stamps)
    assert np.allclose(without_gyro,
                       recording.accel / np.linalg.norm(recording.accel, axis=1)[:, None])
    broken = recording.accel.copy()
    broken[10] = (math.nan, 0.0, 0.0)
    broken[11] = 0.0
    assert np.isnan(gravity_directions(broken, recording.gyro, stamps)[0][10:12]).all()


def test_the_session_levels_only_by_what_was_gravity():
    board = robot()
    recording = course_recording(board, motion.CourseDriver(TURN_AND_DRIVE), rate_hz=RATE_HZ)
    session = CalibrationSession(SessionSettings(auto_calibrate=False))
    feed(session, recording.mag, RATE_HZ, frame_id='imu_link', accel=recording.accel,
         gyro=recording.gyro)
    report = session.report(0.0, measure_coverage=True)
    assert report.imu.accelerating > 50
    assert report.values['imu_samples_accelerating'] == report.imu.accelerating


def test_a_gyroscope_that_does_not_turn_with_the_accelerometer_is_named():
    """A gyroscope in deg/s (or with its signs flipped) makes every tilt look like an
    acceleration; checked against the accelerometer's own turning, on a simulated hand and on a
    real Razor's."""
    stamps, accel, gyro = handheld()
    agreeing = rates_over(stamps, accel, gyro)
    assert agreeing.agree and agreeing.scale > 0.8 and agreeing.problem() == ''
    in_degrees = rates_over(stamps, accel, np.degrees(gyro))
    assert not in_degrees.agree and in_degrees.scale < RATE_DISAGREE
    assert 'look like deg/s' in in_degrees.problem()
    flipped = rates_over(stamps, accel, -gyro)
    assert not flipped.agree and flipped.scale < 0.0
    assert 'axes' in flipped.problem() and 'look like deg/s' not in flipped.problem()
    razor = read_recording(RAZOR, accel_topic='')
    razor_stamps = np.round(razor.stamps * 1e9).astype(np.int64)
    real = rates_over(razor_stamps, razor.accel, razor.gyro)
    assert real.agree and real.scale > 0.8
    assert 'look like deg/s' in rates_over(razor_stamps, razor.accel,
                                           np.degrees(razor.gyro)).problem()


def test_glitches_of_either_sensor_never_turn_the_verdict():
    """One gyroscope sample beyond any hand; a tenth of a second of the accelerometer turned
    90° (a knock): a verdict over a hundred windows, not over the last one."""
    stamps, accel, gyro = handheld()
    clean = rates_over(stamps, accel, gyro)
    middle = len(stamps) // 2
    spiked = gyro.copy()
    spiked[middle] = (30.0, -30.0, 30.0)
    knocked = accel.copy()
    knocked[middle:middle + 10] = np.cross(accel[middle], (0.0, 0.0, 1.0))
    for forces, rates in ((accel, spiked), (knocked, gyro)):
        tracker = GravityTracker()
        for index, (stamp, force, rate) in enumerate(zip(stamps.tolist(), forces.tolist(),
                                                         rates.tolist(), strict=True)):
            tracker.update(stamp, tuple(force), tuple(rate))
            assert tracker.rates.agree, index
        assert abs(tracker.rates.scale - clean.scale) < 0.05


def test_a_gyroscope_bias_not_learnt_yet_is_no_disagreement():
    """A ground robot's correct gyroscope with the ICM-20948's largest zero-rate offset (5 °/s):
    until the tracker learns it, it turns gravity while the accelerometer does not."""
    for seed in (1, 2, 3):
        recording = course_recording(robot(seed, gyro_bias_dps=(5.0, -5.0, 1.0)),
                                     motion.CourseDriver(motion.GROUND_COURSE[:8]),
                                     rate_hz=RATE_HZ)
        tracker = GravityTracker()
        for t, force, rate in zip(recording.times, recording.accel, recording.gyro, strict=True):
            tracker.update(round(t * 1e9), tuple(force), tuple(rate))
            assert tracker.rates.agree, t


def test_the_check_follows_a_gyroscope_that_changes_and_forgets_on_a_restart():
    """A driver restarted in the right unit is trusted again within seconds; a reset or
    another sensor starts the check anew, and the session says it once until then."""
    stamps, accel, gyro = handheld(60.0)
    half = len(stamps) // 2
    tracker = GravityTracker()
    verdicts = []
    for index, (stamp, force, rate) in enumerate(zip(stamps.tolist(), accel.tolist(),
                                                     gyro.tolist(), strict=True)):
        rate = np.degrees(rate) if index < half else rate
        tracker.update(stamp, tuple(force), tuple(rate))
        verdicts.append(tracker.rates.agree)
    assert not verdicts[half - 1] and verdicts[-1] and tracker.rates.scale > 0.8
    tracker.restart()
    assert tracker.rates.agree and tracker.rates.scale is None
    session = CalibrationSession(SessionSettings(auto_calibrate=False))
    for stamp, force, rate in zip(stamps.tolist(), accel.tolist(), np.degrees(gyro).tolist(),
                                  strict=True):
        session.process_imu(stamp, 'imu_link', force, rate)
    said = [event for event in session.take_events() if 'angular_velocity' in event.message]
    assert len(said) == 1 and 'angular_velocity' in session.report().imu.warning
    session.reset()  # another sensor may follow: the check starts anew
    assert session.report().imu.warning == ''
    for stamp, force, rate in zip(stamps.tolist(), accel.tolist(), np.degrees(gyro).tolist(),
                                  strict=True):
        session.process_imu(stamp + stamps[-1] + 10**9, 'imu_link', force, rate)
    assert len([event for event in session.take_events()
                if 'angular_velocity' in event.message]) == 1
    session.close()


def test_a_ground_robot_is_warned_of_a_gyroscope_in_degrees_once():
    """On a 2° wobbly floor a deg/s gyroscope rejected a fifth of the samples as the robot
    accelerating, and nothing said why; turning on a level floor about gravity judges nothing."""
    recording = course_recording(robot(), motion.CourseDriver(motion.GROUND_COURSE[:8]),
                                 rate_hz=RATE_HZ)
    session = CalibrationSession(SessionSettings(auto_calibrate=False))
    feed(session, recording.mag, RATE_HZ, frame_id='imu_link', accel=recording.accel,
         gyro=np.degrees(recording.gyro))
    values = session.report(0.0, measure_coverage=True).values
    assert values['imu_turning_share'] < RATE_DISAGREE
    assert 'angular_velocity' in values['imu_warning'] and 'deg/s' in values['imu_warning']
    said = [event for event in session.take_events() if 'angular_velocity' in event.message]
    assert len(said) == 1 and said[0].level == 'warning'
    right = CalibrationSession(SessionSettings(auto_calibrate=False))
    feed(right, recording.mag, RATE_HZ, frame_id='imu_link', accel=recording.accel,
         gyro=recording.gyro)
    values = right.report(0.0, measure_coverage=True).values
    assert values['imu_warning'] == '' and values.get('imu_turning_share', 1.0) > 0.5
    session.close()
    right.close()


@pytest.mark.parametrize('mode', [[], ['--all']])
def test_the_offline_fit_notes_a_gyroscope_column_in_degrees(tmp_path, capsys, mode):
    """A log's gyroscope columns declared rad/s but holding deg/s: the fit says so."""
    from mag_calibrator_ros.tools import fit

    stamps, accel, gyro, field = handheld(with_field=True)
    lines = ['time,mx,my,mz,ax,ay,az,gx,gy,gz']
    for row in zip(stamps.tolist(), field.tolist(), accel.tolist(), np.degrees(gyro).tolist(),
                   strict=True):
        lines.append(','.join(repr(value) for value in (row[0] * 1e-9, *row[1], *row[2],
                                                       *row[3])))
    log = tmp_path / 'handheld.csv'
    log.write_text('\n'.join(lines) + '\n')
    notes = {}
    for unit in ('rad/s', 'deg/s'):
        fit.main([str(log), '--units', 'uT', '--accel-columns', 'ax,ay,az', '--gyro-columns',
                  'gx,gy,gz', '--gyro-units', unit, '--json', *mode])
        notes[unit] = [note for note in json.loads(capsys.readouterr().out)['input']['notes']
                       if note.startswith('the gyroscope columns')]
    assert len(notes['rad/s']) == 1 and 'look like deg/s' in notes['rad/s'][0]
    assert '--gyro-units' in notes['rad/s'][0]
    assert notes['deg/s'] == []
