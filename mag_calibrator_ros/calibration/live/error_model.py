# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
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
away. Nor can the magnitude see a dip that is wrong (a planar fit trades the vertical offset
against the horizontal scale, |corrected| = F either way): where gravity is paired, the
stream's mean dip against the one expected (the model's, else the alignment's) is that error,
across the corrected field in its vertical plane: ``along`` gives it as a vector whose outer
product the covariance adds (no heading error: it lies in the field's vertical plane).

What a heading made from it is worth follows (``Accuracy``): a component error sigma across the
horizontal field H = F cos(dip) turns the heading by sigma / H radians, whatever the attitude (the
error is isotropic), so the heading's 1-sigma (68 %) needs only the dip: the one measured by the
alignment to gravity, else the one the stream shows (the corrected field against gravity's
direction while the robot does not accelerate, accepted when it scatters no more than the
alignment accepts), else the World Magnetic Model's. Its status follows Android's sensor
accuracy (SensorManager.SENSOR_STATUS_*: unreliable, low, medium, high) with the bounds of
``STATUS_BOUNDS_DEG``.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
import math

from mag_calibrator_ros.calibration.fit.alignment import MAX_DIP_STD_DEG
from mag_calibrator_ros.calibration.fit.calibration import Calibration

WINDOW = 256
"""Readings the running mean square spans (about 2.5 s at 100 Hz)."""
SEED_WEIGHT = 32
"""The fit's residual counts as this many readings until the window has its own."""
GROSS_SIGMAS = 3.0
"""A departure beyond this many sigmas is a gross error of this message, not noise."""
UNKNOWN_RESIDUAL = 0.05
"""The seed when a calibration states no residual (a hand-made file): the fit gate's 5 %."""
STATUS_BOUNDS_DEG = (('high', 2.0), ('medium', 5.0), ('low', 15.0))
"""The heading 1-sigma each status allows at most; beyond the last one it is 'unreliable'."""
UNKNOWN_DIP_STATUS = 'low'
"""The best status while the dip is unknown: the heading's sigma is the direction's over
cos(dip), unbounded from the direction alone."""
DISTURBED_SHARE = 0.25
"""A window with more gross readings than this share is disturbed now: 'unreliable'."""
DIP_WINDOW = 512
"""Paired readings the stream's dip is measured over."""
DIP_MIN_READINGS = 64
"""...and how many it needs before it says anything."""


@dataclass(frozen=True)
class Accuracy:
    """What the calibration in force is worth for a heading, for /diagnostics and answers."""

    status: str
    """'uncalibrated', 'unreliable', 'low', 'medium' or 'high' (``STATUS_BOUNDS_DEG``)."""
    direction_sigma_deg: float | None = None
    """The field direction's 1-sigma, deg: each component's sigma over F."""
    heading_sigma_deg: float | None = None
    """The heading's 1-sigma (68 %), deg; None while the dip is unknown."""
    dip_deg: float | None = None
    dip_source: str = ''
    """'measured' (the alignment to gravity), 'stream' (the readings against gravity), 'model'
    (the World Magnetic Model) or ''."""
    reason: str = ''
    """Why 'unreliable' when it is not the heading sigma itself."""

    def text(self) -> str:
        """One clause for a log line or a service answer."""
        if self.status == 'uncalibrated' or self.direction_sigma_deg is None:
            return 'accuracy uncalibrated'
        if self.heading_sigma_deg is None:
            told = (f'accuracy {self.status}: direction sigma {self.direction_sigma_deg:.2f} '
                    'deg (dip unknown: the heading sigma is at least that, so at best '
                    f'{UNKNOWN_DIP_STATUS}; give the location or an IMU)')
        elif not math.isfinite(self.heading_sigma_deg):
            told = f'accuracy {self.status}: heading sigma unbounded'
        else:
            told = (f'accuracy {self.status}: heading sigma {self.heading_sigma_deg:.2f} deg '
                    f'(68 %) at dip {self.dip_deg:.1f} deg ({self.dip_source})')
        return told + (f'; {self.reason}' if self.reason else '')

    def values(self) -> dict[str, object]:
        """/diagnostics key/values: plain numbers and strings ('' while unknown)."""
        def shown(value: float | None) -> object:
            return '' if value is None else round(value, 3) if math.isfinite(value) else 'inf'
        return {'calibration_status': self.status,
                'heading_sigma_deg': shown(self.heading_sigma_deg),
                'direction_sigma_deg': shown(self.direction_sigma_deg),
                'heading_dip_deg': shown(self.dip_deg), 'heading_dip_source': self.dip_source,
                'calibration_status_reason': self.reason}


def dip_of(calibration: Calibration | None, model_inclination_deg: float | None = None,
           stream_dip_deg: float | None = None) -> tuple[float | None, str]:
    """The dip a heading is judged at: measured by the calibration's alignment (or levelling)
    to gravity, else the stream's, else the model's inclination here, else unknown."""
    for key in ('dip_deg', 'levelled_dip_deg'):
        dip = None if calibration is None else calibration.metadata_number(key)
        if dip is not None and math.isfinite(dip):
            return dip, 'measured'
    if stream_dip_deg is not None and math.isfinite(stream_dip_deg):
        return float(stream_dip_deg), 'stream'
    if model_inclination_deg is not None and math.isfinite(model_inclination_deg):
        return float(model_inclination_deg), 'model'
    return None, ''


def heading_sigma_deg(sigma: float, field: float, dip_deg: float) -> float:
    """The heading's 1-sigma, deg, of a component error ``sigma`` on a field ``field`` at
    ``dip_deg``: sigma across the horizontal field; inf when there is no horizontal field."""
    horizontal = abs(field) * math.cos(math.radians(dip_deg))
    if not math.isfinite(sigma) or horizontal <= abs(field) * 1e-6:
        return math.inf
    return math.degrees(math.atan2(sigma, horizontal))


def accuracy(sigma: float, field: float, dip: tuple[float | None, str], reason: str = ''
             ) -> Accuracy:
    """The ``Accuracy`` of a component 1-sigma ``sigma`` on a field ``field`` (``dip``: of
    ``dip_of``); ``reason``: a cause that makes it 'unreliable' whatever the sigma (a misfit
    confirmed, a disturbed field). Without a dip the status is judged from the direction's
    sigma, a lower bound of the heading's, and is at best UNKNOWN_DIP_STATUS: a heading claim
    nothing bounds from above (on BROAD's trial 28, 'high' at 1.3 deg of direction while the
    heading was off by 4-6 deg at a dip of 69 deg)."""
    if not field > 0.0:
        return Accuracy('uncalibrated')
    direction = math.degrees(math.atan2(sigma, field)) if math.isfinite(sigma) else math.inf
    dip_deg, source = dip
    heading = None if dip_deg is None else heading_sigma_deg(sigma, field, dip_deg)
    judged = direction if heading is None else heading
    status = next((name for name, bound in STATUS_BOUNDS_DEG if judged <= bound), 'unreliable')
    if heading is None and status in ('high', 'medium'):
        status = UNKNOWN_DIP_STATUS
    if reason:
        status = 'unreliable'
    return Accuracy(status, direction, heading, dip_deg, source, reason)


def calibration_accuracy(calibration: Calibration | None,
                         model_inclination_deg: float | None = None,
                         stream_dip_deg: float | None = None) -> Accuracy:
    """What a calibration is worth by its own numbers (its fit's residual and direction
    uncertainty), before any reading judged it: for the answer that puts it in force."""
    if calibration is None:
        return Accuracy('uncalibrated')
    model = ErrorModel()
    model.restart(calibration)
    return accuracy(model.typical(), calibration.field_strength,
                    dip_of(calibration, model_inclination_deg, stream_dip_deg))


class ErrorModel:
    """The 1-sigma error of each corrected component, kept between messages."""

    def __init__(self) -> None:
        self._departures: deque[float] = deque(maxlen=WINDOW)  # squared, clipped
        self._gross: deque[float] = deque(maxlen=WINDOW)  # a gross one's departure, else 0
        self._gross_count = 0
        self._gross_sum = 0.0
        self._sum = 0.0
        self._seed = 0.0  # the fit's residual squared, field units squared
        self._own = 0.0  # the fit's direction uncertainty as a component error, squared
        self._field = 0.0
        self._dips: deque[float] = deque(maxlen=DIP_WINDOW)  # deg
        self._dip_sums = [0.0, 0.0]  # of dip, of dip squared
        self._up: Sequence[float] | None = None  # gravity's latest direction
        self._measured_dip: float | None = None  # the calibration's alignment's
        self._model_dip: float | None = None  # the World Magnetic Model's here

    def restart(self, calibration: Calibration | None) -> None:
        """A new calibration in force: its own residual seeds the model, the window starts
        anew (what the old one departed by says nothing about the new one)."""
        self._departures.clear()
        self._gross.clear()
        self._dips.clear()
        self._sum = 0.0
        self._gross_count = 0
        self._gross_sum = 0.0
        self._dip_sums = [0.0, 0.0]
        self._up = None
        self._measured_dip = dip_of(calibration)[0]
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
        model = self._model()
        gross = departure > GROSS_SIGMAS ** 2 * (model + self._own)
        kept = min(departure, GROSS_SIGMAS ** 2 * model)  # one magnet does not widen it all
        if len(self._departures) == WINDOW:
            self._sum -= self._departures[0]
            self._gross_count -= self._gross[0] > 0.0
            self._gross_sum -= self._gross[0]
        self._departures.append(kept)
        self._gross.append(departure if gross else 0.0)
        self._gross_count += gross
        self._gross_sum = max(self._gross_sum + (departure if gross else 0.0), 0.0)
        self._sum = max(self._sum + kept, 0.0)
        # A disturbed field (a magnet near, a zone): what its gross readings departed by, any
        # reading may be off by, in a direction the magnitude does not show on every one.
        disturbed = (self._gross_sum / self._gross_count
                     if self._gross_count > DISTURBED_SHARE * len(self._gross) else 0.0)
        return math.sqrt(model + self._own + max(departure if gross else 0.0, disturbed))

    def expect_dip(self, model_inclination_deg: float | None) -> None:
        """The World Magnetic Model's inclination here (None: unknown), the dip ``along``
        measures the stream against first."""
        finite = model_inclination_deg is not None and math.isfinite(model_inclination_deg)
        self._model_dip = float(model_inclination_deg) if finite else None

    def along(self, corrected: Sequence[float]) -> tuple[float, float, float]:
        """The dip error the magnitude cannot see, as a vector ``v`` (field units) whose outer
        product ``v v^T`` the covariance adds: the stream's mean dip against the expected one,
        times F, across ``corrected`` in its vertical plane (gravity's latest direction).
        Zero while there is nothing to measure it against or too few paired readings."""
        expected = self._model_dip if self._model_dip is not None else self._measured_dip
        count = len(self._dips)
        if expected is None or self._up is None or count < DIP_MIN_READINGS:
            return (0.0, 0.0, 0.0)
        norm = math.sqrt(sum(value * value for value in corrected))
        if not (math.isfinite(norm) and norm > 0.0):
            return (0.0, 0.0, 0.0)
        up, unit = self._up, [value / norm for value in corrected]
        along_up = sum(a * b for a, b in zip(up, unit, strict=True))
        across = [a - along_up * b for a, b in zip(up, unit, strict=True)]
        length = math.sqrt(sum(value * value for value in across))
        if length < 1e-6:
            return (0.0, 0.0, 0.0)
        size = self._field * math.radians(self._dip_sums[0] / count - expected) / length
        return (across[0] * size, across[1] * size, across[2] * size)

    def observe_dip(self, corrected: Sequence[float], up: Sequence[float]) -> None:
        """One corrected reading paired with gravity's direction ``up`` (unit, where the
        specific force points at rest) while the robot did not accelerate: its dip, O(1)."""
        norm = math.sqrt(sum(value * value for value in corrected))
        if not (math.isfinite(norm) and norm > 0.0):
            return
        sine = -sum(c * u for c, u in zip(corrected, up, strict=True)) / norm
        dip = math.degrees(math.asin(max(-1.0, min(1.0, sine))))
        if not math.isfinite(dip):
            return
        if len(self._dips) == DIP_WINDOW:
            old = self._dips[0]
            self._dip_sums[0] -= old
            self._dip_sums[1] -= old * old
        self._up = tuple(up)
        self._dips.append(dip)
        self._dip_sums[0] += dip
        self._dip_sums[1] += dip * dip

    def stream_dip(self) -> float | None:
        """The dip the recent paired readings show, deg, when there are DIP_MIN_READINGS and
        they scatter by at most the alignment's MAX_DIP_STD_DEG; else None."""
        count = len(self._dips)
        if count < DIP_MIN_READINGS:
            return None
        mean = self._dip_sums[0] / count
        spread = math.sqrt(max(self._dip_sums[1] / count - mean * mean, 0.0))
        return mean if spread <= MAX_DIP_STD_DEG else None

    def typical(self) -> float:
        """Each component's 1-sigma of a reading that is not gross (0.0 without a
        calibration): the model and the calibration's own error."""
        return math.sqrt(self._model() + self._own) if self._field > 0.0 else 0.0

    def accuracy(self, calibration: Calibration | None, model_inclination_deg: float | None,
                 extra_sigma: float = 0.0, misfit: str = '') -> Accuracy:
        """The heading ``Accuracy`` of ``calibration`` (the one in force, this model's) now:
        the typical sigma with ``extra_sigma`` (a misfit's error) in quadrature; unreliable
        while ``misfit`` says why or more than DISTURBED_SHARE of the window was gross."""
        if calibration is None or self._field <= 0.0:
            return Accuracy('uncalibrated')
        reason = misfit
        count = len(self._gross)
        if not reason and count and self._gross_count > DISTURBED_SHARE * count:
            reason = (f'{100.0 * self._gross_count / count:.0f} % of the last {count} readings '
                      'departed from the field strength beyond the model (a magnet near, or '
                      'the field changed)')
        return accuracy(math.hypot(self.typical(), extra_sigma), self._field,
                        dip_of(calibration, model_inclination_deg, self.stream_dip()), reason)

    def _model(self) -> float:
        count = len(self._departures)
        return (self._sum + SEED_WEIGHT * self._seed) / (count + SEED_WEIGHT)
