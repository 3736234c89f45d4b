# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Progress hints from the stream alone (issue #24): the same stream gives the same lines, however
often they are looked at; the ground robot's hint only for yaw-only motion, never in the first
seconds of a tumble."""

from __future__ import annotations

from pathlib import Path
import sys

import numpy as np
import pytest

from mag_calibrator_ros.calibration.live.hints import UNDECIDED_HINT
from mag_calibrator_ros.calibration.live.session import CalibrationSession
from mag_calibrator_ros.sim.board import BoardModel, board_readings
from mag_calibrator_ros.sim.config import SimConfig

sys.path.insert(0, str(Path(__file__).parent))
from test_heading import ROTATION_WORDS, turning  # noqa: E402

RATE_HZ = 100.0
GROUND_WORDS = ('heading coverage', 'turn the robot', 'turn another', 'turning in place')


def tumble(seed: int, seconds: float = 6.0) -> np.ndarray:
    board = BoardModel(SimConfig(hard_iron_ut=(120.0, -80.0, 60.0), noise_ut=0.3,
                                 motion='tumble', seed=seed))
    return board_readings(board, seconds, RATE_HZ)[0]


def lines(raw_t: np.ndarray, look_every: int, show_every: int = 50) -> list[str]:
    """The progress line at every ``show_every``-th message, looked at (the coverage a report
    reads) every ``look_every`` messages as well: a node's timer ticks where it likes."""
    session = CalibrationSession()
    shown = []
    for index, row in enumerate(raw_t):
        session.process(round(index * 1e9 / RATE_HZ), 'imu_link', row)
        if index % look_every == 0:
            session.report()
        if index % show_every == show_every - 1:
            shown.append(session.report().progress)
    return shown


@pytest.mark.parametrize('seed', range(6))
def test_a_tumble_never_gets_the_ground_robots_hint(seed):
    shown = lines(tumble(seed), look_every=7)
    for line in shown:
        assert not any(word in line for word in GROUND_WORDS), line
    assert UNDECIDED_HINT not in shown[-1]  # a few seconds: the tumble is known for one
    assert 'keep rotating' in shown[-1] or 'enough to calibrate' in shown[-1]


def test_the_same_stream_gives_the_same_lines_however_often_it_is_looked_at():
    for raw_t in (tumble(3), turning(25.0)[0] * 1e-6):
        assert lines(raw_t, look_every=3) == lines(raw_t, look_every=41)


def test_a_turning_robot_is_told_to_turn_and_which_way():
    raw_ut, _ = turning(25.0)
    shown = lines(raw_ut * 1e-6, look_every=13, show_every=100)
    assert any('turn another' in line and 'to the left' in line for line in shown), shown
    for line in shown:
        assert not any(word in line for word in ROTATION_WORDS), line
