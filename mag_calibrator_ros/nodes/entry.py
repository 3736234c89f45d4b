# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The nodes' console scripts (``ros2 run``, ``ros2 launch``): they catch the stop signals
before the heavy imports (rclpy, numpy, scipy: a second or more on a small computer), so a
Ctrl-C during start-up is a clean stop, not a KeyboardInterrupt traceback from inside an import
and launch's 'process has died ... exit code -2' (issue #46). This module imports nothing but
the standard library (``signals.py``); ``runtime.spin_node`` keeps what was caught."""

from __future__ import annotations

import signal
import sys

from mag_calibrator_ros.nodes.signals import StopOnSignal, catch_stop_signals, ignore_stop_signals


def icm20948_driver() -> int:
    """Console script ``icm20948_driver``."""
    stop = catch_stop_signals()
    from mag_calibrator_ros.nodes.icm20948_driver import main
    return _stopped(stop) if stop.received is not None else main()


def mag_calibrator() -> int:
    """Console script ``mag_calibrator``."""
    stop = catch_stop_signals()
    from mag_calibrator_ros.nodes.mag_calibrator import main
    return _stopped(stop) if stop.received is not None else main()


def _stopped(stop: StopOnSignal) -> int:
    """A stop signal during the imports: nothing was started, so nothing needs stopping."""
    ignore_stop_signals()
    print(f'{signal.Signals(stop.received).name} during start-up: stopped before the node '
          'started', file=sys.stderr)
    return 0
