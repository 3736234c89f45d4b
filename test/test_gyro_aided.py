"""The hard iron from the gyroscope's turning (fit/gyro_aided.py), the turning integrated between
messages (live/rotation_track.py) and the session's first calibration from it."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mag_calibrator_ros.calibration.fit.gyro_aided import (
    MAX_OFFSET_STD,
    TurnedReadings,
    fit_gyro_aided,
    turned_errors,
)
from mag_calibrator_ros.calibration.live.rotation_track import STEP_S, WINDOW_S, RotationTrack
from mag_calibrator_ros.calibration.live.session import CalibrationSession
from mag_calibrator_ros.calibration.live.settings import SessionSettings

EARTH = np.array([0.0, 19.0, -45.0])  # uT, a world-frame field (ENU, dip 67 deg)
RATE_HZ = 100.0


def wrist_motion(seconds: float, seed: int, axes: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Body rates (rad/s) of a hand turning a sensor within about 60 deg of one pose, and the
    attitudes (body to world) they integrate to; ``axes`` 1 turns about z only."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, seconds, 1.0 / RATE_HZ)
    rates = np.zeros((len(t), 3))
    for axis in range(3 if axes == 3 else 1):
        index = 2 if axes == 1 else axis
        for _ in range(3):
            frequency, phase = rng.uniform(0.1, 0.4), rng.uniform(0, 2 * math.pi)
            rates[:, index] += 0.6 * np.sin(2 * math.pi * frequency * t + phase)
    attitudes = [Rotation.identity()]
    for rate in rates[:-1]:
        attitudes.append(attitudes[-1] * Rotation.from_rotvec(rate / RATE_HZ))
    return rates, Rotation.concatenate(attitudes).as_matrix()


def readings_of(attitudes: np.ndarray, offset: np.ndarray, noise: float, seed: int,
                mounting: np.ndarray | None = None) -> np.ndarray:
    rng = np.random.default_rng(seed + 100)
    body = np.einsum('nji,j->ni', attitudes, EARTH)  # R^T w
    if mounting is not None:
        body = body @ mounting.T
    return body + offset + rng.normal(0.0, noise, body.shape)


def windows_of(attitudes: np.ndarray, readings: np.ndarray, step: int = 2) -> TurnedReadings:
    rows = np.arange(0, len(readings), step)
    return TurnedReadings(readings[rows], attitudes[rows], (rows / RATE_HZ // WINDOW_S)
                          .astype(int))


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_an_offset_is_found_from_a_partial_sphere_within_its_uncertainty(seed):
    _, attitudes = wrist_motion(20.0, seed)
    offset = np.array([12.0, -30.0, 7.5])
    data = windows_of(attitudes, readings_of(attitudes, offset, 0.3, seed))
    fit = fit_gyro_aided(data)
    assert fit.success, fit.reason
    error = np.abs(fit.calibration.offset - offset)
    assert np.all(error <= 4.0 * fit.offset_std + 0.05), (error, fit.offset_std)
    assert np.all(fit.offset_std < MAX_OFFSET_STD * fit.calibration.field_strength)
    assert fit.calibration.field_strength == pytest.approx(np.linalg.norm(EARTH), rel=0.02)
    assert fit.raw_residual_pct > 10 * fit.residual_pct  # the raw field does not turn as one


def test_turning_about_one_axis_leaves_the_offset_along_it_unseen():
    _, attitudes = wrist_motion(20.0, 3, axes=1)
    data = windows_of(attitudes, readings_of(attitudes, np.array([5.0, 5.0, 5.0]), 0.3, 3))
    fit = fit_gyro_aided(data)
    assert not fit.success
    assert 'one axis' in fit.reason or 'uncertain' in fit.reason


def test_a_magnetometer_that_does_not_turn_with_the_gyroscope_is_named():
    _, attitudes = wrist_motion(20.0, 4)
    mounting = Rotation.from_euler('x', 90, degrees=True).as_matrix()  # another frame
    data = windows_of(attitudes, readings_of(attitudes, np.zeros(3), 0.3, 4, mounting))
    fit = fit_gyro_aided(data)
    assert not fit.success
    assert 'mounting or axis-remap error' in fit.reason or 'does not turn' in fit.reason


def test_too_few_windows_is_a_reason_not_a_fit():
    _, attitudes = wrist_motion(3.0, 5)
    fit = fit_gyro_aided(windows_of(attitudes, readings_of(attitudes, np.zeros(3), 0.3, 5)))
    assert not fit.success and fit.calibration is None and 'windows' in fit.reason


def test_turned_errors_tell_the_right_offset_from_none():
    _, attitudes = wrist_motion(20.0, 6)
    offset = np.array([0.0, 10.0, 0.0])
    data = windows_of(attitudes, readings_of(attitudes, offset, 0.3, 6))
    fit = fit_gyro_aided(data)
    assert fit.success, fit.reason
    assert np.sqrt(np.mean(turned_errors(fit.calibration, data) ** 2)) < 0.25 * np.sqrt(
        np.mean(turned_errors(None, data) ** 2))


def test_the_track_integrates_a_constant_turn_and_keeps_one_reading_per_step():
    track = RotationTrack()
    rate = (0.0, 0.0, 1.0)  # rad/s about z
    field = np.array([30.0, 0.0, -40.0])
    for index in range(301):  # 3 s at 100 Hz
        stamp = int(index * 1e7)
        track.add_rate(stamp, rate)
        angle = index * 0.01
        body = Rotation.from_rotvec([0, 0, angle]).inv().apply(field)
        track.add_reading(stamp + 1, body)
    assert track.snapshot() is None  # 3 windows: too few to fit
    track = RotationTrack()
    for index in range(1200):
        stamp = int(index * 1e7)
        track.add_rate(stamp, rate)
        body = Rotation.from_rotvec([0, 0, index * 0.01]).inv().apply(field)
        track.add_reading(stamp, body)
    data = track.snapshot()
    assert data is not None
    assert len(np.unique(data.windows)) == 12 and len(data.readings) == 12 / STEP_S
    assert np.max(turned_errors(None, data)) < 1e-6  # each window's field turned back is one


def test_a_gap_in_the_rates_starts_a_new_window_and_no_reading_is_kept_without_rates():
    track = RotationTrack()
    track.add_reading(0, (1.0, 2.0, 3.0))  # no rate yet: nothing known of its attitude
    assert track.snapshot() is None
    for index in range(50):
        track.add_rate(int(index * 1e7), (0.1, 0.0, 0.0))
        track.add_reading(int(index * 1e7), (1.0, 2.0, 3.0))
    for index in range(100, 150):  # 0.5 s later: a new stream
        track.add_rate(int(index * 1e7), (0.1, 0.0, 0.0))
        track.add_reading(int(index * 1e7), (1.0, 2.0, 3.0))
    track.add_rate(int(151e7), (math.nan, 0.0, 0.0))  # a broken rate stops the stream
    track.add_reading(int(151e7), (1.0, 2.0, 3.0))
    kept = track._readings  # noqa: SLF001 - the part under test
    assert len({window for window, _, _ in kept}) == 2
    assert len(kept) == 50  # one per STEP_S of the 2 x 0.5 s


def replay(offset: np.ndarray, seconds: float, seed: int, settings: SessionSettings,
           mounting: np.ndarray | None = None) -> tuple[CalibrationSession, float | None, list]:
    rates, attitudes = wrist_motion(seconds, seed)
    readings = readings_of(attitudes, offset, 0.3, seed, mounting) * 1e-6  # tesla
    gravity = np.einsum('nji,j->ni', attitudes, np.array([0.0, 0.0, 9.81]))
    session = CalibrationSession(settings)
    first, events = None, []
    for index, reading in enumerate(readings):
        stamp = int(index * 1e9 / RATE_HZ)
        session.process_imu(stamp, '', gravity[index], rates[index])
        session.process(stamp, '', reading)
        events += session.take_events()
        if first is None and session.calibration is not None:
            first = index / RATE_HZ
    return session, first, events


def test_the_session_calibrates_a_hand_turned_sensor_from_the_gyroscope_within_30_s():
    offset = np.array([15.0, -25.0, 10.0])
    session, first, events = replay(offset, 40.0, 7, SessionSettings())
    assert first is not None and first <= 30.0, [e.message for e in events]
    adopted = [e.message for e in events if e.adopted]
    assert "gyroscope's turning" in adopted[0]
    assert np.linalg.norm(session.calibration.offset * 1e6 - offset) < 1.0
    assert session.report().counts.adoptions.get('gyro') == 1


def test_without_the_gyro_aided_fit_the_same_motion_waits_for_the_sphere():
    offset = np.array([15.0, -25.0, 10.0])
    session, _, events = replay(offset, 40.0, 7, SessionSettings(gyro_aided=False))
    assert not any('gyro' in e.message for e in events)
    assert 'gyro' not in session.report().counts.adoptions


def test_a_sensor_that_arrives_calibrated_keeps_its_own_calibration():
    session, first, events = replay(np.zeros(3), 40.0, 8, SessionSettings())
    adopted = [e.message for e in events if e.adopted]
    assert first is not None and adopted, [e.message for e in events]
    assert "sensor's own calibration holds" in adopted[0]
    assert not np.any(session.calibration.offset)


def test_a_magnetometer_in_another_frame_is_not_calibrated_from_the_gyroscope():
    mounting = Rotation.from_euler('x', 90, degrees=True).as_matrix()
    _, _, events = replay(np.array([10.0, 0.0, 0.0]), 30.0, 9, SessionSettings(), mounting)
    assert not any(e.adopted and 'gyroscope' in e.message for e in events)
