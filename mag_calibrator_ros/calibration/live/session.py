"""The live calibrator's decisions, kept apart from ROS so they can be tested without a graph.

A :class:`CalibrationSession` takes one call per message, ``process(stamp, frame, field)``, and
returns the corrected field. Behind it, and nowhere else, it decides:

- which messages are usable (``screening``: one set of counters, stamps and frames confirmed);
- what the buffer keeps and the reference it screens and merges by (its own fit, else the
  calibration in force), and when that reference no longer describes the sensor;
- every fit (``scheduler``): the buffer's reference, automatic calibration, refinement, requested
  fits. Fits run in a ``FitRunner`` (a worker process in the node, inline offline) on a snapshot;
  while one runs, readings are held and fed to the buffer afterwards in order, so the result is
  the same whether the fit took a microsecond or a second: node and ``mag_calibrator_fit`` agree
  on the same stream;
- whether a new fit replaces the calibration in force: automatically only while uncalibrated or
  after a misfit, by refinement only when it is better on held-out readings (``evidence``) and
  covers no less; on request whenever it passes the gates;
- whether the calibration in force still fits the sensor (``evidence.MisfitMonitor``);
- online tracking (``tracker``), judged on the same held-out readings;
- with an IMU (``process_imu``): which readings pair with an accelerometer sample and are held
  still (``alignment.StaticAttitudes``), and whether a fit's rotation into the IMU frame goes in
  force; with a location (``set_earth_field``): the target field strength and the checks of a
  fit against the World Magnetic Model.

What it decided comes out as ``SessionEvent``s for the node to log and act on (auto-save,
service answers). Units are the caller's (tesla in the node); the engine is unit-free.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
import math
import random
import time
from typing import NamedTuple

import numpy as np

from mag_calibrator_ros.calibration.fit.alignment import (
    MAX_ANGLE_DEG,
    Alignment,
    AlignmentOptions,
    StaticAttitudes,
    rotation_angle_deg,
)
from mag_calibrator_ros.calibration.fit.calibration import MODELS, Calibration, CalibrationError
from mag_calibrator_ros.calibration.fit.coverage import HEADING_SECTORS, Coverage
from mag_calibrator_ros.calibration.fit.earth_field import (
    MAX_DIP_ERROR_DEG,
    MAX_FIELD_ERROR_PCT,
    EarthCheck,
    EarthField,
    EarthReference,
    disturbance_text,
)
from mag_calibrator_ros.calibration.fit.fitting import FitOptions
from mag_calibrator_ros.calibration.fit.heading import (
    COMPLETE_HEADING_COVERAGE,
    HeadingCoverage,
    PlaneWatch,
    heading_coverage_of,
    yaw_only,
)
from mag_calibrator_ros.calibration.live.buffer import SampleBuffer
from mag_calibrator_ros.calibration.live.evidence import (
    HOLD_OUT_EVERY,
    MIN_EVIDENCE,
    MISFIT_WINDOW_S,
    Comparison,
    HeldOutEvidence,
    MisfitMonitor,
)
from mag_calibrator_ros.calibration.live.jobs import REFERENCE_OPTIONS, FitJob, JobOutcome
from mag_calibrator_ros.calibration.live.scheduler import (
    CHECK_FIT_PERIOD_S,
    FitScheduler,
    Situation,
    StreamClock,
)
from mag_calibrator_ros.calibration.live.screening import SCREEN_REASONS, ReadingScreen
from mag_calibrator_ros.calibration.live.tracker import OnlineTracker
from mag_calibrator_ros.calibration.live.worker import FitRunner, InlineRunner
from mag_calibrator_ros.icm20948 import registers as reg

TESLA_TO_MICROTESLA = 1e6
AK09916_FULL_SCALE_T = reg.MEASUREMENT_LIMIT * reg.TESLA_PER_LSB
"""The AK09916 saturates at its measurement limit (ST2 HOFL beyond it), in tesla."""

REFUSAL_REASONS = (*SCREEN_REASONS, 'duplicate', 'magnitude_outlier')
"""Every reason a reading is not used: screening, then the buffer's own two."""

STATES = ('uncalibrated', 'collecting', 'calibrated', 'calibrated-refining',
          'calibrated-converged', 'calibrated-misfit')
FITTABLE_MODELS = tuple(MODELS)

HOLD_LIMIT = 5000
"""Readings held while a fit runs; beyond this (a worker far too slow for the rate) the oldest
are fed to the buffer at once and the run is no longer exactly reproducible (counted)."""

DRAIN_PER_MESSAGE = 2
"""Held readings fed per incoming message once a fit is done: bounded work per callback. Each
costs about as much as the message itself, so the callback's worst case stays a few times its
median and the backlog of a fit still shrinks by two readings a message."""

DRAIN_FOR_REQUEST = 64
"""Held readings a poll feeds while a ~/calibrate waits for them (its fit includes every reading
received before the call): a user waits, so the backlog of a slow worker goes first, at a few
milliseconds per poll."""

STALE_SHARE = 0.5
"""When the buffer's reference refuses more than half of a window of readings it no longer
describes the sensor (moved, re-mounted, another sensor's file): it is set aside rather than
starving the buffer of the data a new calibration needs."""

REPORTED_COVERAGE_AGE_S = 2.0 * CHECK_FIT_PERIOD_S
"""Stream seconds a coverage measured by the fit worker stands for the buffer's in reports: a
check measures it every CHECK_FIT_PERIOD_S while calibrated, a readiness test every
CHECK_PERIOD_S while calibrating automatically."""

PERIODIC_S = 1.0
"""Stream seconds between updates of the field's centre (for filing evidence by direction)."""

TRACKING_MIN_SEPARATION_DEG = 6.0
"""A reading teaches the tracker only when its corrected direction is at least this far from the
last one that did (ArduPilot accepts samples about 6 deg apart). A robot standing still next to a
disturbance would otherwise pull the calibration toward fitting that one direction."""

MAX_EVENTS = 1000

