# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Fit jobs: a snapshot of the buffer in, a judged fit out, run inline or in a worker process.

The session decides *when* to fit and what to do with the outcome; this module only runs the one
recipe for each kind of job on a snapshot, so it can run anywhere (``worker``'s runners).
``InlineRunner`` runs a job at once (``mag_calibrator_fit``, tests, benchmarks);
``ProcessRunner`` runs it in a worker process, so the fit never holds the interpreter lock the
message callback needs: a fit in a thread delays messages by up to the interpreter's switch
interval each time it runs. The two give identical results on the same job.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
import math
import time
from typing import Any

import numpy as np

from mag_calibrator_ros.calibration.fit.alignment import (
    Alignment,
    AlignmentOptions,
    estimate_alignment,
)
from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.calibration.fit.compensation import (
    LEARNED,
    CompensationData,
    CompensationFit,
    fit_compensation,
)
from mag_calibrator_ros.calibration.fit.coverage import (
    HEADING_SECTORS,
    Coverage,
    direction_coverage,
    shell_directions,
)
from mag_calibrator_ros.calibration.fit.earth_field import (
    EarthCheck,
    EarthReference,
    disturbance_text,
)
from mag_calibrator_ros.calibration.fit.ellipsoid import robust_sigma
from mag_calibrator_ros.calibration.fit.fitting import FitOptions, FitResult, fit_calibration
from mag_calibrator_ros.calibration.fit.gyro_aided import (
    MIN_WINDOWS,
    GyroAidedFit,
    TurnedReadings,
    fit_gyro_aided,
    fit_gyro_aided_full,
    turned_direction_errors,
)
from mag_calibrator_ros.calibration.fit.heading import (
    COMPLETE_HEADING_COVERAGE,
    heading_coverage_of,
    yaw_only,
)
from mag_calibrator_ros.calibration.live.buffer import DEFAULT_MAGNITUDE_TOLERANCE
from mag_calibrator_ros.calibration.live.evidence import (
    MIN_GAIN,
    Comparison,
    FitCheck,
    check_fit,
    compare_on_evidence,
    compare_residuals,
    relative_errors,
)

JOB_KINDS = ('reference', 'calibrate', 'refine', 'check', 'compensate', 'gyro', 'step')
"""reference: the buffer's own full fit, to screen and merge by; calibrate: a fit to put in force
(automatic or on request); refine: a fit to put in force only if better on held-out evidence;
check: no fit, the calibration in force judged on recent evidence (does it still fit? is the
online-tracked calibration better?) and the buffer's coverage measured for reports; compensate:
the robot's own field learned from the readings kept with their inputs (fit/compensation.py),
the calibration in force its base; gyro: the offset from the gyroscope's turning
(fit/gyro_aided.py), judged against the raw field on held-out windows of turned readings;
step: the latest turned readings refitted for the offset alone (the rest of the calibration in
force kept), judged against the calibration in force on held-out windows: a hard-iron step."""

HELD_OUT_WINDOWS = 3
"""gyro: every third window of turned readings is held out of the fit to judge it by (windows
interleaved in time, so a disturbance for a while touches both sides alike)."""

WINDOWS_NEEDED = math.ceil(MIN_WINDOWS * HELD_OUT_WINDOWS / (HELD_OUT_WINDOWS - 1))
"""Windows a gyro-aided fit takes at least: it sees MIN_WINDOWS, the held-out third judges it."""

REFERENCE_OPTIONS = FitOptions(model='full')
"""How the buffer is fitted for its reference: the default gates, model ``full``, the one that
describes any magnetometer in a uniform field. A sphere or planar fit chosen because ``full`` was
not yet determined misjudges unseen directions, refusing good readings and bending merged means."""


@dataclass(frozen=True)
class FitJob:
    """Everything one fit needs, copied out of the session (picklable, immutable)."""

    kind: str
    samples: np.ndarray
    weights: np.ndarray | None
    readings: np.ndarray | None
    options: FitOptions
    metadata: dict[str, Any] = field(default_factory=dict)
    """Stamped on a fitted calibration (frame_id, units ...), with the time of the fit."""
    previous: Calibration | None = None
    """reference: the reference in use, to tell whether the new one settled."""
    current: Calibration | None = None
    """refine and calibrate: the calibration in force, compared on ``evidence``; a refinement
    also weighs in what it knew of the offset along a ground robot's turning axis."""
    evidence: np.ndarray | None = None
    """Held-out readings no fit has seen (see evidence.HeldOutEvidence)."""
    ticket: int | None = None
    """A request's number (``~/calibrate``), so its answer finds it."""
    ready_coverage: float | None = None
    """Automatic attempts: fit only if the buffer covers this share of directions (judged
    through ``reference``, as SampleBuffer.coverage does); else report the coverage."""
    reference: Calibration | None = None
    recent: np.ndarray | None = None
    """check: the held-out readings of the last MISFIT_WINDOW_S."""
    tracked: Calibration | None = None
    """check: the online tracker's calibration, compared with ``current`` on ``evidence``."""
    attitudes: np.ndarray | None = None
    """calibrate and refine: quasi-static (field, accel) attitudes (StaticAttitudes.snapshot);
    the fitted calibration is aligned to the IMU with them when ``alignment`` is set."""
    alignment: AlignmentOptions | None = None
    earth: EarthReference | None = None
    """calibrate and refine: the World Magnetic Model's field here; the fit is checked against
    it (and fails beyond the tolerances when ``earth.gate``)."""
    ups: np.ndarray | None = None
    """calibrate and refine: gravity's direction behind each sample (SampleBuffer.ups, NaN
    where unpaired): a planar fit is levelled by it (levelled.py)."""
    paired: tuple[np.ndarray, np.ndarray] | None = None
    """SampleBuffer.paired_readings: readings with gravity's direction, preferred for levelling."""
    compensation: CompensationData | None = None
    """compensate: the readings with their inputs (live/compensation.py)."""
    turned: TurnedReadings | None = None
    """gyro: recent readings with the attitude the gyroscope integrated (rotation_track.py)."""


@dataclass(frozen=True)
class ReferenceFit:
    """A sane buffer fit to screen and merge by: its calibration and relative tolerance."""

    calibration: Calibration
    tolerance: float
    settled: bool
    """Whether it moved less than one reading's noise from the previous reference."""


@dataclass(frozen=True)
class JobOutcome:
    """What a job produced: the fit, its reading as a reference, its comparison, or an error."""

    job: FitJob
    result: FitResult | None = None
    reference: ReferenceFit | None = None
    comparison: Comparison | None = None
    coverage: Coverage | None = None
    """The buffer's coverage, when a readiness check ran or a check measured it."""
    fit_check: FitCheck | None = None
    """check: the calibration in force judged on the recent evidence."""
    error: str = ''
    seconds: float = 0.0
    alignment: Alignment | None = None
    """The fit aligned to the IMU (its rotation is in the calibration when it succeeded)."""
    earth_check: EarthCheck | None = None
    """The fit against the World Magnetic Model."""
    compensation: CompensationFit | None = None
    """compensate: the robot's own field learned, with its evidence."""
    gyro_fit: GyroAidedFit | None = None
    """gyro: the offset from the turning, its uncertainty and the raw field's spread."""
    field_seen: float = math.nan
    """step: the strength of the field the look's readings turn, corrected by the calibration
    in force and the offset fitted (its field_strength's units)."""
    turning: Comparison | None = None
    """refine: the calibration in force against the candidate on the turned readings
    (``turned_worse``; ``better``: the candidate turns directions worse than the one in force)."""

    @property
    def fitted(self) -> bool:
        return self.result is not None


def run_job(job: FitJob) -> JobOutcome:
    """The one recipe for every fit the live calibrator and ``mag_calibrator_fit`` make."""
    started = time.perf_counter()
    try:
        outcome = _run(job)
    except Exception as error:  # noqa: BLE001 - a worker must answer, never take the node down
        outcome = JobOutcome(job, error=f'{type(error).__name__}: {error}')
    return replace(outcome, seconds=time.perf_counter() - started)


def _run(job: FitJob) -> JobOutcome:
    if job.kind == 'gyro':
        return gyro_aided_outcome(job)
    if job.kind == 'step':
        return step_outcome(job)
    if job.kind == 'compensate':
        data = job.compensation
        fit = fit_compensation(data, job.current)
        if fit.calibration is None or data.held_raw is None:
            return JobOutcome(job, compensation=fit)
        fit = replace(fit, calibration=fit.calibration.with_metadata(  # when it was learned
            compensation_time=time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime())))
        comparison = compare_on_evidence(job.current, fit.calibration, data.held_raw,
                                         data.held_inputs, data.held_temperatures)
        return JobOutcome(job, compensation=fit,
                          comparison=through_gyroscope(comparison, fit.held_pair_errors))
    if job.kind == 'check':
        fit_check = check_fit(job.current, job.recent, job.options.max_residual_pct)
        comparison = None
        if job.tracked is not None:
            comparison = compare_on_evidence(job.current, job.tracked, job.evidence)
        coverage = None
        if len(job.samples):  # what the session reports (milliseconds: not on its thread)
            coverage = buffer_coverage(job)
        return JobOutcome(job, comparison=comparison, coverage=coverage, fit_check=fit_check)
    if job.kind == 'reference':
        result = fit_calibration(job.samples, job.options, weights=job.weights)
        return JobOutcome(job, result, reference=reference_fit(result, job, job.previous))
    coverage = None
    if job.ready_coverage is not None:
        coverage, needed = readiness(job)
        if coverage.fraction < needed:
            return JobOutcome(job, coverage=coverage)
    result = fit_calibration(job.samples, job.options, weights=job.weights, readings=job.readings,
                             ups=job.ups, paired=job.paired,
                             known=job.current if job.kind == 'refine' else None)
    if result.calibration is not None:
        stamped = result.calibration.with_metadata(
            time=time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime()), **job.metadata
        )
        result = replace(result, calibration=kept_compensation(stamped, job.current))
    result, alignment, earth_check = align_and_check(job, result)
    comparison = turning = None
    if (result.success and job.current is not None and job.evidence is not None
            and len(job.evidence)):
        comparison = compare_on_evidence(job.current, result.calibration, job.evidence)
        if job.turned is not None:
            turning = turned_worse(job.current, result.calibration, job.turned)
    return JobOutcome(job, result, comparison=comparison, coverage=coverage,
                      alignment=alignment, earth_check=earth_check, turning=turning)


