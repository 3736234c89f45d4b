# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""ROS 2 nodes: thin shells that wire parameters, topics, services and diagnostics to the core."""
