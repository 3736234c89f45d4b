# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Turn in place until the heading circle is covered and a fit passes: ``~/rotate_and_calibrate``.

The decisions of a self-calibrating ground robot, apart from ROS, in one state machine with an
injected clock: whether a turn may start, the commanded yaw rate (an acceleration ramp up to
``speed``), when the heading circle is complete enough to ask for a fit, and every reason to
stop. The node only publishes what ``command`` says, at the rate it says, and reports events.

Robots calibrated this way elsewhere (robot_calibration, Clearpath's ``calibrate_compass``,
imu_calibration) spin for a fixed time and fit a circle; this one stops once the heading circle
is covered and the planar fit passes its gates, and every way out ends in a zero command:

- ``done``: a requested fit passed and is in force;
- ``requested``: ``~/stop_rotation``;
- ``timeout``: ``timeout_s`` of turning without a calibration;
- ``no_input``: no magnetometer reading for INPUT_TIMEOUT_S (the sensor or its driver is gone);
- ``fit_error``: the fit itself failed (an exception, the worker died), not merely its gates;
- ``conflict``: another node started publishing on the command topic;
- ``parameters``: a parameter changed (the settings it started with no longer hold);
- ``shutdown``: the node is going down (Ctrl-C, SIGTERM, destroy);
- ``error``: an unexpected error in the node's own turning code (logged with its traceback).

A shorter silence holds the turn instead: after INPUT_HOLD_S without a reading the command is
zero (the robot does not turn blind), and once readings come back the turn ramps up again from
standstill. On a loaded computer the driver is not always given a core in time while the
calibrator runs on (docs/BENCHMARKS.md, "A pause of the driver holds a turn"): stopping then
would throw a calibration turn away for a pause.

After a stop the zero is repeated for ZERO_HOLD_S, so a base that missed one message (a best
effort subscriber, a late match) still stops; while turning the command is re-sent every
COMMAND_PERIOD_S, so a base with a command timeout stops by itself if this node dies.

Words: here a *turn* is the robot turning in place; *rotation* is kept for the alignment matrix R.
The public ROS names keep their word (``~/rotate_and_calibrate``, ``rotation_speed``, the
``rotation*`` diagnostics keys and log lines): users and their launch files rely on them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
import math

from mag_calibrator_ros.calibration.fit.coverage import Coverage
from mag_calibrator_ros.calibration.fit.heading import COMPLETE_HEADING_COVERAGE

COMMAND_PERIOD_S = 0.05
"""The command is re-sent at 20 Hz: well inside the usual base command timeouts (ros2_control's
diff_drive_controller: 0.5 s)."""

ZERO_HOLD_S = 0.5
"""After a stop, zero is re-sent this long, then nothing (the topic is left to others)."""

INPUT_HOLD_S = 0.5
"""No magnetometer reading for this long holds the turn (zero commanded, and refuses a start)
until readings come back."""

INPUT_TIMEOUT_S = 5.0
"""No magnetometer reading for this long stops the turn: a pause lasts less, a driver that
re-initialises after an I2C fault included."""

COVERAGE_PERIOD_S = 0.5
"""Heading coverage is looked at twice a second while turning (not every tick: it scans the
buffer)."""

RETRY_S = 2.0
"""A fit that failed its gates is asked for again after this much more turning."""

PROGRESS_PERIOD_S = 5.0
"""Seconds between progress lines in the log while turning."""

MAX_SPEED = 2.0
"""rad/s: the largest ``speed`` accepted; turning faster smears readings and shakes robots."""

STOP_REASONS = {
    'done': 'calibrated',
    'requested': 'stopped on request (~/stop_rotation)',
    'timeout': 'no calibration within rotation_timeout',
    'no_input': 'no magnetometer input',
    'fit_error': 'the fit failed',
    'conflict': 'another node publishes on the command topic',
    'parameters': 'a parameter changed',
    'shutdown': 'the node is shutting down',
    'error': 'an unexpected error in the node (see the log)',
}

STATES = ('idle', 'turning', 'stopping')


MIN_TURNS = 1.5
"""Turns a timeout should allow: the heading circle once, and the fit and its gates after it."""


