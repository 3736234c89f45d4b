# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The hard iron from the gyroscope: the Earth's field is fixed in the world, so readings turned
back by the rotation the gyroscope measured must all be one vector; only the offset keeps them
apart. No sphere is needed, only rotation about two axes.

Within a window of readings integrated from one gyroscope stream, ``R_i (m_i - b) = w`` (``R_i``
the attitude the gyroscope integrated, ``w`` the field in the window's frame): linear in ``b``
and ``w``, so each window's ``w`` is eliminated by centring and ``b`` is one least-squares
solve (PX4's ``mag_bias_estimator`` learns the same offset from ``dm/dt = -w x (m - b)``;
Kok & Schoen, "Magnetometer calibration using inertial sensors", IEEE Sensors J. 16(14), 2016;
MAGYC, arXiv 2410.13827, adds the soft iron). Windows are short, so the gyroscope's bias turns
the field by little in one; its effect and every other correlated error show in the offset's
uncertainty, measured by leaving groups of windows out (a jackknife), not from the residuals as
if each reading were independent. The same readings judge the raw field: a sensor that arrives
calibrated (many do) has nothing to gain from an offset its own uncertainty cannot tell from
zero, and ``fit_gyro_aided`` says so.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
import math

import numpy as np

from mag_calibrator_ros.calibration.fit.calibration import Calibration, CalibrationError
from mag_calibrator_ros.calibration.fit.robust import mad_sigma

MIN_WINDOWS = 8
"""Windows needed before an offset is solved: each contributes one rotation's worth of turning."""

JACKKNIFE_GROUPS = 8
"""Groups of windows left out in turn to measure the offset's uncertainty: windows next to each
other share a gyroscope bias and a hand's motion, so groups of consecutive windows are left out
together."""

MAX_DIRECTION_STD_DEG = 1.0
"""The largest 1-sigma (jackknife) of the corrected directions a fit may have, in degrees: what
its own uncertainty can move a heading by (the soft iron's, the offset's and the rotation's
together, on the readings it saw), rather than a share of the sphere covered."""


MOUNTING_ITERATIONS = 50
"""Rounds of (rotation into the gyroscope's frame, offset) at most: each moves the rotation part
of the way (each window's field is re-estimated from the last rotation), so a few degrees take
tens of rounds of a millisecond; they stop once the rotation moves less than MOUNTING_SETTLED."""

MOUNTING_SETTLED = 1e-5
"""...radians in a round."""

OUTLIER_ROUNDS = 3
"""Rounds of leaving out the windows that disagree with the rest (``_consistent_windows``)."""

OUTLIER_SIGMAS = 5.0
"""A window disagrees when its field's length is five robust sigmas (over windows) from the
median window's: beyond a sensor's noise and soft iron, well within what a magnet stuck on or
taken off moves."""

ONE_AXIS = 0.05
"""The windows' rotations about their means span less than this share of their largest turn in
some direction: the sensor turned about one axis (a ground robot, a straight drive), and the
offset along it is not seen, however sure the jackknife of so little wobble is: no fit (the
planar fits are that motion's)."""

_ONE_AXIS_TEXT = ('the readings turned about one axis only (the offset along it is not seen): '
                  'turn it about another axis too')


@dataclass(frozen=True)
class TurnedReadings:
    """Readings with the attitude the gyroscope integrated at each, in windows.

    ``readings`` (n, 3) raw readings (the robot's own field removed); ``rotations`` (n, 3, 3)
    the attitude of each reading in its window's frame (body to that frame); ``windows`` (n,)
    integer labels, readings of one label sharing one frame (one stretch of gyroscope
    integration no longer than the gyroscope's bias allows); ``spans`` (n,) labels of longer
    stretches of whole windows of one unbroken integration (None: the windows), what
    ``turned_direction_errors`` judges directions over."""

    readings: np.ndarray
    rotations: np.ndarray
    windows: np.ndarray
    spans: np.ndarray | None = None


@dataclass(frozen=True)
class GyroAidedFit:
    """An offset from the gyroscope, its uncertainty, and the raw field judged by the same
    readings. ``calibration`` is None when no offset could be solved; ``success`` says whether
    it is determined well enough to go in force (``reason`` says why not)."""

    success: bool
    calibration: Calibration | None
    offset_std: np.ndarray
    """1-sigma of each offset component (input units, from the jackknife)."""
    residual_pct: float
    """RMS spread of the turned readings about their windows' field, in % of F (the fit)."""
    raw_residual_pct: float
    """The same for the raw readings (offset zero)."""
    windows: int
    readings: int
    turn: float
    """The windows' turning in their least-turned direction, a share of the most (ONE_AXIS)."""
    reason: str = ''
    used: np.ndarray | None = None
    """The window labels fitted (those that agree with the rest); None: all."""
    direction_std_deg: float = math.inf
    """The jackknife's sigma of the corrected directions (MAX_DIRECTION_STD_DEG)."""


def fit_gyro_aided(data: TurnedReadings, *,
                   max_direction_std_deg: float = MAX_DIRECTION_STD_DEG,
                   max_residual_pct: float = 5.0, max_rotation_deg: float = 15.0
                   ) -> GyroAidedFit:
    """The offset that makes each window's turned readings one vector (see the module), with a
    sphere's correction (``M = I``, ``F`` the field's median radius) and the rotation ``R`` of
    the magnetometer's axes into the gyroscope's (the IMU frame: readings turned by the
    gyroscope agree only in its frame, so no still tilts are needed): a value or the reason."""
    readings = np.asarray(data.readings, dtype=float).reshape(-1, 3)
    rotations = np.asarray(data.rotations, dtype=float).reshape(-1, 3, 3)
    labels = np.asarray(data.windows).reshape(-1)
    design, target, groups = _centred(readings, rotations, labels)
    windows = int(groups.max()) + 1 if len(groups) else 0
    nothing = np.full(3, math.inf)
    if windows < MIN_WINDOWS:
        return GyroAidedFit(False, None, nothing, math.nan, math.nan, windows, len(readings),
                            0.0, f'{windows} windows of turning readings, need {MIN_WINDOWS}')
    spans = np.linalg.svd(design, compute_uv=False)
    turn = float(spans[-1] / spans[0]) if spans[0] > 0.0 else 0.0
    offset, mounting, design, target, groups = _offset_and_mounting(readings, rotations, labels)
    for _ in range(OUTLIER_ROUNDS if offset is not None else 0):
        kept = _consistent_windows(readings, labels, offset)
        if kept.all():
            break
        readings, rotations, labels = readings[kept], rotations[kept], labels[kept]
        offset, mounting, design, target, groups = _offset_and_mounting(
            readings, rotations, labels)
        windows = int(groups.max()) + 1 if len(groups) else 0
        if offset is None or windows < MIN_WINDOWS:
            return GyroAidedFit(False, None, nothing, math.nan, math.nan, windows,
                                len(readings), turn, 'the turned readings disagree with one '
                                'another (a field disturbed, or a magnet come or gone): keep '
                                'turning it')
    if offset is None:
        return GyroAidedFit(False, None, nothing, math.nan, math.nan, windows, len(readings),
                            turn, 'the readings turned about one axis only (the offset along '
                            'it is not seen): turn it about another axis too')
    radius = float(np.median(np.linalg.norm(readings - offset, axis=1)))
    raw_radius = float(np.median(np.linalg.norm(readings, axis=1)))
    if not (radius > 0.0 and raw_radius > 0.0):
        return GyroAidedFit(False, None, nothing, math.nan, math.nan, windows, len(readings),
                            turn, 'the readings have no field left once the offset is removed')
    std, estimates = _jackknife_std(design, target, groups, windows, offset)
    residual = 100.0 * _spread(readings, rotations @ mounting, labels, offset) / radius
    raw_residual = 100.0 * _spread(readings, rotations, labels, np.zeros(3)) / raw_radius
    angle = _angle_deg(mounting)
    calibration = Calibration(offset, np.eye(3), radius, model='sphere', rotation=mounting,
                              metadata={'fit': 'gyro_aided', 'windows': windows,
                                        'aligned_by': 'gyroscope',
                                        'rotation_deg': round(angle, 3)})
    direction_std = _direction_std_deg(readings, calibration, [
        Calibration(estimate, np.eye(3), radius, rotation=mounting) for estimate in estimates])
    calibration = calibration.with_metadata(direction_std_deg=round(direction_std, 3))
    most = max_direction_std_deg
    reason = ''
    if angle > max_rotation_deg:
        reason = _mounting_text(angle, max_rotation_deg)
    elif turn < ONE_AXIS:
        reason = _ONE_AXIS_TEXT
    elif not direction_std <= most:
        reason = _uncertain_text(direction_std, most, std, radius, 'keep turning it')
    elif residual > max_residual_pct:
        reason = (f'the turned readings spread by {residual:.1f} % of the field, the bound is '
                  f'{max_residual_pct:.1f} %: the magnetometer does not turn with the '
                  'gyroscope (another frame, a disturbed field or another unit)')
    return GyroAidedFit(not reason, calibration, std, residual, raw_residual, windows,
                        len(readings), turn, reason, np.unique(labels), direction_std)


def fit_gyro_aided_full(data: TurnedReadings, start: GyroAidedFit, *,
                        max_direction_std_deg: float = MAX_DIRECTION_STD_DEG,
                        max_residual_pct: float = 5.0, max_rotation_deg: float = 15.0
                        ) -> GyroAidedFit:
    """The soft iron too (MAGYC's idea, arXiv 2410.13827): the whole linear map ``G = R M`` and
    the offset that make each window's turned readings one vector and every reading as long as
    the others, from the offset-only fit ``start`` (Levenberg-Marquardt; both residuals relative
    to the field, so ``G``'s scale is free and set afterwards). Its uncertainty, of the offset
    and of ``M`` (relative), by the same jackknife over windows; bounded as the offset's."""
    if start.calibration is None:
        return start
    readings = np.asarray(data.readings, dtype=float).reshape(-1, 3)
    rotations = np.asarray(data.rotations, dtype=float).reshape(-1, 3, 3)
    labels = np.asarray(data.windows).reshape(-1)
    if start.used is not None:  # the windows that agree with the rest
        rows = np.isin(labels, start.used)
        readings, rotations, labels = readings[rows], rotations[rows], labels[rows]
    initial = np.concatenate([start.calibration.correction.reshape(9), start.calibration.offset])
    solution = _full_solve(readings, rotations, labels, initial)
    if solution is None:
        return replace(start, success=False, reason='the soft iron could not be solved')
    groups = np.unique(labels)
    count = min(JACKKNIFE_GROUPS, len(groups))
    estimates = []
    for group in range(count):
        kept = np.isin(labels, groups[np.arange(len(groups)) * count // len(groups) != group])
        estimate = _full_solve(readings[kept], rotations[kept], labels[kept], solution)
        if estimate is None:
            return replace(start, success=False, reason='the soft iron could not be solved')
        estimates.append(_normalised(estimate))
    deviations = np.asarray(estimates) - _normalised(solution)
    std = np.sqrt((count - 1) / count * np.sum(deviations**2, axis=0))
    try:
        calibration = _calibration(solution, readings, start.calibration.metadata)
        alternatives = [_calibration(estimate, readings, {}) for estimate in estimates]
    except (CalibrationError, ValueError, np.linalg.LinAlgError):
        return replace(start, success=False, reason='the soft iron is not positive definite')
    direction_std = _direction_std_deg(readings, calibration, alternatives)
    calibration = calibration.with_metadata(direction_std_deg=round(direction_std, 3))
    most = max_direction_std_deg
    radius = calibration.field_strength
    offset_std, matrix_std = std[9:], float(np.max(std[:9]))
    residual = 100.0 * _spread(readings, rotations @ calibration.rotation, labels,
                               calibration.offset, calibration.matrix) / radius
    angle = _angle_deg(calibration.rotation)
    calibration = calibration.with_metadata(rotation_deg=round(angle, 3))
    reason = ''
    if angle > max_rotation_deg:
        reason = _mounting_text(angle, max_rotation_deg)
    elif start.turn < ONE_AXIS:
        reason = _ONE_AXIS_TEXT
    elif not direction_std <= most:
        reason = _uncertain_text(direction_std, most, offset_std, radius,
                                 f'soft iron by {100 * matrix_std:.1f} %; keep turning it')
    elif residual > max_residual_pct:
        reason = (f'the turned readings spread by {residual:.1f} % of the field, the bound is '
                  f'{max_residual_pct:.1f} %')
    return GyroAidedFit(not reason, calibration, offset_std, residual, start.raw_residual_pct,
                        start.windows, start.readings, start.turn, reason, start.used,
                        direction_std)


def _full_residuals(x: np.ndarray, readings: np.ndarray, rotations: np.ndarray,
                    starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Each window's turned readings from their mean, and each reading's length from the
    mean length, both relative to that mean: ``x`` is ``G`` and ``d = G b``, so the corrected
    reading ``G m - d`` is linear in it."""
    corrected, scale = _corrected(x, readings)
    if not scale > 0.0:
        return np.full(4 * len(readings), 1e6)
    turned = np.einsum('nij,nj->ni', rotations, corrected)
    spread = turned - _window_means(turned, starts, counts)
    magnitude = np.linalg.norm(corrected, axis=1) / scale - 1.0
    return np.concatenate([(spread / scale).ravel(), magnitude])


def _full_jacobian(x: np.ndarray, readings: np.ndarray, rotations: np.ndarray,
                   starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """``_full_residuals``' derivative: the quotient rule over ``d(G m - d)``, which is the
    reading itself for ``G``'s row and minus one for ``d``."""
    corrected, scale = _corrected(x, readings)
    count = len(readings)
    if not scale > 0.0:
        return np.zeros((4 * count, 12))
    lengths = np.linalg.norm(corrected, axis=1)
    units = corrected / np.where(lengths > 0.0, lengths, 1.0)[:, None]
    change = np.zeros((count, 3, 12))  # d corrected_n[i] / d x
    for row in range(3):
        change[:, row, 3 * row:3 * row + 3] = readings
        change[:, row, 9 + row] = -1.0
    scale_change = np.einsum('ni,nik->k', units, change) / count
    turned = np.einsum('nij,nj->ni', rotations, corrected)
    spread = turned - _window_means(turned, starts, counts)
    turned_change = np.einsum('nij,njk->nik', rotations, change)
    spread_change = turned_change - _window_means(turned_change, starts, counts)
    spread_part = (spread_change / scale
                   - spread[:, :, None] * scale_change[None, None, :] / scale**2)
    length_part = (np.einsum('ni,nik->nk', units, change) / scale
                   - lengths[:, None] * scale_change[None, :] / scale**2)
    return np.concatenate([spread_part.reshape(3 * count, 12), length_part])


def _corrected(x: np.ndarray, readings: np.ndarray) -> tuple[np.ndarray, float]:
    corrected = readings @ x[:9].reshape(3, 3).T - x[9:]
    return corrected, float(np.mean(np.linalg.norm(corrected, axis=1)))


def _window_means(values: np.ndarray, starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Each row's window mean, on rows sorted by window (``starts``: where each begins)."""
    sums = np.add.reduceat(values, starts, axis=0)
    return np.repeat(sums / counts.reshape((-1,) + (1,) * (values.ndim - 1)), counts, axis=0)


def _full_solve(readings: np.ndarray, rotations: np.ndarray, labels: np.ndarray,
                initial: np.ndarray) -> np.ndarray | None:
    """Levenberg-Marquardt from ``initial`` (``G`` and the offset ``b``); solved in ``G`` and
    ``G b``, where the spread is linear, and returned as ``G`` and ``b``."""
    from scipy.optimize import least_squares  # the worker's: nodes start without scipy.optimize
    order = np.argsort(labels, kind='stable')
    readings, rotations, labels = readings[order], rotations[order], labels[order]
    starts = np.flatnonzero(np.r_[True, labels[1:] != labels[:-1]])
    counts = np.diff(np.append(starts, len(readings)))
    linear = initial[:9].reshape(3, 3)
    start = np.concatenate([initial[:9], linear @ initial[9:]])
    try:
        result = least_squares(_full_residuals, start, jac=_full_jacobian, method='lm',
                               x_scale='jac', args=(readings, rotations, starts, counts))
        solution = np.concatenate([result.x[:9],
                                   np.linalg.solve(result.x[:9].reshape(3, 3), result.x[9:])])
    except (ValueError, np.linalg.LinAlgError):
        return None
    return solution if np.all(np.isfinite(solution)) else None


def _normalised(x: np.ndarray) -> np.ndarray:
    """``G`` at unit determinant (its scale is free) and the offset: what the jackknife
    compares."""
    linear = x[:9].reshape(3, 3)
    determinant = np.linalg.det(linear)
    scale = np.cbrt(determinant) if determinant > 0 else 1.0
    return np.concatenate([(linear / scale).reshape(9), x[9:]])


def _calibration(x: np.ndarray, readings: np.ndarray, metadata: dict) -> Calibration:
    """``G = R M`` split by the polar decomposition (a rotation, a symmetric positive definite
    soft iron), ``M`` at unit determinant and ``F`` the corrected readings' median length."""
    from scipy.linalg import polar
    linear = _normalised(x)[:9].reshape(3, 3)
    rotation, matrix = polar(linear)
    if np.linalg.det(rotation) < 0:
        raise CalibrationError('a reflection')
    offset = x[9:]
    radius = float(np.median(np.linalg.norm((readings - offset) @ matrix.T, axis=1)))
    return Calibration(offset, matrix, radius, model='full', rotation=rotation,
                       metadata={**metadata, 'fit': 'gyro_aided'})


def turned_errors(calibration: Calibration | None, data: TurnedReadings) -> np.ndarray:
    """Each reading's distance from its window's field once turned back, relative to the
    field's radius (``calibration`` None: the raw readings): how well a calibration makes the
    field one vector, on readings it may never have seen."""
    readings = np.asarray(data.readings, dtype=float).reshape(-1, 3)
    rotations = np.asarray(data.rotations, dtype=float).reshape(-1, 3, 3)
    labels = np.asarray(data.windows).reshape(-1)
    if calibration is None:
        corrected = readings
        radius = float(np.median(np.linalg.norm(readings, axis=1))) if len(readings) else 1.0
    else:  # in the IMU frame (R M (x - b)): the gyroscope turns that frame
        corrected = (readings - calibration.offset) @ calibration.correction.T
        radius = calibration.field_strength
    turned = np.einsum('nij,nj->ni', rotations, corrected)
    return _from_group_means(turned, labels) / (radius if radius > 0.0 else 1.0)


def turned_direction_errors(calibration: Calibration | None, data: TurnedReadings) -> np.ndarray:
    """Each reading's corrected direction (a unit vector) turned back, its distance from its
    span's mean direction (``data.spans``, else its window's; about radians): how well a
    calibration turns directions as the gyroscope does. Scale-free, so no calibration wins by
    its F; over spans, because a soft iron bends a direction by what the sensor turned, and in
    half a second a hand turns too little for that to rise above the noise (BROAD trial 04: a
    soft iron 5 % worse over 2 s spans was 1 % worse over windows, and went in force)."""
    readings = np.asarray(data.readings, dtype=float).reshape(-1, 3)
    corrected = readings if calibration is None else (
        (readings - calibration.offset) @ calibration.correction.T)
    lengths = np.linalg.norm(corrected, axis=1, keepdims=True)
    directions = corrected / np.where(lengths > 0.0, lengths, 1.0)
    turned = np.einsum('nij,nj->ni', np.asarray(data.rotations, dtype=float).reshape(-1, 3, 3),
                       directions)
    labels = np.asarray(data.windows if data.spans is None else data.spans).reshape(-1)
    return _from_group_means(turned, labels)


def _from_group_means(turned: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Each turned vector's distance from the mean of those sharing its label (its frame)."""
    distances = np.zeros(len(turned))
    for label in np.unique(labels):
        rows = labels == label
        distances[rows] = np.linalg.norm(turned[rows] - turned[rows].mean(axis=0), axis=1)
    return distances


def _centred(readings: np.ndarray, rotations: np.ndarray, labels: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The linear system ``(R_i - mean R) b = R_i m_i - mean (R m)`` of every window with at least
    three readings, and each row's window number (0 ..)."""
    design, target, groups = [], [], []
    turned = np.einsum('nij,nj->ni', rotations, readings)
    for label in np.unique(labels):
        rows = np.flatnonzero(labels == label)
        if len(rows) < 3:
            continue
        design.append((rotations[rows] - rotations[rows].mean(axis=0)).reshape(-1, 3))
        target.append((turned[rows] - turned[rows].mean(axis=0)).reshape(-1))
        groups.append(np.full(3 * len(rows), len(groups)))
    if not design:
        return np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=int)
    return np.vstack(design), np.concatenate(target), np.concatenate(groups)


def _offset_and_mounting(readings: np.ndarray, rotations: np.ndarray, labels: np.ndarray):
    """The offset (least squares) and the rotation into the gyroscope's frame (Kabsch rounds),
    with the last round's centred system (for the jackknife)."""
    design, target, groups = _centred(readings, rotations, labels)
    offset = _solve(design, target)
    mounting = np.eye(3)
    for _ in range(MOUNTING_ITERATIONS if offset is not None else 0):
        previous, mounting = mounting, _mounting(readings - offset, rotations, labels, mounting)
        design, target, groups = _centred(readings, rotations @ mounting, labels)
        offset = _solve(design, target)
        if offset is None or np.max(np.abs(mounting - previous)) < MOUNTING_SETTLED:
            break
    return offset, mounting, design, target, groups


def _consistent_windows(readings: np.ndarray, labels: np.ndarray,
                        offset: np.ndarray) -> np.ndarray:
    """Which readings belong to windows that agree with the rest: a window whose field is
    longer or shorter than the others' by OUTLIER_SIGMAS robust sigmas (over windows) was taken
    with another offset (before a magnet came, after it went) or in a disturbed field. (The
    spread of a window's turned readings grows with how fast it turned: no criterion.)"""
    lengths = np.linalg.norm(readings - offset, axis=1)
    windows = np.unique(labels)
    length = np.array([np.median(lengths[labels == label]) for label in windows])
    centre = float(np.median(length))
    sigma = max(mad_sigma(length), 1e-3 * centre)
    bad = np.abs(length - centre) > OUTLIER_SIGMAS * sigma
    return np.isin(labels, windows[~bad])


def _mounting(centred: np.ndarray, rotations: np.ndarray, labels: np.ndarray,
              mounting: np.ndarray) -> np.ndarray:
    """The rotation Q taking the readings (offset removed) onto their windows' field seen from
    each attitude, ``R_i^T w``: Kabsch's solution (SVD of the cross-covariance)."""
    turned = np.einsum('nij,nj->ni', rotations @ mounting, centred)
    targets = np.zeros_like(centred)
    for label in np.unique(labels):
        rows = labels == label
        targets[rows] = np.einsum('nji,j->ni', rotations[rows], turned[rows].mean(axis=0))
    u, _, vt = np.linalg.svd(targets.T @ centred)
    return u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt


def _solve(design: np.ndarray, target: np.ndarray) -> np.ndarray | None:
    offset, _, rank, _ = np.linalg.lstsq(design, target, rcond=None)
    return offset if rank == 3 and np.all(np.isfinite(offset)) else None


def _jackknife_std(design: np.ndarray, target: np.ndarray, groups: np.ndarray, windows: int,
                   offset: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """Delete-a-group jackknife over consecutive windows: sqrt((g-1)/g sum (b_j - b)^2), and
    the offsets b_j (empty when one could not be solved: an infinite sigma)."""
    count = min(JACKKNIFE_GROUPS, windows)
    group_of_row = groups * count // windows
    estimates = []
    for group in range(count):
        kept = group_of_row != group
        estimate = _solve(design[kept], target[kept])
        if estimate is None:
            return np.full(3, math.inf), []
        estimates.append(estimate)
    deviations = np.asarray(estimates) - offset
    return np.sqrt((count - 1) / count * np.sum(deviations**2, axis=0)), estimates


def _direction_std_deg(readings: np.ndarray, calibration: Calibration,
                       alternatives: list[Calibration]) -> float:
    """The jackknife's sigma of the corrected directions (degrees, RMS over the readings): how
    far the calibrations fitted without each group of windows turn the readings from this one.
    Infinite without alternatives."""
    if not alternatives:
        return math.inf
    corrected = calibration.apply(readings)
    corrected /= np.linalg.norm(corrected, axis=1, keepdims=True)
    squares = []
    for alternative in alternatives:
        other = alternative.apply(readings)
        other /= np.linalg.norm(other, axis=1, keepdims=True)
        cosine = np.clip(np.sum(corrected * other, axis=1), -1.0, 1.0)
        squares.append(float(np.mean(np.degrees(np.arccos(cosine)) ** 2)))
    count = len(alternatives)
    return math.sqrt((count - 1) / count * sum(squares))


def _spread(readings: np.ndarray, rotations: np.ndarray, labels: np.ndarray,
            offset: np.ndarray, matrix: np.ndarray | None = None) -> float:
    corrected = readings - offset if matrix is None else (readings - offset) @ matrix.T
    turned = np.einsum('nij,nj->ni', rotations, corrected)
    if not len(turned):
        return math.nan
    return math.sqrt(float(np.mean(_from_group_means(turned, labels) ** 2)))


def _angle_deg(rotation: np.ndarray) -> float:
    return math.degrees(math.acos(max(-1.0, min(1.0, (float(np.trace(rotation)) - 1.0) / 2.0))))


def _mounting_text(angle: float, most: float) -> str:
    return (f"the magnetometer's axes are turned {angle:.0f} deg from the gyroscope's (more "
            f'than {most:g}): a mounting or axis-remap error')


def _uncertain_text(direction_std: float, most: float, offset_std: np.ndarray, radius: float,
                    hint: str) -> str:
    return (f'the corrected directions are uncertain by {direction_std:.2f} deg (the bound is '
            f'{most:g}; the offset by {_pct(offset_std, radius)} of the field): {hint}')


def _pct(std: np.ndarray, radius: float) -> str:
    return f'{100 * float(np.max(std)) / radius:.1f} %'


__all__ = ['GyroAidedFit', 'TurnedReadings', 'fit_gyro_aided', 'fit_gyro_aided_full',
           'turned_direction_errors', 'turned_errors']
