# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""fit_calibration(): choose and fit a model, then judge it with quality gates a user can act on.

Every threshold is relative (percent of the field radius, ratios, fractions), so the same options
work for data in tesla, microtesla, gauss or raw counts. Bad data never raises: unusable rows are
dropped and counted, and anything that cannot be fitted comes back as ``success=False`` with the
reason.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
import math
import sys
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from mag_calibrator_ros.calibration.fit.calibration import MODELS, Calibration, CalibrationError
from mag_calibrator_ros.calibration.fit.coverage import (
    HEADING_SECTORS,
    Coverage,
    direction_coverage,
    finite_rows,
    heading_coverage,
    missing_rotation_hint,
    occupied_cells,
    whitened_directions,
)
from mag_calibrator_ros.calibration.fit.ellipsoid import (
    DIVERGED_CONDITION,
    PARAMETER_COUNTS,
    EllipsoidFit,
    Normalisation,
    fit_ellipsoids,
    information_criterion,
    normalise,
    thickness,
)
from mag_calibrator_ros.calibration.fit.heading import fit_ring
from mag_calibrator_ros.calibration.fit.levelled import level_planar

_HUGE = sys.float_info.max
"""Stands in for an infinite condition number or axis ratio: results never carry inf or NaN."""

LARGEST_READING = sys.float_info.max / 4
"""Readings beyond this magnitude (4.5e307) are refused: differences between them, which every fit
takes, overflow float64. No magnetometer reads anything near it in any unit (a tesla reading in
femtotesla is 1e11); such numbers come from wrong columns or a corrupt log."""

GATE_MARGIN = 0.2
"""A fit that took the fast path (see ellipsoid.py) stands only when it passes every gate by more
than this share of the way from the ideal value (residual 0, condition and axis ratio 1, coverage
1) to the gate. Nearer, or failing, it is redone on the robust path, so no gate decision rests on
the shortcut."""


@dataclass(frozen=True)
class FitOptions:
    """What to fit and the quality gates. Defaults and why:

    - ``min_samples=30``: over three times the 9 parameters of ``full``, so the residual and the
      outlier test have redundancy (NXP's fits use 4/7/10 parameters by sample count).
    - ``min_coverage=0.5``: half of the 80 direction cells. A 100-sample buffer of a full tumble
      reaches 0.8-0.9 and 50 samples at most 0.62; below one half whole rotations are missing and
      the offset along them is extrapolated; the reason names the rotation.
    - ``max_residual_pct=5.0``: RMS of ``|corrected| - F`` in % of F. ArduPilot accepts ~3 %;
      cheap noisy sensors (BNO055) show ~2 % noise alone; a disturbed field gives far more.
      One bound, three uses, each named where it stands: the *gate* here (a fit's RMS residual
      over its samples); the live *misfit check* (``evidence.check_fit``: the median error of
      recent held-out readings against the calibration in force, beyond ``MISFIT_FLOOR`` times
      it); and ``mag_calibrator_fit --calibration``'s *verdict* on a saved calibration, which is
      that same misfit check run over a recording (``tools/fit_start.py``).
    - ``max_condition=15``: of the fit's normalised Jacobian. It grows as the covered share of
      the sphere shrinks: about 2 all round, 5 at three quarters, 10 at 60 %, 20 for a hemisphere
      (whose unseen half is then off by over 1°), 1e5 and more for motion about one axis.
    - ``max_axis_ratio=2.0``: real soft iron stretches axes by < 1.5 (PCB-mounted sensors ~1.1);
      beyond 2 the fit describes something other than a magnetometer in a uniform field.
    - ``outlier_threshold=4.0``: robust sigmas; Gaussian noise exceeds it once in 16,000 samples.
    - ``planar_thickness=0.15``: data spreading less than 15 % out of their best plane (tilts
      below about ±10°) are planar: only ``planar`` is determined by them.
    - ``prior``: the calibration whose out-of-plane terms ``planar`` keeps.
    """

    model: str = 'auto'
    field_strength: float | None = None
    min_samples: int = 30
    min_coverage: float = 0.5
    max_residual_pct: float = 5.0
    max_condition: float = 15.0
    max_axis_ratio: float = 2.0
    outlier_threshold: float = 4.0
    prior: Calibration | None = None
    planar_thickness: float = 0.15

    def __post_init__(self) -> None:
        problems = []
        if self.model not in MODELS:
            problems.append(f'model must be one of {MODELS}, got {self.model!r}')
        if self.field_strength is not None and not (
            math.isfinite(self.field_strength) and self.field_strength > 0
        ):
            problems.append(f'field_strength must be None or > 0, got {self.field_strength}')
        if self.min_samples < 1:
            problems.append(f'min_samples must be >= 1, got {self.min_samples}')
        if not 0.0 <= self.min_coverage <= 1.0:
            problems.append(f'min_coverage must be in [0, 1], got {self.min_coverage}')
        for name in ('max_residual_pct', 'max_condition', 'outlier_threshold'):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                problems.append(f'{name} must be a positive number, got {value}')
        if not self.max_condition < DIVERGED_CONDITION:  # the fit stops beyond it
            problems.append(f'max_condition must be below {DIVERGED_CONDITION:g}, got '
                            f'{self.max_condition}')
        if not (math.isfinite(self.max_axis_ratio) and self.max_axis_ratio >= 1.0):
            problems.append(f'max_axis_ratio must be >= 1, got {self.max_axis_ratio}')
        if not 0.0 <= self.planar_thickness < 1.0:
            problems.append(f'planar_thickness must be in [0, 1), got {self.planar_thickness}')
        if problems:
            raise ValueError('invalid FitOptions: ' + '; '.join(problems))


