# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The calibration value shared by every layer: ``corrected = R M (raw - b - K u - c (T - T0))``.

``b`` and ``M`` (hard and soft iron) make the field a sphere; ``R`` rotates the corrected field
into the IMU's frame (identity unless aligned to an accelerometer, see ``alignment``): a sphere
fit cannot see a rotation, so ``R`` comes from gravity, never from the magnetometer alone.
``K u + c (T - T0)`` (a :class:`Compensation`) is the robot's own field: ``u`` the k interference
inputs (a battery or motor current, a speed), ``K`` their 3 x k coefficients (field units per
input unit), ``T`` the sensor's temperature and ``c`` the hard iron's drift per degree around the
temperature ``T0`` it was learned at. Without a compensation (``K = 0``, ``c = 0``) the
calibration is the static ``R M (raw - b)``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

MODELS = ('sphere', 'axis', 'full', 'planar', 'auto')
"""Fit models. ``auto`` names a request only; a fitted calibration carries the model chosen."""

ROTATION_TOLERANCE = 1e-4
"""Largest |R^T R - I| element and |det R - 1| accepted for a rotation."""


class CalibrationError(ValueError):
    """A calibration's numbers are unusable (wrong shape, non-finite, not positive definite)."""


def calibration_problems(offset: ArrayLike, matrix: ArrayLike, field_strength: float,
                         rotation: ArrayLike | None = None) -> list[str]:
    """Say, in words a user can act on, everything wrong with these calibration numbers."""
    problems = []
    b = np.asarray(offset, dtype=float)
    m = np.asarray(matrix, dtype=float)
    if b.shape != (3,):
        problems.append(f'offset must have 3 elements, got shape {b.shape}')
    elif not np.all(np.isfinite(b)):
        problems.append(f'offset has non-finite values: {b.tolist()}')
    if m.shape != (3, 3):
        problems.append(f'matrix must be 3x3 (9 elements row-major), got shape {m.shape}')
    elif not np.all(np.isfinite(m)):
        problems.append('matrix has non-finite values')
    else:
        symmetric = 0.5 * (m + m.T)
        eigenvalues = np.linalg.eigvalsh(symmetric)
        if eigenvalues.min() <= 0.0:
            problems.append(
                f'matrix is not positive definite (eigenvalues of its symmetric part: '
                f'{np.round(eigenvalues, 6).tolist()})'
            )
    if not np.isfinite(field_strength) or field_strength <= 0.0:
        problems.append(f'field_strength must be a positive finite number, got {field_strength}')
    if rotation is not None:
        problems += rotation_problems(rotation)
    return problems


def rotation_problems(rotation: ArrayLike) -> list[str]:
    """Everything that keeps ``rotation`` from being a proper rotation (R^T R = I, det R = +1)."""
    try:
        r = np.asarray(rotation, dtype=float)
    except (TypeError, ValueError):
        return ['rotation must be a list of 9 numbers (row-major)']
    if r.size != 9:
        return [f'rotation must have 9 numbers, got {r.size}']
    r = r.reshape(3, 3)
    if not np.all(np.isfinite(r)):
        return ['rotation has non-finite values']
    error = float(np.max(np.abs(r.T @ r - np.eye(3))))
    if error > ROTATION_TOLERANCE:
        return [f'rotation is not orthonormal (R^T R differs from identity by {error:.2g}, '
                f'tolerance {ROTATION_TOLERANCE:g})']
    determinant = float(np.linalg.det(r))
    if abs(determinant - 1.0) > ROTATION_TOLERANCE:
        return [f'rotation has determinant {determinant:.6g}: a reflection, not a rotation']
    return []


