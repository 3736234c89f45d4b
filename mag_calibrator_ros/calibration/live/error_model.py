"""How wrong the calibration in force is, per corrected message (issue #45, REP-145).

A corrected field should have ``|corrected| = F``: what departs from it is sensor noise, the
calibration's own error and the world's disturbances together. ``ErrorModel`` keeps the mean
square of that departure over the last readings (O(1) per message), seeded by the fit's own
residual so the first message is never "unknown", and marks a reading that departs by more
than GROSS_SIGMAS of the model with its own departure at once, before any state changes (a
wrong file, a magnet passing). An isotropic component error of sigma gives a magnitude error
of sigma, so the one number is each component's 1-sigma. What the magnitude cannot see (a
direction wrong by the fit's own uncertainty, ``direction_std_deg`` of a gyroscope-aided fit:
its jackknife over windows) is added as the calibration's own error, which no window averages
away.
"""

from __future__ import annotations

from collections import deque
import math

from mag_calibrator_ros.calibration.fit.calibration import Calibration

WINDOW = 256
"""Readings the running mean square spans (about 2.5 s at 100 Hz)."""
SEED_WEIGHT = 32
"""The fit's residual counts as this many readings until the window has its own."""
GROSS_SIGMAS = 3.0
"""A departure beyond this many sigmas is a gross error of this message, not noise."""
UNKNOWN_RESIDUAL = 0.05
"""The seed when a calibration states no residual (a hand-made file): the fit gate's 5 %."""


class ErrorModel:
    """The 1-sigma error of each corrected component, kept between messages."""

    def __init__(self) -> None:
        self._departures: deque[float] = deque(maxlen=WINDOW)  # squared, clipped
        self._sum = 0.0
        self._seed = 0.0  # the fit's residual squared, field units squared
        self._own = 0.0  # the fit's direction uncertainty as a component error, squared
        self._field = 0.0

    def restart(self, calibration: Calibration | None) -> None:
        """A new calibration in force: its own residual seeds the model, the window starts
        anew (what the old one departed by says nothing about the new one)."""
        self._departures.clear()
        self._sum = 0.0
        if calibration is None:
            self._field = self._seed = self._own = 0.0
            return
        residual = calibration.metadata_number('residual_rms_pct')
        share = UNKNOWN_RESIDUAL if residual is None else max(residual, 0.0) / 100.0
        self._field = calibration.field_strength
        self._seed = (share * self._field) ** 2
        direction_deg = calibration.metadata_number('direction_std_deg') or 0.0
        self._own = (self._field * math.radians(max(direction_deg, 0.0))) ** 2

    def sigma(self, magnitude: float) -> float:
        """Each component's 1-sigma for a corrected reading of length ``magnitude``: the
        model's, or the reading's own departure when that is gross. 0.0 without a calibration;
        a non-finite magnitude gives inf (no trust at all)."""
        if self._field <= 0.0:
            return 0.0
        if not math.isfinite(magnitude):
            return math.inf
        departure = (magnitude - self._field) ** 2
        count = len(self._departures)
        model = (self._sum + SEED_WEIGHT * self._seed) / (count + SEED_WEIGHT)
        gross = departure > GROSS_SIGMAS ** 2 * (model + self._own)
        kept = min(departure, GROSS_SIGMAS ** 2 * model)  # one magnet does not widen it all
        if count == WINDOW:
            self._sum -= self._departures[0]
        self._departures.append(kept)
        self._sum = max(self._sum + kept, 0.0)
        return math.sqrt(model + self._own + (departure if gross else 0.0))
