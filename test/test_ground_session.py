# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The live session with yaw-only motion (a ground robot turning in place), without ROS: heading
coverage drives the automatic gate, the hints and the diagnostics; the defaults calibrate."""

from __future__ import annotations

import math
from pathlib import Path
import sys

import numpy as np
import pytest

from mag_calibrator_ros.calibration.fit.coverage import HEADING_SECTORS
from mag_calibrator_ros.calibration.fit.fitting import FitOptions
from mag_calibrator_ros.calibration.live.jobs import FitJob, readiness, run_job
from mag_calibrator_ros.calibration.live.offline import feed
from mag_calibrator_ros.calibration.live.session import CalibrationSession
from mag_calibrator_ros.calibration.live.settings import SessionSettings
from mag_calibrator_ros.sim import motion

sys.path.insert(0, str(Path(__file__).parent))
from test_heading import (  # noqa: E402  (one robot, one place)
    HARD_IRON_UT,
    RATE_HZ,
    ROTATION_WORDS,
    SOFT_IRON,
    turning,
    turning_imu,
)

UT = 1e-6


def stream(session: CalibrationSession, raw_ut: np.ndarray, start_s: float = 0.0) -> None:
    feed(session, raw_ut * UT, RATE_HZ, start_ns=round(start_s * 1e9), frame_id='imu_link')


def measured(session: CalibrationSession):
    """The session's report with the coverage measured now."""
    return session.report(measure_coverage=True)


def yaw_only(session: CalibrationSession) -> bool:
    """Whether coverage and hints are about the heading circle."""
    return measured(session).values['coverage_kind'] == 'heading'


def heading_error_deg(calibration, seed: int = 9, wobble_deg: float = 2.0) -> float:
    """RMS azimuth error about the chip z axis over a full turn of noise-free readings (another
    floor than the calibration saw)."""
    truth_raw, _ = turning(30.0, seed=seed, wobble_deg=wobble_deg, noise_ut=0.0)
    truth = np.linalg.solve(SOFT_IRON, (truth_raw - HARD_IRON_UT).T).T
    corrected = calibration.apply(truth_raw * UT)
    error = (np.arctan2(corrected[:, 1], corrected[:, 0])
             - np.arctan2(truth[:, 1], truth[:, 0]))
    error = np.mod(error + math.pi, 2.0 * math.pi) - math.pi
    return float(np.degrees(np.sqrt(np.mean(error[int(5 * RATE_HZ):] ** 2))))


def test_turning_in_place_calibrates_by_itself_with_the_defaults_after_a_full_turn():
    raw, yaw = turning(45.0)
    session = CalibrationSession()
    turned_at_calibration = None
    for second in range(45):
        chunk = slice(int(second * RATE_HZ), int((second + 1) * RATE_HZ))
        stream(session, raw[chunk], start_s=second)
        if session.calibration is not None and turned_at_calibration is None:
            turned_at_calibration = math.degrees(abs(yaw[chunk.stop - 1] - yaw[0]))
    report = session.report(0.0, measure_coverage=True)
    assert session.calibration is not None, report.progress
    assert session.calibration.model == 'planar'
    assert report.counts.adoptions.get('auto') == 1
    assert 330.0 <= turned_at_calibration <= 420.0  # the whole circle, not half of it
    assert heading_error_deg(session.calibration) < 3.0  # mag alone: wobble limits it
    values = report.values
    assert values['coverage_kind'] == 'heading' and values['coverage_pct'] >= 97.0
    assert 'heading coverage' in report.progress


def test_a_level_turn_calibrates_heading_within_half_a_degree():
    raw, _ = turning(40.0, wobble_deg=0.0)
    session = CalibrationSession()
    stream(session, raw)
    assert session.calibration is not None and session.calibration.model == 'planar'
    assert heading_error_deg(session.calibration, wobble_deg=0.0) < 0.5


def test_hints_speak_of_turning_and_nothing_is_adopted_before_the_circle_closes():
    raw, yaw = turning(40.0)
    half = np.flatnonzero(np.abs(yaw - yaw[0]) <= math.radians(200.0))[-1]
    session = CalibrationSession()
    texts = []
    for second in range(int(half / RATE_HZ)):
        stream(session, raw[int(second * RATE_HZ):int((second + 1) * RATE_HZ)], second)
        report = session.report(float(second), measure_coverage=True)
        texts.append(report.progress)
        texts.append(str(report.values['coverage_hint']))
    assert session.calibration is None
    assert any('turn another' in text and 'to the left' in text for text in texts), texts
    for text in texts:
        assert not any(word in text for word in ROTATION_WORDS), text
    assert yaw_only(session)


