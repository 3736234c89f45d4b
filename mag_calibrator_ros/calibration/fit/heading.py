# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Heading coverage for yaw-only motion: what a ground robot turning in place can complete.

A robot that can only turn sweeps the field around one circle of directions, a ring of 6-16 of
the 80 direction cells: 3-D coverage never completes, and its hints ask for the roll and pitch a
ground robot cannot make. What turning can complete is the heading circle. This module finds the
ring the readings trace without any calibration (its plane and ellipse by a quick, trimmed
algebraic fit, as ``coverage`` whitens a sphere), says which of the 36 heading sectors it covers
(``coverage.heading_coverage``'s sectors, the ones the ``planar`` fit's gate counts), and phrases
what is missing as a turn: 'turn another 120° to the left'.

Left and right: the heading is measured counter-clockwise about the ring's normal, oriented
towards the sensor axis nearest it (positive), as the ``planar`` fit orients it. A robot turning
left (counter-clockwise seen from above) sees the field turn clockwise in its own frame, so its
heading decreases -- when that sensor axis points up, as a level-mounted sensor's z does in
REP-103 frames. Mounted upside down, left and right swap; the amount to turn does not.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
import math

import numpy as np
from numpy.typing import ArrayLike

from mag_calibrator_ros.calibration.fit.coverage import (
    HEADING_SECTORS,
    MIN_LEVELS,
    RING_THICKNESS,
    SHELL_TOLERANCE,
    STILL_SPREAD,
    Coverage,
    distinct_rows,
    finite_rows,
    readings_barely_change,
    sector_of,
)
from mag_calibrator_ros.calibration.fit.ellipsoid import (
    Normalisation,
    normalise,
    quadric_least_squares,
    robust_sigma,
    sphere_least_squares,
    thickness,
    trimmed_start,
)

YAW_ONLY_THICKNESS = RING_THICKNESS
"""Readings spreading less than this out of their best plane, relative to their spread within
it, come from turning about one axis: the threshold at which the fit's ``auto`` model chooses
``planar`` (FitOptions.planar_thickness's default)."""

RING_TOLERANCE = 2.0 * SHELL_TOLERANCE
"""Largest relative radial scatter of a ring (samples about the quick ellipse, and readings
about its radius). Twice a sphere's: tilting while turning moves tan(inclination) x tilt of the
field in and out of the plane (14 % for 3° at 70°), which only a 3-D fit explains, while a
still sensor's noise scatters by 30-40 % about the rim a kNN buffer keeps."""

ARC_FLATNESS = 0.12
"""...or less than this relative to their largest spread: the arc of the first quarter turn,
whose second spread is only the arc's sagitta (a turning robot's noise and wobble put 3-9 %
out of the plane in its first seconds, 2-5 % once round), so hints speak of turning from the
start. A hand's tumble passes it within a second or two; one mostly about a single axis can stay
near 15 % for seconds, which is why the looser share of the largest spread is not the rule
throughout."""

ARC_LINE = 0.35
"""...or their second spread is less than this share of the largest: the readings so far lie
along one short arc, as every motion begins (a robot's first seconds of turning, noise still as
wide as the arc's sagitta). Nothing yet says the motion is not a turn, so hints speak of turning
rather than ask a robot that may be on the ground to roll."""

RING_LINE = 0.25
"""A flat trace whose second spread is at least this share of the largest is round a ring
(about 100 degrees of it or more), not one short arc: ``motion_shape``."""

COMPLETE_HEADING_COVERAGE = (HEADING_SECTORS - 1) / HEADING_SECTORS
"""The heading circle counts as complete with at most one 10° sector missing: what a full turn
gives, and what the automatic calibration of yaw-only data and ``~/rotate_and_calibrate`` wait
for (an ellipse fitted to part of the circle extrapolates the rest: the gate's ``min_coverage``
still lets ``~/calibrate`` accept half a turn)."""

MIN_RING_POINTS = 12
"""An ellipse has five parameters; fewer distinct points than this outline no ring yet."""

TURNING_MIN_STEP_DEG = 3.0
"""A heading change smaller than this between two looks is refitting jitter, not turning."""

_WHITENING_OUTLIER_SIGMAS = 4.0
_MAX_ELLIPSE_RATIO = 3.0
"""Beyond this axis ratio the quick ellipse is no soft iron (real ratios are below 1.5) but an
arc too short to determine one: a circle stands in for it."""

TURN_HINT_START = 'turn the robot in place: a full turn (360°)'
TURN_STILL_HINT = 'turn the robot in place: the readings barely change'


