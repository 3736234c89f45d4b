# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""sim"""