@dataclass(frozen=True)
class FitMetrics:
    """How good a fit is; every number finite (inf stands as the largest float).

    - residuals: ``|corrected|/F - 1`` over the inliers, in percent (for ``planar`` without a
      prior: of the 3-D field when tilts while turning determined the offset along the normal,
      else of the in-plane field).
    - ``n_samples``: finite rows used; ``n_non_finite``: rows dropped for NaN/Inf.
    - ``coverage``: share of the 80 direction cells (3-D models) or of the 36 heading sectors
      (``planar``); ``coverage_hint`` the rotation still missing ('' when complete).
    - ``condition_number``: of the final normalised Jacobian (see FitOptions.max_condition).
    - ``mean_radius``: volume-equivalent radius of the fitted ellipsoid, input units (the output F
      when ``field_strength`` is None).
    - ``axis_ratio``: longest over shortest semi-axis (in the plane for ``planar``).
    - ``parameter_std``: 1-sigma of the output ``offset`` (input units) and ``matrix`` (row-major)
      from the Jacobian; for ``planar`` ``offset_in_plane``, the relative in-plane shape and,
      when fitted, ``offset_normal``.
    - ``unobserved``: what the data could not determine (``planar``: ``matrix_normal``, and
      ``offset_normal`` unless tilts while turning determined it).
    """

    model: str
    n_samples: int
    n_inliers: int
    residual_rms_pct: float
    residual_max_pct: float
    coverage: float
    condition_number: float
    outlier_count: int
    mean_radius: float
    axis_ratio: float
    parameter_std: dict[str, list[float]] | None
    unobserved: tuple[str, ...]
    n_non_finite: int = 0
    coverage_hint: str = ''

    def as_dict(self) -> dict[str, Any]:
        """Plain JSON-able dict (lists, not tuples or arrays)."""
        data = asdict(self)
        data['unobserved'] = list(self.unobserved)
        return data


@dataclass(frozen=True)
class FitResult:
    """Outcome of fit_calibration.

    ``calibration`` is the best effort even when a gate fails (None only when nothing could be
    fitted); apply it only when ``success``. ``outliers`` marks every input row not used by the
    final fit (robust outliers and non-finite rows).
    """

    success: bool
    calibration: Calibration | None
    reason: str
    metrics: FitMetrics
    outliers: np.ndarray = field(repr=False)


