# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The stop signals' handler, in the standard library alone: the console scripts (entry.py) set
it before the heavy imports, ``runtime.spin_node`` keeps it."""

from __future__ import annotations

import signal

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class StopOnSignal:
    """The first SIGINT or SIGTERM ends spinning; further ones are ignored, so a second Ctrl-C
    cannot cut the node's shutdown (its final publishes) short. It only sets a flag: an
    exception raised from a signal handler can land inside a pybind11 call of rclpy, which
    turns it into a RuntimeError ("Unable to convert call argument") and exit 1."""

    def __init__(self) -> None:
        self.received: int | None = None

    def __call__(self, number: int, frame: object) -> None:
        if self.received is None:
            self.received = number


def catch_stop_signals() -> StopOnSignal:
    """The handler in force when it is one of ours (set before the imports), else a new one."""
    current = signal.getsignal(signal.SIGINT)
    stop = current if isinstance(current, StopOnSignal) else StopOnSignal()
    for number in STOP_SIGNALS:
        signal.signal(number, stop)
    return stop


def ignore_stop_signals() -> None:
    """From the end of a node's life on: Python's finalization puts the default action (death by
    the signal, exit -2) back for a handler of its own, not for SIG_IGN, and the second SIGINT
    of a launch's Ctrl-C can arrive that late."""
    for number in STOP_SIGNALS:
        signal.signal(number, signal.SIG_IGN)
