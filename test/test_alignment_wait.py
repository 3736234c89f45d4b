# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""With an IMU, the first automatic calibration waits (bounded) for the still tilts that align
it, so the corrected field is in the IMU frame from its first message (issue #24); with the
gyroscope's own fit (``gyro_aided``, issue #44) the turning aligns it and nothing waits."""

from __future__ import annotations

import numpy as np
import pytest

from mag_calibrator_ros.calibration.fit.alignment import rotation_angle_deg
from mag_calibrator_ros.calibration.live.alignment_wait import NO_STILL_WAIT_S
from mag_calibrator_ros.calibration.live.session import CalibrationSession
from mag_calibrator_ros.calibration.live.settings import SessionSettings
from mag_calibrator_ros.sim.board import BoardModel, board_readings
from mag_calibrator_ros.sim.config import SimConfig

RATE_HZ = 100.0
MISALIGNMENT_DEG = (1.8, -1.9, 1.4)  # 3.0 deg
SENSOR = {'hard_iron_ut': (120.0, -80.0, 60.0), 'noise_ut': 0.3,
          'mag_misalignment_deg': MISALIGNMENT_DEG}


def board(motion: str, seed: int = 1) -> BoardModel:
    return BoardModel(SimConfig(motion=motion, seed=seed, **SENSOR))


def tumble_then_poses(tumble_s: float, poses_s: float):
    """A hand tumbling the sensor (coverage, never still), then holding it still at one tilt
    after another: (mag T, accel, gyro) rows at RATE_HZ, and the misalignment."""
    parts = [board_readings(board('tumble'), tumble_s, RATE_HZ)]
    if poses_s:
        parts.append(board_readings(board('poses'), poses_s, RATE_HZ))
    return (*(np.concatenate(rows) for rows in zip(*parts, strict=True)),
            board('tumble').mag_misalignment)


def run(mag, accel, gyro, imu: bool = True, gyro_aided: bool = False):
    """Stream it; returns the session, the stream time of the first adoption, the calibration
    adopted then, every event and the progress lines once a second. The wait is the rule of
    the sphere's fits: the gyroscope's own (``gyro_aided``) is off unless asked for."""
    session = CalibrationSession(SessionSettings(gyro_aided=gyro_aided))
    first_s = first = None
    events, progress = [], []
    for index in range(len(mag)):
        stamp = round(index * 1e9 / RATE_HZ)
        if imu:
            session.process_imu(stamp, 'imu_link', accel[index], gyro[index])
        session.process(stamp, 'imu_link', mag[index])
        new = session.take_events()
        events += new
        if first is None and any(event.adopted for event in new):
            first_s, first = index / RATE_HZ, session.calibration
        if index % int(RATE_HZ) == 0 and session.calibration is None:
            progress.append(session.report(measure_coverage=True).progress)
    return session, first_s, first, events, progress


@pytest.fixture(scope='module')
def tumbled_then_held():
    mag, accel, gyro, misalignment = tumble_then_poses(12.0, 30.0)
    return run(mag, accel, gyro), misalignment


def test_the_first_calibration_waits_for_still_tilts_and_goes_in_force_aligned(
        tumbled_then_held):
    (session, first_s, first, events, progress), misalignment = tumbled_then_held
    assert first is not None, progress[-1]
    assert first_s > 12.0  # ready during the tumble, held back until aligned
    assert first.aligned
    assert rotation_angle_deg(first.rotation @ misalignment.T) < 0.5
    waiting = [line for line in progress if 'waiting for still tilts' in line]
    assert waiting and 'hold the sensor still' in waiting[0]
    assert sum('waiting for still tilts' in e.message for e in events if e.level == 'info') == 1
    assert session.report().counts.adoptions.get('auto') == 1


def test_a_sensor_never_held_still_is_calibrated_unaligned_after_the_bound():
    mag, accel, gyro, _ = tumble_then_poses(12.0 + NO_STILL_WAIT_S, 0.0)
    session, first_s, first, events, _ = run(mag, accel, gyro)
    assert first is not None and not first.aligned
    assert first_s >= NO_STILL_WAIT_S
    said = [e.message for e in events if e.adopted]
    assert 'NOT aligned to the IMU' in said[0] and e_level(events, said[0]) == 'warning'


def e_level(events, message: str) -> str:
    return next(event.level for event in events if event.message == message)


def test_without_an_imu_nothing_waits():
    mag, accel, gyro, _ = tumble_then_poses(12.0, 0.0)
    session, first_s, first, events, progress = run(mag, accel, gyro, imu=False)
    assert first is not None and first_s < 12.0
    assert not any('still tilts' in line for line in progress)
    assert 'alignment_wait_s' not in session.report(12.0, measure_coverage=True).values


def test_with_the_gyroscope_the_tumble_alone_is_calibrated_aligned_without_waiting():
    """The gyroscope turns the IMU frame: readings it turned back agree only in that frame, so
    the gyro-aided fit finds the magnetometer's 3 deg rotation from the tumble, never still."""
    mag, accel, gyro, misalignment = tumble_then_poses(12.0, 0.0)
    session, first_s, first, events, _ = run(mag, accel, gyro, gyro_aided=True)
    assert first is not None and first_s <= 12.0, [event.message for event in events]
    assert first.metadata.get('aligned_by') == 'gyroscope'
    assert rotation_angle_deg(first.rotation.T @ misalignment) < 1.0
    assert not any('waiting for still tilts' in event.message for event in events)
