# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The simulated ground robot of ``sim.motion: cmd_vel``: it drives as commanded and says what
its battery supplies.

It belongs to the simulated world, not to the driver: commands take effect at the simulated
chip's time, the one its sensors are measured at, and the battery report is paced by the stamps
of the readings it goes out with. No ROS here, so tests drive it without a graph;
``nodes/sim_backend.py`` wires it to ``cmd_vel`` and ``battery_state``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from mag_calibrator_ros.sim.motion import CmdVelTrajectory

BATTERY_PERIOD_NS = 50_000_000
"""The battery goes out with the first imu/mag message at least this long after the last (20 Hz
at the default rate: a battery monitor's), stamped as it: the current when the field was read,
and no timer waking the executor twenty times a second."""


@dataclass(frozen=True)
class Battery:
    """The pack at one moment, as a battery monitor reports it."""

    voltage: float
    """Volts at the pack's terminals."""
    current_a: float
    """Amperes drawn (positive while the robot discharges it)."""


class SimulatedRobot:
    """The robot that follows ``trajectory`` (its limits, tilt and drive current), on ``clock``
    (the simulated chip's seconds since power-on: ``SimulatedIcm20948Bus.sim_time_s``)."""

    def __init__(self, trajectory: CmdVelTrajectory, clock: Callable[[], float]) -> None:
        self.trajectory = trajectory
        self._clock = clock
        self._battery_due_ns = 0

    def drive(self, speed: float, yaw_rate: float) -> None:
        """Drive forward at ``speed`` m/s and turn at ``yaw_rate`` rad/s from now on (a
        differential drive: nothing else of a twist moves it)."""
        self.trajectory.command(yaw_rate, self._clock(), speed=speed)

    def battery_due(self, stamp_ns: int) -> Battery | None:
        """The battery now, when a report is due with a reading stamped ``stamp_ns`` (at most
        every BATTERY_PERIOD_NS of stamps), else None."""
        if stamp_ns < self._battery_due_ns:
            return None
        self._battery_due_ns = stamp_ns + BATTERY_PERIOD_NS
        amperes = self.trajectory.battery_current(self._clock())
        return Battery(float(self.trajectory.drive.voltage(amperes)), float(amperes))
