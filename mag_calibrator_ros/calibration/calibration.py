"""The calibration value shared by every layer: ``corrected = M @ (raw - b)``."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

MODELS = ('sphere', 'axis', 'full', 'planar', 'auto')
"""Fit models. ``auto`` names a request only; a fitted calibration carries the model chosen."""


class CalibrationError(ValueError):
    """A calibration's numbers are unusable (wrong shape, non-finite, not positive definite)."""


def calibration_problems(offset: ArrayLike, matrix: ArrayLike, field_strength: float) -> list[str]:
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
    return problems


@dataclass(frozen=True)
class Calibration:
    """Hard-iron offset ``b`` and soft-iron correction ``M``; ``|corrected|`` is about ``F``.

    Units are those of the raw input (tesla in the nodes, input units offline).
    """

    offset: np.ndarray
    matrix: np.ndarray
    field_strength: float = 1.0
    model: str = 'full'
    metadata: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        problems = calibration_problems(self.offset, self.matrix, self.field_strength)
        if problems:
            raise CalibrationError('; '.join(problems))
        offset = np.array(self.offset, dtype=float).reshape(3)
        matrix = np.array(self.matrix, dtype=float).reshape(3, 3)
        offset.flags.writeable = False
        matrix.flags.writeable = False
        object.__setattr__(self, 'offset', offset)
        object.__setattr__(self, 'matrix', matrix)
        object.__setattr__(self, 'field_strength', float(self.field_strength))
        object.__setattr__(self, 'metadata', dict(self.metadata))

    @classmethod
    def identity(cls, field_strength: float = 1.0) -> Calibration:
        """No correction: useful as a tracker start or a prior."""
        return cls(np.zeros(3), np.eye(3), field_strength, model='identity')

    def apply(self, raw: ArrayLike) -> np.ndarray:
        """Correct one sample (3,) or many (n, 3)."""
        raw = np.asarray(raw, dtype=float)
        return (raw - self.offset) @ self.matrix.T

    def scaled(self, factor: float) -> Calibration:
        """The same calibration for input expressed in other units (``raw_new = factor * raw``)."""
        return Calibration(
            self.offset * factor,
            self.matrix,
            self.field_strength * factor,
            self.model,
            self.metadata,
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
        )
