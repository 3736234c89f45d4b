"""Ellipsoid fitting maths: algebraic starts and robust geometric refinement.

Every fit runs on normalised data ``y = (x - c) / s`` (``c`` the per-axis median, ``s`` the median
distance to it), so hard-iron offsets many times the field radius and any input unit (T, µT, gauss,
counts) cost no accuracy: the numbers the solvers see are always of order one, in float64. Results
are converted back to input units as ``unit = M (x - b)`` with ``|unit| ≈ 1`` on the data;
fitting.py chooses the output scale.

Models (all fits return an :class:`EllipsoidFit`):

- ``sphere``: hard iron only, ``M = I / r`` (4 parameters).
- ``axis``: the brief's least squares ``H = [x, y, z, -y², -z², 1]``, ``w = x²`` (axis-aligned
  ellipsoid, 6 parameters), kept as the reference design: algebraic only, no robust refinement, so
  it measures the method.
- ``full``: hard iron + symmetric soft iron (9 parameters), quadric least-squares start.
- ``planar``: motion confined to a plane (a ground robot yawing). Without a prior: a 2-D ellipse in
  the plane of the data; when the robot tilts a few degrees while turning (every real floor does)
  and that determines it, the 3-D residual with the in-plane parameters and the offset along the
  normal free (see _planar_tilted), else the offset along the normal at the data's mean. With a
  prior: the 3-D residual with only the in-plane parameters free. The normal terms not fitted
  are reported as unobserved.

Algebraic starts are least trimmed squares (fitted to the 60 % of points nearest the current
surface, repeated until that set settles), so even a buffer holding many spikes starts well. The
geometric refinement then minimises a robust loss (soft-L1) of ``e = |M (y - b)| - 1`` with an
analytic Jacobian, flags residuals beyond ``outlier_threshold`` robust sigmas and refits the
inliers by plain least squares (efficient for Gaussian noise).

Optional ``weights`` (one per point, > 0) weight every least-squares step and the robust loss: a
point that stands for the average of ``n`` readings (SampleBuffer merges nearby samples) has ``n``
times less noise variance, so it gets weight ``n``. Outliers are flagged on the plain residual
against the robust sigma of one reading (residual x sqrt(weight)): a lone spike is flagged as
without weights, and an averaged point is never flagged merely because the model's misfit exceeds
its reduced noise. The condition number stays that of the plain Jacobian: weights say how
precisely a point is known, not whether the points determine the model.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from statistics import NormalDist

import numpy as np
from scipy.optimize import least_squares

FIT_MODELS = ('sphere', 'axis', 'full', 'planar')
PARAMETER_COUNTS = {'sphere': 4, 'axis': 6, 'full': 9, 'planar': 5}

MIN_ROBUST_SIGMA = 1e-4
"""Floor of the robust residual sigma (relative to the radius). Below 0.01 % no magnetometer is
that quiet (16-bit quantisation alone is larger), and without a floor noiseless data would flag
rounding as outliers."""

GROSS_OUTLIER_SIGMAS = 10.0
"""Points this many robust sigmas off the start surface never enter the robust fit: soft-L1 grows
without bound, and a few spikes many radii away could otherwise bend M into a hyperboloid through
them."""

_MAD_TO_SIGMA = 1.4826


@dataclass(frozen=True)
class Normalisation:
    """``y = (x - centre) / scale``: data of order one whatever the offset and unit."""

    centre: np.ndarray
    scale: float

    def forward(self, points: np.ndarray) -> np.ndarray:
        return (points - self.centre) / self.scale


def normalise(points: np.ndarray) -> Normalisation | None:
    """Median centre and median distance; None when the points do not spread (all equal)."""
    centre = np.median(points, axis=0)
    deviation = points - centre
    peak = float(np.max(np.abs(deviation))) if deviation.size else 0.0
    if not np.isfinite(peak) or peak <= 1e-12 * max(float(np.max(np.abs(centre))), 1e-300):
        return None
    distances = np.linalg.norm(deviation / peak, axis=1) * peak  # pre-scaled: no overflow
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
    fitted plane.
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


def thickness(y: np.ndarray) -> tuple[float, np.ndarray]:
    """How far the data leave their best plane: sqrt(smallest / middle covariance eigenvalue).

    About 1 for data all round a sphere, about the relative noise for a ring (yaw only), 0.5 for a
    hemisphere. Gross outliers (far from the unit sphere the normalisation centred) are left out,
    or a few spikes would make a ring look three-dimensional. Also returns the eigenvectors
    (columns, largest variance first; the last is the normal).
    """
    distance = np.linalg.norm(y, axis=1) - 1.0
    window = max(GROSS_OUTLIER_SIGMAS * robust_sigma(distance), 0.2)
    kept = y[np.abs(distance) <= window]
    if len(kept) < 3:
        return 0.0, np.eye(3)
    eigenvalues, vectors = np.linalg.eigh(np.cov(kept, rowvar=False))
    eigenvalues, vectors = eigenvalues[::-1], vectors[:, ::-1]
    if eigenvalues[1] <= 0:
        return 0.0, vectors
    return float(np.sqrt(max(eigenvalues[2], 0.0) / eigenvalues[1])), vectors


# -----------------------------------------------------------------------------------------------
# Algebraic starts (on normalised data)


def _weighted_lstsq(
    design: np.ndarray, target: np.ndarray, weights: np.ndarray | None
) -> np.ndarray:
    """Least squares with each row scaled by sqrt(weight) (plain when ``weights`` is None)."""
    if weights is not None:
        root = np.sqrt(weights)
        design, target = design * root[:, None], target * root
    return np.linalg.lstsq(design, target, rcond=None)[0]


def sphere_least_squares(
    y: np.ndarray, weights: np.ndarray | None = None
) -> tuple[np.ndarray, float] | None:
    """Linear circle/sphere fit ``|y|² = 2 b·y + c``: (centre, radius)."""
    design = np.column_stack([2.0 * y, np.ones(len(y))])
    solution = _weighted_lstsq(design, np.einsum('ij,ij->i', y, y), weights)
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
    d = points.shape[1]
    rows, cols = np.triu_indices(d)
    quadratic = points[:, rows] * points[:, cols] * np.where(rows == cols, 1.0, 2.0)
    design = np.column_stack([quadratic, 2.0 * points])
    solution = _weighted_lstsq(design, np.ones(len(points)), weights)
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
    """The brief's reference least squares (geometrikal / mag-calibrator-rs): (offset, semi-axes).

    ``H = [x, y, z, -y², -z², 1]``, ``w = x²``, ``X = (HᵀH)⁻¹Hᵀw``, done here in float64 on
    normalised data (the library's float32 on raw data fails once the offset exceeds a few field
    radii).
    """
    design = np.column_stack([y, -(y[:, 1] ** 2), -(y[:, 2] ** 2), np.ones(len(y))])
    x = _weighted_lstsq(design, y[:, 0] ** 2, weights)
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


def trimmed_start(
    points: np.ndarray,
    algebraic: Callable[[np.ndarray, np.ndarray | None], tuple[np.ndarray, np.ndarray] | None],
    threshold: float,
    weights: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray] | None:
    """An algebraic fit that spikes cannot ruin (in plain least squares they enter squared).

    Least trimmed squares by concentration steps: from the unit sphere about the median (where
    the normalisation put the data), fit the ``TRIMMED_SHARE`` of points closest to the current
    surface, repeat until that set settles; then refit once on every point within ``threshold``
    robust sigmas of it, for an efficient start when there are few outliers.
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
        residuals = np.abs(np.linalg.norm((points - centre) @ matrix, axis=1) - 1.0)
        new_kept = np.zeros(len(points), dtype=bool)
        new_kept[np.argpartition(residuals, n_kept - 1)[:n_kept]] = True
        settled = np.count_nonzero(new_kept != kept) <= max(2, len(points) // 50)
        kept = new_kept
        if settled and best is not None:
            break
        fitted = algebraic(points[kept], _part(weights, kept))
        if fitted is None or _ratio(fitted[1]) > 10.0:
            break
        best = centre, matrix = fitted
    if best is None:
        return None
    residuals = np.linalg.norm((points - centre) @ matrix, axis=1) - 1.0
    # the kept residuals are the smallest ones: their median is the TRIMMED_SHARE/2 quantile of |e|
    sigma = max(float(np.median(np.abs(residuals[kept]))) / _TRIMMED_MEDIAN, MIN_ROBUST_SIGMA)
    inliers = np.abs(residuals) <= threshold * sigma
    if inliers.sum() >= n_needed:
        refitted = algebraic(points[inliers], _part(weights, inliers))
        if refitted is not None and _ratio(refitted[1]) <= 10.0:
            return refitted
    return best


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
    """Residuals and analytic Jacobian of ``|M (p - b)| - 1`` over parameters [b, upper(M)].

    ``free`` (indices into that vector) optimises only some parameters, the others held at
    ``base``: the planar model with a prior frees the in-plane ones. ``weights`` scale the
    ``weighted_*`` residuals and Jacobian by their square root (``residuals`` stay plain).
    """

    def __init__(
        self,
        points: np.ndarray,
        spherical: bool,
        free: np.ndarray | None = None,
        base: np.ndarray | None = None,
        weights: np.ndarray | None = None,
    ) -> None:
        self.points = points
        self.weights = weights
        self.root_weights = None if weights is None else np.sqrt(weights)
        self.d = points.shape[1]
        self.spherical = spherical
        self.rows, self.cols = np.triu_indices(self.d)
        self.diagonal = self.rows == self.cols
        self.free = free
        self.base = base

    def subset(self, mask: np.ndarray) -> _Geometric:
        return _Geometric(
            self.points[mask], self.spherical, self.free, self.base, _part(self.weights, mask)
        )

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

    def residuals(self, params: np.ndarray, points: np.ndarray | None = None) -> np.ndarray:
        centre, matrix = self.unpack(params)
        w = (self.points if points is None else points) - centre
        return np.linalg.norm(w @ matrix, axis=1) - 1.0

    def jacobian(self, params: np.ndarray) -> np.ndarray:
        centre, matrix = self.unpack(params)
        z = self.points - centre
        w = z @ matrix
        radius = np.maximum(np.linalg.norm(w, axis=1), 1e-300)
        g = w / radius[:, None]
        d_centre = -(g @ matrix)
        if self.spherical:
            d_matrix = (np.linalg.norm(z, axis=1))[:, None]
        else:
            r, c = self.rows, self.cols
            d_matrix = g[:, r] * z[:, c] + np.where(self.diagonal, 0.0, 1.0) * g[:, c] * z[:, r]
        jacobian = np.column_stack([d_centre, d_matrix])
        return jacobian if self.free is None else jacobian[:, self.free]

    def weighted_residuals(self, params: np.ndarray) -> np.ndarray:
        residuals = self.residuals(params)
        return residuals if self.root_weights is None else residuals * self.root_weights

    def weighted_jacobian(self, params: np.ndarray) -> np.ndarray:
        jacobian = self.jacobian(params)
        return jacobian if self.root_weights is None else jacobian * self.root_weights[:, None]

    def robust_loss(self) -> str | Callable[[np.ndarray], np.ndarray]:
        """soft-L1, each point's term multiplied by its weight (scipy's loss-callable form)."""
        if self.weights is None:
            return 'soft_l1'
        weights = self.weights

        def weighted_soft_l1(z: np.ndarray) -> np.ndarray:
            t = 1.0 + z
            return np.vstack([weights * 2.0 * (np.sqrt(t) - 1.0), weights / np.sqrt(t),
                              -0.5 * weights * t**-1.5])

        return weighted_soft_l1


def robust_sigma(residuals: np.ndarray) -> float:
    """1.4826 x median absolute residual, floored at MIN_ROBUST_SIGMA."""
    if residuals.size == 0:
        return MIN_ROBUST_SIGMA
    return max(_MAD_TO_SIGMA * float(np.median(np.abs(residuals))), MIN_ROBUST_SIGMA)


@dataclass(frozen=True)
class _Refined:
    centre: np.ndarray
    matrix: np.ndarray
    residuals: np.ndarray
    inliers: np.ndarray
    condition: float
    std: np.ndarray | None


def _refine(
    points: np.ndarray,
    centre: np.ndarray,
    matrix: np.ndarray,
    spherical: bool,
    outlier_threshold: float,
    free: np.ndarray | None = None,
    weights: np.ndarray | None = None,
) -> _Refined:
    """Robust soft-L1 fit from an algebraic start; outliers flagged; least squares on inliers.

    With ``free``, only those parameters move; the rest stay at the start's values.
    """
    model = _Geometric(points, spherical, weights=weights)
    if free is not None:
        model = _Geometric(points, spherical, free, model.pack(centre, matrix), weights)
    params = model.pack(centre, matrix)
    n_params = len(params)
    start_residuals = model.residuals(params)
    # sigma of one reading (a point of weight w is the mean of w readings: sqrt(w) less noise);
    # every point is held to it, so an averaged point is never flagged for a misfit smaller
    # than one reading's noise, and a lone spike still is
    f_scale = robust_sigma(model.weighted_residuals(params))
    candidates = np.abs(start_residuals) <= max(GROSS_OUTLIER_SIGMAS, outlier_threshold) * f_scale
    if candidates.sum() > n_params:
        subset = model.subset(candidates)
        robust = least_squares(
            subset.residuals, params, jac=subset.jacobian, loss=subset.robust_loss(),
            f_scale=f_scale, method='trf', x_scale=1.0, max_nfev=50,
        )  # fmt: skip
        params = _better(model, params, robust.x)
    residuals = model.residuals(params)
    sigma = robust_sigma(model.weighted_residuals(params)[candidates])
    inliers = np.abs(residuals) <= outlier_threshold * sigma
    if inliers.sum() > n_params:
        inlier_model = model.subset(inliers)
        final = least_squares(
            inlier_model.weighted_residuals, params, jac=inlier_model.weighted_jacobian,
            method='lm', max_nfev=100,
        )
        params = _better(model, params, final.x)
        residuals = model.residuals(params)
        sigma = robust_sigma(model.weighted_residuals(params)[inliers])
        inliers = np.abs(residuals) <= outlier_threshold * sigma
    final_model = model.subset(inliers)
    condition, std = _condition_and_std(final_model.jacobian(params), residuals[inliers])
    if weights is not None:  # determinacy from the geometry, precision from the weights
        _, std = _condition_and_std(
            final_model.weighted_jacobian(params), final_model.weighted_residuals(params)
        )
    fitted_centre, fitted_matrix = model.unpack(params)
    return _Refined(fitted_centre, fitted_matrix, residuals, inliers, condition, std)


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


def _condition_and_std(
    jacobian: np.ndarray, residuals: np.ndarray
) -> tuple[float, np.ndarray | None]:
    """Condition number of J and parameter 1-sigma from sigma² (JᵀJ)⁻¹ (via the SVD)."""
    n, p = jacobian.shape
    if n == 0 or not np.all(np.isfinite(jacobian)):
        return np.inf, None
    _, singular, vt = np.linalg.svd(jacobian, full_matrices=False)
    if singular[-1] <= 0:
        return np.inf, None
    condition = float(singular[0] / singular[-1])
    if n <= p:
        return condition, None
    variance = float(residuals @ residuals) / (n - p)
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
) -> EllipsoidFit | None:
    """Fit ``model`` (one of FIT_MODELS) to finite (n, 3) input-unit points; None when impossible.

    ``prior`` is (offset, unit-radius matrix) in input units, used by ``planar`` out of the plane.
    ``weights`` (n,) are finite and > 0 (see the module docstring), or None for equal weights.
    """
    if model not in FIT_MODELS:
        raise ValueError(f'unknown fit model {model!r}; expected one of {FIT_MODELS}')
    if len(points) < PARAMETER_COUNTS[model] + 1:
        return None
    norm = normalise(points)
    if norm is None:
        return None
    y = norm.forward(points)
    with np.errstate(all='ignore', under='ignore'):
        try:
            if model == 'planar':
                return _fit_planar(points, outlier_threshold, prior, weights)
            fitted = _fit_3d(y, model, outlier_threshold, weights)
        except (np.linalg.LinAlgError, ValueError):
            return None
    if fitted is None:
        return None
    return _to_input_units(fitted, norm, model)