@dataclass(frozen=True)
class Compensation:
    """The robot's own field at the sensor: ``K u + c (T - T0)``, in the calibration's units.

    ``inputs`` names the k interference inputs in the order of ``K``'s columns (what the node
    subscribes, e.g. ``battery_state:sensor_msgs/msg/BatteryState:current``); ``interference``
    is ``K`` (3, k), ``temperature_coefficient`` is ``c`` (3,) per degree Celsius and
    ``reference_temperature`` ``T0`` in degrees Celsius (needed when ``c`` is not zero). An
    input or temperature that is unknown for a reading contributes nothing: the field at the
    inputs' reference (u = 0, T = T0) is what the static part describes.
    """

    inputs: tuple[str, ...] = ()
    interference: np.ndarray | None = None
    temperature_coefficient: np.ndarray | None = None
    reference_temperature: float | None = None

    def __post_init__(self) -> None:
        problems = compensation_problems(self.inputs, self.interference,
                                         self.temperature_coefficient,
                                         self.reference_temperature)
        if problems:
            raise CalibrationError('; '.join(problems))
        k = len(self.inputs)
        gains = (np.zeros((3, k)) if self.interference is None
                 else np.array(self.interference, dtype=float).reshape(3, k))
        drift = (np.zeros(3) if self.temperature_coefficient is None
                 else np.array(self.temperature_coefficient, dtype=float).reshape(3))
        for array in (gains, drift):
            array.flags.writeable = False
        object.__setattr__(self, 'inputs', tuple(str(name) for name in self.inputs))
        object.__setattr__(self, 'interference', gains)
        object.__setattr__(self, 'temperature_coefficient', drift)
        if self.reference_temperature is not None:
            object.__setattr__(self, 'reference_temperature', float(self.reference_temperature))

    @property
    def empty(self) -> bool:
        """Whether it changes nothing (K = 0 and c = 0): today's static calibration."""
        return not (np.any(self.interference) or np.any(self.temperature_coefficient))

    def same_field(self, other: Compensation | None) -> bool:
        """Whether ``other`` takes off the same field: the same inputs, K, c and T0."""
        return other is not None and (
            self.inputs == other.inputs
            and np.array_equal(self.interference, other.interference)
            and np.array_equal(self.temperature_coefficient, other.temperature_coefficient)
            and self.reference_temperature == other.reference_temperature)

    def field(self, inputs: ArrayLike | None = None,
              temperature: ArrayLike | None = None) -> np.ndarray:
        """``K u + c (T - T0)`` for one reading (3,) or many (n, 3): ``inputs`` (k,) or (n, k),
        ``temperature`` a number or (n,). None, or a NaN entry (not known for that reading),
        contributes nothing."""
        total = np.zeros(3)
        if inputs is not None and len(self.inputs):
            u = np.nan_to_num(np.asarray(inputs, dtype=float), nan=0.0, posinf=0.0, neginf=0.0)
            total = total + u @ self.interference.T
        if temperature is not None and self.reference_temperature is not None:
            t = np.asarray(temperature, dtype=float) - self.reference_temperature
            t = np.nan_to_num(t, nan=0.0, posinf=0.0, neginf=0.0)
            total = total + np.multiply.outer(t, self.temperature_coefficient)
        return total

    def scaled(self, factor: float) -> Compensation:
        """The same compensation for input in other units (``raw_new = factor * raw``)."""
        return Compensation(self.inputs, self.interference * factor,
                            self.temperature_coefficient * factor, self.reference_temperature)


def compensation_problems(inputs: Sequence[str], interference: ArrayLike | None,
                          temperature_coefficient: ArrayLike | None,
                          reference_temperature: float | None) -> list[str]:
    """Everything wrong with a compensation's numbers, in words a user can act on."""
    problems = []
    if isinstance(inputs, str) or not all(isinstance(name, str) and name for name in inputs):
        return [f'interference_inputs must be a list of non-empty names, got {inputs!r}']
    k = len(inputs)
    if interference is not None:
        gains = np.asarray(interference, dtype=float)
        if gains.size != 3 * k:
            problems.append(f'interference must have 3 x {k} numbers (one column per input in '
                            f'interference_inputs, row-major), got {gains.size}')
        elif not np.all(np.isfinite(gains)):
            problems.append('interference has non-finite values')
    if temperature_coefficient is not None:
        drift = np.asarray(temperature_coefficient, dtype=float)
        if drift.shape != (3,):
            problems.append(f'temperature_coefficient must have 3 numbers, got {drift.size}')
        elif not np.all(np.isfinite(drift)):
            problems.append('temperature_coefficient has non-finite values')
        elif np.any(drift) and reference_temperature is None:
            problems.append('temperature_coefficient needs reference_temperature (the degrees '
                            'Celsius it was learned around)')
    if reference_temperature is not None and not math.isfinite(float(reference_temperature)):
        problems.append(f'reference_temperature must be finite, got {reference_temperature}')
    return problems


