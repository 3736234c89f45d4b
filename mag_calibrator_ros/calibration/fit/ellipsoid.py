# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Ellipsoid fitting maths: algebraic starts, a fast path for clean data, robust refinement.

Every fit runs on normalised data ``y = (x - c) / s`` (``c`` the per-axis median, ``s`` the median
distance to it), so hard-iron offsets many times the field radius and any input unit (T, µT, gauss,
counts) cost no accuracy: the numbers the solvers see are always of order one, in float64. Results
are converted back to input units as ``unit = M (x - b)`` with ``|unit| ≈ 1`` on the data;
fitting.py chooses the output scale.

Models (all fits return an :class:`EllipsoidFit`):

- ``sphere``: hard iron only, ``M = I / r`` (4 parameters).
- ``axis``: the least squares of mag-calibrator-rs ``H = [x, y, z, -y², -z², 1]``, ``w = x²``
  (axis-aligned ellipsoid, 6 parameters), kept as the reference design: algebraic only, no
  geometric refinement, so it measures the method.
- ``full``: hard iron + symmetric soft iron (9 parameters), quadric least-squares start.
- ``planar``: motion confined to a plane (a ground robot yawing). Without a prior: a 2-D ellipse in
  the plane of the data; when the robot tilts a few degrees while turning (every real floor does)
  and that determines it, the 3-D residual with the in-plane parameters and the offset along the
  normal free (see _planar_tilted), else the offset along the normal at the data's mean. With a
  prior: the 3-D residual with only the in-plane parameters free. The normal terms not fitted
  are reported as unobserved.

Every fit ends in the geometric least-squares fit of its inliers: ``e = |M (y - b)| - 1`` over
the points within ``outlier_threshold`` robust sigmas, which are then flagged again. What comes
before depends on the data:

- fast path: the algebraic fit to every point is the start and its inliers are fitted at once,
  refitted until the inliers settle (FAST_PATH_FITS). It stands when the residuals show that
  nothing needed the robust path: hardly any outliers (FAST_PATH_OUTLIERS), none of them among
  the points the fit used beyond GROSS_OUTLIER_SIGMAS, settled inliers, and a plausible shape
  (axis ratio at most 10, as for any start).
  One pass over the points and a few Gauss–Newton steps.
- robust path (otherwise, or ``always_robust``): the algebraic start is least trimmed squares
  (fitted to the 60 % of points nearest the current surface, repeated until that set settles),
  then a robust loss (soft-L1) of ``e`` is minimised, so that spikes cannot bend the fit before
  they are flagged.

On clean data both paths reach the least-squares fit of the same inliers (up to a point on the
border); the robust stage matters when spikes would bend a plain fit, and then the fast path's
own check sends the fit down the robust one.

Solvers: Levenberg–Marquardt on the normal equations (at most 9 parameters), accumulated over
blocks of CHUNK_ROWS rows, iteratively reweighted for soft-L1. They find the minima
``scipy.optimize.least_squares`` finds (method 'lm', and 'trf' with ``loss='soft_l1'``) without
ever forming an n x p Jacobian, so millions of rows fit in bounded memory, and without importing
scipy.optimize (a heavy import) where a node or a command line starts. Algebraic fits solve their
normal equations from the moment matrix of the monomials (x², xy, ..., x, 1): one pass over the
rows serves the sphere, the quadric and the axis fits alike. Where the normal equations would
square an ill-conditioned Jacobian (condition above EXACT_CONDITION), its condition number and
the parameter errors come from a QR factorisation of the Jacobian itself.

Optional ``weights`` (one per point, > 0) weight every least-squares step and the robust loss: a
point that stands for the average of ``n`` readings (SampleBuffer merges nearby samples) has ``n``
times less noise variance, so it gets weight ``n``. Outliers are flagged on the plain residual
against the robust sigma of one reading (residual x sqrt(weight)): a lone spike is flagged as
without weights, and an averaged point is never flagged merely because the model's misfit exceeds
its reduced noise. The condition number stays that of the plain Jacobian: weights say how
precisely a point is known, not whether the points determine the model.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
import math
from statistics import NormalDist

import numpy as np

from mag_calibrator_ros.calibration.fit.robust import mad_sigma

FIT_MODELS = ('sphere', 'axis', 'full', 'planar')
PARAMETER_COUNTS = {'sphere': 4, 'axis': 6, 'full': 9, 'planar': 5}

MIN_ROBUST_SIGMA = 1e-4
"""Floor of the robust residual sigma (relative to the radius). Below 0.01 % no magnetometer is
that quiet (16-bit quantisation alone is larger), and without a floor noiseless data would flag
rounding as outliers."""

GROSS_OUTLIER_SIGMAS = 10.0
"""Points this many robust sigmas off the start surface never enter the robust fit: soft-L1 grows
without bound, and a few spikes many radii away could otherwise bend M into a hyperboloid through
them. One such point also sends a fit down the robust path."""

FAST_PATH_OUTLIERS = 1e-3
"""Largest share of the points a fast-path fit may flag as outliers (one is always allowed if the
fit did not use it): Gaussian noise puts 0.006 % beyond 4 sigma, so more means spikes or a
heavy-tailed disturbance, whose inliers the robust path judges on a fit they did not bend. Of
the points the fit used, as many may turn out beyond the border (none in a buffer of 100)."""

FAST_PATH_FITS = 3
"""Least-squares fits the fast path may take for its inliers to settle: the start's inliers, then
each fit's, until only points on the BORDER move."""

BORDER = (0.8, 1.25)
"""Residuals within these factors of ``outlier_threshold`` robust sigmas are on the border: a fit
whose inliers differ from the points it used only there has settled (on clean data a point or
two cross it as the fit moves from its start to the least-squares fit, on either path)."""

CHUNK_ROWS = 1 << 11
"""Rows per block in every pass over the points: temporaries stay in the cache however many rows
(a 2-million-row Jacobian alone would take 144 MB). Sized for the fits the node and the command
line run most, thousands to tens of thousands of rows: larger blocks only pay off on millions."""

GRAM_ROWS = 1 << 11
"""Rows per matrix product of a block's columns with themselves (10 x 2048 x 10): below
OpenBLAS's threading threshold. Its threads, spinning between calls, only compete with the main
one for products this small, the more so on a busy machine with few cores."""

EXACT_CONDITION = 1e6
"""Above this condition number the normal equations (which square it) lose the smallest singular
value to rounding; the condition and parameter errors are then taken from a QR factorisation."""

_LEAST_SQUARES_ITERATIONS = 100
_LEAST_SQUARES_TOLERANCE = 1e-12
_ROBUST_ITERATIONS = 50
_ROBUST_TOLERANCE = 1e-8
DIVERGED_CONDITION = 1000.0
"""A fit whose Jacobian's condition number passes 1000 while it rises is walking where the
readings determine nothing (a cap of the sphere fits ever larger ellipsoids: the minimum is at
infinity), and its iterations stop. 66x the fit's gate (15 by default; FitOptions keeps
``max_condition`` below this): no fit that passed it on the shared recordings and benchmarks
started above 100."""


def _spans(n: int) -> Iterator[slice]:
    """Consecutive blocks of at most CHUNK_ROWS rows covering ``range(n)``."""
    for start in range(0, n, CHUNK_ROWS):
        yield slice(start, min(start + CHUNK_ROWS, n))


def _norms(vectors: np.ndarray) -> np.ndarray:
    """``|v|`` of every row of a block."""
    return np.sqrt(np.einsum('ij,ij->i', vectors, vectors))


def row_norms(vectors: np.ndarray) -> np.ndarray:
    """``|v|`` of every row, block by block."""
    norms = np.empty(len(vectors))
    for span in _spans(len(vectors)):
        norms[span] = _norms(vectors[span])
    return norms