def test_model_planar_uses_heading_coverage_whatever_the_motion():
    session = CalibrationSession(SessionSettings(model='planar'))
    raw, _ = turning(4.0)
    stream(session, raw)
    assert yaw_only(session)
    assert measured(session).coverage.cells == 36


def planar_job(raw_ut: np.ndarray, model: str = 'auto') -> FitJob:
    return FitJob('calibrate', raw_ut * UT, None, raw_ut * UT, FitOptions(model=model),
                  ready_coverage=0.5)


@pytest.mark.parametrize('model', ['auto', 'planar'])
def test_automatic_readiness_of_yaw_only_data_is_the_whole_heading_circle(model):
    raw, yaw = turning(40.0)
    most = np.flatnonzero(np.abs(yaw - yaw[0]) <= math.radians(300.0))[-1]
    coverage, needed = readiness(planar_job(raw[:most:5], model))
    assert coverage.cells == 36 and needed > 0.95
    assert coverage.fraction < needed
    assert run_job(planar_job(raw[:most:5], model)).result is None  # not fitted: not ready
    coverage, needed = readiness(planar_job(raw[::5], model))
    assert coverage.fraction >= needed
    outcome = run_job(planar_job(raw[::5], model))
    assert outcome.result is not None and outcome.result.success, outcome.result.reason


def test_tumbling_keeps_direction_coverage():
    from mag_calibrator_ros.sim import motion

    tumble = motion.body_field_samples('tumble', 1500, RATE_HZ, 50.0, 60.0, seed=2)
    coverage, needed = readiness(planar_job(tumble @ SOFT_IRON.T + HARD_IRON_UT))
    assert coverage.cells == 80 and needed == 0.5


def tumbling_raw(seconds: float, seed: int = 1) -> np.ndarray:
    field = motion.body_field_samples('tumble', int(seconds * RATE_HZ), RATE_HZ, 50.0, 60.0,
                                      seed=seed)
    noise = np.random.default_rng(seed).normal(0.0, 0.3, field.shape)
    return field @ SOFT_IRON.T + HARD_IRON_UT + noise


@pytest.mark.parametrize('with_imu', [False, True])
def test_a_planar_calibration_gives_way_to_a_full_one_once_the_sensor_tumbles(with_imu):
    raw, _, up, _ = turning_imu(30.0, seed=1)
    session = CalibrationSession()
    feed(session, raw * UT, RATE_HZ, frame_id='imu_link', accel=up * 9.81 if with_imu else None)
    assert session.calibration.model == 'planar'
    session.take_events()
    stream(session, tumbling_raw(40.0), start_s=30.0)
    events = session.take_events()
    messages = [event.message for event in events]
    assert any('moved out of the plane' in message for message in messages)
    # Not taken for a wrong calibration: the planar one is judged in its plane only.
    assert not any(event.level == 'warning' for event in events), messages
    assert session.calibration.model == 'full'
    assert session.report().counts.adoptions.get('refine', 0) >= 1


def test_a_bump_in_the_floor_does_not_leave_the_plane():
    raw, _, up, _ = turning_imu(30.0, seed=1)
    session = CalibrationSession()
    feed(session, raw * UT, RATE_HZ, frame_id='imu_link', accel=up * 9.81)
    session.take_events()
    bump = tumbling_raw(1.0, seed=2)  # a second of wild tilts
    stream(session, bump, start_s=30.0)
    more, _, more_up, _ = turning_imu(20.0, seed=1)
    feed(session, more * UT, RATE_HZ, start_ns=int(31e9), frame_id='imu_link',
         accel=more_up * 9.81)
    messages = [event.message for event in session.take_events()]
    assert not any('moved out of the plane' in message for message in messages)
    assert session.calibration.model == 'planar'


def event_texts(session: CalibrationSession) -> list[str]:
    return [event.message for event in session.take_events()]