IMU_RING = 256
"""Recent accelerometer samples kept to pair magnetometer readings with (256 ms at 1 kHz)."""
PAIR_TOLERANCE_NS = 20_000_000
"""A magnetometer reading pairs with the accelerometer sample nearest its stamp within 20 ms
(a 50 Hz IMU); a still reading does not change in that time, a moving one is never still."""


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
    """Input units (tesla in the node); 0 keeps the fitted mean radius (magnitude preserved)."""
    min_coverage: float = float(_DEFAULT_FIT.min_coverage)
    max_residual_pct: float = float(_DEFAULT_FIT.max_residual_pct)
    full_scale: float = AK09916_FULL_SCALE_T
    """A component at or beyond it is saturated. 0 disables the check."""
    auto_calibrate: bool = True
    auto_calibrate_period: float = 2.0
    """Stream seconds between automatic fits that failed, so a failing fit does not run on
    every check."""
    refine: bool = True
    """Keep fitting after the first calibration; adopt a fit only when better on held-out data."""
    refine_period: float = 10.0
    """Stream seconds between refinement fits (doubling up to 8x once converged)."""
    online_tracking: bool = False
    tracking_improvement: float = 0.8
    """Adopt a tracked calibration only when its residual is below this share of the current."""
    tracking_max_change_rate: float = 0.01
    """Per second: offset change as a share of the field, matrix change as a relative norm."""
    align: bool = True
    """With paired accelerometer readings (``process_imu``), align fits to the IMU frame."""
    max_alignment_deg: float = MAX_ANGLE_DEG
    """A larger rotation is reported as a mounting error (with the remap) and not applied."""
    max_field_error_pct: float = MAX_FIELD_ERROR_PCT
    max_dip_error_deg: float = MAX_DIP_ERROR_DEG
    """Tolerances against the World Magnetic Model (``set_earth_field``)."""
    earth_field_gate: bool = True
    """Beyond them a fit fails (True) or is only warned about (False)."""

    @property
    def full_scale_limit(self) -> float | None:
        """``full_scale`` as the screen takes it: None when the check is off (0)."""
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
            problems.append(f'field_strength must be >= 0 (0 = fitted radius), '
                            f'got {self.field_strength}')
        if not 0.0 <= self.min_coverage <= 1.0:
            problems.append(f'min_coverage must be a fraction in [0, 1], got {self.min_coverage}')
        if not math.isfinite(self.max_residual_pct) or self.max_residual_pct <= 0.0:
            problems.append(f'max_residual_pct must be > 0, got {self.max_residual_pct}')
        if not math.isfinite(self.full_scale) or self.full_scale < 0.0:
            problems.append(f'full_scale must be >= 0 (0 = no check), got {self.full_scale}')
        for name in ('auto_calibrate_period', 'refine_period'):
            value = getattr(self, name)
            if not math.isfinite(value) or value <= 0.0:
                problems.append(f'{name} must be > 0 s, got {value}')
        if not 0.0 < self.tracking_improvement < 1.0:
            problems.append(f'tracking_improvement must be in (0, 1), got '
                            f'{self.tracking_improvement}')
        if not math.isfinite(self.tracking_max_change_rate) or self.tracking_max_change_rate <= 0:
            problems.append(f'tracking_max_change_rate must be > 0 per second, got '
                            f'{self.tracking_max_change_rate}')
        if not 0.0 <= self.max_alignment_deg <= 180.0:
            problems.append(f'max_alignment_deg must be in [0, 180], got {self.max_alignment_deg}')
        if not (math.isfinite(self.max_field_error_pct) and self.max_field_error_pct > 0.0):
            problems.append(f'max_field_error_pct must be > 0, got {self.max_field_error_pct}')
        if not 0.0 < self.max_dip_error_deg <= 90.0:
            problems.append(f'max_dip_error_deg must be in (0, 90], got {self.max_dip_error_deg}')
        return problems

    def fit_options(self) -> FitOptions:
        return replace(
            _DEFAULT_FIT,
            model=self.model,
            field_strength=self.field_strength if self.field_strength > 0.0 else None,
            min_coverage=self.min_coverage,
            max_residual_pct=self.max_residual_pct,
        )


    def alignment_options(self, earth: EarthField | None = None) -> AlignmentOptions:
        return AlignmentOptions(
            max_angle_deg=self.max_alignment_deg,
            expected_inclination_deg=None if earth is None else earth.inclination_deg)


class Processed(NamedTuple):
    """What ``process`` made of one message."""

    accepted: bool
    corrected: np.ndarray | None
    """The corrected field, None while uncalibrated (or when refused)."""
    calibration: Calibration | None
    """The calibration that corrected it (for the covariance)."""


_REFUSED = Processed(False, None, None)


@dataclass(frozen=True)
class CalibrationAttempt:
    """The outcome of one fit, phrased for a service answer or a log line."""

    success: bool
    message: str
    outcome: JobOutcome | None = None


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


def transform_covariance(matrix: np.ndarray, covariance: Sequence[float]) -> np.ndarray:
    """``A C A^T`` for a known covariance (``A`` = ``calibration.correction``, R M); all-zero
    (unknown) and -1 (not reported) pass as is, and a covariance with NaN/Inf (or one that
    overflows) becomes all-zero: unknown (REP-145)."""
    covariance = np.asarray(covariance, dtype=float).reshape(3, 3)
    if not np.all(np.isfinite(covariance)):
        return np.zeros(9)
    if not np.any(covariance) or covariance[0, 0] == -1.0:
        return covariance.reshape(9).copy()
    with np.errstate(all='ignore'):
        transformed = (matrix @ covariance @ matrix.T).reshape(9)
    return transformed if np.all(np.isfinite(transformed)) else np.zeros(9)


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
        current.rotation,
    )


def calibration_summary(calibration: Calibration, units: str = 'T') -> str:
    """One line: model, offset, residual % and coverage % (when the fit recorded them)."""
    offset = ', '.join(format_field(v, units, unit=False) for v in calibration.offset)
    text = f'model {calibration.model}, offset [{offset}] {display_units(units)}'
    residual, coverage, samples = (calibration.metadata_number(key)
                                   for key in ('residual_rms_pct', 'coverage', 'samples'))
    if residual is not None:
        text += f', residual {residual:.2f} %'
    if coverage is not None:
        text += f', coverage {100.0 * coverage:.0f} %'
    if samples is not None:
        text += f', {samples:.0f} samples'
    if calibration.metadata.get('levelled_by_gravity') is True:
        dip = calibration.metadata_number('levelled_dip_deg')
        text += ', levelled by gravity' + ('' if dip is None else f' (dip {dip:.1f} deg)')
    if calibration.aligned:
        text += f', rotated {rotation_angle_deg(calibration.rotation):.2f} deg into the IMU frame'
    return text


def display_units(units: str) -> str:
    return 'uT' if units == 'T' else units


def format_field(value: float, units: str, unit: bool = True) -> str:
    """A field value for people: microtesla for tesla input, else as given."""
    text = f'{value * TESLA_TO_MICROTESLA:.2f}' if units == 'T' else f'{value:.6g}'
    return f'{text} {display_units(units)}' if unit else text


def coverage_kept(current: Calibration, candidate: Calibration) -> bool:
    """A candidate may not cover less than the calibration in force: no fewer directions, and
    never a planar fit in place of a 3-D one (a 3-D fit in place of a planar one is an upgrade).
    """
    if candidate.model == 'planar' and current.model != 'planar':
        return current.model == 'identity'
    if current.model == 'planar' and candidate.model != 'planar':
        return True
    before, after = (c.metadata_number('coverage') for c in (current, candidate))
    if before is None:
        return True
    return after is not None and after >= before - 1e-9