def radial_residuals(points: np.ndarray, centre: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """``|M (p - c)| - 1`` of every row (M symmetric), block by block."""
    radii = np.empty(len(points))
    for span in _spans(len(points)):
        radii[span] = _norms((points[span] - centre) @ matrix)
    return radii - 1.0


@dataclass(frozen=True)
class Normalisation:
    """``y = (x - centre) / scale``: data of order one whatever the offset and unit."""

    centre: np.ndarray
    scale: float

    def forward(self, points: np.ndarray) -> np.ndarray:
        return (points - self.centre) / self.scale


def normalise(points: np.ndarray) -> Normalisation | None:
    """Median centre and median distance; None when the points do not spread (all equal)."""
    if len(points) == 0:
        return None
    centre = np.median(points, axis=0)
    with np.errstate(all='ignore'):  # an overflowing spread is refused below, not warned about
        peaks = [np.max(np.abs(points[span] - centre)) for span in _spans(len(points))]
        peak = float(np.max(peaks))
        if not np.isfinite(peak) or peak <= 1e-12 * max(float(np.max(np.abs(centre))), 1e-300):
            return None
        distances = np.empty(len(points))
        for span in _spans(len(points)):  # pre-scaled: no overflow
            distances[span] = np.linalg.norm((points[span] - centre) / peak, axis=1) * peak
    scale = float(np.median(distances))
    if not np.isfinite(scale) or scale <= 0.0:
        scale = float(np.mean(distances))
    if not np.isfinite(scale) or scale <= 0.0:
        return None
    return Normalisation(centre, scale)


@dataclass(frozen=True)
class EllipsoidFit:
    """A fit in input units: ``unit = matrix @ (x - offset)`` has ``|unit| ≈ 1`` on the inliers.

    ``residuals`` are ``|unit| - 1`` for every point given (in the plane for ``planar``),
    ``inliers`` marks the points of the final fit, ``condition`` is the condition number of the
    final (normalised) Jacobian, ``radius`` the volume-equivalent radius ``det(matrix)^(-1/3)`` in
    input units, ``axis_ratio`` longest over shortest fitted semi-axis (in the plane for
    ``planar``; inf when not positive definite). ``parameter_std`` holds 1-sigma standard
    deviations in input units when known. ``headings`` (planar only) is each point's angle in the
    fitted plane. ``robust`` says whether the robust stage ran (False: the fast path).
    """

    model: str
    offset: np.ndarray
    matrix: np.ndarray
    residuals: np.ndarray
    inliers: np.ndarray
    condition: float
    radius: float
    axis_ratio: float
    parameter_std: dict[str, list[float]] | None = None
    unobserved: tuple[str, ...] = ()
    plane_normal: np.ndarray | None = None
    headings: np.ndarray | None = field(default=None, repr=False)
    robust: bool = True
    levelled: bool = False
    """planar: levelled by gravity (levelled.py)."""
    dip_deg: float | None = None
    """The inclination a levelled fit determined from the tilts, else None."""
    normal_offset_std: float | None = None
    """A levelled fit's 1-sigma of its offset along the normal, relative to the field, from its
    own readings (None: not levelled, or the offset held)."""


def thickness(y: np.ndarray) -> tuple[float, np.ndarray]:
    """How far the data leave their best plane: sqrt(smallest / middle covariance eigenvalue).

    About 1 for data all round a sphere, about the relative noise for a ring (yaw only), 0.5 for a
    hemisphere. Gross outliers (far from the unit sphere the normalisation centred) are left out,
    or a few spikes would make a ring look three-dimensional. Also returns the eigenvectors
    (columns, largest variance first; the last is the normal).
    """
    distance = row_norms(y) - 1.0
    window = max(GROSS_OUTLIER_SIGMAS * robust_sigma(distance), 0.2)
    kept = np.abs(distance) <= window
    if np.count_nonzero(kept) < 3:
        return 0.0, np.eye(3)
    eigenvalues, vectors = np.linalg.eigh(_covariance(y, kept))
    eigenvalues, vectors = eigenvalues[::-1], vectors[:, ::-1]
    if eigenvalues[1] <= 0:
        return 0.0, vectors
    return float(np.sqrt(max(eigenvalues[2], 0.0) / eigenvalues[1])), vectors


def _covariance(points: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """np.cov of the rows in ``mask`` (two passes, block by block: no copy of the rows)."""
    count = int(np.count_nonzero(mask))
    total = np.zeros(points.shape[1])
    for span in _spans(len(points)):
        total += np.compress(mask[span], points[span], axis=0).sum(axis=0)
    mean = total / count
    scatter = np.zeros((points.shape[1], points.shape[1]))
    for span in _spans(len(points)):
        centred = np.compress(mask[span], points[span], axis=0) - mean
        scatter += centred.T @ centred
    return scatter / (count - 1)


# -----------------------------------------------------------------------------------------------
# Algebraic fits (on normalised data), all from the moments of the monomials


def _weighted_lstsq(
    design: np.ndarray, target: np.ndarray, weights: np.ndarray | None
) -> np.ndarray:
    """Least squares with each row scaled by sqrt(weight) (plain when ``weights`` is None)."""
    if weights is not None:
        root = np.sqrt(weights)
        design, target = design * root[:, None], target * root
    return np.linalg.lstsq(design, target, rcond=None)[0]


def _monomials(points: np.ndarray) -> np.ndarray:
    """Per row ``[p_i p_j (i <= j), p_i, 1]``: every algebraic design here is linear in them."""
    d = points.shape[1]
    quadratic = d * (d + 1) // 2
    block = np.empty((len(points), quadratic + d + 1))
    for k, (i, j) in enumerate(zip(*np.triu_indices(d), strict=True)):
        np.multiply(points[:, i], points[:, j], out=block[:, k])
    block[:, quadratic : quadratic + d] = points
    block[:, -1] = 1.0
    return block


def _gram(columns: np.ndarray, weights: np.ndarray | None) -> np.ndarray:
    """``columnsᵀ W columns``, GRAM_ROWS rows per product (see there)."""
    gram = np.zeros((columns.shape[1], columns.shape[1]))
    for start in range(0, len(columns), GRAM_ROWS):
        part = columns[start:start + GRAM_ROWS]
        weighted = part if weights is None else part * weights[start:start + GRAM_ROWS, None]
        gram += weighted.T @ part
    return gram


def moments(points: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """``sum w m mᵀ`` over the rows' monomials ``m``: all an algebraic fit needs of the data."""
    d = points.shape[1]
    size = d * (d + 1) // 2 + d + 1
    gram = np.zeros((size, size))
    for span in _spans(len(points)):
        gram += _gram(_monomials(points[span]), None if weights is None else weights[span])
    return gram


@dataclass(frozen=True)
class _Design:
    """An algebraic least-squares problem ``min sum w (m A s - m t)²`` in the monomials ``m``."""

    design: np.ndarray  # (monomials, unknowns)
    target: np.ndarray  # (monomials,)

    def solve(self, gram: np.ndarray) -> np.ndarray:
        """The minimum-norm least-squares solution, from the normal equations."""
        normal = self.design.T @ gram @ self.design
        right = self.design.T @ gram @ self.target
        return np.linalg.lstsq(normal, right, rcond=None)[0]


def _quadric_design(d: int) -> _Design:
    """``pᵀ A p + 2 gᵀ p = 1``: unknowns upper(A) (off-diagonal counted twice) and g."""
    n_quadratic = d * (d + 1) // 2
    rows, cols = np.triu_indices(d)
    design = np.zeros((n_quadratic + d + 1, n_quadratic + d))
    design[np.arange(n_quadratic), np.arange(n_quadratic)] = np.where(rows == cols, 1.0, 2.0)
    design[n_quadratic + np.arange(d), n_quadratic + np.arange(d)] = 2.0
    target = np.zeros(n_quadratic + d + 1)
    target[-1] = 1.0
    return _Design(design, target)


def _sphere_design(d: int) -> _Design:
    """``|p|² = 2 b·p + c``: unknowns b and c."""
    n_quadratic = d * (d + 1) // 2
    rows, cols = np.triu_indices(d)
    design = np.zeros((n_quadratic + d + 1, d + 1))
    design[n_quadratic + np.arange(d), np.arange(d)] = 2.0
    design[-1, d] = 1.0
    target = np.zeros(n_quadratic + d + 1)
    target[:n_quadratic][rows == cols] = 1.0
    return _Design(design, target)


def _axis_design() -> _Design:
    """mag-calibrator-rs: ``H = [x, y, z, -y², -z², 1]``, ``w = x²`` (monomials of d = 3)."""
    design = np.zeros((10, 6))
    design[[6, 7, 8], [0, 1, 2]] = 1.0  # x, y, z
    design[[3, 5], [3, 4]] = -1.0  # -y², -z²
    design[9, 5] = 1.0
    target = np.zeros(10)
    target[0] = 1.0  # x²
    return _Design(design, target)


_QUADRIC = {d: _quadric_design(d) for d in (2, 3)}
_SPHERE = {d: _sphere_design(d) for d in (2, 3)}
_AXIS = _axis_design()


def sphere_least_squares(
    y: np.ndarray, weights: np.ndarray | None = None
) -> tuple[np.ndarray, float] | None:
    """Linear circle/sphere fit ``|y|² = 2 b·y + c``: (centre, radius)."""
    return _sphere_from_moments(moments(y, weights), y.shape[1])


def _sphere_from_moments(gram: np.ndarray, d: int) -> tuple[np.ndarray, float] | None:
    solution = _SPHERE[d].solve(gram)
    centre = solution[:-1]
    radius_sq = solution[-1] + centre @ centre
    if not np.isfinite(radius_sq) or radius_sq <= 0:
        return None
    return centre, float(np.sqrt(radius_sq))


def quadric_least_squares(
    points: np.ndarray, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray] | None:
    """Algebraic ellipse/ellipsoid ``pᵀ A p + 2 gᵀ p = 1``: (centre, M) with M = sqrt(A / k).

    None unless the conic is an ellipse/ellipsoid (A/k positive definite).
    """
    return _quadric_from_moments(moments(points, weights), points.shape[1])


def _quadric_from_moments(gram: np.ndarray, d: int) -> tuple[np.ndarray, np.ndarray] | None:
    solution = _QUADRIC[d].solve(gram)
    rows, cols = np.triu_indices(d)
    a = np.zeros((d, d))
    a[rows, cols] = solution[: len(rows)]
    a[cols, rows] = solution[: len(rows)]
    g = solution[len(rows) :]
    try:
        centre = -np.linalg.solve(a, g)
    except np.linalg.LinAlgError:
        return None
    k = 1.0 + centre @ a @ centre
    if not np.isfinite(k) or k <= 0:
        return None
    matrix = _symmetric_sqrt(a / k)
    if matrix is None:
        return None
    return centre, matrix


def axis_least_squares(
    y: np.ndarray, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray] | None:
    """The least squares of mag-calibrator-rs (geometrikal): (offset, semi-axes).

    ``H = [x, y, z, -y², -z², 1]``, ``w = x²``, ``X = (HᵀH)⁻¹Hᵀw``, done here in float64 on
    normalised data (the library's float32 on raw data fails once the offset exceeds a few field
    radii).
    """
    x = _AXIS.solve(moments(y, weights))
    if x[3] <= 0 or x[4] <= 0:
        return None
    offset = np.array([x[0] / 2.0, x[1] / (2.0 * x[3]), x[2] / (2.0 * x[4])])
    temp = x[5] + offset[0] ** 2 + x[3] * offset[1] ** 2 + x[4] * offset[2] ** 2
    if not np.isfinite(temp) or temp <= 0:
        return None
    scale = np.sqrt([temp, temp / x[3], temp / x[4]])
    return offset, scale


TRIMMED_SHARE = 0.6
"""Share of points the algebraic start is fitted to (least trimmed squares): up to 40 % spikes
(a buffer that keeps far-out samples can hold that many) cannot pull it."""
_TRIMMED_MEDIAN = NormalDist().inv_cdf(0.5 + TRIMMED_SHARE / 4)

SETTLED_CHANGE = 1e-3
"""A concentration step that moves the centre and matrix by less than this (0.1 % of the
normalised radius) ends the trimming: on many points thousands swap across the 60 % border from
step to step without moving the fit, and the robust fit that follows finds its own minimum."""

Algebraic = Callable[[np.ndarray, np.ndarray | None], tuple[np.ndarray, np.ndarray] | None]


def trimmed_start(
    points: np.ndarray,
    algebraic: Algebraic,
    threshold: float,
    weights: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray] | None:
    """An algebraic fit that spikes cannot ruin (in plain least squares they enter squared).

    Least trimmed squares by concentration steps: from the unit sphere about the median (where
    the normalisation put the data), fit the ``TRIMMED_SHARE`` of points closest to the current
    surface, repeat until that set or the fit settles (SETTLED_CHANGE); then refit once on every
    point within ``threshold`` robust sigmas of it, for an efficient start when there are few
    outliers.
    """
    d = points.shape[1]
    n_needed = 2 * (d + 1 + d * (d + 1) // 2)
    n_kept = max(int(np.ceil(TRIMMED_SHARE * len(points))), n_needed)
    if len(points) < n_needed:
        return None
    centre, matrix = np.zeros(d), np.eye(d)
    best = None
    kept = np.zeros(len(points), dtype=bool)
    for _ in range(8):
        residuals = np.abs(radial_residuals(points, centre, matrix))
        new_kept = np.zeros(len(points), dtype=bool)
        new_kept[np.argpartition(residuals, n_kept - 1)[:n_kept]] = True
        settled = np.count_nonzero(new_kept != kept) <= max(2, len(points) // 50)
        kept = new_kept
        if settled and best is not None:
            break
        fitted = algebraic(points[kept], _part(weights, kept))
        if fitted is None or _ratio(fitted[1]) > 10.0:
            break
        moved = max(np.max(np.abs(fitted[0] - centre)), np.max(np.abs(fitted[1] - matrix)))
        best = centre, matrix = fitted
        if moved <= SETTLED_CHANGE:
            break  # the fit stands still while points on the trimming border keep swapping
    if best is None:
        return None
    residuals = radial_residuals(points, centre, matrix)
    # the kept residuals are the smallest ones: their median is the TRIMMED_SHARE/2 quantile of |e|
    sigma = max(float(np.median(np.abs(residuals[kept]))) / _TRIMMED_MEDIAN, MIN_ROBUST_SIGMA)
    inliers = np.abs(residuals) <= threshold * sigma
    if inliers.sum() >= n_needed:
        refitted = algebraic(points[inliers], _part(weights, inliers))
        if refitted is not None and _ratio(refitted[1]) <= 10.0:
            return refitted
    return best


def _plain_start(
    points: np.ndarray, algebraic: Algebraic, weights: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray] | None:
    """The algebraic fit to every point, the fast path's start (None when implausible)."""
    plain = algebraic(points, weights)
    return plain if plain is not None and _ratio(plain[1]) <= 10.0 else None


def _weigh(residuals: np.ndarray, weights: np.ndarray | None) -> np.ndarray:
    """Residuals in units of one reading's noise: a point of weight w averages w readings."""
    return residuals if weights is None else residuals * np.sqrt(weights)


def _part(weights: np.ndarray | None, mask: np.ndarray) -> np.ndarray | None:
    return None if weights is None else weights[mask]


def _sphere_start(
    points: np.ndarray, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray] | None:
    fitted = sphere_least_squares(points, weights)
    return None if fitted is None else (fitted[0], np.eye(points.shape[1]) / fitted[1])


def _symmetric_sqrt(a: np.ndarray) -> np.ndarray | None:
    a = 0.5 * (a + a.T)
    if not np.all(np.isfinite(a)):
        return None
    eigenvalues, vectors = np.linalg.eigh(a)
    if eigenvalues.min() <= 0:
        return None
    return (vectors * np.sqrt(eigenvalues)) @ vectors.T


# -----------------------------------------------------------------------------------------------
# Geometric residual |M (p - b)| - 1 and its Jacobian; d = 2 or 3; M = rho I (sphere) or symmetric


class _Geometric:
    """Residuals of ``|M (p - b)| - 1`` over parameters [b, upper(M)] and the normal equations of
    their analytic Jacobian, block by block.

    ``free`` (indices into that vector) optimises only some parameters, the others held at
    ``base``: the planar model with a prior frees the in-plane ones.
    """

    def __init__(
        self,
        points: np.ndarray,
        spherical: bool,
        free: np.ndarray | None = None,
        base: np.ndarray | None = None,
    ) -> None:
        self.points = points
        self.d = points.shape[1]
        self.spherical = spherical
        self.rows, self.cols = np.triu_indices(self.d)
        self.free = free
        self.base = base

    def pack(self, centre: np.ndarray, matrix: np.ndarray) -> np.ndarray:
        if self.spherical:
            return np.append(centre, np.mean(np.diag(matrix)))
        params = np.concatenate([centre, matrix[self.rows, self.cols]])
        return params if self.free is None else params[self.free]

    def unpack(self, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.free is not None:
            full = self.base.copy()
            full[self.free] = params
            params = full
        centre = params[: self.d]
        if self.spherical:
            return centre, params[self.d] * np.eye(self.d)
        matrix = np.zeros((self.d, self.d))
        matrix[self.rows, self.cols] = params[self.d :]
        matrix[self.cols, self.rows] = params[self.d :]
        return centre, matrix

    def residuals(self, params: np.ndarray) -> np.ndarray:
        return radial_residuals(self.points, *self.unpack(params))

    def _jacobian(
        self, z: np.ndarray, w: np.ndarray, radius: np.ndarray, matrix: np.ndarray
    ) -> np.ndarray:
        """Jacobian rows for a block (``z = p - b``, ``w = M z``, ``radius = |w|``):
        ``d|w|/db = -M g``, ``d|w|/dM_ij = g_i z_j + g_j z_i`` (``g_i z_i`` on the diagonal),
        ``d|w|/drho = |z|`` (sphere), with ``g = w / |w|``."""
        d = self.d
        g = w / np.maximum(radius, 1e-300)[:, None]
        jacobian = np.empty((len(z), d + (1 if self.spherical else len(self.rows))))
        np.matmul(g, -matrix, out=jacobian[:, :d])
        if self.spherical:
            jacobian[:, d] = _norms(z)
        else:
            for k, (i, j) in enumerate(zip(self.rows, self.cols, strict=True)):
                column = jacobian[:, d + k]
                np.multiply(g[:, i], z[:, j], out=column)
                if i != j:
                    column += g[:, j] * z[:, i]
        return jacobian if self.free is None else jacobian[:, self.free]

    def _blocks(
        self, params: np.ndarray, mask: np.ndarray, weights: np.ndarray | None
    ) -> Iterator[tuple[slice, np.ndarray, np.ndarray, np.ndarray]]:
        """Per block: (rows, residuals, Jacobian, row weights: the weights times the mask)."""
        centre, matrix = self.unpack(params)
        for span in _spans(len(self.points)):
            z = self.points[span] - centre
            w = z @ matrix
            radius = _norms(w)
            row_weights = mask[span].astype(float)
            if weights is not None:
                row_weights *= weights[span]
            yield span, radius - 1.0, self._jacobian(z, w, radius, matrix), row_weights

    def evaluate(
        self,
        params: np.ndarray,
        mask: np.ndarray,
        weights: np.ndarray | None = None,
        f_scale: float | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One pass: every row's residual ``e``, and the Gauss–Newton system over the rows in
        ``mask`` (weights W, 1 without): ``JᵀWJ`` and ``JᵀWe`` for least squares; for soft-L1
        of scale ``f_scale``, with ``s = 1 + e²/f²``, the curvature ``JᵀW s^-1.5 J`` and the
        gradient ``JᵀW s^-0.5 e`` of its loss (the loss's second derivative included, as scipy's
        least_squares does: far fewer steps than plain reweighting when residuals are large)."""
        size = len(self.pack(*self.unpack(params)))
        residuals = np.empty(len(self.points))
        augmented = np.zeros((size + 1, size + 1))  # [J e']ᵀ U [J e']: one product per block
        for span, block_residuals, jacobian, row_weights in self._blocks(params, mask, weights):
            residuals[span] = block_residuals
            scaled = block_residuals
            if f_scale is not None:
                stretch = 1.0 + (block_residuals / f_scale) ** 2
                row_weights = row_weights / (stretch * np.sqrt(stretch))
                scaled = block_residuals * stretch
            augmented += _gram(np.column_stack([jacobian, scaled]), row_weights)
        return residuals, augmented[:size, :size], augmented[:size, size]

    def triangular_factor(
        self, params: np.ndarray, mask: np.ndarray, weights: np.ndarray | None
    ) -> np.ndarray:
        """R of ``sqrt(U) J = Q R`` (p x p) over the rows in ``mask``, block by block (TSQR)."""
        size = len(self.pack(*self.unpack(params)))
        factor = np.zeros((0, size))
        for _, _, jacobian, row_weights in self._blocks(params, mask, weights):
            rows = jacobian * np.sqrt(row_weights)[:, None]
            factor = np.linalg.qr(np.vstack([factor, rows]), mode='r')
        padded = np.zeros((size, size))
        padded[: len(factor)] = factor
        return padded


def robust_sigma(
    residuals: np.ndarray, *, about_median: bool = False, floor: float | None = MIN_ROBUST_SIGMA
) -> float:
    """The normal sigma a median absolute deviation stands for: 1.4826 x median |residual|.

    The one robust scale of the package; its callers differ in two ways, chosen here explicitly:

    - ``about_median=False`` (default) measures the deviations about zero: residuals of a fitted
      surface, where zero *is* the expected value and a shifted median is itself an error.
      ``about_median=True`` subtracts the values' own median first (the classical MAD), for
      values whose centre is unknown (dips of a candidate rotation, say).
    - ``floor`` (default MIN_ROBUST_SIGMA) bounds the sigma below, so that noiseless data do not
      flag rounding as outliers; it also answers for no residuals at all. ``floor=None`` returns
      the bare value (NaN for none), for comparing a scatter against a tolerance.
    """
    if floor is not None and residuals.size == 0:
        return floor
    sigma = mad_sigma(residuals, about_median=about_median)
    return sigma if floor is None else max(sigma, floor)


def _minimise(
    model: _Geometric,
    params: np.ndarray,
    mask: np.ndarray,
    weights: np.ndarray | None,
    f_scale: float | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Levenberg–Marquardt over the rows in ``mask``: least squares ``sum w e²`` (``f_scale``
    None), else soft-L1 ``sum w f² 2 (sqrt(1 + e²/f²) - 1)`` by iteratively reweighted steps.

    A step is taken only when it lowers the loss; the damping (Marquardt's, scaled by the
    diagonal) grows until one does. Stops when the loss or the step changes by less than the
    tolerance, relatively. Returns the parameters, every row's residual there and the normal
    equations ``JᵀWJ`` there (None when the start was kept for want of a finite loss).
    """
    robust = f_scale is not None
    iterations = _ROBUST_ITERATIONS if robust else _LEAST_SQUARES_ITERATIONS
    tolerance = _ROBUST_TOLERANCE if robust else _LEAST_SQUARES_TOLERANCE
    masked_weights = _part(weights, mask)

    def loss(residuals: np.ndarray) -> float:
        e = residuals[mask]
        if robust:
            terms = 2.0 * f_scale**2 * (np.sqrt(1.0 + (e / f_scale) ** 2) - 1.0)
        else:
            terms = e * e
        return float(np.sum(terms if masked_weights is None else masked_weights * terms))

    residuals, normal, gradient = model.evaluate(params, mask, weights, f_scale)
    cost = loss(residuals)
    if not np.isfinite(cost):
        return params, residuals, None
    damping = 0.0
    condition = _condition(normal)
    for _ in range(iterations):
        if not (np.all(np.isfinite(normal)) and np.all(np.isfinite(gradient))):
            break
        diagonal = np.diag(normal)
        scale = np.diag(np.maximum(diagonal, 1e-12 * max(float(np.max(diagonal)), 1e-300)))
        while True:
            try:
                step = np.linalg.solve(normal + damping * scale, -gradient)
            except np.linalg.LinAlgError:
                step = None
            if step is not None and np.all(np.isfinite(step)):
                trial = params + step
                evaluated = model.evaluate(trial, mask, weights, f_scale)
                trial_cost = loss(evaluated[0])
                if trial_cost <= cost:
                    break
            damping = max(10.0 * damping, 1e-6)
            if damping > 1e10:
                return params, residuals, normal
        converged = cost - trial_cost <= tolerance * cost or np.linalg.norm(step) <= tolerance * (
            np.linalg.norm(params) + tolerance
        )
        params, cost = trial, trial_cost
        residuals, normal, gradient = evaluated
        damping = 0.0 if damping < 1e-5 else damping / 10.0
        if converged or _predicted_reduction(normal, gradient) <= tolerance * cost:
            break  # (the second test spares a pass that would move nothing: Gauss-Newton from an
            # algebraic start is there after one or two steps)
        previous, condition = condition, _condition(normal)
        if condition > max(DIVERGED_CONDITION, previous):
            break  # see DIVERGED_CONDITION
    return params, residuals, normal


def _condition(normal: np.ndarray) -> float:
    """The condition number of the Jacobian behind ``normal`` (JᵀWJ): sqrt of its own."""
    with np.errstate(all='ignore'):
        scales = np.linalg.eigvalsh(normal) if np.all(np.isfinite(normal)) else None
    if scales is None or not scales[0] > 0.0:
        return np.inf
    return math.sqrt(scales[-1] / scales[0])


def _predicted_reduction(normal: np.ndarray, gradient: np.ndarray) -> float:
    """The loss a full Gauss–Newton step would remove (gᵀ (JᵀJ)⁻¹ g), inf when unknown."""
    try:
        reduction = float(gradient @ np.linalg.solve(normal, gradient))
    except np.linalg.LinAlgError:
        return np.inf
    return reduction if np.isfinite(reduction) else np.inf


@dataclass(frozen=True)
class _Refined:
    centre: np.ndarray
    matrix: np.ndarray
    residuals: np.ndarray
    inliers: np.ndarray
    condition: float
    std: np.ndarray | None
    robust: bool = True


def _refine(
    points: np.ndarray,
    centre: np.ndarray,
    matrix: np.ndarray,
    spherical: bool,
    outlier_threshold: float,
    free: np.ndarray | None = None,
    weights: np.ndarray | None = None,
    robust: bool = True,
) -> _Refined | None:
    """Geometric least squares of the inliers from a start; outliers flagged before and after.

    ``robust``: run the robust soft-L1 fit first (the start's gross outliers left out), so that
    the inliers are judged on a fit spikes did not bend. Without it (the fast path) the start's
    inliers are fitted at once, and None is returned when a fit shows that spikes bent it or its
    inliers do not settle (see FAST_PATH_FITS). With ``free``, only those parameters move; the
    rest stay at the start's values.
    """
    model = _Geometric(points, spherical)
    if free is not None:
        model = _Geometric(points, spherical, free, model.pack(centre, matrix))
    params = model.pack(centre, matrix)
    n_params = len(params)
    residuals = model.residuals(params)
    # sigma of one reading (a point of weight w is the mean of w readings: sqrt(w) less noise);
    # every point is held to it, so an averaged point is never flagged for a misfit smaller
    # than one reading's noise, and a lone spike still is
    sigma = robust_sigma(_weigh(residuals, weights))
    if robust:
        window = max(GROSS_OUTLIER_SIGMAS, outlier_threshold) * sigma
        candidates = np.abs(residuals) <= window
        if candidates.sum() > n_params:
            params, residuals, _ = _step(model, params, residuals, candidates, weights, sigma)
        sigma = robust_sigma(_weigh(residuals, weights)[candidates])
    used = np.abs(residuals) <= outlier_threshold * sigma
    if not robust and np.count_nonzero(~used) > 2 * FAST_PATH_OUTLIERS * len(used) + 1:
        return None  # the start already shows outliers: no point trying
    inliers, normal = used, None
    for attempt in range(1 if robust else FAST_PATH_FITS):
        if used.sum() <= n_params:
            if robust:
                break
            return None
        params, residuals, normal = _step(model, params, residuals, used, weights)
        sigma = robust_sigma(_weigh(residuals, weights)[used])
        inliers = np.abs(residuals) <= outlier_threshold * sigma
        if robust:
            break
        if np.any(np.abs(residuals[used]) > GROSS_OUTLIER_SIGMAS * sigma):
            return None  # the plain start let a spike into the fit
        moved = np.abs(residuals[used != inliers]) / (outlier_threshold * sigma)
        if np.all((moved >= BORDER[0]) & (moved <= BORDER[1])):
            break  # settled: as on the robust path, a border point may be fitted, then flagged
        if attempt == FAST_PATH_FITS - 1:
            return None  # the inliers did not settle
        used = inliers
    if not robust:
        outliers = ~inliers
        share = FAST_PATH_OUTLIERS * len(inliers)
        fitted_outliers = np.count_nonzero(used & outliers)
        if np.count_nonzero(outliers) > max(1.0, share) or fitted_outliers > share:
            return None  # outliers: judge them on the robust path
    fitted_centre, fitted_matrix = model.unpack(params)
    if not robust and _ratio(fitted_matrix if free is None else fitted_matrix[:2, :2]) > 10.0:
        return None  # implausible (a cap fitted by a huge ellipsoid): the robust path decides
    if weights is not None or not np.array_equal(inliers, used):
        normal = None  # not the plain normal equations of the inliers
    condition, std = _condition_and_std(model, params, inliers, weights, residuals, normal)
    return _Refined(fitted_centre, fitted_matrix, residuals, inliers, condition, std, robust)


def _refine_fast_or_robust(
    points: np.ndarray,
    centre: np.ndarray,
    matrix: np.ndarray,
    outlier_threshold: float,
    free: np.ndarray,
    weights: np.ndarray | None,
    always_robust: bool,
) -> _Refined:
    """_refine from a start that is no algebraic fit (planar): the fast path, else robust."""
    fitted = None
    if not always_robust:
        fitted = _refine(points, centre, matrix, False, outlier_threshold, free, weights, False)
    return fitted or _refine(points, centre, matrix, False, outlier_threshold, free, weights)


def _step(
    model: _Geometric,
    params: np.ndarray,
    residuals: np.ndarray,
    mask: np.ndarray,
    weights: np.ndarray | None,
    f_scale: float | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """_minimise, kept only when _better: (parameters, residuals, normal equations or None)."""
    fitted, fitted_residuals, normal = _minimise(model, params, mask, weights, f_scale)
    if _better(model, params, fitted) is params:
        return params, residuals, None
    return fitted, fitted_residuals, normal


def _better(model: _Geometric, previous: np.ndarray, candidate: np.ndarray) -> np.ndarray:
    """The candidate unless it is non-finite or its M lost positive definiteness (a
    hyperboloid)."""
    if not np.all(np.isfinite(candidate)):
        return previous
    _, matrix = model.unpack(candidate)
    if (
        np.linalg.eigvalsh(matrix).min() <= 0
        and np.linalg.eigvalsh(model.unpack(previous)[1]).min() > 0
    ):
        return previous
    return candidate


def _singular_values(
    model: _Geometric,
    params: np.ndarray,
    mask: np.ndarray,
    weights: np.ndarray | None,
    normal: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray] | None:
    """Singular values (descending) and right singular vectors (rows) of ``sqrt(W) J`` over the
    rows in ``mask`` (``normal``: its ``JᵀWJ`` when known); None when not finite."""
    if normal is None:
        normal = model.evaluate(params, mask, weights)[1]
    if not np.all(np.isfinite(normal)):
        return None
    eigenvalues, vectors = np.linalg.eigh(normal)  # ascending
    if eigenvalues[0] > eigenvalues[-1] / EXACT_CONDITION**2:
        return np.sqrt(eigenvalues[::-1]), vectors[:, ::-1].T
    factor = model.triangular_factor(params, mask, weights)
    if not np.all(np.isfinite(factor)):
        return None
    _, singular, vt = np.linalg.svd(factor)
    return singular, vt


def _condition_and_std(
    model: _Geometric,
    params: np.ndarray,
    mask: np.ndarray,
    weights: np.ndarray | None,
    residuals: np.ndarray,
    normal: np.ndarray | None = None,
) -> tuple[float, np.ndarray | None]:
    """Condition number of the plain Jacobian over the rows in ``mask``, and the parameters'
    1-sigma from ``sigma² (JᵀWJ)⁻¹`` (W the weights; sigma² from the weighted residuals).
    ``residuals``: every row's at ``params``; ``normal``: the plain ``JᵀJ`` there, if known."""
    n, p = int(np.count_nonzero(mask)), len(params)
    plain = _singular_values(model, params, mask, None, normal) if n else None
    if plain is None or plain[0][-1] <= 0:
        return np.inf, None
    condition = float(plain[0][0] / plain[0][-1])
    if n <= p:
        return condition, None
    weighted = plain if weights is None else _singular_values(model, params, mask, weights)
    if weighted is None or weighted[0][-1] <= 0:
        return condition, None
    singular, vt = weighted
    inlier_residuals = residuals[mask]
    squares = inlier_residuals**2 if weights is None else weights[mask] * inlier_residuals**2
    variance = float(np.sum(squares)) / (n - p)
    covariance_diag = np.sum((vt.T / singular) ** 2, axis=1) * variance
    return condition, np.sqrt(covariance_diag)


# -----------------------------------------------------------------------------------------------
# Public fits (input units in, input units out)


def fit_ellipsoid(
    points: np.ndarray,
    model: str,
    outlier_threshold: float = 4.0,
    prior: tuple[np.ndarray, np.ndarray] | None = None,
    weights: np.ndarray | None = None,
    always_robust: bool = False,
) -> EllipsoidFit | None:
    """Fit ``model`` (one of FIT_MODELS) to finite (n, 3) input-unit points; None when impossible.

    ``prior`` is (offset, unit-radius matrix) in input units, used by ``planar`` out of the plane.
    ``weights`` (n,) are finite and > 0 (see the module docstring), or None for equal weights.
    ``always_robust`` takes the robust path even when the data look clean.
    """
    fits = fit_ellipsoids(points, (model,), outlier_threshold, prior, weights, always_robust)
    return fits[model]


def fit_ellipsoids(
    points: np.ndarray,
    models: tuple[str, ...],
    outlier_threshold: float = 4.0,
    prior: tuple[np.ndarray, np.ndarray] | None = None,
    weights: np.ndarray | None = None,
    always_robust: bool = False,
    normalised: tuple[Normalisation, np.ndarray] | None = None,
) -> dict[str, EllipsoidFit | None]:
    """fit_ellipsoid for several models of the same points (``auto``): the normalisation and
    the algebraic moments are computed once, and when a well-determined ``full`` took the robust
    path, the sphere's robust fit starts from the sphere through full's inliers (the spikes are
    the same points whatever the model) instead of a trimmed start of its own. ``normalised``:
    ``normalise(points)`` and its ``forward(points)`` when the caller has them."""
    for model in models:
        if model not in FIT_MODELS:
            raise ValueError(f'unknown fit model {model!r}; expected one of {FIT_MODELS}')
    fits: dict[str, EllipsoidFit | None] = dict.fromkeys(models)
    wanted = [model for model in models if len(points) >= PARAMETER_COUNTS[model] + 1]
    if not wanted:
        return fits
    with np.errstate(all='ignore', under='ignore'):
        norm, y = normalised if normalised is not None else (normalise(points), None)
        if norm is None:
            return fits
        gram = None
        spike_free = None  # full's inliers, when its robust path judged them
        for model in sorted(wanted, key=lambda name: name != 'full'):
            try:
                if model == 'planar':
                    fits[model] = _fit_planar(
                        points, outlier_threshold, prior, weights, always_robust
                    )
                    continue
                if y is None:
                    y = norm.forward(points)
                if gram is None and not always_robust and model != 'axis':
                    gram = moments(y, weights)
                fitted = _fit_3d(
                    y, model, outlier_threshold, weights, always_robust, gram, spike_free
                )
            except (np.linalg.LinAlgError, ValueError):
                continue
            if (model == 'full' and fitted is not None and fitted.robust
                    and fitted.condition <= SHARED_START_CONDITION):
                spike_free = fitted.inliers
            if fitted is not None:
                fits[model] = _to_input_units(fitted, norm, model)
    return fits


SHARED_START_CONDITION = 100.0
"""``full`` fits up to this condition number share their inliers as the sphere's robust start:
data that determine the ellipsoid determine the sphere's one minimum, which any spike-free start
reaches; an ill-posed arc has several, and keeps its own trimmed start."""

_AXIS_PARAMETERS = np.array([0, 1, 2, 3, 6, 8])
"""b and the diagonal of M among [b, upper(M)]: the axis model's own parameters."""


def _fit_3d(
    y: np.ndarray,
    model: str,
    outlier_threshold: float,
    weights: np.ndarray | None = None,
    always_robust: bool = False,
    gram: np.ndarray | None = None,
    spike_free: np.ndarray | None = None,
) -> _Refined | None:
    """``spike_free``: inliers of a robust full fit, the sphere's robust start (see
    fit_ellipsoids)."""
    if model == 'axis':
        solved = axis_least_squares(y, weights)
        if solved is None:
            return None
        centre, semi_axes = solved
        matrix = np.diag(1.0 / semi_axes)
        residuals = radial_residuals(y, centre, matrix)
        inliers = np.abs(residuals) <= outlier_threshold * robust_sigma(residuals)
        full = _Geometric(y, spherical=False).pack(centre, matrix)
        geometry = _Geometric(y, False, _AXIS_PARAMETERS, full)
        condition, _ = _condition_and_std(
            geometry, full[_AXIS_PARAMETERS], inliers, None, residuals
        )
        return _Refined(centre, matrix, residuals, inliers, condition, None)
    spherical = model == 'sphere'
    algebraic = _sphere_start if spherical else quadric_least_squares
    if not always_robust:
        if gram is None:
            plain = _plain_start(y, algebraic, weights)
        elif spherical:
            sphere = _sphere_from_moments(gram, 3)
            plain = None if sphere is None else (sphere[0], np.eye(3) / sphere[1])
        else:
            plain = _quadric_from_moments(gram, 3)
            plain = plain if plain is not None and _ratio(plain[1]) <= 10.0 else None
        if plain is not None:
            fast = _refine(y, *plain, spherical, outlier_threshold, weights=weights, robust=False)
            if fast is not None:
                return fast
    start = None
    if spherical and spike_free is not None and np.count_nonzero(spike_free) >= 8:
        start = _sphere_start(y[spike_free], _part(weights, spike_free))
    if start is None:
        start = trimmed_start(y, algebraic, outlier_threshold, weights)
    if start is None and not spherical:  # the sphere is the next start, as robustly found
        start = trimmed_start(y, _sphere_start, outlier_threshold, weights)
    if start is None:  # the unit sphere about the median: the normalisation put the data there
        start = (np.zeros(3), np.eye(3))
    return _refine(y, start[0], start[1], spherical, outlier_threshold, weights=weights)


def _ratio(matrix: np.ndarray) -> float:
    eigenvalues = np.linalg.eigvalsh(matrix)
    return float(eigenvalues.max() / eigenvalues.min()) if eigenvalues.min() > 0 else np.inf


def _to_input_units(fitted: _Refined, norm: Normalisation, model: str) -> EllipsoidFit | None:
    offset = norm.centre + norm.scale * fitted.centre
    matrix = fitted.matrix / norm.scale
    if not (np.all(np.isfinite(offset)) and np.all(np.isfinite(matrix))):
        return None
    std = None
    if fitted.std is not None and np.all(np.isfinite(fitted.std)):
        if model == 'sphere':
            std = {
                'offset': (fitted.std[:3] * norm.scale).tolist(),
                'matrix': (np.eye(3) * fitted.std[3] / norm.scale).ravel().tolist(),
            }
        else:
            m_std = np.zeros((3, 3))
            rows, cols = np.triu_indices(3)
            m_std[rows, cols] = fitted.std[3:] / norm.scale
            m_std[cols, rows] = fitted.std[3:] / norm.scale
            std = {
                'offset': (fitted.std[:3] * norm.scale).tolist(),
                'matrix': m_std.ravel().tolist(),
            }
    return EllipsoidFit(
        model, offset, matrix, fitted.residuals, fitted.inliers, fitted.condition,
        _radius(matrix), _ratio(matrix), std, robust=fitted.robust,
    )  # fmt: skip


def _radius(matrix: np.ndarray) -> float:
    determinant = float(np.linalg.det(matrix))
    return determinant ** (-1.0 / 3.0) if determinant > 0 else np.inf


def _fit_planar(
    points: np.ndarray,
    outlier_threshold: float,
    prior: tuple[np.ndarray, np.ndarray] | None,
    weights: np.ndarray | None = None,
    always_robust: bool = False,
) -> EllipsoidFit | None:
    """Motion in one plane: fit what it determines, in the prior's corrected frame.

    The prior (identity without one) corrects the points first. Without a prior a 2-D ellipse is
    fitted in the plane of the data (area-preserving shape and in-plane centre); when tilts taken
    while turning determine the offset along the normal, the 3-D fit of _planar_tilted replaces
    it, else that offset is the data's mean there: the corrected field lies in the plane, heading
    is right, the vertical component is unknown. With a prior the 3-D residual is minimised with
    only the in-plane parameters free, so the normal terms stay the prior's and tilts taken while
    turning (which change the horizontal field by tan(inclination) x tilt: 5 % for ±3° at 60°)
    are explained instead of counted as error.
    """
    prior_offset, prior_matrix = prior if prior is not None else (np.zeros(3), np.eye(3))
    u = (points - prior_offset) @ prior_matrix.T
    if prior is not None:  # unit radius on these data, whatever the prior's scale or units
        radius = float(np.median(np.linalg.norm(u, axis=1)))
        if not (np.isfinite(radius) and radius > 0):
            return None
        prior_matrix = prior_matrix / radius
        u = u / radius
    norm = normalise(u)
    if norm is None:
        return None
    y = norm.forward(u)
    _, basis = thickness(y)
    if np.linalg.det(basis) < 0:
        basis[:, 2] = -basis[:, 2]
    if basis[np.argmax(np.abs(basis[:, 2])), 2] < 0:  # normal toward its nearest body axis (+z...)
        basis[:, [1, 2]] = -basis[:, [1, 2]]
    w = y @ basis  # plane coordinates, normal last
    flat = _fit_ellipse_2d(w[:, :2], outlier_threshold, weights, always_robust)
    if flat is None:
        return None
    if prior is not None:
        prior_normal = float(basis[:, 2] @ (-norm.centre / norm.scale))
        in_3d = _planar_in_3d(
            w, norm.scale, prior_normal, flat, outlier_threshold, weights, always_robust
        )
        if in_3d is not None:
            return _planar_result(
                points, in_3d, basis, norm, prior_offset, prior_matrix, False, weights
            )
    if prior is None:  # tilts while turning may determine the offset along the normal
        tilted = _planar_tilted(w, basis, flat, outlier_threshold, weights, always_robust)
        if tilted is not None:
            rotated, normal_std = tilted
            return _planar_result(
                points, rotated, basis, norm, prior_offset, prior_matrix, False, weights,
                normal_std,
            )  # fmt: skip
    block = np.eye(3)
    block[:2, :2] = flat.matrix / np.sqrt(np.linalg.det(flat.matrix))  # shape; scale set below
    if prior is not None:
        normal_offset = float(basis[:, 2] @ (-norm.centre / norm.scale))
    else:
        normal_offset = float(np.average(w[flat.inliers, 2], weights=_part(weights, flat.inliers)))
    rotated = _Refined(
        np.append(flat.centre, normal_offset), block, flat.residuals, flat.inliers,
        flat.condition, flat.std, flat.robust,
    )  # fmt: skip
    return _planar_result(points, rotated, basis, norm, prior_offset, prior_matrix, True, weights)


def _fit_ellipse_2d(
    in_plane: np.ndarray,
    outlier_threshold: float,
    weights: np.ndarray | None = None,
    always_robust: bool = False,
) -> _Refined | None:
    if not always_robust:
        plain = _plain_start(in_plane, quadric_least_squares, weights)
        if plain is not None:
            fast = _refine(in_plane, *plain, False, outlier_threshold, weights=weights,
                           robust=False)  # fmt: skip
            if fast is not None and np.linalg.det(fast.matrix) > 0:
                return fast
    start = trimmed_start(in_plane, quadric_least_squares, outlier_threshold, weights)
    if start is None:
        start = trimmed_start(in_plane, _sphere_start, outlier_threshold, weights)
    if start is None:
        centre = np.median(in_plane, axis=0)
        radius = float(np.median(row_norms(in_plane - centre)))
        if not radius > 0:
            return None
        start = (centre, np.eye(2) / radius)
    fitted = _refine(in_plane, start[0], start[1], False, outlier_threshold, weights=weights)
    return fitted if np.linalg.det(fitted.matrix) > 0 else None


_IN_PLANE = np.array([0, 1, 3, 4, 6])
"""Parameters [b_u, b_v, M_uu, M_uv, M_vv] of the 3-D model in the plane's frame (normal last)."""


def _planar_in_3d(
    w: np.ndarray,
    scale: float,
    prior_normal: float,
    flat: _Refined,
    outlier_threshold: float,
    weights: np.ndarray | None = None,
    always_robust: bool = False,
) -> _Refined | None:
    """3-D residual, in-plane parameters free, the rest at the prior (``s I`` centred on it)."""
    centre = np.append(flat.centre, prior_normal)
    vertical = scale * (w[flat.inliers, 2] - prior_normal)
    horizontal_share = np.sqrt(max(1.0 - float(np.mean(vertical**2)), 0.05))
    matrix = scale * np.eye(3)
    matrix[:2, :2] = flat.matrix * horizontal_share
    refined = _refine_fast_or_robust(
        w, centre, matrix, outlier_threshold, _IN_PLANE, weights, always_robust
    )
    if np.linalg.eigvalsh(refined.matrix).min() <= 0:
        return None
    std = None
    if refined.std is not None:  # in-plane offset in normalised units, matrix relative to s
        std = np.concatenate([refined.std[:2], refined.std[2:] / scale])
    return _Refined(
        refined.centre, refined.matrix, refined.residuals, refined.inliers, refined.condition, std,
        refined.robust,
    )  # fmt: skip


MAX_NORMAL_OFFSET_STD = 0.05
"""The offset along the plane normal counts as observed only when its 1-sigma is below 5 % of the
field (2.5 µT at 50 µT) and the 3-D fit explains the data better than the 2-D ellipse by the
information criterion (``TILT_EVIDENCE``); a level ring determines it not at all, and the fit
then falls back to the 2-D ellipse and reports it unobserved."""

TILT_EVIDENCE = 10.0
"""BIC margin the 3-D (tilted) planar fit must win by: 'very strong' evidence on the usual scale,
so noise alone (whose normal component the regression would otherwise fit) never frees the
offset along the normal."""

MAX_FIELD_TO_PLANE = 6.0
"""Largest ratio of the tilted fit's field to the horizontal field the 2-D ellipse sees: the
inclination's secant, 6 at 80°. Beyond it the 3-D fit of a ring has wandered off to a huge
ellipsoid (seen on disturbed rings, with a deceptively small relative error of the normal
offset), and the 2-D fit stands."""

_TILTED = np.array([0, 1, 2, 3, 4, 6])
"""Parameters [b_u, b_v, b_n, M_uu, M_uv, M_vv] of the 3-D model in the plane's frame."""


def _planar_tilted(
    w: np.ndarray,
    basis: np.ndarray,
    flat: _Refined,
    outlier_threshold: float,
    weights: np.ndarray | None = None,
    always_robust: bool = False,
) -> tuple[_Refined, float] | None:
    """3-D fit of a turning robot that tilts a little; None when the tilts do not determine it.

    Tilting by θ moves about V θ of the vertical field V into the plane and H θ of the
    horizontal field H out of it, keeping the total constant; a 2-D fit sees its radius change by
    tan(inclination) θ (10 % for 3° at 70°). In 3-D that is no error, and because the reading
    along the normal changes with the tilt, the offset along it is determined as well.

    Held, as turning about one axis cannot determine them: the out-of-plane scale at the in-plane
    one, and the cross terms such that the corrected plane is perpendicular to the body axis
    nearest its normal (``M z ∥ n``: a sensor mounted with an axis along the yaw axis, as the
    true symmetric soft iron does then). Cross terms of zero instead would leave the corrected
    vertical along the raw plane's normal, which soft iron tilts off the yaw axis, and with a
    vertical component of tan(inclination) times the horizontal one that tilt leaks into the
    heading (15° at 70° inclination for a 7° tilt).

    The start is linear: with ``q`` the shape-corrected in-plane radius and ``v`` the normal
    coordinate, ``q² + (v - b)² = R²`` is ``q² + v² = 2 b v + (R² - b²)``; the sign of ``v - b``
    comes from how ``q`` shrinks as ``|v - b|`` grows. Returns the refined fit (``std`` without
    the normal offset, the matrix std relative to the in-plane scale) and the normal offset's
    1-sigma relative to the field.
    """
    inliers = flat.inliers
    shape = flat.matrix / np.sqrt(np.linalg.det(flat.matrix))
    q_sq = np.sum(((w[inliers, :2] - flat.centre) @ shape) ** 2, axis=1)
    v = w[inliers, 2]
    design = np.column_stack([2.0 * v, np.ones(len(v))])
    target = q_sq + v**2
    solution = _weighted_lstsq(design, target, _part(weights, inliers))
    normal_offset = float(solution[0])
    radius_sq = float(solution[1]) + normal_offset**2
    if not (np.isfinite(radius_sq) and radius_sq > 0):
        return None
    radius = np.sqrt(radius_sq)
    body_axis = basis.T[:, np.argmax(np.abs(basis[:, 2]))]  # in plane coordinates
    if abs(body_axis[2]) < 0.5:  # the plane is far from every body plane: nothing to hold to
        return None
    matrix = _held_out_of_plane(shape / radius, body_axis)
    centre = np.append(flat.centre, normal_offset)
    for _ in range(3):  # the held terms follow the in-plane ones
        refined = _refine_fast_or_robust(
            w, centre, matrix, outlier_threshold, _TILTED, weights, always_robust
        )
        if np.linalg.det(refined.matrix[:2, :2]) <= 0:
            return None
        centre = refined.centre
        matrix = _held_out_of_plane(refined.matrix[:2, :2], body_axis)
    if refined.std is None or np.linalg.eigvalsh(refined.matrix).min() <= 0:
        return None
    field_radius = 1.0 / np.sqrt(np.linalg.det(refined.matrix[:2, :2]))
    flat_radius = 1.0 / np.sqrt(np.linalg.det(flat.matrix))
    if not field_radius <= MAX_FIELD_TO_PLANE * flat_radius:
        return None  # wandered off (a disturbed ring): no tilt explains that
    normal_std = float(refined.std[2]) / field_radius
    if not (np.isfinite(normal_std) and normal_std <= MAX_NORMAL_OFFSET_STD):
        return None
    # evidence: the same points' residuals in the same (normalised input) units, 2-D vs 3-D
    common = flat.inliers & refined.inliers
    root = np.ones(len(w)) if weights is None else np.sqrt(weights)
    flat_score = information_criterion((flat.residuals * flat_radius * root)[common], 5)
    tilted_score = information_criterion((refined.residuals * field_radius * root)[common], 6)
    if not tilted_score < flat_score - TILT_EVIDENCE:
        return None
    # Whether the points determine the in-plane parameters is the 2-D fit's condition on the same
    # points (what the condition gate is calibrated on); the 3-D Jacobian's would grow with the
    # vertical share of the field (F/H: 3 at 70° inclination) without the data being any worse.
    # The normal offset is judged by its std and the evidence above.
    std = np.concatenate([refined.std[:2], refined.std[3:] * field_radius])
    fitted = _Refined(
        refined.centre, refined.matrix, refined.residuals, refined.inliers, flat.condition, std,
        refined.robust,
    )  # fmt: skip
    return fitted, normal_std


def _held_out_of_plane(in_plane: np.ndarray, body_axis: np.ndarray) -> np.ndarray:
    """M in plane coordinates from its in-plane block: ``M_nn`` the in-plane scale, the cross
    terms ``c = -A z_uv / z_n`` so that ``M z`` lies along the normal (see _planar_tilted)."""
    matrix = np.zeros((3, 3))
    matrix[:2, :2] = in_plane
    cross = -in_plane @ body_axis[:2] / body_axis[2]
    matrix[:2, 2] = matrix[2, :2] = cross
    matrix[2, 2] = np.sqrt(np.linalg.det(in_plane))
    return matrix


def _planar_result(
    points: np.ndarray,
    rotated: _Refined,
    basis: np.ndarray,
    norm: Normalisation,
    prior_offset: np.ndarray,
    prior_matrix: np.ndarray,
    rescale: bool,
    weights: np.ndarray | None = None,
    normal_std: float | None = None,
) -> EllipsoidFit | None:
    """From the plane's normalised frame back to input units, through the prior's correction.

    ``normal_std`` (relative to the field) marks the offset along the normal as fitted.
    """
    centre_u = norm.centre + norm.scale * (basis @ rotated.centre)
    correction = basis @ rotated.matrix @ basis.T / norm.scale
    matrix = _symmetric_polar_factor(correction @ prior_matrix)
    offset = prior_offset + np.linalg.solve(prior_matrix, centre_u)
    if rescale:  # unit radius on the data (2-D: the corrected field lies in the plane)
        magnitudes = np.linalg.norm((points[rotated.inliers] - offset) @ matrix.T, axis=1)
        mean = (
            float(np.average(magnitudes, weights=_part(weights, rotated.inliers)))
            if magnitudes.size else 0.0
        )
        if not mean > 0:
            return None
        matrix = matrix / mean
    if not (np.all(np.isfinite(offset)) and np.all(np.isfinite(matrix))):
        return None
    std = None
    if rotated.std is not None and np.all(np.isfinite(rotated.std)):
        std = {
            'offset_in_plane': (rotated.std[:2] * norm.scale).tolist(),
            'matrix_in_plane_relative': rotated.std[2:].tolist(),
        }
        if normal_std is not None:  # relative to the field radius -> input units
            field_radius = 1.0 / np.sqrt(np.linalg.det(rotated.matrix[:2, :2]))
            std['offset_normal'] = [normal_std * field_radius * norm.scale]
    unobserved = ('offset_normal', 'matrix_normal') if normal_std is None else ('matrix_normal',)
    w = norm.forward((points - prior_offset) @ prior_matrix.T) @ basis
    unit = (w - rotated.centre) @ rotated.matrix
    return EllipsoidFit(
        'planar', offset, matrix, rotated.residuals, rotated.inliers, rotated.condition,
        _radius(matrix), _ratio(rotated.matrix[:2, :2]), std,
        unobserved=unobserved, plane_normal=basis[:, 2],
        headings=np.arctan2(unit[:, 1], unit[:, 0]), robust=rotated.robust,
    )  # fmt: skip


def _symmetric_polar_factor(matrix: np.ndarray) -> np.ndarray:
    """P of M = R P: the same magnitudes |M v| = |P v|, without M's rotation (the symmetric
    convention every calibration here uses; a prior times a correction is not symmetric)."""
    _, singular, vt = np.linalg.svd(matrix)
    return (vt.T * singular) @ vt


def information_criterion(residuals: np.ndarray, n_params: int) -> float:
    """BIC of a least-squares fit with Gaussian residuals: n log(RSS/n) + k log(n)."""
    n = len(residuals)
    rss = max(float(np.einsum('i,i->', residuals, residuals)), 1e-300)  # no threaded BLAS
    return n * np.log(rss / n) + n_params * np.log(n)