def _fit_3d(
    y: np.ndarray, model: str, outlier_threshold: float, weights: np.ndarray | None = None
) -> _Refined | None:
    if model == 'axis':
        solved = axis_least_squares(y, weights)
        if solved is None:
            return None
        centre, semi_axes = solved
        matrix = np.diag(1.0 / semi_axes)
        residuals = np.linalg.norm((y - centre) @ matrix, axis=1) - 1.0
        inliers = np.abs(residuals) <= outlier_threshold * robust_sigma(residuals)
        jacobian = _Geometric(y[inliers], spherical=False).jacobian(
            np.concatenate([centre, matrix[np.triu_indices(3)]])
        )[:, [0, 1, 2, 3, 6, 8]]  # b and the diagonal of M: the axis model's own parameters
        condition, _ = _condition_and_std(jacobian, residuals[inliers])
        return _Refined(centre, matrix, residuals, inliers, condition, None)
    # the unit sphere about the median is the fallback start: the normalisation put it there
    sphere = trimmed_start(y, _sphere_start, outlier_threshold, weights)
    sphere = sphere or (np.zeros(3), np.eye(3))
    if model == 'sphere':
        return _refine(y, sphere[0], sphere[1], True, outlier_threshold, weights=weights)
    start = trimmed_start(y, quadric_least_squares, outlier_threshold, weights) or sphere
    return _refine(y, start[0], start[1], False, outlier_threshold, weights=weights)


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
        _radius(matrix), _ratio(matrix), std,
    )  # fmt: skip


