"""Calibration engine: pure numpy/scipy, no rclpy (DESIGN.md §2)."""

from mag_calibrator_ros.calibration.calibration import (
    MODELS,
    Calibration,
    CalibrationError,
    calibration_problems,
)
from mag_calibrator_ros.calibration.coverage import Coverage, direction_coverage
from mag_calibrator_ros.calibration.fitting import (
    FitMetrics,
    FitOptions,
    FitResult,
    fit_calibration,
)

__all__ = ['MODELS', 'Calibration', 'CalibrationError', 'calibration_problems']
__all__ += ['Coverage', 'direction_coverage']
__all__ += ['FitMetrics', 'FitOptions', 'FitResult', 'fit_calibration']