def gyro_aided_outcome(job: FitJob) -> JobOutcome:
    """The fit of ``_gyro_aided_fit`` on the windows taken, or, when those fail, on the latest
    half of them, and so on while at least WINDOWS_NEEDED remain: a magnet attached (a tool
    mounted, a start-up transient) within the span leaves windows of two offsets, which no one
    offset fits, and the sensor as it is now is the latest windows'. Each span meets the same
    gates; the longest that passes them is taken (the most turning, the surest). With a
    calibration in force (``verdicts.gyro_improvable``), the whole span is fitted once, and its
    comparison is against the one in force on the same held-out windows."""
    outcome = _gyro_aided_fit(job)
    if job.current is not None:
        return _against_current(outcome)
    data, windows = job.turned, int(job.turned.windows.max()) + 1 if len(job.turned.windows) else 0
    while not _fitted(outcome) and windows // 2 >= WINDOWS_NEEDED:
        windows //= 2
        latest = data.windows >= data.windows.max() - windows + 1
        part = _part(data, latest)
        part = TurnedReadings(part.readings, part.rotations, part.windows - part.windows.min(),
                              None if part.spans is None else part.spans - part.spans.min())
        outcome = _gyro_aided_fit(replace(job, turned=part))
    return replace(outcome, job=job)


