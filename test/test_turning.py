# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""TurnController without ROS: every decision of ~/rotate_and_calibrate on an injected clock --
refusals, the ramp, when a fit is asked for, and that every way out commands zero."""

from __future__ import annotations

import pytest

from mag_calibrator_ros.calibration.fit.coverage import Coverage
from mag_calibrator_ros.calibration.live.turning import (
    COMMAND_PERIOD_S,
    INPUT_HOLD_S,
    INPUT_TIMEOUT_S,
    RETRY_S,
    STOP_REASONS,
    ZERO_HOLD_S,
    TurnController,
    TurnSettings,
)


class Robot:
    """Drives a controller as the node does: a tick every COMMAND_PERIOD_S with fresh input."""

    def __init__(self, **settings) -> None:
        self.controller = TurnController(TurnSettings(**settings), '/imu/mag', '/cmd_vel')
        self.now = 100.0
        self.fraction = 0.0
        self.looks = 0
        self.input_age: float | None = 0.01
        self.others = 0
        self.commands: list[float | None] = []
        self.fits = 0

    def coverage(self) -> Coverage:
        self.looks += 1
        return Coverage(self.fraction, round(36 * self.fraction), 36, '')

    def start(self) -> tuple[bool, str]:
        return self.controller.start(self.now, self.input_age, self.others)

    def tick(self, seconds: float = COMMAND_PERIOD_S):
        """Advance ``seconds`` in ticks; returns the steps."""
        steps = []
        for _ in range(max(1, round(seconds / COMMAND_PERIOD_S))):
            self.now += COMMAND_PERIOD_S
            step = self.controller.update(self.now, self.input_age, self.others, self.coverage)
            self.commands.append(step.command)
            self.fits += step.calibrate
            steps.append(step)
        return steps


def test_refuses_without_fresh_input_beside_another_commander_or_twice():
    robot = Robot()
    robot.input_age = None
    started, message = robot.start()
    assert not started and 'no input on /imu/mag' in message
    robot.input_age = INPUT_HOLD_S + 0.1
    started, message = robot.start()
    assert not started and 'for 0.6 s' in message
    robot.input_age, robot.others = 0.01, 1
    started, message = robot.start()
    assert not started and 'other publisher' in message and '/cmd_vel' in message
    robot.others = 0
    assert robot.start()[0]
    started, message = robot.start()
    assert not started and 'already rotating' in message
    assert robot.controller.state == 'turning'


def test_ramps_up_to_the_speed_and_resends_it_every_tick():
    robot = Robot(speed=0.3, acceleration=0.5)
    assert robot.controller.command(robot.now) is None  # idle: nothing published
    robot.start()
    assert robot.controller.command(robot.now) == 0.0
    robot.tick(0.3)
    assert robot.commands[-1] == pytest.approx(0.15)
    robot.tick(2.0)
    assert robot.commands[-1] == pytest.approx(0.3)
    assert all(c is not None for c in robot.commands)  # one command per tick while turning
    assert max(robot.commands) == pytest.approx(0.3)


def test_looks_at_coverage_twice_a_second_not_every_tick():
    robot = Robot()
    robot.start()
    robot.tick(10.0)
    assert 18 <= robot.looks <= 21


def stopped(robot: Robot, reason: str) -> None:
    """The stop happened for ``reason`` and the very next command is zero, held, then none."""
    assert robot.controller.state == 'stopping'
    assert robot.controller.last_stop[0] == reason
    assert robot.controller.command(robot.now) == 0.0
    robot.tick(ZERO_HOLD_S / 2)
    assert robot.commands[-1] == 0.0
    robot.tick(ZERO_HOLD_S)
    assert robot.commands[-1] is None and robot.controller.state == 'idle'


def test_asks_for_a_fit_once_the_circle_is_complete_and_stops_when_it_passes():
    robot = Robot()
    robot.start()
    robot.fraction = 0.9
    robot.tick(3.0)
    assert robot.fits == 0
    robot.fraction = 1.0
    robot.tick(3.0)
    assert robot.fits == 1  # one at a time, while it is being fitted
    line = robot.controller.calibration_answered(robot.now, True, False, 'model planar, ...')
    assert 'calibrated' in line and 'model planar' in line
    stopped(robot, 'done')


def test_a_failed_gate_is_retried_after_more_turning_and_an_error_stops():
    robot = Robot()
    robot.start()
    robot.fraction = 1.0
    robot.tick(0.5)
    assert robot.fits == 1
    line = robot.controller.calibration_answered(robot.now, False, False, 'residual 7 %')
    assert 'turning on' in line and robot.controller.state == 'turning'
    robot.tick(RETRY_S - 0.2)
    assert robot.fits == 1
    robot.tick(0.5)
    assert robot.fits == 2
    assert robot.commands[-1] > 0.0
    robot.controller.calibration_answered(robot.now, False, True, 'fit worker process ended')
    stopped(robot, 'fit_error')


def test_holds_still_while_the_input_is_silent_and_ramps_up_again_when_it_returns():
    robot = Robot(speed=0.3, acceleration=0.5)
    robot.start()
    robot.tick(3.0)
    robot.input_age = INPUT_HOLD_S - 0.01  # not yet: readings come at 100 Hz, a pause is short
    assert robot.tick()[-1].command == pytest.approx(0.3)
    robot.input_age = INPUT_HOLD_S + 0.01
    step = robot.tick()[-1]
    controller = robot.controller
    assert step.command == 0.0 and controller.state == 'turning' and controller.holding
    assert 'holding still: nothing on /imu/mag for 0.5 s' in step.messages[0]
    assert 'holding still' in controller.progress_text(robot.now)
    assert controller.diagnostic_values(robot.now)['rotation_holding_s'] == 0.5
    robot.fraction, looks = 1.0, robot.looks
    robot.tick(2.0)
    assert set(robot.commands[-40:]) == {0.0}
    assert robot.looks == looks and robot.fits == 0  # nothing new to look at or fit while silent
    robot.input_age = 0.01
    step = robot.tick()[-1]
    assert 'readings on /imu/mag again after 0.5 s; turning on' in step.messages[0]
    assert not controller.holding and step.command == 0.0  # a new ramp from standstill
    assert robot.fits == 1  # the circle, seen before the pause, is asked for at once
    robot.tick()
    assert 0.0 < robot.commands[-1] < 0.1
    robot.tick(1.0)
    assert robot.commands[-1] == pytest.approx(0.3)
    assert controller.last_stop is None


def test_stops_when_the_input_stays_silent():
    robot = Robot()
    robot.start()
    robot.tick(1.0)
    robot.input_age = INPUT_HOLD_S + 0.01
    robot.tick()
    robot.input_age = INPUT_TIMEOUT_S
    robot.tick()
    assert robot.controller.state == 'turning' and robot.commands[-1] == 0.0
    robot.input_age = INPUT_TIMEOUT_S + 0.01
    step = robot.tick()[-1]
    assert 'no magnetometer input (nothing on /imu/mag for 5 s)' in step.messages[0]
    stopped(robot, 'no_input')


def test_stops_at_the_timeout():
    robot = Robot(timeout_s=10.0)
    robot.start()
    robot.tick(9.9)
    assert robot.controller.state == 'turning'
    robot.tick(0.2)
    stopped(robot, 'timeout')


def test_stops_when_another_commander_appears():
    robot = Robot()
    robot.start()
    robot.tick(1.0)
    robot.others = 1
    robot.tick()
    stopped(robot, 'conflict')


@pytest.mark.parametrize('reason', ['requested', 'parameters', 'shutdown'])
def test_stops_on_request_parameter_change_and_shutdown(reason):
    robot = Robot()
    robot.start()
    robot.tick(2.0)
    line = robot.controller.stop(robot.now, reason, 'detail')
    assert STOP_REASONS[reason] in line and 'detail' in line
    stopped(robot, reason)
    assert robot.controller.stop(robot.now, reason) is None  # nothing to stop


def test_a_late_answer_after_a_stop_changes_nothing():
    robot = Robot()
    robot.start()
    robot.fraction = 1.0
    robot.tick(0.5)
    robot.controller.stop(robot.now, 'requested')
    assert robot.controller.calibration_answered(robot.now, True, False, 'ok') is None
    assert robot.controller.last_stop[0] == 'requested'


def test_may_start_again_while_its_zero_is_still_held():
    robot = Robot()
    robot.start()
    robot.tick(1.0)
    robot.controller.stop(robot.now, 'requested')
    robot.tick(0.1)
    assert robot.start()[0]
    assert robot.controller.command(robot.now) == 0.0  # a new ramp from standstill
    robot.tick(1.0)
    assert robot.commands[-1] > 0.0


def test_settings_and_reasons_are_checked():
    for settings in ({'speed': 0.0}, {'speed': 5.0}, {'acceleration': -1.0},
                     {'timeout_s': float('nan')}):
        with pytest.raises(ValueError):
            TurnController(TurnSettings(**settings))
    with pytest.raises(ValueError):
        TurnController().stop(0.0, 'bored')


def test_reports_progress_and_diagnostics():
    robot = Robot()
    assert robot.controller.diagnostic_values(robot.now) == {'rotation': 'idle'}
    robot.start()
    robot.fraction = 0.5
    robot.tick(6.0)
    values = robot.controller.diagnostic_values(robot.now)
    assert values['rotation'] == 'turning' and values['rotation_heading_coverage_pct'] == 50.0
    assert 'heading coverage 50 %' in robot.controller.progress_text(robot.now)
    robot.controller.stop(robot.now, 'requested')
    assert robot.controller.diagnostic_values(robot.now)['rotation_last_stop'] == 'requested'


def test_a_timeout_too_short_for_the_heading_circle_is_said_when_the_turn_starts():
    """0.05 rad/s for 120 s is under one turn: it finished at 119.6 of 120 s without a word
    that it could not have covered the circle (issue #46)."""
    started, message = Robot(speed=0.05).start()
    assert started
    assert 'is 0.95 of a turn: it may stop before the heading circle is covered' in message
    started, message = Robot().start()  # 0.3 rad/s for 120 s: 5.7 turns
    assert started and 'of a turn' not in message
    assert TurnSettings(speed=1.0, acceleration=0.5, timeout_s=2.0).turns() == pytest.approx(
        0.5 * 0.5 * 2.0**2 / (2 * 3.141592653589793))  # all of it on the ramp
