# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Calibration engine: pure numpy/scipy, no rclpy (docs/ARCHITECTURE.md)."""

from mag_calibrator_ros.calibration.fit.calibration import (
    MODELS,
    Calibration,
    CalibrationError,
    calibration_problems,
)
from mag_calibrator_ros.calibration.fit.coverage import Coverage, direction_coverage
from mag_calibrator_ros.calibration.fit.fitting import (
    FitMetrics,
    FitOptions,
    FitResult,
    fit_calibration,
)
from mag_calibrator_ros.calibration.live.buffer import SampleBuffer
from mag_calibrator_ros.calibration.live.tracker import OnlineTracker, TrackerHealth
from mag_calibrator_ros.calibration.store.calibration_file import (
    CalibrationFileError,
    calibration_from_parameters,
    load_calibration,
    save_calibration,
)

__all__ = ['MODELS', 'Calibration', 'CalibrationError', 'calibration_problems']
__all__ += ['Coverage', 'direction_coverage']
__all__ += ['FitMetrics', 'FitOptions', 'FitResult', 'fit_calibration']
__all__ += ['SampleBuffer', 'OnlineTracker', 'TrackerHealth']
__all__ += ['CalibrationFileError', 'calibration_from_parameters', 'load_calibration']
__all__ += ['save_calibration']
