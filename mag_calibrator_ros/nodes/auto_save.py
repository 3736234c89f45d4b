# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""When ``auto_save`` writes the calibration in force to ``calibration_file``.

Online tracking and refinement may put calibrations in force in quick succession; writing each
would rewrite the file (flash wear, I/O) for little. So one write at a time, at most every
AUTO_SAVE_MIN_INTERVAL_S, and a calibration adopted meanwhile is written afterwards (the one in
force then: the file always ends up with the latest).
"""

from __future__ import annotations

import math

AUTO_SAVE_MIN_INTERVAL_S = 10.0
"""auto_save writes at most this often; a calibration adopted meanwhile is saved afterwards."""


class AutoSaveThrottle:
    """The decision alone; ``now`` is seconds of any monotonic clock."""

    def __init__(self, min_interval_s: float = AUTO_SAVE_MIN_INTERVAL_S) -> None:
        self.min_interval_s = min_interval_s
        self._wanted = False
        self._saving = False
        self._last_start = -math.inf

    def adopted(self, auto_save: bool) -> None:
        """A calibration went in force; ``auto_save`` is the parameter's value now."""
        self._wanted = auto_save

    def start(self, now: float) -> bool:
        """True when a write should begin now; it counts as running until ``finished``."""
        if not self._wanted or self._saving or now - self._last_start < self.min_interval_s:
            return False
        self._wanted = False
        self._last_start = now
        self._saving = True
        return True

    def finished(self) -> None:
        """The write ended (written or failed)."""
        self._saving = False