@dataclass(frozen=True)
class Calibration:
    """Hard-iron offset ``b``, soft-iron correction ``M`` and rotation ``R`` into the IMU frame;
    ``|corrected|`` is about ``F``; ``compensation`` (optional) removes the robot's own field
    first (``K u + c (T - T0)``, see :class:`Compensation`).

    Units are those of the raw input (tesla in the nodes, input units offline). ``rotation``
    None means identity; ``correction`` is the whole linear map ``R @ M`` (what ``apply`` uses
    and what a covariance transforms by). ``rotation`` is not metadata: a metadata key of that
    name is refused, so a rotation can never be silently ignored.
    """

    offset: np.ndarray
    matrix: np.ndarray
    field_strength: float = 1.0
    model: str = 'full'
    metadata: Mapping[str, Any] = field(default_factory=dict)
    rotation: np.ndarray | None = None
    compensation: Compensation | None = None

    def __post_init__(self) -> None:
        problems = calibration_problems(self.offset, self.matrix, self.field_strength,
                                        self.rotation)
        if 'rotation' in self.metadata:
            problems.append("'rotation' is a field of the calibration, not metadata "
                            '(Calibration(..., rotation=R))')
        if problems:
            raise CalibrationError('; '.join(problems))
        offset = np.array(self.offset, dtype=float).reshape(3)
        matrix = np.array(self.matrix, dtype=float).reshape(3, 3)
        rotation = (np.eye(3) if self.rotation is None
                    else np.array(self.rotation, dtype=float).reshape(3, 3))
        correction = rotation @ matrix
        for array in (offset, matrix, rotation, correction):
            array.flags.writeable = False
        object.__setattr__(self, 'offset', offset)
        object.__setattr__(self, 'matrix', matrix)
        object.__setattr__(self, 'rotation', rotation)
        object.__setattr__(self, 'field_strength', float(self.field_strength))
        object.__setattr__(self, 'metadata', dict(self.metadata))
        object.__setattr__(self, '_correction', correction)
        if self.compensation is not None and self.compensation.empty and not (
                self.compensation.inputs):
            object.__setattr__(self, 'compensation', None)  # K = 0, c = 0: the static one

    @property
    def correction(self) -> np.ndarray:
        """``R @ M``: the linear part of the correction (3, 3)."""
        return self._correction

    @property
    def aligned(self) -> bool:
        """Whether a rotation other than identity is in the calibration."""
        return not np.array_equal(self.rotation, np.eye(3))

    def field_radius(self) -> float:
        """The raw field's mean radius this calibration describes, in input units: the points
        with ``|M (x - b)| = F`` form an ellipsoid of mean radius ``F / det(M)^(1/3)``."""
        determinant = float(np.linalg.det(self.matrix))
        return self.field_strength / determinant ** (1.0 / 3.0) if determinant > 0 else 0.0

    @classmethod
    def identity(cls, field_strength: float = 1.0) -> Calibration:
        """No correction: useful as a tracker start or a prior."""
        return cls(np.zeros(3), np.eye(3), field_strength, model='identity')

    def apply(self, raw: ArrayLike, inputs: ArrayLike | None = None,
              temperature: ArrayLike | None = None) -> np.ndarray:
        """Correct one sample (3,) or many (n, 3): ``R M (raw - b - K u - c (T - T0))``; without
        ``inputs`` and ``temperature`` (or a compensation) the static ``R M (raw - b)``."""
        raw = self.compensated(raw, inputs, temperature)
        return (raw - self.offset) @ self._correction.T

    def compensated(self, raw: ArrayLike, inputs: ArrayLike | None = None,
                    temperature: ArrayLike | None = None) -> np.ndarray:
        """``raw - K u - c (T - T0)``: the reading without the robot's own field (``raw`` as is
        without a compensation), what the static part ``R M (x - b)`` describes."""
        raw = np.asarray(raw, dtype=float)
        if self.compensation is None or (inputs is None and temperature is None):
            return raw
        return raw - self.compensation.field(inputs, temperature)

    def unrotated(self, raw: ArrayLike) -> np.ndarray:
        """``M @ (raw - b)``: corrected in the magnetometer's own axes (before ``R``)."""
        raw = np.asarray(raw, dtype=float)
        return (raw - self.offset) @ self.matrix.T

    def with_compensation(self, compensation: Compensation | None,
                          offset: ArrayLike | None = None, **metadata: Any) -> Calibration:
        """A copy with ``compensation`` (None: none), optionally a new offset, and metadata."""
        return Calibration(self.offset if offset is None else offset, self.matrix,
                           self.field_strength, self.model, {**self.metadata, **metadata},
                           self.rotation, compensation)

    def with_rotation(self, rotation: ArrayLike | None, **metadata: Any) -> Calibration:
        """A copy with rotation ``R`` (None: identity) and metadata entries added or replaced."""
        return Calibration(self.offset, self.matrix, self.field_strength, self.model,
                           {**self.metadata, **metadata}, rotation, self.compensation)

    def scaled(self, factor: float) -> Calibration:
        """The same calibration for input expressed in other units (``raw_new = factor * raw``)."""
        return Calibration(
            self.offset * factor,
            self.matrix,
            self.field_strength * factor,
            self.model,
            self.metadata,
            self.rotation,
            None if self.compensation is None else self.compensation.scaled(factor),
        )

    def metadata_number(self, key: str) -> float | None:
        """Metadata ``key`` as a finite float, or None: a hand-edited file may hold anything."""
        value = self.metadata.get(key)
        if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
            return None
        try:
            number = float(value)
        except OverflowError:
            return None
        return number if math.isfinite(number) else None

    def with_metadata(self, **metadata: Any) -> Calibration:
        """A copy with metadata entries added or replaced."""
        return Calibration(
            self.offset,
            self.matrix,
            self.field_strength,
            self.model,
            {**self.metadata, **metadata},
            self.rotation,
            self.compensation,
        )