@dataclass(frozen=True)
class Ring:
    """The ring yaw-only readings trace: ``headings`` of any raw readings on it (radians)."""

    norm: Normalisation
    basis: np.ndarray
    """Columns u, v, n of the ring's plane (normalised input frame), n its normal."""
    centre: np.ndarray
    """The ellipse's centre in (u, v)."""
    whitening: np.ndarray
    """2x2: (u, v) - centre -> the unit circle."""

    @property
    def normal(self) -> np.ndarray:
        return self.basis[:, 2]

    def in_plane(self, points: np.ndarray) -> np.ndarray:
        """(n, 2) whitened in-plane coordinates: unit length on the ring."""
        w = self.norm.forward(np.atleast_2d(points)) @ self.basis
        return (w[:, :2] - self.centre) @ self.whitening.T

    def headings(self, points: ArrayLike) -> np.ndarray:
        """Angle of each reading on the ring, counter-clockwise about the normal (radians)."""
        unit = self.in_plane(np.asarray(points, dtype=float))
        return np.arctan2(unit[:, 1], unit[:, 0])


def yaw_only(samples: ArrayLike) -> bool:
    """Whether the readings lie near one plane, as turning about one axis leaves them, or along
    one short arc so far (see YAW_ONLY_THICKNESS, ARC_FLATNESS and ARC_LINE)."""
    return motion_shape(samples, still_is_few=False) in ('arc', 'ring')


def motion_shape(samples: ArrayLike, still_is_few: bool = True) -> str:
    """What the readings trace: 'ring' (near one plane and round it: turning about one axis),
    'arc' (one short arc so far: any motion begins so, a turn or a tumble), '3d' (off any
    plane) or 'few' (fewer than MIN_RING_POINTS distinct, or a still sensor's noise). Only a
    'ring' can say the motion is yaw-only: a tumble's first arc is as flat as a turn's."""
    points = distinct_rows(finite_rows(samples))
    if len(points) < MIN_RING_POINTS:
        return 'few'
    norm = normalise(points)
    if norm is None or (still_is_few and norm.scale < STILL_SPREAD * float(
            np.linalg.norm(norm.centre))):
        return 'few'  # a still sensor's noise: no motion yet (``yaw_only`` takes an arc in it)
    y = norm.forward(points)
    spreads = np.linalg.eigvalsh(np.cov(y, rowvar=False))
    if not spreads[-1] > 0:
        return 'few'
    smallest, second = (math.sqrt(max(spread, 0.0) / spreads[-1]) for spread in spreads[:2])
    arc = bool(smallest < ARC_FLATNESS or second < ARC_LINE)
    if thickness(y)[0] < YAW_ONLY_THICKNESS:
        return 'arc' if second < RING_LINE else 'ring'
    return 'arc' if arc else '3d'


def fit_ring(samples: ArrayLike, readings: ArrayLike | None = None) -> tuple[Ring | None, str]:
    """(the ring the samples trace, '') or (None, why not) -- no calibration needed.

    The samples must lie on a ring (relative radial scatter at most ``RING_TOLERANCE``), and
    ``readings`` (the readings behind a buffer's samples), when given, on the same ring: a still
    sensor's noise fills the inside of the rim a kNN buffer keeps (see
    ``coverage.shell_directions``).
    """
    points = distinct_rows(finite_rows(samples))
    if len(points) < MIN_RING_POINTS or max(
            len(np.unique(column)) for column in points.T) < MIN_LEVELS:
        return None, TURN_STILL_HINT if len(points) and readings_barely_change(points) else ''
    norm = normalise(points)
    if norm is None:
        return None, TURN_STILL_HINT
    with np.errstate(all='ignore'):
        _, basis = thickness(norm.forward(points))
        basis = basis.copy()
        if np.linalg.det(basis) < 0:
            basis[:, 2] = -basis[:, 2]
        if basis[np.argmax(np.abs(basis[:, 2])), 2] < 0:  # normal toward its nearest axis (+)
            basis[:, [1, 2]] = -basis[:, [1, 2]]
        in_plane = (norm.forward(points) @ basis)[:, :2]
        circle = trimmed_start(in_plane, _circle, _WHITENING_OUTLIER_SIGMAS)
        if circle is None:
            return None, _not_a_ring(points, readings)
        ring = Ring(norm, basis, circle[0], circle[1])
        if len(np.unique(sector_of(ring.headings(points)))) >= HEADING_SECTORS // 2:
            # half the circle or more: an ellipse (soft iron) is determined; on a shorter arc
            # it would be anything, and the circle's headings are the better guess
            ellipse = trimmed_start(in_plane, quadric_least_squares, _WHITENING_OUTLIER_SIGMAS)
            if ellipse is not None:
                eigenvalues = np.linalg.eigvalsh(ellipse[1])
                if 0 < eigenvalues.max() <= _MAX_ELLIPSE_RATIO * eigenvalues.min():
                    ring = Ring(norm, basis, ellipse[0], ellipse[1])
        radius = np.linalg.norm(ring.in_plane(points), axis=1)
        if not robust_sigma(radius - 1.0) <= RING_TOLERANCE:
            return None, _not_a_ring(points, readings)
        evidence = None if readings is None else finite_rows(readings)
        if evidence is not None and len(evidence):
            scatter = robust_sigma(
                np.linalg.norm(ring.in_plane(evidence), axis=1) - 1.0, floor=None)
            if not scatter <= RING_TOLERANCE:
                return None, TURN_STILL_HINT
    return ring, ''


