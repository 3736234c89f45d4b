# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Before/after pictures of a magnetometer calibration, as PNG files (no display needed).

Top row: the raw samples; bottom row: the corrected samples ``M (raw - b)``. Columns: the XY, YZ
and ZX projections with the reference circle of radius F about the origin (as in the figures of
the gradient-descent notebook, github.com/antsundq/Magnetometer-Auto-Calibration), a 3-D view
with the sphere of radius F, and |field|/F per sample (raw: about the fitted centre) with its
spread. A good calibration puts the corrected points on the circles
and on the sphere of radius F; the raw row shows how far off the sensor was (the fitted centre
``b`` is marked). Outliers found by the fit are drawn as red crosses.

Used by ``mag_calibrator_fit --plot`` and by the demo::

    from mag_calibrator_ros.tools.plotting import plot_calibration
    plot_calibration(raw, result.calibration, 'calibration.png', title='bench test',
                     outliers=result.outliers, units='uT')

Built on ``matplotlib.figure.Figure`` with the Agg canvas, never ``pyplot``: no display, no global
state, safe from any thread.
"""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.calibration.store.safe_file import (
    resolve_path,
    shown_name,
    write_atomically,
)

if TYPE_CHECKING:  # matplotlib (heavy) is imported when a figure is drawn, not with this module
    from matplotlib.figure import Figure

MAX_POINTS = 5000
"""Points drawn per panel; longer recordings are thinned evenly (the fit still used every one)."""
PLANES = ((0, 1, 'XY'), (1, 2, 'YZ'), (2, 0, 'ZX'))
COLUMNS = 5
"""Three projections, the 3-D view, and |field|/F per sample."""
AXIS_NAMES = 'xyz'
BEFORE_COLOUR = 'tab:blue'
AFTER_COLOUR = 'tab:green'
OUTLIER_COLOUR = 'tab:red'
REFERENCE_COLOUR = 'black'


def plot_calibration(
    raw: ArrayLike,
    calibration: Calibration | None,
    path: str | Path,
    *,
    title: str = '',
    outliers: ArrayLike | None = None,
    units: str = '',
    dpi: int = 110,
) -> Path:
    """Write the before/after figure to ``path`` (parent directories are created).

    The format is the name's suffix (``.png``, ``.svg``, ``.pdf`` ...); a new name without one
    gets ``.png``, as matplotlib names it (an existing one is written as it is, in PNG). The
    image is drawn in memory and then replaces the file atomically (:func:`write_atomically`),
    so a failed write leaves no partial image, and only a regular file or a new path is written
    (a device such as /dev/full is refused). ``raw`` (n, 3) in input units; ``calibration``
    None draws the raw row only (nothing was fitted); ``outliers`` an (n,) bool mask from the
    fit. Returns the path written. Raises
    ``FileAccessError`` (a ``ValueError``) when the file cannot be written, ``ValueError`` for a
    format matplotlib cannot write.
    """
    path = Path(path)
    if not path.suffix and not os.path.lexists(path):
        path = path.with_name(path.name + '.png')
    figure = calibration_figure(raw, calibration, title=title, outliers=outliers, units=units)
    image = io.BytesIO()
    figure.savefig(image, dpi=dpi, format=path.suffix[1:].lower() or 'png')
    target = resolve_path(path)
    write_atomically(target, image.getvalue(), shown_name(path, target))
    return path


def calibration_figure(
    raw: ArrayLike,
    calibration: Calibration | None,
    *,
    title: str = '',
    outliers: ArrayLike | None = None,
    units: str = '',
) -> Figure:
    """The figure itself, for callers that want to add to it or save it in another format."""
    samples = np.asarray(raw, dtype=float).reshape(-1, 3)
    finite = np.all(np.isfinite(samples), axis=1)
    mask = np.zeros(len(samples), dtype=bool)
    if outliers is not None:
        given = np.asarray(outliers, dtype=bool).reshape(-1)
        if given.shape == mask.shape:
            mask = given
    keep = _thin(np.flatnonzero(finite))
    samples, mask = samples[keep], mask[keep]

    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    rows = 1 if calibration is None else 2
    figure = Figure(figsize=(21, 4.3 * rows + 0.6), layout='constrained')
    figure.get_layout_engine().set(wspace=0.06)  # room for the 3-D z label (not laid out)
    FigureCanvasAgg(figure)
    if title:
        figure.suptitle(title)
    label = f' [{units}]' if units else ''
    radius = None if calibration is None else calibration.field_strength
    centre = None if calibration is None else calibration.offset
    _draw_row(figure, 0, rows, samples, mask, radius, centre, 'raw', BEFORE_COLOUR, label)
    if calibration is not None:
        corrected = calibration.apply(samples)
        _draw_row(figure, 1, rows, corrected, mask, radius, None,
                  f'corrected ({calibration.model})', AFTER_COLOUR, label)
    return figure


def _thin(indices: np.ndarray) -> np.ndarray:
    if len(indices) <= MAX_POINTS:
        return indices
    return indices[np.linspace(0, len(indices) - 1, MAX_POINTS).round().astype(int)]


def _draw_row(
    figure: Figure, row: int, rows: int, points: np.ndarray, outliers: np.ndarray,
    radius: float | None, centre: np.ndarray | None, name: str, colour: str, units: str,
) -> None:
    inliers = ~outliers
    extent = _extent(points[inliers] if inliers.any() else points, radius)
    for column, (i, j, plane) in enumerate(PLANES):
        axes = figure.add_subplot(rows, COLUMNS, row * COLUMNS + column + 1)
        axes.axhline(0.0, color='0.6', linewidth=0.8)
        axes.axvline(0.0, color='0.6', linewidth=0.8)
        axes.scatter(points[inliers, i], points[inliers, j], s=5, color=colour, alpha=0.6,
                     linewidths=0, label=f'{name} ({int(inliers.sum())})')
        if outliers.any():
            axes.scatter(points[outliers, i], points[outliers, j], s=22, color=OUTLIER_COLOUR,
                         marker='x', linewidths=1.0, label=f'outliers ({int(outliers.sum())})')
        if radius is not None:
            angle = np.linspace(0.0, 2.0 * np.pi, 361)
            axes.plot(radius * np.cos(angle), radius * np.sin(angle), '--',
                      color=REFERENCE_COLOUR, linewidth=1.0,
                      label=f'reference circle F={radius:.4g}')
        if centre is not None:
            axes.plot(centre[i], centre[j], '+', color=OUTLIER_COLOUR, markersize=12,
                      markeredgewidth=2, label='fitted centre b')
        axes.set_xlim(-extent, extent)
        axes.set_ylim(-extent, extent)
        axes.set_aspect('equal')
        axes.set_xlabel(f'{AXIS_NAMES[i]}{units}')
        axes.set_ylabel(f'{AXIS_NAMES[j]}{units}')
        axes.set_title(f'{name}: {plane} projection')
        axes.grid(True, linewidth=0.3)
        if column == 0:
            axes.legend(loc='upper left', fontsize='small', framealpha=0.8)
    _draw_3d(figure, row, rows, points, inliers, outliers, radius, name, colour, units, extent)
    _draw_magnitude(figure, row, rows, points, outliers, radius, centre, name, colour)


def _draw_magnitude(
    figure: Figure, row: int, rows: int, points: np.ndarray, outliers: np.ndarray,
    radius: float | None, centre: np.ndarray | None, name: str, colour: str,
) -> None:
    """|sample - centre| / F per sample: flat at 1 after a good calibration."""
    axes = figure.add_subplot(rows, COLUMNS, row * COLUMNS + 5)
    if centre is None:
        centre = np.zeros(3) if radius is not None else np.mean(points, axis=0)
    magnitude = np.linalg.norm(points - centre, axis=1)
    scale = radius if radius is not None else float(np.median(magnitude)) or 1.0
    relative = magnitude / scale
    index = np.arange(len(points))
    axes.scatter(index[~outliers], relative[~outliers], s=4, color=colour, linewidths=0)
    if outliers.any():
        axes.scatter(index[outliers], relative[outliers], s=22, color=OUTLIER_COLOUR, marker='x')
    axes.axhline(1.0, color=REFERENCE_COLOUR, linestyle='--', linewidth=1.0)
    inlier = relative[~outliers] if (~outliers).any() else relative
    spread = 100.0 * float(np.std(inlier)) if len(inlier) else 0.0
    axes.set_title(f'{name}: |field|/F (std {spread:.2g} %)')
    axes.set_xlabel('sample (plotted order)')
    axes.set_ylabel('|field| / F' if radius is not None else '|field| / median')
    low, high = np.percentile(inlier, [0.5, 99.5]) if len(inlier) else (1.0, 1.0)
    margin = max(0.02, 0.15 * (high - low))
    axes.set_ylim(min(low, 1.0) - margin, max(high, 1.0) + margin)
    axes.grid(True, linewidth=0.3)


def _draw_3d(
    figure: Figure, row: int, rows: int, points: np.ndarray, inliers: np.ndarray,
    outliers: np.ndarray, radius: float | None, name: str, colour: str, units: str,
    extent: float,
) -> None:
    axes = figure.add_subplot(rows, COLUMNS, row * COLUMNS + 4, projection='3d')
    axes.scatter(points[inliers, 0], points[inliers, 1], points[inliers, 2], s=6, color=colour,
                 alpha=0.8, linewidths=0)
    if outliers.any():
        axes.scatter(points[outliers, 0], points[outliers, 1], points[outliers, 2], s=18,
                     color=OUTLIER_COLOUR, marker='x')
    if radius is not None:
        u, v = np.meshgrid(np.linspace(0, 2 * np.pi, 25), np.linspace(0, np.pi, 13))
        axes.plot_wireframe(radius * np.cos(u) * np.sin(v), radius * np.sin(u) * np.sin(v),
                            radius * np.cos(v), color=REFERENCE_COLOUR, linewidth=0.3, alpha=0.25)
    for setter in (axes.set_xlim, axes.set_ylim, axes.set_zlim):
        setter(-extent, extent)
    axes.set_box_aspect((1, 1, 1))
    axes.set_xlabel(f'x{units}')
    axes.set_ylabel(f'y{units}')
    axes.set_zlabel(f'z{units}')
    axes.set_title(f'{name}: 3-D')


def _extent(points: np.ndarray, radius: float | None) -> float:
    """Half-width of a square view about the origin that holds the points and the circle."""
    extent = float(np.max(np.abs(points))) if len(points) else 1.0
    if radius is not None:
        extent = max(extent, radius)
    return 1.08 * extent if extent > 0 else 1.0
