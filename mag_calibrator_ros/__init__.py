# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""mag_calibrator_ros: live magnetometer calibration for ROS 2 Jazzy."""

__version__ = '0.1.0'
