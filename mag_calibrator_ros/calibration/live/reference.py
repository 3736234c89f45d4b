# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""What the buffer screens and merges readings by, and when that stops describing the sensor.

The buffer refuses a reading far off its reference's sphere and merges near-duplicates by it
(``SampleBuffer.set_reference``). The reference is the buffer's own fit (a 'reference' job) once
one is sane, else the calibration in force; a planar calibration screens only while the sensor
stays in the plane it was turned in. The field's centre it gives files held-out readings by
direction (``evidence``).
"""

from __future__ import annotations

import numpy as np

from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.calibration.fit.heading import PlaneWatch
from mag_calibrator_ros.calibration.live.buffer import SampleBuffer

STALE_SHARE = 0.5
"""When the buffer's reference refuses more than half of a window of readings it no longer
describes the sensor (moved, re-mounted, another sensor's file): it is set aside rather than
starving the buffer of the data a new calibration needs."""


class BufferReference:
    """The buffer's reference, where it came from, and the field's centre."""

    def __init__(self, buffer: SampleBuffer) -> None:
        self.buffer = buffer
        self.source: str | None = None
        """'fit' (the buffer's own), 'calibration' (the one in force) or None (none)."""
        self.provisional: Calibration | None = None
        """The latest sane reference fit (the next reference job starts from it)."""
        self.calibration_plane: PlaneWatch | None = None
        """The plane of a planar calibration in force (it knows nothing off its plane)."""
        self.centre: np.ndarray | None = None
        """The field's centre in raw units, for filing evidence by direction."""
        self._plane: PlaneWatch | None = None  # a planar calibration's plane, while screened by it
        self._window = (0, 0)  # the buffer's (checked, outliers) when the window began

    def set(self, calibration: Calibration | None, tolerance: float | None,
            source: str | None) -> None:
        """Screen (and, a fit's, merge) by ``calibration``; None sets the reference aside."""
        self._plane = self.calibration_plane if source == 'calibration' else None
        if calibration is None:
            self.buffer.set_reference(None)
        elif tolerance is None:
            self.buffer.set_reference(calibration)
        else:
            self.buffer.set_reference(calibration, tolerance, merge=source == 'fit')
        self.source = source if calibration is not None else None
        self._window = (0, 0)

    def left_plane(self, reading: np.ndarray) -> bool:
        """Whether this reading shows the sensor left the plane of the planar calibration the
        buffer is screened by."""
        return self._plane is not None and self._plane.add(reading)

    def stale(self) -> tuple[str | None, int, int] | None:
        """Set the reference aside once it refused most of a window of readings: then its
        source, the readings it refused and the window's length; else None."""
        checked, outliers = self.buffer.reference_checks
        start_checked, start_outliers = self._window
        window = checked - start_checked
        if window < max(100, self.buffer.capacity):
            return None
        refused = outliers - start_outliers
        self._window = (checked, outliers)
        if refused <= STALE_SHARE * window:
            return None
        source = self.source
        self.set(None, None, None)
        if source == 'fit':
            self.provisional = None
        return source, refused, window

    def update_centre(self) -> None:
        """The centre from the buffer (its own fit, else the mean of its spread-out samples),
        never from the calibration in force: a wrong calibration must not make all evidence
        look alike."""
        if self.source == 'fit':
            self.centre = self.buffer.reference.offset
        elif self.buffer.fill >= 10:
            self.centre = self.buffer.anchors.mean(axis=0)
        else:
            self.centre = None

    def direction(self, reading: np.ndarray) -> np.ndarray:
        """Where a reading points from the field's centre, for filing it as evidence."""
        if self.centre is None:
            return reading
        direction = reading - self.centre
        return direction if np.any(direction) else reading


__all__ = ['STALE_SHARE', 'BufferReference']