def _against_current(outcome: JobOutcome) -> JobOutcome:
    fit, data = outcome.gyro_fit, outcome.job.turned
    if fit is None or fit.calibration is None:
        return outcome
    part = _part(data, _held_out(data))
    return replace(outcome, comparison=_turned_better(outcome.job.current, fit.calibration,
                                                      part))


def _fitted(outcome: JobOutcome) -> bool:
    """The span's fit passed its own gates (whether it beats the raw field is the verdict's:
    a sensor calibrated already is not searched for a span that says otherwise)."""
    return outcome.gyro_fit is not None and outcome.gyro_fit.success


def _gyro_aided_fit(job: FitJob) -> JobOutcome:
    """The offset alone, then the soft iron with it, fitted on two of every three windows of
    turned readings and judged on the third's directions (``_turned_better``: the rule every
    candidate meets): the raw field is the first candidate, the offset replaces it only when
    better, the soft iron replaces the offset only when it is not worse (a sensor calibrated
    already keeps its own calibration unless another is clearly better). The fit returned is
    the one chosen, its comparison the one against the raw field."""
    data = job.turned
    held = _held_out(data)
    train, part = _part(data, ~held), _part(data, held)
    most = 15.0 if job.alignment is None else job.alignment.max_angle_deg
    bounds = {'max_residual_pct': job.options.max_residual_pct, 'max_rotation_deg': most}
    sphere = fit_gyro_aided(train, **bounds)
    if sphere.calibration is None:
        return JobOutcome(job, gyro_fit=sphere)
    full = fit_gyro_aided_full(train, sphere, **bounds)
    stamp = time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime())
    fits = [replace(fit, calibration=fit.calibration.with_metadata(time=stamp, **job.metadata))
            for fit in (sphere, full)]
    raw = turned_direction_errors(None, part)
    errors = [turned_direction_errors(fit.calibration, part) for fit in fits]
    what = 'held-out turned readings'
    against_raw = [compare_residuals(raw, error, what) for error in errors]
    sphere, full = fits
    chosen, comparison = sphere, against_raw[0]
    full_worse = compare_residuals(errors[1], errors[0], what).better
    if full.success and against_raw[1].better and not (
            sphere.success and against_raw[0].better and full_worse):
        chosen, comparison = full, against_raw[1]
    elif not sphere.success and full.success:
        chosen, comparison = full, against_raw[1]
    return JobOutcome(job, comparison=comparison, gyro_fit=chosen)


