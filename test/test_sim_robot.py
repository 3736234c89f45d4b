# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The simulated cmd_vel robot without a ROS graph: commands on its clock, the battery paced by
the readings' stamps."""

import pytest

from mag_calibrator_ros.sim.motion import CmdVelTrajectory, DriveCurrent
from mag_calibrator_ros.sim.robot import BATTERY_PERIOD_NS, SimulatedRobot


def test_the_robot_drives_on_its_clock_and_reports_its_battery_at_most_every_period():
    now = [0.0]
    trajectory = CmdVelTrajectory(seed=3, command_timeout=5.0, drive=DriveCurrent(1.0, 6.0))
    robot = SimulatedRobot(trajectory, lambda: now[0])
    first = robot.battery_due(1_000)
    assert first is not None and first.current_a == pytest.approx(1.0)  # standing: idle
    assert first.voltage == pytest.approx(DriveCurrent.NOMINAL_V - DriveCurrent.RESISTANCE_OHM)
    assert robot.battery_due(1_000 + BATTERY_PERIOD_NS - 1) is None
    robot.drive(0.5, 0.0)  # the default top speed: the full current, once reached
    now[0] = 2.0
    assert robot.trajectory.speed(now[0]) == pytest.approx(0.5)
    driving = robot.battery_due(1_000 + BATTERY_PERIOD_NS)
    assert driving is not None and driving.current_a == pytest.approx(6.0)
