# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""What a user can tune in the live calibrator, and the engine's defaults behind each setting.

The node mirrors every field of :class:`SessionSettings` as a ROS parameter; ``mag_calibrator_fit``
builds one from its options. ``problems()`` is the one place a setting is validated.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
import math

from mag_calibrator_ros.calibration.fit.alignment import MAX_ANGLE_DEG, AlignmentOptions
from mag_calibrator_ros.calibration.fit.calibration import MODELS
from mag_calibrator_ros.calibration.fit.earth_field import (
    MAX_DIP_ERROR_DEG,
    MAX_FIELD_ERROR_PCT,
    EarthField,
)
from mag_calibrator_ros.calibration.fit.fitting import FitOptions
from mag_calibrator_ros.calibration.live.buffer import DEFAULT_CAPACITY, DEFAULT_K
from mag_calibrator_ros.calibration.live.inputs import input_problems

FITTABLE_MODELS = tuple(MODELS)

DEFAULT_FIT = FitOptions()
"""The fit gates as the engine chose them from its benchmarks (see FitOptions)."""


@dataclass(frozen=True)
class SessionSettings:
    """Everything a user can tune; the node mirrors each field as a ROS parameter."""

    buffer_size: int = DEFAULT_CAPACITY
    k: int = DEFAULT_K
    model: str = 'auto'
    field_strength: float = 0.0
    """Input units (tesla in the node); 0 keeps the fitted mean radius (magnitude preserved)."""
    min_coverage: float = float(DEFAULT_FIT.min_coverage)
    max_residual_pct: float = float(DEFAULT_FIT.max_residual_pct)
    full_scale: float = 0.0
    """A component at or beyond it is saturated. 0 (the default: the engine knows no chip)
    disables the check; the node passes its magnetometer's limit."""
    auto_calibrate: bool = True
    auto_calibrate_period: float = 2.0
    """Stream seconds between automatic fits that failed, so a failing fit does not run on
    every check."""
    refine: bool = True
    """Keep fitting after the first calibration; adopt a fit only when better on held-out data."""
    refine_period: float = 10.0
    """Stream seconds between refinement fits (doubling up to 8x once converged)."""
    online_tracking: bool = False
    tracking_improvement: float = 0.8
    """Adopt a tracked calibration only when its residual is below this share of the current."""
    tracking_max_change_rate: float = 0.01
    """Per second: offset change as a share of the field, matrix change as a relative norm."""
    align: bool = True
    """With paired accelerometer readings (``process_imu``), align fits to the IMU frame."""
    gyro_aided: bool = True
    """With gyroscope rates (``process_imu``), calibrate first from the turning they measure
    (``fit/gyro_aided.py``): the offset from rotation about two axes, no sphere needed, put in
    force only when held-out readings say it beats the raw field (else the raw field, confirmed,
    is); the sphere fits refine it later."""
    max_alignment_deg: float = MAX_ANGLE_DEG
    """A larger rotation is reported as a mounting error (with the remap) and not applied."""
    max_field_error_pct: float = MAX_FIELD_ERROR_PCT
    max_dip_error_deg: float = MAX_DIP_ERROR_DEG
    """Tolerances against the World Magnetic Model (``set_earth_field``)."""
    earth_field_gate: bool = True
    """Beyond them a fit fails (True) or is only warned about (False)."""
    use_temperature: bool = True
    """Pair readings with the sensor's temperature (``imu/temperature``) when it is published:
    learn the hard iron's drift with it and compensate it (``live/compensation.py``)."""
    interference_inputs: tuple[str, ...] = ()
    """Inputs whose field the robot carries (``topic:package/msg/Type:field``): learned and
    compensated like the temperature. None by default."""
    learn_compensation: bool = True
    """Learn the robot's own field (``K``, ``c``) live; adopted only on held-out evidence."""

    @property
    def full_scale_limit(self) -> float | None:
        """``full_scale`` as the screen takes it: None when the check is off (0)."""
        return self.full_scale if self.full_scale > 0.0 else None

    @property
    def compensation(self) -> tuple[tuple[str, ...], bool, bool]:
        """(interference_inputs, use_temperature, learn_compensation): what the compensation
        learner (``live/compensation.py``) is configured with."""
        return tuple(self.interference_inputs), self.use_temperature, self.learn_compensation

    @property
    def min_samples(self) -> int:
        """The fewest samples a fit takes: the engine's, or the whole buffer when smaller."""
        return min(DEFAULT_FIT.min_samples, self.buffer_size)

    def check(self) -> None:
        """Raise ValueError with every one of ``problems`` (none: these settings can work)."""
        problems = self.problems()
        if problems:
            raise ValueError('; '.join(problems))

    def problems(self) -> list[str]:
        """Every reason these settings cannot work, in words a user can act on."""
        problems = []
        if self.buffer_size < 10:
            problems.append(f'buffer_size must be >= 10, got {self.buffer_size}')
        if self.k < 1 or self.k >= self.buffer_size:
            problems.append(f'k must be in [1, buffer_size - 1], got k={self.k} with '
                            f'buffer_size={self.buffer_size}')
        if self.model not in FITTABLE_MODELS:
            problems.append(
                f"model must be one of {', '.join(FITTABLE_MODELS)}, got {self.model!r}"
            )
        if not math.isfinite(self.field_strength) or self.field_strength < 0.0:
            problems.append(f'field_strength must be >= 0 (0 = fitted radius), '
                            f'got {self.field_strength}')
        if not 0.0 <= self.min_coverage <= 1.0:
            problems.append(f'min_coverage must be a fraction in [0, 1], got {self.min_coverage}')
        if not math.isfinite(self.max_residual_pct) or self.max_residual_pct <= 0.0:
            problems.append(f'max_residual_pct must be > 0, got {self.max_residual_pct}')
        if not math.isfinite(self.full_scale) or self.full_scale < 0.0:
            problems.append(f'full_scale must be >= 0 (0 = no check), got {self.full_scale}')
        for name in ('auto_calibrate_period', 'refine_period'):
            value = getattr(self, name)
            if not math.isfinite(value) or value <= 0.0:
                problems.append(f'{name} must be > 0 s, got {value}')
        if not 0.0 < self.tracking_improvement < 1.0:
            problems.append(f'tracking_improvement must be in (0, 1), got '
                            f'{self.tracking_improvement}')
        if not math.isfinite(self.tracking_max_change_rate) or self.tracking_max_change_rate <= 0:
            problems.append(f'tracking_max_change_rate must be > 0 per second, got '
                            f'{self.tracking_max_change_rate}')
        if not 0.0 <= self.max_alignment_deg <= 180.0:
            problems.append(f'max_alignment_deg must be in [0, 180], got {self.max_alignment_deg}')
        if not (math.isfinite(self.max_field_error_pct) and self.max_field_error_pct > 0.0):
            problems.append(f'max_field_error_pct must be > 0, got {self.max_field_error_pct}')
        if not 0.0 < self.max_dip_error_deg <= 90.0:
            problems.append(f'max_dip_error_deg must be in (0, 90], got {self.max_dip_error_deg}')
        problems += input_problems(self.interference_inputs)
        return problems

    def fit_options(self) -> FitOptions:
        """The engine's fit options with this model, target field strength and gates."""
        return replace(
            DEFAULT_FIT,
            model=self.model,
            field_strength=self.field_strength if self.field_strength > 0.0 else None,
            min_coverage=self.min_coverage,
            max_residual_pct=self.max_residual_pct,
        )

    def alignment_options(self, earth: EarthField | None = None) -> AlignmentOptions:
        """How a fit is aligned to the IMU; the model's dip, when known, checks the alignment."""
        return AlignmentOptions(
            max_angle_deg=self.max_alignment_deg,
            expected_inclination_deg=None if earth is None else earth.inclination_deg)


__all__ = ['DEFAULT_FIT', 'FITTABLE_MODELS', 'SessionSettings']