def _radius(matrix: np.ndarray) -> float:
    determinant = float(np.linalg.det(matrix))
    return determinant ** (-1.0 / 3.0) if determinant > 0 else np.inf


def _fit_planar(
    points: np.ndarray,
    outlier_threshold: float,
    prior: tuple[np.ndarray, np.ndarray] | None,
    weights: np.ndarray | None = None,
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
    flat = _fit_ellipse_2d(w[:, :2], outlier_threshold, weights)
    if flat is None:
        return None
    if prior is not None:
        prior_normal = float(basis[:, 2] @ (-norm.centre / norm.scale))
        in_3d = _planar_in_3d(w, norm.scale, prior_normal, flat, outlier_threshold, weights)
        if in_3d is not None:
            return _planar_result(
                points, in_3d, basis, norm, prior_offset, prior_matrix, False, weights
            )
    if prior is None:  # tilts while turning may determine the offset along the normal
        tilted = _planar_tilted(w, basis, flat, outlier_threshold, weights)
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
        flat.condition, flat.std,
    )  # fmt: skip
    return _planar_result(points, rotated, basis, norm, prior_offset, prior_matrix, True, weights)


def _fit_ellipse_2d(
    in_plane: np.ndarray, outlier_threshold: float, weights: np.ndarray | None = None
) -> _Refined | None:
    start = trimmed_start(in_plane, quadric_least_squares, outlier_threshold, weights)
    if start is None:
        start = trimmed_start(in_plane, _sphere_start, outlier_threshold, weights)
    if start is None:
        centre = np.median(in_plane, axis=0)
        radius = float(np.median(np.linalg.norm(in_plane - centre, axis=1)))
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
) -> _Refined | None:
    """3-D residual, in-plane parameters free, the rest at the prior (``s I`` centred on it)."""
    centre = np.append(flat.centre, prior_normal)
    vertical = scale * (w[flat.inliers, 2] - prior_normal)
    horizontal_share = np.sqrt(max(1.0 - float(np.mean(vertical**2)), 0.05))
    matrix = scale * np.eye(3)
    matrix[:2, :2] = flat.matrix * horizontal_share
    refined = _refine(w, centre, matrix, False, outlier_threshold, _IN_PLANE, weights)
    if np.linalg.eigvalsh(refined.matrix).min() <= 0:
        return None
    std = None
    if refined.std is not None:  # in-plane offset in normalised units, matrix relative to s
        std = np.concatenate([refined.std[:2], refined.std[2:] / scale])
    return _Refined(
        refined.centre, refined.matrix, refined.residuals, refined.inliers, refined.condition, std
    )


