"""The live calibrator's decisions, kept apart from ROS so they can be tested without a graph.

A ``CalibrationSession`` owns everything the ``mag_calibrator`` node decides per message and per
second: which messages are usable (screening, with counters), what goes into the sample buffer,
the state (uncalibrated / collecting / calibrated), when to calibrate by itself, whether a
calibration tracked online is clearly better and how far it may move per second, and the
progress text a user reads. The node only turns ROS messages, parameters and services into calls
here. Units are tesla throughout (REP-103); the engine itself is unit-free.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, replace
import math
from pathlib import Path
import time

import numpy as np

from mag_calibrator_ros.calibration.buffer import SampleBuffer, reading_problem
from mag_calibrator_ros.calibration.calibration import MODELS, Calibration, CalibrationError
from mag_calibrator_ros.calibration.calibration_file import (
    CalibrationFileError,
    load_calibration,
    save_calibration,
)
from mag_calibrator_ros.calibration.coverage import direction_coverage
from mag_calibrator_ros.calibration.fitting import FitOptions, FitResult, fit_calibration
from mag_calibrator_ros.calibration.tracker import OnlineTracker

TESLA_TO_MICROTESLA = 1e6
AK09916_FULL_SCALE_T = 32752 * 0.15e-6
"""The ICM-20948's magnetometer saturates at +-32752 LSB x 0.15 uT (DESIGN.md section 5)."""

SCREEN_REASONS = ('non_finite', 'zero', 'saturated', 'stamp_backwards', 'frame_changed')
"""Why a message is refused before it reaches the buffer or the corrected topic."""

STATES = ('uncalibrated', 'collecting', 'calibrated')
FITTABLE_MODELS = tuple(MODELS)
TRACKING_EVALUATION_SAMPLES = 200
"""Recent samples on which a tracked calibration must beat the one in force."""
TRACKING_MIN_SAMPLES = 50
TRACKING_MIN_SEPARATION_DEG = 6.0
"""A reading teaches the tracker only when its corrected direction is at least this far from the
last one that did (ArduPilot accepts samples about 6 deg apart). A robot standing still next to a
disturbance would otherwise pull the calibration toward fitting that one direction."""
TRACKING_MIN_COVERAGE = 0.25
"""Share of direction cells the recent readings must span before a tracked calibration may be
judged better: better in one corner of the sphere is not better."""


def _engine_defaults() -> tuple[int, int, FitOptions]:
    """Buffer size, k and fit gates as the engine chose them from its benchmarks."""
    buffer = SampleBuffer()
    return buffer.capacity, buffer.k, FitOptions()


_DEFAULT_BUFFER_SIZE, _DEFAULT_K, _DEFAULT_FIT = _engine_defaults()