def fit_calibration(
    samples: ArrayLike,
    options: FitOptions | None = None,
    weights: ArrayLike | None = None,
    readings: ArrayLike | None = None,
    ups: ArrayLike | None = None,
    paired: tuple[ArrayLike, ArrayLike] | None = None,
    known: Calibration | None = None,
) -> FitResult:
    """Fit ``options.model`` to (n, 3) raw samples; never raises on data, never returns NaN/Inf.

    ``weights`` (n,), optional: how many readings each row stands for (SampleBuffer.counts, when
    a row is the average of several), or any relative precision; finite and > 0. They weight the
    least squares only: residual metrics, outlier flags and the condition gate stay per row.
    ``readings`` (m, 3), optional: the sensor's readings behind selected samples
    (SampleBuffer.readings), so the coverage gate tells the field's sphere from the rim of a
    still sensor's noise (see coverage.shell_directions).
    ``ups`` (n, 3), optional: gravity's direction in the sensor frame behind each sample (the
    paired accelerometer; NaN rows: none); ``paired`` (readings (m, 3), their gravity
    directions (m, 3)), preferred when given (SampleBuffer.paired_readings: an unbiased draw). A
    planar fit without a prior is then levelled by them (see levelled.py): a ground robot's tilts
    explained, its heading right on a tilted floor. ``known``, optional: the calibration in
    force, whose offset along the turning axis such a fit weighs in as far as its own tilts
    determined it (metadata ``levelled_offset_normal_std``): a refinement.
    """
    options = options or FitOptions()
    rows, finite, problem = _usable_rows(samples)
    n_bad = int((~finite).sum())
    if not problem and weights is not None:
        weights, problem = _usable_weights(weights, finite)
    if problem:
        return _failure(options, problem, finite, 0, n_bad)
    n = len(rows)
    if n == 0:
        reason = (
            f'no usable samples: all {n_bad} rows contain NaN or Inf' if n_bad else 'no samples'
        )
        return _failure(options, reason, finite, 0, n_bad)
    largest = float(np.max(np.abs(rows)))
    if largest > LARGEST_READING:
        return _failure(
            options,
            f'samples reach {largest:.3g}, beyond {LARGEST_READING:.2g} where the differences '
            'between readings overflow: these are no magnetometer readings in any unit (wrong '
            'columns, a corrupt log?)',
            finite, n, n_bad,
        )  # fmt: skip
    norm = normalise(rows)
    if norm is None:
        return _failure(
            options,
            f'all {n} samples are (nearly) identical: rotate the sensor through many orientations',
            finite, n, n_bad,
        )  # fmt: skip
    # Work in input units / 2^k (exact in floating point): tesla and counts alike are of order one.
    unit = 2.0 ** round(math.log2(norm.scale))
    rows = rows / unit
    norm = Normalisation(norm.centre / unit, norm.scale / unit)  # normalise(rows), exactly
    normalised = norm, norm.forward(rows)
    options = replace(
        options,
        field_strength=None if options.field_strength is None else options.field_strength / unit,
        prior=None if options.prior is None else options.prior.scaled(1.0 / unit),
    )
    gravity = _gravity(rows, unit, weights, finite, ups, paired)
    if gravity is not None:
        gravity = (*gravity, _known_normal(known, unit))
    with np.errstate(all='ignore'):
        layer_thickness, _ = thickness(normalised[1])
        fitted, choice_note = _level(rows, options, gravity, *_fit_model(
            rows, options, layer_thickness, weights, normalised))
        if fitted is None:
            reasons = [
                _too_few(n, options)
                or f'the {options.model} model could not be fitted to {n} samples: they do not '
                'outline an ellipsoid; rotate the sensor through many orientations'
            ]
            if options.model != 'planar' and layer_thickness < options.planar_thickness:
                reasons.append(_planar_reason(rows, options.model, layer_thickness, options))
            return _failure(options, '; '.join(reasons), finite, n, n_bad)
        evidence = None if readings is None else finite_rows(readings) / unit
        result = _judge(
            rows, finite, fitted, options, layer_thickness, n_bad, choice_note, evidence
        )
        if not fitted.robust and _near_a_gate(result, options):
            refitted, note = _level(rows, options, gravity, *_fit_model(
                rows, options, layer_thickness, weights, normalised, True))
            if refitted is not None:
                result = _judge(
                    rows, finite, refitted, options, layer_thickness, n_bad, note, evidence
                )
        result = _tilted_planar(result, rows, options, gravity)
    return _in_input_units(result, unit)