MAX_NORMAL_OFFSET_STD = 0.05
"""The offset along the plane normal counts as observed only when its 1-sigma is below 5 % of the
field (2.5 µT at 50 µT) and the 3-D fit explains the data better than the 2-D ellipse by the
information criterion (``TILT_EVIDENCE``); a level ring determines it not at all, and the fit
then falls back to the 2-D ellipse and reports it unobserved."""

TILT_EVIDENCE = 10.0
"""BIC margin the 3-D (tilted) planar fit must win by: 'very strong' evidence on the usual scale,
so noise alone (whose normal component the regression would otherwise fit) never frees the
offset along the normal."""

_TILTED = np.array([0, 1, 2, 3, 4, 6])
"""Parameters [b_u, b_v, b_n, M_uu, M_uv, M_vv] of the 3-D model in the plane's frame."""


def _planar_tilted(
    w: np.ndarray,
    basis: np.ndarray,
    flat: _Refined,
    outlier_threshold: float,
    weights: np.ndarray | None = None,
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
        refined = _refine(w, centre, matrix, False, outlier_threshold, _TILTED, weights)
        if np.linalg.det(refined.matrix[:2, :2]) <= 0:
            return None
        centre = refined.centre
        matrix = _held_out_of_plane(refined.matrix[:2, :2], body_axis)
    if refined.std is None or np.linalg.eigvalsh(refined.matrix).min() <= 0:
        return None
    field_radius = 1.0 / np.sqrt(np.linalg.det(refined.matrix[:2, :2]))
    normal_std = float(refined.std[2]) / field_radius
    if not (np.isfinite(normal_std) and normal_std <= MAX_NORMAL_OFFSET_STD):
        return None
    # evidence: the same points' residuals in the same (normalised input) units, 2-D vs 3-D
    common = flat.inliers & refined.inliers
    flat_radius = 1.0 / np.sqrt(np.linalg.det(flat.matrix))
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
        refined.centre, refined.matrix, refined.residuals, refined.inliers, flat.condition, std
    )
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
        headings=np.arctan2(unit[:, 1], unit[:, 0]),
    )  # fmt: skip


def _symmetric_polar_factor(matrix: np.ndarray) -> np.ndarray:
    """P of M = R P: the same magnitudes |M v| = |P v|, without M's rotation (the symmetric
    convention every calibration here uses; a prior times a correction is not symmetric)."""
    _, singular, vt = np.linalg.svd(matrix)
    return (vt.T * singular) @ vt


def information_criterion(residuals: np.ndarray, n_params: int) -> float:
    """BIC of a least-squares fit with Gaussian residuals: n log(RSS/n) + k log(n)."""
    n = len(residuals)
    rss = max(float(residuals @ residuals), 1e-300)
    return n * np.log(rss / n) + n_params * np.log(n)
