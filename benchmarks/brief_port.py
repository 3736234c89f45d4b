# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""A faithful Python/numpy port of the brief's Rust library (peterkrull/mag-calibrator-rs).

This is the yardstick issue #2 measures the engine against, so it reproduces the original's
behaviour, quirks included, rather than fixing them (the fixes live in
``mag_calibrator_ros.calibration``). Source: ``evaluate_sample_vec`` and ``perform_calibration``
in ``src/lib.rs`` of peterkrull/mag-calibrator-rs.

What is ported, one function per Rust method:

- ``MagCalibrator<N>``: a fixed ``N x 6`` float32 matrix initialised to 1.0 everywhere, ``k = 2``
  neighbours and ``pre_scaler = 1`` by default.
- ``evaluate_sample_vec``: the first N samples are stored as they come; after that every sample
  recomputes the full N x N distance matrix, sorts every row completely (O(N^2 log N) per sample,
  as the Rust code does) and replaces the buffered row with the lowest mean k-NN distance when
  the candidate's own mean distance is strictly larger.
- ``perform_calibration``: columns 3 and 4 become -y^2 and -z^2, column 5 keeps its initial 1.0,
  ``w = x^2``, ``X = (H^T H)^-1 H^T w`` via the normal equations in float32, then
  ``off = [X0/2, X1/(2 X3), X2/(2 X4)]``, ``temp = X5 + off0^2 + X3 off1^2 + X4 off2^2``,
  ``scale = [sqrt(temp), sqrt(temp/X3), sqrt(temp/X4)]``; ``None`` when the inverse does not exist
  or any value is not finite. Corrected field: ``(raw / pre_scaler - off) / scale`` (unit sphere).