def transform_covariance(matrix: np.ndarray, covariance: Sequence[float]) -> np.ndarray:
    """``A C A^T`` for a known covariance (``A`` = ``calibration.correction``, R M); all-zero
    (unknown) and -1 (not reported) pass as is, and a covariance with NaN/Inf (or one that
    overflows) becomes all-zero: unknown (REP-145)."""
    covariance = np.asarray(covariance, dtype=float).reshape(3, 3)
    if not np.all(np.isfinite(covariance)):
        return np.zeros(9)
    if not np.any(covariance) or covariance[0, 0] == -1.0:
        return covariance.reshape(9).copy()
    with np.errstate(all='ignore'):
        transformed = (matrix @ covariance @ matrix.T).reshape(9)
    return transformed if np.all(np.isfinite(transformed)) else np.zeros(9)


def with_uncertainty(covariance: Sequence[float], sigma: float,
                     along: Sequence[float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """A row-major 3x3 covariance raised to each component's variance ``sigma**2`` and with
    ``along along^T`` added (an error in one direction): the mark of a correction known to be off
    by about that much (REP-145: the covariance is the field's uncertainty, so a fusion filter
    down-weights or gates it). ``sigma`` is measured on the readings, their noise included, so
    only what it holds beyond the input's own mean variance is added (the noise is not counted
    twice). An unknown (all-zero) or unreported (-1) covariance becomes just what is added."""
    covariance = np.asarray(covariance, dtype=float).reshape(3, 3)
    if covariance[0, 0] == -1.0 or not np.all(np.isfinite(covariance)):
        covariance = np.zeros((3, 3))
    vector = np.asarray(along, dtype=float)
    if not np.all(np.isfinite(vector)):
        vector = np.zeros(3)
    beyond = max(float(sigma) ** 2 - max(float(np.trace(covariance)), 0.0) / 3.0, 0.0)
    return (covariance + beyond * np.eye(3) + np.outer(vector, vector)).reshape(9)
