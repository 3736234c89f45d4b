# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Planar calibration levelled by gravity: a ground robot that tilts while it turns.

A robot turning on a real floor tilts a few degrees, and a tilt of θ moves about V θ of the
vertical field V into the chip's x-y plane: the horizontal readings no longer lie on one ellipse,
and a fit that cannot see the tilt takes part of it for soft iron (about 1.5° of heading error
for 2° of wobble at 60° inclination). Even on a level floor a 2-D fit leaves the corrected ring
in the plane of the raw readings, which soft iron tilts off the yaw axis, and the heading in the
chip frame then carries a second-harmonic error.

With the accelerometer paired to each reading, ``up`` (gravity's direction in the chip frame,
the accelerometer at rest: specific force points up) is known per sample. In the frame it
levels, the true field has a constant horizontal magnitude H and a constant vertical component V
(the angle between field and gravity is fixed: the invariant joint accelerometer-magnetometer
calibration rests on, Papafotis and Sotiriadis, "Accelerometer and Magnetometer Joint
Calibration and Axes Alignment", Technologies 8(1):11, 2020). Fitting both to
``c = M (x - b)`` with ``M`` symmetric fixes what a turn about one axis leaves open: the
corrected ring is perpendicular to gravity, its heading (rotation about the vertical) is the
symmetric one, and a tilt explains the wobble instead of bending the shape. As in the plain
planar fit, the out-of-plane scale is held at the in-plane one; the offset along the plane normal
(and with it V, the dip) is fitted unless the tilts leave it degenerate (a level floor), then held
at the plain fit's. A refinement weighs it with what the calibration in force knew of it (a
Gaussian prior of that fit's own 1-sigma), and keeps that on a level floor: the held-out |B|
residuals that judge a refinement barely see it, so a refit on a few headings must not move it
by more than its data tell.

The model is fitted with H = 1 (the horizontal ring has unit radius), so no scale can shrink its
residuals, and each residual is taken over how far the raw reading's noise moves it (to first
order the reading's distance from the model in its own units). The result is an
:class:`EllipsoidFit` like every other (``|unit| ≈ 1`` on the full field), so gates, evidence
and the magnitude checks judge it the same way.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .ellipsoid import EllipsoidFit, robust_sigma

MIN_PAIRED_SHARE = 0.8
"""Share of the readings that must carry gravity: a ring half of whose readings came without it
(an IMU that started late, dropped messages, a robot accelerating: ``live/gravity.py``) levels
only part of the turn."""

MAX_UP_TO_NORMAL_DEG = 30.0
"""Gravity must lie within this of the plane of the turn's normal: soft iron tilts the raw plane
a few degrees (up to about 10° for off-diagonals of 0.15), a turn about another axis is no
ground robot turning, and levelling it by gravity would be wrong."""

MIN_POINTS = 12
"""Fewest paired readings to level with: twice the parameters."""

MAX_NORMAL_OFFSET_STD = 0.05
"""The offset along the normal (hence the dip) is reported as observed when its 1-sigma is below
5 % of the field (the plain planar fit's bar). A less certain one still levels the tilts far
better than none: its error leaks into the heading only times the tilt (0.1 H x 2° is 0.2°)."""

MAX_CONDITION = 1e6
"""Condition number of the column-scaled Jacobian beyond which the offset along the normal and
the dip are not determined at all (a level floor: they trade one for the other exactly); the
plain fit's offset is then held, which a level floor's heading does not depend on."""

MAX_RESIDUAL_GROWTH = 1.1
"""The levelled fit replaces the plain one only if its horizontal residual (in the frame gravity
levels) is at most 10 % above the plain fit's on the same samples: gravity explains tilt, it
must not buy a worse ring (a disturbed field, an accelerometer shaken by the drive)."""


@dataclass(frozen=True)
class Levelling:
    """What levelling by gravity gave: ``unit = matrix (x - offset)``, ``|unit| ≈ 1`` on the full
    field (None: the plain fit stands, ``note`` says why)."""

    offset: np.ndarray | None
    matrix: np.ndarray | None
    note: str
    dip_deg: float | None = None
    """The fitted inclination when the tilts determined it, else None."""
    normal_std: float | None = None
    """The offset along the normal's 1-sigma from this fit's own readings, relative to the
    field (None: held, not fitted)."""

    def ellipsoid_fit(self, rows: np.ndarray, plain: EllipsoidFit,
                      outlier_threshold: float) -> EllipsoidFit:
        """The levelled calibration judged on ``rows`` (the samples the plain fit was judged on):
        magnitude residuals and inliers as every model reports them."""
        corrected = (rows - self.offset) @ self.matrix.T
        residuals = np.linalg.norm(corrected, axis=1) - 1.0
        inliers = np.abs(residuals) <= outlier_threshold * robust_sigma(residuals)
        normal = plain.plane_normal
        basis = _basis(normal)
        in_plane = corrected @ basis
        block = (basis.T @ self.matrix @ basis)[:2, :2]
        eigenvalues = np.linalg.eigvalsh(block)
        return EllipsoidFit(
            'planar', self.offset, self.matrix, residuals, inliers, plain.condition,
            float(np.linalg.det(self.matrix) ** (-1.0 / 3.0)),
            float(eigenvalues.max() / eigenvalues.min()), plain.parameter_std,
            unobserved=('matrix_normal',) if self.dip_deg is not None
            else ('offset_normal', 'matrix_normal'),
            plane_normal=normal, headings=np.arctan2(in_plane[:, 1], in_plane[:, 0]),
            robust=plain.robust, levelled=True, dip_deg=self.dip_deg,
            normal_offset_std=self.normal_std,
        )  # fmt: skip


def level_planar(
    points: np.ndarray,
    ups: np.ndarray,
    plain: EllipsoidFit,
    weights: np.ndarray | None = None,
    outlier_threshold: float = 4.0,
    known: tuple[np.ndarray, float] | None = None,
) -> Levelling:
    """Refit the planar fit ``plain`` on ``points`` (n, 3) with gravity directions ``ups`` (n, 3;
    NaN rows: none paired). Best on an unbiased draw of readings (SampleBuffer.readings): the
    most spread-out samples of a thin ring are the noisiest ones. Points off the plain fit by
    more than ``outlier_threshold`` robust sigmas are left out, then flagged again on the result.
    ``known``: (an offset (3,), its 1-sigma along the normal > 0), in the points' units: what
    the calibration in force knew of the offset along the normal, weighed in as a prior.
    """
    if plain.plane_normal is None or len(points) != len(ups):
        return Levelling(None, None, 'no plane to level')
    paired = np.all(np.isfinite(ups), axis=1) & np.all(np.isfinite(points), axis=1)
    paired[paired] = np.linalg.norm(ups[paired], axis=1) > 0
    if paired.sum() < MIN_PAIRED_SHARE * len(points) or paired.sum() < MIN_POINTS:
        return Levelling(None, None,
                         f'{int(paired.sum())} of {len(points)} readings carry gravity (paired '
                         'with the IMU while the robot did not accelerate)')
    up = np.full_like(points, np.nan)
    up[paired] = ups[paired] / np.linalg.norm(ups[paired], axis=1)[:, None]
    normal = np.asarray(plain.plane_normal, dtype=float)
    normal = normal / np.linalg.norm(normal)
    mean_up = np.mean(up[paired], axis=0)
    mean_up /= np.linalg.norm(mean_up)
    angle = float(np.degrees(np.arccos(min(abs(float(mean_up @ normal)), 1.0))))
    if angle > MAX_UP_TO_NORMAL_DEG:
        return Levelling(None, None,
                         f'gravity is {angle:.0f} deg off the turn axis: not a ground turn')
    model = _Model(points, up, _basis(normal), weights)
    start = model.start(plain, paired)
    if start is None:
        return Levelling(None, None, 'the plain fit gives no start')
    residuals = model.horizontal_residuals(start)
    inliers = paired.copy()
    inliers[paired] = np.abs(residuals[paired]) <= outlier_threshold * robust_sigma(
        residuals[paired])
    if inliers.sum() < MIN_POINTS:
        return Levelling(None, None, 'too few readings near the plain fit')
    fitted = model.solve(start, inliers, free_normal=True)
    held = fitted is None or model.degenerate()
    kept = held and known is not None and bool(np.all(np.isfinite(known[0])))
    if held:
        if kept:  # a level floor tells nothing of it: what the calibration in force knew stands
            start = start.copy()
            start[7] = model.along_normal(known[0])
        fitted = model.solve(start, inliers, free_normal=False)
    if fitted is None:
        return Levelling(None, None, 'the levelled fit did not converge')
    normal_std = (model.relative(fitted, known[1]) if kept else None) if held else (
        model.normal_std(fitted, inliers))
    observed = not held and normal_std is not None and normal_std <= MAX_NORMAL_OFFSET_STD
    weighed = not held and known is not None and model.know(known, fitted, inliers)
    if weighed:
        again = model.solve(fitted, inliers, free_normal=True)
        if again is None:
            model.prior, weighed = None, False
        else:
            fitted = again
    prior_std = model.relative(fitted, known[1]) if weighed else None
    # said where the prior carried at least a tenth of what the readings told of it
    weighed_much = (prior_std is not None and normal_std is not None
                    and (normal_std / prior_std) ** 2 >= 0.1)
    level = model.horizontal_residuals(fitted)
    refit = paired.copy()
    refit[paired] = np.abs(level[paired]) <= outlier_threshold * robust_sigma(level[paired])
    if refit.sum() >= MIN_POINTS and not np.array_equal(refit, inliers):
        again = model.solve(fitted, refit, free_normal=not held)
        if again is not None:
            fitted, inliers = again, refit
            level = model.horizontal_residuals(fitted)
    plain_rms = float(np.sqrt(np.mean(residuals[inliers] ** 2)))
    level_rms = float(np.sqrt(np.mean(level[inliers] ** 2)))
    if not level_rms <= MAX_RESIDUAL_GROWTH * plain_rms:
        return Levelling(None, None, f'levelled residual {100 * level_rms:.2f} % exceeds the '
                         f"plain fit's {100 * plain_rms:.2f} %")
    offset, matrix = model.calibration(fitted)
    if not (np.all(np.isfinite(matrix)) and np.all(np.isfinite(offset))
            and np.linalg.eigvalsh(matrix).min() > 0):
        return Levelling(None, None, 'the levelled soft-iron matrix is not positive definite')
    dip = float(np.degrees(np.arctan(abs(fitted[8]))))
    said = ([f'dip {dip:.1f} deg fitted'] if observed else []) + (
        ["the offset along the turning axis weighed with the calibration in force's"]
        if weighed_much else
        ["the offset along the turning axis kept at the calibration in force's"]
        if kept else [])
    note = 'levelled by gravity' + (f' ({"; ".join(said)})' if said else '')
    return Levelling(offset, matrix, note, dip if observed else None, normal_std)


def _basis(normal: np.ndarray) -> np.ndarray:
    """Orthonormal columns (u, v, n), right-handed, n the plane normal."""
    helper = np.eye(3)[int(np.argmin(np.abs(normal)))]
    u = np.cross(helper, normal)
    u /= np.linalg.norm(u)
    return np.column_stack([u, np.cross(normal, u), normal])


class _Model:
    """Parameters p = [A_uu, A_uv, A_vv, k_u, k_v, b_u, b_v, b_n, V] in the plane's frame:
    ``M = [[A, k], [kᵀ, sqrt(det A)]]``, offset ``b``, vertical component V (H = 1)."""

    def __init__(self, rows: np.ndarray, up: np.ndarray, basis: np.ndarray,
                 weights: np.ndarray | None) -> None:
        self.basis = basis
        self.mean = np.nanmean(rows, axis=0)
        self.w = (rows - self.mean) @ basis
        self.up = up @ basis
        self.root = None if weights is None else np.sqrt(np.asarray(weights, dtype=float))
        self.prior: tuple[float, float] | None = None
        """(offset along the normal, weight): one more residual, (b_n - offset) x weight."""

    @staticmethod
    def matrix(p: np.ndarray) -> np.ndarray:
        a = np.array([[p[0], p[1]], [p[1], p[2]]])
        m = np.empty((3, 3))
        m[:2, :2] = a
        m[:2, 2] = m[2, :2] = p[3:5]
        m[2, 2] = np.sqrt(max(float(np.linalg.det(a)), 1e-300))
        return m

    def start(self, plain: EllipsoidFit, paired: np.ndarray) -> np.ndarray | None:
        matrix = self.basis.T @ plain.matrix @ self.basis
        offset = self.basis.T @ (plain.offset - self.mean)
        corrected = (self.w[paired] - offset) @ matrix.T
        up = self.up[paired]
        vertical = np.einsum('ij,ij->i', corrected, up)
        horizontal = np.linalg.norm(corrected - vertical[:, None] * up, axis=1)
        scale = float(np.median(horizontal))
        if not (np.isfinite(scale) and scale > 0):
            return None
        matrix = matrix / scale
        v = float(np.median(vertical)) / scale
        return np.array([matrix[0, 0], matrix[0, 1], matrix[1, 1], matrix[0, 2], matrix[1, 2],
                         *offset, v])

    def _split(self, p: np.ndarray, rows: np.ndarray | slice
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(matrix, gravity's directions, the corrected readings across them, along them)."""
        matrix = self.matrix(p)
        corrected = (self.w[rows] - p[5:8]) @ matrix.T
        up = self.up[rows]
        vertical = np.einsum('ij,ij->i', corrected, up)
        return matrix, up, corrected - vertical[:, None] * up, vertical

    def parts(self, p: np.ndarray, rows: np.ndarray | slice = slice(None)
              ) -> tuple[np.ndarray, np.ndarray]:
        _, _, across, vertical = self._split(p, rows)
        return np.linalg.norm(across, axis=1), vertical

    def horizontal_residuals(self, p: np.ndarray) -> np.ndarray:
        return self.parts(p)[0] - 1.0

    def _residuals(self, p: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """Each residual over its noise gain, how far it moves per unit the raw reading moves:
        to first order the reading's distance from the model in its own units (Sampson,
        "Fitting conic sections to 'very scattered' data", CGIP 18(1):97-108, 1982; gradient-
        weighted, as Taubin, IEEE PAMI 13(11), 1991). Unscaled, the noise pulled the weakly
        seen offset along the normal by about the noise squared, with or without soft iron,
        most on readings that dwell at a few headings (BENCHMARKS.md, "The levelled fit and
        noise"); a prior (``know``) is one more residual."""
        matrix, up, across, vertical = self._split(p, rows)
        horizontal = np.maximum(np.linalg.norm(across, axis=1), 1e-300)
        horizontal_gain = np.linalg.norm((across / horizontal[:, None]) @ matrix, axis=1)
        vertical_gain = np.linalg.norm(up @ matrix, axis=1)
        e = np.concatenate([(horizontal - 1.0) / horizontal_gain,
                            (vertical - p[8]) / vertical_gain])
        if self.root is not None:
            e = e * np.tile(self.root[rows], 2)
        if self.prior is not None:
            e = np.append(e, (p[7] - self.prior[0]) * self.prior[1])
        return e

    def solve(self, start: np.ndarray, rows: np.ndarray, free_normal: bool) -> np.ndarray | None:
        from scipy.optimize import least_squares  # the fit worker's import, not a node start-up

        free = np.ones(9, dtype=bool)
        if not free_normal:
            free[7] = False

        def residuals(q: np.ndarray) -> np.ndarray:
            p = start.copy()
            p[free] = q
            return self._residuals(p, rows)

        try:
            solution = least_squares(residuals, start[free], method='lm', x_scale='jac')
        except (ValueError, np.linalg.LinAlgError):
            return None
        p = start.copy()
        p[free] = solution.x
        if not (np.all(np.isfinite(p)) and np.linalg.eigvalsh(self.matrix(p)).min() > 0):
            return None
        self._jacobian = solution.jac
        self._cost = float(2.0 * solution.cost)
        self._free = free
        return p

    def degenerate(self) -> bool:
        """Whether the last solve's parameters are not all determined (column-scaled)."""
        norms = np.linalg.norm(self._jacobian, axis=0)
        if not np.all(norms > 0):
            return True
        singular = np.linalg.svd(self._jacobian / norms, compute_uv=False)
        return not singular[-1] * MAX_CONDITION > singular[0]

    def normal_std(self, p: np.ndarray, rows: np.ndarray) -> float | None:
        """The offset along the normal's 1-sigma relative to the field, from the last (free,
        prior-less) solve's Jacobian; None when it cannot be had."""
        jacobian, dof = self._jacobian, 2 * int(rows.sum()) - int(self._free.sum())
        if dof <= 0 or not self._free[7]:
            return None
        try:
            covariance = np.linalg.inv(jacobian.T @ jacobian) * (self._cost / dof)
        except np.linalg.LinAlgError:
            return None
        return self.relative(p, float(np.sqrt(max(covariance[7, 7], 0.0))))

    def along_normal(self, offset: np.ndarray) -> float:
        """An offset (input units) as this model's offset along the normal."""
        return float(self.basis[:, 2] @ (np.asarray(offset, dtype=float) - self.mean))

    def relative(self, p: np.ndarray, std: float) -> float | None:
        """A 1-sigma of the offset along the normal (input units) as a share of the field."""
        scale = float(np.sqrt(np.linalg.det(self.matrix(p)[:2, :2])))  # 1 / H in input units
        relative = float(std) * scale / float(np.hypot(1.0, p[8]))
        return relative if np.isfinite(relative) and relative > 0.0 else None

    def know(self, known: tuple[np.ndarray, float], p: np.ndarray, rows: np.ndarray) -> bool:
        """Take ``known`` (offset, its 1-sigma along the normal, input units) as the prior of
        the offset along the normal, weighed against the readings' noise as the last solve
        (at ``p``, on ``rows``) measured it; False when either is unusable."""
        offset, std = np.asarray(known[0], dtype=float), float(known[1])
        dof = 2 * int(rows.sum()) - int(self._free.sum())
        if offset.shape != (3,) or not (np.all(np.isfinite(offset)) and std > 0.0
                                        and np.isfinite(std) and dof > 0):
            return False
        noise = float(np.sqrt(self._cost / dof))  # per unit weight, in the points' units
        if not (np.isfinite(noise) and noise > 0.0):
            return False
        self.prior = (self.along_normal(offset), noise / std)
        return True

    def calibration(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(offset, matrix) in input units, ``|unit| = 1`` on the full field (H = 1, V)."""
        field = float(np.hypot(1.0, p[8]))
        matrix = self.basis @ self.matrix(p) @ self.basis.T / field
        return self.mean + self.basis @ p[5:8], matrix