Quirks reproduced on purpose (each one is a measured weakness listed in issue #2):

1. float32 throughout, on uncentred data: with a hard-iron offset several times the field the
   normal equations lose most of their digits and the fit degrades or returns ``None``.
2. Axis-aligned model: no soft-iron cross terms.
3. Inconsistent uniqueness scoring. ``mean_distance_from_single`` sums the ``k + 1`` smallest
   distances and divides by ``N``. For a buffered point the smallest is its zero self-distance, so
   it is scored on k neighbours; the candidate is not in the buffer, so it is scored on k + 1
   real neighbours and nearly always wins: crowded samples get in.
4. The candidate is scored in raw units while the buffer holds ``raw / pre_scaler``: with any
   ``pre_scaler`` other than 1 the candidate is far from every buffered point and is always
   accepted (it replaces the most crowded buffered row).
5. No duplicate check and no outlier screening: spikes are the most "unique" samples and stay.
6. Samples with any component that is not a normal float32 (NaN, Inf, subnormal **or exactly
   zero**) are silently dropped: the ``is_normal()`` guard of later library versions (the report's
   listing has no guard at all, so NaN would poison its buffer; we port the guarded version).
7. Calibrating a half-filled buffer silently fits the untouched dummy rows (1, 1, 1).
8. ``offset`` and ``scale`` come back in pre-scaled units (raw / pre_scaler), undocumented.
9. ``mean_distance`` is divided by N, so any "good enough" threshold on it depends on N.

Known, harmless differences: BLAS and LAPACK sum in a different order than nalgebra, so float32
results agree to rounding, not bit for bit; nalgebra's ``try_inverse`` (LU, partial pivoting) is
``scipy.linalg.inv`` (float32 LAPACK) here, both failing only on an exactly zero pivot.
"""

from __future__ import annotations

import warnings

import numpy as np
from numpy.typing import ArrayLike
import scipy.linalg

from mag_calibrator_ros.calibration import Calibration

F32 = np.float32
_TINY = np.finfo(np.float32).tiny  # smallest normal float32


def is_normal_f32(sample: ArrayLike) -> bool:
    """Rust's ``f32::is_normal`` on every component: finite, non-zero and not subnormal."""
    values = np.asarray(sample, dtype=F32)
    return bool(np.all(np.isfinite(values) & (np.abs(values) >= _TINY)))


class BriefMagCalibrator:
    """``MagCalibrator<N>`` of mag-calibrator-rs: a kNN uniqueness buffer and an axis fit."""

    def __init__(self, capacity: int, k: int = 2, pre_scaler: float = 1.0) -> None:
        if int(capacity) < 1:
            raise ValueError(f'capacity must be >= 1, got {capacity}')
        if int(k) < 0:
            raise ValueError(f'k must be >= 0, got {k}')
        self.capacity = int(capacity)
        self.k = int(k)
        self.pre_scaler = F32(pre_scaler)
        self.matrix = np.ones((self.capacity, 6), dtype=F32)  # SMatrix::from_element(1.0)
        self.matrix_filled = 0
        self.mean_distance = F32(0.0)

    # -- kNN uniqueness ------------------------------------------------------------------------

    def _knn_score(self, sorted_distances: np.ndarray) -> np.ndarray:
        """``take(k + 1).rfold(0, +) / N`` on rows of sorted distances, summed right to left."""
        total = np.zeros(sorted_distances.shape[:-1], dtype=F32)
        for column in range(min(self.k + 1, self.capacity) - 1, -1, -1):
            total = total + sorted_distances[..., column]
        return total / F32(self.capacity)

    def mean_distance_from_single(self, vec: ArrayLike) -> F32:
        """Mean distance of ``vec`` to its k + 1 nearest buffered rows (self included if there)."""
        diff = np.asarray(vec, dtype=F32) - self.matrix[:, :3]
        distances = np.sqrt(np.sum(diff * diff, axis=1, dtype=F32))
        return F32(self._knn_score(np.sort(distances)))

    def mean_distance_from_all(self) -> np.ndarray:
        """The score of every buffered row: N full distance lists, each sorted completely."""
        points = self.matrix[:, :3]
        diff = points[:, None, :] - points[None, :, :]
        distances = np.sqrt(np.sum(diff * diff, axis=2, dtype=F32))
        return self._knn_score(np.sort(distances, axis=1))

    def lowest_mean_distance_by_index(self) -> tuple[int, F32]:
        """Row with the lowest score (first on ties, as ``min_by``); updates ``mean_distance``."""
        mean_dist = self.mean_distance_from_all()
        self.mean_distance = F32(np.cumsum(mean_dist[::-1], dtype=F32)[-1] / F32(self.capacity))
        index = int(np.argmin(mean_dist))
        return index, F32(mean_dist[index])

    def add_sample_at(self, index: int, sample: np.ndarray) -> None:
        """Store ``sample / pre_scaler`` in row ``index`` (columns 0-2 only)."""
        if index < self.capacity:
            self.matrix[index, :3] = sample / self.pre_scaler

    def evaluate_sample(self, sample: ArrayLike) -> str:
        """``evaluate_sample_vec``. Returns what happened (the Rust method returns nothing):
        'dropped' (a component is not a normal float), 'added', 'replaced' or 'not_unique'."""
        x = np.asarray(sample, dtype=F32).reshape(3)
        if not is_normal_f32(x):
            return 'dropped'
        if self.matrix_filled < self.capacity:
            self.add_sample_at(self.matrix_filled, x)
            self.matrix_filled += 1
            return 'added'
        low_index, low_mean_dist = self.lowest_mean_distance_by_index()
        # The candidate is scored in raw units against pre-scaled rows (quirk 4).
        sample_mean_dist = self.mean_distance_from_single(x)
        if low_mean_dist < sample_mean_dist:
            self.add_sample_at(low_index, x)
            return 'replaced'
        return 'not_unique'

    @property
    def samples(self) -> np.ndarray:
        """The buffered rows in raw units (float64 copy), dummy rows excluded."""
        return self.matrix[: self.matrix_filled, :3].astype(float) * float(self.pre_scaler)

    # -- least squares -------------------------------------------------------------------------

    def perform_calibration(self) -> tuple[np.ndarray, np.ndarray] | None:
        """``(offset, scale)`` in pre-scaled units, or ``None``: the report's listing exactly."""
        self.matrix[:, 3] = -self.matrix[:, 1] * self.matrix[:, 1]
        self.matrix[:, 4] = -self.matrix[:, 2] * self.matrix[:, 2]
        w = self.matrix[:, 0] * self.matrix[:, 0]
        h = self.matrix
        with np.errstate(all='ignore'), warnings.catch_warnings():
            # Ill-conditioning is the quirk being measured, not news: no LinAlgWarning spam.
            warnings.simplefilter('ignore', scipy.linalg.LinAlgWarning)
            try:
                # scipy keeps float32 (sgetrf/sgetri); numpy.linalg.inv would compute in float64.
                normal_inverse = scipy.linalg.inv(h.T @ h, check_finite=False)
            except (np.linalg.LinAlgError, ValueError):
                return None
            x = (normal_inverse @ h.T) @ w
            two = F32(2.0)
            off = np.array([x[0] / two, x[1] / (two * x[3]), x[2] / (two * x[4])], dtype=F32)
            temp = x[5] + off[0] * off[0] + x[3] * (off[1] * off[1]) + x[4] * (off[2] * off[2])
            scale = np.sqrt(np.array([temp, temp / x[3], temp / x[4]], dtype=F32))
        if not (np.all(np.isfinite(off)) and np.all(np.isfinite(scale))):
            return None
        return off, scale

    def to_calibration(self, offset: np.ndarray, scale: np.ndarray) -> Calibration | None:
        """The result as a raw-unit :class:`Calibration` (normalised, F = 1), for comparisons.

        ``(raw / p - off) / scale`` equals ``M (raw - b)`` with ``b = p off`` and
        ``M = diag(1 / (p scale))``. ``None`` when a scale is zero (not a usable calibration).
        """
        p = float(self.pre_scaler)
        scale = np.asarray(scale, dtype=float)
        if np.any(scale <= 0.0):
            return None
        return Calibration(
            np.asarray(offset, dtype=float) * p,
            np.diag(1.0 / (scale * p)),
            1.0,
            model='axis',
            metadata={'source': 'brief_port', 'capacity': self.capacity, 'k': self.k},
        )


def brief_calibrate(
    samples: ArrayLike, capacity: int = 50, k: int = 2, pre_scaler: float = 1.0
) -> tuple[Calibration | None, BriefMagCalibrator]:
    """Stream ``samples`` through the brief's buffer, then fit it as the library's user would."""
    calibrator = BriefMagCalibrator(capacity, k=k, pre_scaler=pre_scaler)
    for sample in np.asarray(samples, dtype=float).reshape(-1, 3):
        calibrator.evaluate_sample(sample)
    result = calibrator.perform_calibration()
    if result is None:
        return None, calibrator
    return calibrator.to_calibration(*result), calibrator