@dataclass(frozen=True)
class SessionSettings:
    """Everything a user can tune; the node mirrors each field as a ROS parameter."""

    buffer_size: int = _DEFAULT_BUFFER_SIZE
    k: int = _DEFAULT_K
    model: str = 'auto'
    field_strength: float = 0.0
    """Tesla; 0 keeps the fitted mean radius (magnitude preserved)."""
    min_coverage: float = float(_DEFAULT_FIT.min_coverage)
    max_residual_pct: float = float(_DEFAULT_FIT.max_residual_pct)
    full_scale: float = AK09916_FULL_SCALE_T
    """Tesla; a component at or beyond it is saturated. 0 disables the check."""
    auto_calibrate: bool = True
    auto_calibrate_period: float = 2.0
    """Seconds between automatic attempts, so a failing fit does not run on every tick."""
    online_tracking: bool = False
    tracking_improvement: float = 0.8
    """Adopt a tracked calibration only when its residual is below this share of the current."""
    tracking_max_change_rate: float = 0.01
    """Per second: offset change as a share of the field, matrix change as a relative norm."""

    @property
    def full_scale_limit(self) -> float | None:
        """``full_scale`` as the buffer takes it: None when the check is off (0)."""
        return self.full_scale if self.full_scale > 0.0 else None

    def problems(self) -> list[str]:
        """Every reason these settings cannot work, in words a user can act on."""
        problems = []
        if self.buffer_size < 10:
            problems.append(f'buffer_size must be >= 10, got {self.buffer_size}')
        if self.k < 1 or self.k >= self.buffer_size:
            problems.append(f'k must be in [1, buffer_size - 1], got k={self.k} with '
                            f'buffer_size={self.buffer_size}')
        if self.model not in FITTABLE_MODELS:
            problems.append(
                f"model must be one of {', '.join(FITTABLE_MODELS)}, got {self.model!r}"
            )
        if not math.isfinite(self.field_strength) or self.field_strength < 0.0:
            problems.append(f'field_strength must be >= 0 tesla (0 = fitted radius), '
                            f'got {self.field_strength}')
        if not 0.0 <= self.min_coverage <= 1.0:
            problems.append(f'min_coverage must be a fraction in [0, 1], got {self.min_coverage}')
        if not math.isfinite(self.max_residual_pct) or self.max_residual_pct <= 0.0:
            problems.append(f'max_residual_pct must be > 0, got {self.max_residual_pct}')
        if not math.isfinite(self.full_scale) or self.full_scale < 0.0:
            problems.append(
                f'full_scale must be >= 0 tesla (0 = no check), got {self.full_scale}'
            )
        if not math.isfinite(self.auto_calibrate_period) or self.auto_calibrate_period <= 0.0:
            problems.append(
                f'auto_calibrate_period must be > 0 s, got {self.auto_calibrate_period}'
            )
        if not 0.0 < self.tracking_improvement < 1.0:
            problems.append(f'tracking_improvement must be in (0, 1), got '
                            f'{self.tracking_improvement}')
        if not math.isfinite(self.tracking_max_change_rate) or self.tracking_max_change_rate <= 0:
            problems.append(f'tracking_max_change_rate must be > 0 per second, got '
                            f'{self.tracking_max_change_rate}')
        return problems

    def fit_options(self) -> FitOptions:
        return replace(
            _DEFAULT_FIT,
            model=self.model,
            field_strength=self.field_strength if self.field_strength > 0.0 else None,
            min_coverage=self.min_coverage,
            max_residual_pct=self.max_residual_pct,
        )


@dataclass(frozen=True)
class CalibrationAttempt:
    """The outcome of one fit, phrased for a service answer or a log line."""

    success: bool
    message: str
    result: FitResult | None = None


@dataclass
class _RateMeter:
    """Messages per second since the previous reading (called at the diagnostics rate)."""

    count: int = 0
    _last_count: int = 0
    _last_time: float | None = None
    rate: float = 0.0

    def read(self, now: float) -> float:
        if self._last_time is not None and now > self._last_time:
            self.rate = (self.count - self._last_count) / (now - self._last_time)
        self._last_count, self._last_time = self.count, now
        return self.rate


def magnitude_residual_pct(calibration: Calibration, samples: np.ndarray) -> float:
    """RMS of ``|corrected| - F`` as a percentage of F: the engine's residual measure."""
    if len(samples) == 0:
        return math.inf
    magnitudes = np.linalg.norm(calibration.apply(samples), axis=1)
    return float(100.0 * np.sqrt(np.mean((magnitudes / calibration.field_strength - 1.0) ** 2)))


def transform_covariance(matrix: np.ndarray, covariance: np.ndarray) -> np.ndarray:
    """``M C M^T`` for a known covariance; all-zero (unknown) and -1 (not reported) pass as is."""
    covariance = np.asarray(covariance, dtype=float).reshape(3, 3)
    if not np.any(covariance) or covariance[0, 0] == -1.0:
        return covariance.reshape(9).copy()
    return (matrix @ covariance @ matrix.T).reshape(9)


def bounded_step(current: Calibration, target: Calibration, max_change: float) -> Calibration:
    """Move from ``current`` towards ``target`` by at most ``max_change`` (relative units).

    The offset moves at most ``max_change * F`` and the matrix at most ``max_change`` times its own
    norm, so a tracked calibration can never jump, however wrong the tracker is for a moment.
    """
    offset_delta = target.offset - current.offset
    matrix_delta = target.matrix - current.matrix
    offset_limit = max_change * current.field_strength
    matrix_limit = max_change * np.linalg.norm(current.matrix) / math.sqrt(3.0)
    offset_norm = float(np.linalg.norm(offset_delta))
    matrix_norm = float(np.linalg.norm(matrix_delta))
    fraction = 1.0
    if offset_norm > offset_limit:
        fraction = min(fraction, offset_limit / offset_norm)
    if matrix_norm > matrix_limit:
        fraction = min(fraction, matrix_limit / matrix_norm)
    return Calibration(
        current.offset + fraction * offset_delta,
        current.matrix + fraction * matrix_delta,
        current.field_strength,
        current.model,
        {**current.metadata, 'source': 'online_tracking'},
    )


