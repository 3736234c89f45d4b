# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""What a session hands back: the outcome of each message (``Processed``) and each decision
(``SessionEvent``), and the vocabulary both use (the reasons a reading is refused, the states).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.calibration.live.report import CalibrationAttempt
from mag_calibrator_ros.calibration.live.screening import SCREEN_REASONS

REFUSAL_REASONS = (*SCREEN_REASONS, 'duplicate', 'magnitude_outlier')
"""Every reason a reading is not used: screening, then the buffer's own two."""

STATES = ('uncalibrated', 'collecting', 'calibrated', 'calibrated-refining',
          'calibrated-converged', 'calibrated-misfit')

MAX_EVENTS = 1000
"""Events kept for ``take_events`` at the most (the oldest go first)."""


class Processed(NamedTuple):
    """What ``process`` made of one message."""

    accepted: bool
    corrected: np.ndarray | None
    """The corrected field, None while uncalibrated (or when refused)."""
    calibration: Calibration | None
    """The calibration that corrected it (for the covariance)."""
    uncertainty: float = 0.0
    """Each corrected component's 1-sigma in field units (``ErrorModel.sigma``, with the median
    |B| error of a confirmed misfit added in quadrature); the node puts it on the covariance.
    0.0 only while uncalibrated."""
    along: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """An error in one direction the magnitude cannot see (``ErrorModel.along``, field units):
    the node adds its outer product to the covariance."""


REFUSED = Processed(False, None, None)
"""A message no fit may see (``REFUSAL_REASONS``)."""


@dataclass(frozen=True)
class SessionEvent:
    """Something the session decided, for the log (``level``: 'info', 'warning' or 'debug').

    ``adopted``: a new calibration is in force (auto_save applies); ``ticket``: the answer to
    ``request_calibration``.
    """

    level: str
    message: str
    adopted: bool = False
    ticket: int | None = None
    attempt: CalibrationAttempt | None = None


__all__ = ['MAX_EVENTS', 'REFUSAL_REASONS', 'REFUSED', 'STATES', 'Processed', 'SessionEvent']