def _circle(points: np.ndarray, weights: np.ndarray | None = None):
    fitted = sphere_least_squares(points, weights)
    return None if fitted is None else (fitted[0], np.eye(points.shape[1]) / fitted[1])


def _not_a_ring(points: np.ndarray, readings: ArrayLike | None) -> str:
    evidence = points if readings is None else finite_rows(readings)
    if len(evidence) and readings_barely_change(evidence):
        return TURN_STILL_HINT
    return ('the readings do not outline a circle of headings: rotate the robot slowly in place, '
            'away from iron, magnets, motors and currents')


@dataclass(frozen=True)
class HeadingCoverage:
    """Heading coverage and what is still to turn."""

    coverage: Coverage
    """36 sectors; its ``hint`` says how far to turn, and which way."""
    ring: Ring | None
    heading: float | None
    """The latest reading's heading (radians), when known."""
    turning: int
    """+1 / -1: the heading has been increasing / decreasing (a right / left turn), 0 unknown."""
    occupied: np.ndarray
    """(36,) bool: the sectors seen."""

    @property
    def complete(self) -> bool:
        return self.coverage.fraction >= COMPLETE_HEADING_COVERAGE


def heading_coverage_of(samples: ArrayLike, readings: ArrayLike | None = None,
                        latest: ArrayLike | None = None, previous: ArrayLike | None = None,
                        turning: int = 0) -> HeadingCoverage:
    """Which heading sectors ``samples`` cover, and the turn still needed from the heading of
    the ``latest`` reading. The direction is the way the heading moved since the ``previous``
    reading (a look ago: both are placed on this ring, whose zero heading is its own), else
    ``turning`` (+1 heading increasing, -1 decreasing, 0 unknown: the shorter way is named)."""
    ring, problem = fit_ring(samples, readings)
    occupied = np.zeros(HEADING_SECTORS, dtype=bool)
    if ring is None:
        hint = problem or TURN_HINT_START
        return HeadingCoverage(Coverage(0.0, 0, HEADING_SECTORS, hint), None, None, turning,
                               occupied)
    occupied[sector_of(ring.headings(finite_rows(samples)))] = True
    heading, before = (None if reading is None else _heading(ring, reading)
                       for reading in (latest, previous))
    turning = turning_direction(before, heading, turning)
    count = int(occupied.sum())
    hint = turn_hint(occupied, heading, turning)
    return HeadingCoverage(Coverage(count / HEADING_SECTORS, count, HEADING_SECTORS, hint), ring,
                           heading, turning, occupied)


def _heading(ring: Ring, reading: ArrayLike) -> float | None:
    rows = finite_rows(reading)
    if len(rows) != 1:
        return None
    value = float(ring.headings(rows)[0])
    return value if math.isfinite(value) else None