@dataclass(frozen=True)
class TurnSettings:
    """What a user tunes (the node's ``rotation_*`` parameters)."""

    speed: float = 0.3
    """rad/s, counter-clockwise seen from above (REP-103: positive yaw is a left turn)."""
    acceleration: float = 0.5
    """rad/s^2 of the ramp from standstill to ``speed``."""
    timeout_s: float = 120.0
    """Seconds of turning after which it stops without a calibration."""

    def problems(self) -> list[str]:
        problems = []
        if not (math.isfinite(self.speed) and 0.0 < self.speed <= MAX_SPEED):
            problems.append(f'rotation_speed must be in (0, {MAX_SPEED}] rad/s, got {self.speed}')
        if not (math.isfinite(self.acceleration) and self.acceleration > 0.0):
            problems.append(f'rotation_acceleration must be > 0 rad/s^2, got '
                            f'{self.acceleration}')
        if not (math.isfinite(self.timeout_s) and self.timeout_s > 0.0):
            problems.append(f'rotation_timeout must be > 0 s, got {self.timeout_s}')
        return problems

    def turns(self) -> float:
        """Full turns within ``timeout_s`` at ``speed`` after the ramp up to it."""
        ramp_s = min(self.speed / self.acceleration, self.timeout_s)
        angle = 0.5 * self.acceleration * ramp_s**2 + self.speed * (self.timeout_s - ramp_s)
        return angle / (2.0 * math.pi)

    def caution(self) -> str:
        """'' when the timeout allows the heading circle and some more; else why it may stop
        first (0.05 rad/s for 120 s finished at 119.6 s: issue #46)."""
        turns = self.turns()
        if turns >= MIN_TURNS:
            return ''
        return (f'rotation_speed {self.speed:g} rad/s for rotation_timeout {self.timeout_s:g} s '
                f'is {turns:.2f} of a turn: it may stop before the heading circle is covered '
                f'(raise either to allow {MIN_TURNS:g} turns)')


@dataclass(frozen=True)
class TurnStep:
    """What the node does now: publish ``command`` (None: nothing), ask for a fit, log."""

    command: float | None
    calibrate: bool = False
    messages: tuple[str, ...] = ()