def step_outcome(job: FitJob) -> JobOutcome:
    """The offset a magnet (a battery, a tool) mounted next to the sensor added, from the
    latest turned readings corrected by the calibration in force (so its soft iron and rotation
    stay), fitted and judged as ``gyro_aided_outcome`` does, against the calibration in force."""
    data, current = job.turned, job.current
    corrected = TurnedReadings(current.unrotated(data.readings),
                               data.rotations, data.windows, data.spans)
    held = _held_out(data)
    fit = fit_gyro_aided(_part(corrected, ~held), max_residual_pct=job.options.max_residual_pct)
    if fit.calibration is None:
        return JobOutcome(job, gyro_fit=fit)
    seen = fit.calibration.field_strength  # |M (x - b) - shift|: the field the look turns
    shift = np.linalg.solve(current.matrix, fit.calibration.offset)  # into raw units
    before = current.metadata_number('direction_std_deg') or 0.0  # a file's: none known
    candidate = current.with_compensation(  # its directions: the old terms' and the new offset's
        current.compensation, offset=current.offset + shift,
        step_time=time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime()),
        direction_std_deg=round(math.hypot(before, fit.direction_std_deg), 3))
    fit = replace(fit, calibration=candidate, offset_std=np.abs(
        np.linalg.solve(current.matrix, np.diag(fit.offset_std))).sum(axis=1))
    part = _part(data, held)
    return JobOutcome(job, comparison=_turned_better(current, candidate, part), gyro_fit=fit,
                      field_seen=seen)


def _turned_better(current: Calibration | None, candidate: Calibration,
                   part: TurnedReadings) -> Comparison:
    """The rule every candidate meets, on the directions of held-out turned readings
    (``turned_direction_errors``): judged relative to each one's F, a fit won by its F alone."""
    return compare_residuals(turned_direction_errors(current, part),
                             turned_direction_errors(candidate, part), 'held-out turned readings')


