# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The real chip: ICM-20948 / AK09916 registers, units, I2C bus, driver and supervisor; no rclpy.

Its register-level simulator lives a room above, in ``sim/`` (``sim/simulator.py``).
"""