def test_a_planar_calibration_says_which_terms_it_could_not_observe():
    """Turning in one plane cannot determine the offset along the turning axis nor the scale
    along it: the log says they are held, not fitted, and what F then is."""
    raw, _ = turning(45.0)
    session = CalibrationSession()
    stream(session, raw)
    (adopted,) = [text for text in event_texts(session) if 'calibrated automatically' in text]
    assert 'not observable turning in one plane, held (not fitted): the offset along the ' \
        'turning axis and the scale along it' in adopted
    assert 'is the field in that plane, not the total' in adopted
    assert 'alignment' not in adopted  # no IMU: nothing to say about it


def test_a_ground_robot_is_never_told_to_tilt():
    """With an IMU but only the floor's wobble, the alignment cannot be determined: said in
    the robot's terms, without advice to tilt what cannot tilt."""
    raw, _, up, _ = turning_imu(40.0, seed=1)
    session = CalibrationSession()
    feed(session, raw * UT, RATE_HZ, frame_id='imu_link', accel=up * 9.81)
    report = session.report(0.0, measure_coverage=True)
    texts = event_texts(session) + [report.progress, str(report.values.get('last_alignment'))]
    assert session.calibration is not None and session.calibration.model == 'planar'
    assert any('alignment to the IMU not determined: turning in place' in text
               for text in texts), texts
    for text in texts:
        assert 'tilt the sensor' not in text and 'different tilts and' not in text, text
        assert 'hold the sensor still' not in text and 'more different tilts' not in text, text


def test_no_still_attitude_at_all_says_nothing_about_the_alignment():
    """An IMU that never held still offers no attitude: the summary says nothing about an
    alignment (it used to add 'alignment not determined ... (0 of 0 ...)' to every one)."""
    rng = np.random.default_rng(4)
    raw = tumbling_raw(40.0)
    moving = rng.normal(size=raw.shape)  # gravity's direction never the same twice: not still
    session = CalibrationSession()
    feed(session, raw * UT, RATE_HZ, frame_id='imu_link',
         accel=9.81 * moving / np.linalg.norm(moving, axis=1)[:, None])
    assert session.report().imu.paired > 0 and session.calibration is not None
    (adopted,) = [text for text in event_texts(session) if 'calibrated automatically' in text]
    assert 'alignment' not in adopted and '0 of 0' not in adopted


def test_a_few_still_attitudes_too_few_are_still_reported():
    from mag_calibrator_ros.calibration.fit.alignment import Alignment
    from mag_calibrator_ros.calibration.live.report import alignment_text

    few = Alignment(False, 'too few static attitudes (2 of 3 held still ...): hold the sensor '
                    'still for a second at several different tilts', attitudes=3,
                    static_samples=2)
    assert alignment_text(few, 'full').startswith('alignment not determined: too few')
    assert 'turning in place' in alignment_text(few, 'planar')
    assert alignment_text(Alignment(False, 'too few static attitudes (0 of 0 ...)'), 'full') == ''


def test_a_robot_that_starts_turning_is_reported_on_the_heading_circle_at_once():
    """Reports take the fit worker's latest coverage while it is fresh: one measured while the
    robot stood (the sphere's kind) must not be reported once the buffer is the heading circle,
    or a ground robot is told to roll (seen over DDS as a flaky diagnostics line)."""
    rng = np.random.default_rng(1)
    field = motion.earth_field(50e-6, 60.0)
    hard_iron = np.array([55e-6, -45e-6, 25e-6])
    session = CalibrationSession(SessionSettings())
    turned_at = None
    for index in range(1200):  # a ring held for hints.RING_CONFIRM_S: no tumble's first arc
        t = index / 100.0
        yaw = 0.0 if t < 1.5 else -0.4 * (t - 1.5)  # stands, then turns right
        c, s = math.cos(yaw), math.sin(yaw)
        rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        session.process(index * 10_000_000, 'imu',
                        rotation.T @ field + hard_iron + rng.normal(0.0, 0.3e-6, 3))
        if index % 25 == 0:
            session.poll()
            if yaw_only(session):
                turned_at = t
                break
    assert turned_at is not None, 'the buffer never became yaw-only'
    report = session.report()
    assert report.coverage.cells == HEADING_SECTORS, report.progress
    for word in ROTATION_WORDS:
        assert word not in report.progress
