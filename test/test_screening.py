# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""ReadingScreen: values refused and counted; stamps and frames judged so one bad header never
silences the stream, and a real change (bag loop, clock step, new frame_id) is followed."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.calibration.live.screening import (
    CONFIRM_MESSAGES,
    SCREEN_REASONS,
    ReadingScreen,
    reading_problem,
)
from mag_calibrator_ros.calibration.live.session import CalibrationSession
from mag_calibrator_ros.calibration.live.settings import SessionSettings

GOOD = (20e-6, 30e-6, -10e-6)
SECOND = 1_000_000_000
STEP = 10_000_000  # 100 Hz


def feed(screen, start_ns, count, frame='imu_link', step=STEP):
    """Screen ``count`` good messages from ``start_ns``; returns their verdicts."""
    return [screen.screen(start_ns + i * step, frame, *GOOD) for i in range(count)]


def test_every_value_reason_is_counted():
    screen = ReadingScreen(full_scale=4.9e-3)
    cases = [((math.nan, 0.0, 1e-6), 'non_finite'), ((math.inf, 0.0, 0.0), 'non_finite'),
             ((0.0, 0.0, 0.0), 'zero'), ((-0.0, 0.0, -0.0), 'zero'),
             ((4.9e-3, 0.0, 0.0), 'saturated'), ((1e-6, -5e-3, 0.0), 'saturated')]
    for field, reason in cases:
        assert screen.screen(0, 'imu_link', *field) == reason
    assert screen.counts == {'non_finite': 2, 'zero': 2, 'saturated': 2, 'out_of_range': 0,
                             'stamp_backwards': 0, 'stamp_jump': 0, 'frame_changed': 0}
    assert set(screen.counts) == set(SCREEN_REASONS)
    assert screen.frame_id is None  # nothing accepted yet: no frame fixed by a refused message
    assert screen.screen(0, 'imu_link', 0.0, 2e-5, 1e-5) is None  # one zero component is fine
    assert reading_problem(1e11, 0.0, 1.0, None) is None  # no full scale: no saturation check
    assert reading_problem(1e150, 1e150, 1e150, None) == 'out_of_range'  # but never garbage


def test_a_tesla_reading_below_any_field_is_refused_and_never_published():
    """Issue #47 item 6: a 5e-11 T reading (tesla scaled twice) passed the screen and, with a
    calibration in force, was published as -b. In a tesla stream every component below
    MIN_TESLA (0.1 µT, under one AK09916 count) is out of range; one small component is not,
    nor the same numbers in a stream of another unit."""
    screen = ReadingScreen(full_scale=4.9e-3, tesla=True)
    assert screen.screen(0, 'imu_link', 5e-11, 2e-11, -3e-11) == 'out_of_range'
    assert screen.screen(0, 'imu_link', 5e-11, 2e-11, 0.2e-6) is None
    assert ReadingScreen().screen(0, 'imu_link', 5e-11, 2e-11, -3e-11) is None
    offset = np.array([20e-6, -5e-6, 3e-6])
    session = CalibrationSession(SessionSettings(full_scale=4.9e-3),
                                 calibration=Calibration(offset, np.eye(3), 50e-6))
    processed = session.process(SECOND, 'imu_link', [5e-11, 2e-11, -3e-11])
    assert not processed.accepted and processed.corrected is None
    assert session.report().counts.rejects['out_of_range'] == 1


def test_equal_stamps_are_accepted():
    screen = ReadingScreen()
    assert feed(screen, 5 * SECOND, 10, step=0) == [None] * 10


def test_one_future_stamp_is_refused_alone():
    """A stamp of 2^31 - 1 s used to become the maximum ever seen: nothing after it passed."""
    screen = ReadingScreen()
    assert feed(screen, 100 * SECOND, 10) == [None] * 10
    assert screen.screen((2**31 - 1) * SECOND, 'imu_link', *GOOD) == 'stamp_jump'
    assert feed(screen, 100 * SECOND + 10 * STEP, 40) == [None] * 40
    assert screen.counts['stamp_jump'] == 1 and not screen.take_changes()


def test_a_bag_restarting_is_followed_after_a_few_messages():
    screen = ReadingScreen()
    feed(screen, 100 * SECOND, 50)
    verdicts = feed(screen, 90 * SECOND, 20)  # jumped back 10 s and carries on from there
    assert verdicts[:CONFIRM_MESSAGES - 1] == ['stamp_backwards'] * (CONFIRM_MESSAGES - 1)
    assert verdicts[CONFIRM_MESSAGES - 1:] == [None] * (20 - CONFIRM_MESSAGES + 1)
    (change,) = screen.take_changes()
    assert change.kind == 'stamp' and 'back' in change.message and '10.' in change.message
    assert screen.last_stamp_ns == 90 * SECOND + 19 * STEP


def test_a_paused_stream_resumes_and_a_clock_step_forward_is_followed():
    screen = ReadingScreen()
    feed(screen, 0, 10)
    verdicts = feed(screen, 3600 * SECOND, 10)
    assert verdicts.count('stamp_jump') == CONFIRM_MESSAGES - 1 and verdicts[-1] is None
    assert 'forward' in screen.take_changes()[0].message
    assert feed(screen, 30 * SECOND + 3600 * SECOND, 3) == [None] * 3  # a short gap is fine


def test_scattered_bad_stamps_never_confirm_a_timeline():
    screen = ReadingScreen()
    feed(screen, 1000 * SECOND, 10)
    for i in range(20):  # each far from the one before: no consistent new time
        assert screen.screen((i % 2) * 500 * SECOND, 'imu_link', *GOOD) == 'stamp_backwards'
        assert screen.screen(1000 * SECOND + 10 * STEP + i * STEP, 'imu_link', *GOOD) is None
    assert not screen.take_changes()


def test_a_new_frame_is_followed_after_a_few_consistent_messages():
    """Changing the driver's frame_id at run time used to stop the corrected stream for good."""
    screen = ReadingScreen()
    feed(screen, 0, 10, frame='imu_link')
    verdicts = feed(screen, 10 * STEP, 10, frame='imu_link_2')
    assert verdicts[:CONFIRM_MESSAGES - 1] == ['frame_changed'] * (CONFIRM_MESSAGES - 1)
    assert verdicts[CONFIRM_MESSAGES - 1:] == [None] * (10 - CONFIRM_MESSAGES + 1)
    assert screen.frame_id == 'imu_link_2'
    (change,) = screen.take_changes()
    assert change.kind == 'frame' and "'imu_link' to 'imu_link_2'" in change.message


def test_a_stray_frame_is_refused_and_alternating_frames_never_switch():
    screen = ReadingScreen()
    feed(screen, 0, 5)
    for i in range(30):
        frame = 'bogus' if i % 2 else 'imu_link'
        verdict = screen.screen((5 + i) * STEP, frame, *GOOD)
        assert verdict == ('frame_changed' if i % 2 else None)
    assert screen.frame_id == 'imu_link'


@pytest.mark.parametrize('first', ['bogus_frame', ''])
def test_after_reset_a_bogus_first_frame_does_not_silence_the_good_ones(first):
    screen = ReadingScreen()
    feed(screen, 0, 5)
    screen.reset()
    assert screen.screen(10 * STEP, first, *GOOD) is None  # the first message fixes the frame
    verdicts = feed(screen, 11 * STEP, 100, frame='imu_link')
    assert verdicts.count(None) == 100 - CONFIRM_MESSAGES + 1
    assert screen.frame_id == 'imu_link'