class TurnController:
    """The one decision-maker of a turn in place; ``now`` is seconds of any monotonic clock.

    ``input_topic`` and ``command_topic`` only name things in messages.
    """

    def __init__(self, settings: TurnSettings | None = None, input_topic: str = 'imu/mag',
                 command_topic: str = 'cmd_vel') -> None:
        self.settings = settings or TurnSettings()
        problems = self.settings.problems()
        if problems:
            raise ValueError('; '.join(problems))
        self.input_topic = input_topic
        self.command_topic = command_topic
        self.state = 'idle'
        self.last_stop: tuple[str, str] | None = None
        """(reason, message) of the latest stop."""
        self.coverage: Coverage | None = None
        """The heading coverage last looked at while turning."""
        self.result: str = ''
        """The latest fit's answer while turning (or the calibration that ended it)."""
        self._started = self._stopped = 0.0
        self._ramp_from = 0.0  # the start, or the end of the latest hold
        self.holding = False
        """Turning, but holding still (zero commanded) until magnetometer readings come back."""
        self._silent_s = 0.0
        self._next_look = self._next_progress = 0.0
        self._waiting_fit = False
        self._retry_at = -math.inf

    # -- events ----------------------------------------------------------------------------------

    def start(self, now: float, input_age: float | None, other_publishers: int
              ) -> tuple[bool, str]:
        """Begin turning, or say why not (already turning, no input, another commander)."""
        if self.state == 'turning':
            return False, (f'already rotating ({now - self._started:.1f} s of at most '
                           f'{self.settings.timeout_s:.0f} s); call ~/stop_rotation first')
        if input_age is None:
            return False, f'no input on {self.input_topic} yet: start the magnetometer first'
        if input_age > INPUT_HOLD_S:
            return False, (f'no input on {self.input_topic} for {input_age:.1f} s: the '
                           'magnetometer stopped')
        if other_publishers > 0:
            return False, (f'{other_publishers} other publisher(s) on {self.command_topic} '
                           '(teleop, navigation?): two commanders would fight over the robot; '
                           'stop them first')
        self.state = 'turning'
        self._started = self._ramp_from = now
        self.holding = False
        self._next_look = now
        self._next_progress = now + PROGRESS_PERIOD_S
        self._waiting_fit = False
        self._retry_at = -math.inf
        self.coverage = None
        self.result = ''
        s = self.settings
        caution = s.caution()
        return True, (f'rotating at {s.speed:.2f} rad/s on {self.command_topic} (ramp '
                      f'{s.acceleration:.2f} rad/s^2) until the heading circle is covered and '
                      f'the fit passes; at most {s.timeout_s:.0f} s; ~/stop_rotation stops it'
                      + (f'. Note: {caution}' if caution else ''))

    def stop(self, now: float, reason: str, detail: str = '') -> str | None:
        """Stop turning for ``reason`` (STOP_REASONS); returns the log line, None when it was
        not turning. The next ``command`` is zero."""
        if reason not in STOP_REASONS:
            raise ValueError(f'unknown stop reason {reason!r}')
        if self.state != 'turning':
            return None
        self.state = 'stopping'
        self._stopped = now
        self.holding = False
        message = f'rotation stopped after {now - self._started:.1f} s: {STOP_REASONS[reason]}'
        if detail:
            message += f' ({detail})'
        self.last_stop = (reason, message)
        return message

    def calibration_answered(self, now: float, success: bool, error: bool, message: str
                             ) -> str | None:
        """A requested fit came back: in force (done), an error (stop), or gates failed (turn
        on, ask again after RETRY_S). Returns a log line."""
        if self.state != 'turning' or not self._waiting_fit:
            return None
        self._waiting_fit = False
        self.result = message
        if success:
            return self.stop(now, 'done', message)
        if error:
            return self.stop(now, 'fit_error', message)
        self._retry_at = now + RETRY_S
        return f'rotation: not calibrated yet ({message}); turning on'

    # -- every COMMAND_PERIOD_S ------------------------------------------------------------------

    def command(self, now: float) -> float | None:
        """The yaw rate to publish now (rad/s); 0.0 while holding or stopping; None when
        idle."""
        if self.state == 'turning':
            if self.holding:
                return 0.0
            s = self.settings
            return min(s.speed, s.acceleration * max(now - self._ramp_from, 0.0))
        if self.state == 'stopping':
            if now - self._stopped < ZERO_HOLD_S:
                return 0.0
            self.state = 'idle'
        return None

    def update(self, now: float, input_age: float | None, other_publishers: int,
               heading_coverage: Callable[[], Coverage]) -> TurnStep:
        """Every transition of a running turn; ``heading_coverage`` is called at most every
        COVERAGE_PERIOD_S (it scans the buffer)."""
        messages: list[str] = []
        calibrate = False
        if self.state == 'turning':
            stop = None
            if now - self._started >= self.settings.timeout_s:
                stop = 'timeout', f'{self.settings.timeout_s:.0f} s'
            elif input_age is None or input_age > INPUT_TIMEOUT_S:
                stop = 'no_input', f'nothing on {self.input_topic} for {INPUT_TIMEOUT_S:g} s'
            elif other_publishers > 0:
                stop = 'conflict', f'{other_publishers} on {self.command_topic}'
            if stop is not None:
                messages.append(self.stop(now, *stop))
            elif not self._hold(now, input_age, messages):
                calibrate = self._look(now, heading_coverage, messages)
        return TurnStep(self.command(now), calibrate, tuple(messages))

    def _hold(self, now: float, input_age: float, messages: list[str]) -> bool:
        """Hold still while the input is silent for more than INPUT_HOLD_S; True while
        holding. Readings back: ramp up again from standstill."""
        silent = input_age > INPUT_HOLD_S
        if silent and not self.holding:
            messages.append(f'rotation holding still: nothing on {self.input_topic} for '
                            f'{input_age:.1f} s (zero until readings come back; it stops after '
                            f'{INPUT_TIMEOUT_S:.0f} s without)')
        elif self.holding and not silent:
            messages.append(f'rotation: readings on {self.input_topic} again after '
                            f'{self._silent_s:.1f} s; turning on')
            self._ramp_from = now
        self.holding, self._silent_s = silent, input_age
        return silent

    def _look(self, now: float, heading_coverage: Callable[[], Coverage],
              messages: list[str]) -> bool:
        """Heading coverage now and then; True when a fit should be requested."""
        if now < self._next_look:
            return False
        self._next_look = now + COVERAGE_PERIOD_S
        self.coverage = coverage = heading_coverage()
        if now >= self._next_progress:
            self._next_progress = now + PROGRESS_PERIOD_S
            messages.append(self.progress_text(now))
        if (coverage.fraction >= COMPLETE_HEADING_COVERAGE and not self._waiting_fit
                and now >= self._retry_at):
            self._waiting_fit = True
            return True
        return False

    # -- reporting -------------------------------------------------------------------------------

    def progress_text(self, now: float) -> str:
        if self.state != 'turning':
            return self.last_stop[1] if self.last_stop else 'not rotating'
        text = f'rotating {now - self._started:.0f} s'
        if self.holding:
            text += (f', holding still: nothing on {self.input_topic} for '
                     f'{self._silent_s:.1f} s')
        coverage = self.coverage
        if coverage is not None:
            text += f', heading coverage {100.0 * coverage.fraction:.0f} %'
            if coverage.hint:
                text += f' \u2014 {coverage.hint}'
            elif self._waiting_fit:
                text += ' \u2014 fitting'
            elif self.result:
                text += f' \u2014 {self.result}'
        return text

    def diagnostic_values(self, now: float) -> dict[str, object]:
        values: dict[str, object] = {'rotation': self.state}
        if self.state == 'turning':
            values['rotation_elapsed_s'] = round(now - self._started, 1)
            values['rotation_command'] = round(self.command(now) or 0.0, 3)
            if self.holding:
                values['rotation_holding_s'] = round(self._silent_s, 1)
            if self.coverage is not None:
                values['rotation_heading_coverage_pct'] = round(100 * self.coverage.fraction, 1)
        if self.last_stop is not None:
            values['rotation_last_stop'] = self.last_stop[0]
        return values


__all__ = [
    'COMMAND_PERIOD_S',
    'INPUT_HOLD_S',
    'INPUT_TIMEOUT_S',
    'STOP_REASONS',
    'ZERO_HOLD_S',
    'TurnController',
    'TurnSettings',
    'TurnStep',
]