class CalibrationSession:
    """The calibrator's state between messages: buffer, evidence, calibration in force, fits."""

    def __init__(
        self,
        settings: SessionSettings | None = None,
        calibration: Calibration | None = None,
        runner: FitRunner | None = None,
        metadata: Mapping[str, object] | None = None,
    ) -> None:
        self.settings = settings or SessionSettings()
        problems = self.settings.problems()
        if problems:
            raise ValueError('; '.join(problems))
        self.runner = runner or InlineRunner()
        self.metadata = {'units': 'T', **(metadata or {})}
        """Stamped on every fitted calibration (units, source ...)."""
        self.units = str(self.metadata['units'])
        self.buffer = SampleBuffer(self.settings.buffer_size, self.settings.k)
        self.screen = ReadingScreen(self.settings.full_scale_limit)
        self.evidence = HeldOutEvidence()
        self.scheduler = FitScheduler(self.settings.buffer_size)
        self.misfit = MisfitMonitor()
        self.clock = StreamClock()
        self.refusals = dict.fromkeys(REFUSAL_REASONS[len(SCREEN_REASONS):], 0)
        self.accepted = 0
        self._accepted_at_poll = 0  # accepted messages at the previous poll(): is the stream idle?
        self.input_rate = _RateMeter()
        self.calibration: Calibration | None = None
        self.last_attempt: CalibrationAttempt | None = None
        self.adoptions: dict[str, int] = {}
        """How often a calibration went in force, by source (auto, refine, request, file ...)."""
        self.jobs_run: dict[str, int] = {}
        self.hold_overflows = 0
        self.tracker: OnlineTracker | None = None
        self.tracked_updates = 0
        self._last_taught: np.ndarray | None = None  # corrected direction last fed to the tracker
        self._last_tracking_check: float | None = None
        self._reference_source: str | None = None  # 'fit' or 'calibration': the buffer's
        self._provisional: Calibration | None = None  # the latest sane reference fit
        self._reference_window = (0, 0)
        self._centre: np.ndarray | None = None  # the field's centre in raw units, for evidence
        self._held: deque[tuple[np.ndarray, int]] = deque()
        self._job: FitJob | None = None
        self._job_epoch = 0
        self._measured_coverage: tuple[float, Coverage] | None = None  # (stream s, coverage)
        self._epoch = 0  # bumped by reset(): outcomes of older jobs are stale
        self._requests: deque[tuple[int, int]] = deque()  # (ticket, readings accepted before)
        self._ingested = 0  # accepted readings fed to the buffer or the evidence so far
        self._next_ticket = 1
        self._hold_out = random.Random(0)
        self._next_periodic = 0.0
        self._events: deque[SessionEvent] = deque(maxlen=MAX_EVENTS)
        self._reported_rejects = dict(self.screen.counts)
        self._latest: np.ndarray | None = None  # the latest accepted reading (heading hints)
        self._plane: PlaneWatch | None = None  # a planar calibration's plane, while screened by it
        self._calibration_plane: PlaneWatch | None = None  # the plane of a planar one in force
        self._looked_at: np.ndarray | None = None  # the latest reading at the previous look
        self._turning = 0  # the way the heading last moved between two looks (+1 / -1)
        self.attitudes = StaticAttitudes()
        """Quasi-static (field, accel) attitudes paired from the IMU, for the alignment."""
        self._imu: deque[tuple[int, float, float, float, tuple | None]] = deque(maxlen=IMU_RING)
        self.imu_rate = _RateMeter()
        self.imu_accepted = 0
        self.imu_refused = 0
        self.paired = 0
        """Accepted magnetometer readings paired with an accelerometer sample."""
        self.imu_frame_id = ''
        self.earth: EarthField | None = None
        """The World Magnetic Model's field here (``set_earth_field``), None while unknown."""
        self.alignment: Alignment | None = None
        """The latest fit's alignment to the IMU (applied or not)."""
        self.earth_check: EarthCheck | None = None
        """The latest fit against the model."""
        self._alignment_warning = ''
        self._earth_warning = ''
        if calibration is not None:
            self.apply_calibration(calibration, 'given')

    # -- configuration -------------------------------------------------------------------------

    def reconfigure(self, settings: SessionSettings) -> None:
        """Adopt new settings; a resized buffer keeps its most unique samples."""
        problems = settings.problems()
        if problems:
            raise ValueError('; '.join(problems))
        old, self.settings = self.settings, settings
        if (settings.buffer_size, settings.k) != (old.buffer_size, old.k):
            self.buffer.resize(settings.buffer_size, settings.k)
            self.scheduler.capacity = settings.buffer_size
        self._measured_coverage = None  # measured with the old settings (model, buffer)
        self.screen.full_scale = settings.full_scale_limit
        if settings.online_tracking != old.online_tracking:
            self._restart_tracker()

    def close(self) -> None:
        """Stop the fit worker (the node calls this on shutdown)."""
        self.runner.close()

    # -- per message ---------------------------------------------------------------------------

    def process(self, stamp_ns: int, frame_id: str, field: Sequence[float]) -> Processed:
        """Screen one message, learn from it, and correct it with the calibration in force."""
        self.input_rate.count += 1
        try:
            x0, x1, x2 = (float(value) for value in field)
        except (TypeError, ValueError):
            x0 = x1 = x2 = math.nan
        reason = self.screen.screen(stamp_ns, frame_id, x0, x1, x2)
        if self.screen.changes:
            for change in self.screen.take_changes():
                self._event('warning' if change.kind == 'frame' else 'info', change.message)
        if reason is not None:
            return _REFUSED
        self.accepted += 1
        reading = np.array((x0, x1, x2))
        self._latest = reading
        pair = self._pair(stamp_ns) if self._imu else None
        self._advance()
        if self._job is None and not self._held:
            self._ingest(reading, stamp_ns, pair)
        else:
            self._hold(reading, stamp_ns, pair)
        calibration = self.calibration
        if calibration is None:
            return Processed(True, None, None)
        return Processed(True, calibration.apply(reading), calibration)

    def process_imu(self, stamp_ns: int, frame_id: str, accel: Sequence[float],
                    gyro: Sequence[float] | None = None) -> bool:
        """Keep one accelerometer (and gyroscope, rad/s) sample to pair magnetometer readings
        with; O(1). False when refused (non-finite or zero specific force). A gyroscope sample
        with a non-finite value counts as none."""
        self.imu_rate.count += 1
        try:
            ax, ay, az = (float(value) for value in accel)
        except (TypeError, ValueError):
            ax = ay = az = math.nan
        if not (math.isfinite(ax + ay + az) and (ax or ay or az)):
            self.imu_refused += 1
            return False
        rates = None
        if gyro is not None:
            try:
                gx, gy, gz = (float(value) for value in gyro)
            except (TypeError, ValueError):
                gx = gy = gz = math.nan
            rates = (gx, gy, gz) if math.isfinite(gx + gy + gz) else None
        self._imu.append((int(stamp_ns), ax, ay, az, rates))
        self.imu_accepted += 1
        self.imu_frame_id = frame_id
        return True

    def _pair(self, stamp_ns: int) -> tuple[tuple[float, float, float], tuple | None] | None:
        """The accelerometer sample nearest ``stamp_ns`` within PAIR_TOLERANCE_NS, searched from
        the newest back (samples arrive in stamp order: a few steps)."""
        best, best_gap = None, PAIR_TOLERANCE_NS + 1
        for sample in reversed(self._imu):
            gap = sample[0] - stamp_ns
            if abs(gap) < best_gap:
                best, best_gap = sample, abs(gap)
            elif gap < 0:
                break  # older still: only further away
        if best is None:
            return None
        self.paired += 1
        return (best[1], best[2], best[3]), best[4]

    def set_earth_field(self, field: EarthField | None) -> None:
        """The World Magnetic Model's field here (None: unknown); used by the next fits."""
        self.earth = field

    def poll(self) -> None:
        """Take a finished fit's outcome and feed held readings; the node calls this on a timer
        (messages call it too), so answers arrive even when no message does. While messages
        flow, each feeds DRAIN_PER_MESSAGE and so does a poll (a long drain here would delay the
        messages queued behind it), DRAIN_FOR_REQUEST while a request waits; once none came
        since the last poll, all that is held."""
        flowing = self.accepted != self._accepted_at_poll
        self._accepted_at_poll = self.accepted
        if not flowing:
            budget = HOLD_LIMIT
        else:
            budget = DRAIN_FOR_REQUEST if self._requests else DRAIN_PER_MESSAGE
        self._advance(budget=budget)

    def _advance(self, budget: int = DRAIN_PER_MESSAGE) -> None:
        if self._job is not None:
            outcome = self.runner.poll()
            if outcome is None:
                return
            self._job = None
            self._complete(outcome)
        while self._held and self._job is None and budget > 0:
            self._ingest(*self._held.popleft())
            budget -= 1
        if self._job is None and not self._held and self._requests:
            self._submit('request')

    def _hold(self, reading: np.ndarray, stamp_ns: int, pair: tuple | None = None) -> None:
        if len(self._held) >= HOLD_LIMIT:
            self.hold_overflows += 1
            self._ingest(*self._held.popleft())
        self._held.append((reading, stamp_ns, pair))

    def _ingest(self, reading: np.ndarray, stamp_ns: int, pair: tuple | None = None) -> None:
        """Everything a reading teaches, in stream order (the held ones after the fit)."""
        now = self.clock.advance(stamp_ns)
        self._ingested += 1
        if pair is not None and self.settings.align:
            self.attitudes.add(now, reading, pair[0], pair[1])
        # Evidence judges a calibration: none yet, none needed. The draw is pseudo-random (and
        # deterministic), so a recording replayed again holds out other readings.
        if self.calibration is not None and self._hold_out.random() * HOLD_OUT_EVERY < 1.0:
            self.evidence.add(reading, self._direction(reading), now)
        else:
            if self._plane is not None and self._plane.add(reading):
                self._leave_plane()
            outcome = self.buffer.add(reading, None if pair is None else _up(pair[0]))
            if outcome in self.refusals:
                self.refusals[outcome] += 1
            else:
                self.scheduler.sample_added(self.buffer.fill == self.buffer.capacity)
            if self._reference_source is not None:
                self._check_reference()
            if self.tracker is not None and self._teaches_tracker(reading):
                self.tracker.update(reading)
        if now >= self._next_periodic:
            self._next_periodic = now + PERIODIC_S
            self._update_centre()
        if self._job is None:
            kind = self.scheduler.due(self._situation(now))
            if kind is not None:
                self._submit(kind)

    def _direction(self, reading: np.ndarray) -> np.ndarray:
        """Where a reading points from the field's centre, for filing it as evidence. The centre
        comes from the buffer (its own fit, else the mean of its spread-out samples), never from
        the calibration in force: a wrong calibration must not make all evidence look alike."""
        if self._centre is None:
            return reading
        direction = reading - self._centre
        return direction if np.any(direction) else reading

    def _update_centre(self) -> None:
        radius = 0.0
        if self.calibration is not None:
            radius = self.calibration.field_radius()
        elif self.buffer.fill >= 10:
            radius = self.buffer.field_radius()
        self.attitudes.field_scale = radius if radius > 0.0 else None
        if self._reference_source == 'fit':
            self._centre = self.buffer.reference.offset
        elif self.buffer.fill >= 10:
            self._centre = self.buffer.anchors.mean(axis=0)
        else:
            self._centre = None

    def _situation(self, now: float) -> Situation:
        settings = self.settings
        return Situation(
            now=now,
            buffer_full=self.buffer.fill == self.buffer.capacity,
            buffer_fill=self.buffer.fill,
            calibrated=self.calibration is not None,
            misfit=self.misfit.misfit,
            auto_calibrate=settings.auto_calibrate,
            auto_calibrate_period=settings.auto_calibrate_period,
            refine=settings.refine,
            refine_period=settings.refine_period,
            min_samples=min(_DEFAULT_FIT.min_samples, settings.buffer_size),
            request_waiting=bool(self._requests) and self._requests[0][1] <= self._ingested,
        )

    # -- fits ----------------------------------------------------------------------------------

    def _submit(self, kind: str) -> None:
        ticket = self._requests.popleft()[0] if kind == 'request' else None
        job = self._make_job(kind, ticket)
        self.jobs_run[job.kind] = self.jobs_run.get(job.kind, 0) + 1
        self._job, self._job_epoch = job, self._epoch
        self.runner.submit(job)
        outcome = self.runner.poll()  # an inline runner has it already
        if outcome is not None:
            self._job = None
            self._complete(outcome)

    def _make_job(self, kind: str, ticket: int | None) -> FitJob:
        buffer = self.buffer
        samples, weights, readings = buffer.samples, buffer.counts, buffer.readings
        if kind == 'reference':
            return FitJob('reference', samples, weights, readings, REFERENCE_OPTIONS,
                          previous=self._provisional)
        if kind == 'check':
            recent = self.evidence.readings(since_s=self.clock.now - MISFIT_WINDOW_S)
            if self._calibration_plane is not None:  # a planar one knows nothing off its plane
                recent = recent[self._calibration_plane.near(recent)]
            tracked = None if self.tracker is None else self.tracker.calibration
            return FitJob('check', samples, weights, readings, self.settings.fit_options(),
                          current=self.calibration, evidence=self.evidence.readings(),
                          recent=recent, tracked=tracked, reference=buffer.reference)
        metadata = {**self.metadata, 'frame_id': self.screen.frame_id or ''}
        evidence = self.evidence.readings() if self.calibration is not None else None
        attitudes = self.attitudes.snapshot() if self.settings.align else None
        return FitJob(
            'refine' if kind == 'refine' else 'calibrate', samples, weights, readings,
            self._fit_options(), metadata=metadata, current=self.calibration,
            evidence=evidence, ticket=ticket,
            ready_coverage=self.settings.min_coverage if kind == 'calibrate' else None,
            reference=buffer.reference,
            attitudes=attitudes if attitudes is not None and (len(attitudes) or self.paired)
            else None,
            alignment=self.settings.alignment_options(self.earth),
            earth=self._earth_reference(),
            ups=buffer.ups if buffer.paired else None,
            paired=buffer.paired_readings if buffer.paired else None,
        )

    def _earth_reference(self) -> EarthReference | None:
        if self.earth is None:
            return None
        settings = self.settings
        return EarthReference(self.earth, self.units, settings.max_field_error_pct,
                              settings.max_dip_error_deg, settings.earth_field_gate)

    def _fit_options(self) -> FitOptions:
        """The settings' fit options; with the model's field known (and field_strength 0), the
        target field strength is the model's intensity."""
        options = self.settings.fit_options()
        if options.field_strength is None and self.earth is not None:
            intensity = self.earth.intensity_in(self.units)
            if intensity is not None:
                options = replace(options, field_strength=intensity)
        return options

    def _complete(self, outcome: JobOutcome) -> None:
        job = outcome.job
        if self._job_epoch != self._epoch:  # fitted to a buffer since reset
            if job.ticket is not None:
                self._answer(job.ticket, CalibrationAttempt(
                    False, 'calibration abandoned: the buffer was reset while it ran', outcome))
            return
        if outcome.coverage is not None:
            self._measured_coverage = (self.clock.now, outcome.coverage)
        if job.kind == 'reference':
            self._reference_done(outcome)
        elif job.kind == 'check':
            self._check_done(outcome)
        elif job.ticket is not None:
            self._request_done(outcome)
        elif job.kind == 'calibrate':
            self._auto_done(outcome)
        else:
            self._refine_done(outcome)

    def _reference_done(self, outcome: JobOutcome) -> None:
        fit = outcome.reference
        self.scheduler.reference_done(fit is not None and fit.settled)
        if fit is None:
            return
        self._provisional = fit.calibration
        self._set_reference(fit.calibration, fit.tolerance, 'fit')

    def _request_done(self, outcome: JobOutcome) -> None:
        result = outcome.result
        kept = ('; the previous calibration stays in force' if self.calibration is not None
                else '; still uncalibrated')
        if outcome.error or result is None:
            attempt = CalibrationAttempt(False, f'calibration failed: {outcome.error}{kept}',
                                         outcome)
        elif result.success:
            message = calibration_summary(result.calibration, self.units)
            if outcome.comparison is not None and outcome.comparison.readings >= MIN_EVIDENCE:
                comparison = outcome.comparison
                message += (f'; on held-out readings {comparison.current_pct:.2f} % before, '
                            f'{comparison.candidate_pct:.2f} % now')
            message += self._reference_text(outcome)
            attempt = CalibrationAttempt(True, message, outcome)
            self._adopt(result.calibration, 'request')
        else:
            attempt = CalibrationAttempt(
                False, f'calibration failed: {result.reason}{kept}{self._reference_text(outcome)}',
                outcome)
        self._note_reference(outcome)
        self.last_attempt = attempt
        self._answer(outcome.job.ticket, attempt)

    def _answer(self, ticket: int, attempt: CalibrationAttempt) -> None:
        level = 'info' if attempt.success else 'warning'
        text = f'calibrated: {attempt.message}' if attempt.success else attempt.message
        self._event(level, text, adopted=attempt.success, ticket=ticket, attempt=attempt)

    def _auto_done(self, outcome: JobOutcome) -> None:
        settings = self.settings
        self.scheduler.calibrate_done(self.clock.now, outcome.fitted or bool(outcome.error),
                                      settings.auto_calibrate_period)
        if outcome.error:
            self._event('warning', f'automatic calibration failed: {outcome.error}')
            return
        result = outcome.result
        if result is None:
            return  # not ready: coverage below min_coverage
        self._note_reference(outcome)
        if not result.success:
            attempt = CalibrationAttempt(False, f'calibration failed: {result.reason}', outcome)
            self.last_attempt = attempt
            self._event('info', f'automatic calibration not yet: {result.reason}')
            return
        if self.calibration is not None and not self.misfit.misfit:
            return  # calibrated meanwhile (a request or a file): refinement takes over
        anew = self.calibration is not None
        attempt = CalibrationAttempt(True, calibration_summary(result.calibration, self.units)
                                     + self._reference_text(outcome), outcome)
        self.last_attempt = attempt
        self._adopt(result.calibration, 'auto')
        what = 'recalibrated automatically' if anew else 'calibrated automatically'
        self._event('info', f'{what}: {attempt.message}', adopted=True, attempt=attempt)

    def _refine_done(self, outcome: JobOutcome) -> None:
        result, comparison = outcome.result, outcome.comparison
        current = self.calibration
        judged = comparison is not None and math.isfinite(comparison.current_pct) and (
            comparison.readings >= MIN_EVIDENCE)
        adopted = False
        if outcome.error:
            self._event('warning', f'refinement failed: {outcome.error}')
        elif (result is not None and result.success and comparison is not None
              and comparison.better and current is outcome.job.current
              and coverage_kept(current, result.calibration)):
            candidate = result.calibration
            before = _coverage_pct(current)
            after = _coverage_pct(candidate)
            self._adopt(candidate, 'refine')
            adopted = True
            self._event('info', f'refined: residual {comparison.current_pct:.2f} % -> '
                                f'{comparison.candidate_pct:.2f} % on {comparison.readings} '
                                f'held-out readings, coverage {before} -> {after} '
                                f'({candidate.model})', adopted=True)
        elif comparison is not None:
            self._event('debug', f'refinement kept the calibration: {comparison.reason}')
        if not outcome.error:
            self._note_reference(outcome)
        if (not adopted and current is not None and current is outcome.job.current
                and _passed_own_gates(outcome)):
            self._realign(current, outcome.alignment)
        self.scheduler.refine_done(judged, adopted)

    # -- the IMU and the Earth's field ---------------------------------------------------------

    def _note_reference(self, outcome: JobOutcome) -> None:
        """Remember a fit's alignment and model check; warn once per new finding (a mounting
        error, a disturbed field), not at every refinement. Only a fit that passed its own gates
        (the model's aside) says anything about the sensor or the place."""
        if not _passed_own_gates(outcome):
            return
        if outcome.alignment is not None:
            self.alignment = outcome.alignment
            alignment = outcome.alignment
            finding = ('' if alignment.success or not math.isfinite(alignment.dip_deg)
                       else alignment.reason)
            if finding and finding.split(':')[0] != self._alignment_warning.split(':')[0]:
                self._event('warning', f'alignment to the IMU not applied: {finding}')
            self._alignment_warning = finding
        if outcome.earth_check is not None:
            self.earth_check = outcome.earth_check
            text = disturbance_text(outcome.earth_check)
            if text and not self._earth_warning:
                self._event('warning', f'against the World Magnetic Model: {text}')
            self._earth_warning = text

    def _realign(self, current: Calibration, alignment: Alignment | None) -> None:
        """A refinement not adopted may still align better: put its rotation in force when the
        calibration in force has none, or when it moved by more than its uncertainty."""
        if alignment is None or not alignment.success:
            return
        change = rotation_angle_deg(alignment.rotation @ current.rotation.T)
        if current.aligned and change <= max(3.0 * alignment.rotation_std_deg, 0.05):
            return
        self.calibration = current.with_rotation(alignment.rotation, **alignment.metadata())
        self._restart_tracker()
        self._event('info', f'{alignment.summary()} (changed by {change:.2f} deg)',
                    adopted=True)

    def _reference_text(self, outcome: JobOutcome) -> str:
        """'; aligned to the IMU: ...; field 1.01x the model's ...' for an answer or a log."""
        text = ''
        if outcome.alignment is not None:
            text += f'; {outcome.alignment.summary()}'
        check = outcome.earth_check
        if check is not None:
            parts = []
            if check.radius_ratio is not None:
                parts.append(f"field {check.radius_ratio:.3f}x the model's")
            if check.dip_error_deg is not None:
                parts.append(f'dip {check.dip_error_deg:+.2f} deg against it')
            parts.append(f'declination {check.declination_deg:.2f} deg')
            text += f'; {self.earth.model if self.earth else "model"}: {", ".join(parts)}'
        return text

    def alignment_warning(self) -> str:
        """A mounting error the latest alignment found, for a diagnostics WARN ('' if none)."""
        return self._alignment_warning

    def earth_warning(self) -> str:
        """The calibration in force against the model, for a diagnostics WARN ('' if fine)."""
        reference = self._earth_reference()
        calibration = self.calibration
        if reference is None or calibration is None:
            return ''
        check = reference.check(calibration.field_radius(), calibration.metadata_number('dip_deg'))
        return disturbance_text(check)

    def request_calibration(self) -> int:
        """Ask for a fit of the buffer (``~/calibrate``) once every reading received so far is
        in it (some may wait while another fit runs); the answer comes as an event with this
        ticket. A fit that passes the gates goes in force."""
        ticket = self._next_ticket
        self._next_ticket += 1
        self._requests.append((ticket, self.accepted))  # after every reading received so far
        self._advance()
        return ticket

    def calibrate_now(self, timeout_s: float = 60.0) -> CalibrationAttempt:
        """Request a fit and wait for it (offline use: ``mag_calibrator_fit``, tests)."""
        ticket = self.request_calibration()
        deadline = time.monotonic() + timeout_s
        while True:
            for event in self._events:
                if event.ticket == ticket and event.attempt is not None:
                    return event.attempt
            if time.monotonic() > deadline:
                return CalibrationAttempt(False, f'calibration did not finish in {timeout_s} s')
            time.sleep(0.001)
            self.poll()

    # -- the calibration in force --------------------------------------------------------------

    def apply_calibration(self, calibration: Calibration, source: str = 'file') -> None:
        """Put a calibration in force at once (a file, parameters)."""
        self._adopt(calibration, source)

    def _adopt(self, calibration: Calibration, source: str) -> None:
        self.calibration = calibration
        self._calibration_plane = None
        if calibration.model == 'planar':
            self._calibration_plane = PlaneWatch.of(calibration.metadata.get('plane_normal'),
                                                    self.buffer.samples)
        self.adoptions[source] = self.adoptions.get(source, 0) + 1
        self.misfit.reset()
        self.scheduler.calibration_changed()
        if self._reference_source != 'fit':
            self._set_reference(calibration, None, 'calibration')
        self._restart_tracker()

    def _set_reference(self, calibration: Calibration | None, tolerance: float | None,
                       source: str | None) -> None:
        self._plane = self._calibration_plane if source == 'calibration' else None
        if calibration is None:
            self.buffer.set_reference(None)
        elif tolerance is None:
            self.buffer.set_reference(calibration)
        else:
            self.buffer.set_reference(calibration, tolerance, merge=source == 'fit')
        self._reference_source = source if calibration is not None else None
        self._reference_window = (0, 0)

    def _leave_plane(self) -> None:
        """The sensor left the plane its planar calibration was turned in: stop screening the
        buffer by it (it knows nothing off the plane) and refine from the first interval, so a
        full calibration is collected and judged at once. The planar one stays in force."""
        self._set_reference(None, None, None)
        self.scheduler.calibration_changed()
        self._event('info', 'the sensor moved out of the plane it was calibrated turning in: '
                            'collecting in 3-D for a full calibration (keep turning it through '
                            'every orientation); the planar calibration stays in force until a '
                            'better one is found')

    def _check_reference(self) -> None:
        """Set the buffer's reference aside once it refuses most of a window of readings."""
        checked, outliers = self.buffer.reference_checks
        start_checked, start_outliers = self._reference_window
        window = checked - start_checked
        if window < max(100, self.buffer.capacity):
            return
        refused = outliers - start_outliers
        self._reference_window = (checked, outliers)
        if refused <= STALE_SHARE * window:
            return
        source = self._reference_source
        self._set_reference(None, None, None)
        if source == 'fit':
            self._provisional = None
            self.scheduler.reference_done(False)
        what = 'its own fit' if source == 'fit' else 'the calibration in force'
        self._event('info', f'the buffer stopped screening by {what}: it refused {refused} of '
                            f'the last {window} readings, so it no longer describes the sensor; '
                            'collecting without it')

    def _check_done(self, outcome: JobOutcome) -> None:
        """The calibration in force judged on recent evidence: misfit, and online tracking."""
        if outcome.error:
            self._event('warning', f'checking the calibration failed: {outcome.error}')
            return
        if outcome.job.current is not self.calibration:
            return  # judged a calibration no longer in force
        now = self.clock.now
        verdict = self.misfit.update(now, outcome.fit_check)
        if verdict == 'confirmed':
            self._event('warning', self.misfit_text())
            if self.settings.auto_calibrate:
                self._collect_anew(now)
        elif verdict == 'cleared':
            self._event('info', f'the calibration in force fits the live data again (median '
                                f'error {outcome.fit_check.median_error_pct:.1f} %)')
        if outcome.comparison is not None:
            self._track(now, outcome.job.tracked, outcome.comparison)

    def misfit_text(self) -> str:
        """Why the calibration in force does not fit, and what happens about it."""
        check = self.misfit.last
        if check is None or not check.judged:
            return ''
        measured = format_field(check.measured_field, self.units)
        expected = format_field(check.expected_field, self.units)
        action = ('collecting to calibrate anew (auto_calibrate)' if self.settings.auto_calibrate
                  else 'call ~/reset then ~/calibrate, or set auto_calibrate')
        return (f'calibration does not fit the live data: |B| {measured} vs {expected} '
                f'expected (median error {check.median_error_pct:.1f} % over the last '
                f'{MISFIT_WINDOW_S:.0f} s, {100 * check.span:.0f} % of the directions) - other '
                f'sensor, new payload, or a magnet nearby? {action}')

    def _collect_anew(self, now: float) -> None:
        """After a misfit: forget samples and evidence from before it, keep the calibration."""
        self.buffer.clear()
        self._measured_coverage = None
        self.evidence.forget_before(now - MISFIT_WINDOW_S)
        self.scheduler.reset()
        self._provisional = None
        self._set_reference(None, None, None)
        self.attitudes.clear()

    # -- online tracking -----------------------------------------------------------------------

    def _restart_tracker(self) -> None:
        self._last_taught = None
        self._last_tracking_check = None
        if self.settings.online_tracking and self.calibration is not None:
            self.tracker = OnlineTracker(self.calibration)
        else:
            self.tracker = None

    def _teaches_tracker(self, reading: np.ndarray) -> bool:
        """Whether this reading points somewhere new (see TRACKING_MIN_SEPARATION_DEG)."""
        direction = self.calibration.apply(reading)
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

    def _track(self, now: float, candidate: Calibration, comparison: Comparison) -> None:
        """Step towards the tracked calibration when it is better on held-out readings."""
        last, self._last_tracking_check = self._last_tracking_check, now
        if last is None or now <= last:
            return
        if not (comparison.better and comparison.candidate_pct
                < self.settings.tracking_improvement * comparison.current_pct):
            return
        try:
            stepped = bounded_step(
                self.calibration, candidate, self.settings.tracking_max_change_rate * (now - last)
            )
        except CalibrationError:
            return
        self.calibration = stepped
        self.tracked_updates += 1
        if self._reference_source == 'calibration':
            self._set_reference(stepped, None, 'calibration')

    # -- state, reset --------------------------------------------------------------------------

    @property
    def state(self) -> str:
        if self.calibration is None:
            return 'collecting' if self.buffer.fill > 0 else 'uncalibrated'
        if self.misfit.misfit:
            return 'calibrated-misfit'
        if not self.settings.refine:
            return 'calibrated'
        return 'calibrated-converged' if self.scheduler.converged else 'calibrated-refining'

    @property
    def last_residual_pct(self) -> float | None:
        if self.calibration is None:
            return None
        return self.calibration.metadata_number('residual_rms_pct')

    def reset(self) -> None:
        """Empty the buffer and evidence, forget the stream's frame and stamps (a new sensor may
        follow); the calibration in force stays. A fit running now is abandoned."""
        self.buffer.clear()
        self._measured_coverage = None
        self.evidence.clear()
        self.screen.reset()
        self.scheduler.reset()
        self.misfit.reset()
        self._held.clear()
        self._ingested = self.accepted  # what was held is dropped: requests need not wait for it
        self._epoch += 1
        self._provisional = None
        self._set_reference(self.calibration, None, 'calibration' if self.calibration else None)
        self._restart_tracker()
        self.attitudes.clear()
        self._imu.clear()

    def feed(self, samples: np.ndarray, rate_hz: float = 100.0, start_ns: int = 0,
             frame_id: str = '', accel: np.ndarray | None = None,
             gyro: np.ndarray | None = None) -> None:
        """Stream recorded rows through ``process`` with stamps at ``rate_hz`` (offline use);
        ``accel`` (and ``gyro``, rad/s) rows, when given, go through ``process_imu`` first with
        the same stamps."""
        step = 1e9 / rate_hz
        accel_rows = None if accel is None else np.asarray(accel, dtype=float).tolist()
        gyro_rows = None if gyro is None else np.asarray(gyro, dtype=float).tolist()
        for index, row in enumerate(np.asarray(samples, dtype=float).tolist()):
            stamp = start_ns + round(index * step)
            if accel_rows is not None:
                self.process_imu(stamp, frame_id, accel_rows[index],
                                 None if gyro_rows is None else gyro_rows[index])
            self.process(stamp, frame_id, row)

    # -- reporting -----------------------------------------------------------------------------

    def take_events(self) -> list[SessionEvent]:
        """What the session decided since the last call, oldest first."""
        events = list(self._events)
        self._events.clear()
        return events

    def _event(self, level: str, message: str, **kwargs) -> None:
        self._events.append(SessionEvent(level, message, **kwargs))

    @property
    def has_events(self) -> bool:
        return bool(self._events)

    def rejects(self) -> dict[str, int]:
        """Every refusal by reason: screening, then duplicates and magnitude outliers."""
        return {**self.screen.counts, **self.refusals}

    def coverage(self) -> Coverage:
        """The buffer's coverage now: of the heading circle when the motion is yaw-only (see
        ``yaw_only``), else of the direction sphere (milliseconds: call at the reporting rate)."""
        if self.yaw_only():
            return self.heading_coverage().coverage
        return self.buffer.coverage()

    @property
    def held(self) -> int:
        """Readings received while a fit ran, not yet fed to the buffer (in order, later)."""
        return len(self._held)

    def reported_coverage(self) -> Coverage:
        """``coverage()`` for reports (diagnostics, the progress log), without its milliseconds
        on the caller's thread: what the fit worker measured with its latest check or readiness
        test (jobs.buffer_coverage), while no older than REPORTED_COVERAGE_AGE_S of stream (a
        stream that stopped changes no buffer); measured here otherwise. Heading coverage is
        looked at here, so its hint knows which way the robot turns."""
        measured = self._measured_coverage
        if measured is None or self.clock.now - measured[0] > REPORTED_COVERAGE_AGE_S:
            return self.coverage()
        if measured[1].cells == HEADING_SECTORS:
            return self.heading_coverage().coverage
        return measured[1]

    def yaw_only(self) -> bool:
        """Whether coverage, hints and the automatic gate are about the heading circle: model
        ``planar``, or ``auto`` with the buffer's samples near one plane (a robot turning)."""
        if self.settings.model == 'planar':
            return True
        return self.settings.model == 'auto' and yaw_only(self.buffer.samples)

    def heading_coverage(self) -> HeadingCoverage:
        """The buffer's heading coverage and the turn still needed, which way (milliseconds).

        Each call is a look: the direction of turning is how the heading moved since the
        previous look's latest reading."""
        buffer = self.buffer
        progress = heading_coverage_of(buffer.samples, buffer.readings, self._latest,
                                       self._looked_at, self._turning)
        self._looked_at, self._turning = self._latest, progress.turning
        return progress

    def progress_text(self, coverage: Coverage | None = None) -> str:
        """What to do next, e.g. 'coverage 63 % - keep rotating about the pitch axis (y)'."""
        coverage = coverage or self.coverage()
        fill = f'buffer {self.buffer.fill}/{self.buffer.capacity}'
        heading = coverage.cells == HEADING_SECTORS
        text = f'{"heading " if heading else ""}coverage {100.0 * coverage.fraction:.0f} %'
        if self.calibration is not None:
            return f'{self.state} ({self.calibration.model}); {text}, {fill}'
        needed = self.settings.min_coverage
        if heading and self.settings.auto_calibrate:
            needed = max(needed, COMPLETE_HEADING_COVERAGE)  # see jobs.readiness
        if coverage.fraction < needed:
            hint = coverage.hint or ('keep turning in place' if heading
                                     else 'keep rotating the sensor through every orientation')
            return f'{text} \u2014 {hint}; {fill}'
        if self.settings.auto_calibrate:
            return f'{text}, {fill} \u2014 enough to calibrate; calibrating automatically'
        return f'{text}, {fill} \u2014 enough to calibrate: call ~/calibrate'

    def new_screen_rejects(self) -> dict[str, int]:
        """Messages refused by screening since the previous call, by reason (those that
        occurred)."""
        counts = self.screen.counts
        new = {reason: count - self._reported_rejects[reason]
               for reason, count in counts.items() if count > self._reported_rejects[reason]}
        self._reported_rejects = dict(counts)
        return new

    def diagnostic_values(self, now: float, coverage: Coverage | None = None
                          ) -> dict[str, object]:
        """Key/values for /diagnostics, plain numbers and strings; read once per diagnostics
        period (updates the input rate)."""
        coverage = coverage or self.coverage()
        calibration = self.calibration
        values: dict[str, object] = {
            'state': self.state,
            'coverage_pct': round(100.0 * float(coverage.fraction), 1),
            'coverage_kind': 'heading' if coverage.cells == HEADING_SECTORS else 'direction',
            'coverage_hint': coverage.hint,
            'buffer_fill': int(self.buffer.fill),
            'buffer_capacity': int(self.buffer.capacity),
            'relative_knn_distance': round(float(self.buffer.relative_knn_distance), 5),
            'held_out_readings': len(self.evidence),
            'waiting_readings': len(self._held),
            'input_rate_hz': round(self.input_rate.read(now), 2),
            'messages_accepted': int(self.accepted),
            'frame_id': self.screen.frame_id or '',
            'last_residual_pct': ('' if self.last_residual_pct is None
                                  else round(self.last_residual_pct, 3)),
            'last_calibrate': '' if self.last_attempt is None else self.last_attempt.message,
            'fits': ', '.join(f'{kind} {count}' for kind, count in sorted(self.jobs_run.items())),
            'adopted': ', '.join(f'{source} {count}'
                                 for source, count in sorted(self.adoptions.items())),
        }
        values.update({f'rejected_{k}': int(v) for k, v in self.rejects().items()})
        check = self.misfit.last
        if check is not None and check.judged:
            values['live_median_error_pct'] = round(check.median_error_pct, 2)
        if calibration is not None:
            scale = TESLA_TO_MICROTESLA if self.units == 'T' else 1.0
            unit = display_units(self.units)
            values['model'] = calibration.model
            values[f'offset_{unit}'] = [round(float(v) * scale, 3) for v in calibration.offset]
            values[f'field_strength_{unit}'] = round(float(calibration.field_strength) * scale, 3)
        if self.tracker is not None:
            values['tracked_updates'] = self.tracked_updates
        if self.hold_overflows:
            values['hold_overflows'] = self.hold_overflows
        values.update(self._reference_values(now))
        return values

    def _reference_values(self, now: float) -> dict[str, object]:
        """The IMU alignment and the model's field, for /diagnostics."""
        values: dict[str, object] = {}
        if self.imu_rate.count or self.imu_accepted:
            values['imu_rate_hz'] = round(self.imu_rate.read(now), 2)
            values['imu_messages_accepted'] = int(self.imu_accepted)
            values['imu_messages_refused'] = int(self.imu_refused)
            values['readings_paired'] = int(self.paired)
            values['static_attitudes'] = int(self.attitudes.fill)
        calibration = self.calibration
        if calibration is not None and calibration.aligned:
            for key in ('alignment_angle_deg', 'dip_deg', 'dip_std_deg', 'static_samples'):
                number = calibration.metadata_number(key)
                if number is not None:
                    values[key] = round(number, 3)
        if self.alignment is not None:
            values['last_alignment'] = ('applied' if self.alignment.success
                                        else self.alignment.reason)
        if self.earth is not None:
            values['earth_model'] = self.earth.model
            values['model_intensity_uT'] = round(self.earth.intensity_nt / 1000.0, 3)
            values['model_inclination_deg'] = round(self.earth.inclination_deg, 3)
            values['declination_deg'] = round(self.earth.declination_deg, 3)
            reference = self._earth_reference()
            if calibration is not None and reference is not None:
                check = reference.check(calibration.field_radius(),
                                        calibration.metadata_number('dip_deg'))
                if check.radius_ratio is not None:
                    values['field_ratio_to_model'] = round(check.radius_ratio, 4)
                if check.dip_error_deg is not None:
                    values['dip_error_deg'] = round(check.dip_error_deg, 3)
        return values


def _passed_own_gates(outcome: JobOutcome) -> bool:
    """The fit passed its gates, or failed only the World Magnetic Model's."""
    result, check = outcome.result, outcome.earth_check
    if result is None or outcome.error:
        return False
    return result.success or (check is not None and result.reason == disturbance_text(check))


def _coverage_pct(calibration: Calibration) -> str:
    coverage = calibration.metadata_number('coverage')
    return '?' if coverage is None else f'{100.0 * coverage:.0f} %'


__all__ = [
    'AK09916_FULL_SCALE_T',
    'REFUSAL_REASONS',
    'SCREEN_REASONS',
    'STATES',
    'CalibrationAttempt',
    'CalibrationSession',
    'Processed',
    'SessionEvent',
    'SessionSettings',
    'bounded_step',
    'calibration_summary',
    'coverage_kept',
    'magnitude_residual_pct',
    'transform_covariance',
]


def _up(accel: Sequence[float]) -> tuple[float, float, float]:
    """Gravity's unit direction from a paired specific force (never zero: process_imu refuses
    that)."""
    ax, ay, az = accel
    norm = math.sqrt(ax * ax + ay * ay + az * az)
    return ax / norm, ay / norm, az / norm
