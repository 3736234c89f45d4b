# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""When the live calibrator fits: one small decision-maker, driven by the stream alone.

Every decision is a function of the accepted readings and their stamps (stream time), never of
the wall clock, so a recording replayed through ``mag_calibrator_fit`` triggers the same fits at
the same readings as the node that received it live, at any replay speed.

Five kinds of work, in priority order:

- a requested fit (``~/calibrate``);
- the buffer's reference: once the buffer is full, a full fit every ``capacity`` new samples,
  less often (up to REFERENCE_MAX_FACTOR x) while successive fits agree (it has settled);
- automatic calibration, while uncalibrated or after the calibration in force was found not to
  fit: a readiness check every CHECK_PERIOD_S (coverage, which is cheap), a fit at most every
  ``auto_calibrate_period`` once ready;
- refinement, while calibrated: a fit judged on held-out readings REFINE_FIRST_S after a new
  calibration, then at doubling intervals up to ``refine_period`` (a first calibration from
  half the sphere is improved within seconds of more turning); after CONVERGED_AFTER judged
  attempts in a row that changed nothing the calibration counts as converged and the period
  doubles on up to REFINE_MAX_FACTOR x (NXP's sensor fusion re-solves every 300 s; a converged
  calibration here is re-checked every 80 s by default);
- a check of the calibration in force on recent held-out readings, every CHECK_FIT_PERIOD_S.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

from mag_calibrator_ros.calibration.live.buffer import SampleBuffer
from mag_calibrator_ros.calibration.live.evidence import MisfitMonitor
from mag_calibrator_ros.calibration.live.settings import SessionSettings

CHECK_PERIOD_S = 0.25
"""Stream seconds between readiness checks while uncalibrated (a coverage check, no fit)."""

CHECK_FIT_PERIOD_S = 1.0
"""Stream seconds between checks that the calibration in force still fits (and online
tracking's comparison)."""

REFINE_FIRST_S = 1.0
"""Stream seconds from a new calibration to the first refinement."""

REFERENCE_MAX_FACTOR = 8
CONVERGED_AFTER = 3
REFINE_MAX_FACTOR = 8
MAX_STEP_S = 1.0
"""Stream time advances by at most 1 s per reading: a paused stream is not time spent turning."""
NOMINAL_STEP_S = 0.01
"""Stream time per reading when stamps do not advance (a driver that stamps nothing): 100 Hz."""


class StreamClock:
    """Seconds of stream since the start, from message stamps (see MAX_STEP_S, NOMINAL_STEP_S)."""

    def __init__(self) -> None:
        self.now = 0.0
        self._last_ns: int | None = None

    def advance(self, stamp_ns: int) -> float:
        last, self._last_ns = self._last_ns, stamp_ns
        if last is not None:
            step = (stamp_ns - last) / 1e9
            self.now += min(step, MAX_STEP_S) if step > 0.0 else NOMINAL_STEP_S
        return self.now


@dataclass(frozen=True)
class Situation:
    """What the scheduler needs to know about the session, at one reading."""

    now: float
    buffer_full: bool
    buffer_fill: int
    calibrated: bool
    misfit: bool
    auto_calibrate: bool
    auto_calibrate_period: float
    refine: bool
    refine_period: float
    min_samples: int
    request_waiting: bool
    disturbed: bool = False
    """The misfit is the world's (``MisfitMonitor.world``): nothing to learn, only checks."""

    @classmethod
    def of(cls, now: float, settings: SessionSettings, buffer: SampleBuffer, calibrated: bool,
           misfit: MisfitMonitor, request_waiting: bool) -> Situation:
        """The situation at one reading, from the session's settings and state."""
        return cls(now=now, buffer_full=buffer.fill == buffer.capacity, buffer_fill=buffer.fill,
                   calibrated=calibrated, misfit=misfit.misfit,
                   auto_calibrate=settings.auto_calibrate,
                   auto_calibrate_period=settings.auto_calibrate_period, refine=settings.refine,
                   refine_period=settings.refine_period, min_samples=settings.min_samples,
                   request_waiting=request_waiting, disturbed=misfit.world)


class FitScheduler:
    """Decides which fit is due (``due``) and learns how each ended (``*_done``)."""

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self.reset()

    def reset(self) -> None:
        """Start over (new buffer contents): every period back to its base."""
        self._since_reference = 0
        self._reference_factor = 1
        self._next_check = -math.inf
        self._next_auto_fit = -math.inf
        self._next_refine: float | None = None
        self._refine_interval = REFINE_FIRST_S
        self._next_fit_check = -math.inf
        self._refine_factor = 1
        self.unimproved = 0
        """Judged refinements in a row that did not change the calibration."""

    @property
    def converged(self) -> bool:
        return self.unimproved >= CONVERGED_AFTER

    def sample_added(self, buffer_full: bool) -> None:
        """A reading changed the buffer (added, replaced or merged)."""
        if buffer_full:
            self._since_reference += 1

    def due(self, situation: Situation) -> str | None:
        """'request', 'reference', 'calibrate', 'refine' or 'check' when one is due, else None.

        'calibrate' is automatic: the job checks readiness (coverage) first and fits only then.
        """
        s = situation
        if s.request_waiting:
            return 'request'
        if s.disturbed:
            return self._check_due(s)
        if s.buffer_full and self._since_reference >= self._reference_factor * self.capacity:
            return 'reference'
        if s.auto_calibrate and (not s.calibrated or s.misfit) and (
                s.buffer_fill >= s.min_samples
                and s.now >= max(self._next_check, self._next_auto_fit)):
            return 'calibrate'
        if s.calibrated and s.refine and not s.misfit:
            if self._next_refine is None:  # the first interval starts with the calibration
                self._next_refine = s.now + min(self._refine_interval, s.refine_period)
            if s.now >= self._next_refine:
                self._refine_interval = min(2.0 * self._refine_interval, s.refine_period)
                self._next_refine = s.now + self._refine_factor * self._refine_interval
                return 'refine'
        return self._check_due(s)

    def _check_due(self, s: Situation) -> str | None:
        if s.calibrated and s.now >= self._next_fit_check:
            self._next_fit_check = s.now + CHECK_FIT_PERIOD_S
            return 'check'
        return None

    def reference_done(self, settled: bool) -> None:
        self._since_reference = 0
        self._reference_factor = (
            min(2 * self._reference_factor, REFERENCE_MAX_FACTOR) if settled else 1
        )

    def calibrate_done(self, now: float, fitted: bool, auto_calibrate_period: float) -> None:
        """An automatic attempt ended (``fitted``: it was ready and a fit ran, whatever its
        gates; else only the readiness check ran)."""
        self._next_check = now + CHECK_PERIOD_S
        if fitted:
            self._next_auto_fit = now + auto_calibrate_period

    def refine_done(self, judged: bool, adopted: bool) -> None:
        if adopted:
            self.calibration_changed()
        elif judged:
            self.unimproved += 1
            if self.converged:
                self._refine_factor = min(2 * self._refine_factor, REFINE_MAX_FACTOR)

    def calibration_changed(self) -> None:
        """A new calibration is in force: refine it from the first interval again."""
        self.unimproved = 0
        self._refine_factor = 1
        self._refine_interval = REFINE_FIRST_S
        self._next_refine = None


__all__ = ['CHECK_FIT_PERIOD_S', 'CHECK_PERIOD_S', 'FitScheduler', 'Situation', 'StreamClock']