def turned_worse(current: Calibration, candidate: Calibration,
                 turned: TurnedReadings) -> Comparison:
    """Whether ``candidate`` turns directions worse than ``current`` (``better``: the one in
    force is): its RMS direction error over the turned spans (``turned_direction_errors``;
    uncapped: a soft iron that bends some directions is exactly the large errors a cap would
    hide) above the current one's by more than MIN_GAIN. A refinement must not be worse;
    proving it better is the magnitudes' job."""
    now = float(np.sqrt(np.mean(turned_direction_errors(current, turned) ** 2)))
    new = float(np.sqrt(np.mean(turned_direction_errors(candidate, turned) ** 2)))
    worse = new > (1.0 + MIN_GAIN) * now
    return Comparison(worse, 100.0 * now, 100.0 * new, len(turned.readings), math.nan,
                      f'{"better" if worse else "not better"} on {len(turned.readings)} '
                      f'readings turned by the gyroscope: directions off by RMS '
                      f'{math.degrees(new):.2f} deg (the fit) vs {math.degrees(now):.2f} deg '
                      '(in force)')


def _held_out(data: TurnedReadings) -> np.ndarray:
    """The readings of every HELD_OUT_WINDOWS-th window: what judges a gyro fit."""
    return data.windows % HELD_OUT_WINDOWS == HELD_OUT_WINDOWS - 1


def _part(data: TurnedReadings, rows: np.ndarray) -> TurnedReadings:
    return TurnedReadings(data.readings[rows], data.rotations[rows], data.windows[rows],
                          None if data.spans is None else data.spans[rows])


def through_gyroscope(comparison: Comparison, pair_errors: tuple | None) -> Comparison:
    """A compensation the held-out magnitudes cannot judge yet (the robot faced few ways) is
    judged on the held-out pairs of readings compared through the gyroscope, by the same rule,
    as long as the magnitudes do not say it is worse."""
    if comparison.better or pair_errors is None:
        return comparison
    turned = compare_residuals(*pair_errors, 'held-out pairs compared through the gyroscope')
    worse = (math.isfinite(comparison.candidate_pct) and comparison.candidate_pct
             > (1.0 + MIN_GAIN) * comparison.current_pct)
    if not turned.better or worse:
        return replace(comparison, reason=f'{comparison.reason}; {turned.reason}')
    return replace(turned, reason=f'{turned.reason} ({comparison.reason})')


def kept_compensation(calibration: Calibration, current: Calibration | None) -> Calibration:
    """A static fit keeps the compensation in force: its samples were compensated by it (the
    answer to ``~/calibrate`` and the file then show it)."""
    if current is None or current.compensation is None or calibration.compensation is not None:
        return calibration
    learned = {key: current.metadata[key] for key in LEARNED if key in current.metadata}
    return calibration.with_compensation(current.compensation, **learned)


def align_and_check(job: FitJob, result: FitResult
                    ) -> tuple[FitResult, Alignment | None, EarthCheck | None]:
    """The fit aligned to the IMU (its rotation put in the calibration when the alignment
    succeeds) and judged against the World Magnetic Model (a failed gate when ``job.earth.gate``
    and the field or the dip is off)."""
    calibration = result.calibration
    if calibration is None:
        return result, None, None
    alignment = None
    if job.alignment is not None and job.attitudes is not None:
        alignment = estimate_alignment(job.attitudes, calibration, job.alignment)
        if alignment.success:
            calibration = calibration.with_rotation(alignment.rotation, **alignment.metadata())
    earth_check = None
    if job.earth is not None:
        dip = None  # a dip of the other sign too: a wrong location must not pass (issue #46)
        if alignment is not None and alignment.dip_std_deg <= job.alignment.max_dip_std_deg:
            dip = alignment.dip_deg
        radius = calibration.field_radius()
        earth_check = job.earth.check(radius, dip)
        calibration = calibration.with_metadata(
            declination_deg=round(job.earth.field.declination_deg, 4))
        if earth_check.problems and job.earth.gate and result.success:
            result = replace(result, success=False, reason=disturbance_text(earth_check))
    return replace(result, calibration=calibration), alignment, earth_check


def readiness(job: FitJob) -> tuple[Coverage, float]:
    """An automatic attempt's coverage and the share it needs before a fit is worth running.

    Yaw-only data (model ``planar``, or ``auto`` on samples near one plane: a ground robot
    turning) are judged by heading coverage and need the whole circle (heading.
    COMPLETE_HEADING_COVERAGE): a turning robot can complete it, and an ellipse fitted to part
    of it extrapolates the rest. Everything else: direction coverage, ``ready_coverage``.
    """
    coverage = buffer_coverage(job)
    if coverage.cells == HEADING_SECTORS:
        return coverage, max(job.ready_coverage, COMPLETE_HEADING_COVERAGE)
    return coverage, job.ready_coverage