MAX_PLANAR_TILT_DEG = 5.0
"""With gravity paired, ``auto`` adopts a planar fit only while gravity stayed within this of its
mean direction in the chip frame (95 % of the paired samples), as a floor keeps a turning robot
(2-4 deg: test_session.py). Readings near one plane while the board tilts (a tumble's first
seconds turning about one axis) leave the offset along the plane's normal unseen, and it leaks
into the heading as the board tilts (issue #46: 6.4 deg adopted and saved)."""


def _tilted_planar(result: FitResult, rows: np.ndarray, options: FitOptions,
                   gravity: tuple | None) -> FitResult:
    """``result``, failed when ``auto`` chose planar while gravity says the board tilted."""
    if (options.model != 'auto' or gravity is None or result.calibration is None
            or result.calibration.model != 'planar'):
        return result
    directions = gravity[1][np.all(np.isfinite(gravity[1]), axis=1)]
    if len(directions) < 2:
        return result
    directions = directions / np.linalg.norm(directions, axis=1)[:, None]
    mean = directions.mean(axis=0)
    if not np.linalg.norm(mean) > 0.0:
        return result
    cosines = np.clip(directions @ (mean / np.linalg.norm(mean)), -1.0, 1.0)
    tilt = float(np.degrees(np.arccos(np.percentile(cosines, 5.0))))
    if tilt <= MAX_PLANAR_TILT_DEG:
        return result
    reason = (f'the samples lie near one plane, but gravity says the sensor tilted by '
              f'{tilt:.0f} deg meanwhile (a planar calibration needs it within '
              f'{MAX_PLANAR_TILT_DEG:g} deg): off that plane it would be wrong; '
              f'{_tilt_hint(rows)} (or set model planar for a robot that only turns)')
    failed = reason if result.success else f'{result.reason}; {reason}'
    return replace(result, success=False, reason=failed)


def _near_a_gate(result: FitResult, options: FitOptions) -> bool:
    """True when a gate failed or is within GATE_MARGIN of failing."""
    metrics, near = result.metrics, 1.0 - GATE_MARGIN
    return (
        not result.success
        or metrics.residual_rms_pct >= near * options.max_residual_pct
        or metrics.condition_number >= 1.0 + near * (options.max_condition - 1.0)
        or metrics.axis_ratio >= 1.0 + near * (options.max_axis_ratio - 1.0)
        or metrics.coverage <= options.min_coverage + GATE_MARGIN * (1.0 - options.min_coverage)
    )


def _in_input_units(result: FitResult, unit: float) -> FitResult:
    """Undo the power-of-two working unit: offsets and radii scale, matrices do not."""
    std = result.metrics.parameter_std
    if std is not None:
        std = {
            key: [v * unit for v in values] if key.startswith('offset') else values
            for key, values in std.items()
        }
    metrics = replace(
        result.metrics, mean_radius=_finite(result.metrics.mean_radius * unit), parameter_std=std
    )
    calibration = result.calibration.scaled(unit) if result.calibration is not None else None
    return replace(result, calibration=calibration, metrics=metrics)


def _usable_rows(samples: ArrayLike) -> tuple[np.ndarray, np.ndarray, str]:
    """(finite rows, finite mask over the input rows, problem text or '')."""
    try:
        array = np.asarray(samples, dtype=float)
    except (TypeError, ValueError) as error:
        return np.empty((0, 3)), np.zeros(0, bool), f'samples are not numbers: {error}'
    if array.ndim == 1 and array.size == 0:
        array = array.reshape(0, 3)
    if array.ndim != 2 or array.shape[1] != 3:
        return (
            np.empty((0, 3)),
            np.zeros(0, bool),
            f'samples must be an (n, 3) array, got shape {array.shape}',
        )
    finite = np.all(np.isfinite(array), axis=1)
    return (array if finite.all() else array[finite]), finite, ''


