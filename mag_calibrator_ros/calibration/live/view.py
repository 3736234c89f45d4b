# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""What a person watching the calibration sees: the buffer, the fitted surface, the directions
covered (MotionCal shows the sphere filling, ArduPilot the cells); the node draws it in RViz."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.calibration.fit.coverage import (
    cell_centres,
    occupied_cells,
    whitened_directions,
)


@dataclass(frozen=True)
class Surface:
    """An ellipsoid ``centre + axes @ u`` over unit vectors ``u`` (axes: columns are the
    semi-axis vectors, a proper rotation times the semi-axis lengths)."""

    centre: np.ndarray
    rotation: np.ndarray
    semi_axes: np.ndarray


@dataclass(frozen=True)
class CalibrationView:
    raw: np.ndarray
    """The buffered points (merged means), input units, (n, 3)."""
    weights: np.ndarray
    """Readings each point stands for, (n,)."""
    corrected: np.ndarray | None
    """The points through the calibration in force, (n, 3), or None while uncalibrated."""
    raw_surface: Surface | None
    """Where |M (x - b)| = F in raw units: the ellipsoid the calibration in force describes."""
    field_strength: float | None
    """F: the corrected points should lie on the sphere of this radius."""
    cell_directions: np.ndarray
    """The 80 equal-area direction cells' centres, (80, 3)."""
    occupied: np.ndarray
    """Which cells the buffer covers, (80,)."""
    anchors: np.ndarray | None = None
    """The reading each point began as, before readings were merged into it, (n, 3)."""


def calibration_surface(calibration: Calibration) -> Surface:
    """The raw-space ellipsoid of ``calibration``: x = b + F M^-1 u."""
    shape = calibration.field_strength * np.linalg.inv(calibration.matrix)
    left, lengths, _ = np.linalg.svd(shape)
    if np.linalg.det(left) < 0.0:  # a proper rotation (the sign of an axis is free)
        left[:, -1] = -left[:, -1]
    return Surface(calibration.offset.copy(), left, lengths)


def calibration_view(samples: np.ndarray, weights: np.ndarray,
                     calibration: Calibration | None,
                     anchors: np.ndarray | None = None) -> CalibrationView:
    """The view of a buffer's ``samples`` (weights: counts; ``anchors``: the readings they began
    as) under ``calibration`` (or none)."""
    samples = np.asarray(samples, dtype=float).reshape(-1, 3)
    occupied = np.zeros(len(cell_centres()), dtype=bool)
    corrected = surface = strength = None
    if calibration is not None:
        corrected = calibration.apply(samples)
        surface = calibration_surface(calibration)
        strength = calibration.field_strength
        norms = np.linalg.norm(corrected, axis=1)
        directions = corrected[norms > 0.0] / norms[norms > 0.0, None]
        occupied = occupied_cells(directions)
    elif len(samples) >= 10:
        occupied = occupied_cells(whitened_directions(samples))
    return CalibrationView(samples, np.asarray(weights, dtype=float).reshape(-1), corrected,
                           surface, strength, cell_centres(), occupied, anchors)


__all__ = ['CalibrationView', 'Surface', 'calibration_surface', 'calibration_view']
