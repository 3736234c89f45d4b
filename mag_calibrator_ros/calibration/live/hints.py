# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Which kind of hint the progress line gives, decided from the stream alone.

The kind (a ground robot's heading circle, or the direction sphere of a sensor turned by hand)
and the way a robot is turning are judged at points of stream time, in the order the readings
are learnt (``CalibrationSession._ingest``), on the buffer as it is then: so the same stream
gives the same hints, however the messages were timed, however long fits took and however often
someone looked. Reports (the progress line, /diagnostics, the turn in place) read the decision;
they never make it.

Only a ring (``heading.motion_shape``: near one plane, and round it for a third of a turn or
more) held for RING_CONFIRM_S makes the motion yaw-only. An arc so far is how every motion
starts, a hand's tumble as much as a robot's turn, so until the readings leave the plane or
stay on a ring, the hint names neither: 'keep turning'.
"""

from __future__ import annotations

from dataclasses import replace
import math

import numpy as np

from mag_calibrator_ros.calibration.fit.coverage import HEADING_SECTORS, STILL_HINT, Coverage
from mag_calibrator_ros.calibration.fit.heading import (
    HeadingCoverage,
    heading_coverage_of,
    motion_shape,
)
from mag_calibrator_ros.calibration.live.buffer import SampleBuffer
from mag_calibrator_ros.calibration.live.scheduler import CHECK_FIT_PERIOD_S

UNDECIDED_HINT = ('keep turning (a robot: in place; a sensor in the hand: through every '
                  'orientation)')
"""The hint while the readings trace one arc: nothing yet says which motion it is."""

UNDECIDED_STILL_HINT = f'the readings barely change: {UNDECIDED_HINT}'
"""...and while they barely move: said, without naming a rotation a robot could not make."""


UNDECIDED_PERIOD_S = 0.25
DECIDED_PERIOD_S = 1.0
"""Stream seconds between judgements of the motion's kind: often while undecided (a tumble
leaves its first arc within a second or two, and should be told so soon), then seldom (a few
milliseconds each, on the message path)."""

RING_CONFIRM_S = 2.5
"""Stream seconds the readings must stay round one ring before the motion counts as yaw-only: a
hand's tumble turns about one axis for a second or two before it leaves the plane (1.5 s at
most over 40 simulated tumbles), a robot turning in place stays on its ring."""

REPORTED_COVERAGE_AGE_S = 2.0 * CHECK_FIT_PERIOD_S
"""Stream seconds a coverage measured by the fit worker stands for the buffer's in reports: a
check measures it every CHECK_FIT_PERIOD_S while calibrated, a readiness test every
CHECK_PERIOD_S while calibrating automatically."""

DIRECTION_PERIOD_S = 1.0
"""Stream seconds between the readings whose headings say which way a robot turns: far enough
apart for a slow turn to move by more than ``heading.TURNING_MIN_STEP_DEG``."""


class MotionHints:
    """The motion's kind and the turning direction, from stream points only."""

    def __init__(self) -> None:
        self.kind = ''
        """'ring' (yaw-only), '3d', or '' (undecided: too few readings, or one arc so far)."""
        self._next_shape = -math.inf
        self._ring_since: float | None = None  # stream time the readings were first a ring
        self._next_direction = -math.inf
        self._reading: np.ndarray | None = None  # the reading at the latest direction point
        self._previous: np.ndarray | None = None  # ... at the one before
        self._turning = 0  # the way the heading moved between the last two (+1 / -1)
        self._measured: tuple[float, Coverage] | None = None  # (stream s, the worker's)

    def learnt(self, now: float, buffer: SampleBuffer, reading: np.ndarray) -> None:
        """One reading learnt at stream time ``now`` (O(1) unless a judgement is due). Leaving
        the plane decides '3d' at once, a ring held for RING_CONFIRM_S 'ring'; an arc (or too
        few readings) leaves a decided kind as it is: the buffer keeps those samples."""
        if now >= self._next_direction:
            self._next_direction = now + DIRECTION_PERIOD_S
            self._previous, self._reading = self._reading, reading
        if now >= self._next_shape:
            self._next_shape = now + (DECIDED_PERIOD_S if self.kind else UNDECIDED_PERIOD_S)
            shape = motion_shape(buffer.samples)
            if shape != 'ring':
                self._ring_since = None
            elif self._ring_since is None:
                self._ring_since = now
            if shape == '3d' or (shape == 'ring' and now - self._ring_since >= RING_CONFIRM_S):
                self.kind = shape

    @property
    def yaw_only(self) -> bool:
        return self.kind == 'ring'

    def heading(self, samples: np.ndarray, readings: np.ndarray) -> HeadingCoverage:
        """Heading coverage of ``samples`` and the turn still needed, from the heading of the
        reading at the latest judgement, the way it moved since the one before."""
        progress = heading_coverage_of(samples, readings, self._reading, self._previous,
                                       self._turning)
        self._turning = progress.turning
        return progress

    def dress(self, coverage: Coverage) -> Coverage:
        """A direction coverage as reported while undecided: its hint names no rotation a
        robot on the ground could not make."""
        if self.kind or coverage.cells == HEADING_SECTORS or not coverage.hint:
            return coverage
        still = coverage.hint == STILL_HINT
        return replace(coverage, hint=UNDECIDED_STILL_HINT if still else UNDECIDED_HINT)

    def clear(self) -> None:
        """The buffer was emptied: judge afresh."""
        self.__init__()

    # -- coverage for reports ------------------------------------------------------------------

    def measured(self, now: float | None, coverage: Coverage | None = None) -> None:
        """The fit worker measured the buffer's ``coverage`` at stream time ``now`` (None: what
        it measured no longer holds: other settings, an emptied buffer)."""
        self._measured = None if now is None or coverage is None else (now, coverage)

    def yaw_only_for(self, model: str) -> bool:
        """Whether coverage and hints are about the heading circle: model ``planar``, or
        ``auto`` with the buffer's samples round a ring when last judged."""
        return model == 'planar' or (model == 'auto' and self.yaw_only)

    def coverage(self, buffer: SampleBuffer, model: str) -> Coverage:
        """The buffer's coverage now (milliseconds): of the heading circle when yaw-only, else
        of the sphere."""
        if self.yaw_only_for(model):
            return self.heading(buffer.samples, buffer.readings).coverage
        return self.dress(buffer.coverage())

    def reported(self, now: float, buffer: SampleBuffer, model: str) -> Coverage:
        """``coverage`` without its milliseconds on the caller's thread: what the fit worker
        measured with its latest check or readiness test (jobs.buffer_coverage), while no older
        than REPORTED_COVERAGE_AGE_S of stream and of the kind the buffer is now (a robot that
        starts turning); measured here otherwise. Heading coverage is looked at here, so its
        hint knows which way the robot turns."""
        measured = self._measured
        if (measured is None or now - measured[0] > REPORTED_COVERAGE_AGE_S
                or (measured[1].cells == HEADING_SECTORS) != self.yaw_only_for(model)):
            return self.coverage(buffer, model)
        if measured[1].cells == HEADING_SECTORS:
            return self.heading(buffer.samples, buffer.readings).coverage
        return self.dress(measured[1])


__all__ = ['REPORTED_COVERAGE_AGE_S', 'UNDECIDED_HINT', 'UNDECIDED_STILL_HINT', 'MotionHints']
