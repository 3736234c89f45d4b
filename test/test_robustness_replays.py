# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The calibrator under attack (issue #9), replayed through its session: the messages the DDS
tests of test_calibrator_robustness.py sent, with the same stamps, frames and values, given to
the ``CalibrationSession`` the node is wiring around. The session decides from stamps only, so
what it makes of them is what the node published; the node's own wiring (topics, services,
files, covariances) stays over DDS in test_calibrator_robustness.py.
"""

from __future__ import annotations

import numpy as np

from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.calibration.live.session import CalibrationSession, SessionEvent
from mag_calibrator_ros.calibration.live.settings import SessionSettings
from mag_calibrator_ros.icm20948 import registers as reg

CALIBRATION = Calibration(np.array([20e-6, -10e-6, 5e-6]), np.diag([1.1, 0.9, 1.0]), 50e-6,
                          'full', {'residual_rms_pct': 0.5, 'coverage': 0.9})
"""The calibration file the DDS tests' calibrator loaded at start-up."""
GOOD = np.array([40e-6, -20e-6, 10e-6])
SECOND = 1_000_000_000
FULL_SCALE_T = reg.MEASUREMENT_LIMIT * reg.TESLA_PER_LSB
"""The node's ``full_scale`` default (the AK09916's measurement limit, tesla)."""


def node_session(**settings) -> CalibrationSession:
    """The session of the DDS tests' calibrator: ``auto_calibrate`` off, the node's full scale,
    the calibration file in force."""
    session = CalibrationSession(SessionSettings(**{
        'auto_calibrate': False, 'full_scale': FULL_SCALE_T, **settings}))
    session.apply_calibration(CALIBRATION, 'file')
    return session


def published(session: CalibrationSession, stamps, frame: str = 'imu_link', field=GOOD,
              imu=None) -> list[int]:
    """Process one message per stamp (seconds), each after ``imu(sec)``'s sample if given: the
    stamps whose message the node publishes (a corrected output: a calibration is in force)."""
    out = []
    for sec in stamps:
        if imu is not None:
            imu(sec)
        if session.process(sec * SECOND, frame, field).corrected is not None:
            out.append(sec)
    return out


def messages(events: list[SessionEvent], level: str) -> list[str]:
    return [event.message for event in events if event.level == level]


def test_one_future_stamp_never_silences_the_output():
    session = node_session()
    assert published(session, [1000]) == [1000]  # the warm-up message
    assert published(session, range(1001, 1006)) == list(range(1001, 1006))
    assert published(session, [2**31 - 1]) == []  # refused alone
    assert len(published(session, range(1006, 1046))) == 40  # was 0 of 40 until ~/reset
    session.take_events()
    # a bag looping back 40 s: followed after a few messages, and said so
    again = published(session, range(966, 986))
    assert len(again) >= 20 - 5 and again[-1] == 985
    assert any('jumped back' in text for text in messages(session.take_events(), 'info'))
    counts = session.report().counts
    assert counts.rejects['stamp_jump'] == 1
    assert counts.received == 1 + 5 + 1 + 40 + 20
    # nothing else was refused: the future stamp, and the few back until the loop was confirmed
    assert counts.accepted == (counts.received - counts.rejects['stamp_jump']
                               - counts.rejects['stamp_backwards'])


def test_a_new_frame_id_is_followed_with_a_warning():
    session = node_session()
    assert published(session, range(1000, 1011)) == list(range(1000, 1011))
    session.take_events()
    moved = published(session, range(1011, 1031), frame='imu_link_renamed')
    assert len(moved) >= 20 - 5 and moved[-1] == 1030
    (warning,) = messages(session.take_events(), 'warning')
    assert "'imu_link_renamed'" in warning, warning
    assert session.report().frame_id == 'imu_link_renamed'
    session.reset()  # then a bogus first frame must not silence the good ones either
    assert published(session, [1031], frame='bogus_frame') == [1031]
    assert len(published(session, range(1032, 1062), frame='imu_link')) >= 30 - 5
    assert session.report().frame_id == 'imu_link'
    assert session.calibration is CALIBRATION  # ~/reset keeps the calibration in force


def test_absurd_values_with_the_saturation_check_off_are_refused():
    """full_scale 0 ('no check') and one (1e150, 1e150, 1e150) message used to kill the node."""
    session = node_session(full_scale=0.0)
    assert published(session, [1000]) == [1000]
    assert published(session, [1001], field=np.full(3, 1e150)) == []
    report = session.report(1.0)  # the node's next diagnostics period
    assert report.counts.rejects['out_of_range'] == 1
    assert report.values['rejected_out_of_range'] == 1
    assert published(session, range(1002, 1005)) == [1002, 1003, 1004]
    report = session.report(2.0)
    assert report.state == 'calibrated-refining' and report.counts.accepted == 4


def imu_sender(session: CalibrationSession, force, frame: str = 'imu_link'):
    """What the DDS tests' IMU publisher sent before each magnetometer message: one sample
    stamped as it, without a gyroscope."""

    def send(sec: int) -> None:
        session.process_imu(sec * SECOND, frame, force)

    return send


def test_a_subnormal_accelerometer_sample_never_stalls_the_output():
    """(1e-200, 0, 0) on imu/data_raw passed the IMU screen; its norm underflowed to 0 and every
    reading paired with it raised: imu/mag_corrected fell from 100 Hz to 25 Hz, diagnostics OK."""
    session = node_session()
    assert published(session, [1000]) == [1000]
    subnormal = imu_sender(session, (1e-200, 0.0, 0.0))
    for sec in range(1001, 1006):  # paired with it before the fix: nothing out
        assert published(session, [sec], imu=subnormal) == [sec]
    imu = session.report().imu
    assert imu.refusals['too_weak'] >= 5 and imu.paired == 0
    assert published(session, [1006], imu=imu_sender(session, (0.0, 0.0, 9.81))) == [1006]
    report = session.report(1.0)
    assert report.imu.paired == 1
    assert report.values['imu_rejected_too_weak'] == 5


def test_an_imu_in_another_frame_is_refused_and_named_in_diagnostics():
    """An IMU in base_link beside a magnetometer in imu_link: its rotation was adopted as the
    magnetometer's mounting. Now refused, and /diagnostics names both frames."""
    session = node_session()
    assert published(session, [1000]) == [1000]
    other = imu_sender(session, (0.0, 1.7, 9.66), frame='base_link')
    assert published(session, range(1001, 1004), imu=other) == [1001, 1002, 1003]
    report = session.report(1.0)
    assert report.imu.paired == 0
    assert report.imu.refusals['other_frame'] >= 3
    assert report.level == 'WARN'
    assert "'base_link'" in report.message and "'imu_link'" in report.message
    assert report.values['imu_rejected_other_frame'] >= 3
