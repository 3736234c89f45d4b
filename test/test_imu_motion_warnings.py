# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""A hand's fast motion is not a wrong unit: the accelerometer is judged on a second of stream
(live/sanity.py IMU_SPAN_S), so a real m/s^2 stream that dips for a fraction of a second while
the hand swings (BROAD's trial 28) is never called g, and one really in g still is."""

import numpy as np

from mag_calibrator_ros.calibration.live.sanity import InputWatch

RATE_HZ = 285.7  # BROAD's aktos-t


def swinging(seconds: float) -> tuple[np.ndarray, np.ndarray]:
    """Stamps and accelerometer rows (m/s^2): gravity, with a 0.25 s dip to 1.5 m/s^2 (the
    hand's deceleration cancelling it) every 1.2 s."""
    t = np.arange(0.0, seconds, 1.0 / RATE_HZ)
    magnitude = np.where((t % 1.2) < 0.25, 1.5, 9.81)
    rows = np.column_stack([np.zeros_like(t), np.zeros_like(t), magnitude])
    return (t * 1e9).astype(np.int64), rows


def said(stamps: np.ndarray, rows: np.ndarray) -> list[str]:
    watch, problems = InputWatch(), []
    for stamp, row in zip(stamps, rows, strict=True):
        watch.offer_imu(int(stamp), row)
        problems += watch.take_new()
    return problems


def test_a_swinging_hand_in_metres_per_second_squared_is_not_called_g():
    stamps, rows = swinging(20.0)
    assert not said(stamps, rows)
    # the dips alone, judged on a fraction of a second, would read as g: the test can fail
    short = rows[(stamps * 1e-9 % 1.2) < 0.25][:50]
    assert 0.4 <= float(np.median(np.linalg.norm(short, axis=1))) <= 4.0


def test_the_same_swinging_in_g_is_said_once_within_a_second():
    stamps, rows = swinging(20.0)
    problems = said(stamps, rows / 9.80665)
    assert len(problems) == 1 and 'looks like g' in problems[0]


def test_stamps_that_jump_start_the_second_anew():
    stamps, rows = swinging(3.0)
    jumped = np.concatenate([stamps, stamps[-1] + int(60e9) + stamps])
    assert not said(jumped, np.concatenate([rows, rows]))
