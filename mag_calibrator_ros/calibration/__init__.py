"""Calibration engine: pure numpy/scipy, no rclpy (DESIGN.md §2)."""

from mag_calibrator_ros.calibration.calibration import (
    MODELS,
    Calibration,
    CalibrationError,
    calibration_problems,
)
from mag_calibrator_ros.calibration.coverage import Coverage, direction_coverage

__all__ = ['MODELS', 'Calibration', 'CalibrationError', 'calibration_problems']
__all__ += ['Coverage', 'direction_coverage']
