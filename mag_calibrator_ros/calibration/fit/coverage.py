# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""How much of the sphere of field directions the samples cover, and which rotation would fill the
gaps.

The directions are taken after centring and whitening (with the given calibration, or a quick
algebraic ellipsoid fit, or the mean and a bounded covariance whitening), so hard and soft iron do
not bias the measure. The sphere is split into 80 exactly equal-area cells (zonal bands of equal
height, as in ArduPilot's 80-cell completion mask); coverage is the share of cells holding at least
one sample. It depends only on where the samples point, not on a buffer size or a distance
threshold.

The cells' directions are in the sensor (body) frame: the fitted soft-iron matrix is symmetric, so
it does not rotate. A rotation about a body axis sweeps the field around that axis and can never
bring it onto the axis itself, so empty cells near ``±a`` need rotations about the axes
perpendicular to ``a``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.calibration.fit.ellipsoid import (
    CHUNK_ROWS,
    GROSS_OUTLIER_SIGMAS,
    PARAMETER_COUNTS,
    Normalisation,
    normalise,
    quadric_least_squares,
    robust_sigma,
    sphere_least_squares,
    thickness,
    trimmed_start,
)

BAND_CELLS = (1, 6, 11, 14, 16, 14, 11, 6, 1)
"""Cells per zonal band, north to south. Band height in z is proportional to its cell count, so
every cell has area 4π/80 (Archimedes); these counts make the cells nearly square (about 23°
across)."""

CELL_COUNT = sum(BAND_CELLS)
HEADING_SECTORS = 36
"""In-plane coverage for planar (yaw-only) motion: 10° heading sectors."""

AXIS_NAMES = ('roll axis (x)', 'pitch axis (y)', 'yaw axis (z)')
_BAND_EDGES = 1.0 - 2.0 * np.cumsum((0,) + BAND_CELLS) / CELL_COUNT  # z from +1 down to -1
_BAND_FIRST_CELL = np.cumsum((0,) + BAND_CELLS)[:-1]
_REACH_DEG = 12.0
_WHITENING_OUTLIER_SIGMAS = 4.0
_MAX_WHITENING_RATIO = 3.0
"""A whitening that stretches one axis more than 3x the others is not soft iron (real ratios are <
1.5) but a plane of data: stretching its noise would fake coverage."""
MAX_OFFSET_RATIO = 50.0
"""Without readings to check against (see ``shell_directions``), the largest hard-iron offset, in
field radii, of a shell taken as the field sphere: a last, loose guard against the rim of a still
sensor's noise that a kNN buffer keeps (10-60 radii from zero for noise of 0.5-3 % of the field,
more with an offset). Real offsets reach 15 radii (300 uT on a 22 uT field; the AK09916's
zero-field tolerance alone is +-300 uT), so the bound sits well above them."""
SHELL_TOLERANCE = 0.1
"""Largest relative radial scatter (robust sigma of |v| / median |v| - 1) of centred, whitened
readings that still describe a shell of field directions: twice the fit's residual gate (5 %).
Real sensors in real fields give 0.5-6 % (the shared recordings 0.7-5 %); a still sensor's noise
blob about 40 % however it is fitted (the radii of a 3-D Gaussian cloud), as does a wobble of a
few degrees (a flat noisy patch); the rim of such a blob that a kNN buffer keeps 7-20 %."""
STILL_SPREAD = 0.15
"""For the hint only (no gate): readings scattering by less than this share of their magnitude
barely change, as a still sensor or a small wobble. A tumble with an offset of more than ~5x the
field scatters less, but then it describes a shell and needs no hint."""
STILL_HINT = 'rotate the sensor through many orientations: the readings barely change'
NOT_A_SHELL_HINT = (
    'the readings do not outline a sphere of field directions: rotate the sensor slowly through '
    'many orientations, away from iron, magnets, motors and currents'
)
FEW_HINT = 'too few distinct readings yet: keep rotating the sensor through new orientations'
MIN_LEVELS = 8
"""Fewer distinct values than this on every axis (a still sensor read in counts, or the first few
samples) describe no shell: any sphere fits a handful of quantisation steps exactly."""
RING_THICKNESS = 0.15
"""FitOptions.planar_thickness's default: thinner data are a ring from turning about one axis."""
_FEW_CELLS = 4
"""A wobble of a few degrees seen through a good calibration touches at most about 4 cells."""


@dataclass(frozen=True)
class Coverage:
    """Share of direction cells occupied and, when incomplete, which rotation is missing."""

    fraction: float
    occupied: int
    cells: int
    hint: str


def cell_index(directions: np.ndarray) -> np.ndarray:
    """Equal-area cell of each unit vector (n, 3) -> (n,) int in [0, CELL_COUNT)."""
    z = np.clip(directions[:, 2], -1.0, 1.0)
    band = np.clip(np.searchsorted(-_BAND_EDGES[1:-1], -z, side='right'), 0, len(BAND_CELLS) - 1)
    longitude = np.mod(np.arctan2(directions[:, 1], directions[:, 0]), 2.0 * np.pi)
    counts = np.asarray(BAND_CELLS)[band]
    sector = np.minimum((longitude / (2.0 * np.pi) * counts).astype(int), counts - 1)
    return _BAND_FIRST_CELL[band] + sector


def cell_centres() -> np.ndarray:
    """Unit vector at the (area) centre of every cell, (CELL_COUNT, 3)."""
    centres = []
    for band, count in enumerate(BAND_CELLS):
        z = 0.5 * (_BAND_EDGES[band] + _BAND_EDGES[band + 1])
        if count == 1:
            z = 1.0 if band == 0 else -1.0
        rho = np.sqrt(max(1.0 - z * z, 0.0))
        angles = (np.arange(count) + 0.5) * 2.0 * np.pi / count
        centres.extend(
            np.column_stack([rho * np.cos(angles), rho * np.sin(angles), np.full(count, z)])
        )
    return np.asarray(centres)


_CENTRES = cell_centres()


def finite_rows(samples: ArrayLike) -> np.ndarray:
    """(n, 3) float rows with every component finite (the input itself when all are); empty
    (0, 3) when the input is unusable."""
    try:
        array = np.asarray(samples, dtype=float)
    except (TypeError, ValueError):
        return np.empty((0, 3))
    if array.ndim == 1 and array.size == 3:
        array = array.reshape(1, 3)
    if array.ndim != 2 or array.shape[1] != 3:
        return np.empty((0, 3))
    finite = np.all(np.isfinite(array), axis=1)
    return array if finite.all() else array[finite]


def whitened_directions(
    samples: ArrayLike, calibration: Calibration | None = None, readings: ArrayLike | None = None
) -> np.ndarray:
    """Unit field directions (m, 3) in the sensor frame after centring and whitening.

    With a calibration: its corrected directions. Without: a quick trimmed algebraic ellipsoid fit
    when it is plausible, else a bounded covariance whitening or a sphere fit. Empty when the
    readings do not describe a shell of field directions (see ``shell_directions``).
    """
    return shell_directions(samples, calibration, readings)[0]


def shell_directions(
    samples: ArrayLike, calibration: Calibration | None = None, readings: ArrayLike | None = None
) -> tuple[np.ndarray, str]:
    """(unit directions (m, 3), '') when the samples describe a shell, else (empty, advice).

    Any centring and whitening fitted to the data themselves turns a still sensor's noise blob
    into a ball of "directions" all round, and a kNN buffer fed that blob keeps its rim, a shell
    of a few noise sigmas. So directions are trusted only when the centred, whitened samples lie
    on a shell (relative radial scatter at most ``SHELL_TOLERANCE``) that is the field sphere, not
    a noise rim. ``readings``, when given, are the sensor's own readings behind the samples (e.g.
    ``SampleBuffer.readings``, a random draw of what it was fed): a field puts them all on its
    sphere, so they scatter about the shell within ``SHELL_TOLERANCE`` as the samples do; a still
    sensor's readings fill the inside of the rim of their noise cloud that a kNN buffer keeps
    (measured: median radius 0.75-0.8 of the rim's, scatter about it 30-40 %). That test needs
    no noise level, unit, offset bound or sample order. Without readings, raw readings are their
    own evidence (a noise blob is no shell) and only the loose ``MAX_OFFSET_RATIO`` guards
    against a rim passed in alone.
    """
    points = distinct_rows(finite_rows(samples))
    if len(points) == 0:
        return np.empty((0, 3)), ''
    if not _has_levels(points, MIN_LEVELS):
        # a few quantisation steps (a still sensor read in counts): any shell fits them exactly
        return np.empty((0, 3)), STILL_HINT if readings_barely_change(points) else FEW_HINT
    evidence = None if readings is None else finite_rows(readings)
    if evidence is not None and len(evidence) == 0:
        evidence = None
    filled = False  # some shell was refused because the readings fill its inside
    with np.errstate(all='ignore'):
        max_offset_ratio = MAX_OFFSET_RATIO
        if calibration is not None:
            candidates = [calibration.apply]
        else:
            candidates = _quick_whitenings(points)
            if _is_ring(points):
                # yawing: the ring's radius is the horizontal field only, which can be far below
                # the field, and a noise rim is never flat, so the offset says nothing here
                max_offset_ratio = np.inf
        for whiten in candidates:
            directions, radius = _unit_and_radius(points, whiten)
            if len(radius) == 0:
                continue
            median = np.median(radius)
            deviation = radius / median - 1.0
            if not robust_sigma(deviation) <= SHELL_TOLERANCE:
                continue
            if evidence is not None:
                if not _scatter_about(evidence, whiten, median) <= SHELL_TOLERANCE:
                    filled = True
                    continue
            else:
                zero = whiten(np.zeros((1, 3)))[0]
                if not np.max(np.abs(zero)) / median <= max_offset_ratio:  # max norm: no overflow
                    continue
            # spikes are no field direction: leave out gross radius outliers (> 10 sigma, > 10 %)
            window = max(GROSS_OUTLIER_SIGMAS * robust_sigma(deviation), 0.1)
            kept = np.abs(deviation) <= window
            return (directions if kept.all() else directions[kept]), ''
    still = filled or readings_barely_change(points if evidence is None else evidence)
    return np.empty((0, 3)), STILL_HINT if still else NOT_A_SHELL_HINT


def _scatter_about(
    readings: np.ndarray, whiten: Callable[[np.ndarray], np.ndarray], radius: float
) -> float:
    """Robust relative scatter of the lengths of the whitened ``readings`` about ``radius``
    (not about their own median: readings inside the shell must count against it)."""
    length = _unit_and_radius(readings, whiten)[1]
    if len(length) < len(readings):  # zero or non-finite: a reading at the centre is inside
        length = np.concatenate([length, np.zeros(len(readings) - len(length))])
    return robust_sigma(length / radius - 1.0, floor=None)


def _is_ring(points: np.ndarray) -> bool:
    """True when the readings lie near one plane (yaw only), as the fit's ``planar`` choice."""
    norm = normalise(points)
    return norm is not None and thickness(norm.forward(points))[0] < RING_THICKNESS


def _has_levels(points: np.ndarray, levels: int) -> bool:
    """True when some axis takes at least ``levels`` distinct values (the first rows usually
    show it; all of them are sorted only when they do not)."""
    for column in points.T:
        if len(np.unique(column[: 8 * levels])) >= levels or len(np.unique(column)) >= levels:
            return True
    return False


_ROW_HASH = np.array([0x9E3779B97F4A7C15, 0xC2B2AE3D27D4EB4F, 0x165667B19E3779F9], np.uint64)


PLACE_SHARE = 0.02
"""The cell one place covers: 2 % of the readings' extent (the 1-99 % range of the widest axis:
about 4 % of the field on a whole sphere, 2 deg of direction; spikes left out). Coarse next to
the 23 deg coverage cells and the 5 % residual gate; the mean of a cell's readings lies within
0.1 % of the field's sphere."""


def places(points: np.ndarray, extras: np.ndarray | None = None
           ) -> tuple[np.ndarray, np.ndarray | None]:
    """Finite readings one per place: the mean of those in each PLACE_SHARE cell (and of their
    ``extras`` rows, NaN-aware: gravity's direction behind each), in order of first arrival.

    A recording weighs time, a calibration needs places: a sensor that paused between turns (or
    lay still for most of a log) gives most of its rows from a few places, and every median a
    fit and its gates take of the rows, the robust start's included, is then the pauses'. On
    the BROAD trials with breaks a fit of every row was won by them (F 7.7 uT for 44, coverage
    0 %: "the readings barely change"); one per place they fit as the moving trials do.
    """
    if len(points) < 2:
        return points, extras
    low, high = np.percentile(points, [1.0, 99.0], axis=0)
    size = PLACE_SHARE * float(np.max(high - low))
    if not (size > 0.0 and np.isfinite(size)):
        return points, extras
    cells = np.floor((points - low) / size)
    cells -= cells.min(axis=0)
    spans = cells.max(axis=0) + 1.0
    if float(np.prod(spans)) < 2.0**62:
        key = np.ravel_multi_index(cells.astype(np.int64).T, spans.astype(np.int64))
        _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    else:  # spikes far beyond the extent: cells too many to number
        _, first, inverse = np.unique(cells, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    if len(first) == len(points):
        return points, extras
    order = np.argsort(first)  # places in order of first arrival
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    inverse = rank[inverse]
    counts = np.bincount(inverse, minlength=len(first)).astype(float)
    means = np.stack([np.bincount(inverse, points[:, axis], len(first)) for axis in range(3)],
                     axis=1) / counts[:, None]
    if extras is None:
        return means, None
    known = np.all(np.isfinite(extras), axis=1)
    seen = np.bincount(inverse[known], minlength=len(first)).astype(float)
    with np.errstate(invalid='ignore', divide='ignore'):
        extra_means = np.stack(
            [np.bincount(inverse[known], extras[known, axis], len(first))
             for axis in range(extras.shape[1])], axis=1) / seen[:, None]
    return means, extra_means


def distinct_rows(points: np.ndarray) -> np.ndarray:
    """The rows without repeats, in their first order: a repeated reading is no new evidence of
    a shell (and many repeats would make the robust radial scatter zero).

    Rows are grouped by a hash of their bits (one sort of n integers, block-wise keys: no copy
    of the rows; np.unique(axis=0) would sort the rows themselves, a far slower sort) and compared
    exactly within a group. Returns ``points`` itself when nothing repeats.
    """
    if len(points) < 2:
        return points
    key = np.empty(len(points), dtype=np.uint64)
    for start in range(0, len(points), CHUNK_ROWS):
        block = np.ascontiguousarray(points[start:start + CHUNK_ROWS], dtype=float) + 0.0
        # + 0.0 turns -0.0 into 0.0: equal values, equal bits
        key[start:start + len(block)] = np.bitwise_xor.reduce(
            block.view(np.uint64) * _ROW_HASH, axis=1)
    order = np.argsort(key, kind='stable')  # a repeat follows its first occurrence
    sorted_key = key[order]
    pairs = np.flatnonzero(sorted_key[1:] == sorted_key[:-1])  # (pairs, pairs + 1) share a key
    if len(pairs) == 0:
        return points
    same_row = np.all(points[order[pairs]] == points[order[pairs + 1]], axis=1)
    if not same_row.all():  # a hash collision: fall back on sorting the rows
        first = np.unique(points, axis=0, return_index=True)[1]
        return points[np.sort(first)]
    repeat = np.zeros(len(points), dtype=bool)
    repeat[order[pairs + 1]] = True
    return points[~repeat]


def readings_barely_change(points: np.ndarray) -> bool:
    """True when the readings scatter by less than ``STILL_SPREAD`` of their magnitude.

    Scale-free (any unit): the median distance from the median reading over that reading's
    magnitude, one reading per place (``places``: pauses between turns are no stillness); see
    ``STILL_SPREAD``.
    """
    norm = normalise(places(finite_rows(points))[0])
    if norm is None:
        return True
    magnitude = float(np.linalg.norm(norm.centre / norm.scale)) * norm.scale
    return bool(norm.scale < STILL_SPREAD * magnitude)


def _unit_and_radius(
    points: np.ndarray, whiten: Callable[[np.ndarray], np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors and lengths of the whitened rows that are finite and non-zero (no overflow
    in the norm), block by block."""
    units, lengths = np.empty((len(points), 3)), np.empty(len(points))
    filled = 0
    for start in range(0, len(points), CHUNK_ROWS):
        vectors = whiten(points[start:start + CHUNK_ROWS])
        peak = np.max(np.abs(vectors), axis=1, keepdims=True)
        keep = np.isfinite(peak[:, 0]) & (peak[:, 0] > 0)
        if not keep.all():
            vectors, peak = vectors[keep], peak[keep]
        vectors = vectors / peak
        length = np.linalg.norm(vectors, axis=1)
        units[filled:filled + len(length)] = vectors / length[:, None]
        lengths[filled:filled + len(length)] = length * peak[:, 0]
        filled += len(length)
    return units[:filled], lengths[:filled]


def _quick_whitenings(points: np.ndarray) -> list[Callable[[np.ndarray], np.ndarray]]:
    """Centrings and whitenings fitted without a calibration, most trusted first, each a map from
    raw readings (n, 3) to whitened vectors.

    A trimmed algebraic ellipsoid (spikes do not move it) when its axis ratio is plausible; a
    bounded covariance whitening about the median (a ring from yawing); a sphere fit (few samples,
    or a cap seen from a small rotation). The caller takes the first that describes a shell.
    """
    norm = normalise(points)
    if norm is None:
        return []
    y = norm.forward(points)  # the median is at the origin
    candidates = []
    try:
        start = trimmed_start(y, quadric_least_squares, _WHITENING_OUTLIER_SIGMAS)
    except (np.linalg.LinAlgError, ValueError):
        start = None
    if start is not None:
        eigenvalues = np.linalg.eigvalsh(start[1])
        if eigenvalues.max() <= _MAX_WHITENING_RATIO * eigenvalues.min():
            candidates.append(_affine(norm, start[0], start[1]))
    if len(y) >= 4:
        eigenvalues, vectors = np.linalg.eigh(np.cov(y, rowvar=False))
        floor = eigenvalues.max() / _MAX_WHITENING_RATIO**2
        scales = 1.0 / np.sqrt(np.maximum(eigenvalues, max(floor, 1e-300)))
        candidates.append(_affine(norm, np.zeros(3), (vectors * scales) @ vectors.T))
    if len(y) >= 2 * PARAMETER_COUNTS['sphere']:
        try:
            sphere = sphere_least_squares(y)
        except (np.linalg.LinAlgError, ValueError):
            sphere = None
        if sphere is not None:
            candidates.append(_affine(norm, sphere[0], np.eye(3)))
    return candidates


def _affine(
    norm: Normalisation, centre: np.ndarray, whitening: np.ndarray
) -> Callable[[np.ndarray], np.ndarray]:
    """``x -> (norm.forward(x) - centre) @ whitening``, applicable to any raw readings."""
    return lambda x: (norm.forward(np.atleast_2d(x)) - centre) @ whitening


def occupied_cells(directions: np.ndarray) -> np.ndarray:
    """Boolean (CELL_COUNT,) mask of the cells holding at least one direction."""
    occupied = np.zeros(CELL_COUNT, dtype=bool)
    for start in range(0, len(directions), CHUNK_ROWS):
        occupied[cell_index(directions[start:start + CHUNK_ROWS])] = True
    return occupied


def direction_coverage(
    samples: ArrayLike, calibration: Calibration | None = None, readings: ArrayLike | None = None
) -> Coverage:
    """Share of the 80 equal-area direction cells occupied, with a hint naming the missing
    rotation.

    Samples that describe no shell of field directions (a still sensor, a tiny wobble, a
    disturbed field) cover nothing, and the hint says why. ``readings``: the sensor's readings
    behind ``samples`` when these are a selection (a buffer), see ``shell_directions``.
    """
    directions, problem = shell_directions(samples, calibration, readings)
    if problem:
        return Coverage(0.0, 0, CELL_COUNT, problem)
    occupied = occupied_cells(directions)
    count = int(occupied.sum())
    hint = missing_rotation_hint(occupied)
    evidence = finite_rows(samples if readings is None else readings)
    if 0 < count <= _FEW_CELLS and readings_barely_change(evidence):
        hint = STILL_HINT  # e.g. a still sensor seen through a good calibration: one cell
    return Coverage(count / CELL_COUNT, count, CELL_COUNT, hint)


def missing_rotation_hint(occupied: np.ndarray) -> str:
    """Name the body rotation(s) that would sweep the field through the empty cells ('' when full).

    Rotating about axis a moves the field along a circle of constant angle to a. So an empty cell
    is reachable by rotating about a when some occupied cell lies at about the same angle from a
    (within half a cell, 12°); each axis scores the empty cells it reaches, and the axes within 80%
    of the best are named. Yawing a sensor whose field points along z, for example, reaches
    nothing new. The body direction most of the empty cells lie around is named too.
    """
    empty = _CENTRES[~occupied]
    if len(empty) == 0:
        return ''
    if not occupied.any():
        return 'no usable samples yet: rotate the sensor slowly through all orientations'
    full = _CENTRES[occupied]
    scores = np.zeros(3, dtype=int)
    for axis in range(3):
        empty_angle = np.degrees(np.arccos(np.clip(empty[:, axis], -1.0, 1.0)))
        full_angle = np.degrees(np.arccos(np.clip(full[:, axis], -1.0, 1.0)))
        gap = np.min(np.abs(empty_angle[:, None] - full_angle[None, :]), axis=1)
        scores[axis] = int(np.sum(gap <= _REACH_DEG))
    best = scores.max()
    axes = [AXIS_NAMES[a] for a in range(3) if scores[a] >= 0.8 * best and scores[a] > 0]
    if not axes:
        axes = list(AXIS_NAMES)
    direction = _dominant_missing_direction(empty)
    if len(axes) == len(AXIS_NAMES):
        # every axis reaches the gaps equally (scattered holes): naming all three says nothing
        return (
            'keep rotating through new orientations; the field has not yet pointed along '
            f'{direction}'
        )
    rotation = ' and the '.join(axes)
    return f'keep rotating about the {rotation}; the field has not yet pointed along {direction}'


def _dominant_missing_direction(empty: np.ndarray) -> str:
    """The body direction (e.g. '-z', or '+z and -z') most of the empty cells lie around.

    One-sided gaps (a hemisphere, a cap) have a clear mean direction; two-sided ones (a ring seen
    from yawing) have none, and the axis they spread along is named with both signs.
    """
    mean = empty.mean(axis=0)
    if np.linalg.norm(mean) > 0.1:
        axis = int(np.argmax(np.abs(mean)))
        return f'{"+" if mean[axis] > 0 else "-"}{"xyz"[axis]} of the sensor'
    name = 'xyz'[int(np.argmax((empty**2).mean(axis=0)))]
    return f'+{name} and -{name} of the sensor'


def sector_of(angles: np.ndarray) -> np.ndarray:
    """Heading sector (0..35) of each finite angle (radians): the planar fit's gate and the
    heading coverage of a turning robot (``heading``) count the same sectors."""
    finite = angles[np.isfinite(angles)]
    sector = (np.mod(finite, 2.0 * np.pi) / (2.0 * np.pi) * HEADING_SECTORS).astype(int)
    return np.minimum(sector, HEADING_SECTORS - 1)


def heading_coverage(angles: np.ndarray, normal: np.ndarray) -> Coverage:
    """In-plane coverage for planar motion: share of 36 heading sectors seen, hint about the
    gap."""
    occupied = np.zeros(HEADING_SECTORS, dtype=bool)
    occupied[sector_of(angles)] = True
    count = int(occupied.sum())
    hint = ''
    if count < HEADING_SECTORS:
        finite_normal = np.all(np.isfinite(normal))
        axis = AXIS_NAMES[int(np.argmax(np.abs(normal)))] if finite_normal else 'plane normal'
        missing = HEADING_SECTORS - count
        hint = (
            f'keep turning about the {axis}: {missing * 360 // HEADING_SECTORS}° of heading '
            'not yet seen'
        )
    return Coverage(count / HEADING_SECTORS, count, HEADING_SECTORS, hint)
