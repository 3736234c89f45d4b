# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Ground robots calibrating by themselves, replayed through the session: the simulated board of
test_ground_node.py's driver (``sim.motion`` cmd_vel or yaw, its hard and soft iron, its seed),
its magnetometer and IMU streamed with their stamps through the ``CalibrationSession`` the
calibrator node wires around, with the node's defaults and a /diagnostics report each second.
The session decides from stamps only, so this is what the node decided, in milliseconds; the
turn in place and every way it ends (cmd_vel) stay over DDS in test_ground_node.py.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
import re
import sys

import numpy as np

from mag_calibrator_ros.calibration.live.session import CalibrationSession
from mag_calibrator_ros.calibration.live.settings import SessionSettings
from mag_calibrator_ros.icm20948 import registers as reg
from mag_calibrator_ros.sim.board import BoardModel
from mag_calibrator_ros.sim.config import SimConfig

sys.path.insert(0, str(Path(__file__).parent))
from test_heading import HARD_IRON_UT, ROTATION_WORDS, SOFT_IRON  # noqa: E402

RATE_HZ = 100.0  # the driver's rate_hz
SECOND = 1_000_000_000
NODE_DEFAULTS = SessionSettings(full_scale=reg.MEASUREMENT_LIMIT * reg.TESLA_PER_LSB)
"""The calibrator node's session with its default parameters (``full_scale`` the AK09916's)."""


def board(motion: str, seed: int = 0) -> BoardModel:
    """The driver's simulated board in test_ground_node.py (``sim_robot``, ``sim.motion``)."""
    return BoardModel(SimConfig(motion=motion, seed=seed, hard_iron_ut=tuple(HARD_IRON_UT),
                                soft_iron=tuple(SOFT_IRON.reshape(-1))))


def diagnostics_line(session: CalibrationSession, now: float) -> str:
    """What the DDS test's commander kept of the calibrator's /diagnostics status: its message
    and the coverage hint."""
    report = session.report(now)
    return f"{report.message} coverage_hint={report.values['coverage_hint']}"


def driven(robot: BoardModel, session: CalibrationSession, seconds: float = 120.0):
    """Stream the board's magnetometer and IMU (read at one instant, as the driver publishes
    them) through ``session`` at RATE_HZ, each IMU sample first; yields each reading's time
    (s), after it was processed, for the caller to command the robot, look, or stop.
    ``seconds``: the DDS tests' bound on waiting (CALIBRATION_S)."""
    step = round(SECOND / RATE_HZ)
    for k in range(int(seconds * RATE_HZ)):
        stamp = k * step
        t = stamp / SECOND
        yield t
        field, _ = robot.magnetometer(t)
        accel, gyro, _ = robot.inertial(t, 57.0, 57.0)
        session.process_imu(stamp, 'imu_link', accel, gyro)
        session.process(stamp, 'imu_link', field * 1e-6)


def test_turning_by_any_means_calibrates_with_the_defaults_and_hints_speak_of_turning():
    """No service: a teleop turns the sim robot clockwise (a right turn), re-sending its command
    every 0.1 s; the session (default parameters) calibrates by itself (planar), and its
    diagnostics never ask a ground robot to roll."""
    robot = board('cmd_vel', seed=9)  # SIM_SEED
    session = CalibrationSession(NODE_DEFAULTS)
    lines: list[str] = []
    adopted = False
    for k, t in enumerate(driven(robot, session)):
        if k % 10 == 0:  # the teleop: -0.4 rad/s until calibrated, then a zero twist
            robot.trajectory.command(0.0 if adopted else -0.4, t)
        if k and k % int(RATE_HZ) == 0:  # the node's diagnostics period
            lines.append(diagnostics_line(session, t))
            if lines[-1].startswith('calibrated'):
                break
        adopted = adopted or any(event.adopted for event in session.take_events())
    assert adopted, lines[-1:]
    report = session.report()
    assert session.calibration.model == 'planar'
    assert report.counts.adoptions.get('auto') == 1
    assert any('to the right' in line for line in lines), lines
    for line in lines:
        assert not any(word in line for word in ROTATION_WORDS), line
    # Calibrated, it still reports the heading circle (not ~7 % of the 3-D directions), nearly
    # all of it: the gate waited for 35 of 36 sectors.
    calibrated = [line for line in lines if line.startswith('calibrated')]
    covered = [int(found) for line in calibrated
               for found in re.findall(r'heading coverage (\d+) %', line)]
    assert covered and max(covered) >= 80, calibrated
    assert all(re.search(r'(?<!heading )coverage \d', line) is None for line in calibrated)


def test_yaw_motion_calibrates_with_the_defaults():
    """The older time-driven 'yaw' motion (tilting with time) calibrates by itself as well."""
    session = CalibrationSession(NODE_DEFAULTS)
    for _ in driven(board('yaw'), session):
        if session.calibration is not None:
            break
    report = session.report(measure_coverage=True)
    assert session.calibration is not None, report.progress
    assert session.calibration.model == 'planar'
    assert 'heading coverage' in report.progress


def test_driving_after_calibrating_never_walks_the_field_strength_away():
    """Issue #47: a ground robot that drew a battery current (3 µT/A) drove with stops after it
    had calibrated; each refinement was "better on held-out readings" and moved the barely
    observed offset along the turning axis with F: 48 -> 58 µT in 16 s, 242 µT in 400 s (this
    drive). A refinement moves F by 5 % at most, a chain of them by 10 %."""
    robot = BoardModel(SimConfig(motion='cmd_vel', seed=0, hard_iron_ut=tuple(HARD_IRON_UT),
                                 soft_iron=tuple(SOFT_IRON.reshape(-1)),
                                 current_field_ut_per_a=(3.0, 0.0, 0.0)))
    battery = 'battery_state:sensor_msgs/msg/BatteryState:current'
    session = CalibrationSession(replace(NODE_DEFAULTS, interference_inputs=(battery,)))
    rng = np.random.default_rng(0)  # speeds 0-0.5 m/s and turns, each for 2-6 s, with stops
    command, next_command, first, strengths = (0.0, -0.4), 0.0, None, []
    for k, t in enumerate(driven(robot, session, 45.0)):
        if k % 10 == 0:
            if first is not None and t >= next_command:
                command = (rng.choice([0.0, 0.1, 0.3, 0.5]), rng.choice([0.0, 0.0, 0.3, -0.3]))
                next_command = t + rng.uniform(2.0, 6.0)
            robot.trajectory.command(command[1], t, command[0])
            session.process_input(0, k * round(SECOND / RATE_HZ), robot.battery_current_a(t))
        if any(event.adopted for event in session.take_events()):
            strengths.append(session.calibration.field_strength)
            first = first or strengths[0]
    assert first is not None, 'never calibrated'
    assert max(abs(strength / first - 1.0) for strength in strengths) <= 0.10 + 1e-9, strengths