def turn_needed(occupied: np.ndarray, heading: float, direction: int) -> int:
    """Degrees to turn from ``heading`` in ``direction`` (+1 / -1 in heading) until every
    empty sector has been passed (0 when none is empty)."""
    empty = np.flatnonzero(~occupied)
    if len(empty) == 0:
        return 0
    here = int(sector_of(np.array([heading]))[0])
    steps = np.mod((empty - here) * direction, HEADING_SECTORS)
    return int(steps.max() + 1) * (360 // HEADING_SECTORS)


def turn_hint(occupied: np.ndarray, heading: float | None, turning: int = 0) -> str:
    """'' when the circle is complete, else e.g. 'turn another 120° to the left'.

    ``turning``: the direction the heading has been moving (+1, -1), 0 when unknown (the
    shorter way is named). Heading decreasing is a left turn (see the module docstring).
    """
    missing = int((~occupied).sum())
    if missing == 0 or missing / HEADING_SECTORS <= 1.0 - COMPLETE_HEADING_COVERAGE + 1e-9:
        return ''
    if missing == HEADING_SECTORS:
        return TURN_HINT_START
    if heading is None:
        degrees = missing * 360 // HEADING_SECTORS
        return f'keep turning in place: {degrees}° of heading not yet seen'
    if turning == 0:
        turning = min((+1, -1), key=lambda d: turn_needed(occupied, heading, d))
    side = 'left' if turning < 0 else 'right'
    return f'turn another {turn_needed(occupied, heading, turning)}° to the {side}'


def turning_direction(previous: float | None, heading: float | None, known: int = 0) -> int:
    """+1 / -1 when the heading moved clearly one way since ``previous``, else ``known``."""
    if previous is None or heading is None:
        return known
    step = math.remainder(heading - previous, 2.0 * math.pi)
    if abs(step) < math.radians(TURNING_MIN_STEP_DEG):
        return known
    return 1 if step > 0 else -1


__all__ = [
    'COMPLETE_HEADING_COVERAGE',
    'ARC_LINE',
    'YAW_ONLY_THICKNESS',
    'HeadingCoverage',
    'Ring',
    'fit_ring',
    'heading_coverage_of',
    'motion_shape',
    'sector_of',
    'turn_hint',
    'turn_needed',
    'turning_direction',
    'yaw_only',
]


PLANE_BAND = 0.25
"""A reading counts as off the plane a planar calibration was turned in when it lies off it by
more than a quarter of the ring's radius (a tilt of about 15°): a floor's wobble of a few degrees
stays inside, a robot picked up or a sensor tumbled does not."""

OFF_PLANE_WINDOW = 200
OFF_PLANE_SHARE = 0.25
"""The motion has left the plane once a quarter of the last 200 readings were off it: sustained
(2 s at 100 Hz), not a bump in the floor."""


class PlaneWatch:
    """Tells when readings leave the plane a planar calibration was fitted in: O(1) a reading.

    A planar calibration knows nothing off its plane, so the buffer screened by it would refuse
    a tumble's readings until the calibration is declared a misfit; the owner stops screening by
    it once the motion has left the plane, so a full calibration can be collected at once.
    """

    def __init__(self, normal: np.ndarray, centre: float, band: float) -> None:
        self._normal = [float(v) for v in normal]
        self._centre = float(centre)
        self._band = float(band)
        self._recent: list[bool] = []
        self._next = 0
        self.off = 0

    @classmethod
    def of(cls, plane_normal: ArrayLike | None, samples: np.ndarray) -> PlaneWatch | None:
        """From a planar calibration's raw plane normal and the samples it was fitted to; None
        when either is unusable."""
        try:
            normal = np.asarray(plane_normal, dtype=float).reshape(3)
        except (TypeError, ValueError):
            return None
        length = float(np.linalg.norm(normal))
        points = finite_rows(samples)
        if not (math.isfinite(length) and length > 0) or len(points) < MIN_RING_POINTS:
            return None
        normal = normal / length
        along = points @ normal
        in_plane = points - np.outer(along, normal)
        radius = float(np.median(np.linalg.norm(in_plane - in_plane.mean(axis=0), axis=1)))
        if not (math.isfinite(radius) and radius > 0):
            return None
        return cls(normal, float(np.median(along)), PLANE_BAND * radius)

    def near(self, points: np.ndarray) -> np.ndarray:
        """Which of ``points`` (n, 3) lie in the plane's band: what a planar calibration can be
        judged on."""
        return np.abs(points @ np.array(self._normal) - self._centre) <= self._band

    def add(self, reading: Sequence[float]) -> bool:
        """Count one reading; True once the motion has left the plane."""
        n = self._normal
        off = abs(reading[0] * n[0] + reading[1] * n[1] + reading[2] * n[2]
                  - self._centre) > self._band
        if len(self._recent) < OFF_PLANE_WINDOW:
            self._recent.append(off)
        else:
            self.off -= self._recent[self._next]
            self._recent[self._next] = off
            self._next = (self._next + 1) % OFF_PLANE_WINDOW
        self.off += off
        return self.off >= OFF_PLANE_SHARE * OFF_PLANE_WINDOW