def buffer_coverage(job: FitJob) -> Coverage:
    """The snapshot's coverage as the session reports it: of the heading circle for yaw-only
    data, else of the direction sphere (judged through ``job.reference``)."""
    model = job.options.model
    if model == 'planar' or (model == 'auto' and yaw_only(job.samples)):
        return heading_coverage_of(job.samples, job.readings).coverage
    return direction_coverage(job.samples, job.reference, job.readings)


def reference_fit(
    result: FitResult, job: FitJob, previous: Calibration | None
) -> ReferenceFit | None:
    """The fit as a reference if it is sane, with the tolerance to screen by; else None.

    Sane means determined and plausible (the condition and axis-ratio gates), describing most
    of the buffer (a majority of inliers) and the field's sphere (the buffer's readings lie on its
    shell: those of a still sensor fill the inside of the noise rim the buffer keeps), even if the
    coverage, sample-count or residual gates fail: a reference only judges magnitudes. The
    tolerance is ``outlier_threshold`` sigmas, capped at DEFAULT_MAGNITUDE_TOLERANCE: the robust
    sigma of one reading (a point averaging n readings has sqrt(n) less noise) combined with the
    fit's own uncertainty, so an early fit from part of the sphere does not refuse the good
    readings of a region it extrapolates to.
    """
    metrics, calibration, options = result.metrics, result.calibration, job.options
    if calibration is None or not (
        metrics.condition_number <= options.max_condition
        and metrics.axis_ratio <= options.max_axis_ratio
        and 2 * metrics.n_inliers > metrics.n_samples
    ):
        return None
    if not len(shell_directions(job.samples, calibration, job.readings)[0]):
        return None
    sigma = robust_sigma(relative_errors(calibration, job.samples) * np.sqrt(job.weights))
    spread = math.hypot(sigma, prediction_sigma(result))
    tolerance = min(options.outlier_threshold * spread, DEFAULT_MAGNITUDE_TOLERANCE)
    if not tolerance > 0.0:
        return None
    settled = previous is not None and not moved(previous, calibration, sigma)
    return ReferenceFit(calibration, tolerance, settled)


def prediction_sigma(result: FitResult) -> float:
    """Rough 1-sigma of the relative magnitude a fit predicts (its parameter uncertainty).

    |δ|u|| <= |δb| / R + ||δM|| R / F for unit-radius u; std norms stand in for the worst
    direction. Infinite when the fit reported no standard deviations.
    """
    std, metrics = result.metrics.parameter_std, result.metrics
    if not std or result.calibration is None or not metrics.mean_radius > 0.0:
        return math.inf
    offset = std.get('offset', std.get('offset_in_plane'))
    if 'matrix' in std:
        matrix = float(np.linalg.norm(std['matrix'])) * metrics.mean_radius
        matrix /= result.calibration.field_strength
    else:
        matrix = float(np.linalg.norm(std.get('matrix_in_plane_relative', [math.inf])))
    if offset is None:
        return math.inf
    return float(np.linalg.norm(offset)) / metrics.mean_radius + matrix


def moved(old: Calibration, new: Calibration, tolerance: float) -> bool:
    """Whether ``new`` judges magnitudes visibly differently from ``old`` (relative units)."""
    radius = old.field_radius()
    offset_shift = float(np.linalg.norm(new.offset - old.offset)) / radius
    matrix_shift = float(np.linalg.norm(
        new.matrix / new.field_strength - old.matrix / old.field_strength, ord=2
    )) * radius
    return not offset_shift + matrix_shift <= tolerance


# --- runners ---------------------------------------------------------------------------------


__all__ = [
    'JOB_KINDS',
    'REFERENCE_OPTIONS',
    'FitJob',
    'JobOutcome',
    'ReferenceFit',
    'align_and_check',
    'buffer_coverage',
    'moved',
    'prediction_sigma',
    'readiness',
    'reference_fit',
    'run_job',
]
