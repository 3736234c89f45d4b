"""Calibration engine: pure numpy/scipy, no rclpy (DESIGN.md §2)."""

from mag_calibrator_ros.calibration.buffer import SampleBuffer
from mag_calibrator_ros.calibration.calibration import (
    MODELS,
    Calibration,
    CalibrationError,
    calibration_problems,
)
from mag_calibrator_ros.calibration.calibration_file import (
    CalibrationFileError,
    calibration_from_parameters,
    load_calibration,
    save_calibration,
)
from mag_calibrator_ros.calibration.coverage import Coverage, direction_coverage
from mag_calibrator_ros.calibration.fitting import (
    FitMetrics,
    FitOptions,
    FitResult,
    fit_calibration,
)
from mag_calibrator_ros.calibration.tracker import OnlineTracker, TrackerHealth

__all__ = ['MODELS', 'Calibration', 'CalibrationError', 'calibration_problems']
__all__ += ['Coverage', 'direction_coverage']
__all__ += ['FitMetrics', 'FitOptions', 'FitResult', 'fit_calibration']
__all__ += ['SampleBuffer', 'OnlineTracker', 'TrackerHealth']
__all__ += ['CalibrationFileError', 'calibration_from_parameters', 'load_calibration']
__all__ += ['save_calibration']
