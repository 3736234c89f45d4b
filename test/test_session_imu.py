"""CalibrationSession with an IMU and a location: readings paired by stamp, the alignment computed
in the fit jobs (never on the message path), the World Magnetic Model as the reference."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from mag_calibrator_ros.calibration.fit.alignment import rotation_angle_deg
from mag_calibrator_ros.calibration.fit.calibration import Calibration, transform_covariance
from mag_calibrator_ros.calibration.fit.earth_field import EarthField
from mag_calibrator_ros.calibration.live.pairing import PAIR_TOLERANCE_NS
from mag_calibrator_ros.calibration.live.report import calibration_summary
from mag_calibrator_ros.calibration.live.session import CalibrationSession
from mag_calibrator_ros.calibration.live.settings import SessionSettings
from mag_calibrator_ros.sim.board import BoardModel, board_readings
from mag_calibrator_ros.sim.config import SimConfig

RATE_HZ = 100.0
SOFT_IRON = (1.15, 0.10, -0.08, 0.10, 0.85, 0.12, -0.08, 0.12, 1.00)
HARD_IRON_UT = (120.0, -80.0, 60.0)
MODEL = EarthField(50_000.0, 60.0, 3.0, 52.0, 13.0, 0.0, '2026-11-23')
"""What the simulated field (50 uT, dip 60) is: the 'model' the session is told."""


def recording(seconds: float = 60.0, motion: str = 'poses', seed: int = 0, **config):
    """(mag T, accel m/s^2, gyro rad/s) rows at RATE_HZ from the simulated board, and the board."""
    board = BoardModel(SimConfig(hard_iron_ut=HARD_IRON_UT, soft_iron=SOFT_IRON, noise_ut=0.3,
                                 motion=motion, seed=seed, **config))
    return (*board_readings(board, seconds, RATE_HZ), board)


@pytest.fixture(scope='module')
def misaligned():
    return recording(mag_misalignment_deg=(1.8, -1.9, 1.4))


def calibrated(rows, settings=None, earth=None, **feed):
    mag, accel, gyro, _ = rows
    session = CalibrationSession(settings or SessionSettings(auto_calibrate=False))
    session.set_earth_field(earth)
    session.feed(mag, RATE_HZ, frame_id='imu_link', accel=accel, gyro=gyro, **feed)
    return session, session.calibrate_now()


def test_a_misaligned_magnetometer_is_aligned_to_the_imu(misaligned):
    session, attempt = calibrated(misaligned)
    board = misaligned[3]
    assert attempt.success, attempt.message
    assert re.search(r'aligned to the IMU: rotation (2\.9|3\.0)\d deg', attempt.message)
    calibration = session.calibration
    assert calibration.aligned
    assert rotation_angle_deg(calibration.rotation @ board.mag_misalignment.T) < 0.2
    assert calibration.metadata['dip_deg'] == pytest.approx(60.0, abs=0.2)
    assert calibration.metadata['dip_std_deg'] < 0.3
    assert session.pairing.paired == session.accepted == len(misaligned[0])
    assert calibration_summary(calibration).endswith('rotated 3.00 deg into the IMU frame') or (
        'rotated 2.9' in calibration_summary(calibration))
    values = session.diagnostic_values(1.0)
    assert values['static_attitudes'] >= 15 and values['last_alignment'] == 'applied'
    assert values['alignment_angle_deg'] == pytest.approx(3.0, abs=0.2)
    # corrected = R M (raw - b): the corrected field is the true field in the IMU frame
    t = 7.0
    raw, truth = board.magnetometer(t)
    corrected = calibration.apply(raw * 1e-6)
    cosine = corrected @ truth / (np.linalg.norm(corrected) * np.linalg.norm(truth))
    assert math.degrees(math.acos(min(1.0, cosine))) < 1.5  # one noisy reading
    covariance = transform_covariance(calibration.correction, np.eye(3).reshape(9) * 1e-14)
    np.testing.assert_allclose(covariance.reshape(3, 3),
                               calibration.correction @ calibration.correction.T * 1e-14)


def test_without_an_imu_nothing_changes(misaligned):
    mag = misaligned[0]
    with_imu, _ = calibrated(misaligned, SessionSettings(auto_calibrate=False, align=False))
    without = CalibrationSession(SessionSettings(auto_calibrate=False))
    without.feed(mag, RATE_HZ, frame_id='imu_link')
    attempt = without.calibrate_now()
    assert attempt.success and 'aligned' not in attempt.message
    assert not without.calibration.aligned and without.pairing.paired == 0
    np.testing.assert_array_equal(without.calibration.offset, with_imu.calibration.offset)
    assert 'static_attitudes' not in without.diagnostic_values(1.0)


def test_a_flipped_magnetometer_is_named_not_applied_and_warned_once():
    rows = recording(40.0, mag_misalignment_deg=(180.0, 0.0, 0.0), seed=1)
    session, attempt = calibrated(rows)
    assert attempt.success  # the hard and soft iron are fine
    assert 'gross mounting error' in attempt.message and '(x, -y, -z)' in attempt.message
    assert not session.calibration.aligned
    warnings = [e.message for e in session.take_events() if e.level == 'warning']
    assert len([w for w in warnings if 'gross mounting error' in w]) == 1
    assert 'gross mounting error' in session.alignment_warning()
    session.calibrate_now()
    assert not [e for e in session.take_events() if 'gross' in e.message and e.level == 'warning']


def test_the_model_sets_the_field_strength_and_checks_the_fit(misaligned):
    session, attempt = calibrated(misaligned, earth=MODEL)
    assert attempt.success, attempt.message
    assert session.calibration.field_strength == pytest.approx(50e-6)
    gain = np.linalg.det(np.reshape(SOFT_IRON, (3, 3))) ** (1 / 3)  # the raw radius / 50 uT
    assert f'field {gain:.2f}' in attempt.message and 'declination 3.00 deg' in attempt.message
    assert session.calibration.metadata['declination_deg'] == 3.0
    values = session.diagnostic_values(1.0)
    assert values['field_ratio_to_model'] == pytest.approx(gain, abs=0.005)
    assert abs(values['dip_error_deg']) < 0.3 and values['declination_deg'] == 3.0
    assert session.earth_warning() == ''


@pytest.mark.parametrize(('disturbance', 'reason'), [
    ({'field_scale': 1.2}, r'field strength \+1[89] % against the model'),  # x 0.98 gain
    ({'inclination_offset_deg': 8.0}, r'dip 68\.0 deg against the model'),
])
def test_a_disturbed_field_is_refused_with_the_reason_or_warned(disturbance, reason):
    rows = recording(40.0, seed=2, **disturbance)
    session, attempt = calibrated(rows, earth=MODEL)
    assert not attempt.success
    assert re.search(reason, attempt.message) and 'steel structure' in attempt.message
    assert session.calibration is None
    warned, attempt = calibrated(rows, SessionSettings(auto_calibrate=False,
                                                       earth_field_gate=False), earth=MODEL)
    assert attempt.success
    assert re.search(reason, warned.earth_warning())
    assert any(re.search(reason, e.message) for e in warned.take_events() if e.level == 'warning')


def test_a_calibration_in_force_is_aligned_by_refinement(misaligned):
    mag, accel, gyro, board = misaligned
    truth = Calibration(np.array(HARD_IRON_UT) * 1e-6,
                        np.linalg.inv(np.reshape(SOFT_IRON, (3, 3))), 50e-6, 'full',
                        {'coverage': 0.5})
    session = CalibrationSession(SessionSettings(), calibration=truth)
    session.feed(mag, RATE_HZ, frame_id='imu_link', accel=accel, gyro=gyro)
    while session.runner.busy:
        session.poll()
    assert session.calibration.aligned
    assert rotation_angle_deg(session.calibration.rotation @ board.mag_misalignment.T) < 0.2
    assert any('aligned to the IMU' in e.message and e.adopted for e in session.take_events())


def test_imu_samples_pair_by_nearest_stamp_and_bad_ones_are_refused():
    session = CalibrationSession(SessionSettings(auto_calibrate=False))
    assert not session.process_imu(0, 'imu_link', (math.nan, 0.0, 9.8))
    assert not session.process_imu(0, 'imu_link', (0.0, 0.0, 0.0))
    assert not session.process_imu(0, 'imu_link', 'garbage')
    assert session.pairing.refused == 3
    assert session.process_imu(1_000_000, 'imu_link', (0.0, 0.0, 9.8), (math.inf, 0, 0))
    assert session.process_imu(11_000_000, 'imu_link', (0.0, 1.0, 9.8), (0.0, 0.0, 0.0))
    assert session.pairing.pair(9_000_000) == ((0.0, 1.0, 9.8), (0.0, 0.0, 0.0))
    assert session.pairing.pair(2_000_000) == ((0.0, 0.0, 9.8), None)  # a NaN/Inf gyro is no gyro
    assert session.pairing.pair(11_000_000 + PAIR_TOLERANCE_NS + 1) is None
    session.reset()
    assert session.pairing.pair(11_000_000) is None


def test_field_radius_is_the_raw_ellipsoid_mean_radius():
    calibration = Calibration(np.zeros(3), np.diag([2.0, 2.0, 2.0]), 50.0)
    assert calibration.field_radius() == pytest.approx(25.0)


def test_a_fit_that_fails_its_own_gates_says_nothing_about_the_place(misaligned):
    """A refinement from the first seconds (one or two poses) fails its gates: its radius and
    rotation are no evidence of a disturbed field or a mounting error."""
    mag, accel, gyro, _ = misaligned
    truth = Calibration(np.array(HARD_IRON_UT) * 1e-6,
                        np.linalg.inv(np.reshape(SOFT_IRON, (3, 3))), 50e-6, 'full')
    session = CalibrationSession(SessionSettings(), calibration=truth)
    session.set_earth_field(MODEL)
    session.feed(mag[:400], RATE_HZ, frame_id='imu_link', accel=accel[:400], gyro=gyro[:400])
    assert session.jobs_run.get('refine', 0) >= 1
    assert not [e for e in session.take_events() if e.level == 'warning']
    assert session.findings.earth_check is None and session.findings.alignment is None
    assert session.calibration is truth
