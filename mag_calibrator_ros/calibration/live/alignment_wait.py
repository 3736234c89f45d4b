# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The first automatic calibration waits for the alignment to the IMU, for a bounded time.

With an IMU paired, a calibration put in force before its rotation into the IMU frame is known
corrects the field in the magnetometer's own axes, off by the whole mounting error, until a
refinement realigns it seconds later: a fusion filter consuming ``imu/mag_corrected`` sees a
heading step. So the first automatic calibration that passes every gate but whose alignment is
not yet determined for want of still tilts (``report.NEEDS_TILTS``) is not put in force; the
progress line says it waits and for what, and the next automatic fit (``auto_calibrate_period``
later) tries again with the attitudes held still meanwhile. The wait is bounded by
ALIGNMENT_WAIT_S of stream time (NO_STILL_WAIT_S while no still tilt was seen at all): a sensor
that is never held still (a robot driving, a tumble) is calibrated unaligned after it, said in
a warning, and realigned by refinement once still tilts come. Waiting cannot help (and so does
not happen) without paired IMU readings, with ``align`` off, for a yaw-only (``planar``)
calibration, a ground robot that cannot tilt, or when the alignment failed for another reason
(a gross mounting error is named, not applied).

The other choice, to go in force at once with an inflated covariance and a flag, was not taken:
a filter that ignores covariances (many do) would still take the unaligned heading.
"""

from __future__ import annotations

from dataclasses import replace

from mag_calibrator_ros.calibration.live.jobs import JobOutcome
from mag_calibrator_ros.calibration.live.report import NEEDS_TILTS
from mag_calibrator_ros.calibration.live.verdicts import Verdict

ALIGNMENT_WAIT_S = 30.0
"""Longest wait, in stream seconds from the first calibration ready but unaligned, once some
still tilts were seen: enough for a hand to hold the sensor still at six tilts (a second each, a
few seconds to turn between)."""

NO_STILL_WAIT_S = 10.0
"""...while none was seen at all (a tumble, a robot driving): long enough to start holding still
after the progress line asks, short enough not to keep a moving robot uncalibrated."""


class AlignmentWait:
    """Holds back the first automatic calibration until it is aligned to the IMU (bounded)."""

    def __init__(self) -> None:
        self.since: float | None = None
        """Stream time the wait began (None: not waiting)."""
        self.reason = ''
        """Why the latest ready calibration was not aligned."""
        self.now = 0.0
        self.bound = ALIGNMENT_WAIT_S

    def judge(self, verdict: Verdict, outcome: JobOutcome, now: float, paired: bool,
              align: bool) -> Verdict:
        """The automatic ``verdict`` as it stands, or held back (nothing in force, a progress
        message) while the alignment waits for still tilts; ``paired``: readings were paired
        with the IMU."""
        alignment = outcome.alignment
        adopt = verdict.adopt
        if adopt is None or verdict.source != 'auto' or outcome.job.current is not None:
            return verdict  # nothing to hold back (a fit that failed its gates waits anyway)
        if (not (paired and align) or adopt.model == 'planar' or alignment is None
                or alignment.success or not alignment.reason.startswith(NEEDS_TILTS)):
            self.since, self.reason = None, ''
            return verdict
        first = self.since is None
        if first:
            self.since = now
        self.now, self.reason = now, alignment.reason
        self.bound = ALIGNMENT_WAIT_S if alignment.attitudes else NO_STILL_WAIT_S
        if now - self.since >= self.bound:
            waited = now - self.since
            self.since, self.reason = None, ''
            why = f' ({alignment.reason})' if alignment.attitudes else ''
            return replace(verdict, level='warning', message=(
                f'{verdict.message}; NOT aligned to the IMU: too few still tilts in '
                f'{waited:.0f} s{why}; refinement aligns it once the sensor is held still at '
                'several tilts'))
        return Verdict(level='info' if first else 'debug', message=self.progress())

    @property
    def waiting(self) -> bool:
        return self.since is not None

    def progress(self) -> str:
        """The progress line while waiting ('' when not)."""
        if self.since is None:
            return ''
        left = max(0.0, self.bound - (self.now - self.since))
        return (f'calibration ready, waiting for still tilts to align it to the IMU before it '
                f'goes in force (at most {left:.0f} s more): {self.reason}')

    def values(self) -> dict[str, object]:
        """For /diagnostics while waiting: the seconds waited so far."""
        return {} if self.since is None else {'alignment_wait_s': round(self.now - self.since, 1)}

    def clear(self) -> None:
        self.since, self.reason = None, ''


__all__ = ['ALIGNMENT_WAIT_S', 'NO_STILL_WAIT_S', 'AlignmentWait']
