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

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from mag_calibrator_ros.calibration.calibration import Calibration
from mag_calibrator_ros.calibration.ellipsoid import (
    GROSS_OUTLIER_SIGMAS,
    normalise,
    quadric_least_squares,
    robust_sigma,
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
    """(n, 3) float rows with every component finite; empty (0, 3) when the input is unusable."""
    try:
        array = np.asarray(samples, dtype=float)
    except (TypeError, ValueError):
        return np.empty((0, 3))
    if array.ndim == 1 and array.size == 3:
        array = array.reshape(1, 3)
    if array.ndim != 2 or array.shape[1] != 3:
        return np.empty((0, 3))
    return array[np.all(np.isfinite(array), axis=1)]


def whitened_directions(samples: ArrayLike, calibration: Calibration | None = None) -> np.ndarray:
    """Unit field directions (m, 3) in the sensor frame after centring and whitening.

    With a calibration: its corrected directions. Without: a quick trimmed algebraic ellipsoid fit
    when it is plausible, else the median centre and a covariance whitening bounded to ratio 3.
    """
    points = finite_rows(samples)
    if len(points) == 0:
        return np.empty((0, 3))
    with np.errstate(all='ignore'):
        if calibration is not None:
            vectors = calibration.apply(points)
        else:
            vectors = _quick_whiten(points)
        peak = np.max(np.abs(vectors), axis=1, keepdims=True)  # no overflow in the norm
        keep = np.isfinite(peak[:, 0]) & (peak[:, 0] > 0)
        vectors, peak = vectors[keep] / peak[keep], peak[keep, 0]
        radius = np.linalg.norm(vectors, axis=1) * peak
        vectors = vectors / np.linalg.norm(vectors, axis=1, keepdims=True)
        if len(radius) == 0:
            return vectors
        # spikes are no field direction: leave out gross radius outliers (> 10 sigma, > 10 %)
        deviation = radius / np.median(radius) - 1.0
        return vectors[
            np.abs(deviation) <= max(GROSS_OUTLIER_SIGMAS * robust_sigma(deviation), 0.1)
        ]


def _quick_whiten(points: np.ndarray) -> np.ndarray:
    """Centred, whitened vectors without a calibration.

    A trimmed algebraic ellipsoid (spikes do not move it) when plausible, else the median centre
    and a bounded covariance whitening.
    """
    norm = normalise(points)
    if norm is None:
        return np.empty((0, 3))
    y = norm.forward(points)  # the median is at the origin
    with np.errstate(all='ignore'):
        try:
            start = trimmed_start(y, quadric_least_squares, _WHITENING_OUTLIER_SIGMAS)
        except (np.linalg.LinAlgError, ValueError):
            start = None
        if start is not None:
            eigenvalues = np.linalg.eigvalsh(start[1])
            if eigenvalues.max() <= _MAX_WHITENING_RATIO * eigenvalues.min():
                return (y - start[0]) @ start[1]
        if len(y) < 4:
            return y
        eigenvalues, vectors = np.linalg.eigh(np.cov(y, rowvar=False))
        floor = eigenvalues.max() / _MAX_WHITENING_RATIO**2
        scales = 1.0 / np.sqrt(np.maximum(eigenvalues, max(floor, 1e-300)))
        return y @ (vectors * scales) @ vectors.T


def occupied_cells(directions: np.ndarray) -> np.ndarray:
    """Boolean (CELL_COUNT,) mask of the cells holding at least one direction."""
    occupied = np.zeros(CELL_COUNT, dtype=bool)
    if len(directions):
        occupied[cell_index(directions)] = True
    return occupied


def direction_coverage(samples: ArrayLike, calibration: Calibration | None = None) -> Coverage:
    """Share of the 80 equal-area direction cells occupied, with a hint naming the missing
    rotation."""
    directions = whitened_directions(samples, calibration)
    occupied = occupied_cells(directions)
    count = int(occupied.sum())
    return Coverage(count / CELL_COUNT, count, CELL_COUNT, missing_rotation_hint(occupied))


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


def heading_coverage(angles: np.ndarray, normal: np.ndarray) -> Coverage:
    """In-plane coverage for planar motion: share of 36 heading sectors seen, hint about the
    gap."""
    occupied = np.zeros(HEADING_SECTORS, dtype=bool)
    finite = angles[np.isfinite(angles)]
    if finite.size:
        sector = (np.mod(finite, 2.0 * np.pi) / (2.0 * np.pi) * HEADING_SECTORS).astype(int)
        occupied[np.minimum(sector, HEADING_SECTORS - 1)] = True
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