def calibration_summary(calibration: Calibration, metrics: Mapping[str, object] | None) -> str:
    """One line for the ``~/calibrate`` answer: model, offset in uT, residual %, coverage %."""
    offset = ', '.join(f'{v * TESLA_TO_MICROTESLA:.2f}' for v in calibration.offset)
    text = f'model {calibration.model}, offset [{offset}] uT'
    if metrics:
        text += (f", residual {float(metrics['residual_rms_pct']):.2f} %"
                 f", coverage {100.0 * float(metrics['coverage']):.0f} %"
                 f", {int(metrics['n_samples'])} samples")
    return text


class CalibrationSession:
    """The calibrator's state between messages: buffer, calibration in force, counters, tracker."""

    def __init__(
        self,
        settings: SessionSettings | None = None,
        calibration: Calibration | None = None,
    ) -> None:
        self.settings = settings or SessionSettings()
        problems = self.settings.problems()
        if problems:
            raise ValueError('; '.join(problems))
        self.buffer = self._new_buffer(self.settings)
        self.screen_rejects = dict.fromkeys(SCREEN_REASONS, 0)
        self.accepted = 0
        self.input_rate = _RateMeter()
        self.frame_id: str | None = None
        self._last_stamp_ns: int | None = None
        self.calibration: Calibration | None = None
        self.last_attempt: CalibrationAttempt | None = None
        self.last_residual_pct: float | None = None
        self.tracker: OnlineTracker | None = None
        self.tracked_updates = 0
        self._recent: deque[np.ndarray] = deque(maxlen=TRACKING_EVALUATION_SAMPLES)
        self._last_taught: np.ndarray | None = None  # corrected direction last fed to the tracker
        self._last_auto_attempt = -math.inf
        self._last_tracking_check: float | None = None
        self._reported_rejects = dict(self.screen_rejects)
        if calibration is not None:
            self.apply_calibration(calibration)

    # -- configuration -------------------------------------------------------------------------

    @staticmethod
    def _new_buffer(settings: SessionSettings) -> SampleBuffer:
        return SampleBuffer(
            capacity=settings.buffer_size, k=settings.k, full_scale=settings.full_scale_limit
        )

    def reconfigure(self, settings: SessionSettings) -> None:
        """Adopt new settings; a resized buffer keeps its most unique samples."""
        problems = settings.problems()
        if problems:
            raise ValueError('; '.join(problems))
        old = self.settings
        self.settings = settings
        if (settings.buffer_size, settings.k) != (old.buffer_size, old.k):
            self.buffer.resize(settings.buffer_size, settings.k)
        self.buffer.full_scale = settings.full_scale_limit
        if settings.online_tracking != old.online_tracking:
            self._restart_tracker()

    # -- per message ---------------------------------------------------------------------------

    def screen(self, stamp_ns: int, frame_id: str, field_t: np.ndarray) -> str | None:
        """Why this message is unusable (a SCREEN_REASONS entry), or None; counts the reason."""
        if field_t.shape != (3,):
            reason = 'non_finite'
        else:
            reason = reading_problem(*field_t.tolist(), self.settings.full_scale_limit)
        if reason is None and self.frame_id is not None and frame_id != self.frame_id:
            reason = 'frame_changed'
        if reason is None and self._last_stamp_ns is not None and stamp_ns < self._last_stamp_ns:
            reason = 'stamp_backwards'
        if reason is not None:
            self.screen_rejects[reason] += 1
        return reason

    def ingest(self, stamp_ns: int, frame_id: str, field_t: np.ndarray) -> str | None:
        """Screen one message and feed it to the buffer and tracker; returns the reject reason.

        The first accepted message fixes the frame: a calibration belongs to one sensor frame.
        """
        self.input_rate.count += 1
        field_t = np.asarray(field_t, dtype=float)
        reason = self.screen(stamp_ns, frame_id, field_t)
        if reason is not None:
            return reason
        self.accepted += 1
        self.frame_id = frame_id
        self._last_stamp_ns = stamp_ns
        self.buffer.add(field_t)
        if self.tracker is not None and self._teaches_tracker(field_t):
            self.tracker.update(field_t)
            self._recent.append(field_t)
        return None

    def _teaches_tracker(self, field_t: np.ndarray) -> bool:
        """Whether this reading points somewhere new (see TRACKING_MIN_SEPARATION_DEG)."""
        direction = self.calibration.apply(field_t)
        norm = float(np.linalg.norm(direction))
        if not norm > 0.0:
            return False
        direction /= norm
        if self._last_taught is not None and float(direction @ self._last_taught) > math.cos(
            math.radians(TRACKING_MIN_SEPARATION_DEG)
        ):
            return False
        self._last_taught = direction
        return True

    def correct(self, field_t: np.ndarray) -> np.ndarray | None:
        """The corrected field, or None while no calibration is in force."""
        if self.calibration is None:
            return None
        return self.calibration.apply(field_t)

    # -- state and calibration -----------------------------------------------------------------

    @property
    def state(self) -> str:
        if self.calibration is not None:
            return 'calibrated'
        return 'collecting' if self.buffer.fill > 0 else 'uncalibrated'

    def apply_calibration(self, calibration: Calibration) -> None:
        """Put a calibration in force at once (fit, file or parameters)."""
        self.calibration = calibration
        self.buffer.set_reference(calibration)
        residual = calibration.metadata.get('residual_rms_pct')
        self.last_residual_pct = float(residual) if residual is not None else None
        self._restart_tracker()

    def _restart_tracker(self) -> None:
        self._recent.clear()
        self._last_taught = None
        self._last_tracking_check = None
        if self.settings.online_tracking and self.calibration is not None:
            self.tracker = OnlineTracker(self.calibration)
        else:
            self.tracker = None

    def calibrate(self) -> CalibrationAttempt:
        """Fit the buffer; apply on success, keep the previous calibration on failure."""
        # counts: how many readings each buffered point averages (SampleBuffer merging);
        # readings: recent raw readings, so coverage can tell a noise rim from the field sphere
        result = fit_calibration(
            self.buffer.samples,
            self.settings.fit_options(),
            weights=self.buffer.counts,
            readings=self.buffer.readings,
        )
        metrics = result.metrics.as_dict()
        if result.success and result.calibration is not None:
            calibration = result.calibration.with_metadata(
                residual_rms_pct=float(result.metrics.residual_rms_pct),
                coverage=float(result.metrics.coverage),
                time=time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime()),
                frame_id=self.frame_id or '',
                units='T',
            )
            self.apply_calibration(calibration)
            attempt = CalibrationAttempt(True, calibration_summary(calibration, metrics), result)
        else:
            kept = ('; the previous calibration stays in force' if self.calibration is not None
                    else '; still uncalibrated')
            message = f'calibration failed: {result.reason}{kept}'
            attempt = CalibrationAttempt(False, message, result)
        self.last_attempt = attempt
        return attempt

    def reset(self) -> None:
        """Empty the buffer and forget the stream's frame and stamps (a new sensor may follow)."""
        self.buffer.clear()
        self.frame_id = None
        self._last_stamp_ns = None
        self._recent.clear()
        self._last_taught = None

    def maybe_auto_calibrate(self, now: float) -> CalibrationAttempt | None:
        """Calibrate by itself once the buffer looks ready, at most every auto_calibrate_period.

        Only while uncalibrated: a calibration in force is changed by ~/calibrate or, slowly, by
        online tracking, never replaced behind the user's back.
        """
        settings = self.settings
        if not settings.auto_calibrate or self.calibration is not None:
            return None
        if now - self._last_auto_attempt < settings.auto_calibrate_period:
            return None
        if self.buffer.fill < min(_DEFAULT_FIT.min_samples, settings.buffer_size):
            return None
        if self.buffer.coverage().fraction < settings.min_coverage:
            return None
        self._last_auto_attempt = now
        return self.calibrate()

    def maybe_adopt_tracked(self, now: float) -> bool:
        """Adopt the tracker's calibration if clearly better on recent data, by a bounded step."""
        if self.tracker is None or self.calibration is None:
            return False
        if self._last_tracking_check is None:
            self._last_tracking_check = now
            return False
        elapsed = now - self._last_tracking_check
        if elapsed <= 0.0:
            return False
        self._last_tracking_check = now
        if len(self._recent) < TRACKING_MIN_SAMPLES:
            return False
        recent = np.array(self._recent)
        if direction_coverage(recent, self.calibration).fraction < TRACKING_MIN_COVERAGE:
            return False
        current_residual = magnitude_residual_pct(self.calibration, recent)
        candidate = self.tracker.calibration
        candidate_residual = magnitude_residual_pct(candidate, recent)
        if not candidate_residual < self.settings.tracking_improvement * current_residual:
            return False
        try:
            stepped = bounded_step(
                self.calibration, candidate, self.settings.tracking_max_change_rate * elapsed
            )
        except CalibrationError:
            return False
        self.calibration = stepped
        self.buffer.set_reference(stepped)
        self.last_residual_pct = magnitude_residual_pct(stepped, recent)
        self.tracked_updates += 1
        return True

    # -- persistence ---------------------------------------------------------------------------

    def load(self, path: str | Path) -> str:
        """Load and apply the file; raises CalibrationFileError (message names the problem)."""
        calibration = load_calibration(Path(path).expanduser())
        self.apply_calibration(calibration)
        return f'loaded {Path(path).expanduser()}: {calibration_summary(calibration, None)}'

    def save(self, path: str | Path) -> str:
        """Write the calibration in force atomically; raises ValueError/OSError when impossible."""
        if self.calibration is None:
            raise ValueError('nothing to save: no calibration in force (call ~/calibrate first)')
        target = Path(path).expanduser()
        save_calibration(target, self.calibration)
        return f'saved to {target}'

    # -- reporting -----------------------------------------------------------------------------

    def rejects(self) -> dict[str, int]:
        """Screening counters plus the buffer's own (duplicates, magnitude outliers)."""
        counts = dict(self.screen_rejects)
        for reason, count in self.buffer.rejects.items():
            counts[reason] = counts.get(reason, 0) + int(count)
        return counts

    def progress_text(self) -> str:
        """What to do next, e.g. 'coverage 63 % - keep rotating about the pitch axis (y)'."""
        coverage = self.buffer.coverage()
        fill = f'buffer {self.buffer.fill}/{self.buffer.capacity}'
        text = f'coverage {100.0 * coverage.fraction:.0f} %'
        if self.calibration is not None:
            return f'calibrated ({self.calibration.model}); {text}, {fill}'
        if coverage.fraction < self.settings.min_coverage:
            hint = coverage.hint or 'keep rotating the sensor through every orientation'
            return f'{text} \u2014 {hint}; {fill}'
        if self.settings.auto_calibrate:
            return f'{text}, {fill} \u2014 enough to calibrate; calibrating automatically'
        return f'{text}, {fill} \u2014 enough to calibrate: call ~/calibrate'

    def new_screen_rejects(self) -> dict[str, int]:
        """Messages refused since the previous call, by reason (only reasons that occurred)."""
        new = {reason: count - self._reported_rejects[reason]
               for reason, count in self.screen_rejects.items()
               if count > self._reported_rejects[reason]}
        self._reported_rejects = dict(self.screen_rejects)
        return new

    def diagnostic_values(self, now: float) -> dict[str, object]:
        """Key/values for /diagnostics; read once per diagnostics period (updates the rate)."""
        coverage = self.buffer.coverage()
        values: dict[str, object] = {
            'state': self.state,
            'coverage_pct': round(100.0 * coverage.fraction, 1),
            'coverage_hint': coverage.hint,
            'buffer_fill': self.buffer.fill,
            'buffer_capacity': self.buffer.capacity,
            'relative_knn_distance': float(self.buffer.relative_knn_distance),
            'input_rate_hz': round(self.input_rate.read(now), 2),
            'messages_accepted': self.accepted,
            'frame_id': self.frame_id or '',
            'last_residual_pct': ('' if self.last_residual_pct is None
                                  else round(self.last_residual_pct, 3)),
            'last_calibrate': '' if self.last_attempt is None else self.last_attempt.message,
        }
        values.update({f'rejected_{k}': v for k, v in self.rejects().items()})
        if self.calibration is not None:
            values['model'] = self.calibration.model
            values['offset_uT'] = [round(v * TESLA_TO_MICROTESLA, 3)
                                   for v in self.calibration.offset]
            values['field_strength_uT'] = round(
                self.calibration.field_strength * TESLA_TO_MICROTESLA, 3)
        if self.tracker is not None:
            values['tracked_updates'] = self.tracked_updates
        return values


__all__ = [
    'AK09916_FULL_SCALE_T',
    'SCREEN_REASONS',
    'STATES',
    'CalibrationAttempt',
    'CalibrationFileError',
    'CalibrationSession',
    'SessionSettings',
    'bounded_step',
    'calibration_summary',
    'magnitude_residual_pct',
    'transform_covariance',
]