def _usable_weights(weights: ArrayLike, finite: np.ndarray) -> tuple[np.ndarray | None, str]:
    """(weights of the finite rows, problem text or '')."""
    try:
        array = np.asarray(weights, dtype=float)
    except (TypeError, ValueError) as error:
        return None, f'weights are not numbers: {error}'
    if array.shape != finite.shape:
        return None, f'weights must have shape ({len(finite)},), one per sample, got {array.shape}'
    if not np.all(np.isfinite(array) & (array > 0.0)):
        return None, 'weights must be finite and > 0'
    return array[finite], ''


def _gravity(
    rows: np.ndarray,
    unit: float,
    weights: np.ndarray | None,
    finite: np.ndarray,
    ups: ArrayLike | None,
    paired: tuple[ArrayLike, ArrayLike] | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None] | None:
    """What to level a planar fit with: the paired readings and their gravity directions when
    given and usable, else the samples' (``rows`` are the finite samples / ``unit``)."""
    if paired is not None and len(paired) == 2:
        points, directions = _paired_rows(*paired)
        if points is not None:
            return points / unit, directions, None
    if ups is not None:
        directions = _paired_rows(np.zeros((len(finite), 3)), ups)[1]
        if directions is not None:
            return rows, directions[finite], weights
    return None


def _paired_rows(points: ArrayLike, ups: ArrayLike
                 ) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(finite points, their gravity directions with NaN where unusable), or (None, None) when the
    shapes differ or no direction is usable."""
    try:
        points = np.asarray(points, dtype=float)
        ups = np.asarray(ups, dtype=float)
    except (TypeError, ValueError):
        return None, None
    if points.ndim != 2 or points.shape[1:] != (3,) or ups.shape != points.shape:
        return None, None
    keep = np.all(np.isfinite(points), axis=1)
    points, ups = points[keep], ups[keep].copy()
    usable = np.all(np.isfinite(ups), axis=1) & np.any(ups != 0.0, axis=1)
    if not usable.any():
        return None, None
    ups[~usable] = np.nan
    return points, ups


def _known_normal(known: Calibration | None, unit: float) -> tuple[np.ndarray, float] | None:
    """(offset, its 1-sigma along the turning axis) of ``known`` in the rows' units, when its
    levelled fit determined one (a finite, positive share of the field it read: the raw field's
    radius, whatever F the output was scaled to); else None."""
    if known is None:
        return None
    std = known.metadata_number('levelled_offset_normal_std')
    if not (std is not None and math.isfinite(std) and std > 0.0):
        return None
    std = std * known.field_radius() / unit
    if not (math.isfinite(std) and std > 0.0):
        return None
    return np.asarray(known.offset, dtype=float) / unit, std


def _too_few(n: int, options: FitOptions) -> str:
    if n >= options.min_samples:
        return ''
    return (
        f'too few samples: {n}, need at least {options.min_samples}; keep rotating the sensor '
        'through new orientations'
    )


def _level(
    rows: np.ndarray,
    options: FitOptions,
    gravity: tuple[np.ndarray, np.ndarray, np.ndarray | None, tuple | None] | None,
    fitted: EllipsoidFit | None,
    note: str,
) -> tuple[EllipsoidFit | None, str]:
    """A planar fit without a prior, levelled by ``gravity`` (points in the rows' units, their
    gravity directions, weights, what was known of the offset along the normal) when that
    stands (levelled.py); any other fit as it is."""
    if fitted is None or fitted.model != 'planar' or gravity is None or options.prior is not None:
        return fitted, note
    levelling = level_planar(*gravity[:2], fitted, gravity[2], options.outlier_threshold,
                             gravity[3])
    if levelling.offset is None:
        return fitted, note
    return (levelling.ellipsoid_fit(rows, fitted, options.outlier_threshold),
            '; '.join(part for part in (note, levelling.note) if part))


def _fit_model(
    rows: np.ndarray,
    options: FitOptions,
    layer_thickness: float,
    weights: np.ndarray | None,
    normalised: tuple[Normalisation, np.ndarray],
    always_robust: bool = False,
) -> tuple[EllipsoidFit | None, str]:
    """The requested model, or for ``auto`` the one the data determine with the lowest BIC.
    ``normalised``: ``normalise(rows)`` and the normalised rows (shared by every fit)."""
    prior = None
    if options.prior is not None:
        prior = (options.prior.offset, options.prior.matrix / options.prior.field_strength)
    threshold = options.outlier_threshold

    def fit(*models: str) -> dict[str, EllipsoidFit | None]:
        return fit_ellipsoids(rows, models, threshold, prior, weights, always_robust, normalised)

    if options.model != 'auto':
        return fit(options.model)[options.model], ''
    if layer_thickness < options.planar_thickness:
        note = f'auto: planar (samples lie near one plane, thickness {layer_thickness:.2f})'
        return fit('planar')['planar'], note
    models = ('sphere', 'full') if len(rows) >= 2 * PARAMETER_COUNTS['full'] else ('sphere',)
    fits = fit(*models)
    sphere, full = fits['sphere'], fits.get('full')
    determined = [
        fit for fit in (sphere, full) if fit is not None and fit.condition <= options.max_condition
    ]
    if not determined:
        # Nearly planar motion (a robot yawing with some tilt) determines the heading plane at
        # least; anything thicker gets the best-conditioned 3-D fit, and the gates say what is
        # missing.
        chosen = None
        if layer_thickness < 2.0 * options.planar_thickness:
            chosen = fit('planar')['planar']
        candidates = [fit for fit in (sphere, full) if fit is not None]
        if chosen is None and candidates:
            chosen = min(candidates, key=lambda fit: fit.condition)
        note = 'neither a sphere nor an ellipsoid is determined by the samples'
        return chosen, f'auto: {chosen.model} ({note})' if chosen else ''
    if len(determined) == 1:
        chosen = determined[0]
        return chosen, f'auto: {chosen.model} (condition {chosen.condition:.0f})'
    common = full.inliers  # the flexible model's inliers: a sphere must not win by discarding
    root = np.ones(len(rows)) if weights is None else np.sqrt(weights)
    scores = {  # on weighted residuals: an averaged row's residual is that much more telling
        fit.model: information_criterion(
            (fit.residuals * root)[common], PARAMETER_COUNTS[fit.model]
        )
        for fit in (sphere, full)
    }
    chosen = full if scores['full'] < scores['sphere'] else sphere
    return (
        chosen,
        f'auto: {chosen.model} (BIC sphere {scores["sphere"]:.1f}, full {scores["full"]:.1f})',
    )


def _judge(
    rows: np.ndarray,
    finite: np.ndarray,
    fitted: EllipsoidFit,
    options: FitOptions,
    layer_thickness: float,
    n_bad: int,
    choice_note: str,
    readings: np.ndarray | None = None,
) -> FitResult:
    inliers = fitted.inliers
    inlier_residuals = fitted.residuals[inliers]
    residual_rms = _finite(100.0 * float(np.sqrt(np.mean(inlier_residuals**2))))
    residual_max = _finite(100.0 * float(np.max(np.abs(inlier_residuals))))
    mean_radius = _finite(fitted.radius)
    field_strength = options.field_strength or mean_radius
    reasons = []
    calibration = None
    matrix = fitted.matrix * field_strength
    positive_definite = bool(np.linalg.eigvalsh(0.5 * (matrix + matrix.T)).min() > 0)
    if positive_definite and field_strength > 0:
        try:
            calibration = Calibration(fitted.offset, matrix, field_strength, fitted.model)
        except CalibrationError as error:
            reasons.append(f'fitted calibration unusable: {error}')
    else:
        reasons.append(
            'fitted soft-iron matrix is not positive definite: the samples do not outline an '
            'ellipsoid (disturbed field or too little rotation)'
        )
    trusted = calibration if fitted.condition <= options.max_condition else None
    coverage = _coverage(rows, fitted, trusted, readings)
    n_inliers = int(inliers.sum())
    reasons = _gates(rows, fitted, options, layer_thickness, coverage, residual_rms) + reasons
    metrics = FitMetrics(
        model=fitted.model,
        n_samples=len(rows),
        n_inliers=n_inliers,
        residual_rms_pct=residual_rms,
        residual_max_pct=residual_max,
        coverage=float(coverage.fraction),
        condition_number=_finite(fitted.condition),
        outlier_count=int((~inliers).sum()),
        mean_radius=mean_radius,
        axis_ratio=_finite(fitted.axis_ratio),
        parameter_std=_output_std(fitted.parameter_std, field_strength),
        unobserved=fitted.unobserved,
        n_non_finite=n_bad,
        coverage_hint=coverage.hint,
    )
    if calibration is not None:
        extra: dict[str, Any] = {}
        if fitted.plane_normal is not None:
            extra['plane_normal'] = fitted.plane_normal.tolist()
        if fitted.unobserved:
            extra['unobserved'] = list(fitted.unobserved)
        if fitted.levelled:
            extra['levelled_by_gravity'] = True
            if fitted.dip_deg is not None:
                extra['levelled_dip_deg'] = round(fitted.dip_deg, 3)
            if fitted.normal_offset_std is not None:
                extra['levelled_offset_normal_std'] = float(fitted.normal_offset_std)
        calibration = calibration.with_metadata(
            residual_rms_pct=residual_rms,
            coverage=float(coverage.fraction),
            samples=n_inliers,
            **extra,
        )
    outliers = ~finite
    outliers[np.flatnonzero(finite)[~inliers]] = True
    notes = [choice_note] if choice_note else []
    if n_bad:
        notes.append(f'{n_bad} rows with NaN/Inf dropped')
    reason = '; '.join(reasons) if reasons else 'ok' + (f' ({"; ".join(notes)})' if notes else '')
    return FitResult(not reasons, calibration, reason, metrics, outliers)


def _output_std(
    std: dict[str, list[float]] | None, field_strength: float
) -> dict[str, list[float]] | None:
    """Standard deviations of the output calibration: its matrix is F times the unit-radius one."""
    if std is None:
        return None
    scaled = {
        key: [v * field_strength for v in values] if key == 'matrix' else list(values)
        for key, values in std.items()
    }
    finite = all(math.isfinite(v) for values in scaled.values() for v in values)
    return scaled if finite else None


def _gates(
    rows: np.ndarray,
    fitted: EllipsoidFit,
    options: FitOptions,
    layer_thickness: float,
    coverage: Coverage,
    residual_rms: float,
) -> list[str]:
    """Every failed quality gate, each with what to do about it."""
    reasons = []
    too_few = _too_few(len(rows), options)
    if too_few:
        reasons.append(too_few)
    if coverage.fraction < options.min_coverage:
        reasons.append(
            f'coverage {100 * coverage.fraction:.0f} % is below '
            f'{100 * options.min_coverage:.0f} %: {coverage.hint}'
        )
    if coverage.occupied == 0 and coverage.fraction < options.min_coverage:
        return reasons  # no field direction told apart (a still sensor): other gates judge noise
    if fitted.model != 'planar' and layer_thickness < options.planar_thickness:
        reasons.append(_planar_reason(rows, fitted.model, layer_thickness, options))
    if fitted.condition > options.max_condition:
        simpler = '' if fitted.model == 'sphere' else ' or choose a simpler model (sphere)'
        reasons.append(
            f'ill-conditioned fit (condition number {_finite(fitted.condition):.3g} > '
            f'{options.max_condition:.3g}): the samples do not determine the {fitted.model} '
            f'model; rotate through more orientations{simpler}'
        )
    ratio = fitted.axis_ratio
    if ratio > options.max_axis_ratio:
        reasons.append(
            f'soft-iron axis ratio {_finite(ratio):.3g} exceeds {options.max_axis_ratio:.3g}: '
            'strong magnetic material near the sensor, a changing field, or a bad fit'
        )
    if residual_rms > options.max_residual_pct:
        exceeds = (
            f'residual {residual_rms:.2f} % of the field exceeds {options.max_residual_pct:.2f} %'
        )
        tilt = _tilt_correlation(rows, fitted) if fitted.model == 'planar' else 0.0
        if abs(tilt) >= TILT_CORRELATION:
            held = 'the prior' if options.prior is not None else 'the data'
            reasons.append(
                f'{exceeds}: the robot tilts while turning (the residual follows the reading '
                f'along the plane normal, correlation {tilt:.2f}): a tilt moves part of the '
                f'vertical field into the plane, which the vertical offset from {held} does not '
                'explain; tilt it a few degrees in every direction while turning (so the '
                'vertical offset is fitted), calibrate on level ground, or tumble it for a full '
                'calibration'
            )
        else:
            reasons.append(
                f'{exceeds}: the field was disturbed (nearby iron, motors, currents) or the '
                'sensor is very noisy'
            )
    return reasons


TILT_CORRELATION = 0.5
"""|correlation| between a planar fit's residuals and the reading along the plane normal beyond
which the residual is put down to tilting, not to a disturbed field or noise: a tilt changes both
together (the in-plane field by V θ, the normal reading by H θ), disturbances and noise do not."""


def _tilt_correlation(rows: np.ndarray, fitted: EllipsoidFit) -> float:
    """Correlation of the inlier residuals with the corrected reading along its least-spread
    axis (the plane normal, whatever frame the fit's prior put the plane in); 0 when undefined."""
    inliers = fitted.inliers
    if inliers.sum() < 3:
        return 0.0
    corrected = (rows[inliers] - fitted.offset) @ fitted.matrix.T
    centred = corrected - corrected.mean(axis=0)
    normal = np.linalg.svd(centred, full_matrices=False)[2][-1]
    along, residuals = centred @ normal, fitted.residuals[inliers]
    if np.std(along) <= 0 or np.std(residuals) <= 0:
        return 0.0
    correlation = float(np.corrcoef(along, residuals)[0, 1])
    return correlation if math.isfinite(correlation) else 0.0


def _planar_reason(
    rows: np.ndarray, model: str, layer_thickness: float, options: FitOptions
) -> str:
    return (
        f'samples lie near one plane (thickness {layer_thickness:.2f} < '
        f'{options.planar_thickness:.2f}): the {model} model needs tilting as well; '
        f'{_tilt_hint(rows)}, or use model planar'
    )


def _tilt_hint(rows: np.ndarray) -> str:
    """Which rotation would take planar data off its plane."""
    hint = missing_rotation_hint(occupied_cells(whitened_directions(rows)))
    return hint or 'tilt the sensor about its other axes'


def _coverage(
    rows: np.ndarray,
    fitted: EllipsoidFit,
    calibration: Calibration | None,
    readings: np.ndarray | None = None,
) -> Coverage:
    """3-D direction coverage, or heading coverage in the plane for ``planar``; ``readings``:
    the readings behind the rows (see fit_calibration)."""
    if fitted.headings is not None and fitted.plane_normal is not None:
        ring, problem = fit_ring(rows[fitted.inliers], readings)
        if ring is None:  # a flat noise blob (a still sensor) has headings all round too
            return Coverage(0.0, 0, HEADING_SECTORS, problem)
        # the ring's headings: a circle on a short arc, where the fit's ellipse is anything
        return heading_coverage(ring.headings(rows[fitted.inliers]), fitted.plane_normal)
    inliers = rows if fitted.inliers.all() else rows[fitted.inliers]
    coverage = direction_coverage(inliers, calibration, readings)
    if coverage.occupied == 0 and calibration is not None:
        # A model too simple for the data (e.g. `axis` under rotated soft iron) leaves a shell too
        # thick to trust its directions; that is the residual gate's finding, not missing
        # rotation. Coverage is a property of the data: judge it by their own whitening.
        own = direction_coverage(inliers, None, readings)
        if own.occupied > 0:
            return own
    return coverage


def _finite(value: float) -> float:
    value = float(value)
    if math.isnan(value):
        return _HUGE
    return max(min(value, _HUGE), -_HUGE)


def _failure(
    options: FitOptions, reason: str, finite: np.ndarray, n: int, n_bad: int
) -> FitResult:
    model = options.model
    metrics = FitMetrics(
        model=model, n_samples=n, n_inliers=0, residual_rms_pct=0.0, residual_max_pct=0.0,
        coverage=0.0, condition_number=0.0, outlier_count=0, mean_radius=0.0, axis_ratio=0.0,
        parameter_std=None, unobserved=(), n_non_finite=n_bad,
        coverage_hint='rotate the sensor slowly through all orientations',
    )  # fmt: skip
    return FitResult(False, None, reason, metrics, ~finite)
