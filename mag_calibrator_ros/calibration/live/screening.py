# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""What makes a magnetometer message unusable, decided once per message with one set of counters.

Values: non-finite, all-zero and saturated readings are never samples. Stamps and frames: a
calibration belongs to one sensor stream, so a message whose stamp goes back in time or jumps far
ahead, or whose frame differs, is refused -- but only until a few consistent messages confirm the
new situation (a bag replay looping, a clock step, a driver whose ``frame_id`` was changed at run
time), which is then followed and reported. Judging against the last accepted stamp alone, as a
maximum kept forever, would let one bad header silence the stream for good.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

from mag_calibrator_ros.calibration.fit.input_sanity import MIN_TESLA

VALUE_REASONS = ('non_finite', 'zero', 'saturated', 'out_of_range')
STREAM_REASONS = ('stamp_backwards', 'stamp_jump', 'frame_changed')
SCREEN_REASONS = VALUE_REASONS + STREAM_REASONS
"""Why a message is refused before it reaches the sample buffer or the corrected topic."""

CONFIRM_MESSAGES = 5
"""Consecutive, mutually consistent messages that confirm a new timeline or frame (50 ms at
100 Hz): one stray header is refused alone, a real change is followed almost at once."""

MAX_FORWARD_JUMP_NS = 60_000_000_000
"""A stamp more than a minute ahead of the last accepted one is a jump (a corrupt or future
stamp) until confirmed; a stream paused for longer resumes after :data:`CONFIRM_MESSAGES`
messages. Shorter pauses (a driver re-initialising) pass at once."""

MAX_CONFIRM_STEP_NS = 1_000_000_000
"""Messages confirm a new timeline only when each is at most 1 s after the one before."""

MAX_READING = 1e12
"""No magnetometer reads beyond this in any unit (1e12 nT is 1000 T; 16-bit counts stay below
1e5): such a value is garbage, refused even with the saturation check off, so that no later
computation (squares, whitening) can overflow."""


def reading_problem(x0: float, x1: float, x2: float, full_scale: float | None,
                    least: float = 0.0) -> str | None:
    """Why one reading can never be a sample (a VALUE_REASONS entry), or None.

    All-zero is refused but one exact-zero component is a legitimate reading; so is a reading
    whose every component is below ``least`` (MIN_TESLA in a tesla stream: below one count of
    an AK09916 and any field, a 5e-11 T reading of tesla scaled twice was published as -b, issue
    #47). Plain floats, as this runs for every message.
    """
    if not (math.isfinite(x0) and math.isfinite(x1) and math.isfinite(x2)):
        return 'non_finite'
    if x0 == 0.0 and x1 == 0.0 and x2 == 0.0:
        return 'zero'
    largest = max(abs(x0), abs(x1), abs(x2))
    if full_scale is not None and largest >= full_scale:
        return 'saturated'
    if largest > MAX_READING or largest < least:
        return 'out_of_range'
    return None


@dataclass(frozen=True)
class StreamChange:
    """A confirmed change of timeline or frame, for the log."""

    kind: str  # 'stamp' or 'frame'
    message: str


@dataclass
class _Pending:
    """Refused messages that agree with each other: a candidate new timeline or frame."""

    last: object
    count: int = 1


class ReadingScreen:
    """Screens messages (values, stamp, frame) and counts every refusal by reason.

    ``screen`` returns the reason a message is refused, or None; a confirmed change of timeline
    or frame is accepted and left in ``changes`` for the caller to report.
    """

    def __init__(self, full_scale: float | None = None, tesla: bool = False) -> None:
        self.full_scale = full_scale
        self.least = MIN_TESLA if tesla else 0.0  # no field is weaker (``reading_problem``)
        self.counts = dict.fromkeys(SCREEN_REASONS, 0)
        self._reported = dict(self.counts)  # the counts at the latest ``new_refusals``
        self.frame_id: str | None = None
        self.last_stamp_ns: int | None = None
        self.changes: list[StreamChange] = []
        self._pending_stamp: _Pending | None = None
        self._pending_frame: _Pending | None = None

    def new_refusals(self) -> dict[str, int]:
        """Messages refused since the previous call, by the reasons that occurred (reports)."""
        new = {reason: count - self._reported[reason]
               for reason, count in self.counts.items() if count > self._reported[reason]}
        self._reported = dict(self.counts)
        return new

    def reset(self) -> None:
        """Forget the stream's frame and stamps (a new sensor or bag may follow); keeps counts."""
        self.frame_id = None
        self.last_stamp_ns = None
        self._pending_stamp = self._pending_frame = None

    def screen(self, stamp_ns: int, frame_id: str, x0: float, x1: float, x2: float) -> str | None:
        """The reason this message is refused (counted), or None when it is accepted."""
        reason = reading_problem(x0, x1, x2, self.full_scale, self.least)
        if reason is None:
            reason = self._frame_problem(frame_id)
        if reason is None:
            reason = self._stamp_problem(stamp_ns)
        if reason is not None:
            self.counts[reason] += 1
            return reason
        self.frame_id = frame_id
        self.last_stamp_ns = stamp_ns
        return None

    def _frame_problem(self, frame_id: str) -> str | None:
        if self.frame_id is None or frame_id == self.frame_id:
            self._pending_frame = None
            return None
        pending = self._pending_frame
        if pending is not None and pending.last == frame_id:
            pending.count += 1
        else:
            pending = self._pending_frame = _Pending(frame_id)
        if pending.count < CONFIRM_MESSAGES:
            return 'frame_changed'
        self.changes.append(StreamChange(
            'frame', f"frame_id changed from '{self.frame_id}' to '{frame_id}' "
            f'({CONFIRM_MESSAGES} messages in a row): following it; the calibration in force '
            'is kept (it belongs to the sensor) - call ~/reset and ~/calibrate if the sensor '
            'changed too'))
        self._pending_frame = None
        return None

    def _stamp_problem(self, stamp_ns: int) -> str | None:
        last = self.last_stamp_ns
        if last is None or 0 <= stamp_ns - last <= MAX_FORWARD_JUMP_NS:
            self._pending_stamp = None
            return None
        pending = self._pending_stamp
        if pending is not None and 0 <= stamp_ns - int(pending.last) <= MAX_CONFIRM_STEP_NS:
            pending.count += 1
            pending.last = stamp_ns
        else:
            pending = self._pending_stamp = _Pending(stamp_ns)
        if pending.count < CONFIRM_MESSAGES:
            return 'stamp_backwards' if stamp_ns < last else 'stamp_jump'
        direction = 'back' if stamp_ns < last else 'forward'
        self.changes.append(StreamChange(
            'stamp', f'message stamps jumped {direction} by {abs(stamp_ns - last) / 1e9:.3f} s '
            f'and stayed there for {CONFIRM_MESSAGES} messages (a bag replay restarting, a clock '
            'step or a paused stream): following the new time'))
        self._pending_stamp = None
        return None

    def take_changes(self) -> list[StreamChange]:
        """Confirmed changes since the last call."""
        changes, self.changes = self.changes, []
        return changes


__all__ = [
    'CONFIRM_MESSAGES',
    'SCREEN_REASONS',
    'ReadingScreen',
    'StreamChange',
    'reading_problem',
]
